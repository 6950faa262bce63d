//! Candidate image pairs from the prior: SiLVR matches only images the SLAM trajectory says can see the
//! same place, instead of COLMAP's exhaustive or vocabulary-tree search (the paper's ≤ 70 % SfM time
//! saving). Two images are a candidate when their centres are within `max_distance_m`, their optical axes
//! within `max_angle_deg`, and their view frusta overlap: of a grid of pixels of one image pushed out to
//! a few depths, at least `min_overlap` land inside the other (both ways, the smaller counts). The rig's
//! cameras pair with each other too (front with left at one instant sees the same corner).

use glam::{DVec2, DVec3};
use serde::Serialize;

use crate::camera::CameraModel;
use crate::geometry::Se3;

/// The gates.
#[derive(Clone, Debug)]
pub struct PairOptions {
    pub max_distance_m: f64,
    pub max_angle_deg: f64,
    pub min_overlap: f64,
    /// Depths (m) the frustum samples are pushed to: near structure and the far street.
    pub depths: Vec<f64>,
    /// Grid of pixels per image side.
    pub grid: u32,
}

impl Default for PairOptions {
    fn default() -> Self {
        PairOptions {
            max_distance_m: 20.0,
            max_angle_deg: 100.0,
            min_overlap: 0.1,
            depths: vec![2.0, 5.0, 10.0, 20.0],
            grid: 8,
        }
    }
}

/// One candidate pair (`i < j`) and why it passed.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Pair {
    pub i: usize,
    pub j: usize,
    pub distance_m: f64,
    pub angle_deg: f64,
    /// The smaller of the two directions' overlap fractions.
    pub overlap: f64,
}

/// Candidate pairs among `cams` (model and OpenCV-axes `T_world_cam` of each image), sorted by (i, j).
pub fn candidate_pairs(cams: &[(CameraModel, Se3)], opts: &PairOptions) -> Vec<Pair> {
    use rayon::prelude::*;
    // Each camera's valid angle, computed once: `project`/`unproject` would redo its scan per call, which
    // was most of the time (8 s for the ci world's 60 images).
    let angles: Vec<f64> = cams.par_iter().map(|(m, _)| m.valid_angle()).collect();
    // Each image's frustum samples in the world frame.
    let samples: Vec<Vec<DVec3>> = cams
        .par_iter()
        .zip(&angles)
        .map(|((m, pose), &max_angle)| frustum_samples(m, pose, max_angle, opts))
        .collect();
    let cos_max = opts.max_angle_deg.to_radians().cos();
    (0..cams.len())
        .into_par_iter()
        .flat_map_iter(|i| {
            let (samples, angles) = (&samples, &angles);
            (i + 1..cams.len()).filter_map(move |j| {
                let (a, b) = (&cams[i].1, &cams[j].1);
                let distance_m = a.trans.distance(b.trans);
                if distance_m > opts.max_distance_m {
                    return None;
                }
                let cos = (a.rot * DVec3::Z).dot(b.rot * DVec3::Z).clamp(-1.0, 1.0);
                if cos < cos_max {
                    return None;
                }
                let o = seen_fraction(&samples[i], &cams[j], angles[j]).min(seen_fraction(
                    &samples[j],
                    &cams[i],
                    angles[i],
                ));
                (o >= opts.min_overlap).then(|| Pair {
                    i,
                    j,
                    distance_m,
                    angle_deg: cos.acos().to_degrees(),
                    overlap: o,
                })
            })
        })
        .collect()
}

/// A grid of the image's pixels unprojected to each sample depth (along the ray), in the world frame;
/// `max_angle` is the camera's [`CameraModel::valid_angle`].
fn frustum_samples(m: &CameraModel, pose: &Se3, max_angle: f64, opts: &PairOptions) -> Vec<DVec3> {
    let g = opts.grid.max(2);
    let mut out = Vec::new();
    for gy in 0..g {
        for gx in 0..g {
            let px = DVec2::new(
                (gx as f64 + 0.5) / g as f64 * m.width as f64 - 0.5,
                (gy as f64 + 0.5) / g as f64 * m.height as f64 - 0.5,
            );
            let Some(d) = m.unproject_within(px, max_angle) else {
                continue;
            };
            let d = d.normalize();
            for &z in &opts.depths {
                out.push(pose.transform_point(d * z));
            }
        }
    }
    out
}

/// Fraction of `points` (world) that project inside image `cam` (`max_angle`: its valid angle).
fn seen_fraction(points: &[DVec3], cam: &(CameraModel, Se3), max_angle: f64) -> f64 {
    if points.is_empty() {
        return 0.0;
    }
    let (m, pose) = cam;
    let inv = pose.inverse();
    let (w, h) = (m.width as f64, m.height as f64);
    let seen = points
        .iter()
        .filter(|&&p| {
            m.project_within(inv.transform_point(p), max_angle)
                .is_some_and(|uv| uv.x >= -0.5 && uv.y >= -0.5 && uv.x < w - 0.5 && uv.y < h - 0.5)
        })
        .count();
    seen as f64 / points.len() as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;

    /// A pinhole camera at `x` along a street, looking along `yaw` (0 = +x) with OpenCV axes (z forward).
    fn cam(x: f64, yaw_deg: f64) -> (CameraModel, Se3) {
        let m = CameraModel::pinhole(200, 150, 120.0, 120.0, 99.5, 74.5);
        // OpenCV camera looking along world +x: z_cam = +x, x_cam = -y, y_cam = -z.
        let base = DQuat::from_mat3(&glam::DMat3::from_cols(
            DVec3::new(0.0, -1.0, 0.0),
            DVec3::new(0.0, 0.0, -1.0),
            DVec3::new(1.0, 0.0, 0.0),
        ));
        let rot = DQuat::from_rotation_z(yaw_deg.to_radians()) * base;
        (m, Se3::new(rot, DVec3::new(x, 0.0, 0.0)))
    }

    #[test]
    fn neighbours_looking_the_same_way_pair_and_opposite_or_far_ones_do_not() {
        let cams = vec![
            cam(0.0, 0.0),
            cam(1.0, 0.0),
            cam(1.0, 180.0),
            cam(60.0, 0.0),
            cam(2.0, 45.0),
        ];
        let pairs = candidate_pairs(&cams, &PairOptions::default());
        let ids: Vec<(usize, usize)> = pairs.iter().map(|p| (p.i, p.j)).collect();
        assert!(ids.contains(&(0, 1)), "{pairs:?}");
        assert!(ids.contains(&(0, 4)) && ids.contains(&(1, 4)), "{pairs:?}");
        // Opposite directions, or 60 m away: not candidates.
        assert!(
            !ids.iter().any(|&(i, j)| i == 2 || j == 2 || j == 3),
            "{pairs:?}"
        );
        let p01 = &pairs[0];
        assert!((p01.distance_m - 1.0).abs() < 1e-12 && p01.angle_deg < 1e-6);
        assert!(p01.overlap > 0.5 && p01.overlap <= 1.0, "{p01:?}");
    }
}
