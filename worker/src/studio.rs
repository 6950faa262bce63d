//! The studio's reconstructions in the worker: opened PLY files as layers, their filter counts and the
//! draw list of a view. Plain Rust (tested natively); `web.rs` feeds it bytes and a canvas.

use glam::DVec3;
use serde::{Deserialize, Serialize};
use silvr_core::pointcloud::{read_ply_bytes_with, write_ply_bytes, PlyReadOptions};
use silvr_core::uncertainty::filter::default_threshold;
use silvr_core::viewer::{
    Colouring, GpuLayer, LayerDraw, ViewCloud, SHOWN_FIELDS, UNCERTAINTY_FIELDS,
};

use crate::view::{Colour, ViewState};

/// Largest file the studio reads (a wasm32 heap is 4 GiB; the file, the parsed cloud and its view copy
/// must fit together).
pub const MAX_FILE_BYTES: u64 = 1536 << 20;
/// Most layers open at once.
pub const MAX_LAYERS: usize = crate::view::MAX_SOURCES;

/// Solid layer colours (Okabe-Ito, colour-blind safe), cycled.
pub const LAYER_COLOURS: [[f32; 3]; 8] = [
    [0.90, 0.62, 0.0],
    [0.34, 0.71, 0.91],
    [0.0, 0.62, 0.45],
    [0.94, 0.89, 0.26],
    [0.0, 0.45, 0.70],
    [0.84, 0.37, 0.0],
    [0.80, 0.47, 0.65],
    [0.95, 0.95, 0.95],
];

/// One scalar property of a layer, as the page shows it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScalarInfo {
    pub name: String,
    /// Finite range; `None` when every value is NaN or infinite.
    pub min: Option<f32>,
    pub max: Option<f32>,
    /// 1st and 99th percentiles of the values below `unconstrained_at`: the colour map's range.
    pub p01: Option<f32>,
    pub p99: Option<f32>,
    /// For an uncertainty (`log_std_*`): the log-std from which a point reads its prior (σ ≥ σ_p/√2),
    /// shown as "unconstrained" apart from the colour map; and how many points do.
    pub unconstrained_at: Option<f32>,
    pub unconstrained: u64,
}

/// Where a field's values stop meaning a measurement: for the uncertainty fields, the log-std of the
/// prior's information (`silvr_core::uncertainty::unconstrained_log_std` of the 1 m prior).
pub fn unconstrained_at(field: &str) -> Option<f32> {
    UNCERTAINTY_FIELDS.contains(&field).then(|| {
        silvr_core::uncertainty::unconstrained_log_std(silvr_core::uncertainty::PRIOR_SIGMA_M)
    })
}

/// A layer, as the page shows it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LayerInfo {
    pub index: u32,
    pub name: String,
    /// Where it came from: a URL, or `file:NAME` for a dropped file.
    pub source: String,
    /// Points drawn.
    pub points: u64,
    /// Points in the file.
    pub total: u64,
    /// Every `stride`-th point is drawn (1: all).
    pub stride: u64,
    pub min: [f64; 3],
    pub max: [f64; 3],
    /// The box "fit to view" frames (1st-99th percentile per axis).
    pub fit_min: [f64; 3],
    pub fit_max: [f64; 3],
    pub has_rgb: bool,
    pub scalars: Vec<ScalarInfo>,
    pub gpu_bytes: u64,
    /// A COPC map's level of detail: what was loaded of the octree (`points` of `total`).
    #[serde(default)]
    pub lod: Option<crate::copc::LodInfo>,
}

/// A layer: the view cloud, and its GPU buffers once a device drew it.
pub struct Layer {
    pub info: LayerInfo,
    pub cloud: ViewCloud,
    pub gpu: Option<GpuLayer>,
}

/// Parses a PLY file into a layer (the core's reader: one reader for native and browser). Errors name
/// the source and the problem.
pub fn parse_layer(bytes: &[u8], name: &str, source: &str, index: u32) -> Result<Layer, String> {
    // Only what the studio shows is decoded (no normals; of the scalars only [`SHOWN_FIELDS`]): a
    // splat file's sixty properties would otherwise each cost a buffer while parsing, a sorted copy
    // and a GPU buffer.
    let opts = PlyReadOptions::only(&SHOWN_FIELDS);
    let cloud = read_ply_bytes_with(bytes, name, &opts).map_err(|e| e.to_string())?;
    if cloud.is_empty() {
        return Err(format!("{name}: the file holds no points"));
    }
    let view = ViewCloud::from_cloud(&cloud, ViewCloud::MAX_POINTS);
    drop(cloud);
    if view.is_empty() {
        return Err(format!("{name}: no point has finite coordinates"));
    }
    Ok(Layer::new(view, name.to_string(), source, index))
}

impl Layer {
    /// A layer of `view`, described for the page.
    pub(crate) fn new(view: ViewCloud, name: String, source: &str, index: u32) -> Self {
        let scalars = view
            .scalars
            .iter()
            .map(|s| {
                let at = unconstrained_at(&s.name);
                let below = at.unwrap_or(f32::INFINITY);
                ScalarInfo {
                    name: s.name.clone(),
                    min: s.quantile(0.0),
                    max: s.quantile(1.0),
                    p01: s.quantile_below(0.01, below),
                    p99: s.quantile_below(0.99, below),
                    unconstrained_at: at,
                    unconstrained: at.map_or(0, |a| s.at_least(a) as u64),
                }
            })
            .collect();
        Layer {
            info: LayerInfo {
                index,
                name,
                source: source.to_string(),
                points: view.len() as u64,
                total: view.total as u64,
                stride: view.stride as u64,
                min: view.min.to_array(),
                max: view.max.to_array(),
                fit_min: view.fit_min.to_array(),
                fit_max: view.fit_max.to_array(),
                has_rgb: view.has_rgb,
                scalars,
                gpu_bytes: 0,
                lod: None,
            },
            cloud: view,
            gpu: None,
        }
    }
}

/// Most camera frames a `transforms.json` may list (a day of driving at 10 Hz × 3 cameras is ~1 M).
pub const MAX_CAMERAS: usize = 2_000_000;

/// A dataset's cameras (nerfstudio `transforms.json`, the layout `silvr` writes) as a layer: each camera
/// centre, and a 0.5 m stick of points along its optical axis, so the trajectory and where the rig looked
/// show beside the reconstructions (same metric frame). Training frames blue, held-out frames orange.
pub fn parse_cameras(bytes: &[u8], name: &str, source: &str, index: u32) -> Result<Layer, String> {
    let text = std::str::from_utf8(bytes).map_err(|_| format!("{name}: not UTF-8 text"))?;
    let path = std::path::Path::new(name);
    let (frames, _, val) =
        silvr_core::dataset::parse_frames(text, path).map_err(|e| e.to_string())?;
    if frames.is_empty() {
        return Err(format!("{name}: the file lists no camera frames"));
    }
    if frames.len() > MAX_CAMERAS {
        return Err(format!(
            "{name}: {} frames, more than the {MAX_CAMERAS} the studio shows",
            frames.len()
        ));
    }
    let val: std::collections::HashSet<&str> = val.iter().map(String::as_str).collect();
    let mut cloud = silvr_core::pointcloud::PointCloud::new();
    for f in &frames {
        let (_, pose) = f.camera(path).map_err(|e| e.to_string())?;
        let held_out = val.contains(f.file_path.as_str());
        let colour = if held_out {
            [240, 150, 30]
        } else {
            [60, 140, 255]
        };
        let forward = pose.rot * DVec3::Z;
        for k in 0..=10 {
            cloud.push_colored(pose.trans + forward * (0.05 * k as f64), colour);
        }
    }
    let view = ViewCloud::from_cloud(&cloud, ViewCloud::MAX_POINTS);
    let name = format!("{name} — {} cameras", frames.len());
    Ok(Layer::new(view, name, source, index))
}

/// The union of the boxes `of` picks over the visible layers (all layers when none is visible). One
/// rule for the worker, which draws, and the page, which fits the camera and states the view matrix.
pub fn union_box<'a>(
    layers: impl Iterator<Item = &'a LayerInfo> + Clone,
    view: &ViewState,
    of: impl Fn(&LayerInfo) -> ([f64; 3], [f64; 3]),
) -> Option<([f64; 3], [f64; 3])> {
    let visible: Vec<&LayerInfo> = layers
        .clone()
        .filter(|l| !view.hidden.contains(&l.index))
        .collect();
    let set = if visible.is_empty() {
        layers.collect()
    } else {
        visible
    };
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for l in &set {
        let (a, b) = of(l);
        lo = lo.min(DVec3::from_array(a));
        hi = hi.max(DVec3::from_array(b));
    }
    (!set.is_empty()).then(|| (lo.to_array(), hi.to_array()))
}

/// The union of the ranges `of` picks from `field` over the visible layers that have it: the colour map's
/// range (2nd-98th percentiles, the worker's colours and the page's legend) or the slider's (min-max).
pub fn scalar_range<'a>(
    layers: impl Iterator<Item = &'a LayerInfo>,
    view: &ViewState,
    field: &str,
    of: impl Fn(&ScalarInfo) -> (Option<f32>, Option<f32>),
) -> Option<(f32, f32)> {
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    for l in layers.filter(|l| !view.hidden.contains(&l.index)) {
        if let Some((Some(a), Some(b))) = l.scalars.iter().find(|s| s.name == field).map(&of) {
            lo = lo.min(a);
            hi = hi.max(b);
        }
    }
    (lo <= hi).then_some((lo, hi))
}

/// The filter's outcome over the visible layers.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FilterCounts {
    pub field: String,
    /// The threshold in force (the view's, or the default rule's).
    pub threshold: Option<f32>,
    /// The default rule's threshold over the visible layers (Tukey's fence of their values together; for
    /// one layer exactly the native `silvr uncertainty` threshold).
    pub default_threshold: Option<f32>,
    /// Kept / total per layer (`None` for a layer without the field).
    pub per_layer: Vec<Option<(u64, u64)>>,
    pub kept: u64,
    pub total: u64,
}

/// The open layers.
#[derive(Default)]
pub struct Layers {
    pub layers: Vec<Layer>,
}

impl Layers {
    pub fn visible<'a>(&'a self, view: &'a ViewState) -> impl Iterator<Item = &'a Layer> + 'a {
        self.layers
            .iter()
            .filter(move |l| !view.hidden.contains(&l.info.index))
    }

    fn infos(&self) -> impl Iterator<Item = &LayerInfo> + Clone {
        self.layers.iter().map(|l| &l.info)
    }

    /// The bounds of all points of the visible layers (see [`union_box`]).
    pub fn bounds(&self, view: &ViewState) -> Option<([f64; 3], [f64; 3])> {
        union_box(self.infos(), view, |l| (l.min, l.max))
    }

    /// The box "fit to view" frames (see [`union_box`]).
    pub fn fit_bounds(&self, view: &ViewState) -> Option<([f64; 3], [f64; 3])> {
        union_box(self.infos(), view, |l| (l.fit_min, l.fit_max))
    }

    /// The default threshold of `field` over the visible layers (`None` when no value is finite: the
    /// rule then keeps every non-NaN point, as the native one does with its infinite threshold).
    pub fn default_threshold(&self, view: &ViewState, field: &str) -> Option<f32> {
        let values: Vec<f32> = self
            .visible(view)
            .filter_map(|l| l.cloud.scalar(field))
            .flat_map(|s| s.values.iter().copied())
            .collect();
        let t = default_threshold(&values);
        t.is_finite().then_some(t)
    }

    /// The threshold the view applies: its own, or the default rule's (infinite when no value is finite,
    /// which still drops NaN, as `points_filtered.ply` does).
    pub fn threshold(&self, view: &ViewState) -> f32 {
        view.threshold
            .or_else(|| self.default_threshold(view, &view.filter))
            .unwrap_or(f32::INFINITY)
    }

    pub fn counts(&self, view: &ViewState) -> FilterCounts {
        let threshold = self.threshold(view);
        let mut per_layer = Vec::new();
        let (mut kept, mut total) = (0, 0);
        for l in &self.layers {
            let hidden = view.hidden.contains(&l.info.index);
            let c = l
                .cloud
                .scalar(&view.filter)
                .map(|s| (s.kept(threshold) as u64, l.cloud.len() as u64));
            if let (Some((k, n)), false) = (c, hidden) {
                kept += k;
                total += n;
            }
            per_layer.push(c);
        }
        FilterCounts {
            field: view.filter.clone(),
            threshold: threshold.is_finite().then_some(threshold),
            default_threshold: self.default_threshold(view, &view.filter),
            per_layer,
            kept,
            total,
        }
    }

    /// How each visible layer with GPU buffers is drawn in `view`.
    pub fn draws<'a>(&'a self, view: &ViewState) -> Vec<LayerDraw<'a>> {
        let threshold = self.threshold(view);
        self.layers
            .iter()
            .filter(|l| !view.hidden.contains(&l.info.index))
            .filter_map(|l| {
                let layer = l.gpu.as_ref()?;
                let solid = LAYER_COLOURS[l.info.index as usize % LAYER_COLOURS.len()];
                let colouring = match &view.colour {
                    Colour::Rgb => Colouring::Rgb,
                    Colour::Layer => Colouring::Solid(solid),
                    Colour::Field(f) => match self.colour_range(view, f) {
                        Some((lo, hi)) => match l.cloud.scalars.iter().position(|s| &s.name == f) {
                            Some(index) => Colouring::Map {
                                index,
                                lo,
                                hi,
                                above: unconstrained_at(f).unwrap_or(f32::INFINITY),
                            },
                            None => Colouring::Solid([0.45, 0.45, 0.45]),
                        },
                        None => Colouring::Solid([0.45, 0.45, 0.45]),
                    },
                };
                let filter = l
                    .cloud
                    .scalars
                    .iter()
                    .position(|s| s.name == view.filter)
                    .map(|i| (i, threshold));
                Some(LayerDraw {
                    layer,
                    colouring,
                    filter,
                })
            })
            .collect()
    }

    /// The colour map's range of `field` (see [`scalar_range`]).
    pub fn colour_range(&self, view: &ViewState, field: &str) -> Option<(f32, f32)> {
        scalar_range(self.infos(), view, field, |s| (s.p01, s.p99))
    }

    /// The kept points of layer `index` as a PLY file (the native writer), with a file name.
    pub fn filtered_ply(&self, view: &ViewState, index: u32) -> Result<(String, Vec<u8>), String> {
        let l = self
            .layers
            .iter()
            .find(|l| l.info.index == index)
            .ok_or_else(|| format!("there is no layer {index}"))?;
        if l.info.stride > 1 {
            return Err(format!(
                "{}: the studio holds every {}th point of this file, so its filtered download would not \
                 be the file's; filter it natively (silvr uncertainty) instead",
                l.info.name, l.info.stride
            ));
        }
        let threshold = self.threshold(view);
        let cloud = l
            .cloud
            .filtered(&view.filter, threshold)
            .ok_or_else(|| format!("{} has no property {}", l.info.name, view.filter))?;
        let bytes = write_ply_bytes(&cloud).map_err(|e| format!("{}: {e}", l.info.name))?;
        let stem = l.info.name.trim_end_matches(".ply");
        Ok((format!("{stem}_filtered.ply"), bytes))
    }
}

#[cfg(all(test, not(target_arch = "wasm32")))]
mod tests {
    use super::*;
    use silvr_core::pointcloud::{read_ply_bytes, PointCloud};

    fn ply(n: usize) -> Vec<u8> {
        let mut c = PointCloud::new();
        for i in 0..n {
            c.push_colored(DVec3::new(i as f64, 0.0, 1.0), [1, 2, 3]);
        }
        let mut v: Vec<f32> = (0..n).map(|i| (i % 50) as f32 * 0.01 - 2.0).collect();
        v[n - 1] = 5.0; // an outlier
        v[0] = f32::NAN;
        c.set_scalar("log_std_combined", v);
        write_ply_bytes(&c).unwrap()
    }

    #[test]
    fn default_threshold_and_counts_match_the_native_filter() {
        let bytes = ply(200);
        let mut layers = Layers::default();
        layers
            .layers
            .push(parse_layer(&bytes, "points.ply", "file:points.ply", 0).unwrap());
        let view = ViewState::default();
        let c = layers.counts(&view);
        let native = silvr_core::pointcloud::read_ply_bytes(&bytes, "p").unwrap();
        let v = native.scalar("log_std_combined").unwrap();
        let t = default_threshold(v);
        assert_eq!(c.threshold, Some(t));
        let kept = v.iter().filter(|&&x| x <= t).count() as u64;
        assert_eq!(c.kept, kept);
        assert_eq!(c.kept, 198, "the NaN and the outlier go");
        assert_eq!(c.total, 200);
        let (name, out) = layers.filtered_ply(&view, 0).unwrap();
        assert_eq!(name, "points_filtered.ply");
        assert_eq!(read_ply_bytes(&out, &name).unwrap().len() as u64, kept);
        // Hiding the layer removes it from the counts.
        let hidden = ViewState {
            hidden: vec![0],
            ..ViewState::default()
        };
        assert_eq!(layers.counts(&hidden).total, 0);
    }

    /// No finite value: the native rule's threshold is infinite and every NaN is still dropped.
    #[test]
    fn a_field_without_finite_values_keeps_no_nan() {
        let mut c = PointCloud::new();
        for i in 0..10 {
            c.push(DVec3::new(i as f64, 0.0, 0.0));
        }
        let mut v = vec![f32::NAN; 10];
        v[3] = f32::INFINITY;
        c.set_scalar("log_std_combined", v);
        c.set_scalar("f_rest_0", vec![1.0; 10]);
        let l = parse_layer(&write_ply_bytes(&c).unwrap(), "n.ply", "", 0).unwrap();
        // Properties the studio does not use are not kept.
        assert_eq!(l.cloud.scalars.len(), 1);
        let layers = Layers { layers: vec![l] };
        let c = layers.counts(&ViewState::default());
        assert_eq!((c.kept, c.total, c.threshold), (1, 10, None));
    }

    #[test]
    fn a_transforms_json_becomes_a_camera_layer() {
        let json = br#"{"fl_x": 100, "fl_y": 100, "cx": 50, "cy": 40, "w": 100, "h": 80,
            "frames": [
              {"file_path": "images/a.png", "transform_matrix": [[1,0,0,2],[0,1,0,3],[0,0,1,4],[0,0,0,1]]},
              {"file_path": "images/b.png", "transform_matrix": [[1,0,0,5],[0,1,0,3],[0,0,1,4],[0,0,0,1]]}
            ], "val_filenames": ["images/b.png"]}"#;
        let l = parse_cameras(json, "transforms.json", "file:transforms.json", 3).unwrap();
        assert_eq!(l.info.points, 22);
        assert_eq!(l.info.index, 3);
        assert!(l.info.name.contains("2 cameras"));
        // Camera centres at the matrices' translations.
        assert!((l.info.min[0] - 2.0).abs() < 1e-9 && (l.info.max[0] - 5.0).abs() < 1e-9);
        let e = parse_cameras(b"{\"frames\": 3}", "t.json", "", 0)
            .err()
            .unwrap();
        assert!(e.contains("t.json"), "{e}");
    }

    #[test]
    fn bad_files_name_the_source_and_the_problem() {
        let e = parse_layer(b"not a ply at all", "x.ply", "file:x.ply", 0)
            .err()
            .unwrap();
        assert!(e.starts_with("x.ply"), "{e}");
        assert_eq!(e.matches("x.ply").count(), 1, "the file is named once: {e}");
        let mut b = ply(100);
        b.truncate(b.len() - 7);
        let e = parse_layer(&b, "cut.ply", "", 0).err().unwrap();
        assert!(e.contains("cut.ply"), "{e}");
        // A header claiming 2^31 points in a tiny file errors before allocating.
        let huge = b"ply\nformat binary_little_endian 1.0\nelement vertex 2147483647\nproperty float x\nproperty float y\nproperty float z\nend_header\n\0\0\0\0";
        let e = parse_layer(huge, "huge.ply", "", 0).err().unwrap();
        assert!(e.contains("huge.ply"), "{e}");
    }
}
