//! The WGSL engine against its CPU referee over whole runs, on the `micro` synthetic world (the ci street
//! at 180×135, exact ground truth): the `small` model trained from the same seed and batches on both,
//! step by step, then held-out PSNR, exported-cloud accuracy, the uncertainty pass (Fisher diagonals and
//! AUSE) and resuming a WGSL checkpoint. The GPU is lavapipe in CI; without an adapter the tests skip,
//! unless `SILVR_REQUIRE_GPU=1` (the test scripts set it), when they fail.
//!
//! How close the two runs can stay: one step's gradients agree to ~1e-6 of each tensor's largest (f32
//! sums in another order: the hash grid's compare-exchange float adds land in whatever order the threads
//! reach them, the CPU sums sequentially). Adam divides by √v, so an entry whose gradient is near zero
//! can move by a whole learning rate on one side and not the other; such differences compound through
//! the sampling (the proposal networks place the next step's samples), so the runs separate like any
//! two runs of a chaotic optimiser after some tens of steps (measured: 3e-8 relative at step 0, 2.5e-5
//! by step 9, 2.4e-2 by step 49, single steps up to 0.5 later). Asserted: the first ten steps' losses
//! agree to 1e-3, the 50-step means of the whole curve to 5 % (measured within 2 %), and the outcomes
//! to the bounds: held-out PSNR within 0.5 dB, accuracy within 15 %; the uncertainty pass over
//! one field on both engines: Fisher diagonals within 2e-3 of the largest entry, AUSE within 0.01.
//!
//! That field is the CPU-trained one, which is the same bits on every run (the WGSL run is not: its
//! atomic adds make each WGSL-trained field a little different). Over a fixed field the two passes differ
//! only by f32 rounding, but a trained field's sharp density peaks amplify a sample position's rounding
//! into its Jacobian, by an amount that depends on the field: over WGSL-trained fields the worst entry
//! ranged from 1.7e-4 to 1.8e-3 of the largest between runs, so a bound on those would be a coin toss.
//! Over the CPU field the worst entry was 1.7e-4 (colour) and 4.7e-4 (depth) with the MLP kernels' loops,
//! 6.7e-4 and 1.1e-3 since their products are straight-line code (2026-12-03: same sums, rounded
//! differently by the driver's compiler), hence 2e-3.

use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard, OnceLock};

use silvr_core::eval::{self, metrics::GeometryOptions};
use silvr_core::field::model::ModelConfig;
use silvr_core::gpu::{Gpu, GpuOptions};
use silvr_core::pointcloud::write_ply;
use silvr_core::synthetic::{generate, Preset};
use silvr_core::train::checkpoint::Checkpoint;
use silvr_core::train::data::{LoadOptions, TrainData};
use silvr_core::train::export::ExportDepth;
use silvr_core::train::{Backend, Mode, TrainConfig, Trainer};
use silvr_core::uncertainty::{self, reliability, sparsify, Posterior, UncertaintyConfig};

const STEPS: u32 = 200;
const RAYS: usize = 512;
const SEED: u64 = 1;

/// Held by each test for its whole run: side by side, lavapipe's threads and the CPU reference's rayon
/// pool oversubscribe a 2-core machine (measured 123 s for both tests together, 113 s one after the other).
fn one_at_a_time() -> MutexGuard<'static, ()> {
    static LOCK: Mutex<()> = Mutex::new(());
    LOCK.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// A device, or `None` (the test skips, [`silvr_tests::skip`]) when there is none and the run does not
/// demand one (`SILVR_REQUIRE_GPU=1`).
fn gpu() -> Option<Gpu> {
    match pollster::block_on(Gpu::new(GpuOptions::default())) {
        Ok(g) => Some(g),
        Err(e) => {
            silvr_tests::skip("SILVR_REQUIRE_GPU", &format!("no usable GPU: {e}"));
            None
        }
    }
}

/// The micro world, generated once per test process.
fn world(gpu: &Gpu) -> &'static Path {
    static DIR: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    &DIR.get_or_init(|| {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("micro");
        pollster::block_on(generate::generate(
            &Preset::micro(SEED),
            gpu,
            &out,
            false,
            &mut |_| {},
        ))
        .unwrap();
        (tmp, out)
    })
    .1
}

fn trainer(dataset: &Path, backend: Backend, steps: u32) -> Trainer {
    let data = TrainData::load(dataset, &LoadOptions::default()).unwrap();
    let model = ModelConfig::preset("small", data.train.len()).unwrap();
    let config = TrainConfig::for_run(Mode::Silvr, steps, RAYS, SEED);
    Trainer::new(data, model, config, backend).unwrap()
}

fn mean_heldout_psnr(t: &mut Trainer) -> f64 {
    let val = t.data.val.clone();
    assert!(!val.is_empty(), "the micro world holds views out");
    let mut s = 0.0;
    for &i in &val {
        let v = pollster::block_on(t.render_view(i, false)).unwrap();
        s += t.score_view(i, &v).unwrap().psnr;
    }
    s / val.len() as f64
}

/// Accuracy (m) of the exported cloud against the world's ground truth, and the evaluation.
fn accuracy(
    t: &mut Trainer,
    world: &Path,
    dir: &Path,
    name: &str,
) -> (f64, eval::metrics::GeometryEvaluation) {
    let cloud =
        pollster::block_on(t.export_points(20_000, SEED ^ 0xE0, false, ExportDepth::Expected))
            .unwrap();
    let path = dir.join(format!("{name}.ply"));
    write_ply(&path, &cloud).unwrap();
    let ev = eval::evaluate_files_full(&path, world, &GeometryOptions::default()).unwrap();
    (ev.report.accuracy_m, ev)
}

fn window_means(v: &[f64], w: usize) -> Vec<f64> {
    v.chunks(w)
        .map(|c| c.iter().sum::<f64>() / c.len() as f64)
        .collect()
}

#[test]
fn wgsl_training_matches_the_cpu_reference_over_a_run() {
    let _serial = one_at_a_time();
    let Some(gpu) = gpu() else { return };
    let dataset = world(&gpu);
    let mut cpu = trainer(dataset, Backend::Cpu, STEPS);
    let mut wgsl = trainer(dataset, Backend::Wgpu(gpu.clone()), STEPS);
    assert_eq!(
        wgsl.engine.name(),
        "wgpu",
        "the WGSL engine must run this test"
    );
    assert_eq!(cpu.engine.name(), "cpu");
    for _ in 0..STEPS {
        pollster::block_on(cpu.train_step()).unwrap();
        pollster::block_on(wgsl.train_step()).unwrap();
    }
    let (lc, lg): (Vec<f64>, Vec<f64>) = cpu
        .history
        .iter()
        .zip(&wgsl.history)
        .map(|(c, g)| (c.loss, g.loss))
        .unzip();
    let rel: Vec<f64> = lc
        .iter()
        .zip(&lg)
        .map(|(c, g)| (c - g).abs() / c.abs().max(1e-12))
        .collect();
    eprintln!(
        "loss rel. diff: step 0 {:.2e}, steps 0-9 max {:.2e}, 10-49 max {:.2e}, all max {:.2e}",
        rel[0],
        rel[..10].iter().cloned().fold(0.0, f64::max),
        rel[10..50].iter().cloned().fold(0.0, f64::max),
        rel.iter().cloned().fold(0.0, f64::max)
    );
    for (k, r) in rel[..10].iter().enumerate() {
        assert!(
            *r < 1e-3,
            "step {k}: loss cpu {} vs wgsl {} ({r:.2e})",
            lc[k],
            lg[k]
        );
    }
    for (k, (c, g)) in window_means(&lc, 50)
        .iter()
        .zip(window_means(&lg, 50))
        .enumerate()
    {
        eprintln!(
            "steps {}-{}: mean loss cpu {c:.5} wgsl {g:.5}",
            50 * k,
            50 * k + 49
        );
        assert!(
            (c - g).abs() <= 0.05 * c,
            "steps {}-{}: mean loss cpu {c} vs wgsl {g}",
            50 * k,
            50 * k + 49
        );
    }
    assert!(
        lc[STEPS as usize - 1] < 0.5 * lc[0],
        "the reference did not learn"
    );

    let (pc, pg) = (mean_heldout_psnr(&mut cpu), mean_heldout_psnr(&mut wgsl));
    eprintln!("held-out PSNR: cpu {pc:.2} dB, wgsl {pg:.2} dB");
    assert!(
        (pc - pg).abs() <= 0.5,
        "held-out PSNR cpu {pc} vs wgsl {pg}"
    );
    assert!(pg > 18.0, "WGSL held-out PSNR {pg} dB: nothing learnt");

    let tmp = tempfile::tempdir().unwrap();
    let (ac, ev_c) = accuracy(&mut cpu, dataset, tmp.path(), "cpu");
    let (ag, _) = accuracy(&mut wgsl, dataset, tmp.path(), "wgsl");
    eprintln!("accuracy: cpu {ac:.4} m, wgsl {ag:.4} m");
    assert!(
        (ac - ag).abs() <= 0.15 * ac,
        "accuracy cpu {ac} m vs wgsl {ag} m"
    );

    // The uncertainty pass on both engines over the same (CPU-trained, reproducible) field.
    let ucfg = UncertaintyConfig {
        batches: 4,
        rays_per_batch: 1024,
        ..Default::default()
    };
    let ck = pollster::block_on(cpu.checkpoint()).unwrap();
    let data = TrainData::load(dataset, &LoadOptions::default()).unwrap();
    let mut on_wgsl = Trainer::resume(data, ck, Backend::Wgpu(gpu.clone())).unwrap();
    assert_eq!(on_wgsl.engine.name(), "wgpu");
    let fg =
        pollster::block_on(uncertainty::compute_fisher(&mut on_wgsl, &ucfg, |_, _| {})).unwrap();
    let fc = pollster::block_on(uncertainty::compute_fisher(&mut cpu, &ucfg, |_, _| {})).unwrap();
    assert_eq!((fg.rays, fg.lidar_rays), (fc.rays, fc.lidar_rays));
    for (what, g, c) in [
        ("colour", &fg.colour, &fc.colour),
        ("depth", &fg.depth, &fc.depth),
    ] {
        let scale = c.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-30);
        let worst = g
            .iter()
            .zip(c.iter())
            .map(|(a, b)| (a - b).abs() / scale)
            .fold(0.0f32, f32::max);
        let l1 = g
            .iter()
            .zip(c.iter())
            .map(|(a, b)| f64::from((a - b).abs()))
            .sum::<f64>()
            / c.iter().map(|v| f64::from(v.abs())).sum::<f64>().max(1e-30);
        eprintln!(
            "Fisher {what}: worst difference {worst:.2e} of the largest entry, L1 difference {l1:.2e} of the total"
        );
        assert!(worst < 2e-3, "Fisher {what}: {worst}");
    }
    // AUSE of the CPU cloud by each engine's read-out.
    let pts = &ev_c.reconstruction.positions;
    let ug = fg.read_out_metric(Posterior::Raw, pts);
    let uc = fc.read_out_metric(Posterior::Raw, pts);
    let ause = |u: &[f32]| {
        sparsify::sparsification(&ev_c.rec_to_gt, u)
            .expect("points")
            .ause
    };
    let (a_g, a_c) = (ause(&ug.combined), ause(&uc.combined));
    eprintln!("AUSE combined: wgsl {a_g:.4}, cpu {a_c:.4}");
    assert!((a_g - a_c).abs() <= 0.01, "AUSE wgsl {a_g} vs cpu {a_c}");

    // σ in metres that matches the error: calibrated on held-out lidar returns (WGSL renders them),
    // never on the ground truth, the read-out of the CPU cloud against its distance to the GT.
    let mut f = fg.clone();
    let held = pollster::block_on(uncertainty::calibrate::held_out_returns(
        &mut on_wgsl,
        uncertainty::CALIBRATION_RETURNS,
        7,
    ))
    .unwrap();
    uncertainty::calibrate::calibrate(&mut f, &held);
    eprintln!(
        "calibration on {} of {} held-out returns: factors {:?}, spread factors {:?}, coverage {:?}",
        held.residual_m.len(),
        held.available,
        f.calibration.factor,
        f.calibration.spread,
        f.calibration.coverage
    );
    assert!(
        held.residual_m.len() > 1000,
        "{} held-out returns",
        held.residual_m.len()
    );
    let at = uncertainty::unconstrained_log_std(f.prior_sigma_m());
    // The error σ speaks of: distance to the GT surface (the micro world's GT is sampled every 5 cm, so
    // the distance to its nearest sample has a ~2 cm floor that is not the field's).
    let errors = &eval::GroundTruth::load(dataset)
        .unwrap()
        .surface_distances(&ev_c.reconstruction.positions);
    // The points' σ as the pass writes it: the field's read-out with each point's ray spread.
    let mut annotated = ev_c.reconstruction.clone();
    assert!(annotated.scalar(uncertainty::DEPTH_SPREAD_FIELD).is_some());
    uncertainty::annotate_cloud(&f, &mut annotated);
    let cal = annotated.scalar("log_std_combined").unwrap().to_vec();
    let r = reliability::reliability(&cal, errors, at, 10).unwrap();
    eprint!("{}", r.table("micro world, combined σ (calibrated)"));
    assert!(
        (0.5..=2.0).contains(&r.median_ratio),
        "median σ {} m vs median error {} m",
        r.median_sigma_m,
        r.median_error_m
    );
    assert!(
        (0.6..=0.8).contains(&r.coverage_1sigma),
        "1σ coverage {}",
        r.coverage_1sigma
    );
    assert!(
        (0.85..=0.99).contains(&r.coverage_2sigma),
        "2σ coverage {}",
        r.coverage_2sigma
    );
    // BayesRays' read-out, the σ of a field constrained by one average ray (H/N, λ = 1e-4/L³), is
    // hundreds of times the error: it fails the same bands.
    let n = f.rays as f32;
    let old = uncertainty::Fisher {
        colour: f.colour.iter().map(|h| h / n).collect(),
        depth: f.depth.iter().map(|h| h / n).collect(),
        prior: 1e-4 / (f.cells as f64).powi(3),
        calibration: uncertainty::Calibration::RAW,
        ..f.clone()
    };
    let o = old.read_out_metric(Posterior::Raw, pts).combined;
    let ro = reliability::reliability(&o, errors, f32::INFINITY, 10).unwrap();
    eprint!(
        "{}",
        ro.table("micro world, combined σ (BayesRays' per-ray read-out)")
    );
    assert!(ro.median_ratio > 10.0, "{}", ro.median_ratio);
}

/// A WGSL run checkpointed halfway and resumed (a new engine on the same device) continues the run: the
/// same step counter, and losses within float tolerance of the uninterrupted run's.
#[test]
fn a_wgsl_checkpoint_resumes_the_same_run() {
    let _serial = one_at_a_time();
    let Some(gpu) = gpu() else { return };
    let dataset = world(&gpu);
    const N: u32 = 30;
    let mut straight = trainer(dataset, Backend::Wgpu(gpu.clone()), N);
    for _ in 0..N {
        pollster::block_on(straight.train_step()).unwrap();
    }
    let mut first = trainer(dataset, Backend::Wgpu(gpu.clone()), N);
    for _ in 0..N / 2 {
        pollster::block_on(first.train_step()).unwrap();
    }
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("half.ckpt");
    pollster::block_on(first.checkpoint())
        .unwrap()
        .save(&path)
        .unwrap();
    drop(first);
    let data = TrainData::load(dataset, &LoadOptions::default()).unwrap();
    let mut resumed =
        Trainer::resume(data, Checkpoint::load(&path).unwrap(), Backend::Wgpu(gpu)).unwrap();
    assert_eq!(resumed.step, N / 2);
    assert_eq!(resumed.engine.name(), "wgpu");
    while resumed.step < N {
        pollster::block_on(resumed.train_step()).unwrap();
    }
    assert_eq!(resumed.history.len(), N as usize);
    for (k, (a, b)) in straight.history.iter().zip(&resumed.history).enumerate() {
        let r = (a.loss - b.loss).abs() / a.loss.abs();
        assert!(
            r < 1e-3,
            "step {k}: uninterrupted {} vs resumed {} ({r:.2e})",
            a.loss,
            b.loss
        );
    }
}
