//! The lidar-only map: every deskewed sweep placed in the world with its keyframe pose. This is the
//! baseline every radiance-field reconstruction is compared with.

use std::path::Path;

use crate::dataset::{read_tum, DatasetError};
use crate::pointcloud::{read_ply, PointCloud};

/// Merges `lidar/deskewed/*.ply` of a dataset using `poses/lidar_tum.txt` (T_world_lidar at each keyframe's
/// image time, in keyframe order). Non-finite points (dropped by deskewing) are skipped.
pub fn lidar_map(dataset: &Path) -> Result<PointCloud, DatasetError> {
    let poses_path = dataset.join("poses/lidar_tum.txt");
    let traj = read_tum(&poses_path)?;
    let mut out = PointCloud::new();
    for (k, pose) in traj.poses().iter().enumerate() {
        let path = dataset.join(format!("lidar/deskewed/{k:05}.ply"));
        let cloud = read_ply(&path).map_err(|e| DatasetError::Format {
            path: path.clone(),
            detail: e.to_string(),
        })?;
        for p in cloud.positions {
            if p.is_finite() {
                out.push(pose.transform_point(p));
            }
        }
    }
    Ok(out)
}
