//! Per-ray volume rendering (nerfstudio's, as nerfacto uses it) and SiLVR's ray losses, forward and backward,
//! on the GPU (`shaders/render.wgsl`) and on the CPU (the reference: same f32 arithmetic in the same order).
//!
//! A batch is R rays of S samples, ray-major (sample i of ray r is element r·S + i); S is fixed per call and
//! rays with fewer samples pad with empty intervals (t_end = t_start), which get weight 0 and zero gradients.
//! Per sample: colour and density (already activated), the interval [t_start, t_end] along the ray and,
//! optionally, a normal (for the normal loss). With δᵢ = t_end − t_start and τᵢ = σᵢδᵢ:
//!
//! αᵢ = 1 − exp(−τᵢ),  Tᵢ = exp(−Σ_{j<i} τⱼ),  wᵢ = αᵢTᵢ  (nerfstudio's `get_weights`),
//!
//! and per ray: colour Σ wᵢcᵢ + b·(1 − acc) (b the [`Background`]), accumulation acc = Σ wᵢ, normal
//! normalize(Σ wᵢnᵢ), and depth Σ wᵢtᵢ with tᵢ the interval midpoint: a distance **along the ray** (range
//! for unit directions, not camera z), **not** divided by acc. SiLVR's exported "expected depth" is
//! depth / acc clipped to the sampled range; callers derive it (and filter on acc) at export.
//!
//! Losses, per ray, then averaged over the batch (every term divides by R, rays without that supervision
//! counting as zero) and weighted by [`LossConfig`]:
//! - colour: MSE over the three channels (torch's `MSELoss` over R×3 elements);
//! - lidar depth (DS-NeRF, SiLVR's `DS_NERF_NEW`), on rays with lidar range D > 0 that are not sky:
//!   Σᵢ −log(wᵢ + 1e-7)·exp(−(tᵢ − D)²/(2σ²))·δᵢ. **σ is a standard deviation in ray-distance units**
//!   (metres in a metric scene), chosen by the caller each step so the trainer can decay it 0.01 → 0.001;
//!   SiLVR's code uses σ as a variance in normalised units (its quirk Q1), which ties the width to the scene
//!   scale;
//! - lidar normal (MonoSDF's): ‖N − N̄‖₁ + (1 − N·N̄), both unit length, on rays with a non-zero lidar normal
//!   N̄ when per-sample normals are given. SiLVR averages it over the rays that have one: scale
//!   [`LossConfig::normal`] by R / (rays with a normal) to reproduce that;
//! - sky: Σᵢ wᵢ² on sky rays. SiLVR folds it into the depth loss under λ_depth; here it has its own weight
//!   (set it equal to [`LossConfig::depth`] to reproduce SiLVR).
//!
//! SiLVR applies the depth/sky loss to the two proposal levels as well and averages the three: run
//! [`record_render_backward`] once per level (colour weight 0, no normals on the proposal levels) with the
//! weights divided by 3.
//!
//! Deliberate deviations, all equal in exact arithmetic or on unpadded rays: αᵢ uses a short series for
//! τ < 0.125 (1 − exp(−τ) in f32 keeps only a few digits for thin samples, and the log in the depth loss
//! amplifies that); the background's share 1 − acc is evaluated as the final transmittance exp(−Στ), which
//! does not cancel on nearly opaque rays; the `last_sample` background is the colour of the last sample with
//! a non-empty interval (nerfstudio's last sample when nothing is padded).
//!
//! Backward: see the derivation above `loss_backward` in the WGSL. It is a reverse scan per ray, so both
//! kernels run one thread per ray looping over its S samples, no atomics and deterministic results.
//! [`render_gpu`] and [`render_backward_gpu`] take host data; [`record_render`] and
//! [`record_render_backward`] record into the caller's encoder over the caller's buffers.

use bytemuck::{Pod, Zeroable};
use rayon::prelude::*;

use crate::gpu::{wgpu, Gpu, GpuError, Kernel};
use crate::shaders;

/// DS-NeRF's ε inside −log(w + ε).
pub const LOG_EPS: f32 = 1e-7;
/// A rendered normal sum shorter than this renders as zero and gets no normal gradient.
pub const NORMAL_EPS: f32 = 1e-20;

const WORKGROUP: u32 = 64;

const KERNEL: Kernel = Kernel {
    name: "render",
    source: shaders::RENDER,
    workgroup_size: WORKGROUP,
};

/// One sample's field output, also the layout of its gradient (16 bytes, the WGSL `Sample`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct Sample {
    pub rgb: [f32; 3],
    /// Volume density σ ≥ 0 (after the activation).
    pub density: f32,
}

/// A sample's interval along its ray, in ray-distance units (t of origin + t·direction).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct Interval {
    pub start: f32,
    pub end: f32,
}

impl Interval {
    fn delta(&self) -> f32 {
        (self.end - self.start).max(0.0)
    }

    fn mid(&self) -> f32 {
        0.5 * (self.start + self.end)
    }
}

/// What one ray is supervised with (32 bytes, the WGSL `Target`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct RayTarget {
    pub rgb: [f32; 3],
    /// Lidar range along the ray (same units as the intervals); ≤ 0 when there is no return.
    pub depth: f32,
    /// Lidar normal, any non-zero length (normalised in the loss); zero when there is none.
    pub normal: [f32; 3],
    /// Non-zero for a sky ray: sky loss instead of the depth loss.
    pub sky: u32,
}

/// One ray's rendering (32 bytes, the WGSL `RayOut`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct RayOutput {
    /// Σ wᵢcᵢ + background·(1 − accumulation).
    pub rgb: [f32; 3],
    /// Σ wᵢ.
    pub accumulation: f32,
    /// normalize(Σ wᵢnᵢ); zero without per-sample normals or when the sum vanishes.
    pub normal: [f32; 3],
    /// Σ wᵢtᵢ (interval midpoints): distance along the ray, not divided by the accumulation.
    pub depth: f32,
}

/// One ray's unweighted loss terms (16 bytes, a WGSL `vec4`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct RayLoss {
    /// Mean over the channels of the squared colour error.
    pub rgb: f32,
    /// DS-NeRF term (0 unless the ray has lidar depth and is not sky).
    pub depth: f32,
    /// ‖N − N̄‖₁ + 1 − N·N̄ (0 unless the ray has a lidar normal and normals were given).
    pub normal: f32,
    /// Σ wᵢ² (0 unless sky).
    pub sky: f32,
}

/// What fills the ray where the samples leave it transparent (weight 1 − accumulation).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Background {
    #[default]
    Black,
    Constant([f32; 3]),
    /// nerfacto's default: the colour of the ray's last (non-empty) sample, gradient included.
    LastSample,
}

impl Background {
    fn mode(&self) -> u32 {
        match self {
            Background::Black => 0,
            Background::Constant(_) => 1,
            Background::LastSample => 2,
        }
    }

    fn colour(&self, samples: &[Sample], last: Option<usize>) -> [f32; 3] {
        match (self, last) {
            (Background::Constant(c), _) => *c,
            (Background::LastSample, Some(i)) => samples[i].rgb,
            _ => [0.0; 3],
        }
    }
}

/// Loss weights (λ) and the DS-NeRF width. Defaults: SiLVR's 2024 configuration (λ_depth 10 with the sky
/// term under the same weight, λ_normal 1e-3) and its starting σ of 1 cm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LossConfig {
    pub rgb: f32,
    pub depth: f32,
    pub normal: f32,
    pub sky: f32,
    /// Standard deviation of the DS-NeRF Gaussian around the lidar range, in ray-distance units (metres).
    pub depth_sigma: f32,
}

impl Default for LossConfig {
    fn default() -> Self {
        Self {
            rgb: 1.0,
            depth: 10.0,
            normal: 1e-3,
            sky: 10.0,
            depth_sigma: 0.01,
        }
    }
}

impl LossConfig {
    fn validate(&self) -> Result<(), GpuError> {
        let ws = [self.rgb, self.depth, self.normal, self.sky];
        if ws.iter().any(|w| !w.is_finite()) {
            return Err(GpuError::InvalidInput(format!(
                "render losses: weights must be finite, got {ws:?}"
            )));
        }
        let inv = self.inv_two_var();
        if !(self.depth_sigma > 0.0 && inv.is_finite()) {
            return Err(GpuError::InvalidInput(format!(
                "render losses: depth_sigma must be positive and not tiny, got {}",
                self.depth_sigma
            )));
        }
        Ok(())
    }

    pub fn inv_two_var(&self) -> f32 {
        1.0 / (2.0 * self.depth_sigma * self.depth_sigma)
    }

    /// The per-ray gradient scales: λ over the elements each mean runs over.
    fn scales(&self, rays: usize) -> [f32; 4] {
        let r = rays.max(1) as f32;
        [
            self.rgb / (3.0 * r),
            self.depth / r,
            self.normal / r,
            self.sky / r,
        ]
    }
}

/// Host-side ray samples: `samples`, `intervals` (and `normals`) hold R·S elements, ray-major.
#[derive(Clone, Copy, Debug)]
pub struct RayBatch<'a> {
    pub samples_per_ray: usize,
    pub samples: &'a [Sample],
    pub intervals: &'a [Interval],
    /// Per-sample normals (e.g. −normalize(∇σ)); needed for the rendered normal and the normal loss.
    pub normals: Option<&'a [[f32; 3]]>,
}

impl RayBatch<'_> {
    /// Number of rays, after checking the lengths agree.
    pub fn rays(&self) -> Result<usize, GpuError> {
        let s = self.samples_per_ray;
        let bad = |what: String| Err(GpuError::InvalidInput(format!("render: {what}")));
        if s == 0 {
            return bad("samples_per_ray must be at least 1".into());
        }
        let n = self.samples.len();
        if !n.is_multiple_of(s) {
            return bad(format!("{n} samples is not a multiple of {s} per ray"));
        }
        if self.intervals.len() != n {
            return bad(format!(
                "{} intervals for {n} samples",
                self.intervals.len()
            ));
        }
        if let Some(nm) = self.normals {
            if nm.len() != n {
                return bad(format!("{} normals for {n} samples", nm.len()));
            }
        }
        if u32::try_from(n).is_err() {
            return bad(format!("{n} samples is more than one call takes"));
        }
        Ok(n / s)
    }

    fn ray(&self, r: usize) -> RayView<'_> {
        let s = self.samples_per_ray;
        let span = r * s..(r + 1) * s;
        RayView {
            samples: &self.samples[span.clone()],
            intervals: &self.intervals[span.clone()],
            normals: self.normals.map(|n| &n[span]),
        }
    }
}

/// Weights and per-ray outputs of the forward pass.
#[derive(Clone, Debug, PartialEq)]
pub struct Rendered {
    /// R·S weights, ray-major.
    pub weights: Vec<f32>,
    pub rays: Vec<RayOutput>,
}

/// The losses of a batch: per-ray terms, their batch means, and the weighted total the gradients are of.
#[derive(Clone, Debug, PartialEq)]
pub struct Losses {
    pub per_ray: Vec<RayLoss>,
    /// Batch means of the unweighted terms (colour: over R·3 elements).
    pub rgb: f64,
    pub depth: f64,
    pub normal: f64,
    pub sky: f64,
    /// λ_rgb·rgb + λ_depth·depth + λ_normal·normal + λ_sky·sky.
    pub total: f64,
}

impl Losses {
    /// Means and total from per-ray terms (summed in f64).
    pub fn from_per_ray(per_ray: Vec<RayLoss>, cfg: &LossConfig) -> Self {
        let r = per_ray.len().max(1) as f64;
        let mut sums = [0.0f64; 4];
        for l in &per_ray {
            for (s, v) in sums.iter_mut().zip([l.rgb, l.depth, l.normal, l.sky]) {
                *s += v as f64;
            }
        }
        let [rgb, depth, normal, sky] = sums.map(|s| s / r);
        let total = cfg.rgb as f64 * rgb
            + cfg.depth as f64 * depth
            + cfg.normal as f64 * normal
            + cfg.sky as f64 * sky;
        Self {
            per_ray,
            rgb,
            depth,
            normal,
            sky,
            total,
        }
    }
}

/// Losses and dL/d(sample inputs) of the total loss.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderGradients {
    pub losses: Losses,
    /// dL/dcolour and dL/ddensity per sample, ray-major.
    pub samples: Vec<Sample>,
    /// dL/dnormal per sample, when normals were given.
    pub normals: Option<Vec<[f32; 3]>>,
}

struct RayView<'a> {
    samples: &'a [Sample],
    intervals: &'a [Interval],
    normals: Option<&'a [[f32; 3]]>,
}

/// σ·δ, 0 for an empty interval even when σ is infinite.
fn tau_of(density: f32, delta: f32) -> f32 {
    if delta > 0.0 {
        density * delta
    } else {
        0.0
    }
}

/// 1 − exp(−τ), by its series below τ = 0.125 (truncation < 1e-7 relative), as the kernel.
pub fn alpha(tau: f32) -> f32 {
    if tau < 0.125 {
        tau * (1.0 - tau * (0.5 - tau * (1.0 / 6.0 - tau * (1.0 / 24.0 - tau * (1.0 / 120.0)))))
    } else {
        1.0 - (-tau).exp()
    }
}

fn add_scaled(acc: &mut [f32; 3], w: f32, v: [f32; 3]) {
    for d in 0..3 {
        acc[d] += w * v[d];
    }
}

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn length(a: [f32; 3]) -> f32 {
    dot(a, a).sqrt()
}

/// v / |v| when |v| > [`NORMAL_EPS`], else zero; and |v|.
fn normalize_or_zero(v: [f32; 3]) -> ([f32; 3], f32) {
    let len = length(v);
    if len > NORMAL_EPS {
        (v.map(|x| x / len), len)
    } else {
        ([0.0; 3], len)
    }
}

fn render_ray(ray: &RayView, background: Background, weights: &mut [f32]) -> RayOutput {
    let mut p = 0.0f32;
    let mut rgb = [0.0f32; 3];
    let mut acc = 0.0f32;
    let mut depth = 0.0f32;
    let mut nsum = [0.0f32; 3];
    let mut last = None;
    for (i, (smp, iv)) in ray.samples.iter().zip(ray.intervals).enumerate() {
        let delta = iv.delta();
        let tau = tau_of(smp.density, delta);
        let w = (-p).exp() * alpha(tau);
        p += tau;
        weights[i] = w;
        add_scaled(&mut rgb, w, smp.rgb);
        acc += w;
        depth += w * iv.mid();
        if let Some(n) = ray.normals {
            add_scaled(&mut nsum, w, n[i]);
        }
        if delta > 0.0 {
            last = Some(i);
        }
    }
    add_scaled(&mut rgb, (-p).exp(), background.colour(ray.samples, last));
    RayOutput {
        rgb,
        accumulation: acc,
        normal: normalize_or_zero(nsum).0,
        depth,
    }
}

/// Gradient outputs of one ray: dL/d(rgb, σ) (whose σ slot holds Pᵢ between the loops, as in the kernel)
/// and dL/dnormal.
struct RayGrads<'a> {
    samples: &'a mut [Sample],
    normals: Option<&'a mut [[f32; 3]]>,
}

/// One ray's loss terms and, with `grads`, its backward: the kernel's `loss_backward`, line for line.
fn ray_loss_backward(
    ray: &RayView,
    target: &RayTarget,
    background: Background,
    cfg: &LossConfig,
    scales: [f32; 4],
    mut grads: Option<RayGrads>,
) -> RayLoss {
    let [scale_rgb, scale_depth, scale_normal, scale_sky] = scales;
    let inv_two_var = cfg.inv_two_var();
    let sky = target.sky != 0;
    let lidar = !sky && target.depth > 0.0;
    let tn_len = length(target.normal);
    let use_normal = ray.normals.is_some() && tn_len > 0.0;
    let gaussian = |iv: &Interval| {
        let e = iv.mid() - target.depth;
        (-e * e * inv_two_var).exp()
    };

    let mut p = 0.0f32;
    let mut rgb = [0.0f32; 3];
    let mut nsum = [0.0f32; 3];
    let mut last = None;
    let mut l_depth = 0.0f32;
    let mut l_sky = 0.0f32;
    for (i, (smp, iv)) in ray.samples.iter().zip(ray.intervals).enumerate() {
        let delta = iv.delta();
        let tau = tau_of(smp.density, delta);
        let w = (-p).exp() * alpha(tau);
        if let Some(g) = grads.as_mut() {
            g.samples[i].density = p;
        }
        p += tau;
        add_scaled(&mut rgb, w, smp.rgb);
        if use_normal {
            add_scaled(&mut nsum, w, ray.normals.unwrap()[i]);
        }
        if delta > 0.0 {
            last = Some(i);
        }
        if lidar {
            l_depth -= (w + LOG_EPS).ln() * gaussian(iv) * delta;
        }
        if sky {
            l_sky += w * w;
        }
    }
    let bg = background.colour(ray.samples, last);
    let t_final = (-p).exp();
    add_scaled(&mut rgb, t_final, bg);
    let err = [0, 1, 2].map(|d| rgb[d] - target.rgb[d]);
    let l_rgb = dot(err, err) / 3.0;
    let d_rgb = err.map(|e| 2.0 * scale_rgb * e);

    let mut l_normal = 0.0f32;
    let mut d_v = [0.0f32; 3];
    if use_normal {
        let tn = target.normal.map(|x| x / tn_len);
        let (n, len) = normalize_or_zero(nsum);
        let dn = [0, 1, 2].map(|d| n[d] - tn[d]);
        l_normal = dn[0].abs() + dn[1].abs() + dn[2].abs() + 1.0 - dot(n, tn);
        if len > NORMAL_EPS {
            // WGSL sign(): 0 at 0.
            let sign = |x: f32| if x == 0.0 { 0.0 } else { x.signum() };
            let d_n = [0, 1, 2].map(|d| scale_normal * (sign(dn[d]) - tn[d]));
            let nd = dot(n, d_n);
            d_v = [0, 1, 2].map(|d| (d_n[d] - n[d] * nd) / len);
        }
    }
    let loss = RayLoss {
        rgb: l_rgb,
        depth: l_depth,
        normal: l_normal,
        sky: l_sky,
    };
    let Some(g) = grads else { return loss };
    let d_tau_bg = t_final * dot(d_rgb, bg);

    // Reverse scan: `suffix` = Σ_{i>k} gᵢwᵢ, `t_next` = T_{k+1} (the previous iteration's Tᵢ).
    let mut suffix = 0.0f32;
    let mut t_next = t_final;
    let with_bg = matches!(background, Background::LastSample);
    let RayGrads {
        samples: d_samples,
        mut normals,
    } = g;
    for i in (0..ray.samples.len()).rev() {
        let smp = &ray.samples[i];
        let iv = &ray.intervals[i];
        let delta = iv.delta();
        let tau = tau_of(smp.density, delta);
        let t_i = (-d_samples[i].density).exp();
        let w = t_i * alpha(tau);
        let mut g = dot(d_rgb, smp.rgb);
        if use_normal {
            g += dot(d_v, ray.normals.unwrap()[i]);
        }
        if lidar {
            g -= scale_depth * gaussian(iv) * delta / (w + LOG_EPS);
        }
        if sky {
            g += scale_sky * 2.0 * w;
        }
        let d_sigma = delta * (g * t_next - suffix - d_tau_bg);
        suffix += g * w;
        t_next = t_i;
        let mut d_c = d_rgb.map(|x| x * w);
        if with_bg && Some(i) == last {
            add_scaled(&mut d_c, t_final, d_rgb);
        }
        d_samples[i] = Sample {
            rgb: d_c,
            density: d_sigma,
        };
        if let Some(dn) = normals.as_mut() {
            dn[i] = d_v.map(|x| x * w);
        }
    }
    loss
}

/// The depth and sky terms on one ray's weights alone (SiLVR applies them to the proposal levels too):
/// returns (DS-NeRF term, Σw²) and adds `scale_depth`·∂/∂w and `scale_sky`·∂/∂w into `d_w`.
/// `t_edges` has one more entry than `w`; `inv_two_var` = 1/(2σ²).
pub fn weight_losses(
    w: &[f32],
    t_edges: &[f32],
    target: &RayTarget,
    inv_two_var: f32,
    scale_depth: f32,
    scale_sky: f32,
    d_w: &mut [f32],
) -> (f32, f32) {
    let sky = target.sky != 0;
    let lidar = !sky && target.depth > 0.0;
    let (mut ld, mut ls) = (0.0f32, 0.0f32);
    for i in 0..w.len() {
        let iv = Interval {
            start: t_edges[i],
            end: t_edges[i + 1],
        };
        if lidar {
            let e = iv.mid() - target.depth;
            let g = (-e * e * inv_two_var).exp() * iv.delta();
            ld -= (w[i] + LOG_EPS).ln() * g;
            d_w[i] -= scale_depth * g / (w[i] + LOG_EPS);
        }
        if sky {
            ls += w[i] * w[i];
            d_w[i] += scale_sky * 2.0 * w[i];
        }
    }
    (ld, ls)
}

/// CPU reference forward: weights and per-ray outputs.
pub fn render_cpu(batch: &RayBatch, background: Background) -> Result<Rendered, GpuError> {
    let rays = batch.rays()?;
    let s = batch.samples_per_ray;
    let mut weights = vec![0.0f32; rays * s];
    let mut out = vec![RayOutput::default(); rays];
    weights
        .par_chunks_mut(s)
        .zip(out.par_iter_mut())
        .enumerate()
        .with_min_len(64)
        .for_each(|(r, (w, o))| *o = render_ray(&batch.ray(r), background, w));
    Ok(Rendered { weights, rays: out })
}

fn check_targets(rays: usize, targets: &[RayTarget]) -> Result<(), GpuError> {
    if targets.len() != rays {
        return Err(GpuError::InvalidInput(format!(
            "render losses: {} targets for {rays} rays",
            targets.len()
        )));
    }
    Ok(())
}

/// CPU reference losses (no gradients).
pub fn losses_cpu(
    batch: &RayBatch,
    background: Background,
    targets: &[RayTarget],
    cfg: &LossConfig,
) -> Result<Losses, GpuError> {
    let rays = batch.rays()?;
    check_targets(rays, targets)?;
    cfg.validate()?;
    let scales = cfg.scales(rays);
    let per_ray = (0..rays)
        .into_par_iter()
        .with_min_len(64)
        .map(|r| ray_loss_backward(&batch.ray(r), &targets[r], background, cfg, scales, None))
        .collect();
    Ok(Losses::from_per_ray(per_ray, cfg))
}

/// CPU reference backward: the losses and dL/d(colour, density, normal) of every sample.
pub fn backward_cpu(
    batch: &RayBatch,
    background: Background,
    targets: &[RayTarget],
    cfg: &LossConfig,
) -> Result<RenderGradients, GpuError> {
    let rays = batch.rays()?;
    check_targets(rays, targets)?;
    cfg.validate()?;
    let s = batch.samples_per_ray;
    let scales = cfg.scales(rays);
    let mut d_samples = vec![Sample::default(); rays * s];
    let mut d_normals = batch.normals.map(|_| vec![[0.0f32; 3]; rays * s]);
    let mut per_ray = vec![RayLoss::default(); rays];
    let run = |r: usize, l: &mut RayLoss, ds: &mut [Sample], dn: Option<&mut [[f32; 3]]>| {
        let grads = RayGrads {
            samples: ds,
            normals: dn,
        };
        *l = ray_loss_backward(
            &batch.ray(r),
            &targets[r],
            background,
            cfg,
            scales,
            Some(grads),
        );
    };
    match d_normals.as_mut() {
        Some(dn) => per_ray
            .par_iter_mut()
            .zip(d_samples.par_chunks_mut(s))
            .zip(dn.par_chunks_mut(s))
            .enumerate()
            .with_min_len(64)
            .for_each(|(r, ((l, ds), dn))| run(r, l, ds, Some(dn))),
        None => per_ray
            .par_iter_mut()
            .zip(d_samples.par_chunks_mut(s))
            .enumerate()
            .with_min_len(64)
            .for_each(|(r, (l, ds))| run(r, l, ds, None)),
    }
    Ok(RenderGradients {
        losses: Losses::from_per_ray(per_ray, cfg),
        samples: d_samples,
        normals: d_normals,
    })
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct ParamsGpu {
    /// rays, samples per ray, has normals, background mode.
    dims: [u32; 4],
    bg: [f32; 4],
    /// λ_rgb/(3R), λ_depth/R, λ_normal/R, λ_sky/R.
    scales: [f32; 4],
    inv_two_var: f32,
    pad: [f32; 3],
}

fn params_for(
    batch: &GpuRayBatch,
    background: Background,
    losses: Option<&LossConfig>,
) -> ParamsGpu {
    let bg = match background {
        Background::Constant(c) => [c[0], c[1], c[2], 0.0],
        _ => [0.0; 4],
    };
    ParamsGpu {
        dims: [
            batch.rays,
            batch.samples_per_ray,
            batch.normals.is_some() as u32,
            background.mode(),
        ],
        bg,
        scales: losses.map_or([0.0; 4], |c| c.scales(batch.rays as usize)),
        inv_two_var: losses.map_or(0.0, |c| c.inv_two_var()),
        pad: [0.0; 3],
    }
}

/// Ray samples already on the GPU, in caller-owned buffers that may be larger than the batch: `samples`
/// holds R·S [`Sample`]s, `intervals` R·S [`Interval`]s, `normals` (optional) R·S·3 f32, ray-major.
#[derive(Clone, Copy, Debug)]
pub struct GpuRayBatch<'a> {
    pub rays: u32,
    pub samples_per_ray: u32,
    pub samples: &'a wgpu::Buffer,
    pub intervals: &'a wgpu::Buffer,
    pub normals: Option<&'a wgpu::Buffer>,
}

impl GpuRayBatch<'_> {
    fn n_samples(&self) -> Result<usize, GpuError> {
        if self.samples_per_ray == 0 {
            return Err(GpuError::InvalidInput(
                "render: samples_per_ray must be at least 1".into(),
            ));
        }
        let n = self.rays as u64 * self.samples_per_ray as u64;
        if n > u32::MAX as u64 {
            return Err(GpuError::InvalidInput(format!(
                "render: {n} samples is more than one call takes"
            )));
        }
        Ok(n as usize)
    }

    fn check(&self) -> Result<usize, GpuError> {
        let n = self.n_samples()?;
        need(self.samples, n * 4, "sample")?;
        need(self.intervals, n * 2, "interval")?;
        if let Some(nm) = self.normals {
            need(nm, n * 3, "normal")?;
        }
        Ok(n)
    }
}

fn need(buffer: &wgpu::Buffer, words: usize, what: &str) -> Result<(), GpuError> {
    let bytes = words as u64 * 4;
    if buffer.size() < bytes {
        return Err(GpuError::InvalidInput(format!(
            "render: {what} buffer holds {} bytes, {bytes} needed",
            buffer.size()
        )));
    }
    Ok(())
}

/// Records the forward pass: `weights` (R·S f32) and `rays_out` (R [`RayOutput`]s) from the batch.
pub async fn record_render(
    gpu: &Gpu,
    encoder: &mut wgpu::CommandEncoder,
    batch: GpuRayBatch<'_>,
    background: Background,
    weights: &wgpu::Buffer,
    rays_out: &wgpu::Buffer,
) -> Result<(), GpuError> {
    let n = batch.check()?;
    need(weights, n, "weight")?;
    need(rays_out, batch.rays as usize * 8, "ray output")?;
    if batch.rays == 0 {
        return Ok(());
    }
    // Binding 3 is in the pipeline layout either way; without normals the kernel never reads it.
    let dummy;
    let normals = match batch.normals {
        Some(b) => b,
        None => {
            dummy = gpu.upload("render no normals", &[0.0f32; 4])?;
            &dummy
        }
    };
    let u = gpu.uniform("render.params", &params_for(&batch, background, None));
    gpu.dispatch(
        encoder,
        &KERNEL,
        "render",
        &[
            (0, &u),
            (1, batch.samples),
            (2, batch.intervals),
            (3, normals),
            (5, weights),
            (6, rays_out),
        ],
        batch.rays,
    )
    .await
}

/// Records the losses and the backward: `losses` (R [`RayLoss`]s), `d_samples` (R·S [`Sample`]s: dL/dcolour,
/// dL/ddensity) and, exactly when the batch has normals, `d_normals` (R·S·3 f32). `targets` holds R
/// [`RayTarget`]s. Every output element is written; nothing is accumulated.
#[allow(clippy::too_many_arguments)]
pub async fn record_render_backward(
    gpu: &Gpu,
    encoder: &mut wgpu::CommandEncoder,
    batch: GpuRayBatch<'_>,
    background: Background,
    cfg: &LossConfig,
    targets: &wgpu::Buffer,
    losses: &wgpu::Buffer,
    d_samples: &wgpu::Buffer,
    d_normals: Option<&wgpu::Buffer>,
) -> Result<(), GpuError> {
    cfg.validate()?;
    let n = batch.check()?;
    let rays = batch.rays as usize;
    need(targets, rays * 8, "target")?;
    need(losses, rays * 4, "loss")?;
    need(d_samples, n * 4, "dL/dsample")?;
    match (batch.normals, d_normals) {
        (Some(_), Some(dn)) => need(dn, n * 3, "dL/dnormal")?,
        (None, None) => {}
        _ => {
            return Err(GpuError::InvalidInput(
                "render backward: d_normals must be given exactly when the batch has normals"
                    .into(),
            ))
        }
    }
    if rays == 0 {
        return Ok(());
    }
    let (dummy_in, dummy_out);
    let (normals, d_normals) = match (batch.normals, d_normals) {
        (Some(a), Some(b)) => (a, b),
        _ => {
            dummy_in = gpu.upload("render no normals", &[0.0f32; 4])?;
            dummy_out = gpu.output("render no dL/dnormals", 4)?;
            (&dummy_in, &dummy_out)
        }
    };
    let u = gpu.uniform("render.params", &params_for(&batch, background, Some(cfg)));
    gpu.dispatch(
        encoder,
        &KERNEL,
        "loss_backward",
        &[
            (0, &u),
            (1, batch.samples),
            (2, batch.intervals),
            (3, normals),
            (4, targets),
            (7, losses),
            (8, d_samples),
            (9, d_normals),
        ],
        batch.rays,
    )
    .await
}

struct Uploaded {
    samples: wgpu::Buffer,
    intervals: wgpu::Buffer,
    normals: Option<wgpu::Buffer>,
    rays: u32,
    s: u32,
}

impl Uploaded {
    fn new(gpu: &Gpu, batch: &RayBatch) -> Result<Self, GpuError> {
        let rays = batch.rays()?;
        Ok(Self {
            samples: gpu.upload("render samples", batch.samples)?,
            intervals: gpu.upload("render intervals", batch.intervals)?,
            normals: batch
                .normals
                .map(|n| gpu.upload("render normals", n))
                .transpose()?,
            rays: rays as u32,
            s: batch.samples_per_ray as u32,
        })
    }

    fn batch(&self) -> GpuRayBatch<'_> {
        GpuRayBatch {
            rays: self.rays,
            samples_per_ray: self.s,
            samples: &self.samples,
            intervals: &self.intervals,
            normals: self.normals.as_ref(),
        }
    }
}

/// The WGSL forward on host data: uploads, one dispatch, one readback. Same result as [`render_cpu`] up to
/// f32 rounding.
pub async fn render_gpu(
    gpu: &Gpu,
    batch: &RayBatch<'_>,
    background: Background,
) -> Result<Rendered, GpuError> {
    let up = Uploaded::new(gpu, batch)?;
    let n = batch.samples.len();
    let rays = up.rays as usize;
    let b_w = gpu.output("render weights", n)?;
    let b_rays = gpu.output("render rays", rays * 8)?;
    let mut enc = gpu.encoder("render");
    record_render(gpu, &mut enc, up.batch(), background, &b_w, &b_rays).await?;
    let mut out = gpu
        .finish_and_read::<f32>(enc, &[(&b_w, n), (&b_rays, rays * 8)])
        .await?
        .into_iter();
    let weights = out.next().unwrap_or_default();
    let rays = bytemuck::pod_collect_to_vec(&out.next().unwrap_or_default());
    Ok(Rendered { weights, rays })
}

/// The WGSL losses and backward on host data, one submit. Same result as [`backward_cpu`] up to f32
/// rounding.
pub async fn render_backward_gpu(
    gpu: &Gpu,
    batch: &RayBatch<'_>,
    background: Background,
    targets: &[RayTarget],
    cfg: &LossConfig,
) -> Result<RenderGradients, GpuError> {
    let up = Uploaded::new(gpu, batch)?;
    let rays = up.rays as usize;
    check_targets(rays, targets)?;
    cfg.validate()?;
    let n = batch.samples.len();
    let b_t = gpu.upload("render targets", targets)?;
    let b_l = gpu.output("render losses", rays * 4)?;
    let b_ds = gpu.output("render dL/dsamples", n * 4)?;
    let b_dn = batch
        .normals
        .map(|_| gpu.output("render dL/dnormals", n * 3))
        .transpose()?;
    let mut enc = gpu.encoder("render backward");
    record_render_backward(
        gpu,
        &mut enc,
        up.batch(),
        background,
        cfg,
        &b_t,
        &b_l,
        &b_ds,
        b_dn.as_ref(),
    )
    .await?;
    let mut reads = vec![(&b_l, rays * 4), (&b_ds, n * 4)];
    if let Some(dn) = &b_dn {
        reads.push((dn, n * 3));
    }
    let mut out = gpu.finish_and_read::<f32>(enc, &reads).await?.into_iter();
    let per_ray: Vec<RayLoss> = bytemuck::pod_collect_to_vec(&out.next().unwrap_or_default());
    let samples = bytemuck::pod_collect_to_vec(&out.next().unwrap_or_default());
    let normals = out.next().map(|d| {
        d.chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect::<Vec<_>>()
    });
    Ok(RenderGradients {
        losses: Losses::from_per_ray(per_ray, cfg),
        samples,
        normals,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn alpha_series_meets_exp_m1() {
        for &tau in &[
            0.0f32, 1e-8, 1e-4, 0.01, 0.1, 0.124_999, 0.125, 0.5, 3.0, 80.0,
        ] {
            let exact = -(-(tau as f64)).exp_m1();
            let a = alpha(tau) as f64;
            assert!(
                (a - exact).abs() <= 3e-7 * exact + 1e-30,
                "{tau}: {a} vs {exact}"
            );
        }
        assert_eq!(alpha(f32::INFINITY), 1.0);
    }

    #[test]
    fn one_opaque_sample_renders_its_colour_and_depth() {
        let samples = [
            Sample {
                rgb: [0.2, 0.4, 0.6],
                density: 1e4,
            },
            Sample {
                rgb: [1.0; 3],
                density: 1e4,
            },
        ];
        let intervals = [
            Interval {
                start: 1.0,
                end: 1.5,
            },
            Interval {
                start: 1.5,
                end: 2.0,
            },
        ];
        let batch = RayBatch {
            samples_per_ray: 2,
            samples: &samples,
            intervals: &intervals,
            normals: None,
        };
        let out = render_cpu(&batch, Background::Constant([1.0, 0.0, 0.0])).unwrap();
        assert_eq!(out.weights, vec![1.0, 0.0]);
        let r = out.rays[0];
        assert_eq!(r.rgb, [0.2, 0.4, 0.6]);
        assert_eq!((r.accumulation, r.depth), (1.0, 1.25));
        assert_eq!(r.normal, [0.0; 3]);
    }

    #[test]
    fn empty_ray_shows_the_background() {
        let samples = [Sample {
            rgb: [0.3, 0.5, 0.7],
            density: 0.0,
        }; 3];
        let intervals = [0.0f32, 1.0, 1.0].map(|t| Interval {
            start: t,
            end: t + 0.5,
        });
        let batch = RayBatch {
            samples_per_ray: 3,
            samples: &samples,
            intervals: &intervals,
            normals: None,
        };
        for (bg, want) in [
            (Background::Black, [0.0; 3]),
            (Background::Constant([0.1, 0.2, 0.3]), [0.1, 0.2, 0.3]),
            (Background::LastSample, [0.3, 0.5, 0.7]),
        ] {
            let out = render_cpu(&batch, bg).unwrap();
            assert_eq!(out.rays[0].rgb, want);
            assert_eq!(out.rays[0].accumulation, 0.0);
        }
    }

    #[test]
    fn mismatched_lengths_are_errors() {
        let s = [Sample::default(); 6];
        let iv = [Interval::default(); 6];
        let ok = RayBatch {
            samples_per_ray: 3,
            samples: &s,
            intervals: &iv,
            normals: None,
        };
        assert_eq!(ok.rays().unwrap(), 2);
        let bad = RayBatch {
            samples_per_ray: 4,
            ..ok
        };
        assert!(bad.rays().is_err());
        let bad = RayBatch {
            intervals: &iv[1..],
            ..ok
        };
        assert!(bad.rays().is_err());
        let t = [RayTarget::default(); 1];
        let err = losses_cpu(&ok, Background::Black, &t, &LossConfig::default()).unwrap_err();
        assert!(err.to_string().contains("targets"), "{err}");
        let cfg = LossConfig {
            depth_sigma: 0.0,
            ..LossConfig::default()
        };
        let t = [RayTarget::default(); 2];
        assert!(losses_cpu(&ok, Background::Black, &t, &cfg).is_err());
    }
}
