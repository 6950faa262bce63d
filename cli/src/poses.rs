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
    /// Leave loop closure out (the first rounds then match every candidate pair under the prior).
    pub no_loops: bool,
    pub max_features: usize,
    /// SIFT's DoG peak threshold, when not the stage's default.
    pub peak_threshold: Option<f32>,
    /// Features found on images downscaled by this factor (1: full size); `None`: the working
    /// resolution's ([`poses::working_downscale`] of the largest image).
    pub downscale: Option<u32>,
    pub quiet: bool,
}

pub fn run(a: &PosesArgs) -> Result<Value> {
    let json = crate::transforms_file(&a.dataset);
    let root_dir = json.parent().unwrap_or(Path::new(".")).to_path_buf();
    let text =
        std::fs::read_to_string(&json).with_context(|| format!("reading {}", json.display()))?;
    let (ns, _, _) = dataset::parse_frames(&text, &json)?;
    // Frames whose image is missing are left out and named, as the training loader does (captures
    // often list more images than they ship); they keep their prior pose in the output.
    let (present, missing): (Vec<usize>, Vec<usize>) =
        (0..ns.len()).partition(|&i| root_dir.join(&ns[i].file_path).is_file());
    let skipped: Vec<String> = missing
        .iter()
        .map(|&i| format!("{}: image file missing", ns[i].file_path))
        .collect();
    if !skipped.is_empty() && !a.quiet {
        eprintln!(
            "[poses] left out {} of {} frames whose image file is missing: {}",
            skipped.len(),
            ns.len(),
            missing
                .iter()
                .map(|&i| ns[i].file_path.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    // Each frame's full-size camera (the COLMAP model's); the working size follows from the largest.
    let (full_models, frames): (Vec<CameraModel>, Vec<PoseFrame>) = present
        .iter()
        .map(|&i| {
            let fr = &ns[i];
            let (model, prior) = fr.camera(&json)?;
            let frame = PoseFrame {
                name: fr.file_path.clone(),
                model,
                prior,
                keyframe: fr.keyframe,
                camera: fr.camera.clone(),
            };
            Ok((model, frame))
        })
        .collect::<Result<Vec<_>, dataset::DatasetError>>()?
        .into_iter()
        .unzip();
    let largest = full_models
        .iter()
        .max_by_key(|m| m.width as u64 * m.height as u64);
    let f = match (a.downscale, largest) {
        (Some(f), _) => f.max(1),
        (None, Some(m)) => poses::working_downscale(m.width, m.height),
        (None, None) => 1,
    };
    let frames: Vec<PoseFrame> = frames
        .into_iter()
        .map(|fr| PoseFrame {
            model: fr.model.downscaled(f),
            ..fr
        })
        .collect();
    if let (Some(m), false) = (largest, a.quiet) {
        eprintln!(
            "[poses] features on {}x{} images (downscale {f}{})",
            m.width / f,
            m.height / f,
            if a.downscale.is_some() {
                ""
            } else {
                ", the working resolution: about a megapixel"
            }
        );
    }
    if a.out.exists() {
        anyhow::bail!("{} exists; choose a new folder", a.out.display());
    }
    if f > 1 {
        if let Some(m) = frames
            .iter()
            .find(|fr| fr.model.width < 16 || fr.model.height < 16)
        {
            anyhow::bail!(
                "{}: --downscale {f} leaves {} at {}x{} pixels; too small to find features",
                json.display(),
                m.name,
                m.model.width,
                m.model.height
            );
        }
    }
    let load = |k: usize| -> Result<GrayImage, String> {
        let fr = &ns[present[k]];
        let p = root_dir.join(&fr.file_path);
        let (w, h, rgb) = dataset::read_rgb(&p).map_err(|e| e.to_string())?;
        let full = &full_models[k];
        if (w, h) != (full.width, full.height) {
            return Err(format!(
                "{}: image is {w}x{h}, its camera {}x{}",
                p.display(),
                full.width,
                full.height
            ));
        }
        let rgb = silvr_core::train::data::resize_rgb(rgb, w, h, f);
        let gray = silvr_core::sfm::features::gray_from_rgb(&rgb);
        let sky = match &fr.sky_mask_path {
            Some(s) => {
                let p = root_dir.join(s);
                let (sw, sh, m) = dataset::read_gray8(&p).map_err(|e| e.to_string())?;
                if (sw, sh) != (w, h) {
                    return Err(format!(
                        "{}: sky mask is {sw}x{sh}, the image {w}x{h}",
                        p.display()
                    ));
                }
                let m = silvr_core::train::data::resize_nearest(m, w, h, f);
                Some(m.iter().map(|&v| v > 127).collect())
            }
            None => None,
        };
        Ok(GrayImage {
            width: w / f,
            height: h / f,
            gray,
            sky,
        })
    };
    let mut opts = PosesOptions {
        refine_extrinsics: a.refine_extrinsics,
        ..Default::default()
    };
    opts.loops.enabled = !a.no_loops;
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
    let mut result = poses::refine_poses(&frames, &load, &opts, &progress)?;
    // Metric scale from the lidar where the dataset has lidar depth: SfM ranges against the returns at
    // the same pixels (the prior's scale drifts; the lidar's does not).
    let depth_of = |k: usize| -> Option<(u32, u32, Vec<u16>)> {
        let rel = ns[present[k]].depth_file_path.as_ref()?;
        let p = root_dir.join(rel);
        let bytes = std::fs::read(&p).ok()?;
        let (w, h, d) = dataset::decode_png16(&bytes, &p).ok()?;
        Some((w, h, d))
    };
    let depths: Vec<Option<(u32, u32, Vec<u16>)>> = (0..frames.len()).map(depth_of).collect();
    let range = |k: usize, uv: glam::DVec2| -> Option<f64> {
        let (w, h, d) = depths[k].as_ref()?;
        // The feature's pixel at full size; the nearest return within a pixel of it.
        let full = (uv + 0.5) * f as f64 - 0.5;
        let (x0, y0) = (full.x.round() as i64, full.y.round() as i64);
        let mut best: Option<(f64, f64)> = None;
        for dy in -1..=1i64 {
            for dx in -1..=1i64 {
                let (x, y) = (x0 + dx, y0 + dy);
                if x < 0 || y < 0 || x >= *w as i64 || y >= *h as i64 {
                    continue;
                }
                let v = d[(y as usize) * (*w as usize) + x as usize];
                if v == 0 || v == silvr_core::lidar::images::SKY_DEPTH {
                    continue;
                }
                let dist = ((x as f64 - full.x).powi(2) + (y as f64 - full.y).powi(2)).sqrt();
                if best.is_none_or(|b| dist < b.0) {
                    best = Some((dist, v as f64 / 256.0));
                }
            }
        }
        best.map(|b| b.1)
    };
    let scale = poses::lidar_scale(&result.poses, &result.points, &result.tracks, &range);
    if let Some(s) = &scale {
        if s.applied {
            poses::rescale(&mut result.poses, &mut result.points, s.ratio);
        }
        if !a.quiet {
            eprintln!(
                "[poses] scale against the lidar: {:.4} ± {:.4} over {} returns at SfM points{}",
                s.ratio,
                s.std_error,
                s.samples,
                if s.applied {
                    " (map rescaled to metric)"
                } else {
                    " (kept)"
                }
            );
        }
    }
    result.report.lidar_scale = scale;
    let rep = &result.report;

    // Scores against exact poses, when given: the prior's and the refined.
    let errors = match &a.gt {
        Some(gt) => {
            let gt_json = crate::transforms_file(gt);
            // Frames matched by the file they name (the exact file may spell paths from elsewhere).
            let named = |poses: &[silvr_core::geometry::Se3]| {
                frames
                    .iter()
                    .zip(poses)
                    .map(|(f, p)| (f.name.clone(), *p))
                    .collect::<Vec<_>>()
            };
            let prior: Vec<_> = frames.iter().map(|f| f.prior).collect();
            let score = |poses: &[silvr_core::geometry::Se3]| {
                silvr_core::eval::poses::compare_named(
                    named(poses),
                    Some(&root_dir),
                    &json.display().to_string(),
                    &gt_json,
                )
            };
            let p = score(&prior)?;
            let r = score(&result.poses)?;
            Some(
                serde_json::json!({ "gt": gt_json.display().to_string(), "prior": p, "refined": r }),
            )
        }
        None => None,
    };

    let tmp = crate::submaps::staging(&a.out)?;
    let prefix = crate::submaps::prefix_to(&root_dir, &a.out)?;
    // transforms.json: the input's, poses replaced, paths pointing back at the dataset.
    let mut by_frame: Vec<Option<silvr_core::geometry::Se3>> = vec![None; ns.len()];
    for (k, &i) in present.iter().enumerate() {
        by_frame[i] = Some(result.poses[k]);
    }
    let root = rewrite_transforms(&text, &by_frame, &prefix)?;
    dataset::write_atomic(
        &tmp.join("transforms.json"),
        serde_json::to_string_pretty(&root)?.as_bytes(),
    )?;
    // The COLMAP text model (cameras, posed images with their observed keypoints, points).
    let model = colmap_model(&frames, &full_models, f, &result)?;
    let cdir = tmp.join("colmap");
    std::fs::create_dir_all(&cdir)?;
    colmap::write_model(&cdir, &model)?;
    let report = serde_json::json!({
        "dataset": json.display().to_string(),
        "poses": rep,
        "errors": errors,
        "downscale": f,
        "downscale_auto": a.downscale.is_none(),
        "skipped": skipped,
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
    if let Some(n) = p["components"].as_u64().filter(|&n| n > 1) {
        eprintln!(
            "[poses] warning: the match graph falls apart into {n} parts: between them only the SLAM \
             odometry ties the keyframes (their relative poses there are the prior's); see the images \
             not registered below, or lower --peak-threshold"
        );
        let images = p["per_image"].as_array().map(Vec::as_slice).unwrap_or(&[]);
        for part in 0..n {
            let names: Vec<&str> = images
                .iter()
                .filter(|r| r["part"].as_u64() == Some(part))
                .filter_map(|r| r["name"].as_str())
                .collect();
            let span = match names.as_slice() {
                [] => String::new(),
                [one] => one.to_string(),
                [first, .., last] => format!("{first} … {last}"),
            };
            eprintln!(
                "[poses]   part {}: {} images, {span}",
                part + 1,
                names.len()
            );
        }
    }
    let l = &p["loops"];
    if let Some(why) = l["skipped"].as_str() {
        eprintln!("[poses] loops: not searched ({why})");
    } else {
        let edges = l["edges"].as_array().map(Vec::as_slice).unwrap_or(&[]);
        eprintln!(
            "[poses] loops: {} closed (of {} image pairs retrieved, {} keyframe pairs verified, {} beyond the drift allowed, {} inconsistent); the pose graph moved keyframes by up to {:.2} m (mean {:.2} m)",
            edges.len(),
            l["retrieved"],
            l["verified"],
            l["beyond_drift"],
            l["inconsistent"],
            l["max_shift_m"].as_f64().unwrap_or(0.0),
            l["mean_shift_m"].as_f64().unwrap_or(0.0)
        );
        for e in edges.iter().take(5) {
            eprintln!(
                "[poses]   {} ↔ {}: {} walked between, {} of {} matches in 3-D, corrected by {:.2} m, {:.2}°",
                e["names"][0].as_str().unwrap_or("?"),
                e["names"][1].as_str().unwrap_or("?"),
                format_args!("{:.0} m", e["path_m"].as_f64().unwrap_or(f64::NAN)),
                e["inliers"],
                e["matches"],
                e["correction_m"].as_f64().unwrap_or(f64::NAN),
                e["correction_deg"].as_f64().unwrap_or(f64::NAN)
            );
        }
        if edges.len() > 5 {
            eprintln!("[poses]   … and {} more in report.json", edges.len() - 5);
        }
    }
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
/// The COLMAP model at full resolution: `full[i]` is frame i's camera before the `f`-fold downscale its
/// features were found at, so keypoints and errors are scaled back to full-size pixels.
fn colmap_model(
    frames: &[PoseFrame],
    full: &[CameraModel],
    f: u32,
    result: &poses::PosesResult,
) -> Result<ColmapModel> {
    let up = |uv: glam::DVec2| (uv + 0.5) * f as f64 - 0.5;
    let mut cameras: BTreeMap<u32, CameraModel> = BTreeMap::new();
    let mut images: Vec<ColmapImage> = Vec::with_capacity(frames.len());
    for (i, f) in frames.iter().enumerate() {
        if f.name.chars().any(char::is_whitespace) {
            anyhow::bail!("{}: COLMAP names cannot hold spaces", f.name);
        }
        let camera_id = match cameras.iter().find(|(_, m)| **m == full[i]) {
            Some((id, _)) => *id,
            None => {
                let id = cameras.len() as u32 + 1;
                cameras.insert(id, full[i]);
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
                xy: up(uv),
                point3d_id: Some(id),
            });
            let p = result.poses[i].inverse().transform_point(*x);
            if let Some(r) = frames[i].model.project_within(p, angles[i]) {
                err += r.distance(uv) * f as f64;
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

/// A transforms.json's text with frame i's pose replaced by `poses[i]` (kept where `None`) and every
/// relative file path prefixed (so the file works from another folder); everything else as it was.
fn rewrite_transforms(
    text: &str,
    poses: &[Option<silvr_core::geometry::Se3>],
    prefix: &str,
) -> Result<Value> {
    let mut root: Value = serde_json::from_str(text)?;
    if let Some(list) = root.get_mut("frames").and_then(Value::as_array_mut) {
        for (i, f) in list.iter_mut().enumerate() {
            let Some(o) = f.as_object_mut() else { continue };
            if let Some(pose) = poses.get(i).copied().flatten() {
                let rows = dataset::transform_matrix_rows(&pose);
                o.insert("transform_matrix".into(), serde_json::to_value(rows)?);
            }
            dataset::prefix_frame_paths(o, prefix);
        }
    }
    for list in ["train_filenames", "val_filenames"] {
        if let Some(arr) = root.get_mut(list).and_then(Value::as_array_mut) {
            for v in arr.iter_mut() {
                if let Some(s) = v.as_str() {
                    *v = Value::from(dataset::prefixed(prefix, s));
                }
            }
        }
    }
    Ok(root)
}

/// `silvr perturb-poses`: the frames' poses with per-image (per-keyframe on a rig) noise and optional
/// drift along the listed order (the first exact), the synthetic world's prior model ([`prior_trajectory`]) applied to a
/// capture, written as OUT/transforms.json pointing back at the dataset's files.
///
/// [`prior_trajectory`]: silvr_core::synthetic::prior::prior_trajectory
pub fn perturb(
    dataset: &Path,
    out: &Path,
    noise: f64,
    noise_deg: f64,
    drift: f64,
    seed: u64,
) -> Result<()> {
    for (what, v) in [
        ("--noise", noise),
        ("--noise-deg", noise_deg),
        ("--drift", drift),
    ] {
        if !(v.is_finite() && v >= 0.0) {
            anyhow::bail!("{what} must be a finite number ≥ 0, not {v}");
        }
    }
    let json = crate::transforms_file(dataset);
    let root_dir = json.parent().unwrap_or(Path::new(".")).to_path_buf();
    let text =
        std::fs::read_to_string(&json).with_context(|| format!("reading {}", json.display()))?;
    let (ns, _, _) = dataset::parse_frames(&text, &json)?;
    if out.exists() {
        anyhow::bail!("{} exists; choose a new folder", out.display());
    }
    let exact: Vec<silvr_core::geometry::Se3> = ns
        .iter()
        .map(|f| f.camera(&json).map(|(_, p)| p))
        .collect::<Result<_, _>>()?;
    let params = silvr_core::synthetic::prior::PriorParams {
        scale_error: drift,
        walk_per_m: drift,
        noise_m: noise,
        noise_deg,
        ..silvr_core::synthetic::prior::PriorParams::exact()
    };
    // A rig moves as one: frames of one keyframe (the `keyframe` field) share their keyframe's error,
    // as in a SLAM trajectory; frames without one are perturbed each on its own.
    let mut groups: Vec<Vec<usize>> = Vec::new();
    let mut group_of_keyframe: std::collections::HashMap<usize, usize> = Default::default();
    for (i, f) in ns.iter().enumerate() {
        match f.keyframe.and_then(|k| group_of_keyframe.get(&k).copied()) {
            Some(g) => groups[g].push(i),
            None => {
                if let Some(k) = f.keyframe {
                    group_of_keyframe.insert(k, groups.len());
                }
                groups.push(vec![i]);
            }
        }
    }
    let bases: Vec<silvr_core::geometry::Se3> = groups.iter().map(|m| exact[m[0]]).collect();
    let (moved_bases, _) = silvr_core::synthetic::prior::prior_trajectory(&bases, &params, seed);
    let mut moved = exact.clone();
    for (members, (b, nb)) in groups.iter().zip(bases.iter().zip(&moved_bases)) {
        let delta = *nb * b.inverse();
        for &i in members {
            moved[i] = delta * exact[i];
        }
    }
    let tmp = crate::submaps::staging(out)?;
    let prefix = crate::submaps::prefix_to(&root_dir, out)?;
    let moved: Vec<_> = moved.into_iter().map(Some).collect();
    let root = rewrite_transforms(&text, &moved, &prefix)?;
    dataset::write_atomic(
        &tmp.join("transforms.json"),
        serde_json::to_string_pretty(&root)?.as_bytes(),
    )?;
    std::fs::rename(&tmp, out)
        .with_context(|| format!("renaming {} to {}", tmp.display(), out.display()))?;
    eprintln!(
        "[perturb] {} frames of {}: noise {noise} per axis, {noise_deg}° per axis, drift {drift}, seed {seed} → {}",
        ns.len(),
        json.display(),
        out.join("transforms.json").display()
    );
    Ok(())
}
