//! Evaluation reports (JSON) and error-coloured clouds.

use super::options::GeometryOptions;
use crate::pointcloud::{write_atomic, PointCloud};
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::Path;

/// Scores at one distance threshold.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ThresholdScores {
    pub threshold_m: f64,
    /// Fraction of reconstruction points closer than the threshold to the GT.
    pub precision: f64,
    /// Fraction of GT points closer than the threshold to the reconstruction.
    pub recall: f64,
    /// 2PR/(P+R), 0 when P+R = 0.
    pub fscore: f64,
    pub reconstruction_inliers: usize,
    pub gt_inliers: usize,
}

/// Point counts through the pipeline stages (a disabled stage repeats the previous count).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct PointCounts {
    pub reconstruction_input: usize,
    /// Input points with a NaN/∞ coordinate (dropped before anything else).
    pub reconstruction_nonfinite: usize,
    pub reconstruction_after_crop: usize,
    pub reconstruction_after_downsample: usize,
    pub reconstruction_after_unknown_filter: usize,
    pub reconstruction_evaluated: usize,
    pub gt_input: usize,
    pub gt_nonfinite: usize,
    pub gt_after_downsample: usize,
    pub gt_after_unknown_filter: usize,
    pub gt_evaluated: usize,
}

/// Geometry evaluation result. Besides the structured `thresholds`, every threshold also appears as
/// flat keys `precision_<t>`, `recall_<t>`, `fscore_<t>` (`<t>` from [`threshold_key`], e.g.
/// `fscore_5cm`), which is what tables and the Spires CSV use. NaN/∞ (empty clouds) serialise as `null`.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GeometryReport {
    /// Mean reconstruction → GT distance (m).
    pub accuracy_m: f64,
    /// Mean GT → reconstruction distance (m).
    pub completeness_m: f64,
    pub accuracy_median_m: f64,
    pub completeness_median_m: f64,
    #[serde(flatten)]
    pub per_threshold: BTreeMap<String, f64>,
    pub thresholds: Vec<ThresholdScores>,
    pub counts: PointCounts,
    /// Whether reconstruction points in GT-unknown space were removed.
    pub unknown_filter_applied: bool,
    /// Whether GT points in sensor-unknown space were removed.
    pub gt_unknown_filter_applied: bool,
    pub notes: Vec<String>,
    pub options: GeometryOptions,
}

impl GeometryReport {
    pub fn to_json_pretty(&self) -> String {
        // Serialising plain data with string keys cannot fail.
        serde_json::to_string_pretty(self).unwrap_or_default()
    }

    /// One-line summary for logs.
    pub fn summary(&self) -> String {
        let mut s = format!(
            "accuracy {:.4} m, completeness {:.4} m",
            self.accuracy_m, self.completeness_m
        );
        for t in &self.thresholds {
            s.push_str(&format!(
                "; @{}: P {:.3} R {:.3} F {:.3}",
                threshold_key(t.threshold_m),
                t.precision,
                t.recall,
                t.fscore
            ));
        }
        s
    }

    /// Writes the pretty JSON atomically; errors name the file.
    pub fn write_json(&self, path: &Path) -> Result<(), super::EvalError> {
        let json = self.to_json_pretty();
        write_atomic(path, |w| std::io::Write::write_all(w, json.as_bytes())).map_err(|source| {
            super::EvalError::Io {
                file: path.display().to_string(),
                source,
            }
        })
    }
}

/// Key suffix for a threshold: whole centimetres as `5cm`, whole millimetres as `25mm`, anything else
/// in metres with `p` for the point (`0p0125m`).
pub fn threshold_key(tau_m: f64) -> String {
    let cm = tau_m * 100.0;
    if (cm - cm.round()).abs() < 1e-9 {
        return format!("{}cm", cm.round() as i64);
    }
    let mm = tau_m * 1000.0;
    if (mm - mm.round()).abs() < 1e-9 {
        return format!("{}mm", mm.round() as i64);
    }
    format!("{tau_m}m").replace('.', "p")
}

/// Turbo colormap (Google's polynomial approximation, Mikhailov 2019): dark blue → cyan → green →
/// yellow → red → dark red, perceptually ordered. `x` is clamped to [0, 1]; NaN maps to 0.
pub fn turbo(x: f64) -> [u8; 3] {
    const R4: [f64; 4] = [0.13572138, 4.61539260, -42.66032258, 132.13108234];
    const G4: [f64; 4] = [0.09140261, 2.19418839, 4.84296658, -14.18503333];
    const B4: [f64; 4] = [0.10667330, 12.64194608, -60.58204836, 110.36276771];
    const R2: [f64; 2] = [-152.94239396, 59.28637943];
    const G2: [f64; 2] = [4.27729857, 2.82956604];
    const B2: [f64; 2] = [-89.90310912, 27.34824973];
    let x = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) };
    let v4 = [1.0, x, x * x, x * x * x];
    let v2 = [v4[2] * v4[2], v4[3] * v4[2]];
    let ch = |c4: [f64; 4], c2: [f64; 2]| {
        let v = c4.iter().zip(v4).map(|(a, b)| a * b).sum::<f64>() + c2[0] * v2[0] + c2[1] * v2[1];
        (v.clamp(0.0, 1.0) * 255.0).round() as u8
    };
    [ch(R4, R2), ch(G4, G2), ch(B4, B2)]
}

/// Error colour for a normalised error `x` ∈ [0, 1]: turbo restricted to [0.1, 0.9], i.e. blue → green →
/// yellow → red without turbo's near-black ends, like the Spires error clouds.
pub fn error_color(x: f64) -> [u8; 3] {
    let x = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) };
    turbo(0.1 + 0.8 * x)
}

/// Colour used for points whose distance is NaN (no reference to measure against).
pub const NO_DISTANCE_COLOR: [u8; 3] = [128, 128, 128];

/// Copy of `cloud` coloured by `distances` ([`error_color`], clipped at `max_error_m`; Spires clips at 1 m) with
/// the distance stored as the scalar property `error_m`. Normals and other scalars are kept.
///
/// # Panics
/// If `distances.len() != cloud.len()`.
pub fn error_colored_cloud(cloud: &PointCloud, distances: &[f64], max_error_m: f64) -> PointCloud {
    assert_eq!(distances.len(), cloud.len(), "one distance per point");
    let scale = if max_error_m.is_finite() && max_error_m > 0.0 {
        1.0 / max_error_m
    } else {
        1.0
    };
    let mut out = cloud.clone();
    out.colors = Some(
        distances
            .iter()
            .map(|&d| {
                if d.is_nan() {
                    NO_DISTANCE_COLOR
                } else {
                    error_color(d * scale)
                }
            })
            .collect(),
    );
    out.set_scalar("error_m", distances.iter().map(|&d| d as f32).collect());
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    #[test]
    fn threshold_keys() {
        assert_eq!(threshold_key(0.03), "3cm");
        assert_eq!(threshold_key(0.05), "5cm");
        assert_eq!(threshold_key(0.1), "10cm");
        assert_eq!(threshold_key(0.2), "20cm");
        assert_eq!(threshold_key(0.025), "25mm");
        assert_eq!(threshold_key(0.0125), "0p0125m");
    }

    #[test]
    fn error_colors_run_blue_to_red() {
        let lo = error_color(0.0);
        let mid = error_color(0.5);
        let hi = error_color(1.0);
        assert!(lo[2] > 200 && lo[0] < 100 && lo[1] < 100, "{lo:?}");
        assert!(mid[1] > 240 && mid[0] < 160 && mid[2] < 100, "{mid:?}");
        assert!(hi[0] > 150 && hi[1] < 50 && hi[2] < 20, "{hi:?}");
        assert_eq!(error_color(-3.0), lo);
        assert_eq!(error_color(7.0), hi);
        // Blue fades steadily from 20 % on, so larger errors look warmer.
        let blues: Vec<u8> = (0..=10).map(|i| error_color(i as f64 / 10.0)[2]).collect();
        assert!(blues.windows(2).skip(2).all(|w| w[1] <= w[0]), "{blues:?}");
    }

    #[test]
    fn error_cloud_has_colors_and_scalar() {
        let c = PointCloud::from_positions(vec![DVec3::ZERO, DVec3::X, DVec3::Y]);
        let e = error_colored_cloud(&c, &[0.0, 2.0, f64::NAN], 1.0);
        assert_eq!(e.colors.as_ref().unwrap()[1], error_color(1.0));
        assert_eq!(e.colors.as_ref().unwrap()[2], NO_DISTANCE_COLOR);
        assert_eq!(e.scalar("error_m").unwrap()[1], 2.0);
        // It is writable as PLY.
        assert!(crate::pointcloud::write_ply_bytes(&e).is_ok());
    }
}
