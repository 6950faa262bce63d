//! The MLP kernels (WGSL, through wgpu — lavapipe where there is no GPU) against their CPU reference, and
//! both against central finite differences of an independent f64 network, on nerfacto's two head shapes
//! and odd ones, with poisoned output buffers.
#![cfg(not(target_arch = "wasm32"))]

use rand::{Rng, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;
use silvr_core::field::mlp::{
    self, backward_cpu, backward_gpu, forward_cpu, forward_gpu, Activation, BackwardBuffers,
    ForwardBuffers, MlpConfig,
};
use silvr_core::gpu::GpuError;

mod common;
use common::gpu;
use common::POISON;

fn cfg(
    input: usize,
    hidden: usize,
    hidden_layers: usize,
    output: usize,
    sigmoid: bool,
) -> MlpConfig {
    MlpConfig {
        input,
        hidden,
        hidden_layers,
        output,
        hidden_activation: Activation::Relu,
        output_activation: if sigmoid {
            Activation::Sigmoid
        } else {
            Activation::None
        },
    }
}

/// nerfacto's density and colour heads, an odd small shape, a deep odd one with a sigmoid, full width and a
/// lone linear layer.
fn configs() -> Vec<MlpConfig> {
    vec![
        MlpConfig::nerfacto_density(),
        MlpConfig::nerfacto_colour(),
        cfg(7, 13, 1, 5, false),
        cfg(17, 9, 3, 2, true),
        cfg(64, 64, 1, 64, false),
        cfg(5, 1, 0, 3, false),
    ]
}

fn rng(seed: u64) -> Xoshiro256PlusPlus {
    Xoshiro256PlusPlus::seed_from_u64(seed)
}

fn random_values(seed: u64, n: usize) -> Vec<f32> {
    let mut r = rng(seed);
    (0..n).map(|_| r.random_range(-1.0f32..1.0)).collect()
}

/// Xavier weights and biases of order 0.1 (zero-initialised biases would leave them untested).
fn random_params(config: &MlpConfig, seed: u64) -> Vec<f32> {
    let mut p = config.init_params(seed);
    let mut r = rng(seed ^ 0x5eed);
    for l in config.layers() {
        for b in &mut p[l.bias..l.bias + l.fan_out] {
            *b = r.random_range(-0.1f32..0.1);
        }
    }
    p
}

fn abs(v: &[f32]) -> Vec<f32> {
    v.iter().map(|x| x.abs()).collect()
}

fn is_poison(v: f32) -> bool {
    v.to_bits() == POISON
}

/// max_i |a_i − b_i| / (scale_i + floor): the error relative to the sum of |terms| that produced b_i.
fn scaled_error(a: &[f32], b: &[f32], scale: &[f32], floor: f32) -> f32 {
    assert_eq!(a.len(), b.len());
    assert_eq!(a.len(), scale.len());
    a.iter()
        .zip(b)
        .zip(scale)
        .map(|((x, y), s)| (x - y).abs() / (s + floor))
        .fold(0.0, f32::max)
}

/// |b| + Σ|W|·|a| layer by layer: the magnitude each pre-activation is summed from (ReLU and the sigmoid
/// are 1-Lipschitz, so it bounds how rounding propagates to the outputs).
fn forward_scale(config: &MlpConfig, params: &[f32], input: &[f32]) -> Vec<f32> {
    let linear = MlpConfig {
        output_activation: Activation::None,
        ..*config
    };
    forward_cpu(&linear, &abs(params), &abs(input))
        .unwrap()
        .output
}

/// The backward run on |params|, |input|, |dL/doutput| with the same ReLU masks: per gradient, the sum of
/// the |terms| it is made of.
fn backward_scale(
    config: &MlpConfig,
    params: &[f32],
    input: &[f32],
    saved: &[f32],
    d_output: &[f32],
) -> mlp::MlpGradients {
    backward_cpu(
        config,
        &abs(params),
        &abs(input),
        saved,
        &abs(d_output),
        true,
    )
    .unwrap()
}

/// Rows for the GPU-vs-CPU tests: several forward workgroups and backward chunks, ragged at both.
const ROWS: usize = 1000;

#[test]
fn forward_matches_cpu() {
    let Some(gpu) = gpu() else { return };
    for (k, c) in configs().iter().enumerate() {
        let params = random_params(c, 100 + k as u64);
        let x = random_values(200 + k as u64, ROWS * c.input);
        let g = pollster::block_on(forward_gpu(&gpu, c, &params, &x)).unwrap();
        let r = forward_cpu(c, &params, &x).unwrap();
        assert_eq!(g.output.len(), ROWS * c.output);
        assert_eq!(g.saved.len(), ROWS * c.saved_per_row());
        assert!(!g.output.iter().any(|&v| is_poison(v)), "unwritten outputs");
        assert!(!g.saved.iter().any(|&v| is_poison(v)), "unwritten saved");
        let scale = forward_scale(c, &params, &x);
        let err = scaled_error(&g.output, &r.output, &scale, 1e-6);
        // Saved activations: each hidden unit against the magnitude of its layer's largest output (a scale
        // per unit would need the per-layer magnitudes; the outputs' bound is coarser but sufficient).
        let smax = scale.iter().fold(0.0f32, |m, &v| m.max(v)).max(1.0);
        let serr = g
            .saved
            .iter()
            .zip(&r.saved)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max)
            / smax;
        let max_abs = g
            .output
            .iter()
            .zip(&r.output)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        eprintln!(
            "forward {}→{}×{}→{} {:?}: output scaled error {err:.2e} (max abs {max_abs:.2e}), saved {serr:.2e}",
            c.input, c.hidden, c.hidden_layers, c.output, c.output_activation
        );
        assert!(err < 1e-5, "{c:?}: {err}");
        assert!(serr < 1e-5, "{c:?}: {serr}");
    }
}

#[test]
fn backward_matches_cpu_and_is_deterministic() {
    let Some(gpu) = gpu() else { return };
    for (k, c) in configs().iter().enumerate() {
        let params = random_params(c, 300 + k as u64);
        let x = random_values(400 + k as u64, ROWS * c.input);
        let dy = random_values(500 + k as u64, ROWS * c.output);
        // Both backwards use the CPU forward's activations, so their ReLU masks are identical.
        let fwd = forward_cpu(c, &params, &x).unwrap();
        let g =
            pollster::block_on(backward_gpu(&gpu, c, &params, &x, &fwd.saved, &dy, true)).unwrap();
        let r = backward_cpu(c, &params, &x, &fwd.saved, &dy, true).unwrap();
        let s = backward_scale(c, &params, &x, &fwd.saved, &dy);
        assert!(!g.params.iter().any(|&v| is_poison(v)), "unwritten dparams");
        let (gi, ri, si) = (g.input.unwrap(), r.input.unwrap(), s.input.unwrap());
        assert!(!gi.iter().any(|&v| is_poison(v)), "unwritten dinput");
        let perr = scaled_error(&g.params, &r.params, &s.params, 1e-6);
        let ierr = scaled_error(&gi, &ri, &si, 1e-6);
        eprintln!(
            "backward {}→{}×{}→{} {:?}: dparams scaled error {perr:.2e}, dinput {ierr:.2e}",
            c.input, c.hidden, c.hidden_layers, c.output, c.output_activation
        );
        assert!(perr < 1e-4, "{c:?}: {perr}");
        assert!(ierr < 1e-5, "{c:?}: {ierr}");
        // No atomics: the same inputs give the same bits.
        let again =
            pollster::block_on(backward_gpu(&gpu, c, &params, &x, &fwd.saved, &dy, false)).unwrap();
        assert_eq!(
            again.params, g.params,
            "{c:?}: GPU gradients not deterministic"
        );
        assert!(again.input.is_none());
    }
}

/// An independent f64 network (same layout, read through `layers()`): outputs and the pre-activation signs
/// of every hidden unit, so finite differences can skip steps that cross a ReLU kink.
fn forward_f64(config: &MlpConfig, params: &[f64], x: &[f64]) -> (Vec<f64>, Vec<bool>) {
    let layers = config.layers();
    let mut a = x.to_vec();
    let mut signs = Vec::new();
    for (l, ly) in layers.iter().enumerate() {
        let mut z = vec![0.0f64; ly.fan_out];
        for (j, zj) in z.iter_mut().enumerate() {
            let mut s = params[ly.bias + j];
            for k in 0..ly.fan_in {
                s += params[ly.weights + j * ly.fan_in + k] * a[k];
            }
            *zj = s;
        }
        if l + 1 < layers.len() {
            signs.extend(z.iter().map(|&v| v > 0.0));
            a = z.iter().map(|&v| v.max(0.0)).collect();
        } else if config.output_activation == Activation::Sigmoid {
            a = z.iter().map(|&v| 1.0 / (1.0 + (-v).exp())).collect();
        } else {
            a = z;
        }
    }
    (a, signs)
}

/// L = Σ w·Y (f64, random w): central differences along a subset of parameters (half weights, half biases,
/// every layer) and of inputs, against the CPU and GPU gradients, errors relative to Σ|terms|. The CPU half
/// runs without an adapter too.
#[test]
fn backward_matches_finite_differences() {
    let gpu = gpu();
    let rows = 150;
    for (k, c) in configs().iter().enumerate() {
        let params = random_params(c, 600 + k as u64);
        let x = random_values(700 + k as u64, rows * c.input);
        let w = random_values(800 + k as u64, rows * c.output);
        let fwd = forward_cpu(c, &params, &x).unwrap();
        let cpu = backward_cpu(c, &params, &x, &fwd.saved, &w, true).unwrap();
        // Without a GPU, the CPU gradients stand in for it (and are checked once more).
        let gpu_g = match &gpu {
            Some(g) => {
                pollster::block_on(backward_gpu(g, c, &params, &x, &fwd.saved, &w, true)).unwrap()
            }
            None => cpu.clone(),
        };
        let s = backward_scale(c, &params, &x, &fwd.saved, &w);
        let p64: Vec<f64> = params.iter().map(|&v| v as f64).collect();
        let x64: Vec<f64> = x.iter().map(|&v| v as f64).collect();
        let row_loss = |p: &[f64], r: usize, xr: &[f64]| -> (f64, Vec<bool>) {
            let (y, signs) = forward_f64(c, p, xr);
            let l = y
                .iter()
                .zip(&w[r * c.output..(r + 1) * c.output])
                .map(|(a, &b)| a * b as f64)
                .sum();
            (l, signs)
        };
        let loss = |p: &[f64]| -> (f64, Vec<bool>) {
            let mut total = 0.0;
            let mut signs = Vec::new();
            for r in 0..rows {
                let (l, s) = row_loss(p, r, &x64[r * c.input..(r + 1) * c.input]);
                total += l;
                signs.extend(s);
            }
            (total, signs)
        };
        let (_, base_signs) = loss(&p64);
        let h = 1e-6;
        let mut r = rng(900 + k as u64);
        let layers = c.layers();
        let (mut worst, mut checked, mut skipped) = ((0.0f64, 0.0f64), 0, 0);
        for (l, ly) in layers.iter().enumerate() {
            for t in 0..8 {
                let i = if t % 2 == 0 {
                    ly.weights + r.random_range(0..ly.fan_in * ly.fan_out)
                } else {
                    ly.bias + r.random_range(0..ly.fan_out)
                };
                let mut p = p64.clone();
                p[i] += h;
                let (lp, sp) = loss(&p);
                p[i] -= 2.0 * h;
                let (lm, sm) = loss(&p);
                if sp != base_signs || sm != base_signs {
                    skipped += 1;
                    continue;
                }
                let fd = (lp - lm) / (2.0 * h);
                let sc = s.params[i] as f64 + 1e-6;
                let ec = (fd - cpu.params[i] as f64).abs() / sc;
                let eg = (fd - gpu_g.params[i] as f64).abs() / sc;
                assert!(
                    ec < 1e-4 && eg < 1e-4,
                    "{c:?} layer {l} param {i}: fd {fd} cpu {} gpu {}",
                    cpu.params[i],
                    gpu_g.params[i]
                );
                worst = (worst.0.max(ec), worst.1.max(eg));
                checked += 1;
            }
        }
        assert!(
            checked >= 6 * layers.len(),
            "{checked} checked, {skipped} skipped"
        );
        let (ci, gi, si) = (
            cpu.input.as_ref().unwrap(),
            gpu_g.input.as_ref().unwrap(),
            s.input.as_ref().unwrap(),
        );
        let mut iworst = (0.0f64, 0.0f64);
        for _ in 0..40 {
            let row = r.random_range(0..rows);
            let col = r.random_range(0..c.input);
            let xr = &x64[row * c.input..(row + 1) * c.input];
            let (_, s0) = row_loss(&p64, row, xr);
            let mut xp = xr.to_vec();
            xp[col] += h;
            let (lp, sp) = row_loss(&p64, row, &xp);
            xp[col] -= 2.0 * h;
            let (lm, sm) = row_loss(&p64, row, &xp);
            if sp != s0 || sm != s0 {
                continue;
            }
            let fd = (lp - lm) / (2.0 * h);
            let i = row * c.input + col;
            let sc = si[i] as f64 + 1e-6;
            iworst = (
                iworst.0.max((fd - ci[i] as f64).abs() / sc),
                iworst.1.max((fd - gi[i] as f64).abs() / sc),
            );
        }
        eprintln!(
            "FD {}→{}×{}→{} {:?}: {checked} params (skipped {skipped}) CPU {:.2e} GPU {:.2e}; inputs CPU {:.2e} GPU {:.2e} (error / Σ|terms|){}",
            c.input, c.hidden, c.hidden_layers, c.output, c.output_activation,
            worst.0, worst.1, iworst.0, iworst.1,
            if gpu.is_none() { " [no GPU: CPU twice]" } else { "" }
        );
        assert!(iworst.0 < 1e-5 && iworst.1 < 1e-5, "{c:?}: {iworst:?}");
    }
}

/// The trainer's path: forward, a second forward into other buffers (as inference would), backward twice
/// (the second accumulating) with dL/dinput, all recorded into one encoder over caller-owned buffers (the
/// input and output larger than the batch), one readback at the end.
#[test]
fn chained_passes_in_one_encoder_with_accumulation() {
    let Some(gpu) = gpu() else { return };
    let c = MlpConfig::nerfacto_colour();
    let n = 700usize;
    let params = random_params(&c, 21);
    let x = random_values(22, (n + 30) * c.input);
    let dy = random_values(23, n * c.output);
    let b_params = gpu.upload("params", &params).unwrap();
    let b_x = gpu.upload("input", &x).unwrap();
    let b_dy = gpu.upload("dy", &dy).unwrap();
    let b_y = gpu.output("output", (n + 30) * c.output).unwrap();
    let b_y2 = gpu.output("output (inference)", n * c.output).unwrap();
    let b_saved = gpu.output("saved", n * c.saved_per_row()).unwrap();
    let b_saved2 = gpu
        .output("saved (inference)", n * c.saved_per_row())
        .unwrap();
    let b_scratch = gpu.output("scratch", c.scratch_words(n)).unwrap();
    let b_dparams = gpu.output("dparams", c.n_params()).unwrap();
    let b_dx = gpu.output("dinput", n * c.input).unwrap();
    let mut enc = gpu.encoder("chain");
    pollster::block_on(async {
        let fb = ForwardBuffers {
            params: &b_params,
            input: &b_x,
            output: &b_y,
            saved: &b_saved,
        };
        mlp::record_forward(&gpu, &mut enc, &c, n as u32, &fb).await?;
        let inference = ForwardBuffers {
            output: &b_y2,
            saved: &b_saved2,
            ..fb
        };
        mlp::record_forward(&gpu, &mut enc, &c, n as u32, &inference).await?;
        for accumulate in [false, true] {
            let bb = BackwardBuffers {
                params: &b_params,
                input: &b_x,
                saved: &b_saved,
                d_output: &b_dy,
                scratch: &b_scratch,
                d_params: Some(&b_dparams),
                d_input: Some(&b_dx),
            };
            mlp::record_backward(&gpu, &mut enc, &c, n as u32, &bb, accumulate).await?;
        }
        Ok::<(), GpuError>(())
    })
    .unwrap();
    let out = pollster::block_on(gpu.finish_and_read::<f32>(
        enc,
        &[
            (&b_y, (n + 30) * c.output),
            (&b_y2, n * c.output),
            (&b_saved, n * c.saved_per_row()),
            (&b_dparams, c.n_params()),
            (&b_dx, n * c.input),
        ],
    ))
    .unwrap();
    let x = &x[..n * c.input];
    let fwd = forward_cpu(&c, &params, x).unwrap();
    let scale = forward_scale(&c, &params, x);
    assert!(scaled_error(&out[0][..n * c.output], &fwd.output, &scale, 1e-6) < 1e-5);
    // Rows past the batch are left alone.
    assert!(out[0][n * c.output..].iter().all(|&v| is_poison(v)));
    assert_eq!(out[1], out[0][..n * c.output], "inference forward differs");
    // The CPU backward over the GPU's saved activations (same ReLU masks), doubled.
    let saved = &out[2];
    let r = backward_cpu(&c, &params, x, saved, &dy, true).unwrap();
    let s = backward_scale(&c, &params, x, saved, &dy);
    let twice: Vec<f32> = r.params.iter().map(|v| 2.0 * v).collect();
    let s2: Vec<f32> = s.params.iter().map(|v| 2.0 * v).collect();
    let perr = scaled_error(&out[3], &twice, &s2, 1e-6);
    let ierr = scaled_error(&out[4], &r.input.unwrap(), &s.input.unwrap(), 1e-6);
    eprintln!("chained: dparams (accumulated twice) {perr:.2e}, dinput {ierr:.2e}");
    assert!(perr < 1e-4 && ierr < 1e-5, "{perr} {ierr}");
}

/// Rows exactly on the ReLU kink, huge pre-activations under the sigmoid, and all-zero inputs: finite results
/// equal to the CPU's (a unit at exactly 0 is inactive on both).
/// The input-only backward (no `d_params`: no parameter-gradient passes, as the uncertainty pass runs it)
/// gives exactly the full backward's dL/dinput.
#[test]
fn input_only_backward_matches_the_full_backward() {
    let Some(gpu) = gpu() else { return };
    for (k, c) in configs().into_iter().enumerate() {
        let n = 300;
        let params = random_params(&c, 40 + k as u64);
        let x = random_values(50 + k as u64, n * c.input);
        let dy = random_values(60 + k as u64, n * c.output);
        let fwd = pollster::block_on(mlp::forward_gpu(&gpu, &c, &params, &x)).unwrap();
        let full = pollster::block_on(mlp::backward_gpu(
            &gpu, &c, &params, &x, &fwd.saved, &dy, true,
        ))
        .unwrap();
        let b_params = gpu.upload("params", &params).unwrap();
        let b_x = gpu.upload("input", &x).unwrap();
        let b_saved = gpu.upload("saved", &fwd.saved).unwrap();
        let b_dy = gpu.upload("dy", &dy).unwrap();
        let b_scratch = gpu.output("scratch", c.scratch_words(n)).unwrap();
        let b_dx = gpu.output("dinput", n * c.input).unwrap();
        let mut enc = gpu.encoder("input only");
        let bb = BackwardBuffers {
            params: &b_params,
            input: &b_x,
            saved: &b_saved,
            d_output: &b_dy,
            scratch: &b_scratch,
            d_params: None,
            d_input: Some(&b_dx),
        };
        pollster::block_on(mlp::record_backward(
            &gpu, &mut enc, &c, n as u32, &bb, false,
        ))
        .unwrap();
        let dx = pollster::block_on(gpu.finish_and_read::<f32>(enc, &[(&b_dx, n * c.input)]))
            .unwrap()
            .remove(0);
        assert_eq!(&dx, full.input.as_ref().unwrap(), "{c:?}");
    }
}

#[test]
fn kinks_and_saturation() {
    let Some(gpu) = gpu() else { return };
    let c = cfg(4, 8, 2, 3, true);
    let mut params = vec![0.0f32; c.n_params()];
    let layers = c.layers();
    // Layer 0: unit j = x_0 − x_1 (zero when they are equal), others large.
    for j in 0..8 {
        params[layers[0].weights + j * 4] = 1.0;
        params[layers[0].weights + j * 4 + 1] = if j == 0 { -1.0 } else { 30.0 };
    }
    for j in 0..8 {
        for k in 0..8 {
            params[layers[1].weights + j * 8 + k] = if j == k { 40.0 } else { 0.0 };
        }
    }
    for j in 0..3 {
        for k in 0..8 {
            params[layers[2].weights + j * 8 + k] = if j == 1 { -50.0 } else { 50.0 };
        }
    }
    let x = vec![
        0.5, 0.5, 0.0, 0.0, // unit 0 exactly at the kink
        0.0, 0.0, 0.0, 0.0, // everything zero
        1.0, 1.0, 1.0, 1.0, // saturated sigmoid
        -1.0, 1.0, 0.3, 0.2,
    ];
    let dy = vec![1.0f32; 4 * 3];
    let g = pollster::block_on(forward_gpu(&gpu, &c, &params, &x)).unwrap();
    let r = forward_cpu(&c, &params, &x).unwrap();
    assert!(g.output.iter().all(|v| v.is_finite()));
    assert_eq!(g.saved[0], 0.0, "unit at the kink");
    let scale = forward_scale(&c, &params, &x);
    assert!(scaled_error(&g.output, &r.output, &scale, 1e-6) < 1e-5);
    for (a, b) in g.saved.iter().zip(&r.saved) {
        assert_eq!(*a == 0.0, *b == 0.0, "ReLU masks differ");
    }
    let gb = pollster::block_on(backward_gpu(&gpu, &c, &params, &x, &r.saved, &dy, true)).unwrap();
    let rb = backward_cpu(&c, &params, &x, &r.saved, &dy, true).unwrap();
    assert!(gb.params.iter().all(|v| v.is_finite()));
    let s = backward_scale(&c, &params, &x, &r.saved, &dy);
    assert!(scaled_error(&gb.params, &rb.params, &s.params, 1e-6) < 1e-4);
    assert!(
        scaled_error(
            gb.input.as_ref().unwrap(),
            rb.input.as_ref().unwrap(),
            s.input.as_ref().unwrap(),
            1e-6
        ) < 1e-5
    );
}

/// More than 65 535 parameter-gradient workgroups (chunks × blocks), so that dispatch folds into 2-D: a
/// deep, 1-wide network keeps the batch cheap. Only the last rows have a gradient, and their chunks' groups
/// sit in the folded dispatch's second row.
#[test]
fn folded_weight_gradient_dispatch_reaches_every_chunk() {
    let Some(gpu) = gpu() else { return };
    let c = cfg(1, 1, 8, 1, false);
    let n = 7300 * mlp::CHUNK_ROWS;
    let blocks: usize = c.layers().iter().map(|l| (l.fan_in + 1).div_ceil(16)).sum();
    assert!(MlpConfig::chunks(n) * blocks > 65_535);
    // Positive weights and biases keep every unit active, so the gradient reaches every layer.
    let params: Vec<f32> = (0..c.n_params()).map(|i| 0.5 + 0.05 * i as f32).collect();
    let x = random_values(41, n);
    // The CPU forward is enough here: the forward's dispatches (one group per 64 rows) do not fold.
    let fwd = forward_cpu(&c, &params, &x).unwrap();
    let mut dy = vec![0.0f32; n];
    dy[n - 3..].copy_from_slice(&[0.5, -1.0, 2.0]);
    let g =
        pollster::block_on(backward_gpu(&gpu, &c, &params, &x, &fwd.saved, &dy, false)).unwrap();
    let r = backward_cpu(&c, &params, &x, &fwd.saved, &dy, false).unwrap();
    assert!(r.params.iter().all(|&v| v != 0.0), "{:?}", r.params);
    // All terms are positive-weighted sums of few rows: a plain relative error suffices.
    let err = g
        .params
        .iter()
        .zip(&r.params)
        .map(|(a, b)| (a - b).abs() / b.abs())
        .fold(0.0, f32::max);
    assert!(err < 1e-4, "{err}: {:?} vs {:?}", g.params, r.params);
}

#[test]
fn bad_inputs_are_errors_and_empty_batches_work() {
    let Some(gpu) = gpu() else { return };
    let c = MlpConfig::nerfacto_density();
    let params = c.init_params(1);
    for bad in [
        MlpConfig { input: 0, ..c },
        MlpConfig { hidden: 65, ..c },
        MlpConfig { output: 70, ..c },
        MlpConfig {
            hidden_layers: 9,
            ..c
        },
        MlpConfig {
            hidden_activation: Activation::Sigmoid,
            ..c
        },
        MlpConfig {
            output_activation: Activation::Relu,
            ..c
        },
    ] {
        let err = pollster::block_on(forward_gpu(&gpu, &bad, &params, &[])).unwrap_err();
        assert!(matches!(err, GpuError::InvalidInput(_)), "{bad:?}: {err}");
    }
    let err = pollster::block_on(forward_gpu(&gpu, &c, &params[1..], &[0.0; 32])).unwrap_err();
    assert!(err.to_string().contains("parameters"), "{err}");
    let err = pollster::block_on(forward_gpu(&gpu, &c, &params, &[0.0; 33])).unwrap_err();
    assert!(err.to_string().contains("multiple"), "{err}");
    let fwd = forward_cpu(&c, &params, &[0.1; 64]).unwrap();
    let err = pollster::block_on(backward_gpu(
        &gpu, &c, &params, &[0.1; 64], &fwd.saved, &[1.0; 31], true,
    ))
    .unwrap_err();
    assert!(err.to_string().contains("dL/doutput"), "{err}");

    // Caller buffers too small for the batch are refused before anything is recorded.
    let b_params = gpu.upload("params", &params).unwrap();
    let b_x = gpu.upload("x", &[0.0f32; 10 * 32]).unwrap();
    let b_small = gpu.output("out", 10).unwrap();
    let b_saved = gpu.output("saved", 11 * c.saved_per_row()).unwrap();
    let mut enc = gpu.encoder("bad");
    let fb = ForwardBuffers {
        params: &b_params,
        input: &b_x,
        output: &b_small,
        saved: &b_saved,
    };
    let err = pollster::block_on(mlp::record_forward(&gpu, &mut enc, &c, 10, &fb)).unwrap_err();
    assert!(err.to_string().contains("output buffer"), "{err}");
    let err = pollster::block_on(mlp::record_forward(&gpu, &mut enc, &c, 11, &fb)).unwrap_err();
    assert!(err.to_string().contains("input buffer"), "{err}");

    let empty = pollster::block_on(forward_gpu(&gpu, &c, &params, &[])).unwrap();
    assert!(empty.output.is_empty() && empty.saved.is_empty());
    let g = pollster::block_on(backward_gpu(&gpu, &c, &params, &[], &[], &[], true)).unwrap();
    assert_eq!(g.params, vec![0.0; c.n_params()], "cleared over the poison");
    assert_eq!(g.input, Some(vec![]));
}

#[test]
fn init_is_xavier_uniform_and_reproducible() {
    let c = MlpConfig::nerfacto_colour();
    let a = c.init_params(7);
    assert_eq!(a, c.init_params(7));
    assert_ne!(a, c.init_params(8));
    assert_eq!(a.len(), 63 * 64 + 64 + 64 * 64 + 64 + 64 * 3 + 3);
    for l in c.layers() {
        let bound = (6.0 / (l.fan_in + l.fan_out) as f32).sqrt();
        let w = &a[l.weights..l.bias];
        assert!(w.iter().all(|v| v.abs() <= bound));
        // Spread over the range, not concentrated near zero.
        let var = w.iter().map(|v| v * v).sum::<f32>() / w.len() as f32;
        assert!((var - bound * bound / 3.0).abs() < 0.15 * bound * bound / 3.0);
        assert!(a[l.bias..l.bias + l.fan_out].iter().all(|&v| v == 0.0));
    }
    let d = MlpConfig::nerfacto_density();
    assert_eq!(d.n_params(), 32 * 64 + 64 + 64 * 16 + 16);
    assert_eq!(d.saved_per_row(), 64);
    assert_eq!(c.saved_per_row(), 64 + 64 + 3);
}

/// Throughput at nerfacto's sizes (not a correctness test; run with `--ignored --nocapture`).
#[test]
#[ignore]
fn bench_nerfacto_heads() {
    use std::time::Instant;
    let Some(gpu) = gpu() else { return };
    let n: usize = std::env::var("MLP_BENCH_N")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1 << 16);
    eprintln!("MLP on {}: {n} rows", gpu.report());
    for c in [MlpConfig::nerfacto_density(), MlpConfig::nerfacto_colour()] {
        let params = random_params(&c, 61);
        let x = random_values(62, n * c.input);
        let dy = random_values(63, n * c.output);
        let b_params = gpu.upload("params", &params).unwrap();
        let b_x = gpu.upload("x", &x).unwrap();
        let b_dy = gpu.upload("dy", &dy).unwrap();
        let b_y = gpu.output("y", n * c.output).unwrap();
        let b_saved = gpu.output("saved", n * c.saved_per_row()).unwrap();
        let b_scratch = gpu.output("scratch", c.scratch_words(n)).unwrap();
        let b_dparams = gpu.output("dparams", c.n_params()).unwrap();
        let b_dx = gpu.output("dx", n * c.input).unwrap();
        let fb = ForwardBuffers {
            params: &b_params,
            input: &b_x,
            output: &b_y,
            saved: &b_saved,
        };
        let bb = BackwardBuffers {
            params: &b_params,
            input: &b_x,
            saved: &b_saved,
            d_output: &b_dy,
            scratch: &b_scratch,
            d_params: Some(&b_dparams),
            d_input: Some(&b_dx),
        };
        let flops = 2.0
            * c.layers()
                .iter()
                .map(|l| (l.fan_in * l.fan_out) as f64)
                .sum::<f64>();
        let time = |what: &str, passes: u32| {
            let mut best = f64::INFINITY;
            for _ in 0..3 {
                let t = Instant::now();
                let mut enc = gpu.encoder(what);
                pollster::block_on(async {
                    if passes & 1 != 0 {
                        mlp::record_forward(&gpu, &mut enc, &c, n as u32, &fb).await?;
                    }
                    if passes & 2 != 0 {
                        mlp::record_backward(&gpu, &mut enc, &c, n as u32, &bb, false).await?;
                    }
                    Ok::<(), GpuError>(())
                })
                .unwrap();
                pollster::block_on(gpu.finish_and_read::<f32>(enc, &[(&b_dparams, 1)])).unwrap();
                best = best.min(t.elapsed().as_secs_f64());
            }
            // Forward ≈ 1×, backward ≈ 2× the forward's multiply-adds.
            let f = flops * n as f64 * [0.0, 1.0, 2.0, 3.0][passes as usize];
            eprintln!(
                "  GPU {what}: {:.1} ms, {:.0} k samples/s, {:.2} GFLOP/s",
                best * 1e3,
                n as f64 / best / 1e3,
                f / best / 1e9
            );
        };
        eprintln!(
            "{}→{}×{}→{} ({} params):",
            c.input,
            c.hidden,
            c.hidden_layers,
            c.output,
            c.n_params()
        );
        time("forward", 1);
        time("backward", 2);
        time("forward+backward", 3);
        let t = Instant::now();
        let fwd = forward_cpu(&c, &params, &x).unwrap();
        let tf = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let _ = backward_cpu(&c, &params, &x, &fwd.saved, &dy, true).unwrap();
        let tb = t.elapsed().as_secs_f64();
        eprintln!(
            "  CPU reference ({} rayon threads): forward {:.1} ms ({:.0} k samples/s), forward+backward {:.0} k samples/s",
            rayon::current_num_threads(),
            tf * 1e3,
            n as f64 / tf / 1e3,
            n as f64 / (tf + tb) / 1e3
        );
    }
}

/// The MLP passes `gpu` ran since the last call, as (kernel::entry, dispatches), from the kernel layer's
/// per-pass profile (`GpuOptions::profile`): what ran, not what a flag says will.
fn passes_ran(gpu: &silvr_core::gpu::Gpu) -> Vec<(String, u64)> {
    gpu.profile_take()
        .into_iter()
        .map(|r| (r.pass, r.calls))
        .collect()
}

/// The dispatches one inference of `c` records: one fused `forward_fused` where [`mlp::fuses_inference`],
/// else the layer by layer forward (hardware GPUs, browsers).
fn inference_passes(gpu: &silvr_core::gpu::Gpu, c: &MlpConfig) -> Vec<(String, u64)> {
    if mlp::fuses_inference(gpu) {
        vec![("mlp::forward_fused".into(), 1)]
    } else {
        vec![("mlp::forward_layer".into(), c.n_layers() as u64)]
    }
}

/// Inference (`record_inference`: one fused dispatch on lavapipe, the layer by layer forward elsewhere)
/// gives the forward's outputs on nerfacto's heads and odd shapes, into a poisoned output buffer, and the
/// dispatches that ran are the path it claims (counted by the kernel layer's profile).
#[test]
fn inference_matches_cpu() {
    let Some(gpu) = common::gpu_with(silvr_core::gpu::GpuOptions {
        poison: Some(POISON),
        profile: true,
        ..Default::default()
    }) else {
        return;
    };
    // lavapipe (CI) must take the fused path this test is for. There every shape fuses: nerfacto's colour
    // head stages its two 64 x 64 layers in the 32 KiB of workgroup memory and reads the last from storage
    // (both paths of the generated forward).
    let lavapipe = gpu.report().driver.contains("llvmpipe");
    assert!(
        !lavapipe || mlp::fuses_inference(&gpu),
        "{:?}",
        gpu.report()
    );
    let shapes = [
        MlpConfig::nerfacto_density(),
        MlpConfig::nerfacto_colour(),
        cfg(17, 9, 3, 2, true),
        cfg(5, 1, 0, 3, false),
    ];
    for (i, c) in shapes.into_iter().enumerate() {
        let params = random_params(&c, 300 + i as u64);
        let input = random_values(400 + i as u64, ROWS * c.input);
        let want = forward_cpu(&c, &params, &input).unwrap();
        let scale = forward_scale(&c, &params, &input);
        passes_ran(&gpu);
        let got = pollster::block_on(mlp::inference_gpu(&gpu, &c, &params, &input)).unwrap();
        assert_eq!(passes_ran(&gpu), inference_passes(&gpu, &c), "{c:?}");
        assert_eq!(got.len(), want.output.len());
        assert!(
            !got.iter().any(|&v| is_poison(v)),
            "{c:?}: a row not written"
        );
        let e = scaled_error(&got, &want.output, &scale, 1e-6);
        assert!(e < 1e-5, "{c:?}: inference vs CPU, scaled error {e}");
    }
}

/// The loop form of the kernels (what every adapter but lavapipe runs: `GpuOptions::loop_kernels`) against
/// the CPU reference on nerfacto's heads and an odd shape: forward, inference (the layer by layer path
/// hardware GPUs and browsers run, checked by the dispatches that ran), and the full backward; every
/// output as long as the reference's.
#[test]
fn loop_kernels_match_cpu() {
    let Some(gpu) = common::gpu_with(silvr_core::gpu::GpuOptions {
        poison: Some(POISON),
        loop_kernels: true,
        profile: true,
        ..Default::default()
    }) else {
        return;
    };
    assert!(!gpu.straight_line_kernels());
    assert!(!mlp::fuses_inference(&gpu));
    let close = |what: &str, c: &MlpConfig, got: &[f32], want: &[f32], tol: &dyn Fn(f32) -> f32| {
        assert_eq!(got.len(), want.len(), "{c:?}: {what} length");
        for (a, b) in got.iter().zip(want) {
            assert!((a - b).abs() <= tol(*b), "{c:?}: {what} {a} vs {b}");
        }
    };
    let rel = |b: f32| 1e-4 * (1.0 + b.abs());
    for (i, c) in [
        MlpConfig::nerfacto_density(),
        MlpConfig::nerfacto_colour(),
        cfg(17, 9, 3, 2, true),
    ]
    .into_iter()
    .enumerate()
    {
        let n = 700;
        let params = c.init_params(11 + i as u64);
        let input = random_values(50 + i as u64, n * c.input);
        let d_out = random_values(90 + i as u64, n * c.output);
        let want = forward_cpu(&c, &params, &input).unwrap();
        let got = pollster::block_on(forward_gpu(&gpu, &c, &params, &input)).unwrap();
        close("forward", &c, &got.output, &want.output, &rel);
        close("saved", &c, &got.saved, &want.saved, &rel);
        passes_ran(&gpu);
        let inf = pollster::block_on(mlp::inference_gpu(&gpu, &c, &params, &input)).unwrap();
        assert_eq!(
            passes_ran(&gpu),
            [("mlp::forward_layer".to_string(), c.n_layers() as u64)],
            "{c:?}: inference on the loop kernels"
        );
        close("inference", &c, &inf, &want.output, &rel);
        let gw = backward_cpu(&c, &params, &input, &want.saved, &d_out, true).unwrap();
        let gg = pollster::block_on(backward_gpu(
            &gpu,
            &c,
            &params,
            &input,
            &want.saved,
            &d_out,
            true,
        ))
        .unwrap();
        let scale = gw.params.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-6);
        close("dparams", &c, &gg.params, &gw.params, &|_| 1e-4 * scale);
        close("dinput", &c, &gg.input.unwrap(), &gw.input.unwrap(), &rel);
    }
}
