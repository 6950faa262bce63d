//! Instant-NGP's alternative to proposal networks, kept for the comparison issue 4 asks to record: a coarse
//! grid over the contracted scene holding a decaying maximum of the field's density per cell; a ray's final
//! samples are drawn over the candidate bins whose cell is occupied (density above a threshold). There is
//! no network to train and no interlevel loss, but the grid must be refreshed from the field.
//!
//! The product samples with proposal networks (`silvr bench-sampler` measured them ahead on the ci world,
//! see BENCHMARKS.md); this CPU path exists to measure that.

use rand::Rng;

use super::{pdf_resample, Spacing};
use crate::field::encoding::contract_unit;

/// Density grid over the unit cube of the contracted scene (`field::encoding::contract_unit`).
#[derive(Clone, Debug)]
pub struct OccupancyGrid {
    pub res: usize,
    /// Decaying maximum of the field's density per cell (scene units⁻¹).
    pub density: Vec<f32>,
    /// A cell is occupied when its density exceeds this (or the grid's mean, if lower).
    pub threshold: f32,
}

impl OccupancyGrid {
    /// Every cell starts occupied (density = ∞), so the first steps sample like uniform sampling.
    /// The threshold is Instant-NGP's: opacity 0.01 over its smallest march step, √3/1024 of the unit
    /// cube (the inner region [-1, 1]³ in scene units fills the middle half of the cube, so 4√3/1024
    /// scene units there).
    pub fn new(res: usize) -> Self {
        let min_step = 4.0 * 3f32.sqrt() / 1024.0;
        OccupancyGrid {
            res,
            density: vec![f32::INFINITY; res * res * res],
            threshold: 0.01 / min_step,
        }
    }

    /// The cell holding a unit-cube point.
    pub fn cell(&self, unit: [f32; 3]) -> usize {
        let r = self.res;
        let c = unit.map(|u| ((u * r as f32) as isize).clamp(0, r as isize - 1) as usize);
        (c[2] * r + c[1]) * r + c[0]
    }

    /// The density level above which a cell counts as occupied now.
    pub fn level(&self) -> f32 {
        let (sum, n) = self
            .density
            .iter()
            .filter(|d| d.is_finite())
            .fold((0.0f64, 0usize), |(s, n), &d| (s + d as f64, n + 1));
        if n == 0 {
            return self.threshold;
        }
        self.threshold.min((sum / n as f64) as f32)
    }

    /// Fraction of cells occupied.
    pub fn occupied_fraction(&self) -> f64 {
        let l = self.level();
        self.density.iter().filter(|&&d| d > l).count() as f64 / self.density.len() as f64
    }

    /// One random point inside every cell (unit coordinates), for [`OccupancyGrid::update`].
    pub fn cell_points(&self, rng: &mut impl Rng) -> Vec<[f32; 3]> {
        let r = self.res;
        let inv = 1.0 / r as f32;
        (0..r * r * r)
            .map(|i| {
                let c = [i % r, (i / r) % r, i / (r * r)];
                c.map(|k| (k as f32 + rng.random::<f32>()) * inv)
            })
            .collect()
    }

    /// Instant-NGP's update: each cell's value decays by `decay` and takes the maximum with the density
    /// just evaluated at a point inside it (`fresh[i]` for cell i, as from [`OccupancyGrid::cell_points`]).
    pub fn update(&mut self, fresh: &[f32], decay: f32) {
        for (d, &f) in self.density.iter_mut().zip(fresh) {
            let f = if f.is_finite() { f } else { 0.0 };
            *d = if d.is_finite() {
                (*d * decay).max(f)
            } else {
                f
            };
        }
    }

    /// A ray's final edges (`out.len()` of them, normalised s): `candidates` uniform bins in s, weight 1 where
    /// the bin's midpoint lies in an occupied cell and 0 elsewhere, resampled like a proposal level (with
    /// `padding`, so a ray through empty space still gets samples).
    #[allow(clippy::too_many_arguments)]
    pub fn ray_edges(
        &self,
        level: f32,
        origin: [f32; 3],
        dir: [f32; 3],
        spacing: &Spacing,
        candidates: usize,
        padding: f32,
        jitter: Option<f32>,
        out: &mut [f32],
    ) {
        let edges: Vec<f32> = (0..=candidates)
            .map(|k| k as f32 / candidates as f32)
            .collect();
        let weights: Vec<f32> = (0..candidates)
            .map(|k| {
                let t = spacing.to_t((k as f32 + 0.5) / candidates as f32);
                let p = [0, 1, 2].map(|a| origin[a] + dir[a] * t);
                if self.density[self.cell(contract_unit(p))] > level {
                    1.0
                } else {
                    0.0
                }
            })
            .collect();
        let mut cdf = vec![0.0f32; candidates + 1];
        pdf_resample(&edges, &weights, 1.0, padding, jitter, &mut cdf, out);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn a_new_grid_is_all_occupied_and_samples_uniformly() {
        let g = OccupancyGrid::new(8);
        assert_eq!(g.occupied_fraction(), 1.0);
        let sp = Spacing::new(0.05, 1000.0);
        let mut out = vec![f32::NAN; 9];
        g.ray_edges(
            g.level(),
            [0.0; 3],
            [0.0, 0.0, 1.0],
            &sp,
            64,
            0.01,
            None,
            &mut out,
        );
        // Evenly spread as pdf_resample spreads a uniform PDF (nerfstudio's (k + ½) / n positions).
        for (k, e) in out.iter().enumerate() {
            assert!((e - (k as f32 + 0.5) / 9.0).abs() < 0.01, "{out:?}");
        }
    }

    #[test]
    fn samples_gather_in_the_occupied_cell_the_ray_crosses() {
        let mut g = OccupancyGrid::new(16);
        let mut fresh = vec![0.0f32; 16 * 16 * 16];
        // A wall at scene z ∈ [0.5, 0.75) (unit z = (z + 2) / 4 → cells 10..11 of 16), x, y near 0.
        let wall = g.cell(contract_unit([0.0, 0.0, 0.6]));
        fresh[wall] = 100.0;
        g.update(&fresh, 0.95);
        assert!(g.occupied_fraction() < 0.01);
        let sp = Spacing::new(0.05, 1000.0);
        let mut out = vec![f32::NAN; 25];
        g.ray_edges(
            g.level(),
            [0.0; 3],
            [0.0, 0.0, 1.0],
            &sp,
            256,
            0.01,
            Some(0.3),
            &mut out,
        );
        let inside = out
            .windows(2)
            .filter(|w| {
                let t = sp.to_t(0.5 * (w[0] + w[1]));
                (0.5..0.75).contains(&t)
            })
            .count();
        assert!(inside >= 18, "{inside} of 24 bins in the wall: {out:?}");
    }

    #[test]
    fn update_decays_and_keeps_the_maximum() {
        let mut g = OccupancyGrid::new(2);
        g.update(&[1.0, 2.0, 0.0, 0.0, 5.0, 0.0, 0.0, f32::NAN], 0.5);
        g.update(&[0.1, 3.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], 0.5);
        assert_eq!(&g.density[..5], &[0.5, 3.0, 0.0, 0.0, 2.5]);
        assert_eq!(g.density[7], 0.0);
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(1);
        let pts = g.cell_points(&mut rng);
        for (i, p) in pts.iter().enumerate() {
            assert_eq!(g.cell(*p), i);
        }
    }
}
