//! Guided descriptor matching between two images whose relative pose the SLAM prior already knows.
//!
//! COLMAP matches every descriptor against every other and verifies the survivors with RANSAC; SiLVR
//! knows roughly where each camera was, so a feature of image A can only match a feature of image B that
//! lies near its epipolar line (the prior's relative pose, inflated by its error). Gating first and
//! comparing descriptors only for the candidates that pass makes the matcher cheaper (most of the
//! N_a x N_b descriptor products are skipped) and more reliable on repetitive facades (the window three
//! bays along is off the line). The usual tests follow: nearest neighbour in descriptor space among the
//! gated candidates, Lowe's ratio against the second nearest, a maximum distance, and the mutual check.

use glam::{DMat3, DVec3, Vec3};

use crate::geometry::Se3;

/// Matcher settings (COLMAP's matcher defaults where they apply).
#[derive(Clone, Debug)]
pub struct MatchOptions {
    /// Lowe's ratio of nearest to second-nearest descriptor distance.
    pub ratio: f32,
    /// Largest L2 distance between unit descriptors.
    pub max_distance: f32,
    /// Keep a match only when each feature is the other's best.
    pub mutual: bool,
    /// Largest angle (degrees) between a feature's ray in B and the epipolar plane of its partner in A:
    /// the prior's relative rotation error plus its translation error seen from the scene's depth.
    pub epipolar_gate_deg: f64,
    /// Nearest scene depth (m) the gate allows along A's ray (a matched point must lie in front of both).
    pub min_depth_m: f64,
    /// A pair with fewer matches is dropped (chance agreements).
    pub min_matches: usize,
}

impl Default for MatchOptions {
    fn default() -> Self {
        MatchOptions {
            ratio: 0.8,
            max_distance: 0.7,
            mutual: true,
            epipolar_gate_deg: 3.0,
            min_depth_m: 0.3,
            min_matches: 15,
        }
    }
}

/// The prior's geometry of a pair: `T_b_a` (camera A's frame into camera B's), from which the epipolar
/// plane of each ray of A follows.
#[derive(Clone, Copy, Debug)]
pub struct EpipolarGate {
    rot_b_a: DMat3,
    /// Centre of camera A in B's frame.
    t_b_a: DVec3,
    sin_gate: f64,
    min_depth: f64,
}

impl EpipolarGate {
    /// From the two cameras' `T_world_cam` (OpenCV axes).
    pub fn new(t_world_a: &Se3, t_world_b: &Se3, opts: &MatchOptions) -> Self {
        let t_b_a = t_world_b.inverse() * *t_world_a;
        EpipolarGate {
            rot_b_a: t_b_a.rotation_matrix(),
            t_b_a: t_b_a.trans,
            sin_gate: opts.epipolar_gate_deg.to_radians().sin(),
            min_depth: opts.min_depth_m,
        }
    }

    /// Whether unit ray `fb` (B's frame) can see the point on unit ray `fa` (A's frame), `ra` being
    /// `rot_b_a * fa`. Two conditions: `fb` lies within the gate of the epipolar plane spanned by the
    /// baseline and `ra`, and it points into the part of that plane the ray of A sweeps beyond
    /// `min_depth` (between the direction of the nearest allowed point and `ra` itself, the vanishing
    /// direction), so a match cannot place the point behind either camera. With no baseline (two cameras
    /// of one rig instant sharing a centre) only the direction test applies. The matcher asks this for
    /// every pair of features, so it goes through [`GateRow`], computed once per feature of A.
    pub fn accepts(&self, ra: DVec3, fb: DVec3) -> bool {
        self.row(ra).accepts(fb.as_vec3())
    }

    /// What the gate needs of one feature of A (`ra` = `rotate(fa)`): three dot products per candidate.
    pub fn row(&self, ra: DVec3) -> GateRow {
        let slack = self.sin_gate.asin();
        let n = self.t_b_a.cross(ra);
        let nn = n.length();
        let baseline = self.t_b_a.length();
        if !(nn > 1e-9 * baseline.max(1e-12) && baseline > 1e-9) {
            // Direction test only: the angle to `ra` within the gate.
            let c = slack.cos() as f32;
            return GateRow {
                normal: Vec3::ZERO,
                sin_gate: 1.0,
                near: ra.as_vec3(),
                ra: ra.as_vec3(),
                cos_limit: c,
            };
        }
        // Within the plane: fb must lie in the wedge between `near` and `ra`, widened by the gate;
        // angle(u, fb) <= θ is u·fb >= cos θ for θ in [0, π].
        let near = (ra * self.min_depth + self.t_b_a).normalize_or_zero();
        let limit = near.angle_between(ra) + slack;
        GateRow {
            normal: (n / nn).as_vec3(),
            sin_gate: self.sin_gate as f32,
            near: near.as_vec3(),
            ra: ra.as_vec3(),
            cos_limit: if limit >= std::f64::consts::PI {
                -2.0
            } else {
                limit.cos() as f32
            },
        }
    }

    /// `rot_b_a * fa`: the direction of A's ray in B's frame.
    #[inline]
    pub fn rotate(&self, fa: DVec3) -> DVec3 {
        self.rot_b_a * fa
    }
}

/// The gate for one feature of A, in `f32`: the unit normal of its epipolar plane in B's frame and the
/// cosine limits of the wedge its point can appear in.
#[derive(Clone, Copy, Debug)]
pub struct GateRow {
    normal: Vec3,
    sin_gate: f32,
    near: Vec3,
    ra: Vec3,
    cos_limit: f32,
}

impl GateRow {
    /// Whether unit ray `fb` (B's frame) passes (see [`EpipolarGate::accepts`]).
    #[inline]
    pub fn accepts(&self, fb: Vec3) -> bool {
        self.normal.dot(fb).abs() <= self.sin_gate
            && self.near.dot(fb) >= self.cos_limit
            && self.ra.dot(fb) >= self.cos_limit
    }
}

/// Matches between A and B as `(index in A, index in B, descriptor distance)`, sorted by A's index. `desc_*` are
/// 128-float unit descriptors back to back; `rays_*` the features' unit rays in their camera frames
/// (`None` where the pixel does not unproject: never matched). With `gate: None` every pair of
/// features is a candidate (the unguided baseline).
pub fn match_features(
    desc_a: &[f32],
    rays_a: &[Option<DVec3>],
    desc_b: &[f32],
    rays_b: &[Option<DVec3>],
    gate: Option<&EpipolarGate>,
    opts: &MatchOptions,
) -> Vec<(u32, u32, f32)> {
    const D: usize = 128;
    let (na, nb) = (rays_a.len(), rays_b.len());
    debug_assert_eq!(desc_a.len(), na * D);
    debug_assert_eq!(desc_b.len(), nb * D);
    if na == 0 || nb == 0 || desc_a.len() != na * D || desc_b.len() != nb * D {
        return Vec::new();
    }
    // Squared L2 distance of unit vectors = 2 - 2 dot; track the best two by largest dot.
    #[derive(Clone, Copy)]
    struct Best {
        dot1: f32,
        dot2: f32,
        idx: u32,
    }
    let empty = Best {
        dot1: f32::NEG_INFINITY,
        dot2: f32::NEG_INFINITY,
        idx: u32::MAX,
    };
    let mut best_a = vec![empty; na];
    let mut best_b = vec![empty; nb];
    let push = |b: &mut Best, dot: f32, idx: u32| {
        if dot > b.dot1 {
            b.dot2 = b.dot1;
            b.dot1 = dot;
            b.idx = idx;
        } else if dot > b.dot2 {
            b.dot2 = dot;
        }
    };
    // B's rays as three coordinate arrays (a ray that does not unproject never passes: NaN), so the
    // plane test runs over all of B in one vectorised pass per feature of A; the wedge test and the
    // descriptor product follow for the few percent that pass.
    let mut bx = vec![f32::NAN; nb];
    let mut by = vec![f32::NAN; nb];
    let mut bz = vec![f32::NAN; nb];
    for (j, r) in rays_b.iter().enumerate() {
        if let Some(f) = r {
            (bx[j], by[j], bz[j]) = (f.x as f32, f.y as f32, f.z as f32);
        }
    }
    let mut plane = vec![0.0f32; nb];
    for (i, ra) in rays_a.iter().enumerate() {
        let Some(fa) = ra else { continue };
        let da = &desc_a[i * D..(i + 1) * D];
        let mut consider = |j: usize| {
            let db = &desc_b[j * D..(j + 1) * D];
            let dot = dot128(da, db);
            push(&mut best_a[i], dot, j as u32);
            push(&mut best_b[j], dot, i as u32);
        };
        match gate {
            Some(g) => {
                let row = g.row(g.rotate(*fa));
                let n = row.normal;
                for (((p, x), y), z) in plane.iter_mut().zip(&bx).zip(&by).zip(&bz) {
                    *p = (n.x * x + n.y * y + n.z * z).abs();
                }
                for (j, &p) in plane.iter().enumerate() {
                    // `!(p > gate)` would let NaN through; `p <= gate` does not.
                    if p <= row.sin_gate && row.accepts(Vec3::new(bx[j], by[j], bz[j])) {
                        consider(j);
                    }
                }
            }
            None => {
                for (j, x) in bx.iter().enumerate() {
                    if !x.is_nan() {
                        consider(j);
                    }
                }
            }
        }
    }
    let dist = |dot: f32| (2.0 - 2.0 * dot).max(0.0).sqrt();
    let max_d = opts.max_distance;
    let passes = |b: &Best| {
        if b.idx == u32::MAX {
            return false;
        }
        let d1 = dist(b.dot1);
        // A lone candidate has no second: the ratio test passes (the gate already did the pruning).
        let d2 = if b.dot2.is_finite() {
            dist(b.dot2)
        } else {
            f32::INFINITY
        };
        d1 <= max_d && d1 < opts.ratio * d2
    };
    let mut out = Vec::new();
    for (i, b) in best_a.iter().enumerate() {
        if !passes(b) {
            continue;
        }
        let j = b.idx as usize;
        if opts.mutual && (best_b[j].idx != i as u32 || !passes(&best_b[j])) {
            continue;
        }
        out.push((i as u32, j as u32, dist(b.dot1)));
    }
    out
}

/// 128-float dot product in four accumulators (auto-vectorised).
#[inline]
pub(crate) fn dot128(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    for (ca, cb) in a.chunks_exact(8).zip(b.chunks_exact(8)) {
        for k in 0..8 {
            acc[k] += ca[k] * cb[k];
        }
    }
    acc.iter().sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;
    use rand::{Rng, SeedableRng};

    fn unit_desc(rng: &mut impl Rng) -> Vec<f32> {
        let v: Vec<f32> = (0..128).map(|_| rng.random::<f32>()).collect();
        let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        v.into_iter().map(|x| x / n).collect()
    }

    /// Two cameras 1 m apart, points in front: the true correspondences are matched, a feature whose
    /// descriptor copies another's but lies off the epipolar line is not, and the unguided matcher
    /// confuses exactly those repeated descriptors (the facade's repeated windows).
    #[test]
    fn gate_keeps_true_matches_and_rejects_repeated_texture_off_the_line() {
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(7);
        let t_wa = Se3::IDENTITY;
        let t_wb = Se3::new(DQuat::from_rotation_y(0.1), DVec3::new(1.0, 0.0, 0.0));
        let n = 60;
        let points: Vec<DVec3> = (0..n)
            .map(|_| {
                DVec3::new(
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-2.0..2.0),
                    rng.random_range(4.0..12.0),
                )
            })
            .collect();
        let mut desc_a = Vec::new();
        let mut desc_b = Vec::new();
        let mut rays_a = Vec::new();
        let mut rays_b = Vec::new();
        let inv_b = t_wb.inverse();
        for p in &points {
            let d = unit_desc(&mut rng);
            desc_a.extend_from_slice(&d);
            desc_b.extend_from_slice(&d);
            rays_a.push(Some(p.normalize()));
            rays_b.push(Some(inv_b.transform_point(*p).normalize()));
        }
        // A decoy in B: the descriptor of A's feature 0 at a direction far off its epipolar plane.
        desc_b.extend_from_slice(&desc_a[0..128]);
        rays_b.push(Some(DVec3::new(0.0, 0.8, 1.0).normalize()));
        let opts = MatchOptions::default();
        let gate = EpipolarGate::new(&t_wa, &t_wb, &opts);
        let m = match_features(&desc_a, &rays_a, &desc_b, &rays_b, Some(&gate), &opts);
        assert_eq!(m.len(), n, "{m:?}");
        assert!(m.iter().all(|&(i, j, _)| i == j), "{m:?}");
        // Unguided: feature 0 has two identical candidates; the ratio test drops it.
        let m = match_features(&desc_a, &rays_a, &desc_b, &rays_b, None, &opts);
        assert!(!m.iter().any(|&(i, _, _)| i == 0), "{m:?}");
        assert_eq!(m.len(), n - 1);
    }

    /// The gate on real geometry: a point's ray in B passes, the same ray turned 5° out of the epipolar
    /// plane fails, and a ray that would put the point behind camera A fails.
    #[test]
    fn gate_tests_plane_and_side() {
        let t_wa = Se3::IDENTITY;
        let t_wb = Se3::new(DQuat::IDENTITY, DVec3::new(1.0, 0.0, 0.0));
        let opts = MatchOptions::default();
        let g = EpipolarGate::new(&t_wa, &t_wb, &opts);
        let p = DVec3::new(0.5, 0.2, 5.0);
        let fa = p.normalize();
        let fb = (p - DVec3::X).normalize();
        assert!(g.accepts(g.rotate(fa), fb));
        let n = DVec3::X.cross(fa).normalize();
        let off = (fb + n * 5f64.to_radians().tan()).normalize();
        assert!(!g.accepts(g.rotate(fa), off));
        // The point mirrored behind A along the same plane: the ray from B to (-p).
        let behind = (-p - DVec3::X).normalize();
        assert!(!g.accepts(g.rotate(fa), behind));
    }
}
