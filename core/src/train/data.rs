//! Training data: the images of a dataset (nerfstudio `transforms.json`, with our lidar depth / normal /
//! sky images when present), their cameras as per-pixel ray-direction tables, and the scene normalisation.
//!
//! Scene frame: nerfstudio's centring and scaling without its rotation: p_scene = s·(p − c) with c the mean
//! camera position and s = 1 / max‖cᵢ − c‖∞, so the cameras fill [−1, 1]³ and everything farther lives in
//! the contracted shell. Distances along unit rays are therefore metres × s.

use std::path::{Path, PathBuf};

use glam::{DMat3, DVec2, DVec3};
use rayon::prelude::*;

use crate::camera::CameraModel;
use crate::dataset::{self, NsFrame};
use crate::geometry::Se3;
use crate::lidar::images::{NO_NORMAL, SKY_DEPTH};
use crate::render::RayTarget;
use crate::source::{Files, Source};

/// Why a dataset could not be loaded, naming the file.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    #[error("{path}: {msg}")]
    Bad { path: PathBuf, msg: String },
    #[error(transparent)]
    Dataset(#[from] dataset::DatasetError),
}

fn bad(path: &Path, msg: impl Into<String>) -> DataError {
    DataError::Bad {
        path: path.to_path_buf(),
        msg: msg.into(),
    }
}

/// Centre and scale of the scene frame.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SceneFrame {
    pub center: [f64; 3],
    pub scale: f64,
}

impl SceneFrame {
    pub fn to_scene(&self, p: DVec3) -> DVec3 {
        (p - DVec3::from(self.center)) * self.scale
    }

    pub fn to_metric(&self, p: DVec3) -> DVec3 {
        p / self.scale + DVec3::from(self.center)
    }
}

/// One image with its camera, pose and lidar supervision.
pub struct Image {
    pub name: String,
    pub width: u32,
    pub height: u32,
    /// Index into [`TrainData::directions`] (images with identical intrinsics share one table).
    pub camera: usize,
    /// Camera-to-scene rotation (OpenCV axes) and centre in the scene frame.
    pub rotation: DMat3,
    pub origin: DVec3,
    pub rgb: Vec<[u8; 3]>,
    /// Lidar depth PNG values (range × 256, 0 none, 65535 sky); empty without lidar.
    pub depth: Vec<u16>,
    /// Lidar normal PNG values (camera frame, 128-grey none); empty without normals.
    pub normals: Vec<[u8; 3]>,
    /// Sky mask (non-zero = sky); empty without one.
    pub sky: Vec<u8>,
    /// Row of the appearance table, or `None` for held-out images (they use the mean embedding).
    pub appearance: Option<u32>,
}

/// A loaded dataset.
pub struct TrainData {
    pub root: PathBuf,
    pub frame: SceneFrame,
    pub images: Vec<Image>,
    /// Per distinct camera model: unit ray directions in the camera frame, row-major, NaN where the
    /// pixel has no ray (outside a fisheye's valid angle).
    pub directions: Vec<Vec<[f32; 3]>>,
    pub cameras: Vec<CameraModel>,
    pub train: Vec<usize>,
    pub val: Vec<usize>,
    /// Frames listed but skipped, with why (missing image files, for instance).
    pub skipped: Vec<String>,
    /// Standard deviation of the lidar's range noise (metres): `range_noise` of `calib/lidar.json` when
    /// the dataset states it (the synthetic world does), else [`DEFAULT_LIDAR_RANGE_NOISE_M`]. The
    /// uncertainty's depth noise model, and what a held-out return's residual is allowed beyond the
    /// field's own error.
    pub lidar_range_noise_m: f64,
    /// The integer downscale the images were loaded at (1 = full size): what a later pass over the same
    /// field (`silvr uncertainty`) must load again to see the pixels it was trained on.
    pub downscale: u32,
}

/// Lidar range noise (1 σ, metres) assumed when a dataset does not state its own: the datasheet figure
/// of the spinning lidars mapping rigs carry (Hesai QT64/XT32, Ouster OS0/OS1, Velodyne VLP-16: ±2–3 cm).
pub const DEFAULT_LIDAR_RANGE_NOISE_M: f64 = 0.02;

/// One lidar return in this many, chosen by a hash of (image, pixel), is held out of training: the
/// uncertainty is calibrated on them ([`TrainData::held_out_returns`]), never on ground truth. A hash
/// rather than a grid, so held-out returns are scattered over every surface and range.
pub const HELD_OUT_RETURN_EVERY: u64 = 16;

/// Whether pixel `pixel` of image `image` is a held-out lidar return (when it has a return at all).
pub fn is_held_out_return(image: usize, pixel: usize) -> bool {
    // SplitMix64's finaliser: neighbouring pixels land in unrelated buckets.
    let mut z = ((image as u64) << 32 ^ pixel as u64).wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    z.is_multiple_of(HELD_OUT_RETURN_EVERY)
}

/// Options for [`TrainData::load`].
#[derive(Clone, Debug, Default)]
pub struct LoadOptions {
    /// Integer downscale of every image (1 = full size).
    pub downscale: u32,
    /// Ignore lidar depth / normal / sky images (vision-only training loads faster).
    pub skip_lidar: bool,
}

pub use crate::dataset::resize_rgb;

/// Lidar depth (and the normals of the same returns) downscaled by `f`: each output pixel takes the lidar
/// return of its f×f block nearest the block's centre, sky where the block has only sky, none otherwise.
/// Depth is never averaged across edges, and unlike a nearest-neighbour pick of one fixed pixel per block
/// this keeps nearly every return of a sparse lidar image (at f = 2 the fixed pick kept a quarter, and all
/// of them half a full-size pixel off the ray's centre in both axes, a bias on surfaces seen at grazing
/// angles such as the road).
fn resize_lidar(
    depth: Vec<u16>,
    normals: Vec<[u8; 3]>,
    w: u32,
    h: u32,
    f: u32,
) -> (Vec<u16>, Vec<[u8; 3]>) {
    if f <= 1 || depth.is_empty() {
        return (depth, resize_nearest(normals, w, h, f));
    }
    let (nw, nh) = (w / f, h / f);
    let with_normals = normals.len() == depth.len();
    let mut d_out = Vec::with_capacity((nw * nh) as usize);
    let mut n_out = Vec::with_capacity(if with_normals { d_out.capacity() } else { 0 });
    // Offsets from the block's centre in doubled units, (2i + 1 − f), so the centre is exact for even f.
    for y in 0..nh {
        for x in 0..nw {
            let mut best: Option<(u32, usize)> = None;
            let mut sky = false;
            for j in 0..f {
                for i in 0..f {
                    let p = ((y * f + j) * w + x * f + i) as usize;
                    match depth[p] {
                        0 => {}
                        SKY_DEPTH => sky = true,
                        _ => {
                            let (dx, dy) = ((2 * i + 1).abs_diff(f), (2 * j + 1).abs_diff(f));
                            let r2 = dx * dx + dy * dy;
                            if best.is_none_or(|(b, _)| r2 < b) {
                                best = Some((r2, p));
                            }
                        }
                    }
                }
            }
            match best {
                Some((_, p)) => {
                    d_out.push(depth[p]);
                    if with_normals {
                        n_out.push(normals[p]);
                    }
                }
                None => {
                    d_out.push(if sky { SKY_DEPTH } else { 0 });
                    if with_normals {
                        n_out.push(NO_NORMAL);
                    }
                }
            }
        }
    }
    if !with_normals {
        n_out = resize_nearest(normals, w, h, f);
    }
    (d_out, n_out)
}

/// Nearest-neighbour downscale (normals, masks must not be averaged across edges).
pub fn resize_nearest<T: Copy>(px: Vec<T>, w: u32, h: u32, f: u32) -> Vec<T> {
    if f <= 1 || px.is_empty() {
        return px;
    }
    let (nw, nh) = (w / f, h / f);
    let mut out = Vec::with_capacity((nw * nh) as usize);
    for y in 0..nh {
        for x in 0..nw {
            out.push(px[((y * f + f / 2) * w + x * f + f / 2) as usize]);
        }
    }
    out
}

impl TrainData {
    /// Loads `dataset`: a folder holding transforms.json, the JSON itself, or a `silvr pack` archive. A
    /// folder's files must lie inside it ([`crate::source::Dir`]).
    pub fn load(dataset: &Path, opts: &LoadOptions) -> Result<TrainData, DataError> {
        Self::load_within(dataset, None, opts)
    }

    /// [`Self::load`], with a folder's files allowed anywhere under `root` (an ancestor of the folder):
    /// silvr's submap and poses outputs name their world's images `../../dataset/images/…`.
    pub fn load_within(
        dataset: &Path,
        root: Option<&Path>,
        opts: &LoadOptions,
    ) -> Result<TrainData, DataError> {
        let (src, json) = crate::source::open_within(dataset, root)?;
        Self::load_from(src.as_ref(), &json, opts)
    }

    /// Loads the dataset whose `transforms.json` is `json` in `src` (a folder natively; dropped files or
    /// an archive in the studio): one loader, one set of errors, each naming the file.
    pub fn load_from(
        src: &dyn Source,
        json_rel: &str,
        opts: &LoadOptions,
    ) -> Result<TrainData, DataError> {
        let json = src.path(json_rel);
        let root = src.root();
        let text = src.read(json_rel)?;
        let text = std::str::from_utf8(&text)
            .map_err(|_| bad(&json, "is not UTF-8 text (a JSON file was expected)"))?;
        let (frames, train_names, val_names) = dataset::parse_frames(text, &json)?;
        if frames.is_empty() {
            return Err(bad(&json, "no frames"));
        }
        let f = opts.downscale.max(1);
        let mut skipped = Vec::new();
        let mut kept = Vec::new();
        for fr in frames {
            if !src.exists(&fr.file_path) {
                skipped.push(format!("{}: image file missing", fr.file_path));
                continue;
            }
            let (model, pose) = fr.camera(&json)?;
            kept.push((fr, model, pose));
        }
        if kept.is_empty() {
            return Err(bad(&json, "none of the frames' image files exist"));
        }
        // Scene frame from the camera centres.
        let n = kept.len() as f64;
        let center = kept.iter().fold(DVec3::ZERO, |a, (_, _, p)| a + p.trans) / n;
        let extent = kept
            .iter()
            .map(|(_, _, p)| (p.trans - center).abs().max_element())
            .fold(0.0f64, f64::max);
        let scale = if extent > 1e-9 { 1.0 / extent } else { 1.0 };
        let frame = SceneFrame {
            center: center.to_array(),
            scale,
        };
        // Split: the file's lists when given, else every 10th frame held out (nerfstudio's fraction 0.9).
        let is_val = |i: usize, name: &str| {
            if !val_names.is_empty() || !train_names.is_empty() {
                val_names.iter().any(|v| v == name)
            } else {
                kept.len() >= 5 && i % 10 == 5
            }
        };
        let mut cameras: Vec<CameraModel> = Vec::new();
        let mut images = Vec::with_capacity(kept.len());
        let mut train = Vec::new();
        let mut val = Vec::new();
        let loaded: Vec<Result<_, DataError>> = kept
            .par_iter()
            .map(|(fr, model, _)| load_pixels(src, fr, model, f, opts.skip_lidar))
            .collect();
        for (i, ((fr, model, pose), px)) in kept.iter().zip(loaded).enumerate() {
            let (rgb, depth, normals, sky, w, h) = px?;
            let model = model.downscaled(f);
            let camera = match cameras.iter().position(|c| *c == model) {
                Some(c) => c,
                None => {
                    cameras.push(model);
                    cameras.len() - 1
                }
            };
            let held_out = is_val(i, &fr.file_path);
            let appearance = if held_out {
                val.push(i);
                None
            } else {
                train.push(i);
                Some(train.len() as u32 - 1)
            };
            images.push(Image {
                name: fr.file_path.clone(),
                width: w,
                height: h,
                camera,
                rotation: DMat3::from_quat(pose.rot),
                origin: frame.to_scene(pose.trans),
                rgb,
                depth,
                normals,
                sky,
                appearance,
            });
        }
        if train.is_empty() {
            return Err(bad(&json, "every frame is held out; nothing to train on"));
        }
        let directions = cameras.par_iter().map(direction_table).collect();
        let lidar_range_noise_m = lidar_range_noise(src);
        Ok(TrainData {
            root,
            frame,
            images,
            directions,
            cameras,
            train,
            val,
            skipped,
            lidar_range_noise_m,
            downscale: opts.downscale.max(1),
        })
    }

    /// Adds a view to render that is neither trained on nor held out (a camera path's pose, say): camera
    /// `model` at `pose` (camera to world, OpenCV axes, the dataset's metric frame), its photo `rgb`
    /// (row-major, the model's size; black when there is none). Returns its image index.
    pub fn add_view(
        &mut self,
        name: &str,
        model: &CameraModel,
        pose: &crate::geometry::Se3,
        rgb: Vec<[u8; 3]>,
    ) -> Result<usize, DataError> {
        let n = (model.width * model.height) as usize;
        if rgb.len() != n {
            return Err(bad(
                &self.root,
                format!(
                    "view {name}: {} pixels for a {}x{} camera",
                    rgb.len(),
                    model.width,
                    model.height
                ),
            ));
        }
        let camera = match self.cameras.iter().position(|c| c == model) {
            Some(c) => c,
            None => {
                self.cameras.push(*model);
                self.directions.push(direction_table(model));
                self.cameras.len() - 1
            }
        };
        self.images.push(Image {
            name: name.to_string(),
            width: model.width,
            height: model.height,
            camera,
            rotation: DMat3::from_quat(pose.rot),
            origin: self.frame.to_scene(pose.trans),
            rgb,
            depth: Vec::new(),
            normals: Vec::new(),
            sky: Vec::new(),
            appearance: None,
        });
        Ok(self.images.len() - 1)
    }

    /// Whether any training image has lidar depth.
    pub fn has_lidar(&self) -> bool {
        self.train.iter().any(|&i| !self.images[i].depth.is_empty())
    }

    /// The ray through pixel (x, y) of image `i` (scene frame, unit direction), or `None` where the
    /// camera has no ray.
    pub fn ray(&self, i: usize, x: u32, y: u32) -> Option<([f32; 3], [f32; 3])> {
        let im = &self.images[i];
        let d = self.directions[im.camera][(y * im.width + x) as usize];
        if !d[0].is_finite() {
            return None;
        }
        let dw = im.rotation * DVec3::new(d[0] as f64, d[1] as f64, d[2] as f64);
        Some((im.origin.as_vec3().to_array(), dw.as_vec3().to_array()))
    }

    /// The lidar returns held out of training ([`is_held_out_return`]) on the training images: (image,
    /// pixel) in image order. Their depth and normal never reach a loss; the uncertainty is calibrated on
    /// them.
    pub fn held_out_returns(&self) -> Vec<(usize, u32)> {
        let mut out = Vec::new();
        for &i in &self.train {
            for (p, &d) in self.images[i].depth.iter().enumerate() {
                if d > 0 && d != SKY_DEPTH && is_held_out_return(i, p) {
                    out.push((i, p as u32));
                }
            }
        }
        out
    }

    /// The lidar range of pixel `p` of image `i` in scene units, when it has a return (held out or not).
    pub fn lidar_range(&self, i: usize, p: usize) -> Option<f32> {
        match self.images[i].depth.get(p) {
            Some(&d) if d > 0 && d != SKY_DEPTH => {
                Some((d as f64 / 256.0 * self.frame.scale) as f32)
            }
            _ => None,
        }
    }

    /// The lidar normal of pixel `p` of image `i` in the scene frame (unit), when it has one.
    pub fn lidar_normal(&self, i: usize, p: usize) -> Option<DVec3> {
        let im = &self.images[i];
        let n = *im.normals.get(p)?;
        if n == NO_NORMAL {
            return None;
        }
        let nc = DVec3::from(n.map(|v| v as f64 / 255.0 * 2.0 - 1.0));
        (nc.length() > 0.5).then(|| im.rotation * nc.normalize())
    }

    /// The supervision of pixel (x, y) of image `i`, depths in scene units. Held-out lidar returns
    /// ([`is_held_out_return`]) supervise colour only.
    pub fn target(&self, i: usize, x: u32, y: u32) -> RayTarget {
        let im = &self.images[i];
        let p = (y * im.width + x) as usize;
        let c = im.rgb[p];
        let mut t = RayTarget {
            rgb: c.map(|v| v as f32 / 255.0),
            ..Default::default()
        };
        if let Some(&d) = im.depth.get(p) {
            if d == SKY_DEPTH {
                t.sky = 1;
            } else if d > 0 && !is_held_out_return(i, p) {
                t.depth = (d as f64 / 256.0 * self.frame.scale) as f32;
            }
        }
        if im.sky.get(p).is_some_and(|&s| s > 127) && t.depth <= 0.0 {
            t.sky = 1;
        }
        if t.depth > 0.0 {
            if let Some(n) = self.lidar_normal(i, p) {
                t.normal = n.as_vec3().to_array();
            }
        }
        t
    }
}

/// `range_noise` (metres) of the dataset's `calib/lidar.json` when it states a positive one.
fn lidar_range_noise(src: &dyn Source) -> f64 {
    let stated = src
        .exists("calib/lidar.json")
        .then(|| src.read("calib/lidar.json").ok())
        .flatten()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .and_then(|v| v["range_noise"].as_f64())
        .filter(|s| s.is_finite() && *s > 0.0 && *s < 10.0);
    stated.unwrap_or(DEFAULT_LIDAR_RANGE_NOISE_M)
}

type Pixels = (Vec<[u8; 3]>, Vec<u16>, Vec<[u8; 3]>, Vec<u8>, u32, u32);

fn load_pixels(
    src: &dyn Source,
    fr: &NsFrame,
    model: &CameraModel,
    f: u32,
    skip_lidar: bool,
) -> Result<Pixels, DataError> {
    let path = src.path(&fr.file_path);
    let img = image::load_from_memory(&src.read(&fr.file_path)?)
        .map_err(|e| bad(&path, format!("cannot read image: {e}")))?
        .to_rgb8();
    let (w, h) = img.dimensions();
    if (w, h) != (model.width, model.height) {
        return Err(bad(
            &path,
            format!(
                "image is {w}x{h} but transforms.json says {}x{}",
                model.width, model.height
            ),
        ));
    }
    if w / f < 8 || h / f < 8 {
        return Err(bad(
            &path,
            format!("downscale {f} leaves too small an image"),
        ));
    }
    let rgb: Vec<[u8; 3]> = img.pixels().map(|p| p.0).collect();
    let check = |p: &Path, (iw, ih): (u32, u32)| {
        if (iw, ih) != (w, h) {
            Err(bad(p, format!("is {iw}x{ih}, its image is {w}x{h}")))
        } else {
            Ok(())
        }
    };
    let (mut depth, mut normals, mut sky) = (Vec::new(), Vec::new(), Vec::new());
    if !skip_lidar {
        if let Some(rel) = &fr.depth_file_path {
            let p = src.path(rel);
            let (dw, dh, d) = dataset::decode_png16(&src.read(rel)?, &p)?;
            check(&p, (dw, dh))?;
            depth = d;
        }
        if let Some(rel) = &fr.normal_file_path {
            let p = src.path(rel);
            let (nw, nh, n) = dataset::decode_rgb(&src.read(rel)?, &p)?;
            check(&p, (nw, nh))?;
            normals = n;
        }
        if let Some(rel) = &fr.sky_mask_path {
            let p = src.path(rel);
            let (sw, sh, s) = dataset::decode_gray8(&src.read(rel)?, &p)?;
            check(&p, (sw, sh))?;
            sky = s;
        }
    }
    let (depth, normals) = resize_lidar(depth, normals, w, h, f);
    Ok((
        resize_rgb(rgb, w, h, f),
        depth,
        normals,
        resize_nearest(sky, w, h, f),
        w / f.max(1),
        h / f.max(1),
    ))
}

/// What `silvr pack` puts in an archive: `transforms.json`, every frame's image, lidar depth, normals and
/// sky mask (what training reads), and the small files that say what the data is (`manifest.json`,
/// `calib/rig.json`, `calib/lidar.json`). Raw sweeps and ground truth stay out (they are most of a
/// dataset's bytes and training does not read them). A frame whose image is missing is left out and
/// named in the second value (the loader skips such frames too, as nerfstudio captures often list more
/// images than they ship); a missing lidar file of a present image is an error naming it.
///
/// With `downscale` f > 1 every image is stored as the loader would read it at that downscale (colour
/// averaged over f×f blocks, lidar depth and normals from the return nearest each block's centre, sky
/// masks by nearest neighbour) and the intrinsics in `transforms.json` are rewritten to match
/// ([`CameraModel::downscaled`]), so the archive loaded as it is equals the folder loaded at f: a
/// smaller download for the studio, and the same training. PNG files stay PNG (lossless); JPEG
/// images are re-encoded as JPEG at quality 95.
pub fn pack(
    src: &dyn Source,
    json_rel: &str,
    downscale: u32,
) -> Result<(Files, Vec<String>), DataError> {
    let json_path = src.path(json_rel);
    let text = src.read(json_rel)?;
    let text = std::str::from_utf8(&text)
        .map_err(|_| bad(&json_path, "is not UTF-8 text (a JSON file was expected)"))?;
    let (frames, _, _) = dataset::parse_frames(text, &json_path)?;
    let f = downscale.max(1);
    let mut out = Files::new(src.root().display().to_string());
    let mut skipped = Vec::new();
    let outside = |rel: &str| {
        bad(
            &json_path,
            format!("{rel}: points outside the dataset folder; pack copies only files inside it"),
        )
    };
    for fr in &frames {
        if !src.exists(&fr.file_path) {
            skipped.push(format!("{}: image file missing", fr.file_path));
            continue;
        }
        if f == 1 {
            let paths = [
                Some(&fr.file_path),
                fr.depth_file_path.as_ref(),
                fr.normal_file_path.as_ref(),
                fr.sky_mask_path.as_ref(),
            ];
            for rel in paths.into_iter().flatten() {
                let bytes = src.read(rel)?.into_owned();
                out.insert(rel, bytes).map_err(|_| outside(rel))?;
            }
            continue;
        }
        let (model, _) = fr.camera(&json_path)?;
        let (rgb, depth, normals, sky, w, h) = load_pixels(src, fr, &model, f, false)?;
        let jpeg = {
            let l = fr.file_path.to_ascii_lowercase();
            l.ends_with(".jpg") || l.ends_with(".jpeg")
        };
        let image = if jpeg {
            jpeg_rgb(w, h, &rgb)
        } else {
            dataset::png_rgb(w, h, &rgb)
        };
        let files = [
            (Some(&fr.file_path), Some(image)),
            (
                fr.depth_file_path.as_ref(),
                (!depth.is_empty()).then(|| dataset::png_gray16(w, h, &depth)),
            ),
            (
                fr.normal_file_path.as_ref(),
                (!normals.is_empty()).then(|| dataset::png_rgb(w, h, &normals)),
            ),
            (
                fr.sky_mask_path.as_ref(),
                (!sky.is_empty()).then(|| dataset::png_gray8(w, h, &sky)),
            ),
        ];
        for (rel, bytes) in files {
            if let (Some(rel), Some(bytes)) = (rel, bytes) {
                out.insert(rel, bytes).map_err(|_| outside(rel))?;
            }
        }
    }
    if skipped.len() == frames.len() {
        return Err(bad(&json_path, "none of the frames' image files exist"));
    }
    let json = if f == 1 {
        text.as_bytes().to_vec()
    } else {
        downscale_intrinsics(text, f, &json_path)?
    };
    out.insert("transforms.json", json)?;
    for extra in ["manifest.json", "calib/rig.json", "calib/lidar.json"] {
        if src.exists(extra) {
            out.insert(extra, src.read(extra)?.into_owned())?;
        }
    }
    Ok((out, skipped))
}

/// `transforms.json` with every intrinsic (top level and per frame) rewritten for images downscaled by
/// `f` ([`CameraModel::downscaled`]); everything else as it was.
fn downscale_intrinsics(text: &str, f: u32, path: &Path) -> Result<Vec<u8>, DataError> {
    use serde_json::Value;
    let mut root: Value =
        serde_json::from_str(text).map_err(|e| bad(path, format!("not JSON: {e}")))?;
    let s = 1.0 / f as f64;
    let scale = |o: &mut serde_json::Map<String, Value>| {
        for (k, v) in o.iter_mut() {
            let Some(x) = v.as_f64() else { continue };
            // nerfstudio's principal point counts from the pixel's corner (ours from its centre, so
            // the centre-based `(c + 0.5) / f − 0.5` is a plain division here).
            let new = match k.as_str() {
                "fl_x" | "fl_y" | "cx" | "cy" => Value::from(x * s),
                "w" | "h" => Value::from((x.round() as u64 / f as u64).max(1)),
                _ => continue,
            };
            *v = new;
        }
    };
    if let Some(o) = root.as_object_mut() {
        scale(o);
        if let Some(frames) = o.get_mut("frames").and_then(Value::as_array_mut) {
            for fr in frames.iter_mut().filter_map(Value::as_object_mut) {
                scale(fr);
            }
        }
        o.insert("downscale".into(), Value::from(f));
    }
    Ok(serde_json::to_vec_pretty(&root).expect("a JSON value serialises"))
}

/// Encodes an RGB image as JPEG at quality 95 (for JPEG sources packed downscaled).
fn jpeg_rgb(w: u32, h: u32, px: &[[u8; 3]]) -> Vec<u8> {
    let flat: Vec<u8> = px.iter().flatten().copied().collect();
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 95)
        .encode(&flat, w, h, image::ExtendedColorType::Rgb8)
        .expect("in-memory JPEG encoding of a correctly sized buffer cannot fail");
    out
}

/// Unit ray directions of every pixel centre (OpenCV convention), NaN where unprojection fails.
pub fn direction_table(model: &CameraModel) -> Vec<[f32; 3]> {
    let angle = model.valid_angle();
    (0..model.height)
        .into_par_iter()
        .flat_map_iter(|y| {
            (0..model.width).map(move |x| {
                model
                    .unproject_within(DVec2::new(x as f64, y as f64), angle)
                    .map_or([f32::NAN; 3], |d| d.normalize().as_vec3().to_array())
            })
        })
        .collect()
}

/// `Se3` of a camera in the scene frame, for renders of arbitrary views.
pub fn scene_pose(frame: &SceneFrame, t_world_cam: &Se3) -> (DMat3, DVec3) {
    (
        DMat3::from_quat(t_world_cam.rot),
        frame.to_scene(t_world_cam.trans),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sparse lidar image keeps every return a block holds, the one nearest the block's centre wins,
    /// normals follow their depth, and sky only marks blocks without a return.
    #[test]
    fn lidar_downscale_keeps_returns_nearest_the_centre() {
        let (w, h, f) = (6u32, 3u32, 3u32);
        let mut depth = vec![0u16; (w * h) as usize];
        let mut normals = vec![NO_NORMAL; depth.len()];
        let at = |x: u32, y: u32| (y * w + x) as usize;
        // Block 0: a corner return and the centre return; the centre wins.
        depth[at(0, 0)] = 100;
        normals[at(0, 0)] = [1, 1, 1];
        depth[at(1, 1)] = 200;
        normals[at(1, 1)] = [2, 2, 2];
        // Block 1: one return in a corner (a fixed centre pick would lose it) and sky elsewhere.
        depth[at(5, 2)] = 300;
        normals[at(5, 2)] = [3, 3, 3];
        depth[at(3, 0)] = SKY_DEPTH;
        let (d, n) = resize_lidar(depth.clone(), normals.clone(), w, h, f);
        assert_eq!(d, vec![200, 300]);
        assert_eq!(n, vec![[2, 2, 2], [3, 3, 3]]);
        // Without the return, block 1 is sky; without anything, block 0 is empty.
        depth[at(5, 2)] = 0;
        for p in [at(0, 0), at(1, 1)] {
            depth[p] = 0;
        }
        let (d, n) = resize_lidar(depth, normals, w, h, f);
        assert_eq!(d, vec![0, SKY_DEPTH]);
        assert_eq!(n, vec![NO_NORMAL, NO_NORMAL]);
    }

    /// Even factors have no centre pixel: the four central pixels tie and the first is taken, so every
    /// return of a 2×2 block survives whichever pixel it sits on.
    #[test]
    fn lidar_downscale_by_two_keeps_a_return_anywhere_in_the_block() {
        for k in 0..4u32 {
            let mut depth = vec![0u16; 4];
            depth[k as usize] = 500 + k as u16;
            let (d, n) = resize_lidar(depth, Vec::new(), 2, 2, 2);
            assert_eq!(d, vec![500 + k as u16]);
            assert!(n.is_empty());
        }
    }
}
