//! The WGSL training step against its CPU referee (`train::cpu`), on random parameters and rays through a
//! poisoned device: every gradient tensor, the loss terms, the Adam update and the renderer. The CPU chain
//! is itself checked against finite differences (`train::cpu` tests), so agreement here carries that over.

mod common;

use rand::{Rng, SeedableRng};
use silvr_core::render::LossConfig;
use silvr_core::train::adam::{AdamConfig, AdamState};
use silvr_core::train::cpu::{self, StepSchedule};
use silvr_core::train::gpu::GpuEngine;

fn schedule(anneal: f32) -> StepSchedule {
    StepSchedule {
        step: 7,
        anneal,
        losses: LossConfig {
            rgb: 1.0,
            depth: 0.5,
            normal: 0.1,
            sky: 0.5,
            depth_sigma: 0.3,
        },
        proposal_depth: 0.5,
        proposal_sky: 0.5,
        interlevel: 1.0,
        distortion: 0.1,
        normals: true,
    }
}

fn close(name: &str, gpu: &[f32], cpu: &[f32], rel: f32) {
    assert_eq!(gpu.len(), cpu.len(), "{name}: lengths");
    let scale = cpu.iter().fold(0.0f32, |a, v| a.max(v.abs())).max(1e-12);
    let mut worst = (0.0f32, 0usize);
    for (i, (g, c)) in gpu.iter().zip(cpu).enumerate() {
        assert!(g.is_finite(), "{name}[{i}] = {g} (poison or NaN), cpu {c}");
        let e = (g - c).abs() / scale;
        if e > worst.0 {
            worst = (e, i);
        }
    }
    eprintln!("{name}: worst relative error {:e}", worst.0);
    assert!(
        worst.0 <= rel,
        "{name}: worst [{}] gpu {} vs cpu {} (relative to max |g| {scale}: {})",
        worst.1,
        gpu[worst.1],
        cpu[worst.1],
        worst.0
    );
}

#[test]
fn training_step_matches_the_cpu_reference() {
    let Some(gpu) = common::gpu() else { return };
    for (seed, anneal) in [(1u64, 1.0f32), (2, 0.0), (3, 0.6)] {
        let (cfg, params, batch) = common::setup(seed, 37);
        let sch = schedule(anneal);
        let (g_cpu, s_cpu) = cpu::train_step(&cfg, &params, &batch, &sch).unwrap();
        let zeros: Vec<Vec<f32>> = params.tensors.iter().map(|t| vec![0.0; t.len()]).collect();
        let mut eng = GpuEngine::new(gpu.clone(), &cfg, &params, &zeros, &zeros).unwrap();
        let adam = AdamConfig::default();
        let s_gpu = pollster::block_on(eng.step(&batch, &sch, &adam, 1e-2, 1, false)).unwrap();
        let g_gpu = pollster::block_on(eng.download_grads()).unwrap();
        for (k, name) in params.names.iter().enumerate() {
            close(&format!("seed {seed} {name}"), &g_gpu[k], &g_cpu[k], 1e-3);
        }
        for (what, a, b) in [
            ("loss", s_gpu.loss, s_cpu.loss),
            ("rgb", s_gpu.rgb_mse, s_cpu.rgb_mse),
            ("depth", s_gpu.depth, s_cpu.depth),
            ("normal", s_gpu.normal, s_cpu.normal),
            ("sky", s_gpu.sky, s_cpu.sky),
            ("interlevel", s_gpu.interlevel, s_cpu.interlevel),
            ("distortion", s_gpu.distortion, s_cpu.distortion),
        ] {
            assert!(
                (a - b).abs() <= 1e-3 * b.abs() + 1e-6,
                "seed {seed} {what}: gpu {a} vs cpu {b}"
            );
        }
        assert!(s_cpu.normal > 0.0 && s_cpu.depth > 0.0 && s_cpu.sky > 0.0);
    }
}

#[test]
fn adam_update_matches_the_cpu_reference() {
    let Some(gpu) = common::gpu() else { return };
    let (cfg, params, batch) = common::setup(4, 20);
    let sch = schedule(1.0);
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(8);
    let m: Vec<Vec<f32>> = params
        .tensors
        .iter()
        .map(|t| {
            (0..t.len())
                .map(|_| rng.random_range(-1e-2..1e-2))
                .collect()
        })
        .collect();
    let v: Vec<Vec<f32>> = params
        .tensors
        .iter()
        .map(|t| (0..t.len()).map(|_| rng.random_range(0.0..1e-4)).collect())
        .collect();
    let adam = AdamConfig::default();
    let mut eng = GpuEngine::new(gpu, &cfg, &params, &m, &v).unwrap();
    pollster::block_on(eng.step(&batch, &sch, &adam, 5e-3, 3, true)).unwrap();
    let grads = pollster::block_on(eng.download_grads()).unwrap();
    let (p_gpu, m_gpu, v_gpu) = pollster::block_on(eng.download()).unwrap();
    // The CPU update from the GPU's own gradients.
    let mut st = AdamState { m, v, t: 2 };
    let mut p_cpu = params.tensors.clone();
    st.update(&adam, 5e-3, &mut p_cpu, &grads);
    for k in 0..p_cpu.len() {
        close(&format!("params {k}"), &p_gpu[k], &p_cpu[k], 1e-5);
        close(&format!("m {k}"), &m_gpu[k], &st.m[k], 1e-5);
        close(&format!("v {k}"), &v_gpu[k], &st.v[k], 1e-5);
    }
    assert_ne!(p_gpu[0], params.tensors[0], "the update moved nothing");
}

#[test]
fn rendering_matches_the_cpu_reference() {
    let Some(gpu) = common::gpu() else { return };
    let (cfg, params, batch) = common::setup(5, 29);
    let zeros: Vec<Vec<f32>> = params.tensors.iter().map(|t| vec![0.0; t.len()]).collect();
    let mut eng = GpuEngine::new(gpu, &cfg, &params, &zeros, &zeros).unwrap();
    for normals in [false, true] {
        // Chunks smaller than the batch exercise buffer reuse.
        let g = pollster::block_on(eng.render(&batch.rays, normals, 11)).unwrap();
        let c = cpu::render_rays(&cfg, &params, &batch.rays, normals, 64).unwrap();
        let flat = |v: &[cpu::RenderedRay]| -> Vec<f32> {
            v.iter()
                .flat_map(|r| {
                    let o = r.out;
                    [
                        o.rgb[0],
                        o.rgb[1],
                        o.rgb[2],
                        o.accumulation,
                        o.normal[0],
                        o.normal[1],
                        o.normal[2],
                        o.depth,
                        r.expected_depth,
                        r.median_depth,
                    ]
                })
                .collect()
        };
        close(
            &format!("render normals={normals}"),
            &flat(&g),
            &flat(&c),
            1e-3,
        );
    }
}

/// A device lost mid-training (here destroyed, as a driver reset would) gives an error that says so and
/// points at resuming from the last checkpoint, never a panic; the engine's host copies from before the
/// loss are intact, so a new device continues from them.
#[test]
fn a_lost_device_is_a_clear_error_and_a_new_one_continues() {
    let Some(gpu) = common::gpu() else { return };
    let (cfg, params, batch) = common::setup(6, 24);
    let sch = schedule(1.0);
    let zeros: Vec<Vec<f32>> = params.tensors.iter().map(|t| vec![0.0; t.len()]).collect();
    let adam = AdamConfig::default();
    let mut eng = GpuEngine::new(gpu.clone(), &cfg, &params, &zeros, &zeros).unwrap();
    pollster::block_on(eng.step(&batch, &sch, &adam, 1e-2, 1, true)).unwrap();
    let (p, m, v) = pollster::block_on(eng.download()).unwrap();
    gpu.device.destroy();
    let mut errors = Vec::new();
    for _ in 0..2 {
        match pollster::block_on(eng.step(&batch, &sch, &adam, 1e-2, 2, true)) {
            Ok(_) => {}
            Err(e) => errors.push(e.to_string()),
        }
    }
    let err = errors
        .last()
        .expect("stepping on a destroyed device must fail");
    assert!(err.contains("lost") && err.contains("--resume"), "{err}");
    // A fresh device takes the state downloaded before the loss.
    let Some(fresh) = common::gpu() else { return };
    let params = silvr_core::field::model::Params {
        names: params.names.clone(),
        tensors: p,
    };
    let mut eng = GpuEngine::new(fresh, &cfg, &params, &m, &v).unwrap();
    let s = pollster::block_on(eng.step(&batch, &sch, &adam, 1e-2, 2, true)).unwrap();
    assert!(s.loss.is_finite());
}
