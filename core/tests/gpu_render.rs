//! The volume-rendering and ray-loss kernels (WGSL, through wgpu — lavapipe where there is no GPU) against
//! their CPU reference, both against central finite differences of an independent f64 implementation of the
//! total loss, and the edge cases (empty, saturated, padded rays, lidar depth off the samples), with
//! poisoned output buffers.
#![cfg(not(target_arch = "wasm32"))]

use rand::{Rng, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;
use silvr_core::gpu::GpuError;
use silvr_core::render::{
    self, backward_cpu, losses_cpu, render_backward_gpu, render_cpu, render_gpu, Background,
    GpuRayBatch, Interval, LossConfig, RayBatch, RayTarget, RenderGradients, Sample, LOG_EPS,
    NORMAL_EPS,
};

mod common;
use common::gpu;
use common::POISON;

fn rng(seed: u64) -> Xoshiro256PlusPlus {
    Xoshiro256PlusPlus::seed_from_u64(seed)
}

fn is_poison(v: f32) -> bool {
    v.to_bits() == POISON
}

/// Owned ray data; `batch()` borrows it as the API's view.
#[derive(Clone)]
struct Rays {
    s: usize,
    samples: Vec<Sample>,
    intervals: Vec<Interval>,
    normals: Option<Vec<[f32; 3]>>,
    targets: Vec<RayTarget>,
}

impl Rays {
    fn batch(&self) -> RayBatch<'_> {
        RayBatch {
            samples_per_ray: self.s,
            samples: &self.samples,
            intervals: &self.intervals,
            normals: self.normals.as_deref(),
        }
    }

    fn rays(&self) -> usize {
        self.targets.len()
    }
}

fn unit(v: [f32; 3]) -> [f32; 3] {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    v.map(|x| x / l)
}

fn random_dir(r: &mut Xoshiro256PlusPlus) -> [f32; 3] {
    loop {
        let v = [0; 3].map(|_| r.random_range(-1.0f32..1.0));
        let l2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
        if l2 > 0.01 && l2 <= 1.0 {
            return unit(v);
        }
    }
}

/// Random rays: opacities from nearly empty to saturating, trailing padding on some rays (with junk colour
/// and density, which must be ignored), and targets that mix lidar depth inside and outside the samples,
/// no lidar, sky, and lidar normals on some rays.
fn random_rays(seed: u64, rays: usize, s: usize, with_normals: bool) -> Rays {
    let mut r = rng(seed);
    let mut samples = Vec::with_capacity(rays * s);
    let mut intervals = Vec::with_capacity(rays * s);
    let mut normals = Vec::with_capacity(rays * s);
    let mut targets = Vec::with_capacity(rays);
    for _ in 0..rays {
        let valid = if r.random_bool(0.7) {
            s
        } else {
            r.random_range(0..=s)
        };
        let opacity = 10f32.powf(r.random_range(-2.0..1.5));
        let base_n = random_dir(&mut r);
        let near = r.random_range(0.05f32..2.0);
        let mut t = near;
        for i in 0..s {
            let rgb = [0; 3].map(|_| r.random_range(0.0f32..1.0));
            let n = base_n.map(|b| b + 0.6 * r.random_range(-1.0f32..1.0));
            normals.push(unit(n));
            if i < valid {
                let density = if r.random_bool(0.15) {
                    0.0
                } else {
                    opacity * 10f32.powf(r.random_range(-1.5..1.5))
                };
                let delta = 10f32.powf(r.random_range(-2.3..-0.8));
                samples.push(Sample { rgb, density });
                intervals.push(Interval {
                    start: t,
                    end: t + delta,
                });
                t += delta;
            } else {
                let density = if r.random_bool(0.5) { 1e30 } else { 3.0 };
                samples.push(Sample { rgb, density });
                intervals.push(Interval { start: t, end: t });
            }
        }
        let far = t;
        let kind = r.random_range(0..20);
        let (depth, sky) = match kind {
            0..=6 => (r.random_range(near..far.max(near + 1e-3)), 0),
            7 => (far + r.random_range(0.5..5.0), 0),
            8 => (near * r.random_range(0.05..0.5), 0),
            9..=12 => (0.0, 1),
            // A sky ray may carry a (meaningless) range: the sky flag wins.
            13 => (r.random_range(near..far.max(near + 1e-3)), 1),
            _ => (0.0, 0),
        };
        let normal = if sky == 0 && r.random_bool(0.5) {
            let n = base_n.map(|b| b + 0.8 * r.random_range(-1.0f32..1.0));
            // Any length: the loss normalises it.
            unit(n).map(|x| x * r.random_range(0.3f32..3.0))
        } else {
            [0.0; 3]
        };
        targets.push(RayTarget {
            rgb: [0; 3].map(|_| r.random_range(0.0f32..1.0)),
            depth,
            normal,
            sky,
        });
    }
    Rays {
        s,
        samples,
        intervals,
        normals: with_normals.then_some(normals),
        targets,
    }
}

/// Weights of order one so every term shows in the total (SiLVR's defaults make the normal term tiny).
fn test_config(depth_sigma: f32) -> LossConfig {
    LossConfig {
        rgb: 1.0,
        depth: 0.5,
        normal: 0.3,
        sky: 0.7,
        depth_sigma,
    }
}

/// (background, with per-sample normals, S, DS-NeRF σ) combinations the comparisons run over.
fn cases() -> Vec<(Background, bool, usize, f32)> {
    vec![
        (Background::LastSample, true, 32, 0.05),
        (Background::Black, false, 48, 0.02),
        (Background::Constant([0.2, 0.9, 0.4]), true, 7, 0.1),
        (Background::LastSample, false, 1, 0.05),
    ]
}

fn max_err(a: &[f32], b: &[f32], scale: impl Fn(usize) -> f64) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .enumerate()
        .map(|(i, (&x, &y))| (x as f64 - y as f64).abs() / scale(i))
        .fold(0.0, f64::max)
}

#[test]
fn forward_matches_cpu() {
    let Some(gpu) = gpu() else { return };
    for (k, (bg, with_normals, s, _)) in cases().into_iter().enumerate() {
        let rays = random_rays(100 + k as u64, 300, s, with_normals);
        let batch = rays.batch();
        let g = pollster::block_on(render_gpu(&gpu, &batch, bg)).unwrap();
        let c = render_cpu(&batch, bg).unwrap();
        assert_eq!(g.weights.len(), rays.samples.len());
        assert_eq!(g.rays.len(), rays.rays());
        assert!(
            !g.weights.iter().any(|&v| is_poison(v)),
            "unwritten weights"
        );
        let flat =
            |o: &[render::RayOutput]| -> Vec<f32> { bytemuck::cast_slice::<_, f32>(o).to_vec() };
        let (go, co) = (flat(&g.rays), flat(&c.rays));
        assert!(!go.iter().any(|&v| is_poison(v)), "unwritten ray outputs");
        // Weights: relative, with a floor far below anything that matters next to Σw ≤ 1.
        let ew = max_err(&g.weights, &c.weights, |i| c.weights[i].abs() as f64 + 1e-7);
        // Colour/accumulation/normal are O(1); depth relative to the ray's far end.
        let ray_scale = |i: usize| {
            let (r, field) = (i / 8, i % 8);
            if field == 7 {
                rays.intervals[(r + 1) * s - 1].end as f64
            } else {
                1.0
            }
        };
        let eo = max_err(&go, &co, ray_scale);
        eprintln!(
            "forward {bg:?} normals={with_normals} S={s}: weights rel err {ew:.2e}, ray outputs err {eo:.2e}"
        );
        assert!(ew < 1e-5 && eo < 1e-5, "{ew} {eo}");
        // Padding gets exactly zero weight, and the weights sum to the accumulation.
        for r in 0..rays.rays() {
            let w = &g.weights[r * s..(r + 1) * s];
            for (i, iv) in rays.intervals[r * s..(r + 1) * s].iter().enumerate() {
                if iv.end == iv.start {
                    assert_eq!(w[i], 0.0);
                }
            }
            let sum: f32 = w.iter().sum();
            assert!((sum - g.rays[r].accumulation).abs() < 1e-5);
            assert!(g.rays[r].accumulation <= 1.0 + 1e-6);
            if !with_normals {
                assert_eq!(g.rays[r].normal, [0.0; 3]);
            }
        }
    }
}

/// An independent f64 model of one ray's contribution to the total loss (transmittance as a running
/// product, α = −expm1(−τ)), with the per-sample quantities the gradient is assembled from. The DS-NeRF
/// Gaussian takes the kernels' f32 midpoint and 1/(2σ²) as given: its condition number is |t − D|·t/σ²
/// (~10³ in the tails), so the rounding of the midpoint alone would otherwise dominate the comparison, as
/// the rounded cell position does in the hash-grid test.
struct Ray64 {
    loss: f64,
    w: Vec<f64>,
    /// T_{i+1}.
    t_next: Vec<f64>,
    /// Σ|terms| of dL/dw_i.
    g_abs: Vec<f64>,
    /// Σ|terms| of dL/dC_c: 2λ/(3R)·(Σ wᵢ|c_ic| + |b_c|(1 − acc) + |target_c|); the error C − target cancels.
    d_rgb_scale: [f64; 3],
    /// Σ_c |(dL/dN)_c| + |N_c|·Σ_j |N_j (dL/dN)_j|, over |v|: the size of the terms of dL/dv_c.
    d_v_scale: [f64; 3],
    /// Final transmittance 1 − acc, and Σ_c d_rgb_scale_c·|b_c|.
    t_final: f64,
    bg_scale: f64,
    /// Σ kᵢδᵢ: the DS-NeRF term with every log factor counted as 1. −log(w + ε) cancels near w = 1, so
    /// the term is good to ε·Σ kᵢδᵢ, not to ε of itself.
    depth_mass: f64,
    last: Option<usize>,
}

#[derive(Clone)]
struct RayIn64 {
    rgb: Vec<[f64; 3]>,
    sigma: Vec<f64>,
    iv: Vec<(f64, f64)>,
    normals: Option<Vec<[f64; 3]>>,
}

impl RayIn64 {
    fn new(rays: &Rays, r: usize) -> Self {
        let span = r * rays.s..(r + 1) * rays.s;
        Self {
            rgb: rays.samples[span.clone()]
                .iter()
                .map(|s| s.rgb.map(f64::from))
                .collect(),
            sigma: rays.samples[span.clone()]
                .iter()
                .map(|s| s.density as f64)
                .collect(),
            iv: rays.intervals[span.clone()]
                .iter()
                .map(|i| (i.start as f64, i.end as f64))
                .collect(),
            normals: rays
                .normals
                .as_ref()
                .map(|n| n[span].iter().map(|v| v.map(f64::from)).collect()),
        }
    }
}

fn dot64(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn ray_f64(
    x: &RayIn64,
    target: &RayTarget,
    bg: Background,
    cfg: &LossConfig,
    rays: usize,
) -> Ray64 {
    let s = x.sigma.len();
    let r = rays as f64;
    let (lr, ld, ln, ls) = (
        cfg.rgb as f64 / (3.0 * r),
        cfg.depth as f64 / r,
        cfg.normal as f64 / r,
        cfg.sky as f64 / r,
    );
    let inv_two_var = (1.0 / (2.0 * cfg.depth_sigma * cfg.depth_sigma)) as f64;
    let d_target = target.depth as f64;
    let sky = target.sky != 0;
    let lidar = !sky && d_target > 0.0;
    let tn = target.normal.map(f64::from);
    let tn_len = dot64(tn, tn).sqrt();
    let use_normal = x.normals.is_some() && tn_len > 0.0;
    let delta = |i: usize| (x.iv[i].1 - x.iv[i].0).max(0.0);
    let gauss = |i: usize| {
        let mid = 0.5 * (x.iv[i].0 as f32 + x.iv[i].1 as f32);
        let e = mid as f64 - d_target;
        (-e * e * inv_two_var).exp()
    };
    let mut w = vec![0.0; s];
    let mut t_next = vec![0.0; s];
    let mut trans = 1.0f64;
    let mut last = None;
    for i in 0..s {
        let tau = if delta(i) > 0.0 {
            x.sigma[i] * delta(i)
        } else {
            0.0
        };
        w[i] = trans * -(-tau).exp_m1();
        trans *= (-tau).exp();
        t_next[i] = trans;
        if delta(i) > 0.0 {
            last = Some(i);
        }
    }
    let acc: f64 = w.iter().sum();
    let bgc = match (bg, last) {
        (Background::Constant(c), _) => c.map(f64::from),
        (Background::LastSample, Some(i)) => x.rgb[i],
        _ => [0.0; 3],
    };
    let mut rgb = [0.0; 3];
    for d in 0..3 {
        rgb[d] = (0..s).map(|i| w[i] * x.rgb[i][d]).sum::<f64>() + bgc[d] * (1.0 - acc);
    }
    let err = [0, 1, 2].map(|d| rgb[d] - target.rgb[d] as f64);
    let mut loss = lr * dot64(err, err);
    let d_rgb_scale = [0, 1, 2].map(|d| {
        let rendered: f64 = (0..s).map(|i| w[i] * x.rgb[i][d].abs()).sum();
        2.0 * lr * (rendered + bgc[d].abs() * (1.0 - acc) + (target.rgb[d] as f64).abs())
    });
    let mut d_v_scale = [0.0; 3];
    if use_normal {
        let nm = x.normals.as_ref().unwrap();
        let v = [0, 1, 2].map(|d| (0..s).map(|i| w[i] * nm[i][d]).sum::<f64>());
        let len = dot64(v, v).sqrt();
        let n = if len > NORMAL_EPS as f64 {
            v.map(|c| c / len)
        } else {
            [0.0; 3]
        };
        let tn = tn.map(|c| c / tn_len);
        let dn = [0, 1, 2].map(|d| n[d] - tn[d]);
        loss += ln * (dn.iter().map(|c| c.abs()).sum::<f64>() + 1.0 - dot64(n, tn));
        if len > NORMAL_EPS as f64 {
            let d_n = [0, 1, 2].map(|d| ln * (dn[d].signum() - tn[d]));
            let nd_abs: f64 = (0..3).map(|d| (n[d] * d_n[d]).abs()).sum();
            d_v_scale = [0, 1, 2].map(|d| (d_n[d].abs() + n[d].abs() * nd_abs) / len);
        }
    }
    let eps = LOG_EPS as f64;
    let mut depth_mass = 0.0;
    let abs3 = |v: [f64; 3]| v.map(f64::abs);
    let mut g_abs = vec![0.0; s];
    for i in 0..s {
        if lidar {
            loss -= ld * (w[i] + eps).ln() * gauss(i) * delta(i);
            g_abs[i] += ld * gauss(i) * delta(i) / (w[i] + eps);
            depth_mass += gauss(i) * delta(i);
        }
        if sky {
            loss += ls * w[i] * w[i];
            g_abs[i] += ls * 2.0 * w[i];
        }
        g_abs[i] += dot64(d_rgb_scale, abs3(x.rgb[i]));
        if use_normal {
            g_abs[i] += dot64(d_v_scale, abs3(x.normals.as_ref().unwrap()[i]));
        }
    }
    Ray64 {
        loss,
        w,
        t_next,
        g_abs,
        d_rgb_scale,
        d_v_scale,
        t_final: 1.0 - acc,
        depth_mass,
        bg_scale: dot64(d_rgb_scale, abs3(bgc)),
        last,
    }
}

/// Σ|terms| each gradient is summed from (f64): the scale its f32 rounding error is relative to.
/// Returns (σ, colour, normal) scales per sample of the ray.
fn grad_scales(m: &Ray64, x: &RayIn64, bg: Background) -> (Vec<f64>, Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let s = m.w.len();
    let mut sig = vec![0.0; s];
    let mut suffix = 0.0;
    for i in (0..s).rev() {
        let delta = (x.iv[i].1 - x.iv[i].0).max(0.0);
        sig[i] = delta * (m.g_abs[i] * m.t_next[i] + suffix + m.t_final * m.bg_scale);
        suffix += m.g_abs[i] * m.w[i];
    }
    let col = (0..s)
        .map(|i| {
            let extra = if matches!(bg, Background::LastSample) && m.last == Some(i) {
                m.t_final.abs()
            } else {
                0.0
            };
            m.d_rgb_scale.map(|d| d * (m.w[i] + extra))
        })
        .collect();
    let nor = (0..s).map(|i| m.d_v_scale.map(|d| d * m.w[i])).collect();
    (sig, col, nor)
}

fn flat_normals(n: &Option<Vec<[f32; 3]>>) -> Vec<f32> {
    n.as_ref()
        .map(|v| v.iter().flatten().copied().collect())
        .unwrap_or_default()
}

/// Per-sample GPU-vs-CPU errors of all gradients, relative to Σ|terms| (floored at 1e-6 of the batch's
/// largest scale of that kind, so exact zeros from the two sides compare cleanly).
fn gradient_errors(
    rays: &Rays,
    bg: Background,
    cfg: &LossConfig,
    a: &RenderGradients,
    b: &RenderGradients,
) -> [f64; 3] {
    let s = rays.s;
    let mut sig_s = Vec::new();
    let mut col_s = Vec::new();
    let mut nor_s = Vec::new();
    for r in 0..rays.rays() {
        let x = RayIn64::new(rays, r);
        let m = ray_f64(&x, &rays.targets[r], bg, cfg, rays.rays());
        let (sg, c, n) = grad_scales(&m, &x, bg);
        sig_s.extend(sg);
        col_s.extend(c.into_iter().flatten());
        nor_s.extend(n.into_iter().flatten());
    }
    let floor = |v: &[f64]| v.iter().copied().fold(0.0, f64::max) * 1e-6 + 1e-30;
    let (fs, fc, fn_) = (floor(&sig_s), floor(&col_s), floor(&nor_s));
    let ds = |g: &RenderGradients| g.samples.iter().map(|x| x.density).collect::<Vec<_>>();
    let dc = |g: &RenderGradients| g.samples.iter().flat_map(|x| x.rgb).collect::<Vec<_>>();
    let es = max_err(&ds(a), &ds(b), |i| sig_s[i] + fs);
    let ec = max_err(&dc(a), &dc(b), |i| col_s[i] + fc);
    let en = if rays.normals.is_some() {
        max_err(&flat_normals(&a.normals), &flat_normals(&b.normals), |i| {
            nor_s[i] + fn_
        })
    } else {
        0.0
    };
    assert_eq!(a.samples.len(), rays.rays() * s);
    [es, ec, en]
}

#[test]
fn losses_and_backward_match_cpu() {
    let Some(gpu) = gpu() else { return };
    for (k, (bg, with_normals, s, sigma)) in cases().into_iter().enumerate() {
        let rays = random_rays(200 + k as u64, 300, s, with_normals);
        let cfg = test_config(sigma);
        let batch = rays.batch();
        let g =
            pollster::block_on(render_backward_gpu(&gpu, &batch, bg, &rays.targets, &cfg)).unwrap();
        let c = backward_cpu(&batch, bg, &rays.targets, &cfg).unwrap();
        let l = losses_cpu(&batch, bg, &rays.targets, &cfg).unwrap();
        assert_eq!(l, c.losses, "losses_cpu and backward_cpu agree exactly");
        assert!(!g
            .samples
            .iter()
            .any(|x| is_poison(x.density) || x.rgb.iter().any(|&v| is_poison(v))));
        assert!(!flat_normals(&g.normals).iter().any(|&v| is_poison(v)));
        assert_eq!(g.normals.is_some(), with_normals);
        // Per-ray loss terms (each a sum of non-negative terms, except the normal one: O(1)).
        let lg: Vec<f32> = bytemuck::cast_slice(&g.losses.per_ray).to_vec();
        let lc: Vec<f32> = bytemuck::cast_slice(&c.losses.per_ray).to_vec();
        assert!(!lg.iter().any(|&v| is_poison(v)));
        // Loss terms: relative, except where they cancel: the colour MSE of a ray rendered almost exactly
        // right squares (rendered − target), good to ε·√MSE; the DS-NeRF term to ε·Σ kᵢδᵢ (see Ray64).
        let mass: Vec<f64> = (0..rays.rays())
            .map(|r| {
                ray_f64(
                    &RayIn64::new(&rays, r),
                    &rays.targets[r],
                    bg,
                    &cfg,
                    rays.rays(),
                )
                .depth_mass
            })
            .collect();
        let el = max_err(&lg, &lc, |i| {
            let l = lc[i].abs() as f64;
            l + match i % 4 {
                0 => l.sqrt(),
                1 => mass[i / 4],
                _ => 0.0,
            } + 1e-6
        });
        let rel_total = (g.losses.total - c.losses.total).abs() / c.losses.total;
        let [es, ec, en] = gradient_errors(&rays, bg, &cfg, &g, &c);
        eprintln!(
            "backward {bg:?} normals={with_normals} S={s} σ={sigma}: loss terms {el:.2e}, total {rel_total:.2e}; \
             dσ {es:.2e}, dc {ec:.2e}, dn {en:.2e} (error / Σ|terms|); total loss {:.4} \
             (rgb {:.4}, depth {:.4}, normal {:.4}, sky {:.4})",
            c.losses.total, c.losses.rgb, c.losses.depth, c.losses.normal, c.losses.sky
        );
        assert!(el < 1e-5 && rel_total < 1e-6, "{el} {rel_total}");
        assert!(es < 1e-5 && ec < 1e-5 && en < 1e-5, "{es} {ec} {en}");
        // Every kind of supervision is present in the batch.
        assert!(c.losses.depth > 0.0 && c.losses.sky > 0.0 && c.losses.rgb > 0.0);
        assert_eq!(c.losses.normal > 0.0, with_normals);
    }
}

/// (finite difference, CPU, GPU, Σ|terms| of the analytic value, round-off bound of the difference).
type FdEntry = (f64, f32, f32, f64, f64);

/// Central differences of the f64 total loss w.r.t. σ, colour and normal of random samples (and of every
/// ray's last non-empty sample, which carries the last_sample background's gradient), against the f32
/// analytic gradients of the CPU reference and the GPU.
#[test]
fn backward_matches_finite_differences() {
    let Some(gpu) = gpu() else { return };
    for (k, (bg, with_normals, s, sigma)) in cases().into_iter().enumerate() {
        let rays = random_rays(300 + k as u64, 120, s, with_normals);
        let cfg = test_config(sigma);
        let batch = rays.batch();
        let cpu = backward_cpu(&batch, bg, &rays.targets, &cfg).unwrap();
        let gpu_g =
            pollster::block_on(render_backward_gpu(&gpu, &batch, bg, &rays.targets, &cfg)).unwrap();
        let n_rays = rays.rays();
        // The f64 model agrees with the reported total.
        let total64: f64 = (0..n_rays)
            .map(|r| ray_f64(&RayIn64::new(&rays, r), &rays.targets[r], bg, &cfg, n_rays).loss)
            .sum();
        let rel = (total64 - cpu.losses.total).abs() / total64;
        assert!(
            rel < 1e-5,
            "f64 total {total64} vs {}: {rel}",
            cpu.losses.total
        );

        let mut r = rng(400 + k as u64);
        // (fd, CPU, GPU, Σ|terms|, bound on the difference quotient's own round-off) per checked derivative,
        // per kind (σ, colour, normal).
        let mut entries: [Vec<FdEntry>; 3] = Default::default();
        for r_i in 0..n_rays {
            let x0 = RayIn64::new(&rays, r_i);
            let m0 = ray_f64(&x0, &rays.targets[r_i], bg, &cfg, n_rays);
            let (ss, cs, ns) = grad_scales(&m0, &x0, bg);
            let mut picks = vec![r.random_range(0..s), r.random_range(0..s)];
            picks.extend(m0.last);
            let loss = |x: &RayIn64| ray_f64(x, &rays.targets[r_i], bg, &cfg, n_rays).loss;
            let fd = |edit: &dyn Fn(&mut RayIn64, f64), h: f64| {
                let mut xp = x0.clone();
                edit(&mut xp, h);
                let mut xm = x0.clone();
                edit(&mut xm, -h);
                (loss(&xp) - loss(&xm)) / (2.0 * h)
            };
            // The ray's loss is (nearly) a sum of non-negative terms, so a few ε·L/h bound the quotient's
            // round-off. It matters for σ = 0 samples, whose step has to be tiny: near w = 0 the log in the
            // DS-NeRF term curves on the scale of its ε = 1e-7.
            let noise = |h: f64| 32.0 * f64::EPSILON * m0.loss / h;
            for i in picks {
                let k_s = r_i * s + i;
                // σ: a relative step (σ spans five decades), floored for empty samples. At σ = 0 on a lidar
                // ray the DS-NeRF log curves on the scale of its ε: the truncation error is about
                // (h·δT/ε)²/3, so the floor keeps h·δ well below ε = 1e-7.
                let h = 1e-6 * x0.sigma[i].max(1e-3);
                let f = fd(&|x, h| x.sigma[i] += h, h);
                let (c, g) = (&cpu.samples[k_s], &gpu_g.samples[k_s]);
                entries[0].push((f, c.density, g.density, ss[i], noise(h)));
                // Colour: the loss is quadratic in it, so any step is exact up to round-off.
                for (d, &scale) in cs[i].iter().enumerate() {
                    let f = fd(&|x, h| x.rgb[i][d] += h, 1e-3);
                    entries[1].push((f, c.rgb[d], g.rgb[d], scale, noise(1e-3)));
                }
                if with_normals {
                    for (d, &scale) in ns[i].iter().enumerate() {
                        let f = fd(&|x, h| x.normals.as_mut().unwrap()[i][d] += h, 1e-5);
                        let (cn, gn) = (
                            cpu.normals.as_ref().unwrap()[k_s][d],
                            gpu_g.normals.as_ref().unwrap()[k_s][d],
                        );
                        entries[2].push((f, cn, gn, scale, noise(1e-5)));
                    }
                }
            }
        }
        // (|analytic − fd| − fd round-off)₊ / Σ|terms|, floored at 1e-6 of the largest scale of the kind:
        // the f32 transmittance exp(−P) carries a relative error of about ε·ΣP (nerfstudio's cumsum-then-exp),
        // which only matters where T, and the gradient, is negligible.
        let worst = entries.each_ref().map(|e| {
            let floor = e.iter().map(|x| x.3).fold(0.0, f64::max) * 1e-6 + 1e-30;
            let err = |f: f64, a: f32, sc: f64, noise: f64| {
                ((f - a as f64).abs() - noise).max(0.0) / (sc + floor)
            };
            e.iter()
                .fold((0.0f64, 0.0f64), |(wc, wg), &(f, c, g, sc, noise)| {
                    (wc.max(err(f, c, sc, noise)), wg.max(err(f, g, sc, noise)))
                })
        });
        eprintln!(
            "FD {bg:?} normals={with_normals} S={s} σ={sigma}: (CPU, GPU) error / Σ|terms|: \
             dσ {:.2e} {:.2e} ({} samples), dc {:.2e} {:.2e} ({}), dn {:.2e} {:.2e} ({})",
            worst[0].0,
            worst[0].1,
            entries[0].len(),
            worst[1].0,
            worst[1].1,
            entries[1].len(),
            worst[2].0,
            worst[2].1,
            entries[2].len()
        );
        for (kind, (ec, eg)) in worst.iter().enumerate() {
            assert!(*ec < 1e-5 && *eg < 1e-5, "kind {kind}: {ec} {eg}");
        }
    }
}

/// One ray per edge case, S = 6, all supervised by lidar depth and a lidar normal (or sky), compared
/// GPU against CPU and checked for the expected values.
#[test]
fn edge_cases() {
    let Some(gpu) = gpu() else { return };
    let s = 6;
    let iv = |start: f32, deltas: [f32; 6]| {
        let mut t = start;
        deltas.map(|d| {
            let i = Interval {
                start: t,
                end: t + d,
            };
            t += d;
            i
        })
    };
    let uniform = iv(1.0, [0.1; 6]);
    let smp = |density: [f32; 6]| {
        let mut k = 0.0;
        density.map(|density| {
            k += 0.15;
            Sample {
                rgb: [k, 1.0 - k, 0.5],
                density,
            }
        })
    };
    let target = |depth: f32, sky: u32| RayTarget {
        rgb: [0.3, 0.6, 0.9],
        depth,
        normal: if sky == 0 { [0.0, 0.0, 2.0] } else { [0.0; 3] },
        sky,
    };
    // (name, samples, intervals, target)
    let cases: Vec<(&str, [Sample; 6], [Interval; 6], RayTarget)> = vec![
        (
            "zero density, lidar",
            smp([0.0; 6]),
            uniform,
            target(1.3, 0),
        ),
        ("zero density, sky", smp([0.0; 6]), uniform, target(0.0, 1)),
        ("huge density", smp([1e6; 6]), uniform, target(1.3, 0)),
        (
            "huge density from the 3rd",
            smp([0.0, 0.5, 1e30, 1e30, 2.0, 1e30]),
            uniform,
            target(1.25, 0),
        ),
        (
            "lidar beyond the samples",
            smp([1.0; 6]),
            uniform,
            target(50.0, 0),
        ),
        (
            "lidar before the samples",
            smp([1.0; 6]),
            uniform,
            target(0.01, 0),
        ),
        (
            "all intervals empty",
            smp([5.0; 6]),
            iv(1.0, [0.0; 6]),
            target(1.0, 0),
        ),
        (
            "empty intervals inside",
            smp([3.0; 6]),
            iv(1.0, [0.1, 0.0, 0.2, 0.0, 0.0, 0.1]),
            target(1.2, 0),
        ),
        (
            "thin samples",
            smp([1e-3; 6]),
            iv(1.0, [1e-4; 6]),
            target(1.0002, 0),
        ),
    ];
    let rays = Rays {
        s,
        samples: cases.iter().flat_map(|c| c.1).collect(),
        intervals: cases.iter().flat_map(|c| c.2).collect(),
        normals: Some(vec![[0.0, 0.6, 0.8]; cases.len() * s]),
        targets: cases.iter().map(|c| c.3).collect(),
    };
    let cfg = LossConfig {
        depth_sigma: 0.05,
        ..LossConfig::default()
    };
    let batch = rays.batch();
    for bg in [
        Background::LastSample,
        Background::Constant([0.1, 0.2, 0.3]),
    ] {
        let gf = pollster::block_on(render_gpu(&gpu, &batch, bg)).unwrap();
        let cf = render_cpu(&batch, bg).unwrap();
        let gb =
            pollster::block_on(render_backward_gpu(&gpu, &batch, bg, &rays.targets, &cfg)).unwrap();
        let cb = backward_cpu(&batch, bg, &rays.targets, &cfg).unwrap();
        let all_f32 = |f: &render::Rendered, b: &RenderGradients| -> Vec<f32> {
            let mut v = f.weights.clone();
            v.extend(bytemuck::cast_slice::<_, f32>(&f.rays));
            v.extend(bytemuck::cast_slice::<_, f32>(&b.losses.per_ray));
            v.extend(bytemuck::cast_slice::<_, f32>(&b.samples));
            v.extend(flat_normals(&b.normals));
            v
        };
        let (vg, vc) = (all_f32(&gf, &gb), all_f32(&cf, &cb));
        assert!(vg.iter().all(|v| v.is_finite()), "GPU non-finite: {vg:?}");
        assert!(vc.iter().all(|v| v.is_finite()), "CPU non-finite");
        for (r, (name, ..)) in cases.iter().enumerate() {
            let span = r * s..(r + 1) * s;
            let (o, w) = (gf.rays[r], &gf.weights[span.clone()]);
            let oc = cf.rays[r];
            for (a, b) in bytemuck::cast_slice::<_, f32>(&[o])
                .iter()
                .zip(bytemuck::cast_slice::<_, f32>(&[oc]))
            {
                assert!(
                    (a - b).abs() <= 1e-5 * b.abs().max(1.0),
                    "{name}: {o:?} vs {oc:?}"
                );
            }
            for (a, b) in w.iter().zip(&cf.weights[span.clone()]) {
                assert!((a - b).abs() <= 1e-5 * b.abs() + 1e-12, "{name}: {w:?}");
            }
            let (lg, lc) = (gb.losses.per_ray[r], cb.losses.per_ray[r]);
            for (a, b) in [
                (lg.rgb, lc.rgb),
                (lg.depth, lc.depth),
                (lg.normal, lc.normal),
                (lg.sky, lc.sky),
            ] {
                assert!(
                    (a - b).abs() <= 1e-5 * b.abs().max(1e-3),
                    "{name}: {lg:?} vs {lc:?}"
                );
            }
            let scale = cb.samples[span.clone()]
                .iter()
                .flat_map(|x| {
                    [
                        x.density.abs(),
                        x.rgb[0].abs(),
                        x.rgb[1].abs(),
                        x.rgb[2].abs(),
                    ]
                })
                .fold(0.0f32, f32::max);
            for (a, b) in gb.samples[span.clone()]
                .iter()
                .zip(&cb.samples[span.clone()])
            {
                assert!(
                    (a.density - b.density).abs() <= 1e-5 * scale + 1e-30,
                    "{name}: dσ {a:?} vs {b:?}"
                );
                for d in 0..3 {
                    assert!(
                        (a.rgb[d] - b.rgb[d]).abs() <= 1e-5 * scale + 1e-30,
                        "{name}"
                    );
                }
            }
            let ivs = &rays.intervals[span.clone()];
            let empty_interval = |i: usize| ivs[i].end == ivs[i].start;
            match *name {
                "zero density, lidar" | "zero density, sky" | "all intervals empty" => {
                    assert_eq!(o.accumulation, 0.0, "{name}");
                    assert!(w.iter().all(|&v| v == 0.0));
                    assert_eq!((o.depth, o.normal), (0.0, [0.0; 3]), "{name}");
                    let want = match bg {
                        Background::Constant(c) => c,
                        // The last non-empty sample; none at all leaves black.
                        _ if *name == "all intervals empty" => [0.0; 3],
                        _ => rays.samples[r * s + 5].rgb,
                    };
                    assert_eq!(o.rgb, want, "{name}");
                    assert_eq!(lg.sky, 0.0);
                    if *name == "zero density, lidar" {
                        // −log(ε)·Σ Gaussian·δ, and a strong pull towards density near D.
                        assert!(lc.depth > 1.0, "{lc:?}");
                        assert!(gb.samples[r * s + 3].density < 0.0);
                    }
                    // No normal is rendered: the loss is |N̄|₁ + 1 = 2 with no gradient.
                    if *name != "zero density, sky" {
                        assert_eq!(lg.normal, 2.0, "{name}");
                    }
                    assert!(flat_normals(&gb.normals)[3 * r * s..3 * (r + 1) * s]
                        .iter()
                        .all(|&v| v == 0.0));
                }
                "huge density" => {
                    assert_eq!(w, &[1.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
                    assert_eq!(o.rgb, rays.samples[r * s].rgb);
                    assert!((o.depth - 1.05).abs() < 1e-6, "{}", o.depth);
                    // Saturated: no density gradient anywhere (T_{i+1} = 0 and no weight after the first).
                    assert!(
                        gb.samples[span.clone()].iter().all(|x| x.density == 0.0),
                        "{:?}",
                        &gb.samples[span.clone()]
                    );
                }
                "huge density from the 3rd" => {
                    assert_eq!(&w[3..], &[0.0; 3]);
                    assert!((o.accumulation - 1.0).abs() < 1e-6);
                    // No weight and no transmittance after the wall: no gradient.
                    assert!(gb.samples[span.start + 3..span.end]
                        .iter()
                        .all(|x| *x == Sample::default()));
                    assert!(gb.samples[span.start + 1].density != 0.0);
                }
                "lidar beyond the samples" | "lidar before the samples" => {
                    // The Gaussian underflows on every sample: no depth loss, no depth gradient.
                    assert_eq!(lg.depth, 0.0, "{name}");
                }
                "empty intervals inside" => {}
                "thin samples" => {
                    // τ = 1e-7: the series keeps w accurate where 1 − exp(−τ) would not.
                    let tau = 1e-3f32 as f64 * (ivs[0].end as f64 - ivs[0].start as f64);
                    let exact = -(-tau).exp_m1();
                    assert!((w[0] as f64 - exact).abs() < 1e-6 * exact, "{w:?}");
                }
                _ => unreachable!(),
            }
            for (i, &wi) in w.iter().enumerate() {
                if empty_interval(i) {
                    assert_eq!(wi, 0.0, "{name}");
                    assert_eq!(gb.samples[r * s + i].density, 0.0, "{name}");
                    if !matches!(bg, Background::LastSample) {
                        assert_eq!(gb.samples[r * s + i].rgb, [0.0; 3], "{name}");
                    }
                }
            }
        }
    }
    // The "all intervals empty" ray gets no gradient at all, even with the last_sample background.
    let gb = pollster::block_on(render_backward_gpu(
        &gpu,
        &batch,
        Background::LastSample,
        &rays.targets,
        &cfg,
    ))
    .unwrap();
    let r = 6;
    assert!(gb.samples[r * s..(r + 1) * s]
        .iter()
        .all(|x| *x == Sample::default()));
}

/// The trainer's path: forward and losses+backward recorded into one encoder over caller-owned buffers
/// that are larger than the batch (reused across batches), one readback at the end.
#[test]
fn chained_passes_in_one_encoder() {
    let Some(gpu) = gpu() else { return };
    let (s, n_rays) = (24, 200);
    let rays = random_rays(500, n_rays, s, true);
    let mut padded = random_rays(500, n_rays, s, true);
    let extra = random_rays(501, 13, s, true);
    padded.samples.extend(&extra.samples);
    padded.intervals.extend(&extra.intervals);
    padded
        .normals
        .as_mut()
        .unwrap()
        .extend(extra.normals.unwrap());
    padded.targets.extend(&extra.targets);
    let cfg = test_config(0.03);
    let bg = Background::LastSample;
    let n = n_rays * s;
    let b_s = gpu.upload("samples", &padded.samples).unwrap();
    let b_i = gpu.upload("intervals", &padded.intervals).unwrap();
    let b_n = gpu
        .upload("normals", padded.normals.as_ref().unwrap())
        .unwrap();
    let b_t = gpu.upload("targets", &padded.targets).unwrap();
    let b_w = gpu.output("weights", n).unwrap();
    let b_o = gpu.output("rays", n_rays * 8).unwrap();
    let b_l = gpu.output("losses", n_rays * 4).unwrap();
    let b_ds = gpu.output("d samples", n * 4).unwrap();
    let b_dn = gpu.output("d normals", n * 3).unwrap();
    let batch = GpuRayBatch {
        rays: n_rays as u32,
        samples_per_ray: s as u32,
        samples: &b_s,
        intervals: &b_i,
        normals: Some(&b_n),
    };
    let mut enc = gpu.encoder("chain");
    pollster::block_on(async {
        render::record_render(&gpu, &mut enc, batch, bg, &b_w, &b_o).await?;
        render::record_render_backward(
            &gpu,
            &mut enc,
            batch,
            bg,
            &cfg,
            &b_t,
            &b_l,
            &b_ds,
            Some(&b_dn),
        )
        .await
    })
    .unwrap();
    let out = pollster::block_on(gpu.finish_and_read::<f32>(
        enc,
        &[
            (&b_w, n),
            (&b_o, n_rays * 8),
            (&b_l, n_rays * 4),
            (&b_ds, n * 4),
            (&b_dn, n * 3),
        ],
    ))
    .unwrap();
    let f = render_cpu(&rays.batch(), bg).unwrap();
    let b = backward_cpu(&rays.batch(), bg, &rays.targets, &cfg).unwrap();
    let close = |a: &[f32], c: &[f32], what: &str| {
        let scale = c.iter().map(|v| v.abs()).fold(0.0f32, f32::max);
        let e = a
            .iter()
            .zip(c)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max)
            / scale;
        assert!(e < 1e-5, "{what}: {e}");
    };
    close(&out[0], &f.weights, "weights");
    close(&out[1], bytemuck::cast_slice(&f.rays), "rays");
    close(&out[2], bytemuck::cast_slice(&b.losses.per_ray), "losses");
    close(&out[3], bytemuck::cast_slice(&b.samples), "dL/dsamples");
    close(&out[4], &flat_normals(&b.normals), "dL/dnormals");
}

#[test]
fn bad_inputs_are_errors_and_empty_batches_work() {
    let Some(gpu) = gpu() else { return };
    let rays = random_rays(600, 4, 5, true);
    let cfg = test_config(0.05);
    let bg = Background::Black;
    let mut bad = rays.batch();
    bad.intervals = &rays.intervals[1..];
    let err = pollster::block_on(render_gpu(&gpu, &bad, bg)).unwrap_err();
    assert!(matches!(err, GpuError::InvalidInput(_)), "{err}");
    let err = pollster::block_on(render_backward_gpu(
        &gpu,
        &rays.batch(),
        bg,
        &rays.targets[1..],
        &cfg,
    ))
    .unwrap_err();
    assert!(err.to_string().contains("targets"), "{err}");
    let neg = LossConfig {
        depth_sigma: -1.0,
        ..cfg
    };
    assert!(pollster::block_on(render_backward_gpu(
        &gpu,
        &rays.batch(),
        bg,
        &rays.targets,
        &neg
    ))
    .is_err());

    // Caller buffers: too small, and d_normals without normals, are refused before anything is recorded.
    let b_s = gpu.upload("samples", &rays.samples).unwrap();
    let b_i = gpu.upload("intervals", &rays.intervals).unwrap();
    let b_t = gpu.upload("targets", &rays.targets).unwrap();
    let small = gpu.output("small", 3).unwrap();
    let b_l = gpu.output("losses", 16).unwrap();
    let b_ds = gpu.output("ds", 80).unwrap();
    let batch = GpuRayBatch {
        rays: 4,
        samples_per_ray: 5,
        samples: &b_s,
        intervals: &b_i,
        normals: None,
    };
    let mut enc = gpu.encoder("bad");
    let err = pollster::block_on(render::record_render(
        &gpu, &mut enc, batch, bg, &small, &small,
    ))
    .unwrap_err();
    assert!(err.to_string().contains("weight buffer"), "{err}");
    let too_many = GpuRayBatch { rays: 5, ..batch };
    let err = pollster::block_on(render::record_render_backward(
        &gpu, &mut enc, too_many, bg, &cfg, &b_t, &b_l, &b_ds, None,
    ))
    .unwrap_err();
    assert!(err.to_string().contains("sample buffer"), "{err}");
    let err = pollster::block_on(render::record_render_backward(
        &gpu,
        &mut enc,
        batch,
        bg,
        &cfg,
        &b_t,
        &b_l,
        &b_ds,
        Some(&b_ds),
    ))
    .unwrap_err();
    assert!(err.to_string().contains("d_normals"), "{err}");

    let empty = RayBatch {
        samples_per_ray: 8,
        samples: &[],
        intervals: &[],
        normals: None,
    };
    let f = pollster::block_on(render_gpu(&gpu, &empty, bg)).unwrap();
    assert!(f.weights.is_empty() && f.rays.is_empty());
    let b = pollster::block_on(render_backward_gpu(&gpu, &empty, bg, &[], &cfg)).unwrap();
    assert!(b.samples.is_empty() && b.losses.per_ray.is_empty());
    assert_eq!(b.losses.total, 0.0);
}

/// Throughput at nerfacto's final level (4096 rays × 48 samples, normals on); not a correctness test:
/// run with `--ignored --nocapture`.
#[test]
#[ignore]
fn bench_nerfacto_batch() {
    use std::time::Instant;
    let Some(gpu) = gpu() else { return };
    let (n_rays, s) = (4096usize, 48usize);
    let rays = random_rays(700, n_rays, s, true);
    let cfg = LossConfig::default();
    let bg = Background::LastSample;
    let n = n_rays * s;
    let b_s = gpu.upload("samples", &rays.samples).unwrap();
    let b_i = gpu.upload("intervals", &rays.intervals).unwrap();
    let b_n = gpu
        .upload("normals", rays.normals.as_ref().unwrap())
        .unwrap();
    let b_t = gpu.upload("targets", &rays.targets).unwrap();
    let b_w = gpu.output("weights", n).unwrap();
    let b_o = gpu.output("rays", n_rays * 8).unwrap();
    let b_l = gpu.output("losses", n_rays * 4).unwrap();
    let b_ds = gpu.output("d samples", n * 4).unwrap();
    let b_dn = gpu.output("d normals", n * 3).unwrap();
    let batch = GpuRayBatch {
        rays: n_rays as u32,
        samples_per_ray: s as u32,
        samples: &b_s,
        intervals: &b_i,
        normals: Some(&b_n),
    };
    eprintln!("render on {}: {n_rays} rays × {s} samples", gpu.report());
    let time = |what: &str, pass: usize, reps: usize| {
        let mut best = f64::INFINITY;
        for _ in 0..5 {
            let t = Instant::now();
            let mut enc = gpu.encoder(what);
            pollster::block_on(async {
                for _ in 0..reps {
                    if pass == 0 {
                        render::record_render(&gpu, &mut enc, batch, bg, &b_w, &b_o).await?;
                    } else {
                        render::record_render_backward(
                            &gpu,
                            &mut enc,
                            batch,
                            bg,
                            &cfg,
                            &b_t,
                            &b_l,
                            &b_ds,
                            Some(&b_dn),
                        )
                        .await?;
                    }
                }
                Ok::<_, GpuError>(())
            })
            .unwrap();
            pollster::block_on(gpu.finish_and_read::<f32>(enc, &[(&b_l, 1)])).unwrap();
            best = best.min(t.elapsed().as_secs_f64() / reps as f64);
        }
        eprintln!(
            "GPU {what}: {:.3} ms per batch, {:.2} M rays/s (best of 5, {reps} dispatches per submit)",
            best * 1e3,
            n_rays as f64 / best / 1e6
        );
    };
    time("render", 0, 10);
    time("losses + backward", 1, 10);
    let best_of = |f: &dyn Fn()| {
        (0..5)
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64()
            })
            .fold(f64::INFINITY, f64::min)
    };
    let dt = best_of(&|| {
        render_cpu(&rays.batch(), bg).unwrap();
    });
    eprintln!(
        "CPU render ({} rayon threads): {:.2} ms, {:.2} M rays/s",
        rayon::current_num_threads(),
        dt * 1e3,
        n_rays as f64 / dt / 1e6
    );
    let dt = best_of(&|| {
        backward_cpu(&rays.batch(), bg, &rays.targets, &cfg).unwrap();
    });
    eprintln!(
        "CPU losses + backward: {:.2} ms, {:.2} M rays/s",
        dt * 1e3,
        n_rays as f64 / dt / 1e6
    );
}
