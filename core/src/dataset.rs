//! The project's dataset layout on disk: what the synthetic world writes and what ingest of real data
//! writes, and what training and evaluation read. Documented in `DATASET.md`.
//!
//! A dataset is assembled in a temporary sibling folder and renamed into place at the end, so a crash or an
//! error never leaves half a dataset under the requested name.

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use glam::{DMat4, DQuat, DVec3};
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::camera::{opencv_to_opengl_c2w, CameraModel, Distortion};
use crate::geometry::{Se3, Trajectory};

/// Layout version written to the manifest.
pub const LAYOUT_VERSION: u32 = 1;

/// Errors reading or writing a dataset; every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {detail}")]
    Format { path: PathBuf, detail: String },
    #[error("{path}: already exists (choose another --out or remove it)")]
    Exists { path: PathBuf },
}

pub(crate) fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> DatasetError + '_ {
    move |source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn fmt_err(path: &Path, detail: impl Into<String>) -> DatasetError {
    DatasetError::Format {
        path: path.to_path_buf(),
        detail: detail.into(),
    }
}

/// The per-frame file keys of a transforms.json: image, lidar depth, normals, sky mask.
pub const FRAME_FILE_KEYS: [&str; 4] = [
    "file_path",
    "depth_file_path",
    "normal_file_path",
    "sky_mask_path",
];

/// `prefix` + `path` for a relative path (the way from another folder back to the file); an absolute path
/// already reaches its file and is returned as it is.
pub fn prefixed(prefix: &str, path: &str) -> String {
    if Path::new(path).is_absolute() {
        path.to_string()
    } else {
        format!("{prefix}{path}")
    }
}

/// A frame's `transform_matrix` (nerfstudio: camera → world, OpenGL axes, rows) of an OpenCV-axes
/// `T_world_cam`.
pub fn transform_matrix_rows(t_world_cam: &Se3) -> [[f64; 4]; 4] {
    let m: DMat4 = opencv_to_opengl_c2w(t_world_cam.to_mat4());
    [m.row(0), m.row(1), m.row(2), m.row(3)].map(|r| r.to_array())
}

/// Every file path of one frame of a transforms.json ([`FRAME_FILE_KEYS`]) [`prefixed`].
pub fn prefix_frame_paths(frame: &mut serde_json::Map<String, Value>, prefix: &str) {
    for k in FRAME_FILE_KEYS {
        if let Some(p) = frame.get(k).and_then(Value::as_str).map(String::from) {
            frame.insert(k.into(), Value::from(prefixed(prefix, &p)));
        }
    }
}

/// Writes `bytes` to `path` through a temporary file in the same folder and a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), DatasetError> {
    if let Some(dir) = path.parent() {
        fs::create_dir_all(dir).map_err(io_err(dir))?;
    }
    let tmp = path.with_extension(format!("tmp-{}", std::process::id()));
    {
        let mut f = fs::File::create(&tmp).map_err(io_err(&tmp))?;
        f.write_all(bytes).map_err(io_err(&tmp))?;
        f.sync_all().ok();
    }
    fs::rename(&tmp, path).map_err(io_err(path))
}

/// A dataset folder being written: everything goes under `staging` until [`DatasetWriter::commit`]. Every
/// file written is remembered with its size, for the manifest ([`DatasetWriter::files`]).
pub struct DatasetWriter {
    pub target: PathBuf,
    pub staging: PathBuf,
    committed: bool,
    files: std::cell::RefCell<std::collections::BTreeMap<String, u64>>,
}

impl DatasetWriter {
    /// Prepares to write `target`, which must not exist yet unless `overwrite`.
    pub fn create(target: &Path, overwrite: bool) -> Result<Self, DatasetError> {
        if target.exists() && !overwrite {
            return Err(DatasetError::Exists {
                path: target.to_path_buf(),
            });
        }
        let name = target
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_else(|| "dataset".into());
        let staging = target.with_file_name(format!(".{name}.partial-{}", std::process::id()));
        // Staging folders of earlier runs that were killed (no chance to clean up) go first.
        let prefix = format!(".{name}.partial-");
        let parent = match target.parent() {
            Some(p) if !p.as_os_str().is_empty() => p,
            _ => Path::new("."),
        };
        if parent.is_dir() {
            for entry in fs::read_dir(parent).map_err(io_err(parent))?.flatten() {
                if entry.file_name().to_string_lossy().starts_with(&prefix) {
                    let p = entry.path();
                    fs::remove_dir_all(&p).map_err(io_err(&p))?;
                }
            }
        }
        fs::create_dir_all(&staging).map_err(io_err(&staging))?;
        Ok(Self {
            target: target.to_path_buf(),
            staging,
            committed: false,
            files: Default::default(),
        })
    }

    /// Absolute path of a dataset-relative file in the staging folder.
    pub fn path(&self, rel: &str) -> PathBuf {
        self.staging.join(rel)
    }

    /// Writes a dataset-relative file.
    pub fn write(&self, rel: &str, bytes: &[u8]) -> Result<(), DatasetError> {
        let p = self.path(rel);
        if let Some(dir) = p.parent() {
            fs::create_dir_all(dir).map_err(io_err(dir))?;
        }
        fs::write(&p, bytes).map_err(io_err(&p))?;
        self.files
            .borrow_mut()
            .insert(rel.to_string(), bytes.len() as u64);
        Ok(())
    }

    /// Records a dataset-relative file written in place at [`Self::path`] by a streaming writer (a file
    /// too large to hold in memory first), with its size.
    pub fn written(&self, rel: &str) -> Result<(), DatasetError> {
        let p = self.path(rel);
        let len = fs::metadata(&p).map_err(io_err(&p))?.len();
        self.files.borrow_mut().insert(rel.to_string(), len);
        Ok(())
    }

    /// Writes `value` as pretty-printed JSON (dataset files hold plain data, which always serialises).
    pub fn write_json(&self, rel: &str, value: &impl Serialize) -> Result<(), DatasetError> {
        let text = serde_json::to_string_pretty(value).expect("plain data serialises");
        self.write(rel, text.as_bytes())
    }

    /// The pose files of every dataset (TUM text): `poses/{base,lidar}_tum.txt` and `poses/<camera>_tum.txt`
    /// (`cameras[i]` for `rig.cameras[i]`) at the keyframe `times`, the trajectory they were taken from,
    /// `poses/odometry_lidar_tum.txt`, and the rig they were taken with, `calib/rig.json`.
    pub fn write_poses(
        &self,
        times: &[f64],
        base: &[Se3],
        lidar: &[Se3],
        rig: &crate::rig::Rig,
        cameras: &[Vec<Se3>],
        odometry: &Trajectory,
    ) -> Result<(), DatasetError> {
        self.write("poses/base_tum.txt", tum_string(times, base).as_bytes())?;
        self.write("poses/lidar_tum.txt", tum_string(times, lidar).as_bytes())?;
        self.write(
            "poses/odometry_lidar_tum.txt",
            tum_string(odometry.stamps(), odometry.poses()).as_bytes(),
        )?;
        for (cam, poses) in rig.cameras.iter().zip(cameras) {
            self.write(
                &format!("poses/{}_tum.txt", cam.name),
                tum_string(times, poses).as_bytes(),
            )?;
        }
        self.write_json("calib/rig.json", rig)
    }

    /// Every file written so far (dataset-relative path → bytes).
    pub fn files(&self) -> std::collections::BTreeMap<String, u64> {
        self.files.borrow().clone()
    }

    /// Moves the finished dataset into place (replacing an old one when overwriting was allowed).
    pub fn commit(mut self) -> Result<PathBuf, DatasetError> {
        if self.target.exists() {
            fs::remove_dir_all(&self.target).map_err(io_err(&self.target))?;
        }
        fs::rename(&self.staging, &self.target).map_err(io_err(&self.target))?;
        self.committed = true;
        Ok(self.target.clone())
    }
}

impl Drop for DatasetWriter {
    fn drop(&mut self) {
        if !self.committed {
            let _ = fs::remove_dir_all(&self.staging);
        }
    }
}

/// Encodes an 8-bit RGB PNG.
pub fn png_rgb(width: u32, height: u32, px: &[[u8; 3]]) -> Vec<u8> {
    let flat: Vec<u8> = px.iter().flatten().copied().collect();
    encode_png(width, height, image::ExtendedColorType::Rgb8, &flat)
}

/// Encodes an 8-bit single-channel PNG.
pub fn png_gray8(width: u32, height: u32, px: &[u8]) -> Vec<u8> {
    encode_png(width, height, image::ExtendedColorType::L8, px)
}

/// Encodes a 16-bit single-channel PNG.
pub fn png_gray16(width: u32, height: u32, px: &[u16]) -> Vec<u8> {
    // PNG stores 16-bit samples big-endian; the encoder takes native-endian bytes.
    let bytes: Vec<u8> = px.iter().flat_map(|v| v.to_ne_bytes()).collect();
    encode_png(width, height, image::ExtendedColorType::L16, &bytes)
}

fn encode_png(width: u32, height: u32, color: image::ExtendedColorType, data: &[u8]) -> Vec<u8> {
    use image::ImageEncoder;
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(data, width, height, color)
        .expect("in-memory PNG encoding of a correctly sized buffer cannot fail");
    out
}

/// Reads a 16-bit PNG (depth images).
pub fn read_png16(path: &Path) -> Result<(u32, u32, Vec<u16>), DatasetError> {
    decode_png16(&fs::read(path).map_err(io_err(path))?, path)
}

/// An image decoded from bytes (`path` names them in errors), its format found from its first bytes.
fn decode(bytes: &[u8], path: &Path, what: &str) -> Result<image::DynamicImage, DatasetError> {
    image::load_from_memory(bytes).map_err(|e| fmt_err(path, format!("not a readable {what}: {e}")))
}

/// [`read_png16`] of bytes already read.
pub fn decode_png16(bytes: &[u8], path: &Path) -> Result<(u32, u32, Vec<u16>), DatasetError> {
    let img = decode(bytes, path, "PNG")?;
    match img {
        image::DynamicImage::ImageLuma16(b) => Ok((b.width(), b.height(), b.into_raw())),
        other => Err(fmt_err(
            path,
            format!("expected a 16-bit grey PNG, found {:?}", other.color()),
        )),
    }
}

/// Reads an 8-bit RGB image (PNG or JPEG), converting grey or RGBA.
pub fn read_rgb(path: &Path) -> Result<(u32, u32, Vec<[u8; 3]>), DatasetError> {
    decode_rgb(&fs::read(path).map_err(io_err(path))?, path)
}

/// [`read_rgb`] of bytes already read.
pub fn decode_rgb(bytes: &[u8], path: &Path) -> Result<(u32, u32, Vec<[u8; 3]>), DatasetError> {
    let img = decode(bytes, path, "image")?;
    let b = img.to_rgb8();
    let (w, h) = (b.width(), b.height());
    Ok((
        w,
        h,
        b.into_raw()
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect(),
    ))
}

/// Reads an 8-bit grey PNG (masks, labels).
pub fn read_gray8(path: &Path) -> Result<(u32, u32, Vec<u8>), DatasetError> {
    decode_gray8(&fs::read(path).map_err(io_err(path))?, path)
}

/// [`read_gray8`] of bytes already read.
pub fn decode_gray8(bytes: &[u8], path: &Path) -> Result<(u32, u32, Vec<u8>), DatasetError> {
    let img = decode(bytes, path, "image")?;
    match img {
        image::DynamicImage::ImageLuma8(b) => Ok((b.width(), b.height(), b.into_raw())),
        other => Err(fmt_err(
            path,
            format!("expected an 8-bit grey PNG, found {:?}", other.color()),
        )),
    }
}

/// TUM trajectory text: `t tx ty tz qx qy qz qw` per line.
pub fn tum_string(stamps: &[f64], poses: &[Se3]) -> String {
    let mut s = String::from("# timestamp tx ty tz qx qy qz qw\n");
    for (t, p) in stamps.iter().zip(poses) {
        let q = p.rot;
        s.push_str(&format!(
            "{t:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}\n",
            p.trans.x, p.trans.y, p.trans.z, q.x, q.y, q.z, q.w
        ));
    }
    s
}

/// Parses a TUM trajectory; errors name the file and line.
pub fn read_tum(path: &Path) -> Result<Trajectory, DatasetError> {
    let text = fs::read_to_string(path).map_err(io_err(path))?;
    parse_tum(&text, path)
}

/// Parses TUM text (see [`read_tum`]); `path` is only used in errors.
pub fn parse_tum(text: &str, path: &Path) -> Result<Trajectory, DatasetError> {
    let mut stamps = Vec::new();
    let mut poses = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let v: Result<Vec<f64>, _> = line.split_whitespace().map(str::parse::<f64>).collect();
        let v = v.map_err(|e| fmt_err(path, format!("line {}: {e}", n + 1)))?;
        if v.len() != 8 || v.iter().any(|x| !x.is_finite()) {
            return Err(fmt_err(
                path,
                format!("line {}: expected 8 finite numbers", n + 1),
            ));
        }
        let q = DQuat::from_xyzw(v[4], v[5], v[6], v[7]);
        if q.length() < 1e-6 {
            return Err(fmt_err(path, format!("line {}: zero quaternion", n + 1)));
        }
        stamps.push(v[0]);
        poses.push(Se3::new(q.normalize(), DVec3::new(v[1], v[2], v[3])));
    }
    Trajectory::new(stamps, poses).map_err(|e| fmt_err(path, e.to_string()))
}

/// One frame of a nerfstudio `transforms.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct NsFrame {
    pub file_path: String,
    /// Camera-to-world, OpenGL camera axes (nerfstudio's convention).
    pub transform_matrix: [[f64; 4]; 4],
    pub fl_x: f64,
    pub fl_y: f64,
    /// nerfstudio/COLMAP pixel-centre convention: ours + 0.5.
    pub cx: f64,
    pub cy: f64,
    pub w: u32,
    pub h: u32,
    pub camera_model: String,
    #[serde(default)]
    pub k1: f64,
    #[serde(default)]
    pub k2: f64,
    #[serde(default)]
    pub k3: f64,
    #[serde(default)]
    pub k4: f64,
    #[serde(default)]
    pub p1: f64,
    #[serde(default)]
    pub p2: f64,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub depth_file_path: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub normal_file_path: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub sky_mask_path: Option<String>,
    /// Our extras: camera name and keyframe index, for joining with the rest of the dataset.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub camera: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub keyframe: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub time: Option<f64>,
}

impl NsFrame {
    /// A frame from our camera model and an OpenCV-axes `T_world_cam`.
    pub fn new(file_path: String, model: &CameraModel, t_world_cam: &Se3) -> NsFrame {
        let rows = transform_matrix_rows(t_world_cam);
        let (camera_model, k) = match model.distortion {
            Distortion::None => ("PINHOLE", [0.0; 6]),
            Distortion::RadTan { k1, k2, p1, p2, k3 } => ("OPENCV", [k1, k2, k3, 0.0, p1, p2]),
            Distortion::Fisheye { k1, k2, k3, k4 } => {
                ("OPENCV_FISHEYE", [k1, k2, k3, k4, 0.0, 0.0])
            }
        };
        NsFrame {
            file_path,
            transform_matrix: rows,
            fl_x: model.fx,
            fl_y: model.fy,
            cx: model.cx + 0.5,
            cy: model.cy + 0.5,
            w: model.width,
            h: model.height,
            camera_model: camera_model.into(),
            k1: k[0],
            k2: k[1],
            k3: k[2],
            k4: k[3],
            p1: k[4],
            p2: k[5],
            depth_file_path: None,
            normal_file_path: None,
            sky_mask_path: None,
            camera: None,
            keyframe: None,
            time: None,
        }
    }

    /// Our camera model (OpenCV pixel centres) and OpenCV-axes `T_world_cam`, back from the file's form.
    pub fn camera(&self, path: &Path) -> Result<(CameraModel, Se3), DatasetError> {
        let distortion = match self.camera_model.as_str() {
            "PINHOLE" | "SIMPLE_PINHOLE" => Distortion::None,
            "OPENCV" => Distortion::RadTan {
                k1: self.k1,
                k2: self.k2,
                p1: self.p1,
                p2: self.p2,
                k3: self.k3,
            },
            "OPENCV_FISHEYE" => Distortion::Fisheye {
                k1: self.k1,
                k2: self.k2,
                k3: self.k3,
                k4: self.k4,
            },
            other => {
                return Err(fmt_err(
                    path,
                    format!(
                        "frame {}: unsupported camera_model {other:?}",
                        self.file_path
                    ),
                ))
            }
        };
        let model = CameraModel {
            width: self.w,
            height: self.h,
            fx: self.fl_x,
            fy: self.fl_y,
            cx: self.cx - 0.5,
            cy: self.cy - 0.5,
            distortion,
        };
        model
            .validate()
            .map_err(|e| fmt_err(path, format!("frame {}: {e}", self.file_path)))?;
        let m = DMat4::from_cols_array_2d(&self.transform_matrix).transpose();
        let c2w = opencv_to_opengl_c2w(m);
        if !c2w.is_finite() {
            return Err(fmt_err(
                path,
                format!("frame {}: non-finite transform_matrix", self.file_path),
            ));
        }
        Ok((model, Se3::from_mat4(c2w)))
    }
}

/// Frames, training file names, validation file names (the lists empty when the file has none).
pub type FrameList = (Vec<NsFrame>, Vec<String>, Vec<String>);

/// Reads a transforms.json, filling per-frame intrinsics from the top level when a frame lacks them
/// (instant-ngp / nerfstudio single-camera files) and accepting w/h written as floats.
pub fn read_frames(path: &Path) -> Result<FrameList, DatasetError> {
    let text = fs::read_to_string(path).map_err(io_err(path))?;
    parse_frames(&text, path)
}

/// [`read_frames`] of text already read (`path` names it in errors): the studio reads dropped files.
pub fn parse_frames(text: &str, path: &Path) -> Result<FrameList, DatasetError> {
    let root: Value =
        serde_json::from_str(text).map_err(|e| fmt_err(path, format!("not JSON: {e}")))?;
    let frames = root
        .get("frames")
        .and_then(Value::as_array)
        .ok_or_else(|| fmt_err(path, "no \"frames\" array"))?;
    let shared = SHARED_INTRINSICS;
    let mut out = Vec::with_capacity(frames.len());
    for (i, f) in frames.iter().enumerate() {
        let mut f = f.clone();
        let obj = f
            .as_object_mut()
            .ok_or_else(|| fmt_err(path, format!("frame {i} is not an object")))?;
        for k in shared {
            if !obj.contains_key(k) {
                if let Some(v) = root.get(k) {
                    obj.insert(k.into(), v.clone());
                }
            }
        }
        obj.entry("camera_model")
            .or_insert_with(|| Value::from("OPENCV"));
        for k in ["w", "h"] {
            if let Some(v) = obj.get(k).and_then(Value::as_f64) {
                obj.insert(k.into(), Value::from(v.round() as u64));
            }
        }
        let frame: NsFrame =
            serde_json::from_value(f).map_err(|e| fmt_err(path, format!("frame {i}: {e}")))?;
        out.push(frame);
    }
    let list = |k: &str| -> Vec<String> {
        root.get(k)
            .and_then(Value::as_array)
            .map(|a| {
                a.iter()
                    .filter_map(|v| v.as_str().map(String::from))
                    .collect()
            })
            .unwrap_or_default()
    };
    Ok((out, list("train_filenames"), list("val_filenames")))
}

/// Frame keys nerfstudio single-camera files give once at the top level instead of per frame.
pub const SHARED_INTRINSICS: [&str; 13] = [
    "fl_x",
    "fl_y",
    "cx",
    "cy",
    "w",
    "h",
    "camera_model",
    "k1",
    "k2",
    "k3",
    "k4",
    "p1",
    "p2",
];

/// nerfstudio `transforms.json` with per-frame intrinsics.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Transforms {
    pub frames: Vec<NsFrame>,
    /// Depth PNG units: metres = value / 256 (Euclidean range).
    #[serde(default)]
    pub depth_unit_scale_factor: Option<f64>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub train_filenames: Vec<String>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub val_filenames: Vec<String>,
}

impl Transforms {
    pub fn read(path: &Path) -> Result<Transforms, DatasetError> {
        let text = fs::read_to_string(path).map_err(io_err(path))?;
        serde_json::from_str(&text)
            .map_err(|e| fmt_err(path, format!("not a valid transforms.json: {e}")))
    }
}

/// Colour downscaled by `f`: each output pixel the mean of an f×f block (what training reads at `--downscale`).
pub fn resize_rgb(px: Vec<[u8; 3]>, w: u32, h: u32, f: u32) -> Vec<[u8; 3]> {
    if f <= 1 {
        return px;
    }
    let (nw, nh) = (w / f, h / f);
    let mut out = Vec::with_capacity((nw * nh) as usize);
    for y in 0..nh {
        for x in 0..nw {
            let mut acc = [0u32; 3];
            for dy in 0..f {
                for dx in 0..f {
                    let p = px[((y * f + dy) * w + x * f + dx) as usize];
                    for c in 0..3 {
                        acc[c] += p[c] as u32;
                    }
                }
            }
            let n = f * f;
            out.push(acc.map(|v| ((v + n / 2) / n) as u8));
        }
    }
    out
}
