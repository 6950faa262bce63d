//! Evaluation against ground truth, following the Oxford Spires protocol (see
//! `shared/reference/silvr_method.md` §5.1 and `formats_and_data.md` §4.1):
//!
//! - [`metrics`]: accuracy, completeness, precision / recall / F-score at 3, 5, 10, 20 cm after cropping
//!   to the GT box, 1 cm voxelisation and removal of GT-unknown space;
//! - [`occupancy`]: the observed-space grid (OctoMap leaf level at 0.1 m) behind "unknown space";
//! - [`image`]: PSNR and SSIM for novel views;
//! - [`report`]: the JSON report and error-coloured clouds;
//! - [`seen`]: the part of the GT a set of cameras sees (a submap scored on what it could reconstruct).
//!
//! On disk a ground-truth folder holds `gt/cloud.ply` and optionally `gt/observed.bin`
//! ([`OccupancyGrid::save`]); [`evaluate_files`] reads both.

pub mod image;
mod kdtree;
pub mod metrics;
pub mod occupancy;
pub mod options;
pub mod plot;
pub mod poses;
pub mod report;
#[cfg(not(target_arch = "wasm32"))]
pub mod scan;
pub mod seen;

pub use image::{psnr, psnr_rgb8, ssim, ssim_rgb8, ImageMetricError};
pub use metrics::{
    evaluate_geometry, nearest_distances, GeometryEvaluation, GeometryOptions, NearestNeighbours,
    ObservedSpace, SPIRES_THRESHOLDS_M,
};
pub use occupancy::{OccupancyError, OccupancyGrid, OccupancyParams, VoxelState};
pub use report::{error_colored_cloud, GeometryReport, PointCounts, ThresholdScores};
pub use seen::SeenVoxels;

use crate::pointcloud::{read_ply, PlyError, PointCloud};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Evaluation errors; the ones about files name them.
#[derive(Debug, Error)]
pub enum EvalError {
    #[error(transparent)]
    Ply(#[from] PlyError),
    #[error(transparent)]
    Occupancy(#[from] OccupancyError),
    #[error("{file}: ground-truth cloud not found (expected <gt_dir>/gt/cloud.ply)")]
    MissingGroundTruth { file: String },
    #[error("{file}: ground truth has no finite points")]
    EmptyGroundTruth { file: String },
    #[error("invalid evaluation options: {0}")]
    BadOptions(String),
    #[cfg(not(target_arch = "wasm32"))]
    #[error(transparent)]
    Scan(#[from] scan::ScanError),
    #[error("{file}: {source}")]
    Io {
        file: String,
        #[source]
        source: std::io::Error,
    },
}

/// Where the ground-truth files of a dataset live.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct GroundTruthPaths {
    pub cloud: PathBuf,
    /// `None` when no observed-space grid exists.
    pub observed: Option<PathBuf>,
}

impl GroundTruthPaths {
    /// Resolves `<gt_dir>/gt/cloud.ply` (and `observed.bin` beside it). A path that is itself the `gt`
    /// folder (holding `cloud.ply` directly) is accepted too.
    pub fn find(gt_dir: &Path) -> Result<Self, EvalError> {
        let nested = gt_dir.join("gt");
        let dir = if nested.join("cloud.ply").is_file() || !gt_dir.join("cloud.ply").is_file() {
            nested
        } else {
            gt_dir.to_path_buf()
        };
        let cloud = dir.join("cloud.ply");
        if !cloud.is_file() {
            return Err(EvalError::MissingGroundTruth {
                file: cloud.display().to_string(),
            });
        }
        let observed = dir.join("observed.bin");
        Ok(Self {
            cloud,
            observed: observed.is_file().then_some(observed),
        })
    }
}

/// Scores `reconstruction_ply` against the GT in `gt_dir` (see [`GroundTruthPaths::find`]). Without
/// `gt/observed.bin` the unknown-space filter is skipped and the report's `notes` say so.
pub fn evaluate_files(
    reconstruction_ply: &Path,
    gt_dir: &Path,
    options: &GeometryOptions,
) -> Result<GeometryReport, EvalError> {
    Ok(evaluate_files_full(reconstruction_ply, gt_dir, options)?.report)
}

/// [`evaluate_files`] keeping the evaluated clouds and per-point distances (for error clouds).
pub fn evaluate_files_full(
    reconstruction_ply: &Path,
    gt_dir: &Path,
    options: &GeometryOptions,
) -> Result<GeometryEvaluation, EvalError> {
    let truth = GroundTruth::load(gt_dir)?;
    truth.evaluate(&read_ply(reconstruction_ply)?, options)
}

/// A dataset's ground truth read once (the cloud and the observed-space grid), to score several clouds
/// against: on the default world they are 1.5 GB to read.
pub struct GroundTruth {
    pub paths: GroundTruthPaths,
    pub cloud: PointCloud,
    pub grid: Option<OccupancyGrid>,
}

impl GroundTruth {
    /// Reads the GT in `gt_dir` (see [`GroundTruthPaths::find`]).
    pub fn load(gt_dir: &Path) -> Result<Self, EvalError> {
        let paths = GroundTruthPaths::find(gt_dir)?;
        let cloud = read_ply(&paths.cloud)?;
        let grid = paths
            .observed
            .as_deref()
            .map(OccupancyGrid::load)
            .transpose()?;
        Ok(Self { paths, cloud, grid })
    }

    /// A scanner's point-cloud file as the ground truth (E57, LAS/LAZ, PLY, PCD: [`scan::read_scan`]),
    /// moved into the map's frame by `transform` (`T_map_scan`) and, for a file beyond
    /// [`scan::MAX_EXACT_POINTS`], voxelised at the evaluation's voxel size while read. It has no
    /// observed-space grid, so the unknown-space filter is not applied (the report's notes say so), and
    /// the notes say how the scan was read.
    #[cfg(not(target_arch = "wasm32"))]
    pub fn from_scan(
        path: &Path,
        transform: Option<glam::DMat4>,
        options: &GeometryOptions,
    ) -> Result<(Self, Vec<String>), EvalError> {
        let voxel = options.voxel_size_m.filter(|_| options.downsample_gt);
        let s = scan::read_scan(path, transform, voxel)?;
        let truth = Self {
            paths: GroundTruthPaths {
                cloud: path.to_path_buf(),
                observed: None,
            },
            cloud: s.cloud,
            grid: None,
        };
        Ok((truth, s.notes))
    }

    /// Scores `rec` against it. Without an observed-space grid the unknown-space filter is skipped and the
    /// report's `notes` say so.
    pub fn evaluate(
        &self,
        rec: &PointCloud,
        options: &GeometryOptions,
    ) -> Result<GeometryEvaluation, EvalError> {
        self.evaluate_against(rec, &self.cloud, options)
    }

    /// Distance from each point (already in the GT's frame, e.g. an evaluation's `reconstruction`) to the
    /// GT surface ([`metrics::NearestNeighbours::surface_distance`]): the error an uncertainty's σ speaks
    /// of, without the GT sampling's floor.
    pub fn surface_distances(&self, points: &[glam::DVec3]) -> Vec<f64> {
        metrics::NearestNeighbours::new(&self.cloud.positions).surface_distances(points)
    }

    /// [`Self::evaluate`] against only the GT points `gt_indices` (what one submap's cameras saw, say),
    /// with the same observed-space grid.
    pub fn evaluate_within(
        &self,
        rec: &PointCloud,
        gt_indices: &[usize],
        options: &GeometryOptions,
    ) -> Result<GeometryEvaluation, EvalError> {
        self.evaluate_against(rec, &self.cloud.select(gt_indices), options)
    }

    fn evaluate_against(
        &self,
        rec: &PointCloud,
        gt: &PointCloud,
        options: &GeometryOptions,
    ) -> Result<GeometryEvaluation, EvalError> {
        let paths = &self.paths;
        let observed = ObservedSpace {
            gt: self.grid.as_ref(),
            sensor: None,
        };
        let mut eval = evaluate_geometry(rec, gt, observed, options).map_err(|e| match e {
            EvalError::EmptyGroundTruth { .. } => EvalError::EmptyGroundTruth {
                file: paths.cloud.display().to_string(),
            },
            other => other,
        })?;
        if options.filter_unknown && self.grid.is_none() {
            let missing = paths.cloud.with_file_name("observed.bin");
            eval.report
                .notes
                .retain(|n| !n.starts_with("no GT observed-space grid"));
            eval.report.notes.insert(
                0,
                format!(
                    "{} not found: unknown-space filter skipped",
                    missing.display()
                ),
            );
        }
        Ok(eval)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pointcloud::write_ply;
    use glam::DVec3;

    #[test]
    fn evaluate_files_with_and_without_observed_grid() {
        let root = std::env::temp_dir().join(format!("silvr-eval-files-{}", std::process::id()));
        let gt_dir = root.join("gt");
        std::fs::create_dir_all(&gt_dir).unwrap();
        // GT: a 1 m line of points along x at 1 cm; the scanner at the origin saw along +x only.
        let gt = PointCloud::from_positions(
            (0..100)
                .map(|i| DVec3::new(0.005 + 0.01 * i as f64, 0.05, 0.05))
                .collect(),
        );
        write_ply(&gt_dir.join("cloud.ply"), &gt).unwrap();
        let mut rec = gt.clone();
        rec.push(DVec3::new(0.5, 0.35, 0.05)); // inside the padded box, never observed
        let rec_path = root.join("rec.ply");
        write_ply(&rec_path, &rec).unwrap();
        let opts = GeometryOptions {
            crop_padding_m: 0.5,
            ..GeometryOptions::default()
        };

        let r = evaluate_files(&rec_path, &root, &opts).unwrap();
        assert!(!r.unknown_filter_applied);
        assert!(
            r.notes[0].contains("observed.bin not found"),
            "{:?}",
            r.notes
        );
        assert_eq!(r.counts.reconstruction_evaluated, 101);
        assert!(r.per_threshold["precision_5cm"] < 1.0);

        let mut grid = OccupancyGrid::new(0.1).unwrap();
        grid.insert_scan(DVec3::new(-0.5, 0.05, 0.05), &gt.positions);
        grid.save(&gt_dir.join("observed.bin")).unwrap();
        let r = evaluate_files(&rec_path, &root, &opts).unwrap();
        assert!(r.unknown_filter_applied);
        assert_eq!(r.counts.reconstruction_evaluated, 100);
        assert_eq!(r.per_threshold["fscore_3cm"], 1.0);
        // The gt folder itself is accepted as gt_dir too.
        assert_eq!(evaluate_files(&rec_path, &gt_dir, &opts).unwrap(), r);
        let json = serde_json::to_value(&r).unwrap();
        for k in [
            "accuracy_m",
            "completeness_m",
            "precision_5cm",
            "recall_10cm",
            "fscore_20cm",
            "fscore_3cm",
        ] {
            assert!(
                json.get(k).is_some_and(|v| v.is_number()),
                "{k} missing in {json}"
            );
        }
        assert!(json["counts"]["gt_evaluated"].is_number());

        // Errors name the file.
        let err = evaluate_files(&root.join("nope.ply"), &root, &opts).unwrap_err();
        assert!(err.to_string().contains("nope.ply"), "{err}");
        std::fs::write(gt_dir.join("observed.bin"), b"SILVROCC").unwrap();
        let err = evaluate_files(&rec_path, &root, &opts).unwrap_err();
        assert!(err.to_string().contains("observed.bin"), "{err}");
        let err = evaluate_files(&rec_path, &root.join("missing"), &opts).unwrap_err();
        assert!(
            matches!(err, EvalError::MissingGroundTruth { .. })
                && err.to_string().contains("missing")
        );
        std::fs::remove_dir_all(root).ok();
    }
}
