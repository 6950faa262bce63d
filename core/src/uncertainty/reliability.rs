//! Is σ the error it claims? Points binned by predicted σ, the RMS error observed in each bin against the
//! RMS σ predicted there (the identity line is perfect calibration), the fraction of points whose error
//! lies within 1σ and 2σ (68.3 % and 95.4 % for a Gaussian error), and the expected calibration error:
//! the mean gap between each central interval's nominal and observed coverage (Kuleshov et al. 2018),
//! over the levels 10 … 90 %.
//!
//! `error` is a point's distance to the ground-truth surface (`GroundTruth::surface_distances`; on
//! real data the held-out lidar returns' point-to-plane residuals): for a point off a surface, its offset
//! along the normal, one Gaussian axis, so |e| ≤ z·σ has the two-sided coverage of z.

use serde::Serialize;

/// Central-interval levels of the calibration error and their two-sided Gaussian z (Φ⁻¹((1 + p) / 2)).
const LEVELS: [(f64, f64); 9] = [
    (0.1, 0.125_661),
    (0.2, 0.253_347),
    (0.3, 0.385_320),
    (0.4, 0.524_401),
    (0.5, 0.674_490),
    (0.6, 0.841_621),
    (0.7, 1.036_433),
    (0.8, 1.281_552),
    (0.9, 1.644_854),
];

/// One bin of points of similar σ.
#[derive(Clone, Debug, Serialize)]
pub struct Bin {
    pub points: usize,
    /// σ range of the bin (metres).
    pub sigma_min_m: f64,
    pub sigma_max_m: f64,
    /// RMS predicted σ and RMS observed error (metres).
    pub rms_sigma_m: f64,
    pub rms_error_m: f64,
    /// Fraction of the bin's points with error ≤ σ.
    pub coverage_1sigma: f64,
}

/// The reliability of one read-out on one evaluated cloud.
#[derive(Clone, Debug, Serialize)]
pub struct Reliability {
    /// Points with a finite σ and error.
    pub points: usize,
    /// Of those, how many read the prior ("unconstrained": σ ≥ σ_p / √2); they are in every figure.
    pub unconstrained: usize,
    pub median_sigma_m: f64,
    pub median_error_m: f64,
    /// median σ / median error (1 = calibrated medians; the goal is within 2x).
    pub median_ratio: f64,
    pub coverage_1sigma: f64,
    pub coverage_2sigma: f64,
    /// Mean |observed − nominal| coverage over the central intervals 10 … 90 %.
    pub ece: f64,
    /// Equal-count bins, ascending σ.
    pub bins: Vec<Bin>,
}

/// The reliability of `log_std` (log10 σ in metres per point) against `errors` (metres), in `bins`
/// equal-count bins; `unconstrained_at` is the log-std from which a point reads the prior. `None` when
/// no point has both a finite σ and error.
pub fn reliability(
    log_std: &[f32],
    errors: &[f64],
    unconstrained_at: f32,
    bins: usize,
) -> Option<Reliability> {
    let mut pts: Vec<(f64, f64)> = log_std
        .iter()
        .zip(errors)
        .filter(|(l, e)| l.is_finite() && e.is_finite())
        .map(|(&l, &e)| (10f64.powf(l as f64), e.abs()))
        .collect();
    if pts.is_empty() {
        return None;
    }
    let n = pts.len();
    let unconstrained_sigma = 10f64.powf(unconstrained_at as f64);
    let unconstrained = pts.iter().filter(|p| p.0 >= unconstrained_sigma).count();
    let covered = |z: f64, p: &[(f64, f64)]| {
        p.iter().filter(|(s, e)| *e <= z * s).count() as f64 / p.len() as f64
    };
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        let m = v.len() / 2;
        if v.len() % 2 == 1 {
            v[m]
        } else {
            0.5 * (v[m - 1] + v[m])
        }
    };
    let median_sigma_m = median(pts.iter().map(|p| p.0).collect());
    let median_error_m = median(pts.iter().map(|p| p.1).collect());
    let ece = LEVELS
        .iter()
        .map(|&(level, z)| (covered(z, &pts) - level).abs())
        .sum::<f64>()
        / LEVELS.len() as f64;
    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
    let nb = bins.clamp(1, n);
    let rms = |v: &mut dyn Iterator<Item = f64>, len: usize| {
        (v.map(|x| x * x).sum::<f64>() / len as f64).sqrt()
    };
    let bins = (0..nb)
        .map(|b| {
            let part = &pts[b * n / nb..(b + 1) * n / nb];
            Bin {
                points: part.len(),
                sigma_min_m: part[0].0,
                sigma_max_m: part[part.len() - 1].0,
                rms_sigma_m: rms(&mut part.iter().map(|p| p.0), part.len()),
                rms_error_m: rms(&mut part.iter().map(|p| p.1), part.len()),
                coverage_1sigma: covered(1.0, part),
            }
        })
        .collect();
    Some(Reliability {
        points: n,
        unconstrained,
        median_sigma_m,
        median_error_m,
        median_ratio: median_sigma_m / median_error_m.max(1e-12),
        coverage_1sigma: covered(1.0, &pts),
        coverage_2sigma: covered(2.0, &pts),
        ece,
        bins,
    })
}

/// σ in the unit that reads best: mm below 1 cm, cm below 1 m, else m (what the CLI and the studio print).
pub fn format_metres(m: f64) -> String {
    if !m.is_finite() {
        return format!("{m}");
    }
    let a = m.abs();
    if a < 0.01 {
        format!("{:.2} mm", m * 1e3)
    } else if a < 1.0 {
        format!("{:.2} cm", m * 1e2)
    } else {
        format!("{:.2} m", m)
    }
}

impl Reliability {
    /// A printed table: one line per bin, then the totals.
    pub fn table(&self, title: &str) -> String {
        let mut s = format!(
            "{title}: {} points ({} unconstrained)\n  {:>22}  {:>10}  {:>10}  {:>8}\n",
            self.points, self.unconstrained, "σ range", "RMS σ", "RMS error", "≤ 1σ"
        );
        for b in &self.bins {
            s.push_str(&format!(
                "  {:>10} – {:>9}  {:>10}  {:>10}  {:>7.1} %\n",
                format_metres(b.sigma_min_m),
                format_metres(b.sigma_max_m),
                format_metres(b.rms_sigma_m),
                format_metres(b.rms_error_m),
                100.0 * b.coverage_1sigma
            ));
        }
        s.push_str(&format!(
            "  median σ {} vs median error {} ({:.2}x); coverage 1σ {:.1} %, 2σ {:.1} %; ECE {:.3}\n",
            format_metres(self.median_sigma_m),
            format_metres(self.median_error_m),
            self.median_ratio,
            100.0 * self.coverage_1sigma,
            100.0 * self.coverage_2sigma,
            self.ece
        ));
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn gauss(rng: &mut impl Rng) -> f64 {
        let (u, v): (f64, f64) = (rng.random::<f64>().max(1e-12), rng.random());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }

    /// Errors drawn with exactly the predicted σ (which spans two decades) are calibrated; the same
    /// errors against σ 4x too small are not.
    #[test]
    fn calibrated_errors_read_as_calibrated() {
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(5);
        let n = 50_000;
        let sigma: Vec<f64> = (0..n)
            .map(|i| 10f64.powf(-3.0 + 2.0 * i as f64 / n as f64))
            .collect();
        let errors: Vec<f64> = sigma.iter().map(|s| (s * gauss(&mut rng)).abs()).collect();
        let ls: Vec<f32> = sigma.iter().map(|s| s.log10() as f32).collect();
        let r = reliability(&ls, &errors, 0.0, 10).unwrap();
        assert!(
            (r.coverage_1sigma - 0.6827).abs() < 0.01,
            "{}",
            r.coverage_1sigma
        );
        assert!(
            (r.coverage_2sigma - 0.9545).abs() < 0.01,
            "{}",
            r.coverage_2sigma
        );
        assert!(r.ece < 0.01, "{}", r.ece);
        assert_eq!(r.bins.len(), 10);
        for b in &r.bins {
            assert!((b.rms_error_m / b.rms_sigma_m - 1.0).abs() < 0.1, "{b:?}");
        }
        // median |N(0, σ²)| = 0.674σ: the ratio of medians is 1.48 for one σ, and grows when σ spreads
        // (1.8 over these two decades), inside the 2x a calibrated read-out is held to.
        assert!((1.3..2.0).contains(&r.median_ratio), "{}", r.median_ratio);
        assert_eq!(r.unconstrained, 0);

        let over: Vec<f32> = ls.iter().map(|l| l - 4f32.log10()).collect();
        let o = reliability(&over, &errors, 0.0, 10).unwrap();
        assert!(o.coverage_1sigma < 0.3 && o.ece > 0.2, "{o:?}");
        // Points at or above the prior's log-std are counted as unconstrained.
        let u = reliability(&ls, &errors, -1.5, 10).unwrap();
        assert_eq!(u.unconstrained, n / 4);
        assert!(reliability(&[f32::NAN], &[1.0], 0.0, 10).is_none());
    }

    #[test]
    fn metres_print_in_the_unit_that_reads_best() {
        assert_eq!(format_metres(0.0042), "4.20 mm");
        assert_eq!(format_metres(0.043), "4.30 cm");
        assert_eq!(format_metres(2.5), "2.50 m");
    }
}
