//! Rigid (SE(3)) and similarity (Sim(3)) transforms, pose trajectories and Umeyama alignment, all in f64.
//!
//! Everything here is f64 because poses are chained over kilometre-scale trajectories and compared to
//! millimetre ground truth; the GPU side converts to f32 only after expressing things relative to a local
//! origin. Naming follows the crate convention: `T_a_b` maps points from frame b into frame a.

use glam::{DMat3, DMat4, DQuat, DVec3};
use serde::{Deserialize, Serialize};
use std::ops::Mul;
use thiserror::Error;

/// Errors from geometric constructors and estimators.
#[derive(Clone, Debug, PartialEq, Error)]
pub enum GeometryError {
    #[error("need at least {needed} point pairs, got {got}")]
    TooFewPoints { needed: usize, got: usize },
    #[error("point sets differ in length: {src} source points vs {dst} destination points")]
    LengthMismatch { src: usize, dst: usize },
    #[error("non-finite coordinate in input (pair {index})")]
    NonFinite { index: usize },
    #[error("degenerate input: {0}")]
    Degenerate(&'static str),
    #[error("trajectory has {stamps} stamps but {poses} poses")]
    TrajectoryLengthMismatch { stamps: usize, poses: usize },
    #[error("trajectory is empty")]
    EmptyTrajectory,
    #[error("trajectory stamps must be finite and strictly increasing (problem at index {index})")]
    UnsortedStamps { index: usize },
    #[error("trajectory pose {index} is not finite")]
    NonFinitePose { index: usize },
}

/// Rotation vector (axis * angle) of a unit quaternion, accurate for small angles (atan2, not acos).
fn quat_log(q: DQuat) -> DVec3 {
    // q and -q are the same rotation; pick the representative with w >= 0 so the angle is in [0, pi].
    let q = if q.w < 0.0 { -q } else { q };
    let v = DVec3::new(q.x, q.y, q.z);
    let n = v.length();
    let k = if n > 1e-12 {
        2.0 * n.atan2(q.w) / n
    } else {
        2.0 / q.w
    };
    v * k
}

/// Rotation angle of a unit quaternion in [0, pi], accurate for small angles.
fn quat_angle(q: DQuat) -> f64 {
    let n = DVec3::new(q.x, q.y, q.z).length();
    2.0 * n.atan2(q.w.abs())
}

/// Shortest-path spherical interpolation built on the relative rotation, so that nearby poses (the
/// common case at 10 Hz) interpolate without the precision loss of `acos` close to 1.
fn quat_slerp(a: DQuat, b: DQuat, t: f64) -> DQuat {
    let rel = a.conjugate() * b;
    (a * DQuat::from_scaled_axis(quat_log(rel) * t)).normalize()
}

fn quat_is_finite(q: DQuat) -> bool {
    q.x.is_finite() && q.y.is_finite() && q.z.is_finite() && q.w.is_finite()
}

/// Rigid transform `p' = rot * p + trans`. As `T_a_b` it maps points from frame b into frame a.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Se3 {
    /// Unit quaternion (serialised by glam as `[x, y, z, w]`).
    pub rot: DQuat,
    pub trans: DVec3,
}

impl Default for Se3 {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Se3 {
    pub const IDENTITY: Se3 = Se3 {
        rot: DQuat::IDENTITY,
        trans: DVec3::ZERO,
    };

    /// Normalises `rot` so that slightly-off quaternions from files (5-decimal calibrations) stay rigid.
    pub fn new(rot: DQuat, trans: DVec3) -> Self {
        Self {
            rot: rot.normalize(),
            trans,
        }
    }

    /// From a rotation matrix and translation. `r` must be (close to) a proper rotation.
    pub fn from_rt(r: DMat3, t: DVec3) -> Self {
        Self::new(DQuat::from_mat3(&r), t)
    }

    /// From a homogeneous matrix whose upper-left 3x3 is (close to) a proper rotation.
    pub fn from_mat4(m: DMat4) -> Self {
        Self::from_rt(DMat3::from_mat4(m), m.w_axis.truncate())
    }

    pub fn to_mat4(&self) -> DMat4 {
        DMat4::from_rotation_translation(self.rot, self.trans)
    }

    pub fn rotation_matrix(&self) -> DMat3 {
        DMat3::from_quat(self.rot)
    }

    /// `T_b_a` from `T_a_b`.
    pub fn inverse(&self) -> Self {
        let rot = self.rot.conjugate();
        Self {
            rot,
            trans: -(rot * self.trans),
        }
    }

    pub fn transform_point(&self, p: DVec3) -> DVec3 {
        self.rot * p + self.trans
    }

    /// Rotates a direction; translation does not apply to vectors.
    pub fn transform_vector(&self, v: DVec3) -> DVec3 {
        self.rot * v
    }

    /// Pose at fraction `t` from `self` (t = 0) to `other` (t = 1): shortest-path slerp of the rotation and
    /// linear interpolation of the translation (the usual choice for pose interpolation between stamps;
    /// it is not the SE(3) geodesic, which would couple translation to rotation).
    pub fn interpolate(&self, other: &Se3, t: f64) -> Se3 {
        Se3 {
            rot: quat_slerp(self.rot, other.rot, t),
            trans: self.trans.lerp(other.trans, t),
        }
    }

    /// Angle in [0, pi] of the relative rotation between the two poses.
    pub fn angle_to(&self, other: &Se3) -> f64 {
        quat_angle(self.rot.conjugate() * other.rot)
    }

    /// Euclidean distance between the two translations.
    pub fn distance_to(&self, other: &Se3) -> f64 {
        self.trans.distance(other.trans)
    }

    pub fn is_finite(&self) -> bool {
        quat_is_finite(self.rot) && self.trans.is_finite()
    }

    /// The SE(3) exponential of a twist `(rho, phi)` (translation part, rotation vector): the rigid
    /// motion of constant velocity over unit time. Used to scale a motion (constant-velocity prediction,
    /// deskewing at a fraction of a sweep) and as the update of a Gauss-Newton step.
    pub fn exp(rho: DVec3, phi: DVec3) -> Se3 {
        let theta = phi.length();
        let rot = DQuat::from_scaled_axis(phi);
        // V = I + (1 - cos θ)/θ² [φ]x + (θ - sin θ)/θ³ [φ]x²; Taylor terms below 1e-6 rad.
        let (a, b) = if theta < 1e-6 {
            (0.5, 1.0 / 6.0)
        } else {
            let t2 = theta * theta;
            (
                (1.0 - theta.cos()) / t2,
                (theta - theta.sin()) / (t2 * theta),
            )
        };
        let c = phi.cross(rho);
        let trans = rho + a * c + b * phi.cross(c);
        Se3::new(rot, trans)
    }

    /// The twist `(rho, phi)` whose exponential is `self` ([`Se3::exp`]'s inverse; rotations up to π).
    pub fn log(&self) -> (DVec3, DVec3) {
        let q = if self.rot.w < 0.0 {
            -self.rot
        } else {
            self.rot
        };
        let v = DVec3::new(q.x, q.y, q.z);
        // glam rounds rotations below ~1e-6 rad to none; first order is exact enough there.
        let phi = if v.length() < 1e-6 {
            2.0 * v / q.w
        } else {
            q.to_scaled_axis()
        };
        let theta = phi.length();
        // V⁻¹ = I - ½[φ]x + (1/θ²)(1 - θ sin θ / (2(1 - cos θ)))[φ]x²
        let d = if theta < 1e-6 {
            1.0 / 12.0
        } else {
            (1.0 - theta * theta.sin() / (2.0 * (1.0 - theta.cos()))) / (theta * theta)
        };
        let c = phi.cross(self.trans);
        let rho = self.trans - 0.5 * c + d * phi.cross(c);
        (rho, phi)
    }
}

impl Mul for Se3 {
    type Output = Se3;
    /// `T_a_b * T_b_c = T_a_c`.
    fn mul(self, rhs: Se3) -> Se3 {
        Se3 {
            // Renormalise so long chains do not drift off the unit sphere.
            rot: (self.rot * rhs.rot).normalize(),
            trans: self.rot * rhs.trans + self.trans,
        }
    }
}

impl Mul<DVec3> for Se3 {
    type Output = DVec3;
    fn mul(self, p: DVec3) -> DVec3 {
        self.transform_point(p)
    }
}

/// Similarity transform `p' = scale * rot * p + trans`: the gauge between a monocular/SfM reconstruction
/// and metric ground truth.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sim3 {
    pub scale: f64,
    pub rot: DQuat,
    pub trans: DVec3,
}

impl Default for Sim3 {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Sim3 {
    pub const IDENTITY: Sim3 = Sim3 {
        scale: 1.0,
        rot: DQuat::IDENTITY,
        trans: DVec3::ZERO,
    };

    pub fn new(scale: f64, rot: DQuat, trans: DVec3) -> Self {
        Self {
            scale,
            rot: rot.normalize(),
            trans,
        }
    }

    pub fn from_se3(t: Se3) -> Self {
        Self {
            scale: 1.0,
            rot: t.rot,
            trans: t.trans,
        }
    }

    /// The rigid part (drops the scale).
    pub fn rigid(&self) -> Se3 {
        Se3 {
            rot: self.rot,
            trans: self.trans,
        }
    }

    pub fn to_mat4(&self) -> DMat4 {
        DMat4::from_scale_rotation_translation(DVec3::splat(self.scale), self.rot, self.trans)
    }

    pub fn inverse(&self) -> Self {
        let rot = self.rot.conjugate();
        let inv_s = 1.0 / self.scale;
        Self {
            scale: inv_s,
            rot,
            trans: -(rot * self.trans) * inv_s,
        }
    }

    pub fn transform_point(&self, p: DVec3) -> DVec3 {
        self.scale * (self.rot * p) + self.trans
    }

    /// Rotates and scales a displacement (no translation).
    pub fn transform_vector(&self, v: DVec3) -> DVec3 {
        self.scale * (self.rot * v)
    }

    /// Applies the similarity to a pose `T_a_b` (a world-frame change): rotation composes, translation is
    /// transformed as a point. The result is rigid; scale only affects positions.
    pub fn transform_pose(&self, pose: &Se3) -> Se3 {
        Se3 {
            rot: (self.rot * pose.rot).normalize(),
            trans: self.transform_point(pose.trans),
        }
    }

    /// Least-squares similarity (Umeyama 1991) with `dst[i] ≈ s * R * src[i] + t`.
    ///
    /// With `with_scale == false` the scale is fixed to 1 (rigid Kabsch/Horn alignment). The SVD sign
    /// correction keeps `R` a proper rotation even when the best orthogonal fit is a reflection (planar or
    /// mirrored data). Errors on fewer than 3 pairs, mismatched lengths, non-finite input and on degenerate
    /// configurations where the rotation is not unique (all points equal or collinear).
    pub fn umeyama(src: &[DVec3], dst: &[DVec3], with_scale: bool) -> Result<Sim3, GeometryError> {
        use nalgebra::{Matrix3, Vector3};

        if src.len() != dst.len() {
            return Err(GeometryError::LengthMismatch {
                src: src.len(),
                dst: dst.len(),
            });
        }
        if src.len() < 3 {
            return Err(GeometryError::TooFewPoints {
                needed: 3,
                got: src.len(),
            });
        }
        if let Some(index) = src
            .iter()
            .zip(dst)
            .position(|(a, b)| !a.is_finite() || !b.is_finite())
        {
            return Err(GeometryError::NonFinite { index });
        }

        let n = src.len() as f64;
        let mu_s = src.iter().copied().sum::<DVec3>() / n;
        let mu_d = dst.iter().copied().sum::<DVec3>() / n;
        let mut var_s = 0.0;
        let mut sigma = Matrix3::<f64>::zeros();
        for (a, b) in src.iter().zip(dst) {
            let a = *a - mu_s;
            let b = *b - mu_d;
            var_s += a.length_squared();
            sigma += Vector3::new(b.x, b.y, b.z) * Vector3::new(a.x, a.y, a.z).transpose();
        }
        var_s /= n;
        sigma /= n;
        if var_s.is_nan() || var_s <= 0.0 {
            return Err(GeometryError::Degenerate(
                "source points have zero variance",
            ));
        }

        let svd = nalgebra::SVD::try_new(sigma, true, true, f64::EPSILON, 0)
            .ok_or(GeometryError::Degenerate("SVD did not converge"))?;
        let (u, v_t) = match (svd.u, svd.v_t) {
            (Some(u), Some(v_t)) => (u, v_t),
            _ => return Err(GeometryError::Degenerate("SVD did not converge")),
        };
        // Sorted descending by SVD::try_new.
        let d = svd.singular_values;
        // The rotation is unique iff rank(Sigma) >= 2 (Umeyama's lemma): this catches coincident and
        // collinear sets, including a collinear or collapsed destination.
        if d[0] <= f64::MIN_POSITIVE || d[1] <= 1e-10 * d[0] {
            return Err(GeometryError::Degenerate(
                "points are collinear or coincident; rotation is not determined",
            ));
        }
        // Sign correction: flip the axis of the smallest singular value when U V^T would be a reflection.
        let mut s = Vector3::new(1.0, 1.0, 1.0);
        if u.determinant() * v_t.determinant() < 0.0 {
            s[2] = -1.0;
        }
        let r = u * Matrix3::from_diagonal(&s) * v_t;
        let scale = if with_scale { d.dot(&s) / var_s } else { 1.0 };
        let rot = quat_from_matrix(&r);
        let trans = mu_d - scale * (rot * mu_s);
        Ok(Sim3 { scale, rot, trans })
    }
}

/// A proper rotation held as a nalgebra matrix (an SVD's product), as a unit quaternion.
pub(crate) fn quat_from_matrix(r: &nalgebra::Matrix3<f64>) -> DQuat {
    // Both store columns first.
    let mut cols = [0.0; 9];
    cols.copy_from_slice(r.as_slice());
    DQuat::from_mat3(&DMat3::from_cols_array(&cols)).normalize()
}

impl Mul for Sim3 {
    type Output = Sim3;
    fn mul(self, rhs: Sim3) -> Sim3 {
        Sim3 {
            scale: self.scale * rhs.scale,
            rot: (self.rot * rhs.rot).normalize(),
            trans: self.scale * (self.rot * rhs.trans) + self.trans,
        }
    }
}

impl Mul<DVec3> for Sim3 {
    type Output = DVec3;
    fn mul(self, p: DVec3) -> DVec3 {
        self.transform_point(p)
    }
}

/// Serialised shape of [`Trajectory`]; deserialisation goes through [`Trajectory::new`] so that a file can
/// never produce an unsorted trajectory.
#[derive(Serialize, Deserialize)]
struct TrajectoryData {
    stamps: Vec<f64>,
    poses: Vec<Se3>,
}

impl TryFrom<TrajectoryData> for Trajectory {
    type Error = GeometryError;
    fn try_from(d: TrajectoryData) -> Result<Self, GeometryError> {
        Trajectory::new(d.stamps, d.poses)
    }
}

impl From<Trajectory> for TrajectoryData {
    fn from(t: Trajectory) -> Self {
        TrajectoryData {
            stamps: t.stamps,
            poses: t.poses,
        }
    }
}

/// Time-stamped poses (e.g. `T_world_base` at each odometry stamp), sorted by time.
///
/// Fields are private so the invariants checked by [`Trajectory::new`] (non-empty, equal lengths, finite
/// and strictly increasing stamps, finite poses) always hold.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "TrajectoryData", into = "TrajectoryData")]
pub struct Trajectory {
    stamps: Vec<f64>,
    poses: Vec<Se3>,
}

impl Trajectory {
    pub fn new(stamps: Vec<f64>, poses: Vec<Se3>) -> Result<Self, GeometryError> {
        if stamps.len() != poses.len() {
            return Err(GeometryError::TrajectoryLengthMismatch {
                stamps: stamps.len(),
                poses: poses.len(),
            });
        }
        if stamps.is_empty() {
            return Err(GeometryError::EmptyTrajectory);
        }
        for (i, s) in stamps.iter().enumerate() {
            if !s.is_finite() || (i > 0 && *s <= stamps[i - 1]) {
                return Err(GeometryError::UnsortedStamps { index: i });
            }
        }
        if let Some(index) = poses.iter().position(|p| !p.is_finite()) {
            return Err(GeometryError::NonFinitePose { index });
        }
        Ok(Self { stamps, poses })
    }

    pub fn stamps(&self) -> &[f64] {
        &self.stamps
    }

    pub fn poses(&self) -> &[Se3] {
        &self.poses
    }

    pub fn len(&self) -> usize {
        self.stamps.len()
    }

    /// Always false (construction rejects empty trajectories); present for API symmetry with `len`.
    pub fn is_empty(&self) -> bool {
        self.stamps.is_empty()
    }

    /// First and last stamp.
    pub fn span(&self) -> (f64, f64) {
        (self.stamps[0], self.stamps[self.stamps.len() - 1])
    }

    /// Pose at time `t`, interpolated between the neighbouring stamps ([`Se3::interpolate`]). Both ends
    /// are inclusive; `None` outside the span, because extrapolating odometry silently invents motion.
    pub fn at(&self, t: f64) -> Option<Se3> {
        let (t0, t1) = self.span();
        if !(t >= t0 && t <= t1) {
            return None;
        }
        // First index with stamp > t; t >= t0 so it is >= 1 unless there is a single stamp.
        let hi = self.stamps.partition_point(|&s| s <= t);
        if hi == self.stamps.len() {
            return Some(self.poses[hi - 1]);
        }
        let lo = hi - 1;
        let (s0, s1) = (self.stamps[lo], self.stamps[hi]);
        let alpha = (t - s0) / (s1 - s0);
        Some(self.poses[lo].interpolate(&self.poses[hi], alpha))
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn se3_exp_and_log_are_inverse_and_exp_is_constant_velocity() {
        let cases = [
            (DVec3::new(0.3, -1.2, 2.0), DVec3::new(0.1, 0.2, -0.3)),
            (DVec3::new(1.0, 0.0, 0.0), DVec3::ZERO),
            (DVec3::new(-0.5, 0.4, 0.1), DVec3::new(0.0, 0.0, 3.0)),
            (DVec3::new(0.0, 0.1, 0.0), DVec3::new(1e-9, 0.0, 0.0)),
        ];
        for (rho, phi) in cases {
            let t = Se3::exp(rho, phi);
            let (r2, p2) = t.log();
            assert!(
                r2.distance(rho) < 1e-9 && p2.distance(phi) < 1e-9,
                "{rho} {phi}: {r2} {p2}"
            );
            // Two half steps of the same twist make the whole motion (a screw, not a lerp).
            let half = Se3::exp(0.5 * rho, 0.5 * phi);
            let twice = half * half;
            assert!(twice.distance_to(&t) < 1e-9 && twice.angle_to(&t) < 1e-9);
        }
    }
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_xoshiro::Xoshiro256PlusPlus;
    use std::f64::consts::{FRAC_PI_2, PI};

    fn rng(seed: u64) -> Xoshiro256PlusPlus {
        Xoshiro256PlusPlus::seed_from_u64(seed)
    }

    fn rand_vec(r: &mut Xoshiro256PlusPlus, s: f64) -> DVec3 {
        DVec3::new(
            r.random_range(-s..s),
            r.random_range(-s..s),
            r.random_range(-s..s),
        )
    }

    fn rand_quat(r: &mut Xoshiro256PlusPlus) -> DQuat {
        loop {
            let q = DQuat::from_xyzw(
                r.random_range(-1.0..1.0),
                r.random_range(-1.0..1.0),
                r.random_range(-1.0..1.0),
                r.random_range(-1.0..1.0),
            );
            let n = q.length();
            if n > 0.1 && n < 1.0 {
                return q / n;
            }
        }
    }

    fn rand_se3(r: &mut Xoshiro256PlusPlus) -> Se3 {
        Se3::new(rand_quat(r), rand_vec(r, 10.0))
    }

    fn assert_se3_close(a: &Se3, b: &Se3, tol: f64) {
        assert!(
            a.angle_to(b) < tol && a.distance_to(b) < tol,
            "{a:?} vs {b:?}: angle {} dist {}",
            a.angle_to(b),
            a.distance_to(b)
        );
    }

    #[test]
    fn se3_inverse_and_composition() {
        let mut r = rng(1);
        for _ in 0..200 {
            let a = rand_se3(&mut r);
            let b = rand_se3(&mut r);
            let c = rand_se3(&mut r);
            assert_se3_close(&(a.inverse() * a), &Se3::IDENTITY, 1e-12);
            assert_se3_close(&(a * a.inverse()), &Se3::IDENTITY, 1e-12);
            assert_se3_close(&((a * b) * c), &(a * (b * c)), 1e-12);
            let p = rand_vec(&mut r, 5.0);
            // Composition applies the right operand first, and agrees with the matrix form.
            assert!(((a * b) * p - a * (b * p)).length() < 1e-12);
            assert!(
                ((a * b).to_mat4().transform_point3(p)
                    - (a.to_mat4() * b.to_mat4()).transform_point3(p))
                .length()
                    < 1e-11
            );
            assert!((a.inverse() * (a * p) - p).length() < 1e-12);
            assert!((a.transform_vector(p) - (a * p - a.trans)).length() < 1e-12);
            assert_se3_close(&Se3::from_mat4(a.to_mat4()), &a, 1e-12);
            assert_se3_close(&Se3::from_rt(a.rotation_matrix(), a.trans), &a, 1e-12);
        }
    }

    #[test]
    fn se3_interpolate() {
        let a = Se3::new(DQuat::IDENTITY, DVec3::new(1.0, 2.0, 3.0));
        let b = Se3::new(
            DQuat::from_rotation_z(FRAC_PI_2),
            DVec3::new(3.0, 2.0, -1.0),
        );
        assert_se3_close(&a.interpolate(&b, 0.0), &a, 1e-15);
        assert_se3_close(&a.interpolate(&b, 1.0), &b, 1e-15);
        let mid = a.interpolate(&b, 0.5);
        assert_se3_close(
            &mid,
            &Se3::new(DQuat::from_rotation_z(PI / 4.0), DVec3::new(2.0, 2.0, 1.0)),
            1e-14,
        );
        // Short path: -q is the same rotation; interpolating towards it must not go the long way round.
        let b_neg = Se3 { rot: -b.rot, ..b };
        assert_se3_close(&a.interpolate(&b_neg, 0.5), &mid, 1e-14);
        assert!((a.angle_to(&b) - FRAC_PI_2).abs() < 1e-14);
        assert!((a.angle_to(&b_neg) - FRAC_PI_2).abs() < 1e-14);
        // Tiny rotations interpolate accurately (no acos precision loss).
        let c = Se3::new(DQuat::from_rotation_x(1e-9), DVec3::ZERO);
        let q = Se3::IDENTITY.interpolate(&c, 0.25);
        assert!((q.angle_to(&Se3::IDENTITY) - 0.25e-9).abs() < 1e-22);
        // Random: the midpoint is equidistant in angle from both ends.
        let mut r = rng(2);
        for _ in 0..100 {
            let a = rand_se3(&mut r);
            let b = rand_se3(&mut r);
            let t = r.random_range(0.0..1.0);
            let m = a.interpolate(&b, t);
            let total = a.angle_to(&b);
            assert!((a.angle_to(&m) - t * total).abs() < 1e-12);
            assert!((m.angle_to(&b) - (1.0 - t) * total).abs() < 1e-12);
        }
    }

    #[test]
    fn trajectory_at() {
        let p0 = Se3::new(DQuat::IDENTITY, DVec3::ZERO);
        let p1 = Se3::new(DQuat::from_rotation_z(0.2), DVec3::new(1.0, 0.0, 0.0));
        let p2 = Se3::new(DQuat::from_rotation_z(0.6), DVec3::new(1.0, 2.0, 0.0));
        let traj = Trajectory::new(vec![10.0, 11.0, 13.0], vec![p0, p1, p2]).unwrap();
        assert_eq!(traj.span(), (10.0, 13.0));
        assert_se3_close(&traj.at(10.0).unwrap(), &p0, 1e-15);
        assert_se3_close(&traj.at(11.0).unwrap(), &p1, 1e-15);
        assert_se3_close(&traj.at(13.0).unwrap(), &p2, 1e-15);
        let q = traj.at(12.5).unwrap();
        assert_se3_close(
            &q,
            &Se3::new(DQuat::from_rotation_z(0.5), DVec3::new(1.0, 1.5, 0.0)),
            1e-14,
        );
        let q = traj.at(10.25).unwrap();
        assert_se3_close(
            &q,
            &Se3::new(DQuat::from_rotation_z(0.05), DVec3::new(0.25, 0.0, 0.0)),
            1e-14,
        );
        assert!(traj.at(9.999).is_none());
        assert!(traj.at(13.001).is_none());
        assert!(traj.at(f64::NAN).is_none());

        let single = Trajectory::new(vec![1.0], vec![p1]).unwrap();
        assert_eq!(single.at(1.0), Some(p1));
        assert!(single.at(1.5).is_none());

        assert!(matches!(
            Trajectory::new(vec![0.0, 0.0], vec![p0, p1]),
            Err(GeometryError::UnsortedStamps { index: 1 })
        ));
        assert!(matches!(
            Trajectory::new(vec![0.0, f64::NAN], vec![p0, p1]),
            Err(GeometryError::UnsortedStamps { index: 1 })
        ));
        assert!(matches!(
            Trajectory::new(vec![0.0], vec![p0, p1]),
            Err(GeometryError::TrajectoryLengthMismatch { .. })
        ));
        assert!(matches!(
            Trajectory::new(vec![], vec![]),
            Err(GeometryError::EmptyTrajectory)
        ));

        // Serde goes through validation.
        let json = serde_json::to_string(&traj).unwrap();
        let back: Trajectory = serde_json::from_str(&json).unwrap();
        assert_eq!(back.len(), 3);
        assert_se3_close(&back.at(12.0).unwrap(), &traj.at(12.0).unwrap(), 1e-12);
        let bad = json.replacen("10.0", "20.0", 1);
        assert!(serde_json::from_str::<Trajectory>(&bad).is_err());
    }

    #[test]
    fn sim3_algebra() {
        let mut r = rng(3);
        for _ in 0..100 {
            let a = Sim3::new(
                r.random_range(0.1..10.0),
                rand_quat(&mut r),
                rand_vec(&mut r, 10.0),
            );
            let b = Sim3::new(
                r.random_range(0.1..10.0),
                rand_quat(&mut r),
                rand_vec(&mut r, 10.0),
            );
            let p = rand_vec(&mut r, 5.0);
            assert!(((a * b) * p - a * (b * p)).length() < 1e-10);
            assert!((a.inverse() * (a * p) - p).length() < 1e-10);
            assert!((a.to_mat4().transform_point3(p) - a * p).length() < 1e-10);
            assert!(
                ((a * b).to_mat4().transform_point3(p)
                    - (a.to_mat4() * b.to_mat4()).transform_point3(p))
                .length()
                    < 1e-9
            );
            let s = rand_se3(&mut r);
            assert!((Sim3::from_se3(s) * p - s * p).length() < 1e-12);
            assert_se3_close(&Sim3::from_se3(s).rigid(), &s, 0.0 + 1e-15);
        }
    }

    fn rms(sim: &Sim3, src: &[DVec3], dst: &[DVec3]) -> f64 {
        (src.iter()
            .zip(dst)
            .map(|(a, b)| (*sim * *a - *b).length_squared())
            .sum::<f64>()
            / src.len() as f64)
            .sqrt()
    }

    #[test]
    fn umeyama_recovers_sim3() {
        let mut r = rng(4);
        for trial in 0..50 {
            let truth = Sim3::new(
                r.random_range(0.2..5.0),
                rand_quat(&mut r),
                rand_vec(&mut r, 20.0),
            );
            let n = 10 + trial;
            let src: Vec<DVec3> = (0..n)
                .map(|_| rand_vec(&mut r, 3.0) + DVec3::new(50.0, -20.0, 5.0))
                .collect();
            let dst: Vec<DVec3> = src.iter().map(|p| truth * *p).collect();
            let est = Sim3::umeyama(&src, &dst, true).unwrap();
            assert!(
                (est.scale - truth.scale).abs() < 1e-9,
                "scale {} vs {}",
                est.scale,
                truth.scale
            );
            assert!(quat_angle(est.rot.conjugate() * truth.rot) < 1e-9);
            assert!(
                (est.trans - truth.trans).length() < 1e-9,
                "{:?} vs {:?}",
                est.trans,
                truth.trans
            );

            // Rigid fit of rigidly related points: scale stays exactly 1 and the fit is exact.
            let rigid = Se3::new(truth.rot, truth.trans);
            let dst_rigid: Vec<DVec3> = src.iter().map(|p| rigid * *p).collect();
            let est = Sim3::umeyama(&src, &dst_rigid, false).unwrap();
            assert_eq!(est.scale, 1.0);
            assert!(est.rigid().angle_to(&rigid) < 1e-9 && est.rigid().distance_to(&rigid) < 1e-9);
            // ... and with scaled data the rigid fit still reports scale 1.
            let est = Sim3::umeyama(&src, &dst, false).unwrap();
            assert_eq!(est.scale, 1.0);
        }
    }

    #[test]
    fn umeyama_planar_needs_sign_correction() {
        // Coplanar points: Sigma has rank 2, so the SVD alone may return a reflection; the sign correction
        // must still recover the exact rotation.
        let mut r = rng(5);
        for _ in 0..50 {
            let truth = Sim3::new(
                r.random_range(0.5..2.0),
                rand_quat(&mut r),
                rand_vec(&mut r, 5.0),
            );
            let src: Vec<DVec3> = (0..12)
                .map(|_| DVec3::new(r.random_range(-2.0..2.0), r.random_range(-2.0..2.0), 0.0))
                .collect();
            let dst: Vec<DVec3> = src.iter().map(|p| truth * *p).collect();
            let est = Sim3::umeyama(&src, &dst, true).unwrap();
            assert!(rms(&est, &src, &dst) < 1e-9);
            assert!((est.scale - truth.scale).abs() < 1e-9);
            assert!(quat_angle(est.rot.conjugate() * truth.rot) < 1e-9);
        }
    }

    #[test]
    fn umeyama_mirrored_data_gives_best_proper_rotation() {
        // dst is a mirror image of src: no rotation fits exactly. The result must be a proper rotation and no
        // random rotation (with its optimal translation) may fit better.
        let mut r = rng(6);
        let src: Vec<DVec3> = (0..20).map(|_| rand_vec(&mut r, 2.0)).collect();
        let dst: Vec<DVec3> = src
            .iter()
            .map(|p| DVec3::new(p.x, p.y, -p.z) + DVec3::new(1.0, 2.0, 3.0))
            .collect();
        let est = Sim3::umeyama(&src, &dst, false).unwrap();
        assert!(est.to_mat4().determinant() > 0.0);
        let best = rms(&est, &src, &dst);
        assert!(best > 0.1, "a rotation cannot fit a reflection exactly");
        let n = src.len() as f64;
        let mu_s = src.iter().copied().sum::<DVec3>() / n;
        let mu_d = dst.iter().copied().sum::<DVec3>() / n;
        for _ in 0..2000 {
            let q = rand_quat(&mut r);
            let cand = Sim3::new(1.0, q, mu_d - q * mu_s);
            assert!(rms(&cand, &src, &dst) >= best - 1e-12);
        }
        // Also with scale: must not flip the scale sign to fake the reflection.
        let est = Sim3::umeyama(&src, &dst, true).unwrap();
        assert!(est.scale > 0.0);
    }

    #[test]
    fn umeyama_rejects_bad_input() {
        let p = |x: f64, y: f64, z: f64| DVec3::new(x, y, z);
        let line: Vec<DVec3> = (0..10)
            .map(|i| p(i as f64, 2.0 * i as f64, -(i as f64)))
            .collect();
        let other: Vec<DVec3> = (0..10).map(|i| p(i as f64, (i * i) as f64, 1.0)).collect();
        assert!(matches!(
            Sim3::umeyama(&line, &other, true),
            Err(GeometryError::Degenerate(_))
        ));
        assert!(matches!(
            Sim3::umeyama(&other, &line, false),
            Err(GeometryError::Degenerate(_))
        ));
        let same = vec![p(1.0, 2.0, 3.0); 5];
        assert!(matches!(
            Sim3::umeyama(&same, &other[..5], true),
            Err(GeometryError::Degenerate(_))
        ));
        assert!(matches!(
            Sim3::umeyama(&other[..5], &same, true),
            Err(GeometryError::Degenerate(_))
        ));
        assert!(matches!(
            Sim3::umeyama(&other[..2], &other[..2], true),
            Err(GeometryError::TooFewPoints { needed: 3, got: 2 })
        ));
        assert!(matches!(
            Sim3::umeyama(&other[..4], &other[..5], true),
            Err(GeometryError::LengthMismatch { src: 4, dst: 5 })
        ));
        let mut nan = other.clone();
        nan[7].y = f64::NAN;
        assert!(matches!(
            Sim3::umeyama(&nan, &other, true),
            Err(GeometryError::NonFinite { index: 7 })
        ));
        // Three non-collinear points are enough.
        let tri = [p(0.0, 0.0, 0.0), p(1.0, 0.0, 0.0), p(0.0, 1.0, 0.0)];
        let t = Se3::new(DQuat::from_rotation_y(0.3), p(1.0, 1.0, 1.0));
        let tri_dst: Vec<DVec3> = tri.iter().map(|q| t * *q).collect();
        let est = Sim3::umeyama(&tri, &tri_dst, false).unwrap();
        assert!(est.rigid().angle_to(&t) < 1e-12 && est.rigid().distance_to(&t) < 1e-12);
    }
}
