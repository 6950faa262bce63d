//! What an evaluation is asked to do: the Spires benchmark's settings. Shared by the metrics that apply
//! them and the report that records them.

use glam::DMat4;
use serde::{Deserialize, Serialize};

/// Spires benchmark thresholds (m).
pub const SPIRES_THRESHOLDS_M: [f64; 4] = [0.03, 0.05, 0.10, 0.20];

/// Evaluation settings. Defaults follow the Spires benchmark.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct GeometryOptions {
    /// `T_gt_rec`: maps the reconstruction into the GT frame before anything else (Spires'
    /// `T_gt_lidar.txt`). Must be affine (last row 0 0 0 1).
    pub reconstruction_to_gt: Option<DMat4>,
    /// Crop the reconstruction to the GT's axis-aligned bounding box.
    pub crop_to_gt_bounds: bool,
    /// Grows the crop box on every side (m).
    pub crop_padding_m: f64,
    /// Voxel size for downsampling both clouds (centroid per voxel); `None` disables it.
    pub voxel_size_m: Option<f64>,
    /// Also downsample the GT (the Spires GT ships at 1 cm already; downsampling it again is harmless).
    pub downsample_gt: bool,
    /// Drop reconstruction points in GT-unknown space when an observed-space grid is given.
    pub filter_unknown: bool,
    /// Distance thresholds for precision / recall / F-score (m).
    pub thresholds_m: Vec<f64>,
}

impl Default for GeometryOptions {
    fn default() -> Self {
        Self {
            reconstruction_to_gt: None,
            crop_to_gt_bounds: true,
            crop_padding_m: 0.0,
            voxel_size_m: Some(0.01),
            downsample_gt: true,
            filter_unknown: true,
            thresholds_m: SPIRES_THRESHOLDS_M.to_vec(),
        }
    }
}

impl GeometryOptions {
    /// No transform, crop, downsampling or unknown-space filter: metrics on the clouds as given
    /// (what the SciPy cross-check compares against).
    pub fn raw() -> Self {
        Self {
            crop_to_gt_bounds: false,
            voxel_size_m: None,
            downsample_gt: false,
            filter_unknown: false,
            ..Self::default()
        }
    }
}
