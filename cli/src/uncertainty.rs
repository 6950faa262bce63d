//! `silvr uncertainty`: the perturbation-field Laplace pass over a trained field (paper §Epistemic
//! uncertainty), its read-out into the exported points and held-out views, the default filter, and, with
//! ground truth, sparsification curves, AUSE and plots.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use silvr_core::eval::{self, metrics::GeometryOptions, plot};
use silvr_core::pointcloud::{read_ply, write_ply, PointCloud};
use silvr_core::train::checkpoint::Checkpoint;
use silvr_core::train::data::{LoadOptions, TrainData};
use silvr_core::train::Trainer;
use silvr_core::uncertainty::{self, sparsify, Fisher, Modality, UncertaintyConfig};

/// The PLY fields the read-out writes (log10 posterior std, metres).
pub const FIELDS: [(&str, Modality); 3] = [
    ("log_std_colour", Modality::Colour),
    ("log_std_depth", Modality::Depth),
    ("log_std_combined", Modality::Combined),
];

use silvr_core::job::{self, DirSink, Observer, Progress};
use std::cell::RefCell;
use std::rc::Rc;

pub struct UncertaintyArgs {
    pub model_dir: PathBuf,
    pub dataset: Option<PathBuf>,
    pub backend: String,
    pub config: UncertaintyConfig,
    pub quiet: bool,
    /// Print the WGSL pass's per-pass timings (WGSL only).
    pub profile: bool,
}

/// What the pass produced.
pub struct UncertaintySummary {
    pub seconds: f64,
    pub fisher_path: PathBuf,
    pub points: Option<PathBuf>,
    pub filtered: Option<PathBuf>,
    pub threshold: f32,
    pub kept: usize,
    pub total: usize,
    pub rays: u64,
    pub lidar_rays: u64,
}

/// `silvr uncertainty MODEL_DIR`: loads `checkpoint.ckpt` (and the dataset recorded in `train.json`, or
/// `--dataset`), runs the pass and annotates the folder's outputs.
pub fn run(a: &UncertaintyArgs) -> Result<UncertaintySummary> {
    let ckpt = a.model_dir.join("checkpoint.ckpt");
    let ck = Checkpoint::load(&ckpt)?;
    let dataset = match &a.dataset {
        Some(d) => d.clone(),
        None => dataset_of(&a.model_dir)?,
    };
    let data = TrainData::load(
        &dataset,
        &LoadOptions {
            downscale: 1,
            skip_lidar: false,
        },
    )?;
    let options = silvr_core::gpu::GpuOptions {
        profile: a.profile,
        ..Default::default()
    };
    let backend = if a.profile {
        "wgpu"
    } else {
        a.backend.as_str()
    };
    let (engine, adapter) = crate::backend::backend_with(backend, options)?;
    if !a.quiet {
        eprintln!("uncertainty on {adapter}");
    }
    let mut trainer = Trainer::resume(data, ck, engine)?;
    let t0 = Instant::now();
    let out = annotate(&mut trainer, &a.config, &a.model_dir, a.quiet)?;
    if let silvr_core::train::Engine::Wgpu(e) = &trainer.engine {
        if a.profile {
            let rows = e.gpu.profile_take();
            crate::backend::print_profile(&rows, 1, t0.elapsed().as_secs_f64());
        }
    }
    Ok(out)
}

fn dataset_of(dir: &Path) -> Result<PathBuf> {
    let p = dir.join("train.json");
    let text = std::fs::read_to_string(&p)
        .with_context(|| format!("reading {} (or pass --dataset)", p.display()))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", p.display()))?;
    v["dataset"]
        .as_str()
        .map(PathBuf::from)
        .with_context(|| format!("{} names no dataset; pass --dataset", p.display()))
}

impl UncertaintySummary {
    /// The CLI's view of the job's summary: the files it wrote into `dir`.
    pub fn from_job(u: &silvr_core::job::UncertaintySummary, dir: &Path) -> UncertaintySummary {
        UncertaintySummary {
            seconds: u.seconds,
            fisher_path: dir.join("uncertainty.bin"),
            points: u.annotated.then(|| dir.join("points.ply")),
            filtered: u.annotated.then(|| dir.join("points_filtered.ply")),
            threshold: u.threshold,
            kept: u.kept,
            total: u.total,
            rays: u.rays,
            lidar_rays: u.lidar_rays,
        }
    }
}

/// Runs the pass on a live trainer and writes into `dir`: `uncertainty.bin` (the Fisher diagonals),
/// the read-out as fields of `points.ply` (when the folder has one), `points_filtered.ply` (default
/// threshold) and `renders/*_uncertainty.png` for the first held-out view (the job API's pass).
pub fn annotate(
    trainer: &mut Trainer,
    config: &UncertaintyConfig,
    dir: &Path,
    quiet: bool,
) -> Result<UncertaintySummary> {
    let points_path = dir.join("points.ply");
    let mut cloud = if points_path.is_file() {
        Some(read_ply(&points_path)?)
    } else {
        None
    };
    let observer: Observer = if quiet {
        job::quiet()
    } else {
        let mut last = Instant::now();
        Rc::new(RefCell::new(move |p: Progress| {
            if last.elapsed().as_secs_f64() > 5.0 || p.done == p.total {
                last = Instant::now();
                eprintln!(
                    "uncertainty batch {}/{} ({:.1} s, ETA {:.0} s)",
                    p.done,
                    p.total,
                    p.elapsed_s,
                    p.eta_s()
                );
            }
        }))
    };
    let mut sink = DirSink(dir.to_path_buf());
    let u = pollster::block_on(job::uncertainty_pass(
        trainer,
        config,
        cloud.as_mut(),
        &mut sink,
        observer,
    ))?;
    if let Some(c) = &cloud {
        write_ply_atomic(&points_path, c)?;
    }
    if !quiet {
        eprintln!(
            "uncertainty: {} rays ({} lidar) in {:.1} s; kept {}/{} points (log10 std ≤ {:.2})",
            u.rays, u.lidar_rays, u.seconds, u.kept, u.total, u.threshold
        );
    }
    Ok(UncertaintySummary::from_job(&u, dir))
}

/// Sparsification curves, AUSE (per modality, and a random ordering's), plots and the filtered cloud's
/// geometry, against the ground truth in `gt_dir`, the clouds mapped into its frame by `opts`
/// (`reconstruction_to_gt`: the field trained on estimated poses). `trained_on` is the dataset the field
/// was trained on (its poses place the per-label read-out). Writes `sparsification.json` and PNG plots
/// into `dir`; returns the report's `uncertainty` block.
pub fn evaluate(
    dir: &Path,
    gt_dir: &Path,
    trained_on: &Path,
    opts: &GeometryOptions,
    summary: &UncertaintySummary,
) -> Result<serde_json::Value> {
    let points = summary
        .points
        .as_ref()
        .context("the uncertainty pass found no points.ply to evaluate")?;
    let opts = opts.clone();
    let ev = eval::evaluate_files_full(points, gt_dir, &opts)?;
    let errors = &ev.rec_to_gt;
    let mut curves = serde_json::Map::new();
    let mut series_data = Vec::new();
    let mut out = serde_json::json!({});
    for (field, m) in FIELDS {
        let u = ev
            .reconstruction
            .scalar(field)
            .with_context(|| format!("{} lost its {field} field", points.display()))?;
        let s = sparsify::sparsification(errors, u)
            .context("no evaluated points for the sparsification")?;
        out[format!("ause_{}", m.name())] = s.ause.into();
        curves.insert(m.name().into(), serde_json::to_value(&s)?);
        series_data.push((m.name(), s));
        // Error against uncertainty.
        let uu: Vec<f64> = u.iter().map(|&v| v as f64).collect();
        let img = plot::density_chart(
            &format!("error vs {} uncertainty", m.name()),
            "log10 std (m)",
            "distance to GT (m)",
            &uu,
            errors,
        );
        write(
            &dir.join(format!("error_vs_{}.png", m.name())),
            &plot::png_bytes(&img),
        )?;
    }
    let random = sparsify::random_ause(errors, 5, 17);
    out["ause_random"] = random.into();
    let fr = series_data[0].1.fractions.clone();
    let mut series = vec![plot::Series {
        name: "oracle",
        x: &fr,
        y: &series_data[0].1.oracle,
        colour: plot::PALETTE[0],
    }];
    for (k, (name, s)) in series_data.iter().enumerate() {
        series.push(plot::Series {
            name,
            x: &fr,
            y: &s.uncertainty,
            colour: plot::PALETTE[1 + k],
        });
    }
    let img = plot::line_chart(
        "sparsification (points)",
        "fraction of points removed (most uncertain first)",
        "mean distance to GT (normalised)",
        &series,
    );
    write(&dir.join("sparsification.png"), &plot::png_bytes(&img))?;
    let sp = serde_json::json!({
        "error": "distance to ground truth (m)",
        "points_evaluated": errors.len(),
        "curves": curves,
        "ause_random": random,
    });
    write(
        &dir.join("sparsification.json"),
        serde_json::to_string_pretty(&sp)?.as_bytes(),
    )?;
    if let Some(f) = &summary.filtered {
        let fe = eval::evaluate_files(f, gt_dir, &opts)?;
        let mut g = crate::report_json(&fe);
        if let Some(o) = g.as_object_mut() {
            o.insert(
                "threshold_log_std_combined".into(),
                summary.threshold.into(),
            );
            o.insert("kept_points".into(), summary.kept.into());
            o.insert("total_points".into(), summary.total.into());
        }
        out["filtered"] = g;
    }
    let fisher = Fisher::from_bytes(
        &std::fs::read(&summary.fisher_path)
            .with_context(|| format!("reading {}", summary.fisher_path.display()))?,
        &summary.fisher_path.display().to_string(),
    )?;
    if let Some(v) = by_label(trained_on, &fisher)? {
        out["by_label"] = v;
    }
    out["seconds"] = summary.seconds.into();
    out["file"] = summary.fisher_path.display().to_string().into();
    out["rays"] = summary.rays.into();
    out["lidar_rays"] = summary.lidar_rays.into();
    out["plots"] = serde_json::json!([
        "sparsification.png",
        "error_vs_colour.png",
        "error_vs_depth.png",
        "error_vs_combined.png"
    ]);
    Ok(out)
}

/// Mean read-out per semantic label at the exact surface points of the training views (synthetic
/// datasets: `gt/semantic` and `gt/depth` beside `images/`), plus points 5 m under the visible surfaces,
/// which no ray reaches (they should read the prior). Each label is also summarised per band of range
/// from the camera ([`RANGE_BANDS_M`]): how many rays see a grid cell, and at what footprint, falls with
/// range, so comparing surfaces in the same band separates what their texture does to the uncertainty from
/// where they stand (the road runs under every camera, the facades are metres away). `None` for datasets
/// without that ground truth.
pub fn by_label(dataset: &Path, fisher: &Fisher) -> Result<Option<serde_json::Value>> {
    use silvr_core::synthetic::world::Label;
    let data = TrainData::load(
        dataset,
        &LoadOptions {
            downscale: 1,
            skip_lidar: true,
        },
    )?;
    let scale = data.frame.scale as f32;
    let mut per_label: Vec<Vec<[f32; 3]>> = vec![Vec::new(); Label::ALL.len()];
    let mut band_of: Vec<Vec<usize>> = vec![Vec::new(); Label::ALL.len()];
    let mut under = Vec::new();
    for &i in &data.train {
        let full = data.root.join(&data.images[i].name);
        let (Some(sem), Some(dep)) = (
            crate::synthetic_gt_file(&full, "semantic"),
            crate::synthetic_gt_file(&full, "depth"),
        ) else {
            return Ok(None);
        };
        let sem = image::open(&sem)
            .with_context(|| format!("reading {}", sem.display()))?
            .to_luma8();
        let dep = image::open(&dep)
            .with_context(|| format!("reading {}", dep.display()))?
            .to_luma16();
        let (w, h) = sem.dimensions();
        for y in (0..h).step_by(3) {
            for x in (0..w).step_by(3) {
                let label = sem.get_pixel(x, y).0[0] as usize;
                let range = dep.get_pixel(x, y).0[0];
                if label == Label::Sky as usize
                    || label >= per_label.len()
                    || range == 0
                    || range == u16::MAX
                {
                    continue;
                }
                let Some((o, d)) = data.ray(i, x, y) else {
                    continue;
                };
                let metres = range as f32 / 256.0;
                let t = metres * scale;
                per_label[label].push([0, 1, 2].map(|k| o[k] + d[k] * t));
                band_of[label].push(range_band(metres));
                if label == Label::Road as usize {
                    let mut p = [0, 1, 2].map(|k| o[k] + d[k] * t);
                    // 5 m below, in the scene frame (z up, as the world).
                    p[2] -= 5.0 * scale;
                    under.push(p);
                }
            }
        }
    }
    let mean = |v: &[f32]| v.iter().map(|&x| x as f64).sum::<f64>() / v.len().max(1) as f64;
    let summary = |u: &uncertainty::PointUncertainty, keep: &dyn Fn(usize) -> bool| {
        let pick = |v: &[f32]| -> Vec<f32> {
            v.iter()
                .enumerate()
                .filter(|(i, _)| keep(*i))
                .map(|(_, &x)| x)
                .collect()
        };
        let colour = pick(&u.colour);
        serde_json::json!({
            "points": colour.len(),
            "colour": mean(&colour),
            "depth": mean(&pick(&u.depth)),
            "combined": mean(&pick(&u.combined)),
        })
    };
    let mut out = serde_json::json!({});
    for l in Label::ALL {
        let pts = &per_label[l as usize];
        if pts.is_empty() {
            continue;
        }
        let u = uncertainty::read_out(fisher, pts, data.frame.scale);
        let mut entry = summary(&u, &|_| true);
        let bands = &band_of[l as usize];
        for (b, name) in RANGE_BAND_NAMES.iter().enumerate() {
            if bands.contains(&b) {
                entry["by_range_m"][*name] = summary(&u, &|i| bands[i] == b);
            }
        }
        out[l.name()] = entry;
    }
    let u = uncertainty::read_out(fisher, &under, data.frame.scale);
    out["under_road_5m"] = summary(&u, &|_| true);
    out["prior"] = (fisher.prior_log_std() as f64 - data.frame.scale.log10()).into();
    Ok(Some(out))
}

/// Upper edges (metres) of the range bands of [`by_label`]; the last band is open.
pub const RANGE_BANDS_M: [f32; 3] = [5.0, 10.0, 20.0];
const RANGE_BAND_NAMES: [&str; 4] = ["0-5", "5-10", "10-20", "20+"];

fn range_band(metres: f32) -> usize {
    RANGE_BANDS_M
        .iter()
        .position(|&edge| metres < edge)
        .unwrap_or(RANGE_BANDS_M.len())
}

fn write(path: &Path, bytes: &[u8]) -> Result<()> {
    silvr_core::dataset::write_atomic(path, bytes)
        .with_context(|| format!("writing {}", path.display()))
}

fn write_ply_atomic(path: &Path, cloud: &PointCloud) -> Result<()> {
    write_ply(path, cloud).with_context(|| format!("writing {}", path.display()))
}
