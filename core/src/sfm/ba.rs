//! Bundle adjustment of keyframe poses and world points with SLAM priors and a camera rig: Levenberg–Marquardt
//! on SE(3)×R³ with the points eliminated (Schur complement) and the reduced camera system factorised by faer's
//! sparse Cholesky (pure Rust, so it builds for wasm32). The explicit reduced system suits submaps up to ~1–2k
//! keyframes (../shared/reference/sfm.md §2); above that an implicit Schur with PCG would be the better fit.
//!
//! **Model.** Keyframe `k` has the pose `T_world_base[k]`; rig camera `c` sits at `T_base_cam[c]`, so
//! `T_world_cam = pose * extrinsic` and a world point projects from `p_cam = T_world_cam⁻¹ p_world`. The
//! reprojection residual is `project(p_cam) - uv` in pixels (OpenCV pixel convention of [`CameraModel`]).
//!
//! **Perturbations.** Poses and (refined) extrinsics are perturbed on the right, `T ← T · Exp(δ)`, with
//! `δ = (ω, v)` (rotation first) and the full SE(3) exponential (`Exp(ω, v) = (Exp_SO3(ω), V(ω) v)`): δ lives in
//! the body frame (base frame for poses, camera frame for extrinsics). Points are updated additively.
//!
//! **Priors.** Both priors compare an SE(3) error `E` with the identity, residual
//! `r = [Log_SO3(R_E) / sigma_rad ; t_E / sigma_m]` (6-vector, rotation first, in sigmas):
//! relative `E = T_meas⁻¹ T_a⁻¹ T_b`, absolute `E = T_meas⁻¹ T_pose`. (The translation part of `E`, not the
//! SE(3) log, so the metre sigma means metres; both vanish together.) Their Jacobians are analytic
//! (`J_r⁻¹`, `J_l⁻¹` of SO(3) and the adjoint of `T_meas⁻¹`).
//!
//! **Cost.** `½ Σ ρ(‖r_obs‖²) + ½ Σ ρ_prior(‖r_prior‖²)`: Huber (or Cauchy) on the pixel norm, Huber in
//! sigmas on each prior (a gross SLAM error costs linearly, so its pull is bounded by `prior_huber` sigmas
//! instead of growing with the error). LM solves the IRLS-weighted normal equations with Marquardt damping
//! `λ·diag(H)` (diagonal clamped to [1e-6, 1e32]) and Nielsen's λ update; one LM iteration is one trial step,
//! accepted or not.
//!
//! **Observations that do not project** (behind the camera, past the model's valid angle) carry no weight in
//! that iteration. A step is judged on the terms that evaluate both before and after it, so losing an
//! observation is neither rewarded nor, for a single ill-conditioned point thrown behind a camera, fatal to
//! the step; a step that loses many observations at once is rejected. On any error the problem is unchanged.

use crate::camera::{CameraError, CameraModel};
use crate::geometry::Se3;
use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use faer::{Mat, Side};
use glam::{DQuat, DVec2, DVec3};
use nalgebra::{Matrix3, Matrix6, SMatrix, Vector2, Vector3, Vector6};
use rayon::prelude::*;
use serde::Serialize;
use thiserror::Error;

type M3 = Matrix3<f64>;
type V3 = Vector3<f64>;
type V2 = Vector2<f64>;
type M6 = Matrix6<f64>;
type V6 = Vector6<f64>;
type M23 = SMatrix<f64, 2, 3>;
type M26 = SMatrix<f64, 2, 6>;
type M63 = SMatrix<f64, 6, 3>;

/// "No block" marker in the index tables.
const NONE: usize = usize::MAX;
/// Marquardt diagonal clamp (as Ceres): a variable without curvature still gets a little damping.
const MIN_DIAG: f64 = 1e-6;
const MAX_DIAG: f64 = 1e32;
const INITIAL_LAMBDA: f64 = 1e-4;
/// Past this the step is zero to working precision: stop (or fail, if even that cannot be factorised).
const MAX_LAMBDA: f64 = 1e32;
/// A damped 3x3 point block whose smallest Cholesky pivot is below this fraction of its largest diagonal entry
/// is treated as singular: that point stays where it is for the step.
const POINT_PIVOT_RATIO: f64 = 1e-12;
/// A step that makes more than this many (and this fraction) of the projecting observations unprojectable is
/// rejected as wild, whatever it does to the cost.
const MAX_LOST_ABS: usize = 10;
const MAX_LOST_FRACTION: f64 = 0.005;
/// Points per parallel work item.
const POINT_CHUNK: usize = 256;

/// One image measurement: keyframe `pose`, rig camera `camera`, 3-D `point`, pixel `uv` (centre of top-left pixel = (0,0)).
#[derive(Clone, Copy, Debug)]
pub struct Observation {
    pub pose: usize,
    pub camera: usize,
    pub point: usize,
    pub uv: DVec2,
}

/// SLAM odometry between two keyframes: measured T_a_b = T_world_a^-1 T_world_b, with 1-sigma in metres and radians.
#[derive(Clone, Copy, Debug)]
pub struct RelativePrior {
    pub a: usize,
    pub b: usize,
    pub t_a_b: Se3,
    pub sigma_m: f64,
    pub sigma_rad: f64,
}

impl RelativePrior {
    /// The steps of a trajectory as relative priors: keyframe k to k + 1 as `base` has them, each with
    /// the same 1-σ (the SLAM odometry; a pose graph's chain).
    pub fn chain(base: &[Se3], sigma_m: f64, sigma_rad: f64) -> Vec<RelativePrior> {
        base.windows(2)
            .enumerate()
            .map(|(k, w)| RelativePrior {
                a: k,
                b: k + 1,
                t_a_b: w[0].inverse() * w[1],
                sigma_m,
                sigma_rad,
            })
            .collect()
    }
}

/// A weak absolute prior on one keyframe pose (gauge; keeps the solution near the SLAM frame).
#[derive(Clone, Copy, Debug)]
pub struct AbsolutePrior {
    pub pose: usize,
    pub t_world_base: Se3,
    pub sigma_m: f64,
    pub sigma_rad: f64,
}

/// The problem; [`solve`] updates `poses`, `points` (and `extrinsics` when refined) in place.
#[derive(Clone, Debug)]
pub struct BaProblem {
    /// Intrinsics of each rig camera (fixed).
    pub cameras: Vec<CameraModel>,
    /// `T_base_cam` of each rig camera (fixed unless `BaOptions::refine_extrinsics`).
    pub extrinsics: Vec<Se3>,
    /// `T_world_base` per keyframe: variables.
    pub poses: Vec<Se3>,
    /// World points: variables.
    pub points: Vec<DVec3>,
    pub observations: Vec<Observation>,
    pub relative_priors: Vec<RelativePrior>,
    pub absolute_priors: Vec<AbsolutePrior>,
}

/// Robust loss on the reprojection error norm, with scale `BaOptions::huber_px`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub enum Loss {
    /// Quadratic up to the scale, linear beyond: outliers keep a bounded pull.
    #[default]
    Huber,
    /// `k² ln(1 + s²/k²)`: redescending, outliers lose almost all pull (stronger but less convex).
    Cauchy,
    /// Plain least squares (no robustness; for comparison and for known-clean data).
    Squared,
}

#[derive(Clone, Debug)]
pub struct BaOptions {
    pub max_iterations: usize,
    /// Scale of the reprojection loss in pixels (the Huber corner, or the Cauchy scale).
    pub huber_px: f64,
    /// Which robust loss the reprojection terms use.
    pub loss: Loss,
    /// Huber corner of the prior terms, in sigmas: gross SLAM errors must not drag the solution.
    pub prior_huber: f64,
    /// false: the rig is a constraint (one pose per keyframe); true: per-camera `T_base_cam` refined too
    /// (camera 0 held fixed for the gauge).
    pub refine_extrinsics: bool,
    /// Keyframes held constant (may be empty when absolute priors fix the gauge).
    pub fixed_poses: Vec<usize>,
    /// Stop when an accepted step lowers the cost by less than this fraction.
    pub function_tolerance: f64,
    /// Stop when `‖δ‖ ≤ tol · (‖x‖ + tol)` (x: translations and points).
    pub parameter_tolerance: f64,
}

impl Default for BaOptions {
    fn default() -> Self {
        BaOptions {
            max_iterations: 50,
            huber_px: 2.0,
            loss: Loss::Huber,
            prior_huber: 3.0,
            refine_extrinsics: false,
            fixed_poses: Vec::new(),
            function_tolerance: 1e-8,
            parameter_tolerance: 1e-10,
        }
    }
}

#[derive(Clone, Debug, Serialize)]
pub struct BaReport {
    /// LM trial steps (accepted or rejected).
    pub iterations: usize,
    /// Robust cost `½ Σ ρ` (reprojection and priors) before and after.
    pub initial_cost: f64,
    pub final_cost: f64,
    /// RMS reprojection error over the observations that project.
    pub initial_rmse_px: f64,
    pub final_rmse_px: f64,
    pub observations: usize,
    /// Observations that do not project (behind the camera, outside the valid angle) with the final values;
    /// they carry no weight.
    pub unprojected: usize,
    pub points: usize,
    pub poses: usize,
    pub converged: bool,
    pub stop_reason: String,
}

#[derive(Debug, Error)]
pub enum BaError {
    #[error("empty problem: {0}")]
    Empty(&'static str),
    #[error("{item} {index}: {field} {value} is out of range (there are {len})")]
    IndexOutOfRange {
        item: &'static str,
        index: usize,
        field: &'static str,
        value: usize,
        len: usize,
    },
    #[error("non-finite input: {0}")]
    NonFinite(String),
    #[error("invalid input: {0}")]
    Invalid(String),
    #[error("camera {index}: {source}")]
    Camera { index: usize, source: CameraError },
    /// `poses`: the keyframes whose terms went non-finite, for the caller to name their images.
    #[error("diverged: {detail}")]
    Diverged { detail: String, poses: Vec<usize> },
    /// `poses`: the least observed keyframes (the likeliest to be unconstrained), fewest first.
    #[error("the reduced camera system is not positive definite even with damping λ = {lambda:e}")]
    Singular { lambda: f64, poses: Vec<usize> },
}

// ---------------------------------------------------------------------------------------------------------
// Small maths.

fn v3(p: DVec3) -> V3 {
    V3::new(p.x, p.y, p.z)
}

fn m3_of(q: DQuat) -> M3 {
    M3::from_column_slice(&glam::DMat3::from_quat(q).to_cols_array())
}

fn skew(v: &V3) -> M3 {
    M3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// Rotation vector of a unit quaternion (atan2: accurate near 0, angle in [0, π]).
fn so3_log(q: DQuat) -> V3 {
    let q = if q.w < 0.0 { -q } else { q };
    let v = V3::new(q.x, q.y, q.z);
    let n = v.norm();
    let k = if n > 1e-12 {
        2.0 * n.atan2(q.w) / n
    } else {
        2.0 / q.w
    };
    v * k
}

/// `J_r⁻¹(φ)`: `Log(Exp(φ) Exp(ω)) ≈ φ + J_r⁻¹(φ) ω`. (`J_l⁻¹(φ) = J_r⁻¹(-φ)`.)
fn so3_jr_inv(phi: &V3) -> M3 {
    let th = phi.norm();
    let k = skew(phi);
    // 1/θ² - (1 + cos θ)/(2 θ sin θ) = 1/θ² - cot(θ/2)/(2θ); series below 1e-4.
    let c = if th < 1e-4 {
        1.0 / 12.0 + th * th / 720.0
    } else {
        1.0 / (th * th) - 1.0 / ((0.5 * th).tan() * 2.0 * th)
    };
    M3::identity() + 0.5 * k + c * k * k
}

/// SE(3) exponential of `δ = (ω, v)`.
fn se3_exp(d: &[f64]) -> Se3 {
    let w = DVec3::new(d[0], d[1], d[2]);
    let v = DVec3::new(d[3], d[4], d[5]);
    let th2 = w.length_squared();
    let th = th2.sqrt();
    let (b, c) = if th < 1e-4 {
        (0.5 - th2 / 24.0, 1.0 / 6.0 - th2 / 120.0)
    } else {
        ((1.0 - th.cos()) / th2, (th - th.sin()) / (th2 * th))
    };
    let wxv = w.cross(v);
    Se3 {
        rot: DQuat::from_scaled_axis(w),
        trans: v + b * wxv + c * w.cross(wxv),
    }
}

/// Rotation matrix and translation of an [`Se3`], for the inner loops.
#[derive(Clone, Copy, Debug)]
struct Frame {
    r: M3,
    t: V3,
}

impl Frame {
    fn of(t: &Se3) -> Self {
        Frame {
            r: m3_of(t.rot),
            t: v3(t.trans),
        }
    }
}

/// Camera-frame point of world point `pw` seen from pose `pose` through rig camera `ext`, and the base-frame point.
fn to_camera(pose: &Frame, ext: &Frame, pw: &V3) -> (V3, V3) {
    let pb = pose.r.tr_mul(&(pw - pose.t));
    let pc = ext.r.tr_mul(&(pb - ext.t));
    (pc, pb)
}

fn reprojection(
    cam: &CameraModel,
    max_angle: f64,
    pose: &Frame,
    ext: &Frame,
    pw: &V3,
    uv: DVec2,
) -> Option<V2> {
    let (pc, _) = to_camera(pose, ext, pw);
    let p = cam.project_within(DVec3::new(pc.x, pc.y, pc.z), max_angle)?;
    Some(V2::new(p.x - uv.x, p.y - uv.y))
}

/// Residual and analytic Jacobians of one observation.
#[derive(Clone, Copy, Debug)]
struct ObsLin {
    r: V2,
    /// d r / d δ_pose (right perturbation of `T_world_base`).
    j_pose: M26,
    /// d r / d δ_ext (right perturbation of `T_base_cam`).
    j_ext: M26,
    /// d r / d p_world.
    j_point: M23,
}

fn observe(
    cam: &CameraModel,
    max_angle: f64,
    pose: &Frame,
    ext: &Frame,
    pw: &V3,
    uv: DVec2,
) -> Option<ObsLin> {
    let (pc, pb) = to_camera(pose, ext, pw);
    let (p, j) = cam.project_jacobian_within(DVec3::new(pc.x, pc.y, pc.z), max_angle)?;
    let jpi = M23::new(j[0][0], j[0][1], j[0][2], j[1][0], j[1][1], j[1][2]);
    // p_cam = R_eᵀ (p_b - t_e); p_b = R_pᵀ (p_w - t_p). Under T ← T Exp(δ): p_b ← Exp(-δ) p_b ≈ p_b + [p_b]× ω - v.
    let a = jpi * ext.r.transpose();
    let mut j_pose = M26::zeros();
    j_pose
        .fixed_view_mut::<2, 3>(0, 0)
        .copy_from(&(a * skew(&pb)));
    j_pose.fixed_view_mut::<2, 3>(0, 3).copy_from(&(-a));
    let mut j_ext = M26::zeros();
    j_ext
        .fixed_view_mut::<2, 3>(0, 0)
        .copy_from(&(jpi * skew(&pc)));
    j_ext.fixed_view_mut::<2, 3>(0, 3).copy_from(&(-jpi));
    Some(ObsLin {
        r: V2::new(p.x - uv.x, p.y - uv.y),
        j_pose,
        j_ext,
        j_point: a * pose.r.transpose(),
    })
}

/// Residual of an SE(3) error `E` against identity, in sigmas: `[Log(R_E)/σr ; t_E/σm]`.
fn se3_error_residual(e: &Se3, sigma_m: f64, sigma_rad: f64) -> (V6, V3, M3, V3) {
    let phi = so3_log(e.rot);
    let t = v3(e.trans);
    let mut r = V6::zeros();
    r.fixed_rows_mut::<3>(0).copy_from(&(phi / sigma_rad));
    r.fixed_rows_mut::<3>(3).copy_from(&(t / sigma_m));
    (r, phi, m3_of(e.rot), t)
}

/// Scales the rotation rows by 1/σr and the translation rows by 1/σm.
fn scale_rows(mut j: M6, sigma_m: f64, sigma_rad: f64) -> M6 {
    for i in 0..3 {
        j.row_mut(i).scale_mut(1.0 / sigma_rad);
        j.row_mut(i + 3).scale_mut(1.0 / sigma_m);
    }
    j
}

/// `d r / d δ` for `E ← E Exp(δ)`: `[[J_r⁻¹(φ), 0], [0, R_E]]` (unscaled).
fn right_jacobian(phi: &V3, re: &M3) -> M6 {
    let mut j = M6::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&so3_jr_inv(phi));
    j.fixed_view_mut::<3, 3>(3, 3).copy_from(re);
    j
}

/// Relative prior residual and its Jacobians with respect to the right perturbations of poses a and b.
fn relative_prior_lin(p: &RelativePrior, ta: &Se3, tb: &Se3) -> (V6, M6, M6) {
    let m_inv = p.t_a_b.inverse();
    let e = m_inv * ta.inverse() * *tb;
    let (r, phi, re, te) = se3_error_residual(&e, p.sigma_m, p.sigma_rad);
    // b: E ← E Exp(δb).
    let jb = right_jacobian(&phi, &re);
    // a: E ← Exp(-Ad(M⁻¹) δa) E; for E ← Exp(η) E, d r / d η = [[J_l⁻¹(φ), 0], [-[t_E]×, I]].
    let mut dl = M6::zeros();
    dl.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&so3_jr_inv(&(-phi)));
    dl.fixed_view_mut::<3, 3>(3, 0).copy_from(&(-skew(&te)));
    dl.fixed_view_mut::<3, 3>(3, 3).copy_from(&M3::identity());
    // Ad(T) for δ = (ω, v): [[R, 0], [[t]× R, R]].
    let rn = m3_of(m_inv.rot);
    let tn = v3(m_inv.trans);
    let mut ad = M6::zeros();
    ad.fixed_view_mut::<3, 3>(0, 0).copy_from(&rn);
    ad.fixed_view_mut::<3, 3>(3, 0).copy_from(&(skew(&tn) * rn));
    ad.fixed_view_mut::<3, 3>(3, 3).copy_from(&rn);
    let ja = -(dl * ad);
    (
        r,
        scale_rows(ja, p.sigma_m, p.sigma_rad),
        scale_rows(jb, p.sigma_m, p.sigma_rad),
    )
}

/// Absolute prior residual and its Jacobian with respect to the right perturbation of the pose.
fn absolute_prior_lin(p: &AbsolutePrior, t: &Se3) -> (V6, M6) {
    let e = p.t_world_base.inverse() * *t;
    let (r, phi, re, _) = se3_error_residual(&e, p.sigma_m, p.sigma_rad);
    (
        r,
        scale_rows(right_jacobian(&phi, &re), p.sigma_m, p.sigma_rad),
    )
}

/// `(ρ(s²), ρ'(s²))` of the loss with scale `k`: the cost term and the IRLS weight.
fn robust(loss: Loss, k: f64, s2: f64) -> (f64, f64) {
    if !k.is_finite() {
        return (s2, 1.0);
    }
    match loss {
        Loss::Squared => (s2, 1.0),
        Loss::Huber => {
            let s = s2.sqrt();
            if s <= k {
                (s2, 1.0)
            } else {
                (2.0 * k * s - k * k, k / s)
            }
        }
        Loss::Cauchy => {
            let k2 = k * k;
            (k2 * (s2 / k2).ln_1p(), 1.0 / (1.0 + s2 / k2))
        }
    }
}

// ---------------------------------------------------------------------------------------------------------
// Validation.

fn se3_ok(t: &Se3) -> bool {
    t.is_finite() && t.rot.length_squared() > 1e-12
}

fn sigma_ok(s: f64) -> bool {
    s.is_finite() && s > 0.0
}

fn validate(p: &BaProblem, o: &BaOptions) -> Result<(), BaError> {
    if p.poses.is_empty() {
        return Err(BaError::Empty("no keyframe poses"));
    }
    if p.observations.is_empty() && p.relative_priors.is_empty() && p.absolute_priors.is_empty() {
        return Err(BaError::Empty("no observations and no priors"));
    }
    if p.extrinsics.len() != p.cameras.len() {
        return Err(BaError::Invalid(format!(
            "{} cameras but {} extrinsics",
            p.cameras.len(),
            p.extrinsics.len()
        )));
    }
    for (index, c) in p.cameras.iter().enumerate() {
        c.validate()
            .map_err(|source| BaError::Camera { index, source })?;
    }
    for (i, e) in p.extrinsics.iter().enumerate() {
        if !se3_ok(e) {
            return Err(BaError::NonFinite(format!(
                "extrinsic {i} (T_base_cam) is not a finite rigid transform: {e:?}"
            )));
        }
    }
    for (i, t) in p.poses.iter().enumerate() {
        if !se3_ok(t) {
            return Err(BaError::NonFinite(format!(
                "pose {i} is not a finite rigid transform: {t:?}"
            )));
        }
    }
    if let Some(i) = p.points.iter().position(|x| !x.is_finite()) {
        return Err(BaError::NonFinite(format!(
            "point {i} is not finite: {}",
            p.points[i]
        )));
    }
    let range = |item, index, field, value: usize, len: usize| {
        if value < len {
            Ok(())
        } else {
            Err(BaError::IndexOutOfRange {
                item,
                index,
                field,
                value,
                len,
            })
        }
    };
    for (i, ob) in p.observations.iter().enumerate() {
        range("observation", i, "pose", ob.pose, p.poses.len())?;
        range("observation", i, "camera", ob.camera, p.cameras.len())?;
        range("observation", i, "point", ob.point, p.points.len())?;
        if !ob.uv.is_finite() {
            return Err(BaError::NonFinite(format!(
                "observation {i}: uv is not finite: {}",
                ob.uv
            )));
        }
    }
    for (i, r) in p.relative_priors.iter().enumerate() {
        range("relative prior", i, "pose a", r.a, p.poses.len())?;
        range("relative prior", i, "pose b", r.b, p.poses.len())?;
        if r.a == r.b {
            return Err(BaError::Invalid(format!(
                "relative prior {i} links pose {} to itself",
                r.a
            )));
        }
        if !se3_ok(&r.t_a_b) {
            return Err(BaError::NonFinite(format!(
                "relative prior {i}: t_a_b is not a finite rigid transform"
            )));
        }
        if !sigma_ok(r.sigma_m) || !sigma_ok(r.sigma_rad) {
            return Err(BaError::Invalid(format!(
                "relative prior {i}: sigmas must be finite and positive (sigma_m {}, sigma_rad {})",
                r.sigma_m, r.sigma_rad
            )));
        }
    }
    for (i, a) in p.absolute_priors.iter().enumerate() {
        range("absolute prior", i, "pose", a.pose, p.poses.len())?;
        if !se3_ok(&a.t_world_base) {
            return Err(BaError::NonFinite(format!(
                "absolute prior {i}: t_world_base is not a finite rigid transform"
            )));
        }
        if !sigma_ok(a.sigma_m) || !sigma_ok(a.sigma_rad) {
            return Err(BaError::Invalid(format!(
                "absolute prior {i}: sigmas must be finite and positive (sigma_m {}, sigma_rad {})",
                a.sigma_m, a.sigma_rad
            )));
        }
    }
    for (i, &k) in o.fixed_poses.iter().enumerate() {
        range("fixed_poses entry", i, "pose", k, p.poses.len())?;
    }
    if o.huber_px.is_nan() || o.huber_px <= 0.0 || o.prior_huber.is_nan() || o.prior_huber <= 0.0 {
        return Err(BaError::Invalid(format!(
            "loss scales must be positive (huber_px {}, prior_huber {})",
            o.huber_px, o.prior_huber
        )));
    }
    if o.function_tolerance.is_nan()
        || o.function_tolerance < 0.0
        || o.parameter_tolerance.is_nan()
        || o.parameter_tolerance < 0.0
    {
        return Err(BaError::Invalid(format!(
            "tolerances must be non-negative (function {}, parameter {})",
            o.function_tolerance, o.parameter_tolerance
        )));
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------------------
// Structure: which unknown blocks exist and the (fixed) sparsity of the reduced camera system.

/// Camera-side unknowns are 6-blocks (free poses first, then refined extrinsics); the reduced camera system
/// `S` is stored block-wise (upper triangle, block CSC, each block a column-major 6x6) and scattered into a
/// scalar upper CSC whose symbolic Cholesky is computed once.
struct Structure {
    nb: usize,
    n_pose_blocks: usize,
    pose_block: Vec<usize>,
    ext_block: Vec<usize>,
    /// Observations of each point (CSR); position `k` in `pt_obs` is the observation's *slot*.
    pt_obs_ptr: Vec<usize>,
    pt_obs: Vec<usize>,
    /// Distinct camera blocks each point touches, sorted (CSR, parallel to the `w` storage).
    pt_blk_ptr: Vec<usize>,
    pt_blk: Vec<usize>,
    /// Global block-pair index of each local upper pair `(a ≤ b)` of a point's blocks, row-major (CSR).
    pt_pair_ptr: Vec<usize>,
    pt_pair: Vec<usize>,
    /// Per slot: local index of its pose block and extrinsic block in its point's block list (or NONE).
    slot_local: Vec<[usize; 2]>,
    /// Per slot: position of the (pose, extrinsic) pair within the extrinsic's block column (or NONE).
    slot_cross: Vec<usize>,
    /// Block pattern: column `bj` holds the row blocks `brow[bcol_ptr[bj]..bcol_ptr[bj+1]]` (sorted, ≤ bj; the
    /// diagonal is last).
    bcol_ptr: Vec<usize>,
    brow: Vec<usize>,
    /// Per block: (point, local index) of the points touching it (CSR).
    blk_pts_ptr: Vec<usize>,
    blk_pts: Vec<(usize, usize)>,
    /// Per block: slots of the observations touching it (CSR).
    blk_obs_ptr: Vec<usize>,
    blk_obs: Vec<usize>,
    /// Per relative prior: block pair of (a, b) when both are free.
    rel_pair: Vec<usize>,
    /// Point chunk boundaries for the parallel passes.
    pchunk: Vec<usize>,
    csc: Option<(SymbolicSparseColMat<usize>, SymbolicLlt<usize>)>,
}

fn csr<T: Copy>(n: usize, items: &[(usize, T)]) -> (Vec<usize>, Vec<T>) {
    let mut ptr = vec![0usize; n + 1];
    for &(i, _) in items {
        ptr[i + 1] += 1;
    }
    for i in 0..n {
        ptr[i + 1] += ptr[i];
    }
    let mut fill = ptr.clone();
    let mut out: Vec<Option<T>> = vec![None; items.len()];
    for &(i, v) in items {
        out[fill[i]] = Some(v);
        fill[i] += 1;
    }
    (ptr, out.into_iter().flatten().collect())
}

/// Start of local pair row `a` in a point's upper pair list over `m` blocks.
fn pair_row(a: usize, m: usize) -> usize {
    a * (2 * m + 1 - a) / 2
}

impl Structure {
    fn pair(&self, bi: usize, bj: usize) -> usize {
        let (lo, hi) = (self.bcol_ptr[bj], self.bcol_ptr[bj + 1]);
        lo + self.brow[lo..hi]
            .binary_search(&bi)
            .expect("block pair is in the pattern by construction")
    }

    fn build(p: &BaProblem, o: &BaOptions) -> Result<Self, BaError> {
        let mut fixed = vec![false; p.poses.len()];
        for &k in &o.fixed_poses {
            fixed[k] = true;
        }
        let mut nb = 0;
        let pose_block: Vec<usize> = fixed
            .iter()
            .map(|&f| {
                if f {
                    NONE
                } else {
                    nb += 1;
                    nb - 1
                }
            })
            .collect();
        let n_pose_blocks = nb;
        let mut observed = vec![false; p.cameras.len()];
        for ob in &p.observations {
            observed[ob.camera] = true;
        }
        let ext_block: Vec<usize> = (0..p.cameras.len())
            .map(|c| {
                if o.refine_extrinsics && c > 0 && observed[c] {
                    nb += 1;
                    nb - 1
                } else {
                    NONE
                }
            })
            .collect();

        let np = p.points.len();
        let (pt_obs_ptr, pt_obs) = csr(
            np,
            &p.observations
                .iter()
                .enumerate()
                .map(|(i, ob)| (ob.point, i))
                .collect::<Vec<_>>(),
        );
        let nslots = pt_obs.len();
        let mut pt_blk_ptr = vec![0usize; np + 1];
        let mut pt_blk = Vec::new();
        let mut slot_local = vec![[NONE, NONE]; nslots];
        for j in 0..np {
            let start = pt_blk.len();
            for &i in &pt_obs[pt_obs_ptr[j]..pt_obs_ptr[j + 1]] {
                let ob = &p.observations[i];
                for b in [pose_block[ob.pose], ext_block[ob.camera]] {
                    if b != NONE {
                        pt_blk.push(b);
                    }
                }
            }
            pt_blk[start..].sort_unstable();
            let mut blocks: Vec<usize> = pt_blk.drain(start..).collect();
            blocks.dedup();
            pt_blk.extend_from_slice(&blocks);
            for k in pt_obs_ptr[j]..pt_obs_ptr[j + 1] {
                let ob = &p.observations[pt_obs[k]];
                let local = |b: usize| {
                    if b == NONE {
                        NONE
                    } else {
                        blocks.binary_search(&b).unwrap_or(NONE)
                    }
                };
                slot_local[k] = [local(pose_block[ob.pose]), local(ext_block[ob.camera])];
            }
            pt_blk_ptr[j + 1] = pt_blk.len();
        }

        // Block pattern: diagonal, co-observation (every pair of blocks sharing a point, which includes the
        // pose-extrinsic pair of each observation) and relative-prior edges.
        let mut pairs: Vec<(usize, usize)> = (0..nb).map(|b| (b, b)).collect();
        for j in 0..np {
            let bl = &pt_blk[pt_blk_ptr[j]..pt_blk_ptr[j + 1]];
            for (a, &bi) in bl.iter().enumerate() {
                for &bj in &bl[a + 1..] {
                    pairs.push((bj, bi));
                }
            }
        }
        for r in &p.relative_priors {
            let (ba, bb) = (pose_block[r.a], pose_block[r.b]);
            if ba != NONE && bb != NONE {
                pairs.push((ba.max(bb), ba.min(bb)));
            }
        }
        pairs.sort_unstable();
        pairs.dedup();
        let (bcol_ptr, brow) = csr(nb, &pairs);

        let mut s = Structure {
            nb,
            n_pose_blocks,
            pose_block,
            ext_block,
            pt_obs_ptr,
            pt_obs,
            pt_blk_ptr,
            pt_blk,
            pt_pair_ptr: vec![0; np + 1],
            pt_pair: Vec::new(),
            slot_local,
            slot_cross: vec![NONE; nslots],
            bcol_ptr,
            brow,
            blk_pts_ptr: Vec::new(),
            blk_pts: Vec::new(),
            blk_obs_ptr: Vec::new(),
            blk_obs: Vec::new(),
            rel_pair: Vec::new(),
            pchunk: (0..np)
                .step_by(POINT_CHUNK)
                .chain(std::iter::once(np))
                .collect(),
            csc: None,
        };
        let mut pt_pair = Vec::new();
        let mut blk_pts = Vec::new();
        for j in 0..np {
            let bl = &s.pt_blk[s.pt_blk_ptr[j]..s.pt_blk_ptr[j + 1]];
            for (a, &bi) in bl.iter().enumerate() {
                for &bj in &bl[a..] {
                    pt_pair.push(s.pair(bi, bj));
                }
                blk_pts.push((bi, (j, a)));
            }
            s.pt_pair_ptr[j + 1] = pt_pair.len();
        }
        s.pt_pair = pt_pair;
        (s.blk_pts_ptr, s.blk_pts) = csr(nb, &blk_pts);
        let mut blk_obs = Vec::new();
        for k in 0..nslots {
            let ob = &p.observations[s.pt_obs[k]];
            let (bp, be) = (s.pose_block[ob.pose], s.ext_block[ob.camera]);
            if bp != NONE {
                blk_obs.push((bp, k));
            }
            if be != NONE {
                blk_obs.push((be, k));
                if bp != NONE {
                    s.slot_cross[k] = s.pair(bp, be) - s.bcol_ptr[be];
                }
            }
        }
        (s.blk_obs_ptr, s.blk_obs) = csr(nb, &blk_obs);
        s.rel_pair = p
            .relative_priors
            .iter()
            .map(|r| {
                let (ba, bb) = (s.pose_block[r.a], s.pose_block[r.b]);
                if ba != NONE && bb != NONE {
                    s.pair(ba.min(bb), ba.max(bb))
                } else {
                    NONE
                }
            })
            .collect();

        if nb > 0 {
            // Scalar upper CSC: column 6bj+c holds the full 6-row strips of the off-diagonal blocks above it and
            // rows 6bj..=6bj+c of the diagonal block.
            let n = 6 * nb;
            let mut col_ptr = Vec::with_capacity(n + 1);
            let mut row_idx = Vec::new();
            col_ptr.push(0usize);
            for bj in 0..nb {
                let rows = &s.brow[s.bcol_ptr[bj]..s.bcol_ptr[bj + 1]];
                for c in 0..6 {
                    for &bi in rows {
                        let count = if bi < bj { 6 } else { c + 1 };
                        row_idx.extend((0..count).map(|r| 6 * bi + r));
                    }
                    col_ptr.push(row_idx.len());
                }
            }
            let sym = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);
            let llt = SymbolicLlt::try_new(sym.as_ref(), Side::Upper).map_err(|e| {
                BaError::Invalid(format!(
                    "symbolic factorisation of the reduced camera system failed: {e:?}"
                ))
            })?;
            s.csc = Some((sym, llt));
        }
        Ok(s)
    }

    fn n_pairs(&self) -> usize {
        self.brow.len()
    }
}

/// Splits `s` into consecutive pieces at the cumulative `bounds` (first 0, last `s.len() / scale`), each
/// bound multiplied by `scale`.
fn split_at_bounds<'a, T>(mut s: &'a mut [T], bounds: &[usize], scale: usize) -> Vec<&'a mut [T]> {
    let mut out = Vec::with_capacity(bounds.len().saturating_sub(1));
    for w in bounds.windows(2) {
        let (head, tail) = std::mem::take(&mut s).split_at_mut((w[1] - w[0]) * scale);
        out.push(head);
        s = tail;
    }
    out
}

fn add_block(dst: &mut [f64], m: &M6) {
    for (d, s) in dst.iter_mut().zip(m.as_slice()) {
        *d += s;
    }
}

// ---------------------------------------------------------------------------------------------------------
// State, cost and linearisation.

struct Ctx<'a> {
    p: &'a BaProblem,
    o: &'a BaOptions,
    angles: Vec<f64>,
}

#[derive(Clone)]
struct State {
    poses: Vec<Se3>,
    exts: Vec<Se3>,
    points: Vec<DVec3>,
}

impl State {
    fn frames(&self) -> (Vec<Frame>, Vec<Frame>) {
        (
            self.poses.iter().map(Frame::of).collect(),
            self.exts.iter().map(Frame::of).collect(),
        )
    }

    fn apply(&self, s: &Structure, step: &Step) -> State {
        let mut out = self.clone();
        for (t, &b) in out.poses.iter_mut().zip(&s.pose_block) {
            if b != NONE {
                *t = *t * se3_exp(&step.dc[6 * b..6 * b + 6]);
            }
        }
        for (t, &b) in out.exts.iter_mut().zip(&s.ext_block) {
            if b != NONE {
                *t = *t * se3_exp(&step.dc[6 * b..6 * b + 6]);
            }
        }
        for (x, d) in out.points.iter_mut().zip(&step.dx) {
            *x += DVec3::new(d.x, d.y, d.z);
        }
        out
    }

    fn norm(&self) -> f64 {
        let t: f64 = self.poses.iter().map(|t| t.trans.length_squared()).sum();
        let e: f64 = self.exts.iter().map(|t| t.trans.length_squared()).sum();
        let x: f64 = self.points.iter().map(|p| p.length_squared()).sum();
        (t + e + x).sqrt()
    }
}

struct Eval {
    /// Robust cost `½ Σ ρ` over the observations that project plus the priors.
    cost: f64,
    prior: f64,
    /// `½ ρ` of each observation; `None` where it does not project.
    terms: Vec<Option<f64>>,
    sq_px: f64,
    n_proj: usize,
}

impl Eval {
    fn rmse(&self) -> f64 {
        if self.n_proj == 0 {
            0.0
        } else {
            (self.sq_px / self.n_proj as f64).sqrt()
        }
    }

    /// Cost decrease from `self` to `cand` over the terms both evaluate: an observation that stops (or
    /// starts) projecting neither rewards nor penalises the step.
    fn decrease_to(&self, cand: &Eval) -> f64 {
        let obs: f64 = self
            .terms
            .iter()
            .zip(&cand.terms)
            .map(|(a, b)| match (a, b) {
                (Some(a), Some(b)) => a - b,
                _ => 0.0,
            })
            .sum();
        obs + self.prior - cand.prior
    }
}

/// The keyframes with a non-finite term in `ev`: an observation's reprojection or a prior on them.
fn non_finite_poses(ctx: &Ctx, st: &State, ev: &Eval) -> Vec<usize> {
    let k = ctx.o.prior_huber;
    let bad = |v: f64| !robust(Loss::Huber, k, v).0.is_finite();
    let mut poses: Vec<usize> = ctx
        .p
        .observations
        .iter()
        .zip(&ev.terms)
        .filter(|(_, t)| t.is_some_and(|t| !t.is_finite()))
        .map(|(ob, _)| ob.pose)
        .collect();
    for r in &ctx.p.relative_priors {
        let (res, _, _) = relative_prior_lin(r, &st.poses[r.a], &st.poses[r.b]);
        if bad(res.norm_squared()) {
            poses.extend([r.a, r.b]);
        }
    }
    for a in &ctx.p.absolute_priors {
        if bad(absolute_prior_lin(a, &st.poses[a.pose]).0.norm_squared()) {
            poses.push(a.pose);
        }
    }
    poses.sort_unstable();
    poses.dedup();
    poses
}

/// Up to `most` keyframes with the fewest observations, fewest first.
fn least_observed_poses(problem: &BaProblem, most: usize) -> Vec<usize> {
    let mut count = vec![0usize; problem.poses.len()];
    for ob in &problem.observations {
        count[ob.pose] += 1;
    }
    let mut order: Vec<usize> = (0..count.len()).collect();
    order.sort_by_key(|&k| (count[k], k));
    order.truncate(most);
    order
}

fn prior_costs(ctx: &Ctx, st: &State) -> f64 {
    let k = ctx.o.prior_huber;
    let rel: f64 = ctx
        .p
        .relative_priors
        .iter()
        .map(|r| {
            let (res, _, _) = relative_prior_lin(r, &st.poses[r.a], &st.poses[r.b]);
            robust(Loss::Huber, k, res.norm_squared()).0
        })
        .sum();
    let abs: f64 = ctx
        .p
        .absolute_priors
        .iter()
        .map(|a| {
            robust(
                Loss::Huber,
                k,
                absolute_prior_lin(a, &st.poses[a.pose]).0.norm_squared(),
            )
            .0
        })
        .sum();
    0.5 * (rel + abs)
}

fn evaluate(ctx: &Ctx, st: &State) -> Eval {
    let (pf, ef) = st.frames();
    let o = ctx.o;
    let res: Vec<Option<(f64, f64)>> = ctx
        .p
        .observations
        .par_iter()
        .map(|ob| {
            let c = ob.camera;
            let r = reprojection(
                &ctx.p.cameras[c],
                ctx.angles[c],
                &pf[ob.pose],
                &ef[c],
                &v3(st.points[ob.point]),
                ob.uv,
            )?;
            let s2 = r.norm_squared();
            Some((0.5 * robust(o.loss, o.huber_px, s2).0, s2))
        })
        .collect();
    let mut cost = 0.0;
    let mut sq_px = 0.0;
    let mut n_proj = 0;
    for &(rho, s2) in res.iter().flatten() {
        cost += rho;
        sq_px += s2;
        n_proj += 1;
    }
    let prior = prior_costs(ctx, st);
    Eval {
        cost: cost + prior,
        prior,
        terms: res.iter().map(|t| t.map(|t| t.0)).collect(),
        sq_px,
        n_proj,
    }
}

/// Square-root-weighted Jacobians of one observation, kept for assembling the camera blocks.
#[derive(Clone, Copy)]
struct SlotLin {
    jp: M26,
    je: M26,
    r: V2,
}

const ZERO_SLOT: SlotLin = SlotLin {
    jp: M26::new(0., 0., 0., 0., 0., 0., 0., 0., 0., 0., 0., 0.),
    je: M26::new(0., 0., 0., 0., 0., 0., 0., 0., 0., 0., 0., 0.),
    r: V2::new(0., 0.),
};

/// IRLS-weighted normal equations `H δ = -g`, split as camera blocks `U` (block pattern of [`Structure`]),
/// per-point `V`, and the coupling `W` (one 6x3 per point and camera block).
struct Linear {
    u: Vec<f64>,
    gc: Vec<f64>,
    v: Vec<M3>,
    gx: Vec<V3>,
    w: Vec<M63>,
}

fn linearize(ctx: &Ctx, s: &Structure, st: &State) -> Linear {
    let (pf, ef) = st.frames();
    let (p, o) = (ctx.p, ctx.o);
    let np = p.points.len();
    let mut lin = Linear {
        u: vec![0.0; 36 * s.n_pairs()],
        gc: vec![0.0; 6 * s.nb],
        v: vec![M3::zeros(); np],
        gx: vec![V3::zeros(); np],
        w: vec![M63::zeros(); s.pt_blk.len()],
    };
    let mut slots = vec![ZERO_SLOT; s.pt_obs.len()];

    // Points in parallel: V, g_x, W, and the weighted Jacobians of each observation.
    let pc = &s.pchunk;
    let wb: Vec<usize> = pc.iter().map(|&j| s.pt_blk_ptr[j]).collect();
    let sb: Vec<usize> = pc.iter().map(|&j| s.pt_obs_ptr[j]).collect();
    split_at_bounds(&mut lin.v, pc, 1)
        .into_par_iter()
        .zip(split_at_bounds(&mut lin.gx, pc, 1))
        .zip(split_at_bounds(&mut lin.w, &wb, 1))
        .zip(split_at_bounds(&mut slots, &sb, 1))
        .enumerate()
        .for_each(|(ci, (((v, g), w), sl))| {
            let (j0, w0, k0) = (pc[ci], wb[ci], sb[ci]);
            for j in j0..pc[ci + 1] {
                let pw = v3(st.points[j]);
                let wj = &mut w[s.pt_blk_ptr[j] - w0..s.pt_blk_ptr[j + 1] - w0];
                for k in s.pt_obs_ptr[j]..s.pt_obs_ptr[j + 1] {
                    let ob = &p.observations[s.pt_obs[k]];
                    let c = ob.camera;
                    let Some(l) = observe(
                        &p.cameras[c],
                        ctx.angles[c],
                        &pf[ob.pose],
                        &ef[c],
                        &pw,
                        ob.uv,
                    ) else {
                        continue;
                    };
                    let wt = robust(o.loss, o.huber_px, l.r.norm_squared()).1;
                    let jxt = l.j_point.transpose();
                    v[j - j0] += wt * jxt * l.j_point;
                    g[j - j0] += wt * jxt * l.r;
                    let [lp, le] = s.slot_local[k];
                    if lp != NONE {
                        wj[lp] += wt * l.j_pose.transpose() * l.j_point;
                    }
                    if le != NONE {
                        wj[le] += wt * l.j_ext.transpose() * l.j_point;
                    }
                    let sw = wt.sqrt();
                    sl[k - k0] = SlotLin {
                        jp: sw * l.j_pose,
                        je: sw * l.j_ext,
                        r: sw * l.r,
                    };
                }
            }
        });

    // Camera blocks in parallel, one block column each (disjoint writes): the observations' J_cᵀ J_c and the
    // pose-extrinsic cross terms (which live in the extrinsic's column since extrinsic blocks come last).
    split_at_bounds(&mut lin.u, &s.bcol_ptr, 36)
        .into_par_iter()
        .zip(lin.gc.par_chunks_mut(6))
        .enumerate()
        .for_each(|(bj, (ucol, g))| {
            let diag = ucol.len() - 36;
            let is_ext = bj >= s.n_pose_blocks;
            for &k in &s.blk_obs[s.blk_obs_ptr[bj]..s.blk_obs_ptr[bj + 1]] {
                let sl = &slots[k];
                let j = if is_ext { &sl.je } else { &sl.jp };
                let jt = j.transpose();
                add_block(&mut ucol[diag..], &(jt * j));
                let gj = jt * sl.r;
                for (a, b) in g.iter_mut().zip(gj.iter()) {
                    *a += b;
                }
                if is_ext && s.slot_cross[k] != NONE {
                    let at = 36 * s.slot_cross[k];
                    add_block(&mut ucol[at..at + 36], &(sl.jp.transpose() * sl.je));
                }
            }
        });

    // Priors (few): serial.
    let k = o.prior_huber;
    let add_grad = |gc: &mut [f64], b: usize, v: &V6| {
        for i in 0..6 {
            gc[6 * b + i] += v[i];
        }
    };
    for (i, r) in p.relative_priors.iter().enumerate() {
        let (res, ja, jb) = relative_prior_lin(r, &st.poses[r.a], &st.poses[r.b]);
        let wt = robust(Loss::Huber, k, res.norm_squared()).1;
        let (ba, bb) = (s.pose_block[r.a], s.pose_block[r.b]);
        for (b, j) in [(ba, &ja), (bb, &jb)] {
            if b != NONE {
                let d = s.bcol_ptr[b + 1] - 1;
                add_block(&mut lin.u[36 * d..36 * d + 36], &(wt * j.transpose() * j));
                add_grad(&mut lin.gc, b, &(wt * j.transpose() * res));
            }
        }
        let gp = s.rel_pair[i];
        if gp != NONE {
            let m = if ba < bb {
                wt * ja.transpose() * jb
            } else {
                wt * jb.transpose() * ja
            };
            add_block(&mut lin.u[36 * gp..36 * gp + 36], &m);
        }
    }
    for a in &p.absolute_priors {
        let b = s.pose_block[a.pose];
        if b != NONE {
            let (res, j) = absolute_prior_lin(a, &st.poses[a.pose]);
            let wt = robust(Loss::Huber, k, res.norm_squared()).1;
            let d = s.bcol_ptr[b + 1] - 1;
            add_block(&mut lin.u[36 * d..36 * d + 36], &(wt * j.transpose() * j));
            add_grad(&mut lin.gc, b, &(wt * j.transpose() * res));
        }
    }
    lin
}

// ---------------------------------------------------------------------------------------------------------
// The damped step by Schur complement.

struct Step {
    /// Camera-block update, 6 per block.
    dc: Vec<f64>,
    /// Point updates (zero for skipped points).
    dx: Vec<V3>,
    /// Decrease of the quadratic model: `½ δᵀ(λ D δ - g)`.
    predicted: f64,
    norm: f64,
    skipped_points: usize,
}

fn damp(d: f64) -> f64 {
    d.clamp(MIN_DIAG, MAX_DIAG)
}

/// Solves `(H + λ D) δ = -g` by eliminating the points. Points whose damped block is singular are held
/// constant: left out of the elimination, so the camera step treats them as fixed. `None` when the reduced
/// system is not positive definite (the caller raises λ).
fn compute_step(s: &Structure, lin: &Linear, lambda: f64) -> Option<Step> {
    let np = lin.v.len();
    // Damped point blocks, their inverses and Y = W V*⁻¹, per point in parallel.
    let mut vinv: Vec<Option<M3>> = vec![None; np];
    let mut y = vec![M63::zeros(); lin.w.len()];
    let pc = &s.pchunk;
    let wb: Vec<usize> = pc.iter().map(|&j| s.pt_blk_ptr[j]).collect();
    split_at_bounds(&mut vinv, pc, 1)
        .into_par_iter()
        .zip(split_at_bounds(&mut y, &wb, 1))
        .enumerate()
        .for_each(|(ci, (vi, yc))| {
            let (j0, w0) = (pc[ci], wb[ci]);
            for j in j0..pc[ci + 1] {
                let v = &lin.v[j];
                let dmax = v.diagonal().max();
                if dmax.is_nan() || dmax <= 0.0 {
                    continue; // no information on this point now
                }
                let mut vd = *v;
                for i in 0..3 {
                    vd[(i, i)] += lambda * damp(v[(i, i)]);
                }
                let Some(ch) = vd.cholesky() else { continue };
                let l = ch.l_dirty();
                let pmin = (0..3)
                    .map(|i| l[(i, i)] * l[(i, i)])
                    .fold(f64::INFINITY, f64::min);
                if pmin.is_nan() || pmin <= POINT_PIVOT_RATIO * vd.diagonal().max() {
                    continue;
                }
                let inv = ch.inverse();
                for q in s.pt_blk_ptr[j]..s.pt_blk_ptr[j + 1] {
                    yc[q - w0] = lin.w[q] * inv;
                }
                vi[j - j0] = Some(inv);
            }
        });
    let skipped_points = (0..np)
        .filter(|&j| vinv[j].is_none() && lin.v[j].diagonal().max() > 0.0)
        .count();

    let nb = s.nb;
    let mut dc = vec![0.0; 6 * nb];
    let mut predicted = 0.0;
    if nb > 0 {
        // S = U* - Σ Y Wᵀ and g_S = g_c - Σ Y g_x, one block column per task.
        let mut sv = lin.u.clone();
        let mut gs = lin.gc.clone();
        split_at_bounds(&mut sv, &s.bcol_ptr, 36)
            .into_par_iter()
            .zip(gs.par_chunks_mut(6))
            .enumerate()
            .for_each(|(bj, (scol, g))| {
                let col0 = s.bcol_ptr[bj];
                let diag = scol.len() - 36;
                for i in 0..6 {
                    let d = damp(lin.u[36 * (col0 + scol.len() / 36 - 1) + 7 * i]);
                    scol[diag + 7 * i] += lambda * d;
                }
                for &(j, b) in &s.blk_pts[s.blk_pts_ptr[bj]..s.blk_pts_ptr[bj + 1]] {
                    if vinv[j].is_none() {
                        continue;
                    }
                    let base = s.pt_blk_ptr[j];
                    let m = s.pt_blk_ptr[j + 1] - base;
                    let wbt = lin.w[base + b].transpose();
                    let pairs = &s.pt_pair[s.pt_pair_ptr[j]..s.pt_pair_ptr[j + 1]];
                    for a in 0..=b {
                        let at = 36 * (pairs[pair_row(a, m) + b - a] - col0);
                        let blk = y[base + a] * wbt;
                        for (d, v) in scol[at..at + 36].iter_mut().zip(blk.as_slice()) {
                            *d -= v;
                        }
                    }
                    let gy = y[base + b] * lin.gx[j];
                    for (d, v) in g.iter_mut().zip(gy.iter()) {
                        *d -= v;
                    }
                }
            });

        // Scatter the upper triangle into the scalar CSC, factorise with the fixed symbolic structure, solve.
        let (sym, symbolic) = s.csc.as_ref()?;
        let mut vals = Vec::with_capacity(sym.row_idx().len());
        for bj in 0..nb {
            let (lo, hi) = (s.bcol_ptr[bj], s.bcol_ptr[bj + 1]);
            for c in 0..6 {
                for gp in lo..hi {
                    let count = if s.brow[gp] < bj { 6 } else { c + 1 };
                    vals.extend_from_slice(&sv[36 * gp + 6 * c..36 * gp + 6 * c + count]);
                }
            }
        }
        let llt = Llt::try_new_with_symbolic(
            symbolic.clone(),
            SparseColMatRef::new(sym.as_ref(), &vals),
            Side::Upper,
        )
        .ok()?;
        let mut rhs = Mat::<f64>::from_fn(6 * nb, 1, |i, _| -gs[i]);
        llt.solve_in_place(rhs.as_mut());
        for (i, d) in dc.iter_mut().enumerate() {
            *d = rhs[(i, 0)];
        }
        if dc.iter().any(|d| !d.is_finite()) {
            return None;
        }
        for bj in 0..nb {
            let d0 = 36 * (s.bcol_ptr[bj + 1] - 1);
            for i in 0..6 {
                let x = dc[6 * bj + i];
                predicted += x * (lambda * damp(lin.u[d0 + 7 * i]) * x - lin.gc[6 * bj + i]);
            }
        }
    }

    // Back-substitution: δx = V*⁻¹ (-g_x - Σ Wᵀ δc).
    let dx: Vec<V3> = (0..np)
        .into_par_iter()
        .map(|j| {
            let Some(inv) = vinv[j] else {
                return V3::zeros();
            };
            let mut rhs = -lin.gx[j];
            for q in s.pt_blk_ptr[j]..s.pt_blk_ptr[j + 1] {
                let b = s.pt_blk[q];
                let d = nalgebra::Vector6::from_column_slice(&dc[6 * b..6 * b + 6]);
                rhs -= lin.w[q].transpose() * d;
            }
            inv * rhs
        })
        .collect();
    if dx.iter().any(|d| !d.iter().all(|x| x.is_finite())) {
        return None;
    }
    for (j, d) in dx.iter().enumerate() {
        if vinv[j].is_some() {
            let v = &lin.v[j];
            for i in 0..3 {
                predicted += d[i] * (lambda * damp(v[(i, i)]) * d[i] - lin.gx[j][i]);
            }
        }
    }
    let norm = (dc.iter().map(|x| x * x).sum::<f64>()
        + dx.iter().map(|d| d.norm_squared()).sum::<f64>())
    .sqrt();
    Some(Step {
        dc,
        dx,
        predicted: 0.5 * predicted,
        norm,
        skipped_points,
    })
}

// ---------------------------------------------------------------------------------------------------------
// Public entry points.

/// Reprojection error (px) of each observation with the current values; None where the point doesn't project (behind, outside valid angle).
/// Never panics: an observation with an out-of-range index is `None` too.
pub fn reprojection_errors(problem: &BaProblem) -> Vec<Option<f64>> {
    let angles: Vec<f64> = problem.cameras.iter().map(|c| c.valid_angle()).collect();
    problem
        .observations
        .iter()
        .map(|ob| {
            let cam = problem.cameras.get(ob.camera)?;
            let ext = Frame::of(problem.extrinsics.get(ob.camera)?);
            let pose = Frame::of(problem.poses.get(ob.pose)?);
            let pw = v3(*problem.points.get(ob.point)?);
            reprojection(cam, angles[ob.camera], &pose, &ext, &pw, ob.uv).map(|r| r.norm())
        })
        .collect()
}

/// Runs Levenberg–Marquardt on `problem`, updating poses and points (and extrinsics when refined) in place.
/// The gauge is whatever `fixed_poses` and the priors fix; an unfixed gauge is held by the damping only.
pub fn solve(problem: &mut BaProblem, opts: &BaOptions) -> Result<BaReport, BaError> {
    validate(problem, opts)?;
    let s = Structure::build(problem, opts)?;
    let ctx = Ctx {
        p: problem,
        o: opts,
        angles: problem.cameras.iter().map(|c| c.valid_angle()).collect(),
    };
    let normalise = |v: &[Se3]| {
        v.iter()
            .map(|t| Se3::new(t.rot, t.trans))
            .collect::<Vec<_>>()
    };
    let mut st = State {
        poses: normalise(&problem.poses),
        exts: normalise(&problem.extrinsics),
        points: problem.points.clone(),
    };
    let mut ev = evaluate(&ctx, &st);
    if !ev.cost.is_finite() {
        return Err(BaError::Diverged {
            detail: format!("the initial cost is not finite ({})", ev.cost),
            poses: non_finite_poses(&ctx, &st, &ev),
        });
    }
    let (initial_cost, initial_rmse_px) = (ev.cost, ev.rmse());

    let mut iterations = 0;
    let mut lambda = INITIAL_LAMBDA;
    let mut nu = 2.0;
    let mut converged = false;
    let mut stop_reason = String::from("maximum iterations reached");
    if s.nb == 0 && problem.points.is_empty() {
        converged = true;
        stop_reason = "nothing to optimise (all poses fixed, no points)".into();
    } else {
        let mut lin = linearize(&ctx, &s, &st);
        while iterations < opts.max_iterations {
            if ev.cost == 0.0 {
                converged = true;
                stop_reason = "zero cost".into();
                break;
            }
            iterations += 1;
            let Some(step) = compute_step(&s, &lin, lambda) else {
                lambda *= nu;
                nu *= 2.0;
                if lambda > MAX_LAMBDA {
                    return Err(BaError::Singular {
                        lambda,
                        poses: least_observed_poses(problem, 5),
                    });
                }
                continue;
            };
            let tol = opts.parameter_tolerance;
            if step.norm <= tol * (st.norm() + tol) {
                converged = true;
                stop_reason = format!("parameter tolerance reached (step {:.3e})", step.norm);
                break;
            }
            let cand = st.apply(&s, &step);
            let cev = evaluate(&ctx, &cand);
            // A badly conditioned point (two nearly coincident views, or views along its ray) can be thrown
            // behind a camera by the linearised step. Rejecting every such step stalls LM (and holding the point
            // back makes the step inconsistent with its model, which crawls), so it may go: its observations
            // carry no weight from then on and are reported in `unprojected`, and the step is judged only on
            // the terms that evaluate in both states. Many lost observations at once means a wild step: reject.
            let lost = ev
                .terms
                .iter()
                .zip(&cev.terms)
                .filter(|(a, b)| a.is_some() && b.is_none())
                .count();
            let wild = lost > MAX_LOST_ABS.max((MAX_LOST_FRACTION * ev.n_proj as f64) as usize);
            let actual = ev.decrease_to(&cev);
            if cev.cost.is_finite() && !wild && actual > 0.0 {
                let rho = actual / step.predicted.max(f64::MIN_POSITIVE);
                lambda = (lambda * (1.0 / 3.0f64).max(1.0 - (2.0 * rho - 1.0).powi(3))).max(1e-20);
                nu = 2.0;
                let rel = actual / ev.cost;
                log::debug!(
                    "ba iteration {iterations}: cost {:.6e} -> {:.6e}, λ {lambda:.2e}, points skipped {}, observations lost {lost}",
                    ev.cost,
                    cev.cost,
                    step.skipped_points,
                );
                st = cand;
                ev = cev;
                if rel < opts.function_tolerance {
                    converged = true;
                    stop_reason =
                        format!("function tolerance reached (relative decrease {rel:.3e})");
                    break;
                }
                lin = linearize(&ctx, &s, &st);
            } else {
                lambda *= nu;
                nu *= 2.0;
                if lambda > MAX_LAMBDA {
                    stop_reason = "no decrease even with maximal damping".into();
                    break;
                }
            }
        }
    }

    problem.poses = st.poses;
    problem.points = st.points;
    if opts.refine_extrinsics {
        problem.extrinsics = st.exts;
    }
    Ok(BaReport {
        iterations,
        initial_cost,
        final_cost: ev.cost,
        initial_rmse_px,
        final_rmse_px: ev.rmse(),
        observations: problem.observations.len(),
        unprojected: problem.observations.len() - ev.n_proj,
        points: problem.points.len(),
        poses: problem.poses.len(),
        converged,
        stop_reason,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Distortion;
    use rand::{Rng, SeedableRng};
    use rand_xoshiro::Xoshiro256PlusPlus;

    fn rng(seed: u64) -> Xoshiro256PlusPlus {
        Xoshiro256PlusPlus::seed_from_u64(seed)
    }

    fn gauss(r: &mut Xoshiro256PlusPlus) -> f64 {
        let u: f64 = r.random_range(f64::MIN_POSITIVE..1.0);
        let v: f64 = r.random_range(0.0..std::f64::consts::TAU);
        (-2.0 * u.ln()).sqrt() * v.cos()
    }

    fn unit(r: &mut Xoshiro256PlusPlus) -> DVec3 {
        DVec3::new(gauss(r), gauss(r), gauss(r)).normalize()
    }

    /// `t` moved by exactly `m` metres and `rad` radians in random directions.
    fn perturb(t: &Se3, m: f64, rad: f64, r: &mut Xoshiro256PlusPlus) -> Se3 {
        Se3::new(
            DQuat::from_scaled_axis(unit(r) * rad) * t.rot,
            t.trans + unit(r) * m,
        )
    }

    fn pose_error(a: &Se3, b: &Se3) -> (f64, f64) {
        (a.distance_to(b), a.angle_to(b))
    }

    fn pinhole() -> CameraModel {
        CameraModel::pinhole(640, 480, 400.0, 401.0, 319.5, 239.5)
    }

    fn fisheye() -> CameraModel {
        CameraModel {
            width: 360,
            height: 270,
            fx: 175.0,
            fy: 174.6,
            cx: 179.2,
            cy: 134.9,
            distortion: Distortion::Fisheye {
                k1: -0.04,
                k2: -0.002,
                k3: 0.003,
                k4: -0.002,
            },
        }
    }

    /// Front pinhole and left/right fisheyes; base frame x forward, y left, z up; OpenCV camera axes.
    fn rig() -> (Vec<CameraModel>, Vec<Se3>) {
        let (x, y, z) = (DVec3::X, DVec3::Y, DVec3::Z);
        let mount = |right: DVec3, down: DVec3, fwd: DVec3, t: DVec3| {
            Se3::from_rt(glam::DMat3::from_cols(right, down, fwd), t)
        };
        (
            vec![pinhole(), fisheye(), fisheye()],
            vec![
                mount(-y, -z, x, DVec3::new(0.25, 0.0, 0.1)),
                mount(x, -z, y, DVec3::new(0.05, 0.15, 0.05)),
                mount(-x, -z, -y, DVec3::new(0.05, -0.15, 0.05)),
            ],
        )
    }

    /// Keyframes every 0.5 m along a gently winding street between two facades 4 m left and right, points
    /// on the facades and on a wall ahead, exact observations. Tracks are cut to a random window of at most
    /// `max_window` keyframes (0: no cut); points keep at least two observations.
    fn scene(n_kf: usize, n_pts: usize, max_window: usize, seed: u64) -> BaProblem {
        let mut r = rng(seed);
        let (cameras, extrinsics) = rig();
        let poses: Vec<Se3> = (0..n_kf)
            .map(|k| {
                let k = k as f64;
                let rot = DQuat::from_rotation_z(0.15 * (0.2 * k).sin())
                    * DQuat::from_rotation_y(0.03 * (0.5 * k).cos())
                    * DQuat::from_rotation_x(0.02 * (0.7 * k).sin());
                Se3::new(rot, DVec3::new(0.5 * k, 0.4 * (0.3 * k).sin(), 1.5))
            })
            .collect();
        let cam_world: Vec<Vec<Se3>> = poses
            .iter()
            .map(|p| extrinsics.iter().map(|e| (*p * *e).inverse()).collect())
            .collect();
        let angles: Vec<f64> = cameras.iter().map(|c| c.valid_angle()).collect();
        let len = 0.5 * (n_kf - 1) as f64;
        let mut points = Vec::new();
        let mut observations = Vec::new();
        while points.len() < n_pts {
            let x = r.random_range(-6.0..len + 10.0);
            let p = match r.random_range(0..5) {
                0 | 1 => DVec3::new(x, 4.0 + r.random_range(-1.0..1.0), r.random_range(0.0..4.0)),
                2 | 3 => DVec3::new(
                    x,
                    -4.0 + r.random_range(-1.0..1.0),
                    r.random_range(0.0..4.0),
                ),
                _ => DVec3::new(
                    len + r.random_range(6.0..12.0),
                    r.random_range(-5.0..5.0),
                    r.random_range(0.0..4.0),
                ),
            };
            let mut obs = Vec::new();
            for (k, cw) in cam_world.iter().enumerate() {
                if (poses[k].trans.x - p.x).abs() > 25.0 {
                    continue;
                }
                for (c, t) in cw.iter().enumerate() {
                    let pc = t.transform_point(p);
                    if pc.z < 0.3 {
                        continue;
                    }
                    if let Some(uv) = cameras[c]
                        .project_within(pc, angles[c])
                        .filter(|&uv| cameras[c].in_image(uv))
                    {
                        obs.push(Observation {
                            pose: k,
                            camera: c,
                            point: points.len(),
                            uv,
                        });
                    }
                }
            }
            if max_window > 0 && !obs.is_empty() {
                let first = obs[0].pose;
                let last = obs[obs.len() - 1].pose;
                let start = r.random_range(first..=last);
                let w = r.random_range(2..=max_window);
                obs.retain(|o| o.pose >= start && o.pose < start + w);
            }
            if obs.len() >= 2 {
                points.push(p);
                observations.extend(obs);
            }
        }
        BaProblem {
            cameras,
            extrinsics,
            poses,
            points,
            observations,
            relative_priors: Vec::new(),
            absolute_priors: Vec::new(),
        }
    }

    /// Perturbs every pose not in `fixed` by 5 cm / 1° and every point by 10 cm.
    fn perturb_problem(p: &mut BaProblem, fixed: &[usize], seed: u64) {
        let mut r = rng(seed);
        for (k, t) in p.poses.iter_mut().enumerate() {
            if !fixed.contains(&k) {
                *t = perturb(t, 0.05, 1f64.to_radians(), &mut r);
            }
        }
        for x in &mut p.points {
            *x += unit(&mut r) * 0.1;
        }
    }

    fn max_pose_error(a: &[Se3], b: &[Se3]) -> (f64, f64) {
        a.iter().zip(b).fold((0.0, 0.0), |(m, r), (a, b)| {
            let (dm, dr) = pose_error(a, b);
            (f64::max(m, dm), f64::max(r, dr))
        })
    }

    fn check_jac<const R: usize, const C: usize>(
        what: &str,
        analytic: &SMatrix<f64, R, C>,
        f: impl Fn(usize, f64) -> SMatrix<f64, R, 1>,
        h: f64,
        worst: &mut f64,
    ) {
        for k in 0..C {
            let fd = (f(k, h) - f(k, -h)) / (2.0 * h);
            for i in 0..R {
                let a = analytic[(i, k)];
                let err = (fd[i] - a).abs() / a.abs().max(1.0);
                *worst = worst.max(err);
                assert!(
                    err < 1e-5,
                    "{what}: J[{i}][{k}] = {a} vs finite difference {}",
                    fd[i]
                );
            }
        }
    }

    fn unit_vec6(k: usize, h: f64) -> [f64; 6] {
        let mut d = [0.0; 6];
        d[k] = h;
        d
    }

    #[test]
    fn ba_jacobians_match_finite_differences() {
        let mut r = rng(1);
        for (name, cam) in [("pinhole", pinhole()), ("fisheye", fisheye())] {
            let lim = cam.valid_angle();
            let mut worst = 0.0f64;
            for _ in 0..300 {
                let pose = Se3::new(
                    DQuat::from_scaled_axis(unit(&mut r) * r.random_range(0.0..3.0)),
                    unit(&mut r) * r.random_range(0.0..20.0),
                );
                let ext = Se3::new(
                    DQuat::from_scaled_axis(unit(&mut r) * r.random_range(0.0..3.0)),
                    unit(&mut r) * r.random_range(0.0..0.5),
                );
                // A camera-frame point well inside the valid angle.
                let th = r.random_range(0.0..0.9 * lim.min(1.4));
                let az = r.random_range(-std::f64::consts::PI..std::f64::consts::PI);
                let pc = DVec3::new(th.sin() * f64::cos(az), th.sin() * f64::sin(az), th.cos())
                    * r.random_range(0.5..30.0);
                let pw = (pose * ext).transform_point(pc);
                let uv = DVec2::new(r.random_range(0.0..300.0), r.random_range(0.0..200.0));
                let (pf, ef) = (Frame::of(&pose), Frame::of(&ext));
                let l = observe(&cam, lim, &pf, &ef, &v3(pw), uv).expect("projects");
                let res = |pose: &Se3, ext: &Se3, pw: DVec3| {
                    reprojection(&cam, lim, &Frame::of(pose), &Frame::of(ext), &v3(pw), uv).unwrap()
                };
                assert!((l.r - res(&pose, &ext, pw)).norm() < 1e-9);
                let h = 1e-6;
                check_jac(
                    &format!("{name} pose"),
                    &l.j_pose,
                    |k, h| res(&(pose * se3_exp(&unit_vec6(k, h))), &ext, pw),
                    h,
                    &mut worst,
                );
                check_jac(
                    &format!("{name} extrinsic"),
                    &l.j_ext,
                    |k, h| res(&pose, &(ext * se3_exp(&unit_vec6(k, h))), pw),
                    h,
                    &mut worst,
                );
                check_jac(
                    &format!("{name} point"),
                    &l.j_point,
                    |k, h| {
                        let mut d = DVec3::ZERO;
                        d[k] = h;
                        res(&pose, &ext, pw + d)
                    },
                    h * pw.length().max(1.0),
                    &mut worst,
                );
            }
            println!("{name}: worst relative reprojection Jacobian error {worst:.2e}");
        }

        // Priors, including large mismatches (the J_r⁻¹ / J_l⁻¹ terms matter there).
        let mut worst = 0.0f64;
        for _ in 0..300 {
            let ta = perturb(
                &Se3::IDENTITY,
                r.random_range(0.0..30.0),
                r.random_range(0.0..3.0),
                &mut r,
            );
            let tb = perturb(
                &ta,
                r.random_range(0.0..3.0),
                r.random_range(0.0..1.0),
                &mut r,
            );
            let meas = perturb(
                &(ta.inverse() * tb),
                r.random_range(0.0..0.5),
                r.random_range(0.0..0.5),
                &mut r,
            );
            let prior = RelativePrior {
                a: 0,
                b: 1,
                t_a_b: meas,
                sigma_m: 0.02,
                sigma_rad: 0.01,
            };
            let (_, ja, jb) = relative_prior_lin(&prior, &ta, &tb);
            let h = 1e-6;
            check_jac(
                "relative prior a",
                &ja,
                |k, h| relative_prior_lin(&prior, &(ta * se3_exp(&unit_vec6(k, h))), &tb).0,
                h,
                &mut worst,
            );
            check_jac(
                "relative prior b",
                &jb,
                |k, h| relative_prior_lin(&prior, &ta, &(tb * se3_exp(&unit_vec6(k, h)))).0,
                h,
                &mut worst,
            );
            let abs = AbsolutePrior {
                pose: 0,
                t_world_base: perturb(
                    &ta,
                    r.random_range(0.0..1.0),
                    r.random_range(0.0..0.5),
                    &mut r,
                ),
                sigma_m: 0.5,
                sigma_rad: 0.05,
            };
            let (_, j) = absolute_prior_lin(&abs, &ta);
            check_jac(
                "absolute prior",
                &j,
                |k, h| absolute_prior_lin(&abs, &(ta * se3_exp(&unit_vec6(k, h)))).0,
                h,
                &mut worst,
            );
        }
        println!("priors: worst relative Jacobian error {worst:.2e}");
        // A correct prior has zero residual.
        let ta = perturb(&Se3::IDENTITY, 3.0, 1.0, &mut r);
        let tb = perturb(&ta, 1.0, 0.5, &mut r);
        let prior = RelativePrior {
            a: 0,
            b: 1,
            t_a_b: ta.inverse() * tb,
            sigma_m: 0.01,
            sigma_rad: 0.01,
        };
        assert!(relative_prior_lin(&prior, &ta, &tb).0.norm() < 1e-9);
    }

    #[test]
    fn ba_noiseless_rig_converges_exactly() {
        let mut gt = scene(15, 500, 0, 7);
        // Five points with a single observation: unconstrained along their ray, they must not upset the solve
        // (they only have to end up on their ray).
        let single: Vec<Observation> = gt
            .observations
            .iter()
            .step_by(997)
            .take(5)
            .copied()
            .collect();
        for o in single {
            gt.points.push(gt.points[o.point]);
            gt.observations.push(Observation {
                point: gt.points.len() - 1,
                ..o
            });
        }
        println!(
            "scene: {} poses x {} cameras, {} points, {} observations",
            gt.poses.len(),
            gt.cameras.len(),
            gt.points.len(),
            gt.observations.len()
        );
        assert!(reprojection_errors(&gt).iter().all(|e| e.unwrap() < 1e-9));

        // Rigid rig, first pose fixed: the rig baseline fixes the scale.
        let mut p = gt.clone();
        perturb_problem(&mut p, &[0], 11);
        let opts = BaOptions {
            fixed_poses: vec![0],
            ..Default::default()
        };
        let rep = solve(&mut p, &opts).unwrap();
        let (em, er) = max_pose_error(&p.poses, &gt.poses);
        let ep = p.points[..500]
            .iter()
            .zip(&gt.points)
            .map(|(a, b)| a.distance(*b))
            .fold(0.0, f64::max);
        println!("rigid rig: {rep:?}\n  max pose error {em:.2e} m {er:.2e} rad, max point error {ep:.2e} m");
        assert!(rep.converged, "{}", rep.stop_reason);
        assert!(rep.initial_rmse_px > 1.0);
        assert!(rep.final_rmse_px < 1e-6, "{}", rep.final_rmse_px);
        assert!(em < 1e-6 && er < 1e-6 && ep < 1e-6);
        assert_eq!(p.poses[0], gt.poses[0]);
        assert_eq!(rep.unprojected, 0);

        // Extrinsics refined too (cameras 1 and 2 perturbed by 2 cm / 1°), first and last poses fixed (the
        // rig no longer fixes the scale).
        let mut p = gt.clone();
        let last = p.poses.len() - 1;
        perturb_problem(&mut p, &[0, last], 12);
        let mut r = rng(13);
        for e in &mut p.extrinsics[1..] {
            *e = perturb(e, 0.02, 1f64.to_radians(), &mut r);
        }
        let opts = BaOptions {
            fixed_poses: vec![0, last],
            refine_extrinsics: true,
            ..Default::default()
        };
        let rep = solve(&mut p, &opts).unwrap();
        let (em, er) = max_pose_error(&p.poses, &gt.poses);
        let (xm, xr) = max_pose_error(&p.extrinsics, &gt.extrinsics);
        println!(
            "refined rig: {rep:?}\n  max pose error {em:.2e} m {er:.2e} rad, extrinsics {xm:.2e} m {xr:.2e} rad"
        );
        assert!(rep.converged, "{}", rep.stop_reason);
        assert!(rep.final_rmse_px < 1e-6, "{}", rep.final_rmse_px);
        assert!(em < 1e-6 && er < 1e-6 && xm < 1e-6 && xr < 1e-6);
        assert_eq!(p.extrinsics[0], gt.extrinsics[0]);

        // No fixed pose: absolute priors (at the truth, 1 m / 0.1 rad) hold the gauge instead.
        let mut p = gt.clone();
        perturb_problem(&mut p, &[], 14);
        p.absolute_priors = gt
            .poses
            .iter()
            .enumerate()
            .map(|(k, t)| AbsolutePrior {
                pose: k,
                t_world_base: *t,
                sigma_m: 1.0,
                sigma_rad: 0.1,
            })
            .collect();
        let rep = solve(&mut p, &BaOptions::default()).unwrap();
        let (em, er) = max_pose_error(&p.poses, &gt.poses);
        println!("absolute priors: {rep:?}\n  max pose error {em:.2e} m {er:.2e} rad");
        assert!(rep.final_rmse_px < 1e-6 && em < 1e-6 && er < 1e-6);
    }

    /// Adds 1-px Gaussian noise to every observation and a 30-px error to 5 % of them.
    fn add_noise(p: &mut BaProblem, seed: u64) -> usize {
        let mut r = rng(seed);
        let mut outliers = 0;
        for o in &mut p.observations {
            o.uv += DVec2::new(gauss(&mut r), gauss(&mut r));
            if r.random_range(0.0..1.0) < 0.05 {
                let a = r.random_range(0.0..std::f64::consts::TAU);
                o.uv += 30.0 * DVec2::new(a.cos(), a.sin());
                outliers += 1;
            }
        }
        outliers
    }

    fn mean_pose_error(a: &[Se3], b: &[Se3]) -> f64 {
        a.iter().zip(b).map(|(a, b)| a.distance_to(b)).sum::<f64>() / a.len() as f64
    }

    #[test]
    fn ba_robust_losses_resist_outliers_and_gross_priors() {
        let gt = scene(15, 500, 0, 21);
        let mut noisy = gt.clone();
        let outliers = add_noise(&mut noisy, 22);
        // First and last keyframes fixed: the gauge including the scale (the 30 cm rig baseline alone leaves
        // the scale loose enough under noise to hide what the outliers do).
        let fixed = vec![0, gt.poses.len() - 1];
        perturb_problem(&mut noisy, &fixed, 23);
        let mut errs = Vec::new();
        for loss in [Loss::Squared, Loss::Huber, Loss::Cauchy] {
            let mut p = noisy.clone();
            let opts = BaOptions {
                fixed_poses: fixed.clone(),
                loss,
                ..Default::default()
            };
            let rep = solve(&mut p, &opts).unwrap();
            let e = mean_pose_error(&p.poses, &gt.poses);
            println!(
                "{loss:?}: {} outliers of {}; mean pose error {:.2} mm, rmse {:.2} -> {:.2} px, {} iterations ({})",
                outliers,
                p.observations.len(),
                e * 1e3,
                rep.initial_rmse_px,
                rep.final_rmse_px,
                rep.iterations,
                rep.stop_reason
            );
            errs.push(e);
        }
        assert!(
            errs[1] < 0.5 * errs[0] && errs[2] < 0.5 * errs[0],
            "{errs:?}"
        );

        // SLAM odometry between consecutive keyframes (2 mm / 0.05° sigma, exact), one of them grossly wrong
        // (30 cm / 3°): the Huber prior loss keeps keyframe 8 where the images and the other priors put it (as
        // with all priors right; a bounded pull of at most ~3 sigma remains); a quadratic loss drags it.
        let bad = 8;
        let base = noisy.clone();
        let mut r = rng(24);
        let priors = |gross: bool, r: &mut Xoshiro256PlusPlus| -> Vec<RelativePrior> {
            (0..gt.poses.len() - 1)
                .map(|k| {
                    let mut t_a_b = gt.poses[k].inverse() * gt.poses[k + 1];
                    if gross && k + 1 == bad {
                        t_a_b = perturb(&t_a_b, 0.3, 3f64.to_radians(), r);
                    }
                    RelativePrior {
                        a: k,
                        b: k + 1,
                        t_a_b,
                        sigma_m: 0.002,
                        sigma_rad: 0.05f64.to_radians(),
                    }
                })
                .collect()
        };
        let mut sols = Vec::new();
        for (gross, prior_huber) in [(false, 3.0), (true, f64::INFINITY), (true, 3.0)] {
            let mut p = base.clone();
            p.relative_priors = priors(gross, &mut r);
            let opts = BaOptions {
                fixed_poses: fixed.clone(),
                prior_huber,
                ..Default::default()
            };
            let rep = solve(&mut p, &opts).unwrap();
            let (em, er) = pose_error(&p.poses[bad], &gt.poses[bad]);
            println!(
                "gross prior {gross}, prior_huber {prior_huber}: keyframe {bad} error {:.2} mm {:.3}°, mean {:.2} mm ({} iterations, {})",
                em * 1e3,
                er.to_degrees(),
                mean_pose_error(&p.poses, &gt.poses) * 1e3,
                rep.iterations,
                rep.stop_reason
            );
            sols.push((em, p.poses[bad]));
        }
        let shift = sols[2].1.distance_to(&sols[0].1);
        println!(
            "robust: keyframe {bad} moved {:.2} mm by the gross prior",
            shift * 1e3
        );
        assert!(
            sols[2].0 < 0.01,
            "robust prior: keyframe error {} m",
            sols[2].0
        );
        assert!(shift < 0.005, "robust prior: keyframe moved {shift} m");
        assert!(
            sols[1].0 > 0.05,
            "the gross prior should drag a quadratic loss: {} m",
            sols[1].0
        );
    }

    #[test]
    fn ba_schur_step_equals_dense_normal_equations() {
        use nalgebra::{DMatrix, DVector};
        let gt = scene(5, 40, 0, 31);
        let mut p = gt.clone();
        add_noise(&mut p, 32);
        perturb_problem(&mut p, &[0], 33);
        let mut r = rng(34);
        for e in &mut p.extrinsics[1..] {
            *e = perturb(e, 0.02, 0.01, &mut r);
        }
        p.relative_priors = (0..4)
            .map(|k| RelativePrior {
                a: k + 1,
                b: k,
                t_a_b: perturb(
                    &(gt.poses[k + 1].inverse() * gt.poses[k]),
                    0.05,
                    0.02,
                    &mut r,
                ),
                sigma_m: 0.01,
                sigma_rad: 0.01,
            })
            .collect();
        p.absolute_priors = vec![AbsolutePrior {
            pose: 3,
            t_world_base: perturb(&gt.poses[3], 0.1, 0.05, &mut r),
            sigma_m: 0.05,
            sigma_rad: 0.02,
        }];
        let opts = BaOptions {
            fixed_poses: vec![0],
            refine_extrinsics: true,
            ..Default::default()
        };
        validate(&p, &opts).unwrap();
        let s = Structure::build(&p, &opts).unwrap();
        assert_eq!(s.nb, 4 + 2);
        let ctx = Ctx {
            p: &p,
            o: &opts,
            angles: p.cameras.iter().map(|c| c.valid_angle()).collect(),
        };
        let st = State {
            poses: p.poses.clone(),
            exts: p.extrinsics.clone(),
            points: p.points.clone(),
        };
        let lin = linearize(&ctx, &s, &st);

        // Dense J, H, g from the same residual functions.
        let nc = 6 * s.nb;
        let n = nc + 3 * p.points.len();
        let mut h = DMatrix::<f64>::zeros(n, n);
        let mut g = DVector::<f64>::zeros(n);
        let (pf, ef) = st.frames();
        let mut downweighted = 0;
        let mut add = |rows: usize, cols: &[(usize, DMatrix<f64>)], res: &DVector<f64>, w: f64| {
            let mut j = DMatrix::<f64>::zeros(rows, n);
            for (c0, m) in cols {
                j.view_mut((0, *c0), (rows, m.ncols())).copy_from(m);
            }
            h += w * j.transpose() * &j;
            g += w * j.transpose() * res;
        };
        for o in &p.observations {
            let l = observe(
                &p.cameras[o.camera],
                ctx.angles[o.camera],
                &pf[o.pose],
                &ef[o.camera],
                &v3(st.points[o.point]),
                o.uv,
            )
            .unwrap();
            let w = robust(opts.loss, opts.huber_px, l.r.norm_squared()).1;
            if w < 1.0 {
                downweighted += 1;
            }
            let mut cols = vec![(
                nc + 3 * o.point,
                DMatrix::from_column_slice(2, 3, l.j_point.as_slice()),
            )];
            if s.pose_block[o.pose] != NONE {
                cols.push((
                    6 * s.pose_block[o.pose],
                    DMatrix::from_column_slice(2, 6, l.j_pose.as_slice()),
                ));
            }
            if s.ext_block[o.camera] != NONE {
                cols.push((
                    6 * s.ext_block[o.camera],
                    DMatrix::from_column_slice(2, 6, l.j_ext.as_slice()),
                ));
            }
            add(2, &cols, &DVector::from_column_slice(l.r.as_slice()), w);
        }
        for pr in &p.relative_priors {
            let (res, ja, jb) = relative_prior_lin(pr, &st.poses[pr.a], &st.poses[pr.b]);
            let w = robust(Loss::Huber, opts.prior_huber, res.norm_squared()).1;
            let mut cols = Vec::new();
            for (k, j) in [(pr.a, ja), (pr.b, jb)] {
                if s.pose_block[k] != NONE {
                    cols.push((
                        6 * s.pose_block[k],
                        DMatrix::from_column_slice(6, 6, j.as_slice()),
                    ));
                }
            }
            add(6, &cols, &DVector::from_column_slice(res.as_slice()), w);
        }
        for pr in &p.absolute_priors {
            let (res, j) = absolute_prior_lin(pr, &st.poses[pr.pose]);
            let w = robust(Loss::Huber, opts.prior_huber, res.norm_squared()).1;
            let cols = vec![(
                6 * s.pose_block[pr.pose],
                DMatrix::from_column_slice(6, 6, j.as_slice()),
            )];
            add(6, &cols, &DVector::from_column_slice(res.as_slice()), w);
        }
        assert!(
            downweighted > 0,
            "the test needs some Huber-downweighted observations"
        );

        for lambda in [1e-3, 1.0] {
            let step = compute_step(&s, &lin, lambda).unwrap();
            assert_eq!(step.skipped_points, 0);
            let mut a = h.clone();
            for i in 0..n {
                a[(i, i)] += lambda * damp(h[(i, i)]);
            }
            let dense = a.cholesky().unwrap().solve(&(-&g));
            let mut diff: f64 = 0.0;
            for i in 0..nc {
                diff = diff.max((step.dc[i] - dense[i]).abs());
            }
            for (j, d) in step.dx.iter().enumerate() {
                for k in 0..3 {
                    diff = diff.max((d[k] - dense[nc + 3 * j + k]).abs());
                }
            }
            let scale = dense.amax();
            let pred = 0.5
                * dense.dot(
                    &(lambda
                        * DVector::from_iterator(n, (0..n).map(|i| damp(h[(i, i)]) * dense[i]))
                        - &g),
                );
            println!(
                "λ {lambda}: max |δ_schur - δ_dense| = {diff:.2e} (max |δ| {scale:.2e}), predicted decrease {:.6e} vs {:.6e}",
                step.predicted, pred
            );
            assert!(diff < 1e-8 * scale.max(1.0));
            assert!((step.predicted - pred).abs() < 1e-8 * pred.abs());
        }
    }

    #[test]
    fn ba_bad_input_is_an_error_naming_the_culprit() {
        let good = scene(3, 20, 0, 41);
        let opts = BaOptions::default();
        let err = |p: &BaProblem, o: &BaOptions| {
            let mut q = p.clone();
            let e = solve(&mut q, o).expect_err("must fail").to_string();
            // Failing validation leaves the problem untouched (compared as text: NaN != NaN).
            assert_eq!(format!("{:?}", q.poses), format!("{:?}", p.poses));
            e
        };

        let empty = BaProblem {
            cameras: vec![],
            extrinsics: vec![],
            poses: vec![],
            points: vec![],
            observations: vec![],
            relative_priors: vec![],
            absolute_priors: vec![],
        };
        let e = err(&empty, &opts);
        assert!(
            e.contains("empty") && e.contains("no keyframe poses"),
            "{e}"
        );
        let mut p = empty.clone();
        p.poses.push(Se3::IDENTITY);
        assert!(err(&p, &opts).contains("no observations and no priors"));

        let mut p = good.clone();
        p.observations[3].point = 999;
        let e = err(&p, &opts);
        assert!(
            e.contains("observation 3") && e.contains("point 999"),
            "{e}"
        );
        let mut p = good.clone();
        p.observations[4].camera = 3;
        let e = err(&p, &opts);
        assert!(e.contains("observation 4") && e.contains("camera 3"), "{e}");
        let mut p = good.clone();
        p.observations[5].uv.y = f64::NAN;
        let e = err(&p, &opts);
        assert!(e.contains("observation 5") && e.contains("NaN"), "{e}");
        let mut p = good.clone();
        p.points[2].x = f64::INFINITY;
        assert!(err(&p, &opts).contains("point 2"));
        let mut p = good.clone();
        p.poses[1].trans.z = f64::NAN;
        assert!(err(&p, &opts).contains("pose 1"));
        let mut p = good.clone();
        p.extrinsics.pop();
        assert!(err(&p, &opts).contains("3 cameras but 2 extrinsics"));
        let mut p = good.clone();
        p.cameras[1].fx = 0.0;
        assert!(err(&p, &opts).contains("camera 1"));
        let mut p = good.clone();
        p.relative_priors.push(RelativePrior {
            a: 0,
            b: 7,
            t_a_b: Se3::IDENTITY,
            sigma_m: 0.1,
            sigma_rad: 0.1,
        });
        let e = err(&p, &opts);
        assert!(
            e.contains("relative prior 0") && e.contains("pose b 7"),
            "{e}"
        );
        p.relative_priors[0].b = 1;
        p.relative_priors[0].sigma_m = 0.0;
        assert!(err(&p, &opts).contains("relative prior 0: sigmas"));
        let mut p = good.clone();
        p.absolute_priors.push(AbsolutePrior {
            pose: 1,
            t_world_base: Se3 {
                rot: DQuat::from_xyzw(0.0, 0.0, 0.0, 0.0),
                trans: DVec3::ZERO,
            },
            sigma_m: 1.0,
            sigma_rad: 1.0,
        });
        assert!(err(&p, &opts).contains("absolute prior 0"));
        let bad_fixed = BaOptions {
            fixed_poses: vec![0, 5],
            ..Default::default()
        };
        let e = err(&good, &bad_fixed);
        assert!(
            e.contains("fixed_poses entry 1") && e.contains("pose 5"),
            "{e}"
        );
        let bad_loss = BaOptions {
            huber_px: f64::NAN,
            ..Default::default()
        };
        assert!(err(&good, &bad_loss).contains("huber_px"));

        // Finite input whose cost overflows: diverged, naming the keyframe whose terms did.
        let mut p = good.clone();
        let victim = p.observations.iter().position(|o| o.pose == 2).unwrap();
        p.observations[victim].uv = DVec2::new(1e300, 1e300);
        let mut q = p.clone();
        match solve(&mut q, &opts) {
            Err(BaError::Diverged { poses, detail }) => {
                assert_eq!(poses, vec![2], "{detail}");
                assert!(detail.contains("not finite"), "{detail}");
            }
            other => panic!("expected a divergence naming pose 2, got {other:?}"),
        }

        // The error query never panics either.
        let mut p = good.clone();
        p.observations[0].point = 999;
        p.observations[1].camera = 9;
        let e = reprojection_errors(&p);
        assert_eq!(e.len(), p.observations.len());
        assert!(e[0].is_none() && e[1].is_none() && e[2].is_some());

        // A point behind every camera is counted, not fatal.
        let mut p = good.clone();
        let behind = (p.poses[0] * p.extrinsics[0]).transform_point(DVec3::new(0.0, 0.0, -5.0));
        p.points.push(behind);
        let np = p.points.len() - 1;
        p.observations.push(Observation {
            pose: 0,
            camera: 0,
            point: np,
            uv: DVec2::new(100.0, 100.0),
        });
        let rep = solve(
            &mut p,
            &BaOptions {
                fixed_poses: vec![0],
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(rep.unprojected, 1);
        assert_eq!(p.points[np], behind);
    }

    #[test]
    fn ba_pose_graph_and_free_gauge() {
        // Priors only (no points): a loop of relative priors from the truth plus one absolute prior recovers
        // the truth from a perturbed start.
        let gt = scene(8, 10, 0, 61);
        let n = gt.poses.len();
        let mut p = BaProblem {
            observations: vec![],
            points: vec![],
            relative_priors: (0..n)
                .map(|k| {
                    let (a, b) = (k, (k + 3) % n);
                    RelativePrior {
                        a,
                        b,
                        t_a_b: gt.poses[a].inverse() * gt.poses[b],
                        sigma_m: 0.01,
                        sigma_rad: 0.01,
                    }
                })
                .collect(),
            absolute_priors: vec![AbsolutePrior {
                pose: 2,
                t_world_base: gt.poses[2],
                sigma_m: 1.0,
                sigma_rad: 1.0,
            }],
            ..gt.clone()
        };
        let mut r = rng(62);
        for t in &mut p.poses {
            *t = perturb(t, 0.3, 0.2, &mut r);
        }
        let rep = solve(&mut p, &BaOptions::default()).unwrap();
        let (em, er) = max_pose_error(&p.poses, &gt.poses);
        println!("pose graph: {rep:?}, max error {em:.2e} m {er:.2e} rad");
        assert!(
            rep.converged && em < 1e-6 && er < 1e-6,
            "{}",
            rep.stop_reason
        );

        // No fixed pose and no prior: the gauge is free (S is singular but for the damping). LM still drives
        // the reprojection error to zero, in some gauge.
        let mut p = gt.clone();
        perturb_problem(&mut p, &[], 63);
        let rep = solve(&mut p, &BaOptions::default()).unwrap();
        println!("free gauge: {rep:?}");
        assert!(rep.final_rmse_px < 1e-6, "{rep:?}");
    }

    /// `cargo test -p silvr-core --lib sfm::ba::tests::ba_timing -- --ignored --nocapture`
    #[test]
    #[ignore = "timing, not a check"]
    fn ba_timing_large() {
        let t0 = web_time::Instant::now();
        let gt = scene(120, 20_000, 14, 51);
        let mut p = gt.clone();
        add_noise(&mut p, 52);
        perturb_problem(&mut p, &[0], 53);
        println!(
            "scene: {} poses x 3 cameras, {} points, {} observations (built in {:.1} s)",
            p.poses.len(),
            p.points.len(),
            p.observations.len(),
            t0.elapsed().as_secs_f64()
        );
        let opts = BaOptions {
            fixed_poses: vec![0],
            ..Default::default()
        };
        let t = web_time::Instant::now();
        let s = Structure::build(&p, &opts).unwrap();
        println!(
            "structure + symbolic factorisation: {:.3} s ({} blocks, {} block pairs)",
            t.elapsed().as_secs_f64(),
            s.nb,
            s.n_pairs()
        );
        let mut q = p.clone();
        let t = web_time::Instant::now();
        let rep = solve(&mut p, &opts).unwrap();
        let dt = t.elapsed().as_secs_f64();
        println!("{rep:?}");
        println!(
            "rigid rig: {:.2} s total, {:.3} s per LM iteration, mean pose error {:.2} mm",
            dt,
            dt / rep.iterations as f64,
            mean_pose_error(&p.poses, &gt.poses) * 1e3
        );
        // Extrinsics refined: two dense block rows/columns in S and the pose-extrinsic cross terms.
        let opts = BaOptions {
            refine_extrinsics: true,
            max_iterations: 10,
            ..opts
        };
        let t = web_time::Instant::now();
        let rep = solve(&mut q, &opts).unwrap();
        let dt = t.elapsed().as_secs_f64();
        println!(
            "extrinsics refined: {} iterations, {:.3} s per LM iteration",
            rep.iterations,
            dt / rep.iterations as f64
        );
    }
}
