//! The local map of lidar odometry: points hashed by voxel, a bounded number per voxel, and the voxel
//! down-sampling that feeds it (KISS-ICP's data structure: nearest-neighbour search touches only the 27
//! voxels around a query, so its cost does not grow with the map).

use glam::{DVec3, IVec3};
use rustc_hash::{FxHashMap, FxHashSet};

fn voxel_of(p: DVec3, size: f64) -> IVec3 {
    let v = (p / size).floor();
    IVec3::new(v.x as i32, v.y as i32, v.z as i32)
}

/// One point per occupied voxel of side `size`: the first in input order (not the centroid, which would
/// invent points between surfaces), so the output keeps the input's order and is deterministic.
pub fn voxel_downsample(points: &[DVec3], size: f64) -> Vec<DVec3> {
    let mut seen = FxHashSet::default();
    seen.reserve(points.len() / 4);
    points
        .iter()
        .copied()
        .filter(|&p| seen.insert(voxel_of(p, size)))
        .collect()
}

/// Points in world coordinates, at most `max_points` per voxel of side `voxel_size`.
pub struct VoxelHashMap {
    voxel_size: f64,
    max_points: usize,
    /// Points closer than this to one already in its voxel add nothing (the voxel's points stay spread
    /// over it rather than piling up where the sensor stood still).
    min_spacing: f64,
    voxels: FxHashMap<IVec3, Vec<DVec3>>,
}

impl VoxelHashMap {
    pub fn new(voxel_size: f64, max_points: usize) -> Self {
        let max_points = max_points.max(1);
        Self {
            voxel_size,
            max_points,
            min_spacing: voxel_size / (max_points as f64).sqrt(),
            voxels: FxHashMap::default(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.voxels.is_empty()
    }

    /// Number of points held.
    pub fn len(&self) -> usize {
        self.voxels.values().map(Vec::len).sum()
    }

    /// Adds world points where their voxel has room and they are not on top of one already there.
    pub fn add(&mut self, points: &[DVec3]) {
        let spacing2 = self.min_spacing * self.min_spacing;
        for &p in points {
            let cell = self.voxels.entry(voxel_of(p, self.voxel_size)).or_default();
            if cell.len() < self.max_points
                && cell.iter().all(|q| q.distance_squared(p) >= spacing2)
            {
                cell.push(p);
            }
        }
    }

    /// Drops the voxels whose first point lies farther than `max_distance` from `origin` (the sensor):
    /// the map is local, its size bounded by the range, not by the length of the mission.
    pub fn remove_far(&mut self, origin: DVec3, max_distance: f64) {
        let d2 = max_distance * max_distance;
        self.voxels.retain(|_, pts| {
            pts.first()
                .is_some_and(|p| p.distance_squared(origin) <= d2)
        });
    }

    /// The points of the voxel holding `p`.
    pub fn voxel_points(&self, p: DVec3) -> &[DVec3] {
        self.voxels
            .get(&voxel_of(p, self.voxel_size))
            .map_or(&[], Vec::as_slice)
    }

    /// The map point nearest to `q` among the 27 voxels around it, with its squared distance; `None`
    /// when those voxels are empty.
    pub fn nearest(&self, q: DVec3) -> Option<(DVec3, f64)> {
        let c = voxel_of(q, self.voxel_size);
        let mut best: Option<(DVec3, f64)> = None;
        for dz in -1..=1 {
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let Some(pts) = self.voxels.get(&(c + IVec3::new(dx, dy, dz))) else {
                        continue;
                    };
                    for &p in pts {
                        let d2 = p.distance_squared(q);
                        if best.is_none_or(|(_, b)| d2 < b) {
                            best = Some((p, d2));
                        }
                    }
                }
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn downsample_keeps_the_first_point_of_each_voxel_in_order() {
        let pts = [
            DVec3::new(0.1, 0.1, 0.1),
            DVec3::new(0.2, 0.2, 0.2),
            DVec3::new(1.5, 0.0, 0.0),
            DVec3::new(-0.1, 0.0, 0.0),
            DVec3::new(1.9, 0.9, 0.9),
        ];
        let out = voxel_downsample(&pts, 1.0);
        assert_eq!(out, vec![pts[0], pts[2], pts[3]]);
    }

    #[test]
    fn map_bounds_each_voxel_finds_the_nearest_and_forgets_far_voxels() {
        let mut m = VoxelHashMap::new(1.0, 4);
        // 100 points in one voxel: at most 4 kept, each at least 0.5 m from the others.
        let pts: Vec<DVec3> = (0..100)
            .map(|i| DVec3::new(0.01 * i as f64 % 1.0, 0.0, 0.0))
            .collect();
        m.add(&pts);
        assert!(m.len() <= 4 && m.len() >= 2, "{}", m.len());
        m.add(&[DVec3::new(5.5, 0.5, 0.5)]);
        let (p, d2) = m.nearest(DVec3::new(5.2, 0.5, 0.5)).unwrap();
        assert_eq!(p, DVec3::new(5.5, 0.5, 0.5));
        assert!((d2 - 0.09).abs() < 1e-12);
        // Beyond the 27 voxels around the query nothing is searched.
        assert!(m.nearest(DVec3::new(20.0, 0.0, 0.0)).is_none());
        m.remove_far(DVec3::new(6.0, 0.0, 0.0), 2.0);
        assert_eq!(m.len(), 1);
    }
}
