//! What a set of cameras sees of the ground truth: the GT points lying on surface that their exact depth
//! images reach. A submap's field can only reconstruct what its own cameras saw, so a submap is scored
//! against that part of the GT (its completeness is not charged for the rest of the map); this is how
//! co-visibility and distance cuts are compared submap by submap.

use crate::camera::CameraModel;
use crate::geometry::Se3;
use glam::{DVec2, DVec3};
use std::collections::HashSet;

/// Voxels (of side `voxel` m) that some camera's exact depth reached.
#[derive(Clone, Debug)]
pub struct SeenVoxels {
    voxel: f64,
    keys: HashSet<[i64; 3]>,
}

impl SeenVoxels {
    /// An empty set. `voxel` must be finite and positive (the caller's constant).
    pub fn new(voxel: f64) -> Self {
        assert!(voxel.is_finite() && voxel > 0.0, "voxel size {voxel}");
        Self {
            voxel,
            keys: HashSet::new(),
        }
    }

    fn key(&self, p: DVec3) -> [i64; 3] {
        let q = (p / self.voxel).floor();
        [q.x as i64, q.y as i64, q.z as i64]
    }

    /// Number of voxels seen.
    pub fn len(&self) -> usize {
        self.keys.len()
    }

    pub fn is_empty(&self) -> bool {
        self.keys.is_empty()
    }

    /// Adds the surface one view sees: `range_m` is the exact Euclidean range in metres per pixel (row-major,
    /// `model.width × model.height`; non-finite or ≤ 0 where nothing was hit, e.g. sky) and `t_gt_cam` the
    /// view's OpenCV-axes pose in the GT frame (a pose estimated in another frame goes through that frame's
    /// Sim(3) first: its rotation and centre, not its scale, since the range is metric). Every `stride`-th
    /// pixel in each direction is used. Returns how many pixels were added.
    pub fn add_view(
        &mut self,
        model: &CameraModel,
        t_gt_cam: &Se3,
        range_m: &[f32],
        stride: u32,
    ) -> usize {
        let (w, h) = (model.width, model.height);
        if range_m.len() != (w as usize) * (h as usize) {
            return 0;
        }
        let stride = stride.max(1) as usize;
        let max_angle = model.valid_angle();
        let mut added = 0;
        for y in (0..h as usize).step_by(stride) {
            for x in (0..w as usize).step_by(stride) {
                let r = range_m[y * w as usize + x] as f64;
                if !(r.is_finite() && r > 0.0) {
                    continue;
                }
                let Some(d) = model.unproject_within(DVec2::new(x as f64, y as f64), max_angle)
                else {
                    continue;
                };
                let p = t_gt_cam.transform_point(d.normalize() * r);
                if p.is_finite() {
                    self.keys.insert(self.key(p));
                    added += 1;
                }
            }
        }
        added
    }

    /// Indices of the points (GT frame) in or next to a seen voxel: a point counts as seen when a voxel
    /// within a quarter voxel of it (along each axis) was hit. Without that slack a surface lying on a voxel
    /// face (a synthetic facade at y = −10 m, say) would be split by rounding noise between the voxels on
    /// either side, its GT points and its depth samples falling on different sides.
    pub fn select(&self, points: &[DVec3]) -> Vec<usize> {
        let d = 0.25 * self.voxel;
        let seen = |p: DVec3| {
            p.is_finite()
                && (0..8).any(|c: u32| {
                    let o = DVec3::new(
                        if c & 1 == 0 { -d } else { d },
                        if c & 2 == 0 { -d } else { d },
                        if c & 4 == 0 { -d } else { d },
                    );
                    self.keys.contains(&self.key(p + o))
                })
        };
        (0..points.len()).filter(|&i| seen(points[i])).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;

    /// A camera 5 m above a floor, looking straight down: the GT points under its footprint are seen, the
    /// ones beyond it and the ones behind a wall its depth stops at are not.
    #[test]
    fn a_view_sees_what_its_depth_reaches() {
        let model = CameraModel::pinhole(40, 40, 20.0, 20.0, 19.5, 19.5);
        // OpenCV axes: z forward. Rotate so the camera's +z points down the world's −z.
        let pose = Se3::new(
            DQuat::from_rotation_x(std::f64::consts::PI),
            DVec3::new(0.0, 0.0, 5.25),
        );
        // The floor is at z = 0.25, on a voxel face: rounding puts its depth samples and GT points on either
        // side. The footprint at 5 m is ±4.9 m. A box 1 m tall covers x in [1, 2], y in [1, 2]: depth stops
        // on its top.
        let mut range = vec![0.0f32; 40 * 40];
        for y in 0..40 {
            for x in 0..40 {
                let d = model
                    .unproject(DVec2::new(x as f64, y as f64))
                    .unwrap()
                    .normalize();
                let dw = pose.transform_vector(d);
                let t_floor = -5.0 / dw.z;
                let hit = pose.trans + dw * t_floor;
                let t = if (1.0..2.0).contains(&hit.x) && (1.0..2.0).contains(&hit.y) {
                    -4.0 / dw.z
                } else {
                    t_floor
                };
                range[y * 40 + x] = if x == 0 && y == 0 { f32::NAN } else { t as f32 };
            }
        }
        let mut seen = SeenVoxels::new(0.25);
        let added = seen.add_view(&model, &pose, &range, 1);
        assert_eq!(added, 40 * 40 - 1, "the NaN pixel is skipped");
        let gt = [
            DVec3::new(0.1, 0.1, 0.25 - 1e-9),  // floor under the camera
            DVec3::new(-4.0, 3.0, 0.25 + 1e-9), // floor near the footprint's corner
            DVec3::new(9.0, 0.0, 0.25),         // floor outside the view
            DVec3::new(1.6, 1.6, 1.25 - 1e-9),  // the box's top
            DVec3::new(1.6, 1.6, 0.25),         // floor under the box: hidden
            DVec3::new(0.1, 0.1, -3.0),         // under the floor
            DVec3::new(f64::NAN, 0.0, 0.0),     // not a point
        ];
        assert_eq!(seen.select(&gt), vec![0, 1, 3]);
        // The same view from a pose moved into another frame sees the moved surface.
        let shift = Se3::new(DQuat::IDENTITY, DVec3::new(100.0, 0.0, 0.0));
        let mut moved = SeenVoxels::new(0.25);
        moved.add_view(&model, &(shift * pose), &range, 1);
        let gt_moved: Vec<DVec3> = gt.iter().map(|p| *p + DVec3::X * 100.0).collect();
        assert_eq!(moved.select(&gt_moved), vec![0, 1, 3]);
        assert_eq!(moved.len(), seen.len());
        let mut sparse = SeenVoxels::new(0.25);
        assert_eq!(sparse.add_view(&model, &pose, &range, 2), 20 * 20 - 1);
        assert!(sparse.len() < seen.len(), "stride 2 reaches fewer voxels");
        // A range image of the wrong size adds nothing.
        assert_eq!(moved.add_view(&model, &pose, &range[1..], 1), 0);
    }
}
