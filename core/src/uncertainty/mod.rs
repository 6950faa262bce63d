//! Epistemic uncertainty per sensor (paper §Epistemic uncertainty): BayesRays' perturbation field with a
//! Laplace approximation, extended to lidar depth as SiLVR does.
//!
//! A regular grid of 3-D offsets θ over the contracted [0, 1]³ displaces the world-space sample positions
//! of the frozen field (trilinearly); θ = 0, the grid exists only to take derivatives. For each ray the
//! Jacobian of the rendered colour (3 channels) and, on lidar rays, of the expected depth with respect to
//! every vertex's offset is summed over the ray's samples and then squared: the diagonal of the Fisher
//! (Gauss–Newton) matrix, accumulated over many training rays separately for colour and depth.
//! Var_v = 1 / (H_v / N + λ) is the posterior variance of vertex v's offset; a point's uncertainty is the
//! log10 standard deviation interpolated from its cell's vertices (BayesRays' squared-weight rule).
//!
//! * [`cpu`]: the referee: per-sample Jacobians from the CPU field, the Fisher by a per-ray map.
//! * [`gpu`]: the WGSL pass (`shaders/uncertainty.wgsl` + the trainer's kernels), the product.
//! * [`sparsify`]: sparsification curves, AUSE and the error-vs-uncertainty plots.

pub mod cpu;
pub mod filter;
pub mod gpu;
pub mod sparsify;

use serde::{Deserialize, Serialize};

use crate::gpu::GpuError;
use crate::train::cpu::TrainRay;
use crate::train::data::TrainData;
use crate::train::{Engine, Mode, Trainer};

/// How the uncertainty pass runs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct UncertaintyConfig {
    /// Perturbation-grid cells per axis over the contracted cube (BayesRays: 2^8); 0 = from the ray
    /// budget ([`Self::grid_cells`]).
    pub cells: u32,
    /// Batches of training rays accumulated (BayesRays: max(images, 1000)).
    pub batches: usize,
    pub rays_per_batch: usize,
    /// Prior precision λ; `None` = BayesRays' 1e-4 / L³.
    pub prior: Option<f64>,
    pub seed: u64,
}

impl Default for UncertaintyConfig {
    fn default() -> Self {
        UncertaintyConfig {
            cells: 0,
            batches: 1000,
            rays_per_batch: 4096,
            prior: None,
            seed: 7,
        }
    }
}

impl UncertaintyConfig {
    pub fn validate(&self) -> Result<(), GpuError> {
        if self.cells > 1024 {
            return Err(GpuError::InvalidInput(format!(
                "uncertainty: {} perturbation cells per axis (0 = auto, at most 1024)",
                self.cells
            )));
        }
        if self.batches == 0 || self.rays_per_batch == 0 {
            return Err(GpuError::InvalidInput(
                "uncertainty: batches and rays per batch must be positive".into(),
            ));
        }
        if let Some(l) = self.prior {
            if !(l.is_finite() && l > 0.0) {
                return Err(GpuError::InvalidInput(format!(
                    "uncertainty: prior precision {l} is not a positive number"
                )));
            }
        }
        Ok(())
    }

    /// Cells per axis: as configured, or from the ray budget. Surfaces are 2-D, so the cells they cross
    /// grow as L²; L = 2^⌊log2 √(2R)⌋ (R colour rays sampled, at most 256, BayesRays' size) keeps about two
    /// sampled rays per surface cell: 256 for BayesRays' 1000 × 4096 rays, 128 for the CPU demo's 8 × 1024.
    /// Finer grids with too few rays read the prior wherever no sampled ray passed.
    pub fn grid_cells(&self) -> u32 {
        if self.cells > 0 {
            return self.cells;
        }
        let r = (self.batches as f64 * self.rays_per_batch as f64 * 2.0).sqrt();
        let l = 2f64.powi(r.log2().floor() as i32);
        l.clamp(8.0, 256.0) as u32
    }

    /// λ: as configured, or BayesRays' 1e-4 / L³.
    pub fn prior_precision(&self) -> f64 {
        self.prior
            .unwrap_or(1e-4 / (self.grid_cells() as f64).powi(3))
    }
}

/// The perturbation grid's geometry: `cells` cells per axis over [0, 1]³, (cells + 1)³ vertices indexed
/// (ix·(L+1) + iy)·(L+1) + iz (BayesRays strides by L and aliases the last layer; we do not).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PerturbationGrid {
    pub cells: u32,
}

impl PerturbationGrid {
    pub fn vertices(&self) -> usize {
        (self.cells as usize + 1).pow(3)
    }

    /// The cell containing a grid position (clamped to the cube) and the position inside it.
    pub fn locate(&self, unit: [f32; 3]) -> ([u32; 3], [f32; 3]) {
        let l = self.cells;
        let mut cell = [0u32; 3];
        let mut frac = [0.0f32; 3];
        for k in 0..3 {
            let x = unit[k].clamp(0.0, 1.0) * l as f32;
            let c = (x.floor() as u32).min(l - 1);
            cell[k] = c;
            frac[k] = x - c as f32;
        }
        (cell, frac)
    }

    pub fn vertex(&self, v: [u32; 3]) -> usize {
        let s = self.cells as usize + 1;
        (v[0] as usize * s + v[1] as usize) * s + v[2] as usize
    }

    /// The 8 vertices of a position's cell (corner c has offset bits (c>>2, c>>1, c)&1) and their
    /// trilinear weights.
    pub fn corners(&self, unit: [f32; 3]) -> ([usize; 8], [f32; 8]) {
        let (cell, t) = self.locate(unit);
        let mut idx = [0usize; 8];
        let mut w = [0.0f32; 8];
        for c in 0..8 {
            let b = [(c >> 2) & 1, (c >> 1) & 1, c & 1].map(|v| v as u32);
            idx[c] = self.vertex([cell[0] + b[0], cell[1] + b[1], cell[2] + b[2]]);
            w[c] = (0..3)
                .map(|k| if b[k] == 1 { t[k] } else { 1.0 - t[k] })
                .product();
        }
        (idx, w)
    }
}

/// Fisher diagonals of one trained field (the trace of each vertex's 3×3 block), with how many rays
/// built them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Fisher {
    pub cells: u32,
    /// Σ over training rays and colour channels of ‖∂C/∂θ_v‖² (estimated from a sample).
    pub colour: Vec<f32>,
    /// Σ over lidar rays of ‖∂E/∂θ_v‖² (E the expected depth, scene units; estimated from a sample).
    pub depth: Vec<f32>,
    /// Training pixels (N of the Laplace normalisation) and lidar returns the diagonals stand for.
    pub rays: u64,
    pub lidar_rays: u64,
    pub prior: f64,
    /// Noise scales of the two sensors (colour in [0, 1] units, depth in scene units) that weigh them in
    /// the combined information H_c/σ_c² + H_d/σ_d².
    pub colour_sigma: f64,
    pub depth_sigma: f64,
}

/// Which Fisher a read-out uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Modality {
    Colour,
    Depth,
    Combined,
}

impl Modality {
    pub const ALL: [Modality; 3] = [Modality::Colour, Modality::Depth, Modality::Combined];

    pub fn name(&self) -> &'static str {
        match self {
            Modality::Colour => "colour",
            Modality::Depth => "depth",
            Modality::Combined => "combined",
        }
    }
}

impl Fisher {
    pub fn grid(&self) -> PerturbationGrid {
        PerturbationGrid { cells: self.cells }
    }

    /// Posterior variance of vertex v: 1 / (H_v / N + λ), each sensor's H divided by its noise variance.
    pub fn variance(&self, m: Modality, v: usize) -> f64 {
        let n = self.rays.max(1) as f64;
        let hc = self.colour[v] as f64 / (self.colour_sigma * self.colour_sigma);
        let hd = self.depth[v] as f64 / (self.depth_sigma * self.depth_sigma);
        let h = match m {
            Modality::Colour => hc,
            Modality::Depth => hd,
            Modality::Combined => hc + hd,
        };
        1.0 / (h / n + self.prior)
    }

    /// log10 of the posterior standard deviation at a grid position: BayesRays' read-out, the variances
    /// of the cell's vertices interpolated with normalised squared trilinear weights.
    pub fn log_std(&self, m: Modality, unit: [f32; 3]) -> f32 {
        let (idx, w) = self.grid().corners(unit);
        let wsum: f64 = w.iter().map(|&b| (b as f64) * (b as f64)).sum();
        let var: f64 = idx
            .iter()
            .zip(w)
            .map(|(&v, b)| (b as f64) * (b as f64) / wsum * self.variance(m, v))
            .sum();
        (var.sqrt() + 1e-12).log10() as f32
    }

    /// The read-out where no ray constrained the field: log10 sqrt(1/λ).
    pub fn prior_log_std(&self) -> f32 {
        (0.5 * (1.0 / self.prior).log10()) as f32
    }

    pub fn check(&self) -> Result<(), GpuError> {
        let n = PerturbationGrid { cells: self.cells }.vertices();
        if self.colour.len() != n || self.depth.len() != n {
            return Err(GpuError::InvalidInput(format!(
                "uncertainty grid: {} / {} values for {} vertices",
                self.colour.len(),
                self.depth.len(),
                n
            )));
        }
        if self
            .colour
            .iter()
            .chain(&self.depth)
            .any(|v| !(v.is_finite() && *v >= 0.0))
        {
            return Err(GpuError::InvalidInput(
                "uncertainty grid holds negative or non-finite information".into(),
            ));
        }
        Ok(())
    }
}

const MAGIC: &[u8; 8] = b"SILVRFI1";

impl Fisher {
    /// A compact little-endian file: magic, cells, rays, lidar rays, prior, σ_c, σ_d, then the colour and
    /// depth diagonals as f32 (the studio loads the same bytes).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(48 + 8 * self.colour.len());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&self.cells.to_le_bytes());
        out.extend_from_slice(&self.rays.to_le_bytes());
        out.extend_from_slice(&self.lidar_rays.to_le_bytes());
        for v in [self.prior, self.colour_sigma, self.depth_sigma] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for v in self.colour.iter().chain(&self.depth) {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out
    }

    /// Parses [`Self::to_bytes`]; `name` (the file) goes into errors.
    pub fn from_bytes(bytes: &[u8], name: &str) -> Result<Fisher, GpuError> {
        let bad = |m: &str| GpuError::InvalidInput(format!("{name}: {m}"));
        if bytes.len() < 52 || &bytes[..8] != MAGIC {
            return Err(bad(
                "not a SiLVR uncertainty file (bad magic or truncated header)",
            ));
        }
        let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
        let u64_at = |o: usize| u64::from_le_bytes(bytes[o..o + 8].try_into().expect("8 bytes"));
        let f64_at = |o: usize| f64::from_bits(u64_at(o));
        let cells = u32_at(8);
        if !(1..=1024).contains(&cells) {
            return Err(bad(&format!("{cells} cells per axis is out of range")));
        }
        let nv = PerturbationGrid { cells }.vertices();
        let want = 52 + 8 * nv;
        if bytes.len() != want {
            return Err(bad(&format!(
                "{} bytes, {want} expected for {cells}^3 cells",
                bytes.len()
            )));
        }
        let floats = |o: usize| -> Vec<f32> {
            bytes[o..o + 4 * nv]
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
                .collect()
        };
        let f = Fisher {
            cells,
            rays: u64_at(12),
            lidar_rays: u64_at(20),
            prior: f64_at(28),
            colour_sigma: f64_at(36),
            depth_sigma: f64_at(44),
            colour: floats(52),
            depth: floats(52 + 4 * nv),
        };
        if !(f.prior > 0.0 && f.colour_sigma > 0.0 && f.depth_sigma > 0.0) {
            return Err(bad("prior and noise scales must be positive"));
        }
        f.check().map_err(|e| bad(&e.to_string()))?;
        Ok(f)
    }
}

/// The derivative of the L∞ contraction + unit mapping (`encoding::contract_unit`) applied to a gradient
/// with respect to the grid position: dY/dx (world, scene units) from dY/du.
pub fn contraction_vjp(x: [f32; 3], d_unit: [f32; 3]) -> [f32; 3] {
    let ax = x.map(f32::abs);
    let m = ax[0].max(ax[1]).max(ax[2]);
    if !(m.is_finite()) || m <= 1.0 {
        return d_unit.map(|g| 0.25 * g);
    }
    // f(x) = k(m)·x, k = 2/m − 1/m², m = |x_a|.
    let k = 2.0 / m - 1.0 / (m * m);
    let dk = -2.0 / (m * m) + 2.0 / (m * m * m);
    let a = if ax[0] >= ax[1] && ax[0] >= ax[2] {
        0
    } else if ax[1] >= ax[2] {
        1
    } else {
        2
    };
    let gx: f32 = (0..3).map(|i| d_unit[i] * x[i]).sum();
    let mut out = d_unit.map(|g| 0.25 * k * g);
    out[a] += 0.25 * gx * dk * x[a].signum();
    out
}

/// Per-point uncertainty of a cloud in the scene frame: log10 std per modality, shifted to metres.
pub struct PointUncertainty {
    pub colour: Vec<f32>,
    pub depth: Vec<f32>,
    pub combined: Vec<f32>,
}

/// Reads the Fisher out at scene-frame points (`scale` = scene units per metre: log-std in metres).
pub fn read_out(fisher: &Fisher, scene_points: &[[f32; 3]], scale: f64) -> PointUncertainty {
    use crate::field::encoding::contract_unit;
    use rayon::prelude::*;
    let shift = scale.log10() as f32;
    let per = |m: Modality| -> Vec<f32> {
        scene_points
            .par_iter()
            .with_min_len(1024)
            .map(|&p| fisher.log_std(m, contract_unit(p)) - shift)
            .collect()
    };
    PointUncertainty {
        colour: per(Modality::Colour),
        depth: per(Modality::Depth),
        combined: per(Modality::Combined),
    }
}

/// Ray flag: the ray adds to the colour Fisher.
pub const COLOUR_RAY: u32 = 1;
/// Ray flag: the ray adds to the depth Fisher (it has a lidar return).
pub const DEPTH_RAY: u32 = 2;

/// Where the pass draws rays: every training pixel (colour) and every lidar pixel (depth), so that the
/// sparse lidar gets as many samples as the images; contributions are scaled back to the whole set.
pub struct RaySource {
    /// (image, pixel) of every training pixel with a lidar return (not sky).
    lidar_pixels: Vec<(usize, u32)>,
    /// Training pixels in all (N of the Laplace normalisation: rays the field was fitted to).
    pub pixels: u64,
    lidar: bool,
}

impl RaySource {
    /// `lidar`: whether the field was trained with lidar (a vision-only field has no depth information).
    pub fn new(data: &TrainData, lidar: bool) -> Self {
        let mut lidar_pixels = Vec::new();
        let mut pixels = 0u64;
        for &i in &data.train {
            let im = &data.images[i];
            pixels += im.width as u64 * im.height as u64;
            if lidar {
                for (p, &d) in im.depth.iter().enumerate() {
                    if d > 0 && d != crate::lidar::images::SKY_DEPTH {
                        lidar_pixels.push((i, p as u32));
                    }
                }
            }
        }
        RaySource {
            lidar_pixels,
            pixels,
            lidar,
        }
    }

    pub fn lidar_pixels(&self) -> u64 {
        self.lidar_pixels.len() as u64
    }

    /// One batch: `colour` rays uniform over the training pixels (flag [`COLOUR_RAY`]) and, for a field
    /// trained with lidar, `depth` rays uniform over the lidar pixels (flag [`DEPTH_RAY`]).
    pub fn batch(
        &self,
        data: &TrainData,
        seed: u64,
        colour: usize,
        depth: usize,
    ) -> (Vec<TrainRay>, Vec<u32>) {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed);
        let (mut rays, mut flags) = (Vec::new(), Vec::new());
        let mut push = |i: usize, x: u32, y: u32, flag: u32| {
            if let Some((o, d)) = data.ray(i, x, y) {
                rays.push(TrainRay {
                    origin: o,
                    dir: d,
                    appearance: data.images[i].appearance.unwrap_or(u32::MAX),
                });
                flags.push(flag);
                true
            } else {
                false
            }
        };
        let mut tries = 0;
        let mut got = 0;
        while got < colour && tries < colour * 20 && !data.train.is_empty() {
            tries += 1;
            let i = data.train[rng.random_range(0..data.train.len())];
            let im = &data.images[i];
            let (x, y) = (
                rng.random_range(0..im.width),
                rng.random_range(0..im.height),
            );
            got += push(i, x, y, COLOUR_RAY) as usize;
        }
        if self.lidar && !self.lidar_pixels.is_empty() {
            for _ in 0..depth {
                let (i, p) = self.lidar_pixels[rng.random_range(0..self.lidar_pixels.len())];
                let w = data.images[i].width;
                push(i, p % w, p / w, DEPTH_RAY);
            }
        }
        (rays, flags)
    }
}

/// The sensors' noise scales for the combined read-out, by rule rather than per-scene tuning: colour, the
/// trained field's own RMS colour residual over the last tenth of training (at least one 8-bit level);
/// depth, the DS-NeRF σ training ended with (the lidar noise the loss assumed), in scene units.
pub fn noise_scales(trainer: &Trainer) -> (f64, f64) {
    let h = &trainer.history;
    let tail = &h[h.len() - h.len().div_ceil(10)..];
    let mse = if tail.is_empty() {
        0.0
    } else {
        tail.iter().map(|s| s.rgb_mse).sum::<f64>() / tail.len() as f64
    };
    let colour = mse.sqrt().max(1.0 / 255.0);
    let depth = trainer.config.depth_sigma_at(trainer.step) as f64 * trainer.data.frame.scale;
    (colour, depth)
}

/// Adds the three read-out fields (`log_std_colour`, `log_std_depth`, `log_std_combined`: log10 posterior
/// std in metres) to a cloud in the dataset's metric frame.
pub fn annotate_cloud(
    fisher: &Fisher,
    frame: &crate::train::data::SceneFrame,
    cloud: &mut crate::pointcloud::PointCloud,
) {
    let scene: Vec<[f32; 3]> = cloud
        .positions
        .iter()
        .map(|&p| frame.to_scene(p).as_vec3().to_array())
        .collect();
    let u = read_out(fisher, &scene, frame.scale);
    cloud.set_scalar("log_std_colour", u.colour);
    cloud.set_scalar("log_std_depth", u.depth);
    cloud.set_scalar("log_std_combined", u.combined);
}

/// The uncertainty pass over a trained field: `config.batches` batches of `config.rays_per_batch` pixel
/// rays (colour) plus as many lidar rays (depth), through the trainer's engine (the WGSL pass on
/// `Engine::Wgpu`, the CPU reference otherwise). Each Fisher is scaled from its samples to the whole
/// training set (every pixel, every lidar return), and N is the training pixel count, so Var = 1/(H/N + λ)
/// is per training ray as in BayesRays. `progress(done, of)` after each batch.
pub async fn compute_fisher(
    trainer: &mut Trainer,
    config: &UncertaintyConfig,
    mut progress: impl FnMut(usize, usize),
) -> Result<Fisher, GpuError> {
    config.validate()?;
    let grid = PerturbationGrid {
        cells: config.grid_cells(),
    };
    let nv = grid.vertices();
    let source = RaySource::new(&trainer.data, trainer.config.mode != Mode::Vision);
    let per_batch = config.rays_per_batch;
    let batch_seed = |b: usize| config.seed ^ (b as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    let (mut n_colour, mut n_depth) = (0u64, 0u64);
    let mut count = |flags: &[u32]| {
        n_colour += flags.iter().filter(|&&f| f & COLOUR_RAY != 0).count() as u64;
        n_depth += flags.iter().filter(|&&f| f & DEPTH_RAY != 0).count() as u64;
    };
    let (colour, depth): (Vec<f64>, Vec<f64>) = match &mut trainer.engine {
        Engine::Wgpu(engine) => {
            let mut f = gpu::GpuFisher::new(engine, grid).await?;
            for b in 0..config.batches {
                let (rays, flags) =
                    source.batch(&trainer.data, batch_seed(b), per_batch, per_batch);
                count(&flags);
                f.accumulate(engine, &rays, &flags).await?;
                // Bound the queued work (and let the device free per-dispatch uniforms) now and then.
                if b % 16 == 15 {
                    let enc = engine.gpu.encoder("uncertainty sync");
                    engine.gpu.finish_and_read::<f32>(enc, &[]).await?;
                }
                progress(b + 1, config.batches);
            }
            let (c, d) = f.download(engine).await?;
            (
                c.into_iter().map(f64::from).collect(),
                d.into_iter().map(f64::from).collect(),
            )
        }
        Engine::Cpu => {
            let (mut hc, mut hd) = (vec![0.0f64; nv], vec![0.0f64; nv]);
            for b in 0..config.batches {
                let (rays, flags) =
                    source.batch(&trainer.data, batch_seed(b), per_batch, per_batch);
                count(&flags);
                let t = cpu::final_edges(&trainer.model, &trainer.params, &rays)?;
                let sj = cpu::sample_jacobians_cpu(&trainer.model, &trainer.params, &rays, &t)?;
                cpu::accumulate_fisher_cpu(grid, &sj, &flags, &mut hc, &mut hd);
                progress(b + 1, config.batches);
            }
            (hc, hd)
        }
    };
    let sc = source.pixels as f64 / n_colour.max(1) as f64;
    let sd = source.lidar_pixels() as f64 / n_depth.max(1) as f64;
    let (colour_sigma, depth_sigma) = noise_scales(trainer);
    let f = Fisher {
        cells: grid.cells,
        colour: colour.into_iter().map(|v| (v * sc) as f32).collect(),
        depth: depth.into_iter().map(|v| (v * sd) as f32).collect(),
        rays: source.pixels,
        lidar_rays: source.lidar_pixels(),
        prior: config.prior_precision(),
        colour_sigma,
        depth_sigma,
    };
    f.check()?;
    Ok(f)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::encoding::contract_unit;

    #[test]
    fn automatic_grid_follows_the_ray_budget() {
        let c = |batches, rays| UncertaintyConfig {
            batches,
            rays_per_batch: rays,
            ..Default::default()
        };
        assert_eq!(c(1000, 4096).grid_cells(), 256);
        assert_eq!(c(10, 1024).grid_cells(), 128);
        assert_eq!(c(1, 64).grid_cells(), 8);
        let fixed = UncertaintyConfig {
            cells: 32,
            ..c(1000, 4096)
        };
        assert_eq!(fixed.grid_cells(), 32);
        assert!((fixed.prior_precision() - 1e-4 / 32768.0).abs() < 1e-15);
        assert!(UncertaintyConfig {
            cells: 2000,
            ..fixed
        }
        .validate()
        .is_err());
    }

    #[test]
    fn corners_interpolate_and_index_uniquely() {
        let g = PerturbationGrid { cells: 4 };
        let (idx, w) = g.corners([0.3, 0.6, 0.99]);
        assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        let mut s = idx.to_vec();
        s.sort();
        s.dedup();
        assert_eq!(s.len(), 8);
        assert!(idx.iter().all(|&v| v < g.vertices()));
        // The weighted vertex positions reproduce the point.
        let side = g.cells as usize + 1;
        for k in 0..3 {
            let p: f32 = idx
                .iter()
                .zip(w)
                .map(|(&v, b)| {
                    let c = [v / (side * side), (v / side) % side, v % side][k];
                    b * c as f32 / g.cells as f32
                })
                .sum();
            assert!((p - [0.3, 0.6, 0.99][k]).abs() < 1e-5, "axis {k}: {p}");
        }
        // The upper face stays in the last cell.
        let (cell, t) = g.locate([1.0, 0.0, 0.5]);
        assert_eq!(cell, [3, 0, 2]);
        assert_eq!(t, [1.0, 0.0, 0.0]);
    }

    #[test]
    fn contraction_vjp_matches_finite_differences() {
        let pts = [
            [0.3f32, -0.2, 0.5],
            [2.5, 0.4, -1.2],
            [-0.7, -3.0, 1.9],
            [0.2, 1.1, 8.0],
        ];
        let g = [0.7f32, -1.3, 0.4];
        for x in pts {
            let a = contraction_vjp(x, g);
            for j in 0..3 {
                let h = 1e-3f32;
                let mut xp = x;
                let mut xm = x;
                xp[j] += h;
                xm[j] -= h;
                let (up, um) = (contract_unit(xp), contract_unit(xm));
                let fd: f32 = (0..3).map(|i| g[i] * (up[i] - um[i]) / (2.0 * h)).sum();
                assert!(
                    (fd - a[j]).abs() < 2e-3,
                    "x {x:?} axis {j}: fd {fd} vs {}",
                    a[j]
                );
            }
        }
    }

    #[test]
    fn unobserved_space_reads_the_prior_and_information_lowers_it() {
        let cfg = UncertaintyConfig {
            cells: 8,
            ..Default::default()
        };
        let n = PerturbationGrid { cells: 8 }.vertices();
        let mut f = Fisher {
            cells: 8,
            colour: vec![0.0; n],
            depth: vec![0.0; n],
            rays: 1000,
            lidar_rays: 500,
            prior: cfg.prior_precision(),
            colour_sigma: 0.1,
            depth_sigma: 0.05,
        };
        f.check().unwrap();
        let p = [0.41f32, 0.52, 0.63];
        for m in Modality::ALL {
            assert!((f.log_std(m, p) - f.prior_log_std()).abs() < 1e-5);
        }
        let (idx, _) = f.grid().corners(p);
        for &v in &idx {
            f.depth[v] = 10.0;
        }
        assert!(f.log_std(Modality::Depth, p) < f.prior_log_std() - 1.0);
        assert!((f.log_std(Modality::Colour, p) - f.prior_log_std()).abs() < 1e-5);
        assert!(f.log_std(Modality::Combined, p) <= f.log_std(Modality::Depth, p) + 1e-6);
        let bytes = f.to_bytes();
        assert_eq!(Fisher::from_bytes(&bytes, "u.bin").unwrap(), f);
        for cut in [0, 10, 51, bytes.len() - 1] {
            let e = Fisher::from_bytes(&bytes[..cut], "u.bin")
                .unwrap_err()
                .to_string();
            assert!(e.contains("u.bin"), "{e}");
        }
        f.depth[idx[0]] = f32::NAN;
        assert!(f.check().is_err());
        assert!(Fisher::from_bytes(&f.to_bytes(), "u.bin").is_err());
    }
}
