//! The Laplace σ checked against lidar returns the field never saw, and one factor per read-out fitted
//! on them (never on ground truth).
//!
//! Training holds one lidar return in [`HELD_OUT_RETURN_EVERY`](crate::train::data::HELD_OUT_RETURN_EVERY)
//! out of its losses. Each held-out return's ray is rendered; the field's point sits at the expected depth
//! E, the return at range d. The residual that speaks to the point's position is the point-to-plane
//! distance |E − d|·|cos θ| (θ between the ray and the lidar normal: a point slid along a wall is not
//! wrong), and the return carries the lidar's own range noise σ_l, which projects to σ_l·|cos θ|. With
//! σ(k) the read-out under factor k, the fit is the smallest k for which
//!
//! |E − d|·|cos θ| ≤ √(σ(k)² + (σ_l·|cos θ|)²)
//!
//! holds for 68.27 % of the returns: what 1σ of a Gaussian error covers. σ grows with k (the information
//! is divided by k²), so coverage does too and bisection finds it. Grazing returns (|cos θ| < 0.2) and
//! rays the field leaves unfinished (accumulation below the export's 0.98) are not used: the first measure
//! the surface's offset poorly, the second are not points the export would keep.

use rand::seq::SliceRandom;
use rand::SeedableRng;

use super::reliability::{reliability, Reliability};
use super::{Calibration, Fisher, Modality, Posterior};
use crate::gpu::GpuError;
use crate::train::cpu::TrainRay;
use crate::train::export::EXPORT_MIN_ACCUMULATION;
use crate::train::Trainer;

/// Fraction of a Gaussian within ±1σ.
pub const ONE_SIGMA: f64 = 0.682_689_492;

/// Returns steeper than this to the surface (|cos θ| below it, 78°) are left out of the fit.
const MIN_COS_INCIDENCE: f64 = 0.2;

/// Held-out lidar returns as the field renders them.
#[derive(Clone, Debug, Default)]
pub struct HeldOutReturns {
    /// The field's point on each return's ray (scene frame).
    pub points: Vec<[f32; 3]>,
    /// Point-to-plane residual |E − d|·|cos θ| (metres).
    pub residual_m: Vec<f64>,
    /// The lidar's range noise projected the same way, σ_l·|cos θ| (metres).
    pub noise_m: Vec<f64>,
    /// Held-out returns the dataset has, and how many were rendered.
    pub available: usize,
    pub rendered: usize,
}

impl HeldOutReturns {
    /// Alternate returns: the half the factors are fitted on and the half they are checked on.
    pub fn split(&self) -> (HeldOutReturns, HeldOutReturns) {
        let half = |parity: usize| HeldOutReturns {
            points: self
                .points
                .iter()
                .skip(parity)
                .step_by(2)
                .copied()
                .collect(),
            residual_m: self
                .residual_m
                .iter()
                .skip(parity)
                .step_by(2)
                .copied()
                .collect(),
            noise_m: self
                .noise_m
                .iter()
                .skip(parity)
                .step_by(2)
                .copied()
                .collect(),
            available: self.available,
            rendered: self.rendered,
        };
        (half(0), half(1))
    }
}

/// The reliability of one read-out on held-out returns: each residual against √(σ² + noise²), the spread
/// the read-out and the lidar's noise predict for it together (`None` without returns).
pub fn held_out_reliability(
    fisher: &Fisher,
    m: Modality,
    post: Posterior,
    held: &HeldOutReturns,
) -> Option<Reliability> {
    let ls = fisher.read_out_scene(m, post, &held.points);
    let predicted: Vec<f32> = ls
        .iter()
        .zip(&held.noise_m)
        .map(|(&l, &n)| {
            let s = 10f64.powf(l as f64);
            (0.5 * (s * s + n * n).log10()) as f32
        })
        .collect();
    let at = super::unconstrained_log_std(fisher.prior_sigma_m());
    reliability(&predicted, &held.residual_m, at, 10)
}

/// Renders up to `max` held-out returns (chosen by `seed`) with the trainer's engine.
pub async fn held_out_returns(
    trainer: &mut Trainer,
    max: usize,
    seed: u64,
) -> Result<HeldOutReturns, GpuError> {
    let mut all = trainer.data.held_out_returns();
    let available = all.len();
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed);
    all.shuffle(&mut rng);
    all.truncate(max);
    // Image order: consecutive rays of one camera render together.
    all.sort_unstable();
    let data = &trainer.data;
    let mut rays = Vec::with_capacity(all.len());
    let mut which = Vec::with_capacity(all.len());
    for &(i, p) in &all {
        let im = &data.images[i];
        if let Some((o, d)) = data.ray(i, p % im.width, p / im.width) {
            rays.push(TrainRay {
                origin: o,
                dir: d,
                appearance: im.appearance.unwrap_or(u32::MAX),
            });
            which.push((i, p as usize));
        }
    }
    let out = trainer.render(&rays, false).await?;
    let data = &trainer.data;
    let (scale, noise) = (data.frame.scale, data.lidar_range_noise_m);
    let mut held = HeldOutReturns {
        available,
        rendered: rays.len(),
        ..Default::default()
    };
    for ((ray, r), &(i, p)) in rays.iter().zip(&out).zip(&which) {
        let e = r.expected_depth;
        let Some(d) = data.lidar_range(i, p) else {
            continue;
        };
        if r.out.accumulation < EXPORT_MIN_ACCUMULATION || !e.is_finite() {
            continue;
        }
        let dir = glam::DVec3::from(ray.dir.map(f64::from));
        let cos = data.lidar_normal(i, p).map_or(1.0, |n| n.dot(dir).abs());
        if cos < MIN_COS_INCIDENCE {
            continue;
        }
        let o = glam::Vec3::from(ray.origin);
        held.points
            .push((o + glam::Vec3::from(ray.dir) * e).to_array());
        held.residual_m.push(((e - d) as f64 / scale).abs() * cos);
        held.noise_m.push(noise * cos);
    }
    Ok(held)
}

/// Fraction of the held-out returns whose residual lies within √(σ² + noise²), σ the read-out `log_std`
/// (log10 metres) at each.
pub fn coverage(held: &HeldOutReturns, log_std: &[f32], within: f64) -> f64 {
    let n = held.residual_m.len();
    if n == 0 {
        return f64::NAN;
    }
    let hit = (0..n)
        .filter(|&i| {
            let s = 10f64.powf(log_std[i] as f64);
            let bound = within * (s * s + held.noise_m[i] * held.noise_m[i]).sqrt();
            held.residual_m[i] <= bound
        })
        .count();
    hit as f64 / n as f64
}

/// The factor of one read-out: the smallest k whose 1σ covers [`ONE_SIGMA`] of the held-out returns
/// (bisection on log k over 10⁻³…10⁸), and the coverage it reached.
pub fn fit_factor(fisher: &Fisher, m: Modality, held: &HeldOutReturns) -> (f64, f64) {
    let at = |log_k: f64| {
        let mut f = fisher.clone();
        f.calibration.factor[m.index()] = 10f64.powf(log_k);
        let ls = f.read_out_scene(m, Posterior::Calibrated, &held.points);
        coverage(held, &ls, 1.0)
    };
    let (mut lo, mut hi) = (-3.0f64, 8.0f64);
    if at(hi) < ONE_SIGMA {
        // Even the prior's σ does not cover them: the field is further off than it claims anywhere.
        return (10f64.powf(hi), at(hi));
    }
    if at(lo) >= ONE_SIGMA {
        return (10f64.powf(lo), at(lo));
    }
    for _ in 0..40 {
        let mid = 0.5 * (lo + hi);
        if at(mid) >= ONE_SIGMA {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    (10f64.powf(hi), at(hi))
}

/// Fits every read-out's factor on `held` (a Fisher without lidar information keeps its depth read-out
/// raw: the prior alone cannot be calibrated). Without returns the Fisher stays uncalibrated.
pub fn calibrate(fisher: &mut Fisher, held: &HeldOutReturns) {
    if held.residual_m.is_empty() {
        fisher.calibration = Calibration::RAW;
        return;
    }
    let mut c = Calibration {
        factor: [1.0; 3],
        returns: held.residual_m.len() as u64,
        coverage: [f64::NAN; 3],
    };
    let has_depth = fisher.depth.iter().any(|&h| h > 0.0);
    for m in Modality::ALL {
        if m == Modality::Depth && !has_depth {
            continue;
        }
        let (k, cov) = fit_factor(fisher, m, held);
        c.factor[m.index()] = k;
        c.coverage[m.index()] = cov;
    }
    fisher.calibration = c;
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::train::data::SceneFrame;
    use crate::uncertainty::PerturbationGrid;

    /// A Fisher whose information is uniform, so every read-out is one σ; residuals drawn from a known
    /// Gaussian: the fit must find the k that makes σ that Gaussian's.
    #[test]
    fn the_fit_recovers_the_scale_of_gaussian_residuals() {
        let cells = 4;
        let n = PerturbationGrid { cells }.vertices();
        let fisher = Fisher {
            cells,
            colour: vec![1e6; n],
            depth: vec![4e6; n],
            rays: 1,
            lidar_rays: 1,
            prior: 1.0,
            colour_sigma: 1.0,
            depth_sigma: 1.0,
            frame: SceneFrame {
                center: [0.0; 3],
                scale: 1.0,
            },
            calibration: Calibration::RAW,
        };
        // Raw combined σ = 1/√(5e6 + 1) ≈ 0.447 mm; the residuals' σ is 5 cm with 1 cm of noise.
        let true_sigma = 0.05f64;
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(3);
        let mut held = HeldOutReturns::default();
        use rand::Rng;
        for _ in 0..20_000 {
            let g: f64 = {
                // Box–Muller.
                let (u, v): (f64, f64) = (rng.random::<f64>().max(1e-12), rng.random());
                (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
            };
            let noise: f64 = {
                let (u, v): (f64, f64) = (rng.random::<f64>().max(1e-12), rng.random());
                (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
            };
            held.points.push([0.1, 0.2, 0.3]);
            held.residual_m.push((g * true_sigma + noise * 0.01).abs());
            held.noise_m.push(0.01);
        }
        let mut f = fisher.clone();
        calibrate(&mut f, &held);
        for m in Modality::ALL {
            let ls = f.read_out_scene(m, Posterior::Calibrated, &held.points[..1])[0];
            let s = 10f64.powf(ls as f64);
            assert!(
                (s / true_sigma - 1.0).abs() < 0.05,
                "{}: calibrated σ {s} m for residuals of σ {true_sigma} m",
                m.name()
            );
            assert!((f.calibration.coverage[m.index()] - ONE_SIGMA).abs() < 0.01);
            let two = coverage(
                &held,
                &f.read_out_scene(m, Posterior::Calibrated, &held.points),
                2.0,
            );
            assert!((two - 0.9545).abs() < 0.01, "2σ coverage {two}");
        }
        // Raw is ~100x overconfident here: its coverage is far below 1σ's.
        let raw = fisher.read_out_scene(Modality::Combined, Posterior::Raw, &held.points);
        assert!(coverage(&held, &raw, 1.0) < 0.3);
        // No returns: uncalibrated.
        let mut g = fisher.clone();
        calibrate(&mut g, &HeldOutReturns::default());
        assert!(!g.calibration.is_calibrated());
    }
}
