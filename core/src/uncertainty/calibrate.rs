//! The point σ checked against lidar returns the field never saw, and two factors per read-out fitted on
//! them (never on ground truth): k on the Laplace σ, a on the ray's spread s ([`super::with_spread`]).
//!
//! Training holds one lidar return in [`HELD_OUT_RETURN_EVERY`](crate::train::data::HELD_OUT_RETURN_EVERY)
//! out of its losses. Each held-out return's ray is rendered; the field's point sits at the expected depth
//! E, the return at range d. The residual that speaks to the point's position is the point-to-plane
//! distance |E − d|·|cos θ| (θ between the ray and the lidar normal: a point slid along a wall is not
//! wrong), and the return carries the lidar's own range noise σ_l, which projects to σ_l·|cos θ|. With
//! σ(k, a) = √(σ_k² + (a·s)²) the point's σ under the factors, for each a on a grid the fit takes the
//! smallest k for which
//!
//! |E − d|·|cos θ| ≤ √(σ(k, a)² + (σ_l·|cos θ|)²)
//!
//! holds for 68.27 % of the returns (what 1σ of a Gaussian error covers; σ grows with k, the information
//! being divided by k², so coverage does too and bisection finds it), and keeps the pair whose 2σ covers
//! closest to 95.45 %. The spread is along the ray and is not projected by |cos θ| as the residual is: a
//! absorbs the returns' mean incidence, as it does for an exported point, whose σ carries s unprojected. Grazing returns (|cos θ| < 0.2) and
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
    /// The rendered ray's termination spread (metres), which an exported point's σ carries
    /// ([`super::with_spread`]).
    pub spread_m: Vec<f64>,
    /// Held-out returns the dataset has, and how many were rendered.
    pub available: usize,
    pub rendered: usize,
}

impl HeldOutReturns {
    /// Return i's point σ (metres) given the field's read-out `log_std` there: with its ray's spread times
    /// `a`, as an exported point carries it.
    fn sigma_m(&self, i: usize, log_std: f32, a: f64) -> f64 {
        let s = 10f64.powf(log_std as f64);
        let spread = a * self.spread_m.get(i).copied().unwrap_or(0.0);
        (s * s + spread * spread).sqrt()
    }

    /// Alternate returns: the half the factors are fitted on and the half they are checked on.
    pub fn split(&self) -> (HeldOutReturns, HeldOutReturns) {
        fn every_other<T: Copy>(v: &[T], parity: usize) -> Vec<T> {
            v.iter().skip(parity).step_by(2).copied().collect()
        }
        let half = |parity: usize| HeldOutReturns {
            points: every_other(&self.points, parity),
            residual_m: every_other(&self.residual_m, parity),
            noise_m: every_other(&self.noise_m, parity),
            spread_m: every_other(&self.spread_m, parity),
            available: self.available,
            rendered: self.rendered,
        };
        (half(0), half(1))
    }

    /// Every return's point σ (metres) under one read-out: the field's σ there with its ray's spread.
    fn point_sigmas(&self, fisher: &Fisher, m: Modality, post: Posterior) -> Vec<f64> {
        let ls = fisher.read_out_scene(m, post, &self.points);
        let a = fisher.spread_factors(post)[m.index()];
        ls.iter()
            .enumerate()
            .map(|(i, &l)| self.sigma_m(i, l, a))
            .collect()
    }
}

/// The reliability of one read-out on held-out returns: each residual against √(σ² + noise²), σ the
/// point's (with its ray's spread), the spread the read-out and the lidar's noise predict for it together
/// (`None` without returns).
pub fn held_out_reliability(
    fisher: &Fisher,
    m: Modality,
    post: Posterior,
    held: &HeldOutReturns,
) -> Option<Reliability> {
    let predicted: Vec<f32> = held
        .point_sigmas(fisher, m, post)
        .iter()
        .zip(&held.noise_m)
        .map(|(&s, &n)| (0.5 * (s * s + n * n).log10()) as f32)
        .collect();
    let at = super::unconstrained_log_std(fisher.prior_sigma_m());
    reliability(&predicted, &held.residual_m, at, 10)
}

/// The AUSE of the held-out residuals ranked by one read-out's point σ (with each ray's spread): how well σ
/// orders the error where there is no ground truth (`None` without returns).
pub fn held_out_ause(
    fisher: &Fisher,
    m: Modality,
    post: Posterior,
    held: &HeldOutReturns,
) -> Option<f64> {
    let sigma: Vec<f32> = held
        .point_sigmas(fisher, m, post)
        .iter()
        .map(|s| s.log10() as f32)
        .collect();
    super::sparsify::sparsification(&held.residual_m, &sigma).map(|s| s.ause)
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
        held.spread_m.push(r.depth_spread as f64 / scale);
    }
    Ok(held)
}

/// Fraction of the held-out returns whose residual lies within `within`·√(σ² + noise²), σ the point's:
/// the read-out `log_std` (log10 metres) at each with its ray's spread times `a`.
pub fn coverage(held: &HeldOutReturns, log_std: &[f32], a: f64, within: f64) -> f64 {
    let n = held.residual_m.len();
    if n == 0 {
        return f64::NAN;
    }
    let hit = (0..n)
        .filter(|&i| {
            let s = held.sigma_m(i, log_std[i], a);
            let bound = within * (s * s + held.noise_m[i] * held.noise_m[i]).sqrt();
            held.residual_m[i] <= bound
        })
        .count();
    hit as f64 / n as f64
}

/// Fraction of a Gaussian within ±2σ.
pub const TWO_SIGMA: f64 = 0.954_499_736;

/// One held-out return's read-out as a function of k: its cell's vertex informations (scene units⁻²)
/// and normalised squared trilinear weights ([`Fisher::log_std`]'s rule).
struct ReturnReadOut {
    info: [f64; 8],
    weight: [f64; 8],
}

/// What one read-out's fit sees of the held-out returns.
struct FitData<'a> {
    held: &'a HeldOutReturns,
    points: Vec<ReturnReadOut>,
    prior: f64,
    scale: f64,
}

impl FitData<'_> {
    fn new<'a>(fisher: &Fisher, m: Modality, held: &'a HeldOutReturns) -> FitData<'a> {
        use crate::field::encoding::contract_unit;
        let grid = fisher.grid();
        let points = held
            .points
            .iter()
            .map(|&p| {
                let (idx, w) = grid.corners(contract_unit(p));
                let wsum: f64 = w.iter().map(|&b| (b as f64).powi(2)).sum();
                ReturnReadOut {
                    info: idx.map(|v| fisher.information(m, v)),
                    weight: w.map(|b| (b as f64).powi(2) / wsum),
                }
            })
            .collect();
        FitData {
            held,
            points,
            prior: fisher.prior,
            scale: fisher.frame.scale,
        }
    }

    /// Coverage at `within`σ under factors k (on the Laplace σ) and a (on the spread).
    fn coverage(&self, k: f64, a: f64, within: f64) -> f64 {
        let n = self.points.len();
        if n == 0 {
            return f64::NAN;
        }
        let held = self.held;
        let hit = self
            .points
            .iter()
            .enumerate()
            .filter(|(i, p)| {
                let var: f64 = (0..8)
                    .map(|j| p.weight[j] / (p.info[j] / (k * k) + self.prior))
                    .sum();
                let sigma2 = var / (self.scale * self.scale);
                let spread = a * held.spread_m.get(*i).copied().unwrap_or(0.0);
                let noise = held.noise_m[*i];
                held.residual_m[*i] <= within * (sigma2 + spread * spread + noise * noise).sqrt()
            })
            .count();
        hit as f64 / n as f64
    }

    /// The smallest k (bisection on log k over 10⁻³…10⁸) whose 1σ covers [`ONE_SIGMA`] of the returns
    /// given a, and the coverage reached.
    fn fit_k(&self, a: f64) -> (f64, f64) {
        let (mut lo, mut hi) = (-3.0f64, 8.0f64);
        let at = |log_k: f64| self.coverage(10f64.powf(log_k), a, 1.0);
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
}

/// The factor k of one read-out with the spread left out (a = 0): the smallest k whose 1σ covers
/// [`ONE_SIGMA`] of the held-out returns, and the coverage it reached.
pub fn fit_factor(fisher: &Fisher, m: Modality, held: &HeldOutReturns) -> (f64, f64) {
    FitData::new(fisher, m, held).fit_k(0.0)
}

/// Both factors of one read-out: for each a on a log grid (0.01…3.2, 0.05 decades apart; and a = 0), the k that makes 1σ cover
/// [`ONE_SIGMA`] of the held-out returns; of those, the pair whose 2σ covers closest to [`TWO_SIGMA`]
/// (a Gaussian's two quantiles: the 1σ condition alone leaves a free). Returns (k, a, 1σ coverage).
/// Where the returns carry no spread every a is the same and a = 0 is kept.
pub fn fit_read_out(fisher: &Fisher, m: Modality, held: &HeldOutReturns) -> (f64, f64, f64) {
    let data = FitData::new(fisher, m, held);
    let candidates =
        std::iter::once(0.0).chain((0..=50).map(|i| 10f64.powf(-2.0 + 0.05 * i as f64)));
    let mut best = (f64::INFINITY, 1.0, 0.0, f64::NAN);
    for a in candidates {
        let (k, one) = data.fit_k(a);
        let two = data.coverage(k, a, 2.0);
        let miss = 2.0 * (one - ONE_SIGMA).abs() + (two - TWO_SIGMA).abs();
        if miss < best.0 - 1e-9 {
            best = (miss, k, a, one);
        }
    }
    (best.1, best.2, best.3)
}

/// Fits every read-out's factors on `held` (a Fisher without lidar information keeps its depth read-out
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
        spread: [0.0; 3],
    };
    let has_depth = fisher.depth.iter().any(|&h| h > 0.0);
    for m in Modality::ALL {
        if m == Modality::Depth && !has_depth {
            continue;
        }
        let (k, a, cov) = fit_read_out(fisher, m, held);
        c.factor[m.index()] = k;
        c.spread[m.index()] = a;
        c.coverage[m.index()] = cov;
    }
    fisher.calibration = c;
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::train::data::SceneFrame;
    use crate::uncertainty::PerturbationGrid;
    use rand::Rng;

    /// A Fisher whose information is uniform over a 4-cell grid (colour 10⁶, depth 4·10⁶, unit noise
    /// and scale), so every read-out is one σ everywhere.
    fn uniform_fisher() -> Fisher {
        let cells = 4;
        let n = PerturbationGrid { cells }.vertices();
        Fisher {
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
        }
    }

    /// A standard normal draw (Box–Muller).
    fn gaussian(rng: &mut impl Rng) -> f64 {
        let (u, v): (f64, f64) = (rng.random::<f64>().max(1e-12), rng.random());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }

    /// Residuals that scale with each return's ray spread (σ = 0.3·s, s from 1 cm to 1 m) and a field
    /// whose Laplace σ is far smaller: the fit must put the spread's factor near 0.3, and the calibrated
    /// σ then covers 68 % and 95 % — where k alone (a = 0) cannot reach 2σ's share.
    #[test]
    fn the_fit_weighs_the_ray_spread_when_the_residuals_follow_it() {
        let fisher = uniform_fisher();
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(5);
        let mut held = HeldOutReturns::default();
        for _ in 0..20_000 {
            let g = gaussian(&mut rng);
            let spread = 10f64.powf(rng.random_range(-2.0..0.0));
            held.points.push([0.1, 0.2, 0.3]);
            held.residual_m.push((g * 0.3 * spread).abs());
            held.noise_m.push(0.0);
            held.spread_m.push(spread);
        }
        let mut f = fisher.clone();
        calibrate(&mut f, &held);
        for m in Modality::ALL {
            let a = f.calibration.spread[m.index()];
            assert!((a / 0.3 - 1.0).abs() < 0.2, "{}: a = {a}", m.name());
            let ls = f.read_out_scene(m, Posterior::Calibrated, &held.points);
            let one = coverage(&held, &ls, a, 1.0);
            let two = coverage(&held, &ls, a, 2.0);
            assert!((one - ONE_SIGMA).abs() < 0.02, "1σ {one}");
            assert!((two - TWO_SIGMA).abs() < 0.02, "2σ {two}");
        }
        // k alone: 1σ is met only by a σ that is the same everywhere, too wide for small spreads and
        // too narrow for large ones.
        let (k, one) = fit_factor(&fisher, Modality::Combined, &held);
        let mut g = fisher.clone();
        g.calibration.factor = [k; 3];
        g.calibration.returns = 1;
        let ls = g.read_out_scene(Modality::Combined, Posterior::Calibrated, &held.points);
        assert!((one - ONE_SIGMA).abs() < 0.01);
        let two = coverage(&held, &ls, 0.0, 2.0);
        assert!(two < 0.85, "2σ with k alone {two}");
    }

    /// A uniform Fisher ([`uniform_fisher`]); residuals drawn from a known Gaussian: the fit must find the
    /// k that makes σ that Gaussian's.
    #[test]
    fn the_fit_recovers_the_scale_of_gaussian_residuals() {
        let fisher = uniform_fisher();
        // Raw combined σ = 1/√(5e6 + 1) ≈ 0.447 mm; the residuals' σ is 5 cm with 1 cm of noise.
        let true_sigma = 0.05f64;
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(3);
        let mut held = HeldOutReturns::default();
        for _ in 0..20_000 {
            let g = gaussian(&mut rng);
            let noise = gaussian(&mut rng);
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
                0.0,
                2.0,
            );
            assert!((two - 0.9545).abs() < 0.01, "2σ coverage {two}");
        }
        // Raw is ~100x overconfident here: its coverage is far below 1σ's.
        let raw = fisher.read_out_scene(Modality::Combined, Posterior::Raw, &held.points);
        assert!(coverage(&held, &raw, 1.0, 1.0) < 0.3);
        // No spread on the returns: a stays 0 (nothing to fit it on).
        assert_eq!(f.calibration.spread, [0.0; 3]);
        // No returns: uncalibrated.
        let mut g = fisher.clone();
        calibrate(&mut g, &HeldOutReturns::default());
        assert!(!g.calibration.is_calibrated());
    }
}
