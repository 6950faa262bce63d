//! `silvr train`: fits a radiance field to a dataset, with progress, checkpoints, held-out scores, renders
//! and the exported point cloud.

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::backend::{backend_for, backend_with, print_profile};
use anyhow::{bail, Context, Result};
use silvr_core::field::model::ModelConfig;
use silvr_core::gpu::{Gpu, GpuOptions};
use silvr_core::job::{self, DirSink, FinishOptions, JobSpec, Observer, Progress, Sink, TrainJob};
use silvr_core::train::checkpoint::Checkpoint;
use silvr_core::train::data::{LoadOptions, TrainData};
use silvr_core::train::export::ViewScore;
use silvr_core::train::{Backend, Mode, TrainConfig, Trainer};
use std::cell::RefCell;
use std::rc::Rc;

/// Model sizes by name (see [`ModelConfig::preset`]).
pub fn model_preset(name: &str, images: usize) -> Result<ModelConfig> {
    Ok(ModelConfig::preset(name, images)?)
}

pub struct TrainArgs {
    pub dataset: PathBuf,
    /// The folder the dataset's files may lie anywhere under (`None`: its own folder; see
    /// [`TrainData::load_within`]).
    pub data_root: Option<PathBuf>,
    pub mode: Mode,
    pub steps: u32,
    pub rays: usize,
    pub model: String,
    pub out: PathBuf,
    pub resume: Option<PathBuf>,
    pub checkpoint_every: u32,
    pub backend: String,
    pub downscale: u32,
    pub seed: u64,
    pub export_rays: usize,
    /// Held-out views to render and score (`None`: all).
    pub render_views: Option<usize>,
    pub export_depth: silvr_core::train::export::ExportDepth,
    pub quiet: bool,
    /// Normals for the first held-out view and the exported points (six more density evaluations per
    /// sample).
    pub view_normals: bool,
    pub depth_sigma: Option<(f32, f32)>,
    /// Run the uncertainty pass after training (annotates points.ply, writes uncertainty.bin).
    pub uncertainty: Option<silvr_core::uncertainty::UncertaintyConfig>,
}

/// What a finished training run measured.
pub struct TrainSummary {
    pub train_s: f64,
    pub steps: u32,
    pub views: Vec<ViewScore>,
    pub points: Option<PathBuf>,
    /// `wgpu` or `cpu`.
    pub backend: String,
    /// The adapter (or, on the CPU, why the CPU).
    pub adapter: String,
    pub uncertainty: Option<crate::uncertainty::UncertaintySummary>,
    /// The engine each stage ran on (`wgpu` or `cpu`): training, renders, export, uncertainty.
    pub stages: serde_json::Value,
}

pub fn run(a: &TrainArgs) -> Result<TrainSummary> {
    let t_load = Instant::now();
    let data = TrainData::load_within(
        &a.dataset,
        a.data_root.as_deref(),
        &LoadOptions {
            downscale: a.downscale,
            skip_lidar: a.mode == Mode::Vision,
        },
    )?;
    for s in &data.skipped {
        eprintln!("warning: skipped {s}");
    }
    if !a.quiet {
        eprintln!(
            "loaded {} images ({} train, {} held out) in {:.1} s; scene scale {:.4} /m",
            data.images.len(),
            data.train.len(),
            data.val.len(),
            t_load.elapsed().as_secs_f64(),
            data.frame.scale
        );
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let (engine, adapter) = backend_for(&a.backend)?;
    let backend = match engine {
        Backend::Cpu => "cpu",
        Backend::Wgpu(_) => "wgpu",
    }
    .to_string();
    if !a.quiet {
        eprintln!("backend: {backend}, {adapter}");
    }
    let mut job = match &a.resume {
        Some(p) => {
            let job = TrainJob::resume(data, Checkpoint::load(p)?, engine, a.steps)?;
            if !a.quiet {
                eprintln!("resumed {} at step {}", p.display(), job.trainer.step);
            }
            job
        }
        None => {
            let spec = JobSpec {
                mode: a.mode,
                model: a.model.clone(),
                steps: a.steps,
                rays: a.rays,
                seed: a.seed,
                depth_sigma: a.depth_sigma,
            };
            TrainJob::new(data, &spec, engine)?
        }
    };
    let mut sink = DirSink(a.out.clone());
    let ckpt = a.out.join("checkpoint.ckpt");
    let mut last_print = Instant::now();
    while !job.done() {
        let r = match pollster::block_on(job.step()) {
            Ok(r) => r,
            Err(e) => {
                let resume = match Checkpoint::load(&ckpt) {
                    Ok(ck) => format!(
                        "the last checkpoint, at step {}, is {}: rerun with --resume {}",
                        ck.header.step,
                        ckpt.display(),
                        ckpt.display()
                    ),
                    Err(_) => "no checkpoint was written yet (--checkpoint-every N writes one every N steps)"
                        .to_string(),
                };
                bail!(
                    "training stopped at step {}: {e}\n{resume}",
                    job.trainer.step
                );
            }
        };
        if !a.quiet && (last_print.elapsed().as_secs_f64() > 5.0 || r.step == r.steps) {
            last_print = Instant::now();
            eprintln!(
                "step {}/{} loss {:.4} psnr {:.2} dB depth {:.4} il {:.4} ({:.1} s, {:.0} rays/s, ETA {:.0} s)",
                r.step, r.steps, r.loss, r.psnr, r.depth, r.interlevel, r.train_s, r.rays_per_s, r.eta_s
            );
        }
        if a.checkpoint_every > 0 && r.step % a.checkpoint_every == 0 {
            sink.put(
                "checkpoint.ckpt",
                &pollster::block_on(job.checkpoint_bytes())?,
            )?;
        }
    }
    let observer: Observer = if a.quiet {
        job::quiet()
    } else {
        let mut last = Instant::now();
        Rc::new(RefCell::new(move |p: Progress| {
            if last.elapsed().as_secs_f64() > 5.0 {
                last = Instant::now();
                eprintln!(
                    "  {} {}/{} ({:.0}/s, ETA {:.0} s)",
                    p.stage,
                    p.done,
                    p.total,
                    p.done as f64 / p.elapsed_s.max(1e-9),
                    p.eta_s()
                );
            }
        }))
    };
    let opts = FinishOptions {
        dataset: a.dataset.display().to_string(),
        render_views: a.render_views,
        view_normals: a.view_normals,
        export_rays: a.export_rays,
        export_depth: a.export_depth,
        uncertainty: a.uncertainty.clone(),
        adapter: adapter.clone(),
    };
    let s = pollster::block_on(job.finish(&opts, &mut sink, observer))?;
    if !a.quiet {
        if let Some(r) = s.render_rays_per_s {
            eprintln!("rendered {} held-out views: {r:.0} rays/s", s.heldout.len());
        }
        if s.points.is_some() {
            eprintln!("exported {} points from {} rays", s.exported, a.export_rays);
        }
        if let (Some(u), Some(cfg)) = (&s.uncertainty, &a.uncertainty) {
            crate::uncertainty::print_summary(u, cfg);
        }
    }
    if !a.quiet && s.heldout.is_empty() && !job.trainer.data.val.is_empty() {
        eprintln!(
            "trained {} steps in {:.1} s; held-out views not rendered (--render-views 0)",
            s.steps, s.train_s
        );
    } else if !a.quiet && s.heldout.is_empty() {
        eprintln!(
            "trained {} steps in {:.1} s; the dataset holds out no view, so there is no held-out PSNR",
            s.steps, s.train_s
        );
    } else if !a.quiet {
        eprintln!(
            "trained {} steps in {:.1} s; held-out PSNR {:.2} dB, SSIM {:.3} ({} views)",
            s.steps,
            s.train_s,
            s.heldout_psnr_mean,
            s.heldout_ssim_mean,
            s.heldout.len()
        );
    }
    let points = s.points.as_ref().map(|p| a.out.join(p));
    let uncertainty = s
        .uncertainty
        .as_ref()
        .map(|u| crate::uncertainty::UncertaintySummary::from_job(u, &a.out));
    Ok(TrainSummary {
        uncertainty,
        train_s: s.train_s,
        steps: s.steps,
        views: s.heldout.clone(),
        points,
        backend,
        adapter,
        stages: serde_json::to_value(&s.backends)?,
    })
}

pub use silvr_core::job::mean;

pub struct BenchArgs {
    pub dataset: PathBuf,
    pub mode: Mode,
    pub backend: String,
    pub model: String,
    pub rays: usize,
    pub steps: u32,
    pub target_psnr: f64,
    pub max_seconds: f64,
    /// Steps to profile pass by pass (WGSL only), after a warm-up.
    pub profile: Option<u32>,
    pub render_checkpoint: Option<PathBuf>,
}

fn new_trainer(
    dataset: &Path,
    mode: Mode,
    model: &str,
    rays: usize,
    steps: u32,
    backend: Backend,
) -> Result<Trainer> {
    let data = TrainData::load(
        dataset,
        &LoadOptions {
            downscale: 1,
            skip_lidar: mode == Mode::Vision,
        },
    )?;
    let model = model_preset(model, data.train.len())?;
    let config = TrainConfig::for_run(mode, steps, rays, 0);
    Ok(Trainer::new(data, model, config, backend)?)
}

/// `silvr bench-train`: per-step timings (each step ends with its loss readback, so a step's time is the
/// device's), field evaluations per second, and the time to a training PSNR.
pub fn bench(a: &BenchArgs) -> Result<()> {
    if let Some(steps) = a.profile {
        return profile(a, steps);
    }
    let (backend, adapter) = backend_for(&a.backend)?;
    let mut t = new_trainer(&a.dataset, a.mode, &a.model, a.rays, a.steps, backend)?;
    let m = &t.model;
    let per_ray_levels: usize =
        m.sampler.proposal_samples.iter().sum::<usize>() + m.sampler.samples;
    let t0 = Instant::now();
    let mut step_s = Vec::new();
    let mut evals = Vec::new();
    let mut reached: Option<(u32, f64)> = None;
    while t.step < a.steps && t0.elapsed().as_secs_f64() < a.max_seconds {
        let batch_normals = if a.mode == Mode::Silvr {
            t.batch(t.step).normal_rays
        } else {
            0
        };
        let ts = Instant::now();
        pollster::block_on(t.train_step())?;
        step_s.push(ts.elapsed().as_secs_f64());
        // Field evaluations: every level's samples, plus six FD evaluations per final sample of a
        // normal ray.
        evals.push(a.rays * per_ray_levels + 6 * batch_normals * t.model.sampler.samples);
        let h = &t.history;
        if reached.is_none() && h.len() >= 20 {
            let mse = h[h.len() - 20..].iter().map(|s| s.rgb_mse).sum::<f64>() / 20.0;
            if -10.0 * mse.log10() >= a.target_psnr {
                reached = Some((t.step, t0.elapsed().as_secs_f64()));
                break;
            }
        }
    }
    // Steady state: skip the first steps (pipeline compiles, buffer allocation).
    let skip = (step_s.len() / 10)
        .clamp(1, 20)
        .min(step_s.len().saturating_sub(1));
    let tot_s: f64 = step_s[skip..].iter().sum();
    let tot_e: usize = evals[skip..].iter().sum();
    let mut sorted = step_s[skip..].to_vec();
    sorted.sort_by(f64::total_cmp);
    let median = sorted.get(sorted.len() / 2).copied().unwrap_or(f64::NAN);
    let last = &t.history[t.history.len().saturating_sub(20)..];
    let mse = last.iter().map(|s| s.rgb_mse).sum::<f64>() / last.len().max(1) as f64;
    // Inference on the same backend: the first held-out view (or a training view) rendered whole, once
    // to warm up its pipelines on a small part, then timed.
    let view = t.data.val.first().or(t.data.train.first()).copied();
    let render = match view {
        Some(i) => {
            let (rays, _) = t.view_rays(i);
            pollster::block_on(t.render(&rays[..rays.len().min(256)], false))?;
            let tr = Instant::now();
            pollster::block_on(t.render(&rays, false))?;
            let s = tr.elapsed().as_secs_f64();
            Some((rays.len(), s))
        }
        None => None,
    };
    let rays_per_s = a.rays as f64 / median;
    let render_rays_per_s = render.map(|(n, s)| n as f64 / s);
    // The same view from a trained field, whose samples concentrate on surfaces.
    let trained_render = match (&a.render_checkpoint, view) {
        (Some(p), Some(i)) => {
            let ck = Checkpoint::load(p)?;
            let data = TrainData::load(&a.dataset, &LoadOptions::default())?;
            let (backend, _) = backend_for(&a.backend)?;
            let mut tt = Trainer::resume(data, ck, backend)?;
            let (rays, _) = tt.view_rays(i);
            pollster::block_on(tt.render(&rays[..rays.len().min(256)], false))?;
            let tr = Instant::now();
            pollster::block_on(tt.render(&rays, false))?;
            Some(rays.len() as f64 / tr.elapsed().as_secs_f64())
        }
        _ => None,
    };
    let v = serde_json::json!({
        "backend": adapter,
        "dataset": a.dataset,
        "mode": a.mode.name(),
        "model": a.model,
        "rays_per_batch": a.rays,
        "steps": t.step,
        "median_step_s": median,
        "rays_per_s": rays_per_s,
        "field_samples_per_s": tot_e as f64 / tot_s,
        "render_rays": render.map(|r| r.0),
        "render_rays_per_s": render_rays_per_s,
        "render_vs_training_rays": render_rays_per_s.map(|r| r / rays_per_s),
        "trained_render_rays_per_s": trained_render,
        "trained_render_vs_training_rays": trained_render.map(|r| r / rays_per_s),
        "target_psnr": a.target_psnr,
        "reached_at_step": reached.map(|r| r.0),
        "time_to_target_s": reached.map(|r| r.1),
        "final_train_psnr_last20": -10.0 * mse.max(1e-12).log10(),
        "wall_s": t0.elapsed().as_secs_f64(),
        "note": "field samples: proposal + final samples per ray and 6 FD evaluations per final sample of a normal ray, each forward and backward; step time includes batch assembly on the CPU and the per-step loss readback",
    });
    println!("{}", serde_json::to_string_pretty(&v)?);
    Ok(())
}

/// `silvr bench-train --profile`: the WGSL step pass by pass. Three warm-up steps (pipeline compiles,
/// buffer allocation), then `steps` steps timed per pass; prints a table (stderr) and JSON (stdout) with
/// time and bound bytes per pass per step beside the step's wall time.
fn profile(a: &BenchArgs, steps: u32) -> Result<()> {
    if a.backend == "cpu" {
        bail!("--profile times the WGSL engine's GPU passes; use --backend wgpu (or auto)");
    }
    let options = GpuOptions {
        profile: true,
        ..Default::default()
    };
    let (backend, adapter) = backend_with("wgpu", options)?;
    let steps = steps.max(1);
    let mut t = new_trainer(&a.dataset, a.mode, &a.model, a.rays, 3 + steps, backend)?;
    let silvr_core::train::Engine::Wgpu(engine) = &t.engine else {
        bail!("the profile needs the WGSL engine");
    };
    let gpu = engine.gpu.clone();
    let mode = gpu.profiling().context("profiling is off on this device")?;
    for _ in 0..3 {
        pollster::block_on(t.train_step())?;
    }
    gpu.profile_take();
    let t0 = Instant::now();
    for _ in 0..steps {
        pollster::block_on(t.train_step())?;
    }
    let wall = t0.elapsed().as_secs_f64() / steps as f64;
    let rows = gpu.profile_take();
    let total: f64 = rows.iter().map(|r| r.seconds).sum::<f64>() / steps as f64;
    eprintln!(
        "{} model, {} rays, {:?} on {adapter}",
        a.model, a.rays, mode
    );
    let out = print_profile(&rows, steps, wall * steps as f64);
    // Inference: one held-out view (or a training view) pass by pass, of this field or, with
    // `--render-checkpoint`, of a trained one (whose samples concentrate on surfaces).
    if let Some(p) = &a.render_checkpoint {
        let ck = Checkpoint::load(p)?;
        let data = TrainData::load(&a.dataset, &LoadOptions::default())?;
        t = Trainer::resume(data, ck, Backend::Wgpu(gpu.clone()))?;
        if let Some(i) = t.data.val.first().copied() {
            let (rays, _) = t.view_rays(i);
            pollster::block_on(t.render(&rays[..rays.len().min(256)], false))?;
        }
        gpu.profile_take();
    }
    let inference = match t.data.val.first().or(t.data.train.first()).copied() {
        Some(i) => {
            let (rays, _) = t.view_rays(i);
            let tr = Instant::now();
            pollster::block_on(t.render(&rays, false))?;
            let s = tr.elapsed().as_secs_f64();
            let rows = gpu.profile_take();
            eprintln!(
                "inference: one view, {} rays, {:.0} rays/s",
                rays.len(),
                rays.len() as f64 / s
            );
            Some(serde_json::json!({
                "rays": rays.len(),
                "rays_per_s": rays.len() as f64 / s,
                "passes": print_profile(&rows, 1, s),
            }))
        }
        None => None,
    };
    let v = serde_json::json!({
        "backend": adapter,
        "timing": mode,
        "model": a.model,
        "mode": a.mode.name(),
        "rays_per_batch": a.rays,
        "steps_profiled": steps,
        "step_wall_ms": wall * 1e3,
        "passes_ms": total * 1e3,
        "passes": out,
        "inference": inference,
        "note": "bytes bound: the sizes of the buffers each pass binds, an upper bound on what it reads and writes",
    });
    println!("{}", serde_json::to_string_pretty(&v)?);
    Ok(())
}

/// The WGSL engine's step against the CPU reference on one batch of this dataset, from a trained field's
/// checkpoint (same parameters, same rays, the batch and schedule of the checkpoint's step): the loss of
/// each, and per tensor the gradient difference relative to the CPU gradient (L2 norm, and largest entry). Run
/// by the demo so that the engine it ships is checked on the data it reports, after training.
pub fn crosscheck(
    dataset: &Path,
    data_root: Option<&Path>,
    checkpoint: &Path,
    rays: usize,
) -> Result<serde_json::Value> {
    let gpu = pollster::block_on(Gpu::new(GpuOptions::default()))?;
    let ck = Checkpoint::load(checkpoint)?;
    let data = TrainData::load_within(
        dataset,
        data_root,
        &LoadOptions {
            downscale: 1,
            skip_lidar: ck.header.config.mode == Mode::Vision,
        },
    )?;
    let mut t = Trainer::resume(data, ck, Backend::Cpu)?;
    t.config.rays_per_batch = rays;
    let batch = t.batch(t.step);
    let sch = t.schedule(t.step);
    let (g_cpu, s_cpu) = silvr_core::train::cpu::train_step(&t.model, &t.params, &batch, &sch)?;
    let mut eng = silvr_core::train::gpu::GpuEngine::new(
        gpu.clone(),
        &t.model,
        &t.params,
        &t.adam.m,
        &t.adam.v,
    )?;
    let s_gpu = pollster::block_on(eng.step(&batch, &sch, &t.config.adam, 1e-2, 1, false))?;
    let g_gpu = pollster::block_on(eng.download_grads())?;
    // Per tensor, the difference relative to the CPU gradient in the L2 norm (the gate) and elementwise
    // relative to the tensor's largest entry (reported). The norm is the right gate: the CAS-atomic sums
    // add in another order (relative error ~1e-6), and the proposal sampler's interval overlaps are
    // piecewise constant in sample positions, so a position that moves by a rounding error can flip one
    // overlap and change a few entries of the proposal grids' gradients by a visible fraction.
    let mut worst = 0.0f64;
    let mut worst_elem = 0.0f64;
    let mut per_tensor = serde_json::Map::new();
    let mut per_tensor_elem = serde_json::Map::new();
    for ((a, b), name) in g_gpu.iter().zip(&g_cpu).zip(&t.params.names) {
        let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-12) as f64;
        let (mut diff2, mut norm2, mut elem) = (0.0f64, 0.0f64, 0.0f64);
        for (x, y) in a.iter().zip(b) {
            let d = (x - y) as f64;
            diff2 += d * d;
            norm2 += (*y as f64) * (*y as f64);
            elem = elem.max(d.abs() / scale);
            if !x.is_finite() {
                elem = f64::INFINITY;
                diff2 = f64::INFINITY;
            }
        }
        let l2 = diff2.sqrt() / norm2.sqrt().max(1e-30);
        let l2 = if l2.is_nan() { f64::INFINITY } else { l2 };
        per_tensor.insert(name.clone(), l2.into());
        per_tensor_elem.insert(name.clone(), elem.min(f64::MAX).into());
        worst = worst.max(l2);
        worst_elem = worst_elem.max(elem);
    }
    let loss_rel = (s_gpu.loss - s_cpu.loss).abs() / s_cpu.loss.abs().max(1e-12);
    Ok(serde_json::json!({
        "adapter": gpu.report().to_string(),
        "checkpoint": checkpoint,
        "step": t.step,
        "rays": batch.rays.len(),
        "loss_cpu": s_cpu.loss,
        "loss_wgsl": s_gpu.loss,
        "loss_rel_diff": loss_rel,
        "grad_rel_l2": worst.min(f64::MAX),
        "grad_rel_l2_per_tensor": per_tensor,
        "grad_max_elem_rel": worst_elem.min(f64::MAX),
        "grad_max_elem_rel_per_tensor": per_tensor_elem,
    }))
}

#[derive(clap::Args)]
pub struct SamplerBenchArgs {
    /// Dataset folder (e.g. from `silvr synth`).
    pub dataset: PathBuf,
    #[arg(long, default_value = "silvr")]
    pub mode: Mode,
    #[arg(long, default_value = "small")]
    pub model: String,
    #[arg(long, default_value_t = 1024)]
    pub rays: usize,
    #[arg(long, default_value_t = 300)]
    pub steps: u32,
    /// Occupancy-grid cells per axis.
    #[arg(long, default_value_t = 64)]
    pub grid: usize,
    /// Steps between occupancy-grid refreshes (Instant-NGP: 16).
    #[arg(long, default_value_t = 16)]
    pub update_every: u32,
    /// Training rays exported for the geometry scores.
    #[arg(long, default_value_t = 60_000)]
    pub export_rays: usize,
}

/// `silvr bench-sampler`: the same training on the CPU reference with nerfacto's proposal networks and with
/// an Instant-NGP occupancy grid placing the final samples (same final sample count, same batches, same
/// losses with the proposal levels' share of depth and sky moved to the final level): wall time, training
/// PSNR along the way, held-out PSNR and, where the dataset has ground truth, the exported cloud's geometry.
pub fn bench_sampler(a: &SamplerBenchArgs) -> Result<()> {
    use rand::SeedableRng;
    use silvr_core::sampler::occupancy::OccupancyGrid;
    use silvr_core::train::cpu::{self, Sampling};
    let mut results = Vec::new();
    for kind in ["proposal", "occupancy_grid"] {
        let mut t = new_trainer(&a.dataset, a.mode, &a.model, a.rays, a.steps, Backend::Cpu)?;
        let mut grid = (kind == "occupancy_grid").then(|| OccupancyGrid::new(a.grid));
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(0x0CC);
        let levels = t.model.sampler.proposal_samples.len() as f32 + 1.0;
        let t0 = Instant::now();
        let mut grid_s = 0.0;
        let mut curve = Vec::new();
        while t.step < a.steps {
            let batch = t.batch(t.step);
            let mut sch = t.schedule(t.step);
            if let Some(g) = grid.as_mut() {
                if t.step % a.update_every.max(1) == 0 {
                    let tg = Instant::now();
                    cpu::update_occupancy(&t.model, &t.params, g, &mut rng, 0.95)?;
                    grid_s += tg.elapsed().as_secs_f64();
                }
                // No proposal levels: the final level carries all of the depth and sky weight.
                sch.losses.depth *= levels;
                sch.losses.sky *= levels;
            }
            let sampling = grid
                .as_ref()
                .map_or(Sampling::Proposal, Sampling::Occupancy);
            let (grads, stats) = cpu::train_step_with(sampling, &t.model, &t.params, &batch, &sch)?;
            let lr = t.config.adam.lr_at(t.step);
            t.adam
                .update(&t.config.adam, lr, &mut t.params.tensors, &grads);
            t.step += 1;
            t.history.push(stats);
            if t.step % 50 == 0 || t.step == a.steps {
                let h = &t.history[t.history.len().saturating_sub(20)..];
                let mse = h.iter().map(|s| s.rgb_mse).sum::<f64>() / h.len() as f64;
                let mut c = serde_json::json!({
                    "step": t.step,
                    "s": t0.elapsed().as_secs_f64(),
                    "train_psnr": -10.0 * mse.max(1e-12).log10(),
                });
                if let Some(g) = &grid {
                    c["occupied_fraction"] = g.occupied_fraction().into();
                }
                curve.push(c);
            }
        }
        let train_s = t0.elapsed().as_secs_f64();
        let sampling = grid
            .as_ref()
            .map_or(Sampling::Proposal, Sampling::Occupancy);
        let mut psnr = Vec::new();
        for &i in &t.data.val.clone() {
            let (rays, valid) = t.view_rays(i);
            let out = cpu::render_rays_with(sampling, &t.model, &t.params, &rays, false, 4096)?;
            psnr.push(t.score_view(i, &t.view_from(i, valid, &out))?.psnr);
        }
        let mut entry = serde_json::json!({
            "sampler": kind,
            "steps": t.step,
            "train_s": train_s,
            "grid_update_s": grid_s,
            "heldout_psnr": mean(psnr.iter().copied()),
            "curve": curve,
        });
        if let Some(g) = &grid {
            entry["grid_cells"] = g.res.into();
            entry["occupied_fraction"] = g.occupied_fraction().into();
        }
        if a.dataset.join("gt/cloud.ply").is_file() && a.export_rays > 0 {
            let rays = t.export_rays(a.export_rays, 0xE0);
            let out = cpu::render_rays_with(sampling, &t.model, &t.params, &rays, false, 4096)?;
            let cloud = silvr_core::train::export::points_from(
                &t.data.frame,
                &rays,
                &out,
                silvr_core::train::export::ExportDepth::default(),
            );
            let tmp = tempfile_path(kind);
            silvr_core::pointcloud::write_ply(&tmp, &cloud)?;
            let ev = silvr_core::eval::evaluate_files_full(
                &tmp,
                &a.dataset,
                &silvr_core::eval::GeometryOptions::default(),
            );
            let _ = std::fs::remove_file(&tmp);
            let r = ev?.report;
            entry["accuracy_m"] = r.accuracy_m.into();
            entry["fscore_10cm"] = r.per_threshold.get("fscore_10cm").copied().into();
        }
        eprintln!("[bench-sampler] {kind}: {entry}");
        results.push(entry);
    }
    let v = serde_json::json!({
        "dataset": a.dataset,
        "mode": a.mode.name(),
        "model": a.model,
        "rays_per_batch": a.rays,
        "backend": "cpu (the occupancy grid exists only in the CPU reference)",
        "results": results,
    });
    println!("{}", serde_json::to_string_pretty(&v)?);
    Ok(())
}

fn tempfile_path(kind: &str) -> PathBuf {
    std::env::temp_dir().join(format!(
        "silvr-bench-sampler-{}-{kind}.ply",
        std::process::id()
    ))
}
