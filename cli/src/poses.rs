//! `silvr poses`: the SLAM prior refined by structure from motion (silvr_core::sfm::poses), written as a
//! dataset folder that trains directly (its transforms.json points back at the dataset's images), a
//! COLMAP text model, and report.json. The folder is written under a temporary name and renamed.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use anyhow::{Context, Result};
use serde_json::Value;
use silvr_core::camera::CameraModel;
use silvr_core::dataset;
use silvr_core::ingest::colmap::{
    self, ColmapImage, ColmapModel, ColmapPoint, ColmapPoint2D, ColmapTrackEntry,
};
use silvr_core::sfm::poses::{self, GrayImage, PoseFrame, PosesOptions};

/// What `silvr poses` was asked.
pub struct PosesArgs {
    pub dataset: PathBuf,
    pub out: PathBuf,
    /// Exact poses to score prior and refined against (a synthetic world's transforms.json).
    pub gt: Option<PathBuf>,
    pub refine_extrinsics: bool,
    pub max_features: usize,
    /// SIFT's DoG peak threshold, when not the stage's default.
    pub peak_threshold: Option<f32>,
    pub quiet: bool,
}

pub fn run(a: &PosesArgs) -> Result<Value> {
    let json = crate::transforms_file(&a.dataset);
    let root_dir = json.parent().unwrap_or(Path::new(".")).to_path_buf();
    let text =
        std::fs::read_to_string(&json).with_context(|| format!("reading {}", json.display()))?;
    let (ns, _, _) = dataset::parse_frames(&text, &json)?;
    let frames: Vec<PoseFrame> = ns
        .iter()
        .map(|f| {
            let (model, prior) = f.camera(&json)?;
            Ok(PoseFrame {
                name: f.file_path.clone(),
                model,
                prior,
                keyframe: f.keyframe,
                camera: f.camera.clone(),
            })
        })
        .collect::<Result<_, dataset::DatasetError>>()?;
    if a.out.exists() {
        anyhow::bail!("{} exists; choose a new folder", a.out.display());
    }
    let load = |i: usize| -> Result<GrayImage, String> {
        let f = &ns[i];
        let p = root_dir.join(&f.file_path);
        let (w, h, rgb) = dataset::read_rgb(&p).map_err(|e| e.to_string())?;
        let gray = silvr_core::sfm::features::gray_from_rgb(&rgb);
        let sky = match &f.sky_mask_path {
            Some(s) => {
                let p = root_dir.join(s);
                let (sw, sh, m) = dataset::read_gray8(&p).map_err(|e| e.to_string())?;
                if (sw, sh) != (w, h) {
                    return Err(format!(
                        "{}: sky mask is {sw}x{sh}, the image {w}x{h}",
                        p.display()
                    ));
                }
                Some(m.iter().map(|&v| v > 127).collect())
            }
            None => None,
        };
        Ok(GrayImage {
            width: w,
            height: h,
            gray,
            sky,
        })
    };
    let mut opts = PosesOptions {
        refine_extrinsics: a.refine_extrinsics,
        ..Default::default()
    };
    opts.sift.max_features = a.max_features;
    if let Some(p) = a.peak_threshold {
        opts.sift.peak_threshold = p;
    }
    // (stage, its start, last line printed)
    let last = Mutex::new((
        String::new(),
        std::time::Instant::now(),
        std::time::Instant::now(),
    ));
    let quiet = a.quiet;
    let progress = move |stage: &str, done: usize, total: usize| {
        if quiet {
            return;
        }
        let mut l = last.lock().unwrap_or_else(|e| e.into_inner());
        if l.0 != stage {
            *l = (
                stage.to_string(),
                std::time::Instant::now(),
                std::time::Instant::now(),
            );
        } else if l.2.elapsed().as_secs_f64() < 2.0 && done != total {
            return;
        }
        l.2 = std::time::Instant::now();
        let elapsed = l.1.elapsed().as_secs_f64();
        let eta = if done > 0 {
            format!(
                ", ETA {:.0} s",
                elapsed / done as f64 * total.saturating_sub(done) as f64
            )
        } else {
            String::new()
        };
        eprintln!("[poses] {stage} {done}/{total} ({elapsed:.1} s{eta})");
    };
    let result = poses::refine_poses(&frames, &load, &opts, &progress)?;
    let rep = &result.report;

    // Scores against exact poses, when given: the prior's and the refined.
    let errors = match &a.gt {
        Some(gt) => {
            let gt_json = crate::transforms_file(gt);
            let (gt_frames, _, _) = dataset::read_frames(&gt_json)?;
            let by_name: BTreeMap<&str, &dataset::NsFrame> = gt_frames
                .iter()
                .map(|f| (f.file_path.as_str(), f))
                .collect();
            let (mut prior, mut refined, mut exact) = (Vec::new(), Vec::new(), Vec::new());
            for (i, f) in frames.iter().enumerate() {
                let g = by_name.get(f.name.as_str()).with_context(|| {
                    format!(
                        "{}: no frame {} in {}",
                        json.display(),
                        f.name,
                        gt_json.display()
                    )
                })?;
                exact.push(g.camera(&gt_json)?.1);
                prior.push(f.prior);
                refined.push(result.poses[i]);
            }
            let p = silvr_core::eval::poses::pose_errors(&prior, &exact)?;
            let r = silvr_core::eval::poses::pose_errors(&refined, &exact)?;
            Some(
                serde_json::json!({ "gt": gt_json.display().to_string(), "prior": p, "refined": r }),
            )
        }
        None => None,
    };

    // Staging folder, renamed into place when complete.
    let parent = a
        .out
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    let tmp = parent.join(format!(
        ".{}.partial",
        a.out
            .file_name()
            .map(|n| n.to_string_lossy())
            .unwrap_or_default()
    ));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
    let abs = |p: &Path| -> Result<PathBuf> {
        std::path::absolute(p).with_context(|| format!("resolving {}", p.display()))
    };
    let rel = crate::submaps::relative_path(&abs(&root_dir)?, &abs(&a.out)?);
    let prefix = {
        let s = rel.to_string_lossy().replace('\\', "/");
        if s.is_empty() {
            String::new()
        } else {
            format!("{s}/")
        }
    };
    // transforms.json: the input's, poses replaced, paths pointing back at the dataset.
    let mut root: Value = serde_json::from_str(&text)?;
    if let Some(list) = root.get_mut("frames").and_then(Value::as_array_mut) {
        for (i, f) in list.iter_mut().enumerate() {
            let Some(o) = f.as_object_mut() else { continue };
            let m = silvr_core::camera::opencv_to_opengl_c2w(result.poses[i].to_mat4());
            let rows: Vec<Value> = [m.row(0), m.row(1), m.row(2), m.row(3)]
                .iter()
                .map(|r| Value::from(r.to_array().to_vec()))
                .collect();
            o.insert("transform_matrix".into(), Value::from(rows));
            for k in [
                "file_path",
                "depth_file_path",
                "normal_file_path",
                "sky_mask_path",
            ] {
                if let Some(p) = o.get(k).and_then(Value::as_str).map(String::from) {
                    // Absolute paths already reach their file from anywhere.
                    if !Path::new(&p).is_absolute() {
                        o.insert(k.into(), Value::from(format!("{prefix}{p}")));
                    }
                }
            }
        }
    }
    for list in ["train_filenames", "val_filenames"] {
        if let Some(arr) = root.get_mut(list).and_then(Value::as_array_mut) {
            for v in arr.iter_mut() {
                if let Some(s) = v.as_str().filter(|s| !Path::new(s).is_absolute()) {
                    *v = Value::from(format!("{prefix}{s}"));
                }
            }
        }
    }
    dataset::write_atomic(
        &tmp.join("transforms.json"),
        serde_json::to_string_pretty(&root)?.as_bytes(),
    )?;
    // The COLMAP text model (cameras, posed images with their observed keypoints, points).
    let model = colmap_model(&frames, &result)?;
    let cdir = tmp.join("colmap");
    std::fs::create_dir_all(&cdir)?;
    colmap::write_model(&cdir, &model)?;
    let report = serde_json::json!({
        "dataset": json.display().to_string(),
        "poses": rep,
        "errors": errors,
    });
    dataset::write_atomic(
        &tmp.join("report.json"),
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;
    std::fs::rename(&tmp, &a.out)
        .with_context(|| format!("renaming {} to {}", tmp.display(), a.out.display()))?;
    if !a.quiet {
        summarise(&report);
    }
    Ok(report)
}

/// A one-screen summary of report.json.
fn summarise(report: &Value) {
    let p = &report["poses"];
    eprintln!(
        "[poses] registered {}/{} images, {} points, {:.0} observations/image (min {}), reprojection RMSE {:.3} px on the prior → {:.3} px refined",
        p["registered"], p["images"], p["points"],
        p["observations_per_image_mean"].as_f64().unwrap_or(f64::NAN),
        p["observations_per_image_min"],
        p["rmse_prior_px"].as_f64().unwrap_or(f64::NAN),
        p["rmse_px"].as_f64().unwrap_or(f64::NAN)
    );
    if let Some(stages) = p["stages"].as_array() {
        let s: Vec<String> = stages
            .iter()
            .map(|s| {
                format!(
                    "{} {:.1} s",
                    s["stage"].as_str().unwrap_or("?"),
                    s["seconds"].as_f64().unwrap_or(f64::NAN)
                )
            })
            .collect();
        eprintln!("[poses] time: {}", s.join(", "));
    }
    if let Some(unreg) = p["per_image"].as_array() {
        for r in unreg.iter().filter(|r| r["registered"] == false) {
            eprintln!(
                "[poses] not registered: {} ({})",
                r["name"].as_str().unwrap_or("?"),
                r["reason"].as_str().unwrap_or("")
            );
        }
    }
    let e = &report["errors"];
    if !e.is_null() {
        let f = |k: &str, m: &str| e[k][m].as_f64().unwrap_or(f64::NAN);
        eprintln!(
            "[poses] vs exact: ATE {:.4} m → {:.4} m, rotation {:.3}° → {:.3}° (prior → refined)",
            f("prior", "ate_rmse_m"),
            f("refined", "ate_rmse_m"),
            f("prior", "rot_rmse_deg"),
            f("refined", "rot_rmse_deg")
        );
    }
}

/// The refined model in COLMAP's terms: one camera per distinct intrinsics, every frame as an image
/// with its keypoints that observe a point.
fn colmap_model(frames: &[PoseFrame], result: &poses::PosesResult) -> Result<ColmapModel> {
    let mut cameras: BTreeMap<u32, CameraModel> = BTreeMap::new();
    let mut images: Vec<ColmapImage> = Vec::with_capacity(frames.len());
    for (i, f) in frames.iter().enumerate() {
        if f.name.chars().any(char::is_whitespace) {
            anyhow::bail!("{}: COLMAP names cannot hold spaces", f.name);
        }
        let camera_id = match cameras.iter().find(|(_, m)| **m == f.model) {
            Some((id, _)) => *id,
            None => {
                let id = cameras.len() as u32 + 1;
                cameras.insert(id, f.model);
                id
            }
        };
        images.push(ColmapImage {
            id: i as u32 + 1,
            camera_id,
            name: f.name.clone(),
            t_cam_world: result.poses[i].inverse(),
            points2d: Vec::new(),
        });
    }
    // Each frame's valid angle once (`project` would rescan the lens per observation).
    let angles: Vec<f64> = frames.iter().map(|f| f.model.valid_angle()).collect();
    let mut points = Vec::new();
    for (pid, (x, track)) in result.points.iter().zip(&result.tracks).enumerate() {
        if track.len() < 2 {
            continue;
        }
        let id = pid as u64 + 1;
        let mut entries = Vec::with_capacity(track.len());
        let mut err = 0.0;
        for &(i, uv) in track {
            let img = &mut images[i];
            entries.push(ColmapTrackEntry {
                image_id: img.id,
                point2d_idx: img.points2d.len() as u32,
            });
            img.points2d.push(ColmapPoint2D {
                xy: uv,
                point3d_id: Some(id),
            });
            let p = result.poses[i].inverse().transform_point(*x);
            if let Some(r) = frames[i].model.project_within(p, angles[i]) {
                err += r.distance(uv);
            }
        }
        points.push(ColmapPoint {
            id,
            position: *x,
            color: [160, 160, 160],
            error: err / track.len() as f64,
            track: entries,
        });
    }
    Ok(ColmapModel {
        cameras,
        images,
        points,
    })
}
