//! Sparsification curves and AUSE (BayesRays' `metrics/ause.py`, from CF-NeRF), with the point-to-ground-
//! truth distance as the error: remove the most uncertain fraction of points and watch the mean error of
//! the rest fall; the oracle removes the largest errors first. A good uncertainty follows the oracle.

use rand::seq::SliceRandom;
use rand::SeedableRng;
use serde::Serialize;

/// Removal fractions 0, 0.01, …, 0.99 (BayesRays).
pub const STEPS: usize = 100;

/// One modality's curves, each normalised by the largest value of the uncertainty and oracle curves.
#[derive(Clone, Debug, Serialize)]
pub struct Sparsification {
    pub fractions: Vec<f64>,
    pub oracle: Vec<f64>,
    pub uncertainty: Vec<f64>,
    /// Area between the uncertainty curve and the oracle (trapezoid rule over the fractions).
    pub ause: f64,
}

/// Mean error of the points left after removing, in `order`, the first `r` of them, for every fraction.
fn curve(errors: &[f64], order: &[usize]) -> Vec<f64> {
    let n = order.len();
    // Suffix sums: the mean of the kept (last n − k) points.
    let mut suffix = vec![0.0f64; n + 1];
    for i in (0..n).rev() {
        suffix[i] = suffix[i + 1] + errors[order[i]];
    }
    (0..STEPS)
        .map(|s| {
            let k = (s * n) / STEPS;
            let kept = n - k;
            if kept == 0 {
                0.0
            } else {
                suffix[k] / kept as f64
            }
        })
        .collect()
}

fn trapezoid(x: &[f64], y: &[f64]) -> f64 {
    x.windows(2)
        .zip(y.windows(2))
        .map(|(a, b)| (a[1] - a[0]) * 0.5 * (b[0] + b[1]))
        .sum()
}

fn normalised_pair(oracle: Vec<f64>, other: Vec<f64>) -> (Vec<f64>, Vec<f64>) {
    let m = oracle
        .iter()
        .chain(&other)
        .cloned()
        .fold(0.0f64, f64::max)
        .max(f64::MIN_POSITIVE);
    (
        oracle.into_iter().map(|v| v / m).collect(),
        other.into_iter().map(|v| v / m).collect(),
    )
}

/// Orders points by decreasing score (NaN scores count as most uncertain), ties by index.
fn descending(score: impl Fn(usize) -> f64, n: usize) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..n).collect();
    idx.sort_by(|&a, &b| {
        let (sa, sb) = (score(a), score(b));
        let key = |s: f64| if s.is_nan() { f64::INFINITY } else { s };
        key(sb).total_cmp(&key(sa)).then(a.cmp(&b))
    });
    idx
}

/// The sparsification of `errors` by `uncertainty` (higher = less certain), or `None` for no points.
pub fn sparsification(errors: &[f64], uncertainty: &[f32]) -> Option<Sparsification> {
    let n = errors.len().min(uncertainty.len());
    if n == 0 {
        return None;
    }
    let fractions: Vec<f64> = (0..STEPS).map(|s| s as f64 / STEPS as f64).collect();
    let oracle = curve(errors, &descending(|i| errors[i], n));
    let unc = curve(errors, &descending(|i| uncertainty[i] as f64, n));
    let (oracle, unc) = normalised_pair(oracle, unc);
    let diff: Vec<f64> = unc.iter().zip(&oracle).map(|(u, o)| u - o).collect();
    let ause = trapezoid(&fractions, &diff);
    Some(Sparsification {
        fractions,
        oracle,
        uncertainty: unc,
        ause,
    })
}

/// The AUSE of a random ordering (the mean over `trials` seeded shuffles): what "no information" scores.
pub fn random_ause(errors: &[f64], trials: usize, seed: u64) -> f64 {
    let n = errors.len();
    if n == 0 || trials == 0 {
        return 0.0;
    }
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed);
    let fractions: Vec<f64> = (0..STEPS).map(|s| s as f64 / STEPS as f64).collect();
    let oracle = curve(errors, &descending(|i| errors[i], n));
    let mut total = 0.0;
    for _ in 0..trials {
        let mut order: Vec<usize> = (0..n).collect();
        order.shuffle(&mut rng);
        let (o, r) = normalised_pair(oracle.clone(), curve(errors, &order));
        let diff: Vec<f64> = r.iter().zip(&o).map(|(a, b)| a - b).collect();
        total += trapezoid(&fractions, &diff);
    }
    total / trials as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_oracle_ordering_has_zero_ause_and_a_reversed_one_is_worst() {
        let errors: Vec<f64> = (0..1000).map(|i| (i as f64 * 0.37).sin().abs()).collect();
        let perfect: Vec<f32> = errors.iter().map(|&e| e as f32).collect();
        let s = sparsification(&errors, &perfect).unwrap();
        assert!(s.ause.abs() < 1e-9, "{}", s.ause);
        assert!((s.oracle[0] - s.uncertainty[0]).abs() < 1e-12);
        // The oracle curve falls monotonically.
        assert!(s.oracle.windows(2).all(|w| w[1] <= w[0] + 1e-12));
        let reversed: Vec<f32> = perfect.iter().map(|v| -v).collect();
        let worst = sparsification(&errors, &reversed).unwrap();
        let random = random_ause(&errors, 5, 1);
        assert!(random > 0.05, "{random}");
        assert!(worst.ause > random, "{} vs {random}", worst.ause);
        // A noisy but informative uncertainty lands in between.
        let noisy: Vec<f32> = errors
            .iter()
            .enumerate()
            .map(|(i, &e)| (e + 0.3 * ((i * 7919 % 1000) as f64 / 1000.0)) as f32)
            .collect();
        let mid = sparsification(&errors, &noisy).unwrap();
        assert!(
            mid.ause > 0.0 && mid.ause < random,
            "{} vs {random}",
            mid.ause
        );
        assert_eq!(s.fractions.len(), STEPS);
        assert!(sparsification(&[], &[]).is_none());
    }
}
