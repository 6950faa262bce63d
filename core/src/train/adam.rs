//! Adam (PyTorch's update and bias correction) with nerfstudio's exponential learning-rate decay.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Optimiser hyper-parameters (nerfacto: lr 1e-2, eps 1e-15, β = (0.9, 0.999)).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamConfig {
    pub lr: f32,
    /// Learning rate reached at `decay_steps` (log-linear in between, constant after).
    pub lr_final: f32,
    pub decay_steps: u32,
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self {
            lr: 1e-2,
            lr_final: 1e-4,
            decay_steps: 200_000,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-15,
        }
    }
}

impl AdamConfig {
    /// nerfstudio's `ExponentialDecayScheduler` without warm-up:
    /// lr(t) = exp(ln lr₀·(1 − t/T) + ln lr₁·t/T).
    pub fn lr_at(&self, step: u32) -> f32 {
        let t = (step as f64 / self.decay_steps.max(1) as f64).min(1.0);
        ((self.lr as f64).ln() * (1.0 - t) + (self.lr_final as f64).ln() * t).exp() as f32
    }

    /// The per-step scalars of the update at 1-based step `t`: (lr / (1 − β₁ᵗ), 1 / √(1 − β₂ᵗ)).
    pub fn corrections(&self, lr: f32, t: u32) -> (f32, f32) {
        let b1 = 1.0 - (self.beta1 as f64).powi(t as i32);
        let b2 = 1.0 - (self.beta2 as f64).powi(t as i32);
        ((lr as f64 / b1) as f32, (1.0 / b2.sqrt()) as f32)
    }
}

/// One parameter update, element-wise (the WGSL `adam` kernel does exactly this):
/// m ← β₁m + (1 − β₁)g; v ← β₂v + (1 − β₂)g²; p ← p − a·m / (√v·c + ε).
#[inline]
pub fn adam_element(
    cfg: &AdamConfig,
    a: f32,
    c: f32,
    p: &mut f32,
    m: &mut f32,
    v: &mut f32,
    g: f32,
) {
    let g = if g.is_finite() { g } else { 0.0 };
    *m = cfg.beta1 * *m + (1.0 - cfg.beta1) * g;
    *v = cfg.beta2 * *v + (1.0 - cfg.beta2) * g * g;
    *p -= a * *m / (v.sqrt() * c + cfg.eps);
}

/// Moments for a list of tensors.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamState {
    pub m: Vec<Vec<f32>>,
    pub v: Vec<Vec<f32>>,
    /// Updates done so far.
    pub t: u32,
}

impl AdamState {
    pub fn new(sizes: impl IntoIterator<Item = usize>) -> Self {
        let sizes: Vec<usize> = sizes.into_iter().collect();
        Self {
            m: sizes.iter().map(|&n| vec![0.0; n]).collect(),
            v: sizes.iter().map(|&n| vec![0.0; n]).collect(),
            t: 0,
        }
    }

    /// One step over every tensor on the CPU (rayon over chunks).
    pub fn update(
        &mut self,
        cfg: &AdamConfig,
        lr: f32,
        params: &mut [Vec<f32>],
        grads: &[Vec<f32>],
    ) {
        self.t += 1;
        let (a, c) = cfg.corrections(lr, self.t);
        for (((p, m), v), g) in params
            .iter_mut()
            .zip(&mut self.m)
            .zip(&mut self.v)
            .zip(grads)
        {
            p.par_chunks_mut(4096)
                .zip(m.par_chunks_mut(4096))
                .zip(v.par_chunks_mut(4096))
                .zip(g.par_chunks(4096))
                .for_each(|(((p, m), v), g)| {
                    for i in 0..p.len() {
                        adam_element(cfg, a, c, &mut p[i], &mut m[i], &mut v[i], g[i]);
                    }
                });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_torch_first_steps() {
        // torch.optim.Adam(lr=0.1) on p = 1 with g = 2 then g = −1: the first step moves by lr exactly.
        let cfg = AdamConfig {
            lr: 0.1,
            eps: 1e-8,
            ..Default::default()
        };
        let mut st = AdamState::new([1]);
        let mut p = vec![vec![1.0f32]];
        st.update(&cfg, 0.1, &mut p, &[vec![2.0]]);
        assert!((p[0][0] - 0.9).abs() < 1e-6, "{}", p[0][0]);
        st.update(&cfg, 0.1, &mut p, &[vec![-1.0]]);
        // m = 0.08, v = 0.004999 → m̂ = 0.08/0.19, v̂ = 0.004999/0.001999.
        let mh = 0.08f64 / 0.19;
        let vh = (0.999 * 0.004 + 0.001) / (1.0 - 0.999f64 * 0.999);
        let want = 0.9 - 0.1 * mh / (vh.sqrt() + 1e-8);
        assert!(
            (p[0][0] as f64 - want).abs() < 1e-5,
            "{} vs {want}",
            p[0][0]
        );
    }

    #[test]
    fn lr_decays_log_linearly() {
        let cfg = AdamConfig {
            lr: 1e-2,
            lr_final: 1e-4,
            decay_steps: 100,
            ..Default::default()
        };
        assert!((cfg.lr_at(0) - 1e-2).abs() < 1e-9);
        assert!((cfg.lr_at(50) - 1e-3).abs() < 1e-7);
        assert!((cfg.lr_at(500) - 1e-4).abs() < 1e-9);
    }
}
