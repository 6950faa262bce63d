//! Where along each ray the field is evaluated: nerfacto's proposal sampling.
//!
//! Distances along a ray live in two coordinates: t (ray distance, scene units) and the normalised spacing
//! s ∈ [0, 1], s = (g(t) − g(near)) / (g(far) − g(near)) with nerfacto's piecewise g (uniform up to 1, then
//! linear in disparity: g(t) = t/2 for t < 1, 1 − 1/(2t) beyond). The first level is uniform in s with one
//! jitter per ray; each later level resamples the previous level's (annealed, padded) weights as a
//! piecewise-constant PDF over s. The interlevel loss teaches the proposal densities to bound the final
//! weights; the distortion loss (on the final level, in s) pulls each ray's weight together. Functions work
//! on one ray (slices of edges and weights), so the batch loop, the rayon fallback and the one-thread-per-ray
//! WGSL kernels (`shaders/sampler.wgsl`) share one definition.

pub mod occupancy;

use serde::{Deserialize, Serialize};

/// Proposal-sampling configuration (nerfacto's defaults).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SamplerConfig {
    /// Near and far plane in scene units (after the dataset's normalisation).
    pub near: f32,
    pub far: f32,
    /// Samples per proposal level, first to last (nerfacto: 256, 96).
    pub proposal_samples: Vec<usize>,
    /// Samples of the final level, where the radiance field is evaluated (nerfacto: 48).
    pub samples: usize,
    /// Added to every weight before resampling (nerfacto: 0.01), so no bin's probability is zero.
    pub histogram_padding: f32,
    /// Steps over which the proposal weights are annealed from uniform (exponent 0) to themselves.
    pub anneal_steps: u32,
    /// Slope of the annealing bias (nerfacto: 10).
    pub anneal_slope: f32,
}

impl Default for SamplerConfig {
    fn default() -> Self {
        Self {
            near: 0.05,
            far: 1000.0,
            proposal_samples: vec![256, 96],
            samples: 48,
            histogram_padding: 0.01,
            anneal_steps: 1000,
            anneal_slope: 10.0,
        }
    }
}

/// nerfacto's piecewise spacing g(t).
pub fn spacing_fn(t: f32) -> f32 {
    if t < 1.0 {
        0.5 * t
    } else {
        1.0 - 0.5 / t
    }
}

/// g⁻¹(s) for s ∈ [0, 1).
pub fn spacing_inv(g: f32) -> f32 {
    if g < 0.5 {
        2.0 * g
    } else {
        0.5 / (1.0 - g).max(1e-7)
    }
}

/// Maps normalised spacing to ray distance for one near/far pair.
#[derive(Clone, Copy, Debug)]
pub struct Spacing {
    g_near: f32,
    g_span: f32,
}

impl Spacing {
    pub fn new(near: f32, far: f32) -> Self {
        let g_near = spacing_fn(near);
        Self {
            g_near,
            g_span: spacing_fn(far) - g_near,
        }
    }

    /// g(near), as the WGSL kernels take it.
    pub fn g_near(&self) -> f32 {
        self.g_near
    }

    /// g(far) − g(near).
    pub fn g_span(&self) -> f32 {
        self.g_span
    }

    pub fn to_t(&self, s: f32) -> f32 {
        spacing_inv(self.g_near + s * self.g_span)
    }
}

/// The exponent the proposal weights are raised to at `step` before resampling:
/// bias(min(step / anneal_steps, 1), slope) with bias(x, b) = b·x / ((b − 1)·x + 1).
pub fn anneal_exponent(cfg: &SamplerConfig, step: u32) -> f32 {
    let x = (step as f32 / cfg.anneal_steps.max(1) as f32).min(1.0);
    let b = cfg.anneal_slope;
    b * x / ((b - 1.0) * x + 1.0)
}

/// First-level edges (n + 1, normalised s): stratified bins with one jitter j ∈ [0, 1) per ray (training),
/// or the bin centres' midpoints (`jitter = None`, evaluation).
pub fn initial_edges(jitter: Option<f32>, edges: &mut [f32]) {
    let n = edges.len() - 1;
    match jitter {
        None => {
            for (k, e) in edges.iter_mut().enumerate() {
                *e = k as f32 / n as f32;
            }
        }
        Some(j) => {
            // nerfstudio: lower/upper bounds from the bin centres, one uniform offset for the whole ray.
            for (k, e) in edges.iter_mut().enumerate() {
                let lo = if k == 0 {
                    0.0
                } else {
                    (k as f32 - 0.5) / n as f32
                };
                let hi = if k == n {
                    1.0
                } else {
                    (k as f32 + 0.5) / n as f32
                };
                *e = lo + (hi - lo) * j;
            }
        }
    }
}

/// Resamples `out.len() − 1` bins from the piecewise-constant PDF (`weights` over `edges`, both in s),
/// nerfstudio's `PDFSampler` with `exponent`-annealed weights plus `padding`; `jitter` as in
/// [`initial_edges`] (one offset per ray). `cdf` is scratch of `weights.len() + 1`.
pub fn pdf_resample(
    edges: &[f32],
    weights: &[f32],
    exponent: f32,
    padding: f32,
    jitter: Option<f32>,
    cdf: &mut [f32],
    out: &mut [f32],
) {
    let n = weights.len();
    let mut sum = 0.0f32;
    for &w in weights {
        sum += annealed(w, exponent) + padding;
    }
    let eps = 1e-5f32;
    let extra = (eps - sum).max(0.0);
    let per = extra / n as f32;
    sum += extra;
    cdf[0] = 0.0;
    let mut acc = 0.0f32;
    for (i, &w) in weights.iter().enumerate() {
        acc += (annealed(w, exponent) + padding + per) / sum;
        cdf[i + 1] = acc.min(1.0);
    }
    let nb = out.len();
    let step = 1.0 / nb as f32;
    let offset = jitter.map_or(0.5 * step, |j| j * step);
    let mut idx = 0usize; // searchsorted(cdf, u, right) walks forward: u increases
    for (k, o) in out.iter_mut().enumerate() {
        // nerfstudio's linspace(0, 1 − 1/nb, nb) + offset.
        let u = k as f32 * step + offset;
        while idx < cdf.len() && cdf[idx] <= u {
            idx += 1;
        }
        let below = idx.saturating_sub(1).min(n);
        let above = idx.min(n);
        let (c0, c1) = (cdf[below], cdf[above]);
        let (b0, b1) = (edges[below], edges[above]);
        let d = c1 - c0;
        let f = if d > 0.0 {
            ((u - c0) / d).clamp(0.0, 1.0)
        } else {
            0.0
        };
        *o = b0 + f * (b1 - b0);
    }
    // Monotone by construction up to rounding; enforce it so intervals are never negative.
    for k in 1..out.len() {
        if out[k] < out[k - 1] {
            out[k] = out[k - 1];
        }
    }
}

fn annealed(w: f32, exponent: f32) -> f32 {
    if exponent == 1.0 {
        w.max(0.0)
    } else {
        w.max(0.0).powf(exponent)
    }
}

/// torch's float32 eps, nerfstudio's EPS in the interlevel loss.
pub const INTERLEVEL_EPS: f32 = 1.192_092_9e-7;

/// nerfacto's interlevel loss for one ray and one proposal level: Σ over final bins of
/// max(0, w − w_outer)² / (w + eps), where w_outer is the proposal weight overlapping the final bin
/// (`c`, `w`: final edges and weights, held fixed; `cp`, `wp`: the proposal's). With `d_wp`, adds
/// `scale` × dloss/dwp into it.
pub fn interlevel(
    c: &[f32],
    w: &[f32],
    cp: &[f32],
    wp: &[f32],
    scale: f32,
    mut d_wp: Option<&mut [f32]>,
    cum: &mut [f32],
) -> f32 {
    let m = wp.len();
    cum[0] = 0.0;
    for j in 0..m {
        cum[j + 1] = cum[j] + wp[j];
    }
    // searchsorted(cp, x, right): first index with cp[idx] > x.
    let search = |x: f32| cp.partition_point(|&v| v <= x);
    let mut loss = 0.0f32;
    for i in 0..w.len() {
        let lo = (search(c[i]) as isize - 1).clamp(0, m as isize) as usize;
        let hi = search(c[i + 1]).min(m);
        let outer = cum[hi] - cum[lo.min(hi)];
        let r = w[i] - outer;
        if r > 0.0 {
            loss += r * r / (w[i] + INTERLEVEL_EPS);
            if let Some(g) = d_wp.as_deref_mut() {
                let dv = -2.0 * r / (w[i] + INTERLEVEL_EPS) * scale;
                for gj in &mut g[lo.min(hi)..hi] {
                    *gj += dv;
                }
            }
        }
    }
    loss
}

/// nerfacto's distortion loss for one ray on normalised edges `c` and weights `w`:
/// Σᵢⱼ wᵢwⱼ|mᵢ − mⱼ| + ⅓Σᵢ wᵢ²(cᵢ₊₁ − cᵢ), mᵢ the bin midpoints (sorted, so both sums are O(n) with
/// prefix sums). With `d_w`, adds `scale` × dloss/dw into it.
pub fn distortion(c: &[f32], w: &[f32], scale: f32, d_w: Option<&mut [f32]>) -> f32 {
    let n = w.len();
    let mid = |i: usize| 0.5 * (c[i] + c[i + 1]);
    let (mut w_tot, mut wm_tot) = (0.0f32, 0.0f32);
    for (i, wi) in w.iter().enumerate() {
        w_tot += wi;
        wm_tot += wi * mid(i);
    }
    let mut loss = 0.0f32;
    let (mut w_lo, mut wm_lo) = (0.0f32, 0.0f32);
    let mut grads = d_w;
    for i in 0..n {
        let m = mid(i);
        let (w_hi, wm_hi) = (w_tot - w_lo - w[i], wm_tot - wm_lo - w[i] * m);
        // Σⱼ wⱼ|mᵢ − mⱼ|.
        let s = m * w_lo - wm_lo + wm_hi - m * w_hi;
        let delta = c[i + 1] - c[i];
        loss += w[i] * s + w[i] * w[i] * delta / 3.0;
        if let Some(g) = grads.as_deref_mut() {
            g[i] += scale * (2.0 * s + 2.0 * w[i] * delta / 3.0);
        }
        w_lo += w[i];
        wm_lo += w[i] * m;
    }
    loss
}

/// Volume-rendering weights wᵢ = Tᵢ(1 − exp(−σᵢδᵢ)) of one ray (the same arithmetic as `render`).
pub fn weights(density: &[f32], t_edges: &[f32], out: &mut [f32]) {
    let mut p = 0.0f32;
    for i in 0..density.len() {
        let delta = (t_edges[i + 1] - t_edges[i]).max(0.0);
        let tau = if delta > 0.0 { density[i] * delta } else { 0.0 };
        out[i] = (-p).exp() * crate::render::alpha(tau);
        p += tau;
    }
}

/// dL/dσ from dL/dw for one ray: dL/dτₖ = gₖTₖ₊₁ − Σ_{i>k} gᵢwᵢ, dL/dσₖ = δₖ·dL/dτₖ; added into `d_density`.
pub fn weights_backward(density: &[f32], t_edges: &[f32], d_w: &[f32], d_density: &mut [f32]) {
    let n = density.len();
    let mut p = 0.0f32;
    // Forward pass for the transmittances (recomputed; rays are short).
    let mut t_before = Vec::with_capacity(n + 1);
    let mut w = Vec::with_capacity(n);
    for i in 0..n {
        let delta = (t_edges[i + 1] - t_edges[i]).max(0.0);
        let tau = if delta > 0.0 { density[i] * delta } else { 0.0 };
        t_before.push((-p).exp());
        w.push((-p).exp() * crate::render::alpha(tau));
        p += tau;
    }
    t_before.push((-p).exp());
    let mut suffix = 0.0f32;
    for k in (0..n).rev() {
        let delta = (t_edges[k + 1] - t_edges[k]).max(0.0);
        let d_tau = d_w[k] * t_before[k + 1] - suffix;
        suffix += d_w[k] * w[k];
        d_density[k] += delta * d_tau;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fd<F: Fn(&[f32]) -> f32>(f: F, x: &[f32], h: f32) -> Vec<f32> {
        (0..x.len())
            .map(|i| {
                let mut a = x.to_vec();
                let mut b = x.to_vec();
                a[i] += h;
                b[i] -= h;
                (f(&a) - f(&b)) / (2.0 * h)
            })
            .collect()
    }

    #[test]
    fn spacing_round_trips() {
        for t in [0.05f32, 0.5, 1.0, 3.0, 999.0] {
            assert!((spacing_inv(spacing_fn(t)) - t).abs() / t < 1e-4, "{t}");
        }
        let sp = Spacing::new(0.05, 1000.0);
        assert!((sp.to_t(0.0) - 0.05).abs() < 1e-6);
        assert!((sp.to_t(1.0) - 1000.0).abs() / 1000.0 < 1e-3);
    }

    #[test]
    fn pdf_resampling_follows_the_weights() {
        let edges: Vec<f32> = (0..=10).map(|k| k as f32 / 10.0).collect();
        let mut w = vec![0.0f32; 10];
        w[7] = 1.0;
        let mut cdf = vec![0.0; 11];
        let mut out = vec![0.0; 33];
        pdf_resample(&edges, &w, 1.0, 0.01, Some(0.3), &mut cdf, &mut out);
        let inside = out
            .windows(2)
            .filter(|p| p[0] >= 0.7 && p[1] <= 0.8)
            .count();
        assert!(
            inside >= 25,
            "{inside} of 32 bins in the heavy bin: {out:?}"
        );
        assert!(out.windows(2).all(|p| p[1] >= p[0]));
        // Exponent 0: uniform regardless of the weights.
        pdf_resample(&edges, &w, 0.0, 0.01, None, &mut cdf, &mut out);
        let widths: Vec<f32> = out.windows(2).map(|p| p[1] - p[0]).collect();
        assert!(
            widths.iter().all(|&d| (d - widths[0]).abs() < 1e-5),
            "{widths:?}"
        );
    }

    #[test]
    fn interlevel_gradient_matches_fd() {
        let c = [0.0, 0.1, 0.25, 0.3, 0.6, 1.0];
        let w = [0.1, 0.5, 0.2, 0.15, 0.05];
        let cp = [0.0, 0.2, 0.28, 0.5, 1.0];
        let wp = [0.2, 0.1, 0.3, 0.05];
        let mut cum = [0.0; 5];
        let mut g = vec![0.0; 4];
        let l0 = interlevel(&c, &w, &cp, &wp, 1.0, Some(&mut g), &mut cum);
        assert!(l0 > 0.0);
        let num = fd(
            |x| interlevel(&c, &w, &cp, x, 1.0, None, &mut [0.0; 5]),
            &wp,
            1e-3,
        );
        for (a, b) in g.iter().zip(&num) {
            assert!((a - b).abs() < 1e-2 * (1.0 + b.abs()), "{g:?} vs {num:?}");
        }
        // A proposal that bounds the final weights costs nothing.
        let big = [1.0, 1.0, 1.0, 1.0];
        assert_eq!(interlevel(&c, &w, &cp, &big, 1.0, None, &mut cum), 0.0);
    }

    #[test]
    fn distortion_matches_brute_force_and_fd() {
        let c: [f32; 6] = [0.0, 0.1, 0.25, 0.3, 0.6, 1.0];
        let w = [0.1, 0.5, 0.2, 0.15, 0.05];
        let brute = |w: &[f32]| {
            let mut l = 0.0f32;
            for i in 0..5 {
                for j in 0..5 {
                    let (mi, mj) = (0.5 * (c[i] + c[i + 1]), 0.5 * (c[j] + c[j + 1]));
                    l += w[i] * w[j] * (mi - mj).abs();
                }
                l += w[i] * w[i] * (c[i + 1] - c[i]) / 3.0;
            }
            l
        };
        let mut g = vec![0.0; 5];
        let l = distortion(&c, &w, 1.0, Some(&mut g));
        assert!((l - brute(&w)).abs() < 1e-6);
        let num = fd(brute, &w, 1e-3);
        for (a, b) in g.iter().zip(&num) {
            assert!((a - b).abs() < 1e-3, "{g:?} vs {num:?}");
        }
    }

    #[test]
    fn weights_backward_matches_fd() {
        let t = [0.0f32, 0.3, 0.5, 0.9, 1.0, 1.6];
        let sigma = [0.5f32, 2.0, 0.1, 4.0, 1.0];
        let g = [0.3f32, -1.0, 0.7, 0.2, -0.4];
        let f = |s: &[f32]| {
            let mut w = [0.0f32; 5];
            weights(s, &t, &mut w);
            w.iter().zip(&g).map(|(a, b)| a * b).sum::<f32>()
        };
        let mut d = vec![0.0; 5];
        weights_backward(&sigma, &t, &g, &mut d);
        let num = fd(f, &sigma, 1e-3);
        for (a, b) in d.iter().zip(&num) {
            assert!((a - b).abs() < 2e-3, "{d:?} vs {num:?}");
        }
    }
}
