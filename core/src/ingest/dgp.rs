//! A DGP scene (the TRI / Parallel Domain "dataset governance policy" layout) → the project's dataset.
//!
//! Layout: `scene_*.json` lists every datum (a lidar sweep `point_cloud/LIDAR/<t>.npz` = N × (X, Y, Z,
//! INTENSITY) f64 in the lidar frame, or an image `rgb/<CAMERA>/<t>.jpg`) with its sensor-to-world `pose`,
//! and `samples` that group one datum per sensor with a calibration key; `calibration/<key>.json` gives
//! per sensor the sensor-to-vehicle extrinsic and pinhole intrinsics (the images are rectified).
//!
//! Each sample becomes a keyframe. Sweeps carry no per-point time (DGP already motion-corrects them), so
//! nothing is deskewed; each camera gets the sweep through `T_cam_lidar = pose_cam⁻¹ · pose_lidar` of that
//! sample, which also absorbs the few milliseconds between the camera and lidar stamps (~11 cm at the
//! vehicle's 12.7 m/s). Sweeps have no ring either: the range image for normals and sky masks is an
//! angular grid ([`crate::lidar::normals::angular_grid`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{DQuat, DVec3};
use serde::Serialize;
use serde_json::Value;

use super::npz;
use crate::camera::{CameraModel, Distortion};
use crate::dataset::{self, DatasetError, DatasetWriter, NsFrame};
use crate::geometry::Se3;
use crate::gpu::{Gpu, GpuError};
use crate::lidar::{images, normals, products};
use crate::pointcloud::{write_ply_bytes, PointCloud};
use crate::rig::{Rig, RigCamera};

/// Why a DGP scene could not be imported; every message names the file.
#[derive(Debug, thiserror::Error)]
pub enum DgpError {
    #[error("{file}: {reason}")]
    Invalid { file: String, reason: String },
    #[error(transparent)]
    Npz(#[from] npz::NpzError),
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error("GPU: {0}")]
    Gpu(#[from] GpuError),
}

fn invalid(file: &Path, reason: impl Into<String>) -> DgpError {
    DgpError::Invalid {
        file: file.display().to_string(),
        reason: reason.into(),
    }
}

/// What an import wrote.
#[derive(Clone, Debug, Serialize)]
pub struct DgpSummary {
    pub path: PathBuf,
    pub keyframes: usize,
    pub images: usize,
    pub lidar_points: usize,
    /// Per camera: lidar pixels in its depth images, summed over keyframes.
    pub depth_pixels: BTreeMap<String, usize>,
}

/// Import options.
#[derive(Clone, Copy, Debug)]
pub struct DgpOptions {
    /// Integer image downscale (1 = full resolution); intrinsics are scaled to match.
    pub downscale: u32,
    /// Lidar returns nearer than this (m) are ignored.
    pub min_range: f64,
}

impl Default for DgpOptions {
    fn default() -> Self {
        Self {
            downscale: 1,
            min_range: 0.5,
        }
    }
}

fn pose_of(v: &Value) -> Option<Se3> {
    let r = v.get("rotation")?;
    let t = v.get("translation")?;
    let f = |o: &Value, k: &str| o.get(k)?.as_f64();
    let q = DQuat::from_xyzw(f(r, "qx")?, f(r, "qy")?, f(r, "qz")?, f(r, "qw")?);
    let p = DVec3::new(f(t, "x")?, f(t, "y")?, f(t, "z")?);
    (q.length() > 0.5 && q.is_finite() && p.is_finite()).then(|| Se3::new(q.normalize(), p))
}

/// The stamp (s) in a DGP file name (units of 100 ns).
fn stamp_of(filename: &str) -> Option<f64> {
    let stem = Path::new(filename).file_stem()?.to_str()?;
    Some(stem.parse::<u64>().ok()? as f64 * 1e-7)
}

struct Datum {
    sensor: String,
    filename: String,
    pose: Se3,
    is_image: bool,
}

fn read_json(path: &Path) -> Result<Value, DgpError> {
    let text = std::fs::read_to_string(path).map_err(|e| invalid(path, e.to_string()))?;
    serde_json::from_str(&text).map_err(|e| invalid(path, format!("not valid JSON: {e}")))
}

/// Imports the DGP scene folder `scene` into a dataset at `out`.
pub async fn import_dgp(
    scene: &Path,
    out: &Path,
    overwrite: bool,
    options: DgpOptions,
    gpu: &Gpu,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<DgpSummary, DgpError> {
    let scene_json = std::fs::read_dir(scene)
        .map_err(|e| invalid(scene, e.to_string()))?
        .flatten()
        .map(|e| e.path())
        .find(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("scene") && n.ends_with(".json"))
        })
        .ok_or_else(|| invalid(scene, "no scene*.json in this folder (not a DGP scene)"))?;
    let doc = read_json(&scene_json)?;
    let bad = |what: &str| invalid(&scene_json, what.to_string());
    let mut data: BTreeMap<String, Datum> = BTreeMap::new();
    for d in doc
        .get("data")
        .and_then(Value::as_array)
        .ok_or_else(|| bad("no 'data' list"))?
    {
        let key = d
            .get("key")
            .and_then(Value::as_str)
            .unwrap_or_default()
            .to_string();
        let sensor = d
            .pointer("/id/name")
            .and_then(Value::as_str)
            .unwrap_or_default()
            .to_string();
        let (inner, is_image) = match (d.pointer("/datum/image"), d.pointer("/datum/point_cloud")) {
            (Some(i), _) => (i, true),
            (None, Some(p)) => (p, false),
            _ => continue,
        };
        let filename = inner
            .get("filename")
            .and_then(Value::as_str)
            .unwrap_or_default()
            .to_string();
        let pose = inner
            .get("pose")
            .and_then(pose_of)
            .ok_or_else(|| bad(&format!("datum {key} ({sensor}): missing or invalid pose")))?;
        if filename.is_empty() || filename.contains("..") || Path::new(&filename).is_absolute() {
            return Err(bad(&format!(
                "datum {key}: unusable file name {filename:?}"
            )));
        }
        data.insert(
            key,
            Datum {
                sensor,
                filename,
                pose,
                is_image,
            },
        );
    }
    let samples = doc
        .get("samples")
        .and_then(Value::as_array)
        .ok_or_else(|| bad("no 'samples' list"))?;
    if samples.is_empty() {
        return Err(bad("no samples"));
    }

    // Calibration of the first sample (a scene has one rig).
    let cal_key = samples[0]
        .get("calibration_key")
        .and_then(Value::as_str)
        .ok_or_else(|| bad("sample 0 has no calibration_key"))?;
    let cal_path = scene.join("calibration").join(format!("{cal_key}.json"));
    let cal = read_json(&cal_path)?;
    let cbad = |what: String| invalid(&cal_path, what);
    let names: Vec<&str> = cal
        .get("names")
        .and_then(Value::as_array)
        .map(|v| v.iter().filter_map(Value::as_str).collect())
        .unwrap_or_default();
    let extrinsics = cal
        .get("extrinsics")
        .and_then(Value::as_array)
        .cloned()
        .unwrap_or_default();
    let intrinsics = cal
        .get("intrinsics")
        .and_then(Value::as_array)
        .cloned()
        .unwrap_or_default();
    if names.is_empty() || extrinsics.len() != names.len() || intrinsics.len() != names.len() {
        return Err(cbad(format!(
            "names ({}), extrinsics ({}) and intrinsics ({}) must be equally long and non-empty",
            names.len(),
            extrinsics.len(),
            intrinsics.len()
        )));
    }
    let vehicle_of = |name: &str| -> Result<Se3, DgpError> {
        let i = names
            .iter()
            .position(|n| *n == name)
            .ok_or_else(|| cbad(format!("no calibration for {name}")))?;
        pose_of(&extrinsics[i]).ok_or_else(|| cbad(format!("{name}: invalid extrinsic")))
    };

    // Sensors: the lidar and the cameras, from sample 0's data.
    let first: Vec<&Datum> = samples[0]
        .get("datum_keys")
        .and_then(Value::as_array)
        .map(|v| v.iter().filter_map(|k| data.get(k.as_str()?)).collect())
        .unwrap_or_default();
    let lidar_name = first
        .iter()
        .find(|d| !d.is_image)
        .map(|d| d.sensor.clone())
        .ok_or_else(|| bad("sample 0 has no point cloud"))?;
    let mut cam_names: Vec<String> = first
        .iter()
        .filter(|d| d.is_image)
        .map(|d| d.sensor.clone())
        .collect();
    cam_names.sort();
    if cam_names.is_empty() {
        return Err(bad("sample 0 has no image"));
    }
    let t_vehicle_lidar = vehicle_of(&lidar_name)?;
    let scale = options.downscale.max(1);
    let mut cameras = Vec::new();
    for name in &cam_names {
        let i = names
            .iter()
            .position(|n| n == name)
            .ok_or_else(|| cbad(format!("no calibration for {name}")))?;
        let k = &intrinsics[i];
        let g = |key: &str| k.get(key).and_then(Value::as_f64);
        let (Some(fx), Some(fy), Some(cx), Some(cy)) = (g("fx"), g("fy"), g("cx"), g("cy")) else {
            return Err(cbad(format!("{name}: intrinsics need fx, fy, cx, cy")));
        };
        if g("skew").unwrap_or(0.0).abs() > 1e-6 {
            return Err(cbad(format!("{name}: skewed pixels are not supported")));
        }
        let img = first
            .iter()
            .find(|d| &d.sensor == name)
            .expect("names come from the data");
        let (w, h) = image::image_dimensions(scene.join(&img.filename))
            .map_err(|e| invalid(&scene.join(&img.filename), e.to_string()))?;
        let full = CameraModel {
            width: w,
            height: h,
            fx,
            fy,
            cx,
            cy,
            distortion: Distortion::None,
        };
        full.validate().map_err(|e| cbad(format!("{name}: {e}")))?;
        let model = if scale > 1 {
            full.scaled(1.0 / scale as f64)
        } else {
            full
        };
        cameras.push(RigCamera {
            name: name.clone(),
            model,
            t_lidar_cam: t_vehicle_lidar.inverse() * vehicle_of(name)?,
        });
    }
    let rig = Rig {
        base_frame: "vehicle".into(),
        lidar_frame: lidar_name.clone(),
        t_base_lidar: t_vehicle_lidar,
        cameras,
    };
    rig.validate().map_err(|e| cbad(e.to_string()))?;

    let w = DatasetWriter::create(out, overwrite)?;
    let mut frames = Vec::new();
    let (mut times, mut lidar_poses, mut base_poses) = (Vec::new(), Vec::new(), Vec::new());
    let mut depth_pixels: BTreeMap<String, usize> = BTreeMap::new();
    let mut lidar_points = 0;
    let total = samples.len();
    for (k, sample) in samples.iter().enumerate() {
        progress(k, total);
        let name = format!("{k:05}");
        let keys: Vec<&Datum> = sample
            .get("datum_keys")
            .and_then(Value::as_array)
            .map(|v| v.iter().filter_map(|key| data.get(key.as_str()?)).collect())
            .unwrap_or_default();
        let lidar = keys
            .iter()
            .find(|d| !d.is_image && d.sensor == lidar_name)
            .ok_or_else(|| bad(&format!("sample {k} has no {lidar_name} sweep")))?;
        let npz_path = scene.join(&lidar.filename);
        let bytes = std::fs::read(&npz_path).map_err(|e| invalid(&npz_path, e.to_string()))?;
        let arr = npz::parse_npz(&bytes, "data", &npz_path.display().to_string())?;
        if arr.cols < 3 {
            return Err(invalid(
                &npz_path,
                format!("{} columns; X, Y, Z needed", arr.cols),
            ));
        }
        let positions: Vec<DVec3> = (0..arr.rows)
            .map(|i| {
                let r = arr.row(i);
                DVec3::new(r[0], r[1], r[2])
            })
            .collect();
        let intensity: Vec<f32> = (0..arr.rows)
            .map(|i| arr.row(i).get(3).copied().unwrap_or(0.0) as f32)
            .collect();
        lidar_points += positions.len();
        let (ring, column, rings, columns) = normals::angular_grid(&positions);
        let mut cloud = PointCloud::from_positions(positions.clone());
        cloud.set_scalar("intensity", intensity);
        cloud.set_scalar("ring", ring.iter().map(|&r| r as f32).collect());
        cloud.set_scalar("column", column.iter().map(|&c| c as f32).collect());
        let ply = write_ply_bytes(&cloud).map_err(|e| invalid(&npz_path, e.to_string()))?;
        w.write(&format!("lidar/raw/{name}.ply"), &ply)?;
        w.write(&format!("lidar/deskewed/{name}.ply"), &ply)?;
        let t_world_lidar = lidar.pose;
        let t_lidar = stamp_of(&lidar.filename).unwrap_or(k as f64);
        times.push(t_lidar);
        lidar_poses.push(t_world_lidar);
        base_poses.push(t_world_lidar * t_vehicle_lidar.inverse());

        // Per camera: this sample's relative pose, the image, and the lidar products.
        let mut cams = Vec::new();
        let mut rgbs = Vec::new();
        let mut stamps = Vec::new();
        for cam in &rig.cameras {
            let d = keys
                .iter()
                .find(|d| d.is_image && d.sensor == cam.name)
                .ok_or_else(|| bad(&format!("sample {k} has no {} image", cam.name)))?;
            let path = scene.join(&d.filename);
            let img = image::open(&path)
                .map_err(|e| invalid(&path, e.to_string()))?
                .to_rgb8();
            let m = &cam.model;
            let img = if (img.width(), img.height()) != (m.width, m.height) {
                image::imageops::resize(
                    &img,
                    m.width,
                    m.height,
                    image::imageops::FilterType::Triangle,
                )
            } else {
                img
            };
            let px: Vec<[u8; 3]> = img.pixels().map(|p| p.0).collect();
            cams.push(RigCamera {
                name: cam.name.clone(),
                model: *m,
                t_lidar_cam: t_world_lidar.inverse() * d.pose,
            });
            rgbs.push(px);
            stamps.push((stamp_of(&d.filename).unwrap_or(t_lidar), d.pose));
        }
        let sweep = products::SweepInput {
            positions: &positions,
            ring: &ring,
            column: &column,
            beams: rings,
            columns,
            min_range: options.min_range,
            t_world_lidar,
        };
        let inputs: Vec<(&RigCamera, &[[u8; 3]])> = cams
            .iter()
            .zip(&rgbs)
            .map(|(c, p)| (c, p.as_slice()))
            .collect();
        let made = products::keyframe_products(gpu, &sweep, &inputs).await?;
        for ((cam, p), (rgb, (t_cam, pose))) in cams.iter().zip(made).zip(rgbs.iter().zip(&stamps))
        {
            *depth_pixels.entry(cam.name.clone()).or_insert(0) += p
                .depth
                .iter()
                .filter(|&&d| d > 0 && d != images::SKY_DEPTH)
                .count();
            frames.push(products::write_camera(&w, cam, k, *t_cam, pose, rgb, &p)?);
        }
    }
    progress(total, total);
    let n_images = frames.len();
    w.write(
        "poses/lidar_tum.txt",
        dataset::tum_string(&times, &lidar_poses).as_bytes(),
    )?;
    w.write(
        "poses/base_tum.txt",
        dataset::tum_string(&times, &base_poses).as_bytes(),
    )?;
    w.write_json("calib/rig.json", &rig)?;
    // A scene is a handful of samples: with three or more, the middle one of every camera is held out for
    // novel-view evaluation (an interpolation between its neighbours); otherwise every image trains.
    let held_out = |f: &NsFrame| total >= 3 && f.keyframe == Some(total / 2);
    let transforms = products::transforms(frames, held_out);
    w.write_json("transforms.json", &transforms)?;
    let summary = DgpSummary {
        path: out.to_path_buf(),
        keyframes: total,
        images: n_images,
        lidar_points,
        depth_pixels,
    };
    let manifest = serde_json::json!({
        "layout_version": dataset::LAYOUT_VERSION,
        "generator": "silvr-import-dgp 1",
        "source": scene.display().to_string(),
        "scene_json": scene_json.display().to_string(),
        "downscale": scale,
        "summary": &summary,
        "notes": "no per-point time in DGP sweeps: lidar/deskewed = lidar/raw; rings and columns from an angular grid",
        "files": w.files(),
    });
    w.write_json("manifest.json", &manifest)?;
    let path = w.commit()?;
    Ok(DgpSummary { path, ..summary })
}
