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
use silvr_core::uncertainty::reliability::{self, format_metres, Reliability};
use silvr_core::uncertainty::{self, sparsify, Fisher, Modality, Posterior, UncertaintyConfig};

/// The PLY fields the read-out writes (log10 σ in metres; DATASET.md).
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
    /// The folder the dataset's files may lie anywhere under (`None`: its own folder).
    pub data_root: Option<PathBuf>,
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
    // The pixels the field was trained on: its run's downscale (the posterior is given those observations).
    let downscale = downscale_of(&a.model_dir);
    let data = TrainData::load_within(
        &dataset,
        a.data_root.as_deref(),
        &LoadOptions {
            downscale,
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

/// The image downscale a `silvr train` run recorded in its `train.json` (1 where it recorded none: runs
/// before 2026-12-05, or a folder without one).
pub fn downscale_of(dir: &Path) -> u32 {
    std::fs::read(dir.join("train.json"))
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .and_then(|v| v["downscale"].as_u64())
        .map_or(1, |d| d.clamp(1, 64) as u32)
}

/// The dataset a `silvr train` run names in its `train.json`.
pub fn dataset_of(dir: &Path) -> Result<PathBuf> {
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

/// What σ means, in one sentence (the CLI's print and the report's uncertainty section).
pub const SIGMA_MEANS: &str = "σ is the posterior standard deviation, in metres, of where the field puts a \
     surface point: the Laplace posterior of a perturbation field given every pixel and lidar return \
     trained on, with the spread of the point's own ray added in quadrature, the two scaled by factors \
     fitted per read-out so that 1σ and 2σ cover 68 % and 95 % of lidar returns held out of training";

/// What the pass did, in metres: the rays it sampled and the observations the posterior stands for, the
/// calibration, and the filter (`silvr uncertainty` and `silvr train` print the same).
pub fn print_summary(u: &job::UncertaintySummary, config: &UncertaintyConfig) {
    eprintln!(
        "uncertainty: {} × {} sampled rays of each kind, the posterior over {} pixels and {} lidar \
         returns, in {:.1} s",
        config.batches, config.rays_per_batch, u.rays, u.lidar_rays, u.seconds
    );
    eprintln!(
        "uncertainty: {}",
        calibration_line(&u.calibration, u.prior_sigma_m)
    );
    if let Some(h) = &u.held_out_check {
        if let [Some(c), Some(d), Some(b)] = h.ause {
            eprintln!(
                "uncertainty: AUSE of the held-out residuals (calibrated): colour {c:.3}, depth {d:.3}, \
                 combined {b:.3} (random {:.3})",
                h.ause_random
            );
        }
        for (post, rows) in [("raw", &h.raw), ("calibrated", &h.calibrated)] {
            if let Some(Some(r)) = rows.last() {
                eprintln!(
                    "uncertainty: on {} held-out lidar returns not fitted on, combined σ ({post}): median \
                     {} against a median residual of {}; {:.1} % within 1σ, {:.1} % within 2σ",
                    h.returns,
                    format_metres(r.median_sigma_m),
                    format_metres(r.median_error_m),
                    100.0 * r.coverage_1sigma,
                    100.0 * r.coverage_2sigma
                );
            }
        }
    }
    if u.annotated {
        eprintln!(
            "uncertainty: kept {}/{} points (σ ≤ {}{}); {} unconstrained (σ near the prior)",
            u.kept,
            u.total,
            format_metres(10f64.powf(u.threshold as f64)),
            if config.max_sigma_m.is_some() {
                ", --max-sigma"
            } else {
                ", Tukey's fence"
            },
            u.unconstrained
        );
    }
}

/// The run's calibration as printed: each read-out's factors (on the Laplace σ and on the ray spread) and
/// the coverage it reached.
pub fn calibration_line(c: &uncertainty::Calibration, prior_sigma_m: f64) -> String {
    if !c.is_calibrated() {
        return format!(
            "σ is the raw Laplace posterior (no held-out lidar returns to calibrate it on); prior σ {}",
            format_metres(prior_sigma_m)
        );
    }
    let parts: Vec<String> = Modality::ALL
        .iter()
        .enumerate()
        .map(|(i, m)| {
            format!(
                "{} ×{:.3e}, spread ×{:.2} ({:.1} % within 1σ)",
                m.name(),
                c.factor[i],
                c.spread[i],
                100.0 * c.coverage[i]
            )
        })
        .collect();
    format!(
        "σ calibrated on {} held-out lidar returns: {}; prior σ {}",
        c.returns,
        parts.join(", "),
        format_metres(prior_sigma_m)
    )
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
        print_summary(&u, config);
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
    data_root: Option<&Path>,
    opts: &GeometryOptions,
    summary: &UncertaintySummary,
) -> Result<serde_json::Value> {
    let points = summary
        .points
        .as_ref()
        .context("the uncertainty pass found no points.ply to evaluate")?;
    let opts = opts.clone();
    let fisher = Fisher::from_bytes(
        &std::fs::read(&summary.fisher_path)
            .with_context(|| format!("reading {}", summary.fisher_path.display()))?,
        &summary.fisher_path.display().to_string(),
    )?;
    // The raw Laplace read-out beside the calibrated one the file holds (in memory only), so both are
    // scored on the same evaluated points.
    let mut cloud = read_ply(points)?;
    add_raw_fields(&mut cloud, |_| Some(&fisher));
    // BayesRays' per-ray read-out of the same Fisher (1/(H/N + 1e-4/L³): what log_std meant before
    // 2026-12-04), for its AUSE beside the metric read-out's on the same points.
    let n = fisher.rays.max(1) as f32;
    let per_ray = Fisher {
        colour: fisher.colour.iter().map(|h| h / n).collect(),
        depth: fisher.depth.iter().map(|h| h / n).collect(),
        prior: 1e-4 / (fisher.cells as f64).powi(3),
        calibration: uncertainty::Calibration::RAW,
        ..fisher.clone()
    };
    let old = per_ray.read_out_metric(Posterior::Raw, &cloud.positions);
    for m in Modality::ALL {
        cloud.set_scalar(&format!("per_ray_{}", m.field()), old.of(m).to_vec());
    }
    let truth = eval::GroundTruth::load(gt_dir)?;
    let ev = truth.evaluate(&cloud, &opts)?;
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
    for m in Modality::ALL {
        if let Some(u) = ev.reconstruction.scalar(&format!("per_ray_{}", m.field())) {
            if let Some(s) = sparsify::sparsification(errors, u) {
                out["ause_per_ray_readout"][m.name()] = s.ause.into();
            }
        }
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
    let at = uncertainty::unconstrained_log_std(fisher.prior_sigma_m());
    let surface = truth.surface_distances(&ev.reconstruction.positions);
    let rel = reliability_block(dir, &ev.reconstruction, &surface, at)?;
    out["reliability"] = rel;
    out["sigma_means"] = SIGMA_MEANS.into();
    out["calibration"] = serde_json::to_value(&fisher.calibration)?;
    out["prior_sigma_m"] = fisher.prior_sigma_m().into();
    if let Some(v) = by_label(trained_on, data_root, &fisher)? {
        out["by_label"] = v;
    }
    out["seconds"] = summary.seconds.into();
    out["file"] = summary.fisher_path.display().to_string().into();
    out["rays"] = summary.rays.into();
    out["lidar_rays"] = summary.lidar_rays.into();
    out["plots"] = serde_json::json!([
        "reliability.png",
        "sparsification.png",
        "error_vs_colour.png",
        "error_vs_depth.png",
        "error_vs_combined.png"
    ]);
    Ok(out)
}

/// The in-memory field of a raw read-out (`raw_log_std_*`).
fn raw_field(m: Modality) -> String {
    format!("raw_{}", m.field())
}

/// Adds the raw Laplace read-out (`raw_log_std_*`, in memory only) beside the calibrated fields of a
/// cloud: each point read from `fisher_of(its submap id)` (0 without a `submap` field); points whose
/// Fisher is missing get NaN.
pub fn add_raw_fields<'a>(cloud: &mut PointCloud, fisher_of: impl Fn(usize) -> Option<&'a Fisher>) {
    let n = cloud.len();
    let submap: Vec<usize> = match cloud.scalar("submap") {
        Some(s) => s.iter().map(|&v| v.max(0.0) as usize).collect(),
        None => vec![0; n],
    };
    let mut raw: Vec<Vec<f32>> = vec![vec![f32::NAN; n]; 3];
    let mut ids = submap.clone();
    ids.sort_unstable();
    ids.dedup();
    for id in ids {
        let Some(f) = fisher_of(id) else { continue };
        let idx: Vec<usize> = (0..n).filter(|&i| submap[i] == id).collect();
        let pts: Vec<glam::DVec3> = idx.iter().map(|&i| cloud.positions[i]).collect();
        let u = f.read_out_metric(Posterior::Raw, &pts);
        for (k, m) in Modality::ALL.iter().enumerate() {
            for (j, &i) in idx.iter().enumerate() {
                raw[k][i] = u.of(*m)[j];
            }
        }
    }
    for (m, v) in Modality::ALL.iter().zip(raw) {
        cloud.set_scalar(&raw_field(*m), v);
    }
}

/// The reliability of every read-out, raw and calibrated, on the evaluated points (`cloud` carries
/// both as fields — [`add_raw_fields`] —, `errors` their distances to the GT; `at` the log-std from which a
/// point is unconstrained): printed as tables, written as `reliability.json` and charted in
/// `reliability.png` in `dir`; returns the JSON.
pub fn reliability_block(
    dir: &Path,
    cloud: &PointCloud,
    errors: &[f64],
    at: f32,
) -> Result<serde_json::Value> {
    let mut out = serde_json::json!({
        "error": "distance to the ground-truth surface (m): to the plane of the 8 nearest GT samples where they are planar, else to the nearest",
        "sigma_means": SIGMA_MEANS,
        "unconstrained_log_std": at,
    });
    let mut lines: Vec<(String, Vec<f64>, Vec<f64>)> = Vec::new();
    for m in Modality::ALL {
        for (post, field) in [("raw", raw_field(m)), ("calibrated", m.field().to_string())] {
            let Some(ls) = cloud.scalar(&field) else {
                continue;
            };
            let Some(r) = reliability::reliability(ls, errors, at, 10) else {
                continue;
            };
            eprint!(
                "{}",
                r.table(&format!("reliability, {} σ ({post})", m.name()))
            );
            if m == Modality::Combined || post == "calibrated" {
                lines.push((
                    format!("{} {post}", m.name()),
                    r.bins.iter().map(|b| b.rms_sigma_m.log10()).collect(),
                    r.bins.iter().map(|b| b.rms_error_m.log10()).collect(),
                ));
            }
            out[post][m.name()] = serde_json::to_value::<&Reliability>(&r)?;
        }
    }
    // The reliability diagram: RMS error against RMS σ per bin, log-log, with the identity line.
    let (lo, hi) = lines
        .iter()
        .flat_map(|(_, x, y)| x.iter().chain(y))
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    if lo.is_finite() && hi > lo {
        let ident = [lo, hi];
        let mut series = vec![plot::Series {
            name: "identity",
            x: &ident,
            y: &ident,
            colour: plot::PALETTE[0],
        }];
        for (k, (name, x, y)) in lines.iter().enumerate() {
            series.push(plot::Series {
                name,
                x,
                y,
                colour: plot::PALETTE[1 + k % (plot::PALETTE.len() - 1)],
            });
        }
        let img = plot::line_chart(
            "reliability: RMS error vs predicted σ per decile of σ",
            "log10 RMS predicted σ (m)",
            "log10 RMS error (m)",
            &series,
        );
        write(&dir.join("reliability.png"), &plot::png_bytes(&img))?;
    }
    write(
        &dir.join("reliability.json"),
        serde_json::to_string_pretty(&out)?.as_bytes(),
    )?;
    Ok(out)
}

/// Mean raw Laplace read-out (k = 1, no ray spread: what the field's information alone says, since these
/// points are not rays' ends) per semantic label at the exact surface points of the training views (synthetic
/// datasets: `gt/semantic` and `gt/depth` beside `images/`), plus points 5 m under the visible surfaces,
/// which no ray reaches (they should read the prior). Each label is also summarised per band of range
/// from the camera ([`RANGE_BANDS_M`]): how many rays see a grid cell, and at what footprint, falls with
/// range, so comparing surfaces in the same band separates what their texture does to the uncertainty from
/// where they stand (the road runs under every camera, the facades are metres away). `None` for datasets
/// without that ground truth.
pub fn by_label(
    dataset: &Path,
    data_root: Option<&Path>,
    fisher: &Fisher,
) -> Result<Option<serde_json::Value>> {
    use silvr_core::synthetic::world::Label;
    let data = TrainData::load_within(
        dataset,
        data_root,
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
        let u = read_scene(fisher, pts);
        let mut entry = summary(&u, &|_| true);
        let bands = &band_of[l as usize];
        for (b, name) in RANGE_BAND_NAMES.iter().enumerate() {
            if bands.contains(&b) {
                entry["by_range_m"][*name] = summary(&u, &|i| bands[i] == b);
            }
        }
        out[l.name()] = entry;
    }
    let u = read_scene(fisher, &under);
    out["under_road_5m"] = summary(&u, &|_| true);
    out["prior"] = fisher.prior_sigma_m().log10().into();
    out["read_out"] = "raw Laplace σ (k = 1, no ray spread), log10 metres".into();
    Ok(Some(out))
}

/// The raw Laplace read-outs at scene-frame points: the calibrated k is fitted beside the rays' spread
/// (a), which points that end no ray lack, so k alone would understate σ there.
fn read_scene(fisher: &Fisher, pts: &[[f32; 3]]) -> uncertainty::PointUncertainty {
    let r = |m| fisher.read_out_scene(m, Posterior::Raw, pts);
    uncertainty::PointUncertainty {
        colour: r(Modality::Colour),
        depth: r(Modality::Depth),
        combined: r(Modality::Combined),
    }
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

#[cfg(test)]
mod tests {
    use super::downscale_of;

    /// `silvr uncertainty` loads the images at the downscale the field was trained at, read from the run's
    /// `train.json`; runs that recorded none (or a folder without one) load full size.
    #[test]
    fn the_pass_reads_the_runs_downscale() {
        let dir = std::env::temp_dir().join(format!("silvr-downscale-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        assert_eq!(downscale_of(&dir), 1, "no train.json");
        let put = |v: &str| std::fs::write(dir.join("train.json"), v).unwrap();
        put(r#"{"dataset": "d", "downscale": 2}"#);
        assert_eq!(downscale_of(&dir), 2);
        put(r#"{"dataset": "d"}"#);
        assert_eq!(downscale_of(&dir), 1, "recorded none");
        put(r#"{"downscale": 0}"#);
        assert_eq!(downscale_of(&dir), 1, "clamped");
        put("not json");
        assert_eq!(downscale_of(&dir), 1);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
