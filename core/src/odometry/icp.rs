//! Point-to-point ICP of a sweep against the local map (KISS-ICP's registration): nearest map point
//! within a correspondence distance, a Gauss-Newton step on SE(3) weighted by a Geman-McClure kernel,
//! until the step is below the convergence threshold.
//!
//! Deterministic: the correspondences are found in parallel but summed in fixed chunks in input order, so
//! the result does not depend on the number of threads (or on running single-threaded in the browser).

use glam::DVec3;
use nalgebra::{Matrix6, Vector6};
use rayon::prelude::*;

use super::voxel_map::VoxelHashMap;
use crate::geometry::Se3;

/// Settings of one registration.
#[derive(Clone, Copy, Debug)]
pub struct IcpSettings {
    /// Correspondences farther than this (m) are not used (KISS-ICP: 3σ of the adaptive threshold).
    pub max_correspondence: f64,
    /// Scale κ of the Geman-McClure kernel w(e) = κ² / (κ + e²)² (m², e² the squared residual; the
    /// odometry passes σ, as KISS-ICP 1.x does).
    pub kernel: f64,
    pub max_iterations: usize,
    /// Stop when the Gauss-Newton step's norm (m and rad together) is below this.
    pub convergence: f64,
}

/// What a registration did.
#[derive(Clone, Copy, Debug, Default)]
pub struct IcpReport {
    pub iterations: usize,
    /// Correspondences in the last iteration.
    pub correspondences: usize,
    /// The last step was below the convergence threshold.
    pub converged: bool,
}

const CHUNK: usize = 1024;

/// Normal equations of one chunk: JᵀWJ (6×6) and JᵀWr, over correspondences within the distance.
fn chunk_system(
    points: &[DVec3],
    pose: &Se3,
    map: &VoxelHashMap,
    s: &IcpSettings,
) -> (Matrix6<f64>, Vector6<f64>, usize) {
    let mut h = Matrix6::<f64>::zeros();
    let mut g = Vector6::<f64>::zeros();
    let mut n = 0;
    let max2 = s.max_correspondence * s.max_correspondence;
    for &p in points {
        let w_p = pose.transform_point(p);
        let Some((q, d2)) = map.nearest(w_p) else {
            continue;
        };
        if d2 >= max2 {
            continue;
        }
        let r = w_p - q;
        let k = s.kernel;
        let w = k * k / ((k + d2) * (k + d2));
        // Residual r(δ) = exp(δ)·(T p) − q; with δ = (ρ, φ) on the left, J = [I, −[x]×] where x = T p,
        // so JᵀJ = [[I, −[x]×], [[x]×, |x|²I − x xᵀ]] and Jᵀr = [r, x × r].
        let x = w_p;
        let xr = x.cross(r);
        for a in 0..3 {
            g[a] += w * r[a];
            g[a + 3] += w * xr[a];
            h[(a, a)] += w;
        }
        let skew = [[0.0, -x.z, x.y], [x.z, 0.0, -x.x], [-x.y, x.x, 0.0]];
        let xx = x.length_squared();
        for a in 0..3 {
            for b in 0..3 {
                h[(a, b + 3)] -= w * skew[a][b];
                h[(a + 3, b)] += w * skew[a][b];
                let d = if a == b { xx } else { 0.0 };
                h[(a + 3, b + 3)] += w * (d - x[a] * x[b]);
            }
        }
        n += 1;
    }
    (h, g, n)
}

/// Registers `points` (sensor frame) to `map` starting from `initial` (T_world_sensor); returns the
/// refined pose. An empty map, or too few correspondences for a well-posed step, leaves `initial`.
pub fn register(
    points: &[DVec3],
    map: &VoxelHashMap,
    initial: Se3,
    s: &IcpSettings,
) -> (Se3, IcpReport) {
    let mut pose = initial;
    let mut report = IcpReport::default();
    if map.is_empty() || points.is_empty() {
        return (pose, report);
    }
    for it in 0..s.max_iterations {
        let parts: Vec<_> = points
            .par_chunks(CHUNK)
            .map(|c| chunk_system(c, &pose, map, s))
            .collect();
        let (mut h, mut g, mut n) = (Matrix6::zeros(), Vector6::zeros(), 0);
        for (ph, pg, pn) in parts {
            h += ph;
            g += pg;
            n += pn;
        }
        report.iterations = it + 1;
        report.correspondences = n;
        if n < 6 {
            break;
        }
        let Some(chol) = h.cholesky() else {
            break;
        };
        let dx = -chol.solve(&g);
        if !dx.iter().all(|v| v.is_finite()) {
            break;
        }
        let step = Se3::exp(
            DVec3::new(dx[0], dx[1], dx[2]),
            DVec3::new(dx[3], dx[4], dx[5]),
        );
        pose = step * pose;
        if dx.norm() < s.convergence {
            report.converged = true;
            break;
        }
    }
    (pose, report)
}

/// How well the matched surfaces pin the translation: the eigenvalues of Σ n nᵀ over the correspondences
/// within `max_correspondence`, n the normal of the matched map voxel's points (their smallest principal
/// direction; voxels of fewer than 4 points are skipped), as `(smallest / largest, direction of the
/// smallest)`. Near 0 the sweep slides freely along that direction (a corridor, a tunnel, an open field
/// seen from one plane): point-to-point ICP then returns the motion model's guess there, not a measurement.
pub fn translation_constraint(
    points: &[DVec3],
    pose: &Se3,
    map: &VoxelHashMap,
    max_correspondence: f64,
) -> Option<(f64, DVec3)> {
    use nalgebra::{Matrix3, SymmetricEigen, Vector3};
    let max2 = max_correspondence * max_correspondence;
    let mut a = Matrix3::<f64>::zeros();
    let mut n_used = 0;
    // A thousand points spread over the sweep say as much as all of them, at a fraction of the cost.
    let stride = points.len().div_ceil(1000).max(1);
    for &p in points.iter().step_by(stride) {
        let w_p = pose.transform_point(p);
        let Some((q, d2)) = map.nearest(w_p) else {
            continue;
        };
        let vox = map.voxel_points(q);
        if d2 >= max2 || vox.len() < 4 {
            continue;
        }
        let mean = vox.iter().copied().sum::<DVec3>() / vox.len() as f64;
        let mut c = Matrix3::<f64>::zeros();
        for v in vox {
            let d = Vector3::new(v.x - mean.x, v.y - mean.y, v.z - mean.z);
            c += d * d.transpose();
        }
        let e = SymmetricEigen::new(c);
        let i = e.eigenvalues.imin();
        let n = e.eigenvectors.column(i).into_owned();
        a += n * n.transpose();
        n_used += 1;
    }
    if n_used < 6 {
        return None;
    }
    let e = SymmetricEigen::new(a);
    let (lo, hi) = (e.eigenvalues.min(), e.eigenvalues.max());
    if hi <= 0.0 {
        return None;
    }
    let v = e.eigenvectors.column(e.eigenvalues.imin()).into_owned();
    Some((lo.max(0.0) / hi, DVec3::new(v.x, v.y, v.z)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;

    /// Points on three perpendicular planes (a corner), the shape that pins all six degrees of freedom.
    /// Scattered (not on a grid: a grid's points alias into false minima of point-to-point ICP).
    fn corner() -> Vec<DVec3> {
        let mut state = 12345u64;
        let mut u = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64 * 10.0 - 5.0
        };
        let mut pts = Vec::new();
        for _ in 0..1600 {
            pts.push(DVec3::new(u(), u(), -2.0));
            pts.push(DVec3::new(u(), 6.0, u()));
            pts.push(DVec3::new(8.0, u(), u()));
        }
        pts
    }

    #[test]
    fn icp_recovers_a_known_motion_and_a_far_start_does_not() {
        let world = corner();
        let mut map = VoxelHashMap::new(0.5, 20);
        map.add(&world);
        let truth = Se3::new(
            DQuat::from_euler(glam::EulerRot::ZYX, 0.05, -0.02, 0.03),
            DVec3::new(0.4, -0.3, 0.2),
        );
        // The sensor sees the world from `truth`: its points are truth⁻¹ · world.
        let inv = truth.inverse();
        let scan: Vec<DVec3> = world.iter().map(|&p| inv.transform_point(p)).collect();
        let s = IcpSettings {
            max_correspondence: 2.0,
            kernel: 2.0 / 3.0,
            max_iterations: 500,
            convergence: 1e-4,
        };
        let (est, rep) = register(&scan, &map, Se3::IDENTITY, &s);
        assert!(
            est.distance_to(&truth) < 2e-3 && est.angle_to(&truth) < 5e-4,
            "{est:?} vs {truth:?} after {rep:?}"
        );
        assert!(rep.correspondences > scan.len() / 2);
        // With a correspondence distance far below the offset, nothing matches and the start stays.
        let tight = IcpSettings {
            max_correspondence: 1e-4,
            ..s
        };
        let (stay, _) = register(&scan, &map, Se3::IDENTITY, &tight);
        assert_eq!(stay, Se3::IDENTITY);
        // A corner pins every direction; a corridor (floor and two walls, no end) leaves its axis free.
        let (ratio, _) = translation_constraint(&world, &Se3::IDENTITY, &map, 1.0).unwrap();
        assert!(ratio > 0.2, "corner {ratio}");
        let corridor: Vec<DVec3> = world.iter().filter(|p| p.x != 8.0).copied().collect();
        let mut cmap = VoxelHashMap::new(0.5, 20);
        cmap.add(&corridor);
        let (ratio, axis) = translation_constraint(&corridor, &Se3::IDENTITY, &cmap, 1.0).unwrap();
        assert!(
            ratio < 0.01 && axis.x.abs() > 0.99,
            "corridor {ratio} along {axis}"
        );
    }
}
