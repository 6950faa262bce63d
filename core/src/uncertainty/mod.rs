//! Epistemic uncertainty per sensor (paper §Epistemic uncertainty): BayesRays' perturbation field with a
//! Laplace approximation, extended to lidar depth as SiLVR does, read out as a standard deviation in
//! metres that is checked against the error.
//!
//! A regular grid of 3-D offsets θ over the contracted [0, 1]³ displaces the world-space sample positions
//! of the frozen field (trilinearly); θ = 0, the grid exists only to take derivatives. For each ray the
//! Jacobian of the rendered colour (3 channels) and, on lidar rays, of the expected depth with respect to
//! every vertex's offset is summed over the ray's samples and then squared: the diagonal of the Fisher
//! (Gauss–Newton) matrix, accumulated over a sample of training rays and scaled to every pixel and every
//! lidar return the field was trained on, separately for colour and depth.
//!
//! The posterior of vertex v's offset given all those observations, each sensor weighted by its noise
//! model (σ_c: the field's colour residual; σ_d: the lidar's range noise) and a prior of
//! [`PRIOR_SIGMA_M`] metres, is
//!
//! Var_v = 1 / ((H_c,v / σ_c² + H_d,v / σ_d²) / k² + 1 / σ_p²)
//!
//! (one sensor's terms for its own read-out). k = 1 is the raw Laplace posterior, which treats every pixel
//! as an independent measurement of a field no more flexible than the perturbation grid; both are false,
//! so it is overconfident by a global factor. [`calibrate`] fits k per read-out on lidar returns held out
//! of training (never on ground truth). A point's σ is interpolated from its cell's vertices (BayesRays'
//! squared-weight rule); `log_std_*` = log10 σ in metres (DATASET.md).
//!
//! * [`cpu`]: the referee: per-sample Jacobians from the CPU field, the Fisher by a per-ray map.
//! * [`gpu`]: the WGSL pass (`shaders/uncertainty.wgsl` + the trainer's kernels), the product.
//! * [`reliability`]: σ against the error: binned RMS error, coverage at 1σ / 2σ, calibration error.
//! * [`sparsify`]: sparsification curves, AUSE and the error-vs-uncertainty plots.

pub mod calibrate;
pub mod cpu;
pub mod filter;
pub mod gpu;
pub mod reliability;
pub mod sparsify;

use serde::{Deserialize, Serialize};

use crate::gpu::GpuError;
use crate::train::cpu::TrainRay;
use crate::train::data::{SceneFrame, TrainData};
pub use crate::train::export::DEPTH_SPREAD_FIELD;
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
    /// Prior standard deviation of a perturbation in metres; `None` = [`PRIOR_SIGMA_M`].
    #[serde(default)]
    pub prior_sigma_m: Option<f64>,
    /// Held-out lidar returns rendered to calibrate the read-out ([`calibrate`]); 0 = none (raw).
    #[serde(default = "default_calibration_returns")]
    pub calibration_returns: usize,
    /// The filter's threshold as a σ in metres (`points_filtered.ply` keeps σ ≤ it); `None` = the default
    /// rule ([`filter::default_threshold`], Tukey's fence).
    #[serde(default)]
    pub max_sigma_m: Option<f64>,
    pub seed: u64,
}

fn default_calibration_returns() -> usize {
    CALIBRATION_RETURNS
}

/// Prior standard deviation of a perturbation (metres): what the read-out says where no observation
/// constrains the field. A rule, not a per-scene setting: a metre is beyond any error a mapping team
/// would keep, so a point that reads it is not measured at all.
pub const PRIOR_SIGMA_M: f64 = 1.0;

/// Held-out lidar returns the calibration renders by default: the 68 % quantile it fits then moves by
/// about ±1 % of its rank.
pub const CALIBRATION_RETURNS: usize = 8192;

/// Where a read-out stops meaning a measurement: σ ≥ σ_p / √2 is where the observations add no more
/// information than the prior (H / k² ≤ 1 / σ_p²), or, for a point's σ, where its ray's spread alone is
/// that wide (a·s ≥ 0.71 m). The studio shows such points as "unconstrained", not as a large σ.
pub fn unconstrained_log_std(prior_sigma_m: f64) -> f32 {
    (prior_sigma_m / std::f64::consts::SQRT_2).log10() as f32
}

impl Default for UncertaintyConfig {
    fn default() -> Self {
        UncertaintyConfig {
            cells: 0,
            batches: 1000,
            rays_per_batch: 4096,
            prior_sigma_m: None,
            calibration_returns: CALIBRATION_RETURNS,
            max_sigma_m: None,
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
        if let Some(s) = self.max_sigma_m {
            if !(s.is_finite() && s > 0.0) {
                return Err(GpuError::InvalidInput(format!(
                    "uncertainty: --max-sigma {s} m is not a positive number"
                )));
            }
        }
        if let Some(s) = self.prior_sigma_m {
            if !(s.is_finite() && s > 0.0) {
                return Err(GpuError::InvalidInput(format!(
                    "uncertainty: prior σ {s} m is not a positive number"
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

    /// The prior's σ in metres: as configured, or [`PRIOR_SIGMA_M`].
    pub fn prior_sigma(&self) -> f64 {
        self.prior_sigma_m.unwrap_or(PRIOR_SIGMA_M)
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

/// Fisher diagonals of one trained field (the trace of each vertex's 3×3 block), the noise models and
/// prior that turn them into a posterior, the scene frame that puts it in metres, and its calibration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Fisher {
    pub cells: u32,
    /// Σ over every training pixel and colour channel of ‖∂C/∂θ_v‖² (scaled from a sample).
    pub colour: Vec<f32>,
    /// Σ over every lidar return trained on of ‖∂E/∂θ_v‖² (E the expected depth, scene units; scaled
    /// from a sample).
    pub depth: Vec<f32>,
    /// Training pixels and lidar returns the diagonals stand for.
    pub rays: u64,
    pub lidar_rays: u64,
    /// Prior precision λ = 1 / σ_p² (scene units⁻²).
    pub prior: f64,
    /// Noise scales of the two sensors: colour in [0, 1] units, depth in scene units.
    pub colour_sigma: f64,
    pub depth_sigma: f64,
    /// The field's scene frame: read-outs in metres, at metric points.
    pub frame: SceneFrame,
    pub calibration: Calibration,
}

/// Global factors k on the Laplace σ and a on each point's ray spread (by read-out: colour, depth,
/// combined), fitted on held-out lidar returns; uncalibrated, k = 1 and a = 0: the Laplace σ alone.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    pub factor: [f64; 3],
    /// Held-out returns the factors were fitted on (0: not calibrated).
    pub returns: u64,
    /// Coverage the fit reached on them at 1σ (≈ 0.683 when it could).
    pub coverage: [f64; 3],
    /// The factor a on the ray spread s in a point's σ = √(σ_k² + (a·s)²) ([`with_spread`]); 0 where
    /// uncalibrated and in files from before the spread was part of σ (`SILVRFI2`).
    #[serde(default)]
    pub spread: [f64; 3],
}

impl Calibration {
    pub const RAW: Calibration = Calibration {
        factor: [1.0; 3],
        returns: 0,
        coverage: [f64::NAN; 3],
        spread: [0.0; 3],
    };

    pub fn is_calibrated(&self) -> bool {
        self.returns > 0
    }
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

    /// The PLY property of this read-out.
    pub fn field(&self) -> &'static str {
        match self {
            Modality::Colour => "log_std_colour",
            Modality::Depth => "log_std_depth",
            Modality::Combined => "log_std_combined",
        }
    }

    pub(crate) fn index(&self) -> usize {
        match self {
            Modality::Colour => 0,
            Modality::Depth => 1,
            Modality::Combined => 2,
        }
    }
}

/// Which posterior a read-out gives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Posterior {
    /// The Laplace posterior as it is (k = 1; a = 0 where the spread is folded in).
    Raw,
    /// With the calibration's factors (k; and a where the spread is folded in).
    Calibrated,
}

impl Fisher {
    pub fn grid(&self) -> PerturbationGrid {
        PerturbationGrid { cells: self.cells }
    }

    /// Information of vertex v from the observations (scene units⁻²), each sensor's H over its noise
    /// variance.
    pub fn information(&self, m: Modality, v: usize) -> f64 {
        let hc = self.colour[v] as f64 / (self.colour_sigma * self.colour_sigma);
        let hd = self.depth[v] as f64 / (self.depth_sigma * self.depth_sigma);
        match m {
            Modality::Colour => hc,
            Modality::Depth => hd,
            Modality::Combined => hc + hd,
        }
    }

    /// Posterior variance of vertex v (scene units²): 1 / (H_v / k² + λ).
    pub fn variance(&self, m: Modality, post: Posterior, v: usize) -> f64 {
        let k = self.factor(m, post);
        1.0 / (self.information(m, v) / (k * k) + self.prior)
    }

    fn factor(&self, m: Modality, post: Posterior) -> f64 {
        match post {
            Posterior::Raw => 1.0,
            Posterior::Calibrated => self.calibration.factor[m.index()],
        }
    }

    /// The factors a on a point's ray spread, by read-out (colour, depth, combined): none in the raw
    /// posterior (the Laplace σ alone, as the held-out tables' "raw" rows show it).
    pub fn spread_factors(&self, post: Posterior) -> [f64; 3] {
        match post {
            Posterior::Raw => [0.0; 3],
            Posterior::Calibrated => self.calibration.spread,
        }
    }

    /// log10 of the posterior standard deviation (scene units) at a grid position: BayesRays' read-out,
    /// the variances of the cell's vertices interpolated with normalised squared trilinear weights.
    pub fn log_std(&self, m: Modality, post: Posterior, unit: [f32; 3]) -> f32 {
        let (idx, w) = self.grid().corners(unit);
        let wsum: f64 = w.iter().map(|&b| (b as f64) * (b as f64)).sum();
        let k = self.factor(m, post);
        let var: f64 = idx
            .iter()
            .zip(w)
            .map(|(&v, b)| {
                let var = 1.0 / (self.information(m, v) / (k * k) + self.prior);
                (b as f64) * (b as f64) / wsum * var
            })
            .sum();
        (var.sqrt() + 1e-12).log10() as f32
    }

    /// The prior's σ in metres: the read-out where no ray constrained the field.
    pub fn prior_sigma_m(&self) -> f64 {
        1.0 / (self.prior.sqrt() * self.frame.scale)
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

const MAGIC: &[u8; 8] = b"SILVRFI3";
/// The version before the spread factors: read with a = 0 (its σ had no spread).
const MAGIC_V2: &[u8; 8] = b"SILVRFI2";
/// Magic, cells, rays, lidar rays, λ, σ_c, σ_d, frame centre (3) and scale, factors (3), returns,
/// coverages (3), spread factors (3; not in version 2).
const HEADER_BYTES: usize = 8 + 4 + 8 + 8 + 8 * 3 + 8 * 4 + 8 * 3 + 8 + 8 * 3 + 8 * 3;
const HEADER_BYTES_V2: usize = HEADER_BYTES - 8 * 3;

impl Fisher {
    /// A compact little-endian file (`uncertainty.bin`): the header ([`HEADER_BYTES`]), then the colour
    /// and depth diagonals as f32.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(HEADER_BYTES + 8 * self.colour.len());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&self.cells.to_le_bytes());
        out.extend_from_slice(&self.rays.to_le_bytes());
        out.extend_from_slice(&self.lidar_rays.to_le_bytes());
        let c = &self.calibration;
        let head = [self.prior, self.colour_sigma, self.depth_sigma]
            .into_iter()
            .chain(self.frame.center)
            .chain([self.frame.scale])
            .chain(c.factor);
        for v in head {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&c.returns.to_le_bytes());
        for v in c.coverage.into_iter().chain(c.spread) {
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
        if bytes.len() >= 8 && &bytes[..8] == b"SILVRFI1" {
            return Err(bad(
                "an uncertainty file of an older silvr (its σ was per training ray, not metric): run \
                 `silvr uncertainty` on the model again",
            ));
        }
        let v2 = bytes.len() >= 8 && &bytes[..8] == MAGIC_V2;
        let header = if v2 { HEADER_BYTES_V2 } else { HEADER_BYTES };
        if bytes.len() < header || !(v2 || &bytes[..8] == MAGIC) {
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
        let want = header + 8 * nv;
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
        let f3 = |o: usize| [f64_at(o), f64_at(o + 8), f64_at(o + 16)];
        let f = Fisher {
            cells,
            rays: u64_at(12),
            lidar_rays: u64_at(20),
            prior: f64_at(28),
            colour_sigma: f64_at(36),
            depth_sigma: f64_at(44),
            frame: SceneFrame {
                center: f3(52),
                scale: f64_at(76),
            },
            calibration: Calibration {
                factor: f3(84),
                returns: u64_at(108),
                coverage: f3(116),
                spread: if v2 { [0.0; 3] } else { f3(140) },
            },
            colour: floats(header),
            depth: floats(header + 4 * nv),
        };
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !(positive(f.prior) && positive(f.colour_sigma) && positive(f.depth_sigma)) {
            return Err(bad("prior and noise scales must be positive"));
        }
        if !(positive(f.frame.scale) && f.frame.center.iter().all(|c| c.is_finite())) {
            return Err(bad("the scene frame is not a finite, positive scale"));
        }
        if !f.calibration.factor.iter().all(|&k| positive(k)) {
            return Err(bad("calibration factors must be positive"));
        }
        if !f
            .calibration
            .spread
            .iter()
            .all(|&a| a.is_finite() && a >= 0.0)
        {
            return Err(bad("spread factors must be finite and not negative"));
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

/// Per-point uncertainty of a cloud: log10 σ in metres per read-out.
pub struct PointUncertainty {
    pub colour: Vec<f32>,
    pub depth: Vec<f32>,
    pub combined: Vec<f32>,
}

impl PointUncertainty {
    pub fn of(&self, m: Modality) -> &[f32] {
        match m {
            Modality::Colour => &self.colour,
            Modality::Depth => &self.depth,
            Modality::Combined => &self.combined,
        }
    }

    /// Folds each point's ray spread (metres, one per point) into every read-out ([`with_spread`]) with
    /// the read-outs' factors `a` (colour, depth, combined).
    pub fn fold_spread(&mut self, spread_m: &[f32], a: [f64; 3]) {
        for (v, a) in [&mut self.colour, &mut self.depth, &mut self.combined]
            .into_iter()
            .zip(a)
        {
            for (l, &s) in v.iter_mut().zip(spread_m) {
                *l = with_spread(*l, s, a);
            }
        }
    }
}

impl Fisher {
    /// log10 σ in metres of one read-out at scene-frame points.
    pub fn read_out_scene(
        &self,
        m: Modality,
        post: Posterior,
        scene_points: &[[f32; 3]],
    ) -> Vec<f32> {
        use crate::field::encoding::contract_unit;
        use rayon::prelude::*;
        let shift = self.frame.scale.log10() as f32;
        scene_points
            .par_iter()
            .with_min_len(1024)
            .map(|&p| self.log_std(m, post, contract_unit(p)) - shift)
            .collect()
    }

    /// The three read-outs (log10 σ, metres) at points of the dataset's metric frame.
    pub fn read_out_metric(&self, post: Posterior, points: &[glam::DVec3]) -> PointUncertainty {
        let scene: Vec<[f32; 3]> = points
            .iter()
            .map(|&p| self.frame.to_scene(p).as_vec3().to_array())
            .collect();
        PointUncertainty {
            colour: self.read_out_scene(Modality::Colour, post, &scene),
            depth: self.read_out_scene(Modality::Depth, post, &scene),
            combined: self.read_out_scene(Modality::Combined, post, &scene),
        }
    }
}

/// Ray flag: the ray adds to the colour Fisher.
pub const COLOUR_RAY: u32 = 1;
/// Ray flag: the ray adds to the depth Fisher (it has a lidar return).
pub const DEPTH_RAY: u32 = 2;

/// Where the pass draws rays: every training pixel (colour) and every lidar return trained on (depth), so
/// that the sparse lidar gets as many samples as the images; contributions are scaled back to the whole
/// set.
pub struct RaySource {
    /// (image, pixel) of every training pixel with a lidar return (not sky) that training used (held-out
    /// returns are not observations of the field).
    lidar_pixels: Vec<(usize, u32)>,
    /// Training pixels in all: the colour observations the field was fitted to.
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
                    if d > 0
                        && d != crate::lidar::images::SKY_DEPTH
                        && !crate::train::data::is_held_out_return(i, p)
                    {
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

/// The sensors' noise models, by rule rather than per-scene tuning: colour, the trained field's own RMS
/// colour residual over the last tenth of training (at least one 8-bit level; image noise and what the
/// field cannot fit alike); depth, the lidar's range noise as the dataset states it
/// ([`TrainData::lidar_range_noise_m`]), in scene units.
pub fn noise_scales(trainer: &Trainer) -> (f64, f64) {
    let h = &trainer.history;
    let tail = &h[h.len() - h.len().div_ceil(10)..];
    let mse = if tail.is_empty() {
        0.0
    } else {
        tail.iter().map(|s| s.rgb_mse).sum::<f64>() / tail.len() as f64
    };
    let colour = mse.sqrt().max(1.0 / 255.0);
    let depth = trainer.data.lidar_range_noise_m * trainer.data.frame.scale;
    (colour, depth)
}

/// Adds the three read-out fields (`log_std_colour`, `log_std_depth`, `log_std_combined`: log10 σ in
/// metres, calibrated when the Fisher is) to a cloud in the dataset's metric frame.
/// Each point's own ray spread ([`DEPTH_SPREAD_FIELD`], written by the export) is folded into every
/// read-out ([`fold_spread`]); a cloud without it (exported before 2026-12-05) reads the field's σ alone.
pub fn annotate_cloud(fisher: &Fisher, cloud: &mut crate::pointcloud::PointCloud) {
    let mut u = fisher.read_out_metric(Posterior::Calibrated, &cloud.positions);
    if let Some(s) = cloud.scalar(DEPTH_SPREAD_FIELD) {
        u.fold_spread(s, fisher.spread_factors(Posterior::Calibrated));
    }
    cloud.set_scalar("log_std_colour", u.colour);
    cloud.set_scalar("log_std_depth", u.depth);
    cloud.set_scalar("log_std_combined", u.combined);
}

/// log10 √(σ² + (a·s)²) of a log10 σ, a spread s (metres) and its factor a: the field's uncertainty about
/// where the surface is and the ray's about where along it the point sits are independent, so variances
/// add. The spread is that of the ray's weights, not of the error of their mean (on one blurred surface the
/// mean is still on it), hence a, fitted like k on held-out returns ([`calibrate`]).
pub fn with_spread(log_std: f32, spread_m: f32, a: f64) -> f32 {
    if !spread_m.is_finite() || spread_m <= 0.0 || a <= 0.0 {
        return log_std;
    }
    let s = 10f64.powf(log_std as f64);
    (0.5 * (s * s + (a * spread_m as f64).powi(2)).log10()) as f32
}

/// The uncertainty pass over a trained field: `config.batches` batches of `config.rays_per_batch` pixel
/// rays (colour) plus as many lidar rays (depth), through the trainer's engine (the WGSL pass on
/// `Engine::Wgpu`, the CPU reference otherwise). Each Fisher is scaled from its samples to the whole
/// training set (every pixel, every lidar return trained on): the posterior is given all the
/// observations, not one average ray (BayesRays' H/N, whose σ is √N too large). Uncalibrated
/// ([`calibrate`] fits the factors). `progress(done, of)` after each batch.
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
    let frame = trainer.data.frame;
    let prior_sigma = config.prior_sigma() * frame.scale;
    let f = Fisher {
        cells: grid.cells,
        colour: colour.into_iter().map(|v| (v * sc) as f32).collect(),
        depth: depth.into_iter().map(|v| (v * sd) as f32).collect(),
        rays: source.pixels,
        lidar_rays: source.lidar_pixels(),
        prior: 1.0 / (prior_sigma * prior_sigma),
        colour_sigma,
        depth_sigma,
        frame,
        calibration: Calibration::RAW,
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
        assert_eq!(fixed.prior_sigma(), PRIOR_SIGMA_M);
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
        let n = PerturbationGrid { cells: 8 }.vertices();
        // Scene units of 0.1 m (scale 10 / m): a 1 m prior is 10 scene units.
        let frame = SceneFrame {
            center: [1.0, 2.0, 3.0],
            scale: 10.0,
        };
        let mut f = Fisher {
            cells: 8,
            colour: vec![0.0; n],
            depth: vec![0.0; n],
            rays: 1000,
            lidar_rays: 500,
            prior: 1.0 / (PRIOR_SIGMA_M * frame.scale).powi(2),
            colour_sigma: 0.1,
            depth_sigma: 0.05,
            frame,
            calibration: Calibration::RAW,
        };
        f.check().unwrap();
        assert!((f.prior_sigma_m() - PRIOR_SIGMA_M).abs() < 1e-12);
        let p = glam::DVec3::new(1.2, 2.1, 3.05);
        let unit = contract_unit(frame.to_scene(p).as_vec3().to_array());
        for post in [Posterior::Raw, Posterior::Calibrated] {
            let u = f.read_out_metric(post, &[p]);
            for m in Modality::ALL {
                assert!(u.of(m)[0].abs() < 1e-5, "the prior reads log10(1 m) = 0");
            }
        }
        let (idx, _) = f.grid().corners(unit);
        // Information 10⁴ per vertex over σ_d² = 0.0025: σ = 1/√(4e6 + 0.01) scene units = 0.05 mm.
        for &v in &idx {
            f.depth[v] = 1e4;
        }
        let depth = f.read_out_metric(Posterior::Raw, &[p]).depth[0];
        let want = (1.0 / (4e6f64 + 0.01).sqrt() / 10.0).log10() as f32;
        assert!((depth - want).abs() < 1e-4, "{depth} vs {want}");
        let raw = f.read_out_metric(Posterior::Raw, &[p]);
        assert!(raw.colour[0].abs() < 1e-5);
        assert!(raw.combined[0] <= raw.depth[0] + 1e-6);
        // A calibration factor k divides the information by k²: σ grows k-fold while it dominates.
        f.calibration = Calibration {
            factor: [1.0, 100.0, 1.0],
            returns: 10,
            coverage: [0.68; 3],
            spread: [0.5, 0.25, 0.0],
        };
        let cal = f.read_out_metric(Posterior::Calibrated, &[p]).depth[0];
        assert!((cal - depth - 2.0).abs() < 1e-3, "{cal} vs {depth} + 2");
        assert!(cal < unconstrained_log_std(PRIOR_SIGMA_M));
        let bytes = f.to_bytes();
        assert_eq!(Fisher::from_bytes(&bytes, "u.bin").unwrap(), f);
        for cut in [0, 10, 51, HEADER_BYTES, bytes.len() - 1] {
            let e = Fisher::from_bytes(&bytes[..cut], "u.bin")
                .unwrap_err()
                .to_string();
            assert!(e.contains("u.bin"), "{e}");
        }
        // A spread adds in quadrature with its factor: 8 cm at a = 0.25 on a 1.5 cm σ reads 2.5 cm.
        assert!((with_spread((0.015f32).log10(), 0.08, 0.25) - (0.025f32).log10()).abs() < 1e-5);
        assert_eq!(with_spread(-2.0, 0.08, 0.0), -2.0);
        assert_eq!(with_spread(-2.0, f32::NAN, 1.0), -2.0);
        // Version 2 (no spread factors): files read a = 0, their σ as it was.
        let mut v2 = bytes[..HEADER_BYTES_V2].to_vec();
        v2[..8].copy_from_slice(b"SILVRFI2");
        v2.extend_from_slice(&bytes[HEADER_BYTES..]);
        let g = Fisher::from_bytes(&v2, "u.bin").unwrap();
        assert_eq!(g.calibration.spread, [0.0; 3]);
        assert_eq!(g.calibration.factor, f.calibration.factor);
        assert_eq!((g.colour, g.depth), (f.colour.clone(), f.depth.clone()));
        let mut old = bytes.clone();
        old[..8].copy_from_slice(b"SILVRFI1");
        let e = Fisher::from_bytes(&old, "u.bin").unwrap_err().to_string();
        assert!(e.contains("older silvr"), "{e}");
        f.depth[idx[0]] = f32::NAN;
        assert!(f.check().is_err());
        assert!(Fisher::from_bytes(&f.to_bytes(), "u.bin").is_err());
    }
}
