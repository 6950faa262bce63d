//! The hash-grid kernels (WGSL, through wgpu — lavapipe where there is no GPU) against their CPU reference,
//! and both against central finite differences, on small grids with dense and hashed levels, with
//! poisoned output buffers.
#![cfg(not(target_arch = "wasm32"))]

use rand::{Rng, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;
use silvr_core::field::hashgrid::{
    self, backward_cpu, backward_gpu, encode_cpu, encode_gpu, GpuPositions, HashGridConfig,
    HashGridLayout,
};
use silvr_core::gpu::GpuError;

mod common;
use common::gpu;
use common::POISON;

/// Small grids; each has dense and hashed levels (checked), and together they cover F = 1, 2, 4, 8.
fn configs() -> Vec<HashGridConfig> {
    let c = |levels, features_per_level, log2_table_size, base_resolution, finest_resolution| {
        HashGridConfig {
            levels,
            features_per_level,
            log2_table_size,
            base_resolution,
            finest_resolution,
        }
    };
    vec![
        c(6, 2, 11, 4, 64),
        c(8, 2, 10, 3, 100),
        c(4, 1, 12, 8, 200),
        c(5, 4, 10, 4, 48),
        c(3, 8, 9, 5, 30),
    ]
}

fn rng(seed: u64) -> Xoshiro256PlusPlus {
    Xoshiro256PlusPlus::seed_from_u64(seed)
}

fn random_positions(seed: u64, n: usize) -> Vec<[f32; 3]> {
    let mut r = rng(seed);
    (0..n)
        .map(|_| [r.random(), r.random(), r.random()])
        .collect()
}

/// Parameters of order one (not tcnn's ±1e-4 init), so errors are measured at a meaningful scale.
fn random_values(seed: u64, n: usize) -> Vec<f32> {
    let mut r = rng(seed);
    (0..n).map(|_| r.random_range(-1.0f32..1.0)).collect()
}

fn abs(v: &[f32]) -> Vec<f32> {
    v.iter().map(|x| x.abs()).collect()
}

/// max_i |a_i − b_i| / (scale_i + floor): the error relative to the sum of |terms| that produced b_i
/// (`scale`), which bounds any f32 summation order's rounding.
fn scaled_error(a: &[f32], b: &[f32], scale: &[f32], floor: f32) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .zip(scale)
        .map(|((x, y), s)| (x - y).abs() / (s + floor))
        .fold(0.0, f32::max)
}

fn is_poison(v: f32) -> bool {
    v.to_bits() == POISON
}

#[test]
fn forward_matches_cpu_on_dense_and_hashed_levels() {
    let Some(gpu) = gpu() else { return };
    for (k, cfg) in configs().into_iter().enumerate() {
        let layout = HashGridLayout::new(&cfg).unwrap();
        assert!(layout.levels.iter().any(|l| l.dense), "{cfg:?}");
        assert!(layout.levels.iter().any(|l| !l.dense), "{cfg:?}");
        let params = random_values(100 + k as u64, layout.n_params());
        let pos = random_positions(200 + k as u64, 1500);
        let g = pollster::block_on(encode_gpu(&gpu, &cfg, &params, &pos)).unwrap();
        let c = encode_cpu(&cfg, &params, &pos).unwrap();
        assert_eq!(g.len(), pos.len() * layout.output_dim());
        assert!(!g.iter().any(|&v| is_poison(v)), "unwritten features");
        // Σ_c w_c |param_c|: the magnitude each feature was summed from.
        let scale = encode_cpu(&cfg, &abs(&params), &pos).unwrap();
        let err = scaled_error(&g, &c, &scale, 1e-6);
        let max_abs = g
            .iter()
            .zip(&c)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        eprintln!("forward {cfg:?}: scaled error {err:.2e}, max abs error {max_abs:.2e}");
        assert!(err < 1e-5, "{cfg:?}: {err}");
    }
}

#[test]
fn backward_matches_cpu() {
    let Some(gpu) = gpu() else { return };
    for (k, cfg) in configs().into_iter().enumerate() {
        let layout = HashGridLayout::new(&cfg).unwrap();
        let params = random_values(300 + k as u64, layout.n_params());
        let pos = random_positions(400 + k as u64, 1500);
        let dfeat = random_values(500 + k as u64, pos.len() * layout.output_dim());
        let g = pollster::block_on(backward_gpu(&gpu, &cfg, &params, &pos, &dfeat, true)).unwrap();
        let c = backward_cpu(&cfg, &params, &pos, &dfeat, true).unwrap();
        assert!(!g.params.iter().any(|&v| is_poison(v)), "uncleared grads");
        // Σ |contributions| per parameter: the CPU backward of |dL/dfeatures| (weights are ≥ 0).
        let scale = backward_cpu(&cfg, &params, &pos, &abs(&dfeat), false).unwrap();
        let err = scaled_error(&g.params, &c.params, &scale.params, 1e-6);
        // Parameters no position touches stay exactly zero (the clear pass ran over the poison).
        for (i, (&gv, &s)) in g.params.iter().zip(&scale.params).enumerate() {
            if s == 0.0 {
                assert_eq!(gv, 0.0, "{cfg:?}: untouched param {i}");
            }
        }
        let (gp, cp) = (g.positions.unwrap(), c.positions.unwrap());
        let gp: Vec<f32> = gp.into_iter().flatten().collect();
        let cp: Vec<f32> = cp.into_iter().flatten().collect();
        let norm = cp.iter().map(|v| v.abs()).fold(0.0, f32::max);
        let perr = gp
            .iter()
            .zip(&cp)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max)
            / norm;
        eprintln!(
            "backward {cfg:?}: params scaled error {err:.2e}, dL/dx max error / max |dL/dx| {perr:.2e}"
        );
        assert!(err < 1e-4, "{cfg:?}: {err}");
        assert!(perr < 1e-5, "{cfg:?}: {perr}");
    }
}

/// Positions as a trainer lays them out: runs of consecutive samples along rays (and points crowded into
/// a few cells), so that one `backward_params` thread sums several points of one cell before its atomic
/// adds, and runs end mid-cell, at cell changes and at the batch's end.
#[test]
fn backward_of_ray_samples_matches_cpu() {
    let Some(gpu) = gpu() else { return };
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(77);
    for (k, cfg) in configs().into_iter().enumerate() {
        let layout = HashGridLayout::new(&cfg).unwrap();
        let params = random_values(600 + k as u64, layout.n_params());
        let mut pos = Vec::new();
        // 37 rays of 24 samples with steps from a thousandth (many points per cell) to a tenth of the box,
        // then 13 points at one spot (every level's same cell), then a ragged tail.
        for r in 0..37 {
            let o: [f32; 3] = [0, 1, 2].map(|_| rng.random_range(0.1..0.9f32));
            let d: [f32; 3] = [0, 1, 2].map(|_| rng.random_range(-1.0..1.0f32));
            let step = [1e-3f32, 1e-2, 0.05, 0.1][r % 4];
            for i in 0..24 {
                pos.push([0, 1, 2].map(|a| (o[a] + d[a] * step * i as f32).clamp(0.0, 1.0)));
            }
        }
        pos.extend(std::iter::repeat_n([0.31f32, 0.52, 0.77], 13));
        pos.extend(random_positions(700 + k as u64, 5));
        let dfeat = random_values(800 + k as u64, pos.len() * layout.output_dim());
        let g = pollster::block_on(backward_gpu(&gpu, &cfg, &params, &pos, &dfeat, false)).unwrap();
        let c = backward_cpu(&cfg, &params, &pos, &dfeat, false).unwrap();
        let scale = backward_cpu(&cfg, &params, &pos, &abs(&dfeat), false).unwrap();
        let err = scaled_error(&g.params, &c.params, &scale.params, 1e-6);
        eprintln!("ray-sample backward {cfg:?}: params scaled error {err:.2e}");
        assert!(err < 1e-4, "{cfg:?}: {err}");
        for (i, (&gv, &s)) in g.params.iter().zip(&scale.params).enumerate() {
            if s == 0.0 {
                assert_eq!(gv, 0.0, "{cfg:?}: untouched param {i}");
            }
        }
    }
}

/// An independent f64 forward (same layout, through the public vertex-index functions), so finite
/// differences are free of f32 rounding and check the f32 gradients to their own precision. With
/// `f32_cell`, the position in vertex units is rounded to f32 first, as the kernels do: the weights then
/// match theirs, which isolates the parameter gradient from that (legitimate) input rounding.
fn encode_f64(layout: &HashGridLayout, params: &[f32], x: [f64; 3], f32_cell: bool) -> Vec<f64> {
    let nf = layout.config.features_per_level as usize;
    let mut out = Vec::with_capacity(layout.output_dim());
    for lv in &layout.levels {
        let q = x.map(|v| {
            if f32_cell {
                ((v as f32).clamp(0.0, 1.0) * lv.scale + 0.5) as f64
            } else {
                v.clamp(0.0, 1.0) * lv.scale as f64 + 0.5
            }
        });
        let base = q.map(|v| v.floor() as u32);
        let t = [0, 1, 2].map(|d| q[d] - q[d].floor());
        let mut acc = vec![0.0f64; nf];
        for c in 0..8u32 {
            let b = [c & 1, (c >> 1) & 1, (c >> 2) & 1];
            let mut w = 1.0;
            for d in 0..3 {
                w *= if b[d] == 1 { t[d] } else { 1.0 - t[d] };
            }
            let e = lv.offset + lv.index([base[0] + b[0], base[1] + b[1], base[2] + b[2]]);
            for (f, a) in acc.iter_mut().enumerate() {
                *a += w * params[e as usize * nf + f] as f64;
            }
        }
        out.extend(acc);
    }
    out
}

/// L = Σ w·features (f64): its central difference along one parameter (exact, L is linear in the table) and
/// along one coordinate of one position, with both ends in the point's cell on every level (L is linear
/// there too), against the CPU and GPU gradients.
#[test]
fn backward_matches_finite_differences() {
    let Some(gpu) = gpu() else { return };
    for (k, cfg) in configs().into_iter().enumerate() {
        let layout = HashGridLayout::new(&cfg).unwrap();
        let d = layout.output_dim();
        let nf = cfg.features_per_level as usize;
        let mut params = random_values(600 + k as u64, layout.n_params());
        let pos = random_positions(700 + k as u64, 300);
        let w = random_values(800 + k as u64, pos.len() * d);
        let point_loss = |params: &[f32], x: [f64; 3], wp: &[f32], f32_cell: bool| -> f64 {
            let f = encode_f64(&layout, params, x, f32_cell);
            f.iter().zip(wp).map(|(&a, &b)| a * b as f64).sum()
        };
        let loss = |params: &[f32]| -> f64 {
            pos.iter()
                .enumerate()
                .map(|(p, x)| point_loss(params, x.map(f64::from), &w[p * d..(p + 1) * d], true))
                .sum()
        };
        let cpu = backward_cpu(&cfg, &params, &pos, &w, true).unwrap();
        let gpu_g = pollster::block_on(backward_gpu(&gpu, &cfg, &params, &pos, &w, true)).unwrap();
        let scale = backward_cpu(&cfg, &params, &pos, &abs(&w), false).unwrap();

        // Parameters: half touched by some position, half drawn anywhere (mostly untouched in hashed levels).
        let touched: Vec<usize> = (0..layout.n_params())
            .filter(|&i| scale.params[i] > 0.0)
            .collect();
        let mut r = rng(900 + k as u64);
        let mut worst = (0.0f64, 0.0f64);
        for j in 0..40 {
            let i = if j % 2 == 0 {
                touched[r.random_range(0..touched.len())]
            } else {
                r.random_range(0..layout.n_params())
            };
            let h = 0.5f32;
            let orig = params[i];
            params[i] = orig + h;
            let lp = loss(&params);
            params[i] = orig - h;
            let lm = loss(&params);
            params[i] = orig;
            let fd = (lp - lm) / (2.0 * h as f64);
            let s = scale.params[i] as f64 + 1e-6;
            let ec = (fd - cpu.params[i] as f64).abs() / s;
            let eg = (fd - gpu_g.params[i] as f64).abs() / s;
            worst = (worst.0.max(ec), worst.1.max(eg));
        }
        eprintln!(
            "FD params {cfg:?}: CPU {:.2e}, GPU {:.2e} (error / Σ|contributions|)",
            worst.0, worst.1
        );
        assert!(worst.0 < 1e-5 && worst.1 < 1e-4, "{cfg:?}: {worst:?}");

        // Positions: one point at a time, L_p = Σ_k w_pk·features_pk.
        let h = 1e-4f64;
        let cpu_dx = cpu.positions.unwrap();
        let gpu_dx = gpu_g.positions.unwrap();
        let mut checked = 0;
        let mut worst = (0.0f64, 0.0f64);
        for (p, x) in pos.iter().enumerate() {
            let wp = &w[p * d..(p + 1) * d];
            // |params| < 1, so Σ_l scale_l·Σ_f |w_lf| bounds the terms dL/dx is summed from.
            let s: f64 = layout
                .levels
                .iter()
                .enumerate()
                .map(|(l, lv)| {
                    lv.scale as f64
                        * wp[l * nf..(l + 1) * nf]
                            .iter()
                            .map(|v| v.abs() as f64)
                            .sum::<f64>()
                })
                .sum();
            let x = x.map(f64::from);
            for axis in 0..3 {
                let (mut xp, mut xm) = (x, x);
                xp[axis] += h;
                xm[axis] -= h;
                let inside = layout.levels.iter().all(|lv| {
                    let cell = |v: f64| (v * lv.scale as f64 + 0.5).floor();
                    let c = cell(x[axis]);
                    cell(xp[axis]) == c && cell(xm[axis]) == c
                });
                if !inside || xm[axis] < 0.0 || xp[axis] > 1.0 {
                    continue;
                }
                let fd = (point_loss(&params, xp, wp, false) - point_loss(&params, xm, wp, false))
                    / (2.0 * h);
                let ec = (fd - cpu_dx[p][axis] as f64).abs() / s;
                let eg = (fd - gpu_dx[p][axis] as f64).abs() / s;
                worst = (worst.0.max(ec), worst.1.max(eg));
                checked += 1;
            }
        }
        eprintln!(
            "FD positions {cfg:?}: {checked} derivatives, CPU {:.2e}, GPU {:.2e} (error / Σ|terms|)",
            worst.0, worst.1
        );
        assert!(checked > 400, "{checked}");
        // The kernels round x·scale + 0.5 to f32, so t carries an absolute error of about ulp(finest scale).
        let tol = 2.0 * f32::EPSILON as f64 * (layout.levels.last().unwrap().scale as f64 + 1.0);
        assert!(
            worst.0 < tol && worst.1 < tol,
            "{cfg:?}: {worst:?} > {tol:.1e}"
        );
    }
}

/// Positions exactly on the faces, edges and corners of the unit cube, just inside them, and outside (clamped).
#[test]
fn boundary_and_clamped_positions() {
    let Some(gpu) = gpu() else { return };
    let vals = [0.0f32, 1e-7, 0.5, 1.0 - 6e-8, 1.0];
    let mut pos = Vec::new();
    for &x in &vals {
        for &y in &vals {
            for &z in &vals {
                pos.push([x, y, z]);
            }
        }
    }
    let inside = pos.len();
    pos.extend([[-0.25, 0.5, 1.5], [2.0, -1.0, 0.3], [0.7, 1.0001, -1e-6]]);
    for cfg in configs() {
        let layout = HashGridLayout::new(&cfg).unwrap();
        let params = random_values(11, layout.n_params());
        let dfeat = random_values(12, pos.len() * layout.output_dim());
        let g = pollster::block_on(encode_gpu(&gpu, &cfg, &params, &pos)).unwrap();
        let c = encode_cpu(&cfg, &params, &pos).unwrap();
        let scale = encode_cpu(&cfg, &abs(&params), &pos).unwrap();
        assert!(scaled_error(&g, &c, &scale, 1e-6) < 1e-5, "{cfg:?}");
        assert!(g.iter().all(|v| v.is_finite()));
        // Outside the cube reads like the clamped position.
        let clamped: Vec<[f32; 3]> = pos[inside..]
            .iter()
            .map(|x| x.map(|v| v.clamp(0.0, 1.0)))
            .collect();
        let gc = pollster::block_on(encode_gpu(&gpu, &cfg, &params, &clamped)).unwrap();
        assert_eq!(&g[inside * layout.output_dim()..], &gc[..], "{cfg:?}");

        let gb = pollster::block_on(backward_gpu(&gpu, &cfg, &params, &pos, &dfeat, true)).unwrap();
        let cb = backward_cpu(&cfg, &params, &pos, &dfeat, true).unwrap();
        let s = backward_cpu(&cfg, &params, &pos, &abs(&dfeat), false).unwrap();
        assert!(
            scaled_error(&gb.params, &cb.params, &s.params, 1e-6) < 1e-4,
            "{cfg:?}"
        );
        let (gx, cx) = (gb.positions.unwrap(), cb.positions.unwrap());
        for (p, (a, b)) in gx.iter().zip(&cx).enumerate() {
            for axis in 0..3 {
                assert!(a[axis].is_finite());
                let tol = 1e-5 * b[axis].abs().max(1.0) * layout.levels.last().unwrap().scale;
                assert!((a[axis] - b[axis]).abs() <= tol, "{cfg:?} {p} {a:?} {b:?}");
                if !(0.0..=1.0).contains(&pos[p][axis]) {
                    assert_eq!(a[axis], 0.0, "clamped axis has no gradient");
                }
            }
        }
    }
}

/// The trainer's path: forward, backward to the table (twice, the second accumulating) and to the positions,
/// recorded into one encoder over caller-owned buffers, one readback at the end.
#[test]
fn chained_passes_in_one_encoder_with_accumulation() {
    let Some(gpu) = gpu() else { return };
    let cfg = configs()[0];
    let layout = HashGridLayout::new(&cfg).unwrap();
    let d = layout.output_dim();
    let params = random_values(21, layout.n_params());
    let pos = random_positions(22, 700);
    let dfeat = random_values(23, pos.len() * d);
    let n = pos.len() as u32;
    // A position buffer larger than the batch, as a trainer reusing its buffers would have.
    let mut padded = pos.clone();
    padded.extend(random_positions(24, 50));
    let b_params = gpu.upload("params", &params).unwrap();
    let b_pos = gpu.upload("positions", &padded).unwrap();
    let b_dfeat = gpu.upload("dfeat", &dfeat).unwrap();
    let b_feat = gpu.output("features", pos.len() * d).unwrap();
    let b_dparams = gpu.output("dparams", layout.n_params()).unwrap();
    let b_dpos = gpu.output("dpos", pos.len() * 3).unwrap();
    let batch = GpuPositions { buffer: &b_pos, n };
    let mut enc = gpu.encoder("chain");
    pollster::block_on(async {
        hashgrid::record_encode(&gpu, &mut enc, &layout, &b_params, batch, &b_feat).await?;
        for accumulate in [false, true] {
            hashgrid::record_backward_params(
                &gpu, &mut enc, &layout, batch, &b_dfeat, &b_dparams, accumulate,
            )
            .await?;
        }
        hashgrid::record_backward_positions(
            &gpu, &mut enc, &layout, &b_params, batch, &b_dfeat, &b_dpos,
        )
        .await
    })
    .unwrap();
    let out = pollster::block_on(gpu.finish_and_read::<f32>(
        enc,
        &[
            (&b_feat, pos.len() * d),
            (&b_dparams, layout.n_params()),
            (&b_dpos, pos.len() * 3),
        ],
    ))
    .unwrap();
    let feat = encode_cpu(&cfg, &params, &pos).unwrap();
    let fscale = encode_cpu(&cfg, &abs(&params), &pos).unwrap();
    assert!(scaled_error(&out[0], &feat, &fscale, 1e-6) < 1e-5);
    let c = backward_cpu(&cfg, &params, &pos, &dfeat, true).unwrap();
    let s = backward_cpu(&cfg, &params, &pos, &abs(&dfeat), false).unwrap();
    let twice: Vec<f32> = c.params.iter().map(|v| 2.0 * v).collect();
    let s2: Vec<f32> = s.params.iter().map(|v| 2.0 * v).collect();
    assert!(scaled_error(&out[1], &twice, &s2, 1e-6) < 1e-4);
    let cx: Vec<f32> = c.positions.unwrap().into_iter().flatten().collect();
    let norm = cx.iter().map(|v| v.abs()).fold(0.0, f32::max);
    let perr = out[2]
        .iter()
        .zip(&cx)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max)
        / norm;
    assert!(perr < 1e-5, "{perr}");
}

/// More than 65 535 workgroups of 64 (level, point) threads: encode and backward_params fold into 2-D, and
/// every feature is written and the last points' gradients land (their threads are in the second row).
#[test]
fn folded_dispatches_reach_every_point() {
    let Some(gpu) = gpu() else { return };
    let cfg = HashGridConfig {
        levels: 16,
        features_per_level: 1,
        log2_table_size: 8,
        base_resolution: 2,
        finest_resolution: 32,
    };
    let layout = HashGridLayout::new(&cfg).unwrap();
    let n = 65_535 * 64 / 16 + 37;
    assert!(n * 16 > 65_535 * 64);
    let params = random_values(31, layout.n_params());
    let pos = random_positions(32, n);
    let g = pollster::block_on(encode_gpu(&gpu, &cfg, &params, &pos)).unwrap();
    let c = encode_cpu(&cfg, &params, &pos).unwrap();
    let scale = encode_cpu(&cfg, &abs(&params), &pos).unwrap();
    assert!(!g.iter().any(|&v| is_poison(v)));
    assert!(scaled_error(&g, &c, &scale, 1e-6) < 1e-5);
    // Gradient only from the last 5 points (level-major threads: the last level's are the very last).
    let d = layout.output_dim();
    let mut dfeat = vec![0.0f32; n * d];
    dfeat[(n - 5) * d..].copy_from_slice(&random_values(33, 5 * d));
    let g = pollster::block_on(backward_gpu(&gpu, &cfg, &params, &pos, &dfeat, false)).unwrap();
    let c = backward_cpu(&cfg, &params, &pos, &dfeat, false).unwrap();
    let s = backward_cpu(&cfg, &params, &pos, &abs(&dfeat), false).unwrap();
    let last = layout.level_params(15);
    assert!(c.params[last.clone()].iter().any(|&v| v != 0.0));
    assert!(scaled_error(&g.params, &c.params, &s.params, 1e-6) < 1e-4);
}

#[test]
fn bad_inputs_are_errors_and_empty_batches_work() {
    let Some(gpu) = gpu() else { return };
    let cfg = configs()[1];
    let layout = HashGridLayout::new(&cfg).unwrap();
    let params = random_values(51, layout.n_params());
    let err = pollster::block_on(encode_gpu(&gpu, &cfg, &params[1..], &[[0.5; 3]])).unwrap_err();
    assert!(matches!(err, GpuError::InvalidInput(_)), "{err}");
    let err = pollster::block_on(backward_gpu(
        &gpu,
        &cfg,
        &params,
        &[[0.5; 3]],
        &[1.0],
        false,
    ))
    .unwrap_err();
    assert!(err.to_string().contains("dL/dfeatures"), "{err}");
    let bad = HashGridConfig { levels: 40, ..cfg };
    let err = pollster::block_on(encode_gpu(&gpu, &bad, &params, &[])).unwrap_err();
    assert!(err.to_string().contains("levels"), "{err}");

    // Caller buffers too small for the batch are refused before anything is recorded.
    let b_params = gpu.upload("params", &params).unwrap();
    let b_pos = gpu.upload("positions", &random_positions(52, 10)).unwrap();
    let b_small = gpu.output("features", 10).unwrap();
    let mut enc = gpu.encoder("bad");
    let batch = GpuPositions {
        buffer: &b_pos,
        n: 10,
    };
    let err = pollster::block_on(hashgrid::record_encode(
        &gpu, &mut enc, &layout, &b_params, batch, &b_small,
    ))
    .unwrap_err();
    assert!(err.to_string().contains("feature buffer"), "{err}");
    let batch = GpuPositions {
        buffer: &b_pos,
        n: 11,
    };
    let err = pollster::block_on(hashgrid::record_encode(
        &gpu, &mut enc, &layout, &b_params, batch, &b_small,
    ))
    .unwrap_err();
    assert!(err.to_string().contains("position buffer"), "{err}");

    assert!(pollster::block_on(encode_gpu(&gpu, &cfg, &params, &[]))
        .unwrap()
        .is_empty());
    let g = pollster::block_on(backward_gpu(&gpu, &cfg, &params, &[], &[], true)).unwrap();
    assert!(g.params.iter().all(|&v| v == 0.0));
    assert_eq!(g.positions, Some(vec![]));
}

/// Timings at nerfacto's sizes (not a correctness test; run with `--ignored --nocapture`).
#[test]
#[ignore]
fn bench_nerfacto_sizes() {
    use std::time::Instant;
    let Some(gpu) = gpu() else { return };
    let cfg = HashGridConfig::default();
    let layout = HashGridLayout::new(&cfg).unwrap();
    let n: usize = std::env::var("HASHGRID_BENCH_N")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1 << 16);
    let params = random_values(61, layout.n_params());
    let pos = random_positions(62, n);
    let dfeat = random_values(63, n * layout.output_dim());
    eprintln!(
        "hashgrid on {}: {} params, {n} positions",
        gpu.report(),
        layout.n_params()
    );
    let b_params = gpu.upload("params", &params).unwrap();
    let b_pos = gpu.upload("positions", &pos).unwrap();
    let b_dfeat = gpu.upload("dfeat", &dfeat).unwrap();
    let b_feat = gpu.output("features", n * layout.output_dim()).unwrap();
    let b_dparams = gpu.output("dparams", layout.n_params()).unwrap();
    let b_dpos = gpu.output("dpos", n * 3).unwrap();
    let batch = GpuPositions {
        buffer: &b_pos,
        n: n as u32,
    };
    let time = |what: &str, pass: usize| {
        let mut best = f64::INFINITY;
        for _ in 0..4 {
            let t = Instant::now();
            let mut enc = gpu.encoder(what);
            pollster::block_on(async {
                match pass {
                    0 => {
                        hashgrid::record_encode(&gpu, &mut enc, &layout, &b_params, batch, &b_feat)
                            .await
                    }
                    1 | 2 => {
                        hashgrid::record_backward_params(
                            &gpu,
                            &mut enc,
                            &layout,
                            batch,
                            &b_dfeat,
                            &b_dparams,
                            pass == 2,
                        )
                        .await
                    }
                    _ => {
                        hashgrid::record_backward_positions(
                            &gpu, &mut enc, &layout, &b_params, batch, &b_dfeat, &b_dpos,
                        )
                        .await
                    }
                }
            })
            .unwrap();
            pollster::block_on(gpu.finish_and_read::<f32>(enc, &[(&b_feat, 1)])).unwrap();
            best = best.min(t.elapsed().as_secs_f64());
        }
        eprintln!("GPU {what}: {:.1} ms", best * 1e3);
    };
    time("encode", 0);
    time("backward params (clear + atomics)", 1);
    time("backward params (atomics only, accumulate)", 2);
    time("backward positions", 3);
    let t = Instant::now();
    let _ = encode_cpu(&cfg, &params, &pos).unwrap();
    eprintln!(
        "CPU encode ({} rayon threads): {:.1} ms",
        rayon::current_num_threads(),
        t.elapsed().as_secs_f64() * 1e3
    );
    let t = Instant::now();
    let _ = backward_cpu(&cfg, &params, &pos, &dfeat, false).unwrap();
    eprintln!(
        "CPU backward params: {:.1} ms",
        t.elapsed().as_secs_f64() * 1e3
    );
    let t = Instant::now();
    let _ = backward_cpu(&cfg, &params, &pos, &dfeat, true).unwrap();
    eprintln!(
        "CPU backward params + positions: {:.1} ms",
        t.elapsed().as_secs_f64() * 1e3
    );
}
