//! Blended renders across submaps (`silvr reconstruct`'s last stage; the paper renders submap
//! intersections by blending two submaps in image space, after Block-NeRF): every view of a camera path
//! is rendered by its nearest submap and, where the second nearest is within the blend radius (a
//! boundary view), by that one too; the two are blended with SiLVR's weights and with Block-NeRF's
//! inverse-distance weights (`silvr_core::submap::blend`), and each is scored against the view's photo.
//!
//! The path: on a synthetic dataset (its `manifest.json` names the generator's preset), the midpoints
//! between consecutive keyframes for every camera, photographed exactly by the generator (without pixel
//! noise) — views no submap trained on, at the places a path crosses a boundary. Elsewhere, the
//! dataset's held-out frames with their photos. One submap's field is loaded at a time.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use glam::DVec3;
use serde::{Deserialize, Serialize};
use silvr_core::camera::CameraModel;
use silvr_core::geometry::{Se3, Sim3};
use silvr_core::submap::blend::{self, BlendRule, Near, IDW_POWER};
use silvr_core::train::checkpoint::Checkpoint;
use silvr_core::train::data::{LoadOptions, TrainData};
use silvr_core::train::Trainer;

/// What the renders are computed from: a rerun with the same key and no retrained submap reuses them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RenderKey {
    pub views: usize,
    pub radius_m: f64,
    pub submaps: Vec<String>,
    /// The training settings of the submaps (as `reconstruct.json` records them).
    pub settings: serde_json::Value,
}

/// One rendering job over a reconstruction's submaps.
pub struct RenderJob<'a> {
    pub out: &'a Path,
    /// The dataset as given (its `manifest.json` tells a synthetic world).
    pub dataset: &'a Path,
    /// The dataset the submaps were cut from (the refined poses, or the dataset itself).
    pub trained_from: &'a Path,
    /// Submaps that finished (name, its training folder).
    pub submaps: Vec<(String, PathBuf)>,
    /// The Sim(3) from the trained-on poses to the dataset's (the refined frame's alignment).
    pub alignment: Option<Sim3>,
    pub backend: &'a str,
    pub key: RenderKey,
}

/// Where a path view's photo comes from.
enum Photo {
    /// Rendered by the generator: camera `index` of the preset's rig at this pose in the world frame.
    Synthetic {
        index: usize,
        pose: Se3,
    },
    File(PathBuf),
}

struct PathView {
    name: String,
    model: CameraModel,
    /// Camera to trained-on frame (OpenCV axes).
    pose: Se3,
    photo: Photo,
}

/// A view's scores (PSNR in dB, SSIM) for one way of rendering it.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct Score {
    pub psnr: f64,
    pub ssim: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ViewReport {
    pub name: String,
    pub nearest: String,
    pub nearest_m: f64,
    pub second: String,
    pub second_m: f64,
    /// Weight of the nearest render under SiLVR's and Block-NeRF's rules.
    pub alpha_silvr: f64,
    pub alpha_idw: f64,
    pub nearest_only: Score,
    pub second_only: Score,
    pub blended_silvr: Score,
    pub blended_idw: Score,
    /// Photo | nearest | second | SiLVR blend, side by side.
    pub strip: PathBuf,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RendersReport {
    pub computed_from: RenderKey,
    /// `synthetic keyframe midpoints` or `held-out frames`.
    pub path: String,
    pub path_views: usize,
    /// Path views whose second-nearest submap is within the radius.
    pub boundary_views: usize,
    pub backend: String,
    pub views: Vec<ViewReport>,
    /// Means over the rendered boundary views.
    pub mean_psnr_nearest: f64,
    pub mean_psnr_blended_silvr: f64,
    pub mean_psnr_blended_idw: f64,
    pub notes: Vec<String>,
}

/// The synthetic path (keyframe midpoints, every camera), or `None` when the dataset is not synthetic.
fn synthetic_path(
    dataset: &Path,
    to_trained: &Sim3,
) -> Result<Option<(silvr_core::synthetic::Preset, Vec<PathView>)>> {
    let dir = crate::transforms_file(dataset)
        .parent()
        .unwrap_or(Path::new("."))
        .to_path_buf();
    let Ok(bytes) = std::fs::read(dir.join("manifest.json")) else {
        return Ok(None);
    };
    let Ok(v) = serde_json::from_slice::<serde_json::Value>(&bytes) else {
        return Ok(None);
    };
    if !v["generator"]
        .as_str()
        .is_some_and(|g| g.starts_with("silvr-synth"))
    {
        return Ok(None);
    }
    let preset: silvr_core::synthetic::Preset = serde_json::from_value(v["preset"].clone())
        .with_context(|| format!("{}/manifest.json: preset", dir.display()))?;
    let mut views = Vec::new();
    for k in 0..preset.keyframes.saturating_sub(1) {
        let t = 0.5 * (preset.image_time(k) + preset.image_time(k + 1));
        for (i, cam) in preset.rig.cameras.iter().enumerate() {
            let world = preset.t_world_cam(i, t);
            views.push(PathView {
                name: format!("{}_{k:05}_mid", cam.name),
                model: cam.model,
                pose: to_trained.transform_pose(&world),
                photo: Photo::Synthetic {
                    index: i,
                    pose: world,
                },
            });
        }
    }
    Ok(Some((preset, views)))
}

/// The held-out frames of the trained-on dataset, with their photos.
fn held_out_path(trained_from: &Path) -> Result<Vec<PathView>> {
    let json = crate::transforms_file(trained_from);
    let root = json.parent().unwrap_or(Path::new(".")).to_path_buf();
    let (frames, _, val) = silvr_core::dataset::read_frames(&json)?;
    let mut views = Vec::new();
    for f in frames.iter().filter(|f| val.contains(&f.file_path)) {
        let (model, pose) = f.camera(&json)?;
        views.push(PathView {
            name: silvr_core::job::stem(&f.file_path),
            model,
            pose,
            photo: Photo::File(root.join(&f.file_path)),
        });
    }
    Ok(views)
}

/// Training camera centres of a submap (its frames that are not held out).
pub(crate) fn training_cameras(submap_dataset: &Path) -> Result<Vec<DVec3>> {
    let json = crate::transforms_file(submap_dataset);
    let (frames, _, val) = silvr_core::dataset::read_frames(&json)?;
    frames
        .iter()
        .filter(|f| !val.contains(&f.file_path))
        .map(|f| Ok(f.camera(&json)?.1.trans))
        .collect()
}

fn score(rgb: &[[u8; 3]], photo: &[[u8; 3]], valid: &[bool], w: u32, h: u32) -> Result<Score> {
    let (psnr, ssim) = silvr_core::train::export::score_pixels(w, h, rgb, photo, valid)?;
    Ok(Score { psnr, ssim })
}

/// Renders the path's boundary views (at most `key.views`, spread along the path) into `OUT/renders`
/// (written under a temporary name, renamed into place) and returns the report.
pub fn run(job: &RenderJob) -> Result<RendersReport> {
    let radius = job.key.radius_m;
    let to_trained = job.alignment.map(|a| a.inverse()).unwrap_or(Sim3::IDENTITY);
    let mut notes = Vec::new();
    let (preset, path, kind) = match synthetic_path(job.dataset, &to_trained)? {
        Some((p, v)) => (Some(p), v, "synthetic keyframe midpoints"),
        None => (None, held_out_path(job.trained_from)?, "held-out frames"),
    };
    let cams: Vec<Vec<DVec3>> = job
        .submaps
        .iter()
        .map(|(name, _)| training_cameras(&job.out.join("submaps").join(name)))
        .collect::<Result<_>>()?;
    // Boundary views: a second submap within the radius.
    let boundary: Vec<(usize, Near, Near)> = path
        .iter()
        .enumerate()
        .filter_map(|(i, v)| {
            let (first, second) = blend::nearest_two(&cams, v.pose.trans)?;
            let second = second.filter(|s| s.1 < radius)?;
            Some((i, first, second))
        })
        .collect();
    let n = boundary.len();
    let chosen: Vec<_> = if n <= job.key.views {
        boundary.clone()
    } else {
        (0..job.key.views)
            .map(|j| boundary[j * n / job.key.views])
            .collect()
    };
    if chosen.is_empty() {
        notes.push(format!(
            "no path view has a second submap within {radius} m: nothing to blend"
        ));
    }
    // Photos (a view whose photo cannot be read, or is not the camera's size, is left out and named).
    let world = preset
        .as_ref()
        .map(|p| silvr_core::synthetic::world::World::generate(p.world.clone(), p.seed));
    let mut photos = Vec::new();
    let mut kept = Vec::new();
    for &(i, a, b) in &chosen {
        let v = &path[i];
        let rgb: Result<Vec<[u8; 3]>> = match &v.photo {
            Photo::Synthetic { index, pose } => {
                let (p, w) = (preset.as_ref().unwrap(), world.as_ref().unwrap());
                Ok(silvr_core::synthetic::sensors::render_camera(
                    w,
                    &p.rig.cameras[*index].model,
                    pose,
                    silvr_core::synthetic::sensors::RenderOptions {
                        supersample: p.supersample,
                        noise_std: 0.0,
                        seed: 0,
                    },
                )
                .rgb)
            }
            Photo::File(f) => image::open(f)
                .with_context(|| format!("reading {}", f.display()))
                .map(|im| im.to_rgb8().pixels().map(|p| p.0).collect()),
        };
        match rgb {
            Ok(rgb) if rgb.len() == (v.model.width * v.model.height) as usize => {
                photos.push(rgb);
                kept.push((i, a, b));
            }
            Ok(rgb) => notes.push(format!(
                "{}: its photo has {} pixels, the camera {}x{}; left out",
                v.name,
                rgb.len(),
                v.model.width,
                v.model.height
            )),
            Err(e) => notes.push(format!("{}: {e:#}; left out", v.name)),
        }
    }
    let chosen = kept;
    // Renders, one submap's field loaded at a time: renders[c] = [nearest, second], each (RGB, valid).
    type Render = Option<(Vec<[u8; 3]>, Vec<bool>)>;
    let mut renders: Vec<[Render; 2]> = vec![[None, None]; chosen.len()];
    let (engine, adapter) = crate::backend::backend_for(job.backend)?;
    let gpu = match engine {
        silvr_core::train::Backend::Wgpu(g) => Some(g),
        silvr_core::train::Backend::Cpu => None,
    };
    // The submaps name their world's images from beside them.
    let root = crate::data_root(job.dataset, job.out)?;
    for (k, (name, dir)) in job.submaps.iter().enumerate() {
        let wanted: Vec<(usize, usize)> = chosen
            .iter()
            .enumerate()
            .flat_map(|(c, (_, a, b))| [(a.0 == k).then_some((c, 0)), (b.0 == k).then_some((c, 1))])
            .flatten()
            .collect();
        if wanted.is_empty() {
            continue;
        }
        let dataset = job.out.join("submaps").join(name);
        let mut data = TrainData::load_within(
            &dataset,
            Some(&root),
            &LoadOptions {
                downscale: 1,
                skip_lidar: true,
            },
        )?;
        let mut index = Vec::new();
        for &(c, _) in &wanted {
            let v = &path[chosen[c].0];
            index.push(data.add_view(&v.name, &v.model, &v.pose, photos[c].clone())?);
        }
        let ck = Checkpoint::load(&dir.join("checkpoint.ckpt"))?;
        let backend = match &gpu {
            Some(g) => silvr_core::train::Backend::Wgpu(g.clone()),
            None => silvr_core::train::Backend::Cpu,
        };
        let mut trainer = Trainer::resume(data, ck, backend)
            .with_context(|| format!("loading {}", dir.display()))?;
        for (&(c, slot), &i) in wanted.iter().zip(&index) {
            let v = pollster::block_on(trainer.render_view(i, false))
                .with_context(|| format!("rendering {} with {name}", path[chosen[c].0].name))?;
            renders[c][slot] = Some((v.rgb, v.valid));
        }
    }
    // Blend, score, write.
    let tmp = crate::submaps::staging(&job.out.join("renders"))?;
    let mut views = Vec::new();
    for (c, &(i, (k1, d1), (k2, d2))) in chosen.iter().enumerate() {
        let v = &path[i];
        let [Some((a, valid)), Some((b, _))] = &renders[c] else {
            anyhow::bail!("view {} was not rendered by both submaps", v.name);
        };
        let (w, h) = (v.model.width, v.model.height);
        let alpha_silvr = BlendRule::Silvr { radius }.alpha(d1, Some(d2));
        let alpha_idw = BlendRule::InverseDistance {
            radius,
            power: IDW_POWER,
        }
        .alpha(d1, Some(d2));
        let silvr = blend::blend_rgb(a, b, alpha_silvr);
        let idw = blend::blend_rgb(a, b, alpha_idw);
        let photo = &photos[c];
        let strip_name = format!("{}.png", v.name);
        let strip = image::RgbImage::from_fn(4 * w, h, |x, y| {
            let p = (y * w + x % w) as usize;
            image::Rgb(match x / w {
                0 => photo[p],
                1 => a[p],
                2 => b[p],
                _ => silvr[p],
            })
        });
        strip
            .save(tmp.join(&strip_name))
            .with_context(|| format!("writing {}", strip_name))?;
        views.push(ViewReport {
            name: v.name.clone(),
            nearest: job.submaps[k1].0.clone(),
            nearest_m: d1,
            second: job.submaps[k2].0.clone(),
            second_m: d2,
            alpha_silvr,
            alpha_idw,
            nearest_only: score(a, photo, valid, w, h)?,
            second_only: score(b, photo, valid, w, h)?,
            blended_silvr: score(&silvr, photo, valid, w, h)?,
            blended_idw: score(&idw, photo, valid, w, h)?,
            strip: job.out.join("renders").join(&strip_name),
        });
    }
    let mean = |f: &dyn Fn(&ViewReport) -> f64| silvr_core::job::mean(views.iter().map(f));
    let report = RendersReport {
        computed_from: job.key.clone(),
        path: kind.into(),
        path_views: path.len(),
        boundary_views: n,
        backend: adapter,
        mean_psnr_nearest: mean(&|v| v.nearest_only.psnr),
        mean_psnr_blended_silvr: mean(&|v| v.blended_silvr.psnr),
        mean_psnr_blended_idw: mean(&|v| v.blended_idw.psnr),
        views,
        notes,
    };
    std::fs::write(
        tmp.join("report.json"),
        serde_json::to_string_pretty(&report)?,
    )?;
    let dest = job.out.join("renders");
    let _ = std::fs::remove_dir_all(&dest);
    std::fs::rename(&tmp, &dest)
        .with_context(|| format!("moving {} into place", dest.display()))?;
    Ok(report)
}

/// The renders of an earlier run, when they were computed from `key`.
pub fn reuse(out: &Path, key: &RenderKey) -> Option<RendersReport> {
    let bytes = std::fs::read(out.join("renders/report.json")).ok()?;
    let r: RendersReport = serde_json::from_slice(&bytes).ok()?;
    (r.computed_from == *key).then_some(r)
}
