//! The WGSL uncertainty pass against its CPU referee (`uncertainty::cpu`, itself checked against finite
//! differences of the displaced render) on random parameters and rays through a poisoned device: the
//! per-sample Jacobians d(R, G, B, E)/d(position) and the accumulated colour and depth Fisher diagonals.

mod common;

use silvr_core::train::cpu::TrainRay;
use silvr_core::train::gpu::GpuEngine;
use silvr_core::uncertainty::cpu::{accumulate_fisher_cpu, final_edges, sample_jacobians_cpu};
use silvr_core::uncertainty::gpu::GpuFisher;
use silvr_core::uncertainty::{PerturbationGrid, COLOUR_RAY, DEPTH_RAY};

fn relative_worst(name: &str, gpu: &[f32], cpu: &[f64]) -> f64 {
    assert_eq!(gpu.len(), cpu.len(), "{name}: lengths");
    let scale = cpu.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(1e-12);
    let mut worst = 0.0f64;
    for (i, (&g, &c)) in gpu.iter().zip(cpu).enumerate() {
        assert!(g.is_finite(), "{name}[{i}] = {g} (poison or NaN), cpu {c}");
        worst = worst.max((g as f64 - c).abs() / scale);
    }
    eprintln!("{name}: worst error {worst:e} of the largest value {scale:e}");
    worst
}

#[test]
fn wgsl_uncertainty_pass_matches_the_cpu_reference() {
    let Some(gpu) = common::gpu() else { return };
    for (seed, cells) in [(3u64, 8u32), (8, 5)] {
        let (cfg, params, batch) = common::setup(seed, 24);
        let grid = PerturbationGrid { cells };
        let rays: Vec<TrainRay> = batch.rays.clone();
        // Every combination of flags, the unflagged rays included.
        let flags: Vec<u32> = (0..rays.len() as u32).map(|i| i % 4).collect();
        // CPU referee.
        let t = final_edges(&cfg, &params, &rays).unwrap();
        let sj = sample_jacobians_cpu(&cfg, &params, &rays, &t).unwrap();
        let nv = grid.vertices();
        let (mut hc, mut hd) = (vec![0.0f64; nv], vec![0.0f64; nv]);
        accumulate_fisher_cpu(grid, &sj, &flags, &mut hc, &mut hd);
        assert_eq!(COLOUR_RAY | DEPTH_RAY, 3);
        // Twice the same batch on the device: accumulation adds up.
        let zeros: Vec<Vec<f32>> = params.tensors.iter().map(|t| vec![0.0; t.len()]).collect();
        let mut engine = GpuEngine::new(gpu.clone(), &cfg, &params, &zeros, &zeros).unwrap();
        let mut f = pollster::block_on(GpuFisher::new(&engine, grid)).unwrap();
        for _ in 0..2 {
            pollster::block_on(f.accumulate(&mut engine, &rays, &flags)).unwrap();
        }
        let n = cfg.sampler.samples;
        let g = pollster::block_on(f.download_sample_jacobians(&engine, rays.len() * n)).unwrap();
        let g_cpu: Vec<f64> =
            sj.g.iter()
                .flat_map(|s| s.iter().flat_map(|v| v.iter().map(|&x| x as f64)))
                .collect();
        assert!(relative_worst("dY/dposition", &g, &g_cpu) < 5e-4);
        let (gc, gd) = pollster::block_on(f.download(&engine)).unwrap();
        let hc2: Vec<f64> = hc.iter().map(|v| 2.0 * v).collect();
        let hd2: Vec<f64> = hd.iter().map(|v| 2.0 * v).collect();
        assert!(relative_worst("H colour", &gc, &hc2) < 5e-4);
        assert!(relative_worst("H depth", &gd, &hd2) < 5e-4);
        // Non-trivial: information landed, on different vertices for the two sensors, and vertices no
        // ray touched stayed exactly zero.
        let touched = hc.iter().filter(|&&v| v > 0.0).count();
        assert!(touched > 8 && touched < nv, "{touched} of {nv} vertices");
        assert!(hd.iter().any(|&v| v > 0.0));
        for v in 0..nv {
            if hc[v] == 0.0 {
                assert_eq!(gc[v], 0.0, "vertex {v} was never touched");
            }
        }
    }
}
