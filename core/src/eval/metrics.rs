//! Cloud-to-cloud geometry metrics following the Oxford Spires reconstruction benchmark
//! (`get_recon_metrics_multi_thresholds`): nearest-neighbour distances both ways by KD-tree,
//! accuracy / completeness as mean distances, precision / recall / F-score at distance thresholds.
//!
//! Pipeline ([`evaluate_geometry`]): reconstruction → optional `T_gt_rec` → crop to the GT bounding box
//! (optionally padded) → voxel downsample (1 cm) → drop points in voxels the GT never observed; GT →
//! voxel downsample → (optionally) drop points the sensor never observed (the SiLVR paper's symmetric
//! filter) → distances → scores.

use super::kdtree::KdTree;
use super::occupancy::OccupancyGrid;
use super::report::{threshold_key, GeometryReport, PointCounts, ThresholdScores};
use super::EvalError;
use crate::pointcloud::PointCloud;
use glam::{DAffine3, DVec3};
use rayon::prelude::*;
use std::collections::BTreeMap;

pub use super::options::{GeometryOptions, SPIRES_THRESHOLDS_M};

/// Checks of the options that the evaluation needs (the options themselves live in `options`, which the
/// report records too).
impl GeometryOptions {
    fn validate(&self) -> Result<Option<DAffine3>, EvalError> {
        if let Some(v) = self.voxel_size_m {
            if !(v.is_finite() && v > 0.0) {
                return Err(EvalError::BadOptions(format!(
                    "voxel_size_m must be positive, got {v}"
                )));
            }
        }
        if !(self.crop_padding_m.is_finite() && self.crop_padding_m >= 0.0) {
            return Err(EvalError::BadOptions(format!(
                "crop_padding_m must be ≥ 0, got {}",
                self.crop_padding_m
            )));
        }
        if let Some(t) = self
            .thresholds_m
            .iter()
            .find(|t| !(t.is_finite() && **t > 0.0))
        {
            return Err(EvalError::BadOptions(format!(
                "thresholds must be positive, got {t}"
            )));
        }
        match self.reconstruction_to_gt {
            None => Ok(None),
            Some(m) => {
                if !m.is_finite() || m.row(3) != glam::DVec4::new(0.0, 0.0, 0.0, 1.0) {
                    return Err(EvalError::BadOptions(
                        "reconstruction_to_gt must be a finite affine 4×4 (last row 0 0 0 1)"
                            .into(),
                    ));
                }
                Ok(Some(DAffine3::from_mat4(m)))
            }
        }
    }
}

/// Nearest-neighbour distance queries against a fixed point set (a static KD-tree that stays fast
/// on duplicate and coplanar points, see `kdtree.rs`; distances are exact, as with SciPy's cKDTree).
pub struct NearestNeighbours {
    tree: KdTree,
}

impl NearestNeighbours {
    /// Indexes the finite points of `reference` (others can never be a nearest neighbour).
    pub fn new(reference: &[DVec3]) -> Self {
        let pts: Vec<[f64; 3]> = reference
            .iter()
            .filter(|p| p.is_finite())
            .map(|p| p.to_array())
            .collect();
        Self {
            tree: KdTree::new(pts),
        }
    }

    /// Whether no point is indexed.
    pub fn is_empty(&self) -> bool {
        self.tree.is_empty()
    }

    /// Euclidean distance from `q` to the nearest indexed point: +∞ when nothing is indexed, NaN for a
    /// non-finite query.
    pub fn distance(&self, q: DVec3) -> f64 {
        if !q.is_finite() {
            return f64::NAN;
        }
        self.tree.nearest_sq(q.to_array()).sqrt()
    }

    /// [`Self::distance`] for every query, in parallel (single-threaded on wasm32).
    pub fn distances(&self, queries: &[DVec3]) -> Vec<f64> {
        queries
            .par_iter()
            .with_min_len(4096)
            .map(|q| self.distance(*q))
            .collect()
    }
}

/// Neighbours of a query that fit the ground truth's local plane.
const SURFACE_NEIGHBOURS: usize = 8;

impl NearestNeighbours {
    /// Distance from `q` to the indexed *surface*: to the plane through its [`SURFACE_NEIGHBOURS`]
    /// nearest points (least squares) when they are planar and `q` projects inside their patch, else to
    /// the nearest point. A ground truth sampled every few centimetres puts a point lying exactly on the
    /// surface up to half a diagonal from its nearest sample (0.38 × spacing on average): the point
    /// distance has that floor, the plane distance does not. NaN for a non-finite query, +∞ with no points.
    pub fn surface_distance(&self, q: DVec3) -> f64 {
        if !q.is_finite() {
            return f64::NAN;
        }
        let nb = self.tree.k_nearest(q.to_array(), SURFACE_NEIGHBOURS);
        let Some(&(d0, _)) = nb.first() else {
            return f64::INFINITY;
        };
        let point = d0.sqrt();
        if nb.len() < 3 {
            return point;
        }
        let pts: Vec<DVec3> = nb.iter().map(|e| DVec3::from(e.1)).collect();
        let c = pts.iter().copied().sum::<DVec3>() / pts.len() as f64;
        let cov = pts.iter().fold(glam::DMat3::ZERO, |m, p| {
            let d = *p - c;
            m + glam::DMat3::from_cols(d * d.x, d * d.y, d * d.z)
        });
        let eig = nalgebra::SymmetricEigen::new(nalgebra::Matrix3::from_fn(|i, j| cov.col(j)[i]));
        let mut order = [0usize, 1, 2];
        order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
        let (l0, l1) = (eig.eigenvalues[order[0]], eig.eigenvalues[order[1]]);
        // Planar: the thinnest direction's spread well below the next one's.
        if !(l1 > 0.0 && l0 <= 0.05 * l1) {
            return point;
        }
        let n = eig.eigenvectors.column(order[0]);
        let normal = DVec3::new(n[0], n[1], n[2]).normalize();
        let off = q - c;
        let along = off.dot(normal);
        let radius = pts.iter().map(|p| (*p - c).length()).fold(0.0, f64::max);
        if (off - along * normal).length() > radius {
            return point;
        }
        along.abs().min(point)
    }

    /// [`Self::surface_distance`] for every query, in parallel.
    pub fn surface_distances(&self, queries: &[DVec3]) -> Vec<f64> {
        queries
            .par_iter()
            .with_min_len(1024)
            .map(|q| self.surface_distance(*q))
            .collect()
    }
}

/// Distance from every point of `queries` to its nearest neighbour in `reference`.
pub fn nearest_distances(queries: &[DVec3], reference: &[DVec3]) -> Vec<f64> {
    NearestNeighbours::new(reference).distances(queries)
}

/// Mean (sequential sum, so results do not depend on the thread count); NaN for no values.
pub fn mean(values: &[f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    values.iter().sum::<f64>() / values.len() as f64
}

/// Median as NumPy defines it (mean of the two middle values for even counts); NaN for no values.
pub fn median(values: &[f64]) -> f64 {
    let n = values.len();
    if n == 0 {
        return f64::NAN;
    }
    let mut v = values.to_vec();
    let (_, hi, _) = v.select_nth_unstable_by(n / 2, f64::total_cmp);
    let hi = *hi;
    if n % 2 == 1 {
        return hi;
    }
    let lo = v[..n / 2].iter().copied().fold(f64::NEG_INFINITY, f64::max);
    0.5 * (lo + hi)
}

/// Precision / recall / F-score at one threshold from the two distance sets. A point counts when its
/// distance is strictly below `tau`. Fractions of empty sets are 0; F = 2PR/(P+R), 0 when P+R = 0.
pub fn scores_at(rec_to_gt: &[f64], gt_to_rec: &[f64], tau: f64) -> ThresholdScores {
    let inliers = |d: &[f64]| d.iter().filter(|&&x| x < tau).count();
    let (ni, nj) = (inliers(rec_to_gt), inliers(gt_to_rec));
    let frac = |k: usize, n: usize| if n == 0 { 0.0 } else { k as f64 / n as f64 };
    let precision = frac(ni, rec_to_gt.len());
    let recall = frac(nj, gt_to_rec.len());
    let fscore = if precision + recall > 0.0 {
        2.0 * precision * recall / (precision + recall)
    } else {
        0.0
    };
    ThresholdScores {
        threshold_m: tau,
        precision,
        recall,
        fscore,
        reconstruction_inliers: ni,
        gt_inliers: nj,
    }
}

/// Report fields that depend only on the two distance sets (counts are left zero).
pub fn report_from_distances(
    rec_to_gt: &[f64],
    gt_to_rec: &[f64],
    thresholds_m: &[f64],
) -> GeometryReport {
    let thresholds: Vec<ThresholdScores> = thresholds_m
        .iter()
        .map(|&t| scores_at(rec_to_gt, gt_to_rec, t))
        .collect();
    let mut flat = BTreeMap::new();
    for s in &thresholds {
        let key = threshold_key(s.threshold_m);
        flat.insert(format!("precision_{key}"), s.precision);
        flat.insert(format!("recall_{key}"), s.recall);
        flat.insert(format!("fscore_{key}"), s.fscore);
    }
    GeometryReport {
        accuracy_m: mean(rec_to_gt),
        completeness_m: mean(gt_to_rec),
        accuracy_median_m: median(rec_to_gt),
        completeness_median_m: median(gt_to_rec),
        per_threshold: flat,
        thresholds,
        counts: PointCounts::default(),
        unknown_filter_applied: false,
        gt_unknown_filter_applied: false,
        notes: Vec::new(),
        options: GeometryOptions::raw(),
    }
}

/// Grids of observed space used to drop points in unknown space.
#[derive(Clone, Copy, Debug, Default)]
pub struct ObservedSpace<'a> {
    /// Built from the GT scans (Spires `gt/observed.bin`); filters the reconstruction.
    pub gt: Option<&'a OccupancyGrid>,
    /// Built from the platform's lidar; filters the GT (SiLVR paper §V: GT regions the device never
    /// scanned are excluded from completeness).
    pub sensor: Option<&'a OccupancyGrid>,
}

/// Everything an evaluation produced: the report, the clouds actually compared, and per-point distances
/// (`rec_to_gt[i]` belongs to `reconstruction.positions[i]`), e.g. for [`super::error_colored_cloud`].
#[derive(Clone, Debug)]
pub struct GeometryEvaluation {
    pub report: GeometryReport,
    pub reconstruction: PointCloud,
    pub ground_truth: PointCloud,
    pub rec_to_gt: Vec<f64>,
    pub gt_to_rec: Vec<f64>,
}

/// Runs the Spires pipeline (module docs) on in-memory clouds. Non-finite points are dropped first.
/// Errors on invalid options and on a GT without finite points; an empty reconstruction is scored
/// (accuracy NaN, completeness +∞, all fractions 0), which JSON writes as `null`.
pub fn evaluate_geometry(
    reconstruction: &PointCloud,
    ground_truth: &PointCloud,
    observed: ObservedSpace<'_>,
    options: &GeometryOptions,
) -> Result<GeometryEvaluation, EvalError> {
    let transform = options.validate()?;
    let mut counts = PointCounts {
        reconstruction_input: reconstruction.len(),
        reconstruction_nonfinite: reconstruction.count_nonfinite(),
        gt_input: ground_truth.len(),
        gt_nonfinite: ground_truth.count_nonfinite(),
        ..PointCounts::default()
    };
    let mut notes = Vec::new();

    let mut gt = ground_truth.finite_only();
    let Some((gt_min, gt_max)) = gt.bounds() else {
        return Err(EvalError::EmptyGroundTruth {
            file: "(ground truth)".into(),
        });
    };
    let mut rec = match transform {
        Some(t) => reconstruction.transformed(&t).finite_only(),
        None => reconstruction.finite_only(),
    };

    if options.crop_to_gt_bounds {
        let pad = DVec3::splat(options.crop_padding_m);
        rec = rec.crop_aabb(gt_min - pad, gt_max + pad);
    }
    counts.reconstruction_after_crop = rec.len();

    if let Some(v) = options.voxel_size_m {
        rec = rec.voxel_downsample(v);
        if options.downsample_gt {
            gt = gt.voxel_downsample(v);
        }
    }
    counts.reconstruction_after_downsample = rec.len();
    counts.gt_after_downsample = gt.len();

    let mut unknown_filter_applied = false;
    match (options.filter_unknown, observed.gt) {
        (true, Some(grid)) => {
            rec = grid.filter_unknown(&rec);
            unknown_filter_applied = true;
        }
        (true, None) => {
            notes.push("no GT observed-space grid: unknown-space filter skipped".to_string())
        }
        (false, _) => notes.push("unknown-space filter disabled by options".to_string()),
    }
    counts.reconstruction_after_unknown_filter = rec.len();
    let mut gt_unknown_filter_applied = false;
    if let (true, Some(grid)) = (options.filter_unknown, observed.sensor) {
        gt = grid.filter_unknown(&gt);
        gt_unknown_filter_applied = true;
    }
    counts.gt_after_unknown_filter = gt.len();
    if gt.is_empty() {
        return Err(EvalError::EmptyGroundTruth {
            file: "(ground truth after filtering)".into(),
        });
    }
    if rec.is_empty() {
        notes.push("no reconstruction points left after filtering".to_string());
    }

    let rec_to_gt = nearest_distances(&rec.positions, &gt.positions);
    let gt_to_rec = nearest_distances(&gt.positions, &rec.positions);
    let mut report = report_from_distances(&rec_to_gt, &gt_to_rec, &options.thresholds_m);
    counts.reconstruction_evaluated = rec.len();
    counts.gt_evaluated = gt.len();
    report.counts = counts;
    report.unknown_filter_applied = unknown_filter_applied;
    report.gt_unknown_filter_applied = gt_unknown_filter_applied;
    report.notes = notes;
    report.options = options.clone();
    Ok(GeometryEvaluation {
        report,
        reconstruction: rec,
        ground_truth: gt,
        rec_to_gt,
        gt_to_rec,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A plane sampled every 5 cm: a point on it between samples is at 0 from the surface (2.5–3.5 cm from
    /// the nearest sample), one 3 cm above at 3 cm, one past the patch's edge at its point distance.
    #[test]
    fn surface_distance_is_to_the_plane_not_to_the_samples() {
        let mut gt = Vec::new();
        for i in 0..40 {
            for j in 0..40 {
                gt.push(DVec3::new(i as f64 * 0.05, j as f64 * 0.05, 1.0));
            }
        }
        let nn = NearestNeighbours::new(&gt);
        let between = DVec3::new(1.025, 1.025, 1.0);
        assert!((nn.distance(between) - 0.025 * 2f64.sqrt()).abs() < 1e-9);
        assert!(nn.surface_distance(between) < 1e-9);
        let above = DVec3::new(1.025, 1.025, 1.03);
        assert!((nn.surface_distance(above) - 0.03).abs() < 1e-9);
        let beyond = DVec3::new(2.5, 1.0, 1.0);
        assert!((nn.surface_distance(beyond) - nn.distance(beyond)).abs() < 1e-12);
        assert!(nn.surface_distance(DVec3::NAN).is_nan());
        assert_eq!(
            nn.surface_distances(&[between, above]).len(),
            2,
            "one per query"
        );
    }

    use glam::DMat4;
    use rand::{Rng, SeedableRng};
    use rand_xoshiro::Xoshiro256PlusPlus;

    /// Random points on the faces of a 2 m box (~3.5 cm apart): a surface-like GT.
    fn box_surface(n: usize, seed: u64) -> PointCloud {
        let mut r = Xoshiro256PlusPlus::seed_from_u64(seed);
        let pts = (0..n)
            .map(|_| {
                let mut p = [
                    r.random_range(0.0..2.0),
                    r.random_range(0.0..2.0),
                    r.random_range(0.0..2.0),
                ];
                let axis = r.random_range(0..3);
                p[axis] = if r.random::<bool>() { 0.0 } else { 2.0 };
                DVec3::from_array(p)
            })
            .collect();
        PointCloud::from_positions(pts)
    }

    fn gaussian(r: &mut Xoshiro256PlusPlus) -> f64 {
        // Box–Muller; 1 - u keeps the log argument in (0, 1].
        let (u, v): (f64, f64) = (r.random(), r.random());
        (-2.0 * (1.0 - u).ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }

    fn brute_force(q: &[DVec3], r: &[DVec3]) -> Vec<f64> {
        q.iter()
            .map(|a| {
                r.iter()
                    .map(|b| a.distance(*b))
                    .fold(f64::INFINITY, f64::min)
            })
            .collect()
    }

    #[test]
    fn kd_tree_matches_brute_force_with_duplicates() {
        let mut r = Xoshiro256PlusPlus::seed_from_u64(5);
        for n in [1usize, 2, 3, 31, 32, 33, 100, 700] {
            // Heavily quantised coordinates: lots of exact ties on every axis.
            let pts: Vec<DVec3> = (0..n)
                .map(|_| {
                    DVec3::new(
                        r.random_range(0..4) as f64,
                        r.random_range(0..3) as f64,
                        0.5,
                    )
                })
                .collect();
            let q: Vec<DVec3> = (0..50)
                .map(|_| {
                    DVec3::new(
                        r.random_range(-1.0..5.0),
                        r.random_range(-1.0..4.0),
                        r.random_range(0.0..1.0),
                    )
                })
                .collect();
            assert_eq!(
                nearest_distances(&q, &pts),
                brute_force(&q, &pts),
                "n = {n}"
            );
        }
        let q = [DVec3::ZERO, DVec3::NAN];
        let d = nearest_distances(&q, &[]);
        assert!(d[0].is_infinite() && d[1].is_nan());
    }

    #[test]
    fn identical_clouds_score_perfectly() {
        let gt = box_surface(20_000, 1);
        let eval = evaluate_geometry(
            &gt,
            &gt,
            ObservedSpace::default(),
            &GeometryOptions::default(),
        )
        .unwrap();
        let r = &eval.report;
        assert_eq!(r.accuracy_m, 0.0);
        assert_eq!(r.completeness_m, 0.0);
        assert_eq!(r.thresholds.len(), 4);
        for s in &r.thresholds {
            assert_eq!((s.precision, s.recall, s.fscore), (1.0, 1.0, 1.0), "{s:?}");
        }
        assert_eq!(r.per_threshold["fscore_5cm"], 1.0);
        assert!(r.counts.reconstruction_after_downsample < 20_000);
        assert_eq!(r.counts.gt_evaluated, r.counts.reconstruction_evaluated);
        assert!(!r.unknown_filter_applied);
    }

    #[test]
    fn noise_lowers_fscore_monotonically() {
        let gt = box_surface(20_000, 2);
        let mut r = Xoshiro256PlusPlus::seed_from_u64(3);
        let mut last_f = 1.0;
        let mut last_acc = 0.0;
        for sigma in [0.02, 0.04, 0.08, 0.16] {
            let noisy = PointCloud::from_positions(
                gt.positions
                    .iter()
                    .map(|p| {
                        *p + DVec3::new(gaussian(&mut r), gaussian(&mut r), gaussian(&mut r))
                            * sigma
                    })
                    .collect(),
            );
            let opts = GeometryOptions {
                crop_padding_m: 1.0,
                ..GeometryOptions::default()
            };
            let rep = evaluate_geometry(&noisy, &gt, ObservedSpace::default(), &opts)
                .unwrap()
                .report;
            let f = rep.per_threshold["fscore_5cm"];
            assert!(f < last_f, "sigma {sigma}: F@5cm {f} not below {last_f}");
            assert!(
                rep.accuracy_m > last_acc,
                "sigma {sigma}: accuracy {} not above {last_acc}",
                rep.accuracy_m
            );
            last_f = f;
            last_acc = rep.accuracy_m;
        }
        assert!(
            last_f < 0.6,
            "σ = 16 cm should leave F@5cm well below 1, got {last_f}"
        );
    }

    #[test]
    fn hand_computed_example() {
        // GT on the x axis; reconstruction points at known distances 0.01, 0.04, 0.08, 0.5 from it.
        let gt = PointCloud::from_positions(vec![
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(1.0, 0.0, 0.0),
            DVec3::new(2.0, 0.0, 0.0),
            DVec3::new(3.0, 0.0, 0.0),
        ]);
        let rec = PointCloud::from_positions(vec![
            DVec3::new(0.0, 0.01, 0.0),
            DVec3::new(1.0, 0.0, 0.04),
            DVec3::new(2.08, 0.0, 0.0),
            DVec3::new(1.5, 0.0, 0.0),
        ]);
        let opts = GeometryOptions {
            thresholds_m: vec![0.05, 0.1, 0.6],
            ..GeometryOptions::raw()
        };
        let e = evaluate_geometry(&rec, &gt, ObservedSpace::default(), &opts).unwrap();
        let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
        let want_rec = [0.01, 0.04, 0.08, 0.5];
        let want_gt = [0.01, 0.04, 0.08, 0.92];
        for (d, w) in e
            .rec_to_gt
            .iter()
            .zip(want_rec)
            .chain(e.gt_to_rec.iter().zip(want_gt))
        {
            assert!(close(*d, w), "{d} vs {w}");
        }
        let r = &e.report;
        assert!(close(r.accuracy_m, (0.01 + 0.04 + 0.08 + 0.5) / 4.0));
        assert!(close(r.accuracy_median_m, 0.06));
        // τ = 5 cm: P = 2/4, R = 2/4; τ = 10 cm: P = 3/4, R = 3/4; τ = 60 cm: P = 1, R = 3/4 (0.92 misses).
        assert_eq!(
            (r.thresholds[0].precision, r.thresholds[0].recall),
            (0.5, 0.5)
        );
        assert_eq!(
            (r.thresholds[1].precision, r.thresholds[1].recall),
            (0.75, 0.75)
        );
        assert_eq!(
            (r.thresholds[2].precision, r.thresholds[2].recall),
            (1.0, 0.75)
        );
        assert!(close(r.thresholds[2].fscore, 2.0 * 0.75 / 1.75));
        assert_eq!(r.per_threshold["recall_60cm"], 0.75);
        assert_eq!(r.thresholds[1].reconstruction_inliers, 3);
    }

    #[test]
    fn pipeline_crops_transforms_and_filters_unknown() {
        let gt = PointCloud::from_positions(vec![
            DVec3::new(0.05, 0.05, 0.05),
            DVec3::new(1.05, 0.05, 0.05),
        ]);
        let mut grid = OccupancyGrid::new(0.1).unwrap();
        grid.insert_ray(
            DVec3::new(0.05, 0.05, 0.05),
            DVec3::new(1.05, 0.05, 0.05),
            true,
        );
        // Reconstruction in a frame shifted by -10 m in x.
        let rec = PointCloud::from_positions(vec![
            DVec3::new(-9.95, 0.05, 0.05), // on GT point 0
            DVec3::new(-9.45, 0.05, 0.05), // between the GT points, in observed free space
            DVec3::new(-9.05, 0.05, 0.05), // 10 cm from GT point 1
            DVec3::new(-9.45, 0.05, 0.25), // above the GT box: cropped
            DVec3::new(-7.0, 0.05, 0.05),  // beyond it: cropped
        ]);
        let opts = GeometryOptions {
            reconstruction_to_gt: Some(DMat4::from_translation(DVec3::new(10.0, 0.0, 0.0))),
            crop_padding_m: 0.001,
            ..GeometryOptions::default()
        };
        let e = evaluate_geometry(
            &rec,
            &gt,
            ObservedSpace {
                gt: Some(&grid),
                sensor: None,
            },
            &opts,
        )
        .unwrap();
        let c = &e.report.counts;
        assert_eq!(c.reconstruction_input, 5);
        assert_eq!(c.reconstruction_after_crop, 3, "{c:?}");
        assert_eq!(c.reconstruction_after_unknown_filter, 3, "{c:?}");
        assert!(e.report.unknown_filter_applied);
        let want = [0.0, 0.5, 0.1];
        for (d, w) in e.rec_to_gt.iter().zip(want) {
            assert!((d - w).abs() < 1e-9, "{d} vs {w}");
        }
        // Now a point in the bbox but in never-observed space (y range widened by padding).
        let rec2 = PointCloud::from_positions(vec![
            DVec3::new(0.55, 0.05, 0.05),
            DVec3::new(0.55, 0.45, 0.05),
        ]);
        let opts2 = GeometryOptions {
            crop_padding_m: 1.0,
            ..GeometryOptions::default()
        };
        let e2 = evaluate_geometry(
            &rec2,
            &gt,
            ObservedSpace {
                gt: Some(&grid),
                sensor: None,
            },
            &opts2,
        )
        .unwrap();
        assert_eq!(e2.report.counts.reconstruction_after_crop, 2);
        assert_eq!(e2.report.counts.reconstruction_after_unknown_filter, 1);
        assert_eq!(
            e2.reconstruction.positions,
            vec![DVec3::new(0.55, 0.05, 0.05)]
        );
        // Without a grid the filter is skipped and the report says so.
        let e3 = evaluate_geometry(&rec2, &gt, ObservedSpace::default(), &opts2).unwrap();
        assert!(!e3.report.unknown_filter_applied && e3.report.notes[0].contains("skipped"));
        assert_eq!(e3.report.counts.reconstruction_evaluated, 2);
    }

    #[test]
    fn empty_and_invalid_inputs() {
        let gt = PointCloud::from_positions(vec![DVec3::ZERO, DVec3::X]);
        let e = evaluate_geometry(
            &PointCloud::new(),
            &gt,
            ObservedSpace::default(),
            &GeometryOptions::raw(),
        )
        .unwrap();
        assert!(e.report.accuracy_m.is_nan() && e.report.completeness_m.is_infinite());
        assert_eq!(e.report.per_threshold["fscore_5cm"], 0.0);
        let json = serde_json::to_value(&e.report).unwrap();
        assert!(json["accuracy_m"].is_null());
        let nan = PointCloud::from_positions(vec![DVec3::NAN]);
        assert!(matches!(
            evaluate_geometry(&gt, &nan, ObservedSpace::default(), &GeometryOptions::raw()),
            Err(EvalError::EmptyGroundTruth { .. })
        ));
        for bad in [
            GeometryOptions {
                voxel_size_m: Some(0.0),
                ..GeometryOptions::default()
            },
            GeometryOptions {
                thresholds_m: vec![0.05, -1.0],
                ..GeometryOptions::default()
            },
            GeometryOptions {
                reconstruction_to_gt: Some(DMat4::ZERO),
                ..GeometryOptions::default()
            },
        ] {
            assert!(matches!(
                evaluate_geometry(&gt, &gt, ObservedSpace::default(), &bad),
                Err(EvalError::BadOptions(_))
            ));
        }
    }

    #[test]
    fn median_matches_numpy_convention() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0]), 2.5);
        assert!(median(&[]).is_nan());
    }
}
