//! Maps for streaming viewers: COPC, a LAZ 1.4 file whose chunks form an octree and are read by byte ranges
//! (PDAL, QGIS, Potree 2 and the copc.io viewer read it). We write every per-point scalar of a map
//! (`log_std_*`, `depth_spread_m`, `submap`, `error_m`, …) as a float extra-bytes dimension, and one VLR of
//! our own, the [`CopcSummary`]: what the uncertainty filter needs over the whole cloud (each field's
//! range, the `log_std_*` histograms, the default threshold and the points it keeps), so a viewer that has
//! loaded only part of the octree can still state whole-cloud counts without reading every point.
//!
//! The summary is read here (wasm32 too: the studio's worker reads it from the header it fetched); the
//! writer is native ([`write`]).

pub mod extra_bytes;
pub mod lod;
pub mod read;
#[cfg(not(target_arch = "wasm32"))]
pub mod write;

use serde::{Deserialize, Serialize};

use crate::uncertainty::filter;

/// The summary VLR's user id (16 bytes at most) and record id.
pub const SUMMARY_USER_ID: &str = "SiLVR";
pub const SUMMARY_RECORD_ID: u16 = 1;

/// What the summary's `format` says; a reader refuses others.
pub const SUMMARY_FORMAT: &str = "silvr-copc-summary/1";

/// `log_std_*` histograms: log10 σ from 1 µm to 1 Mm in 0.01-decade bins (values outside fall in the end
/// bins). Fixed, so one pass over the points fills them.
const HIST_LO: f32 = -6.0;
const HIST_STEP: f32 = 0.01;
const HIST_BINS: usize = 1200;

/// Bounds a summary read from an untrusted file is checked against before use.
const MAX_SUMMARY_BYTES: usize = 65_535;
const MAX_FIELDS: usize = 64;
const MAX_BINS: usize = 4096;

/// The whole-cloud facts of one COPC file, as JSON in its `SiLVR`/1 VLR.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CopcSummary {
    /// [`SUMMARY_FORMAT`].
    pub format: String,
    /// Points in the file.
    pub points: u64,
    /// One entry per extra dimension, in the file's order.
    pub fields: Vec<FieldSummary>,
    /// The default uncertainty filter over every point, when the file has its field.
    pub filter: Option<FilterSummary>,
}

/// One extra dimension over the whole cloud.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FieldSummary {
    pub name: String,
    /// Points whose value is finite.
    pub finite: u64,
    /// Smallest and largest finite value (`None` when none is).
    pub min: Option<f32>,
    pub max: Option<f32>,
    /// For `log_std_*` fields: counts of the finite values by bin.
    pub histogram: Option<Histogram>,
}

/// Counts of values in bins of `step` from `lo`; the first and last bins also hold what lies beyond.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Histogram {
    pub lo: f32,
    pub step: f32,
    pub counts: Vec<u64>,
}

impl Histogram {
    fn log_std() -> Self {
        Self {
            lo: HIST_LO,
            step: HIST_STEP,
            counts: vec![0; HIST_BINS],
        }
    }

    fn bin(&self, v: f32) -> usize {
        let b = ((v - self.lo) / self.step).floor();
        (b.max(0.0) as usize).min(self.counts.len() - 1)
    }

    /// How many values are at most `t`, to the bin: the bins that end at or below `t` count whole, the
    /// one `t` falls in counts in proportion (the values in a bin are taken as spread evenly).
    pub fn count_at_most(&self, t: f32) -> f64 {
        if t.is_nan() {
            return 0.0;
        }
        let last = self.counts.len() - 1;
        let mut n = 0.0;
        for (i, &c) in self.counts.iter().enumerate() {
            let a = self.lo + i as f32 * self.step;
            // The last bin also holds everything above its edge: only +∞ takes all of it for sure.
            let whole = if i == last {
                t == f32::INFINITY
            } else {
                t >= a + self.step
            };
            if whole {
                n += c as f64;
            } else if t > a {
                n += c as f64 * ((t - a) / self.step).min(1.0) as f64;
            }
        }
        n
    }
}

/// The default filter ([`filter::default_threshold`]) over the whole cloud.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FilterSummary {
    /// [`filter::FILTER_FIELD`].
    pub field: String,
    /// `tukey`: Q3 + fence·IQR of the field's finite values.
    pub rule: String,
    pub fence: f32,
    /// The threshold (`None`: no finite value, every point kept as the rule says).
    pub threshold: Option<f32>,
    /// Points whose value is at most the threshold: exactly what `silvr uncertainty` keeps of this cloud.
    pub kept: u64,
}

/// Accumulates a [`CopcSummary`] over a cloud handed in chunks.
pub struct SummaryBuilder {
    points: u64,
    fields: Vec<FieldSummary>,
    /// The filter field's finite values, for the exact quartiles (4 bytes a point: 400 MB at 100 M).
    filter_values: Option<Vec<f32>>,
}

impl SummaryBuilder {
    /// A builder for these extra dimensions, in file order.
    pub fn new(names: &[String]) -> Self {
        Self {
            points: 0,
            fields: names
                .iter()
                .map(|n| FieldSummary {
                    name: n.clone(),
                    finite: 0,
                    min: None,
                    max: None,
                    histogram: n.starts_with("log_std_").then(Histogram::log_std),
                })
                .collect(),
            filter_values: names
                .iter()
                .any(|n| n == filter::FILTER_FIELD)
                .then(Vec::new),
        }
    }

    /// Adds `chunk`'s points with a finite position (the others are not written either).
    pub fn add(&mut self, chunk: &crate::pointcloud::PointCloud) -> Result<(), String> {
        let keep: Vec<usize> = (0..chunk.len())
            .filter(|&i| chunk.positions[i].is_finite())
            .collect();
        self.points += keep.len() as u64;
        for f in &mut self.fields {
            let Some(v) = chunk.scalar(&f.name).filter(|v| v.len() == chunk.len()) else {
                continue;
            };
            let is_filter = f.name == filter::FILTER_FIELD;
            if is_filter {
                if let Some(col) = &mut self.filter_values {
                    col.try_reserve(keep.len()).map_err(|_| {
                        format!(
                            "no memory for the {} values of '{}'",
                            col.len() + keep.len(),
                            f.name
                        )
                    })?;
                }
            }
            for &i in &keep {
                let x = v[i];
                if !x.is_finite() {
                    continue;
                }
                f.finite += 1;
                f.min = Some(f.min.map_or(x, |m| m.min(x)));
                f.max = Some(f.max.map_or(x, |m| m.max(x)));
                if let Some(h) = &mut f.histogram {
                    let b = h.bin(x);
                    h.counts[b] += 1;
                }
                if is_filter {
                    if let Some(col) = &mut self.filter_values {
                        col.push(x);
                    }
                }
            }
        }
        Ok(())
    }

    /// The summary: the default threshold from the exact quartiles, and the points it keeps.
    pub fn finish(self) -> CopcSummary {
        let filter = self.filter_values.map(|mut values| {
            let t = filter::default_threshold_reordering(&mut values);
            let kept = values.iter().filter(|&&v| filter::keeps(v, t)).count() as u64;
            FilterSummary {
                field: filter::FILTER_FIELD.into(),
                rule: "tukey".into(),
                fence: filter::FILTER_FENCE,
                threshold: t.is_finite().then_some(t),
                kept: if t.is_finite() { kept } else { self.points },
            }
        });
        CopcSummary {
            format: SUMMARY_FORMAT.into(),
            points: self.points,
            fields: self.fields,
            filter,
        }
    }
}

/// Why a summary VLR was refused.
#[derive(Debug, thiserror::Error)]
#[error("{source_name}: SiLVR summary VLR: {reason}")]
pub struct SummaryError {
    pub source_name: String,
    pub reason: String,
}

impl CopcSummary {
    /// The VLR payload (JSON).
    pub fn to_bytes(&self) -> Vec<u8> {
        serde_json::to_vec(self).unwrap_or_default()
    }

    /// Parses a summary from a file's VLR, bounded before use (untrusted input: a hostile link's file).
    pub fn from_bytes(bytes: &[u8], source_name: &str) -> Result<Self, SummaryError> {
        let bad = |reason: String| SummaryError {
            source_name: source_name.to_string(),
            reason,
        };
        if bytes.len() > MAX_SUMMARY_BYTES {
            return Err(bad(format!(
                "{} bytes, more than a VLR holds ({MAX_SUMMARY_BYTES})",
                bytes.len()
            )));
        }
        let s: CopcSummary =
            serde_json::from_slice(bytes).map_err(|e| bad(format!("not our JSON: {e}")))?;
        if s.format != SUMMARY_FORMAT {
            return Err(bad(format!(
                "format {:?}, expected {SUMMARY_FORMAT:?}",
                s.format
            )));
        }
        if s.fields.len() > MAX_FIELDS {
            return Err(bad(format!(
                "{} fields (at most {MAX_FIELDS})",
                s.fields.len()
            )));
        }
        for f in &s.fields {
            if f.finite > s.points {
                return Err(bad(format!(
                    "'{}' has {} finite values of {} points",
                    f.name, f.finite, s.points
                )));
            }
            if let Some(h) = &f.histogram {
                if h.counts.is_empty() || h.counts.len() > MAX_BINS {
                    return Err(bad(format!(
                        "'{}': {} histogram bins (1 to {MAX_BINS})",
                        f.name,
                        h.counts.len()
                    )));
                }
                if !(h.lo.is_finite() && h.step.is_finite() && h.step > 0.0) {
                    return Err(bad(format!("'{}': histogram bins are not finite", f.name)));
                }
                let total = h.counts.iter().try_fold(0u64, |a, &c| a.checked_add(c));
                if total != Some(f.finite) {
                    return Err(bad(format!(
                        "'{}': histogram counts do not add up to its {} finite values",
                        f.name, f.finite
                    )));
                }
            }
        }
        if let Some(fl) = &s.filter {
            if fl.kept > s.points {
                return Err(bad(format!("keeps {} of {} points", fl.kept, s.points)));
            }
        }
        Ok(s)
    }

    /// The entry of `name`.
    pub fn field(&self, name: &str) -> Option<&FieldSummary> {
        self.fields.iter().find(|f| f.name == name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pointcloud::PointCloud;
    use glam::DVec3;

    fn cloud(n: usize) -> PointCloud {
        let mut c = PointCloud::from_positions((0..n).map(|i| DVec3::splat(i as f64)).collect());
        c.positions[1] = DVec3::NAN;
        let v: Vec<f32> = (0..n).map(|i| -3.0 + (i % 100) as f32 * 0.01).collect();
        let mut w = v.clone();
        w[0] = 5.0; // an outlier the fence cuts
        w[2] = f32::NAN;
        c.set_scalar("log_std_combined", w);
        c.set_scalar("submap", (0..n).map(|i| (i % 3) as f32).collect());
        c
    }

    /// Chunked accumulation gives the whole cloud's facts: the threshold and kept count equal the native
    /// filter's on the same (finite-position) points; the histogram counts every finite value.
    #[test]
    fn the_summary_of_chunks_is_the_whole_clouds() {
        let c = cloud(1000);
        let names = vec!["log_std_combined".to_string(), "submap".to_string()];
        let mut b = SummaryBuilder::new(&names);
        for k in 0..4 {
            let idx: Vec<usize> = (k * 250..(k + 1) * 250).collect();
            b.add(&c.select(&idx)).unwrap();
        }
        let s = b.finish();
        assert_eq!(s.points, 999);
        let finite = c.finite_only();
        let v = finite.scalar("log_std_combined").unwrap();
        let t = filter::default_threshold(v);
        let fl = s.filter.as_ref().unwrap();
        assert_eq!(fl.threshold, Some(t));
        assert_eq!(
            fl.kept,
            v.iter().filter(|&&x| filter::keeps(x, t)).count() as u64
        );
        assert!(fl.kept < 998, "the outlier is cut");
        let f = s.field("log_std_combined").unwrap();
        assert_eq!(f.finite, 998);
        assert_eq!((f.min, f.max), (Some(-3.0), Some(5.0)));
        let h = f.histogram.as_ref().unwrap();
        assert_eq!(h.counts.iter().sum::<u64>(), 998);
        // Counts from the histogram track exact counts to a bin's worth.
        let exact = v.iter().filter(|&&x| x <= -2.5).count() as f64;
        assert!((h.count_at_most(-2.5) - exact).abs() <= 15.0);
        assert_eq!(h.count_at_most(f32::INFINITY), 998.0);
        assert!(s.field("submap").unwrap().histogram.is_none());
        // Round trip through the VLR bytes.
        let back = CopcSummary::from_bytes(&s.to_bytes(), "x.copc.laz").unwrap();
        assert_eq!(back, s);
        assert!(s.to_bytes().len() < MAX_SUMMARY_BYTES);
    }

    /// Hostile summaries are refused with the source named, never trusted.
    #[test]
    fn hostile_summaries_are_refused() {
        let names = vec!["log_std_combined".to_string()];
        let mut b = SummaryBuilder::new(&names);
        b.add(&cloud(10)).unwrap();
        let good = b.finish();
        let mut cases = vec![];
        let mut s = good.clone();
        s.format = "other/9".into();
        cases.push(s);
        let mut s = good.clone();
        s.fields[0].histogram.as_mut().unwrap().counts = vec![1; MAX_BINS + 1];
        cases.push(s);
        let mut s = good.clone();
        s.fields[0].histogram.as_mut().unwrap().counts[0] += 1;
        cases.push(s);
        let mut s = good.clone();
        s.fields[0].histogram.as_mut().unwrap().counts[0] = u64::MAX;
        cases.push(s);
        let mut s = good.clone();
        s.filter.as_mut().unwrap().kept = 11;
        cases.push(s);
        let mut s = good.clone();
        s.fields[0].finite = 10_000;
        cases.push(s);
        for s in cases {
            let e = CopcSummary::from_bytes(&s.to_bytes(), "bad.copc.laz").unwrap_err();
            assert!(
                e.to_string().starts_with("bad.copc.laz: SiLVR summary VLR"),
                "{e}"
            );
        }
        assert!(CopcSummary::from_bytes(b"{", "x").is_err());
        assert!(CopcSummary::from_bytes(&vec![b' '; 70_000], "x").is_err());
    }
}
