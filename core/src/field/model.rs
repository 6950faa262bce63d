//! nerfacto's fields assembled from the parts: the radiance field (hash grid → density MLP → density logit
//! and geometry features; SH(direction) ⊕ geometry features ⊕ appearance embedding → colour MLP → RGB) and
//! the proposal density fields (small hash grid → tiny MLP → density logit). Sizes are configurable;
//! defaults are nerfacto's. Parameters are a list of named tensors so the optimiser, checkpoints and the
//! GPU engine (one buffer per tensor) agree on one layout.

use serde::{Deserialize, Serialize};

use super::encoding::{contract_unit, sh4, trunc_exp};
use super::hashgrid::{self, HashGridConfig, HashGridLayout};
use super::mlp::{self, Activation, MlpConfig};
use crate::gpu::GpuError;
use crate::sampler::SamplerConfig;

/// The radiance field's shape.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FieldConfig {
    pub grid: HashGridConfig,
    /// Density MLP hidden width (one hidden layer).
    pub density_hidden: usize,
    /// Geometry features passed from the density MLP to the colour MLP (nerfacto: 15).
    pub geo_features: usize,
    pub colour_hidden: usize,
    pub colour_hidden_layers: usize,
    /// Per-image appearance embedding width (nerfacto: 32); 0 turns it off.
    pub appearance_dim: usize,
}

impl Default for FieldConfig {
    fn default() -> Self {
        Self {
            grid: HashGridConfig::default(),
            density_hidden: 64,
            geo_features: 15,
            colour_hidden: 64,
            colour_hidden_layers: 2,
            appearance_dim: 32,
        }
    }
}

/// One proposal density field's shape (nerfacto: 5 levels, 2^17, 16 → 128 / 256, hidden 16).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProposalConfig {
    pub grid: HashGridConfig,
    pub hidden: usize,
}

/// Everything that fixes the parameter layout and the sampling.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelConfig {
    pub field: FieldConfig,
    /// One per proposal level (same length as `sampler.proposal_samples`).
    pub proposals: Vec<ProposalConfig>,
    pub sampler: SamplerConfig,
    /// Training images (rows of the appearance table).
    pub images: usize,
    /// Finite-difference step for density-gradient normals, in the grid's [0, 1]³ coordinates.
    pub normal_step: f32,
}

impl ModelConfig {
    /// nerfacto's sizes for `images` training images.
    pub fn nerfacto(images: usize) -> Self {
        Self {
            field: FieldConfig::default(),
            proposals: vec![
                ProposalConfig {
                    grid: HashGridConfig::proposal(128),
                    hidden: 16,
                },
                ProposalConfig {
                    grid: HashGridConfig::proposal(256),
                    hidden: 16,
                },
            ],
            sampler: SamplerConfig::default(),
            images,
            normal_step: 1.0 / 1024.0,
        }
    }

    /// A model size by name: `nerfacto` (the paper's), `small` (a quick look, the `ci` demo and the parity
    /// tests: 2^16-entry tables up to 1024 cells, proposals 64 → 32 → 24 samples; 2^17 gave +0.5 dB
    /// held-out PSNR on the ci world for ~25% more demo time, 2^15 −0.5 dB) or `medium` (nerfacto's finest
    /// resolution with a 2^18 table and the small model's sample counts: the default world on a CPU).
    pub fn preset(name: &str, images: usize) -> Result<Self, GpuError> {
        let mut m = ModelConfig::nerfacto(images);
        match name {
            "nerfacto" => {}
            "small" => {
                m.field.grid.log2_table_size = 16;
                m.field.grid.finest_resolution = 1024;
                m.sampler.proposal_samples = vec![64, 32];
                m.sampler.samples = 24;
                for p in &mut m.proposals {
                    p.grid.log2_table_size = 15;
                }
            }
            "medium" => {
                m.field.grid.log2_table_size = 18;
                m.sampler.proposal_samples = vec![64, 32];
                m.sampler.samples = 24;
                for p in &mut m.proposals {
                    p.grid.log2_table_size = 16;
                }
            }
            // Seconds per step on a software adapter (the studio's browser tests on SwiftShader): a
            // coarse field for checks and previews, not for maps.
            "tiny" => {
                let images = m.images;
                m = ModelConfig::tiny();
                m.images = images;
            }
            o => {
                return Err(GpuError::InvalidInput(format!(
                    "unknown model size {o:?} (nerfacto, medium, small, tiny)"
                )))
            }
        }
        Ok(m)
    }

    /// A model small enough for kernel tests on a software rasteriser and for finite differences
    /// (3 images, 4 grid levels, 16-wide MLPs, 16 → 12 → 8 samples). Shared by the CPU and GPU tests.
    pub fn tiny() -> Self {
        let mut m = ModelConfig::nerfacto(3);
        m.field.grid = HashGridConfig {
            levels: 4,
            features_per_level: 2,
            log2_table_size: 10,
            base_resolution: 4,
            finest_resolution: 64,
        };
        m.field.density_hidden = 16;
        m.field.colour_hidden = 16;
        m.field.appearance_dim = 4;
        m.sampler.proposal_samples = vec![16, 12];
        m.sampler.samples = 8;
        for p in &mut m.proposals {
            p.grid.log2_table_size = 8;
            p.grid.levels = 3;
        }
        m
    }

    pub fn density_mlp(&self) -> MlpConfig {
        MlpConfig {
            input: self.field.grid.output_dim(),
            hidden: self.field.density_hidden,
            hidden_layers: 1,
            // Saturating: an absurd width (a crafted checkpoint) is refused by `validate`, not overflowed.
            output: self.field.geo_features.saturating_add(1),
            hidden_activation: Activation::Relu,
            output_activation: Activation::None,
        }
    }

    pub fn colour_mlp(&self) -> MlpConfig {
        MlpConfig {
            input: self
                .field
                .geo_features
                .saturating_add(self.field.appearance_dim)
                .saturating_add(16),
            hidden: self.field.colour_hidden,
            hidden_layers: self.field.colour_hidden_layers,
            output: 3,
            hidden_activation: Activation::Relu,
            output_activation: Activation::Sigmoid,
        }
    }

    pub fn proposal_mlp(&self, level: usize) -> MlpConfig {
        let p = &self.proposals[level];
        MlpConfig {
            input: p.grid.output_dim(),
            hidden: p.hidden,
            hidden_layers: 1,
            output: 1,
            hidden_activation: Activation::Relu,
            output_activation: Activation::None,
        }
    }

    /// Refuses shapes the kernels cannot run, naming the part.
    pub fn validate(&self) -> Result<(), GpuError> {
        let bad = |m: String| Err(GpuError::InvalidInput(format!("model: {m}")));
        if self.proposals.len() != self.sampler.proposal_samples.len() {
            return bad(format!(
                "{} proposal fields for {} proposal sample counts",
                self.proposals.len(),
                self.sampler.proposal_samples.len()
            ));
        }
        if self.sampler.samples == 0 || self.sampler.proposal_samples.contains(&0) {
            return bad("every level needs at least one sample".into());
        }
        if !(self.sampler.near > 0.0 && self.sampler.far > self.sampler.near) {
            return bad(format!(
                "need 0 < near < far, got {} and {}",
                self.sampler.near, self.sampler.far
            ));
        }
        if !(self.normal_step > 0.0 && self.normal_step < 0.1) {
            return bad(format!("normal_step {} out of (0, 0.1)", self.normal_step));
        }
        HashGridLayout::new(&self.field.grid)?;
        self.density_mlp().validate()?;
        self.colour_mlp().validate()?;
        for l in 0..self.proposals.len() {
            HashGridLayout::new(&self.proposals[l].grid)?;
            self.proposal_mlp(l).validate()?;
        }
        Ok(())
    }

    /// Tensor names and sizes, in parameter order. Never overflows: an absurd shape is an error.
    pub fn tensor_shapes(&self) -> Result<Vec<(String, usize)>, GpuError> {
        self.validate()?;
        let appearance = self
            .images
            .max(1)
            .checked_mul(self.field.appearance_dim)
            .ok_or_else(|| {
                GpuError::InvalidInput(format!(
                    "model: {} images × appearance_dim {} overflow",
                    self.images, self.field.appearance_dim
                ))
            })?;
        let mut v = vec![
            (
                "field.grid".to_string(),
                HashGridLayout::new(&self.field.grid)?.n_params(),
            ),
            ("field.density".to_string(), self.density_mlp().n_params()),
            ("field.colour".to_string(), self.colour_mlp().n_params()),
            ("field.appearance".to_string(), appearance),
        ];
        for l in 0..self.proposals.len() {
            v.push((
                format!("proposal{l}.grid"),
                HashGridLayout::new(&self.proposals[l].grid)?.n_params(),
            ));
            v.push((format!("proposal{l}.mlp"), self.proposal_mlp(l).n_params()));
        }
        Ok(v)
    }
}

/// Tensor indices in [`Params::tensors`].
pub const GRID: usize = 0;
pub const DENSITY: usize = 1;
pub const COLOUR: usize = 2;
pub const APPEARANCE: usize = 3;
/// Proposal level l's grid is `PROPOSAL + 2l`, its MLP `PROPOSAL + 2l + 1`.
pub const PROPOSAL: usize = 4;

/// The trainable parameters: one flat f32 vector per named tensor.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Params {
    pub names: Vec<String>,
    pub tensors: Vec<Vec<f32>>,
}

impl Params {
    /// Initialised as tcnn/nerfstudio: grids U(±1e-4), MLPs Xavier-uniform, appearance N(0, 1).
    pub fn init(cfg: &ModelConfig, seed: u64) -> Result<Params, GpuError> {
        use rand::{Rng, SeedableRng};
        let shapes = cfg.tensor_shapes()?;
        let mut tensors = vec![
            HashGridLayout::new(&cfg.field.grid)?.init_params(seed),
            cfg.density_mlp().init_params(seed ^ 0x11),
            cfg.colour_mlp().init_params(seed ^ 0x22),
        ];
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed ^ 0x33);
        tensors.push(
            (0..shapes[APPEARANCE].1)
                .map(|_| {
                    // Box–Muller: N(0, 1) as torch's nn.Embedding initialises.
                    let u1: f32 = rng.random_range(f32::EPSILON..1.0);
                    let u2: f32 = rng.random();
                    (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
                })
                .collect(),
        );
        for l in 0..cfg.proposals.len() {
            let s = seed ^ (0x100 + l as u64);
            tensors.push(HashGridLayout::new(&cfg.proposals[l].grid)?.init_params(s));
            tensors.push(cfg.proposal_mlp(l).init_params(s ^ 0x44));
        }
        Ok(Params {
            names: shapes.into_iter().map(|(n, _)| n).collect(),
            tensors,
        })
    }

    /// Checks the tensors fit `cfg` (after loading a checkpoint).
    pub fn check(&self, cfg: &ModelConfig) -> Result<(), GpuError> {
        let shapes = cfg.tensor_shapes()?;
        if shapes.len() != self.tensors.len() {
            return Err(GpuError::InvalidInput(format!(
                "parameters: {} tensors, the model has {}",
                self.tensors.len(),
                shapes.len()
            )));
        }
        for ((name, n), t) in shapes.iter().zip(&self.tensors) {
            if t.len() != *n {
                return Err(GpuError::InvalidInput(format!(
                    "parameters: {name} has {} values, the model needs {n}",
                    t.len()
                )));
            }
            if t.iter().any(|v| !v.is_finite()) {
                return Err(GpuError::InvalidInput(format!(
                    "parameters: {name} holds non-finite values"
                )));
            }
        }
        Ok(())
    }

    pub fn count(&self) -> usize {
        self.tensors.iter().map(Vec::len).sum()
    }

    /// The mean appearance embedding (nerfacto's choice for views it did not train on).
    pub fn mean_appearance(&self, cfg: &ModelConfig) -> Vec<f32> {
        let d = cfg.field.appearance_dim;
        let mut m = vec![0.0f32; d];
        if d == 0 {
            return m;
        }
        let rows = self.tensors[APPEARANCE].chunks(d);
        let n = rows.len().max(1) as f32;
        for r in rows {
            for (a, b) in m.iter_mut().zip(r) {
                *a += b / n;
            }
        }
        m
    }
}

/// A density field evaluated on the CPU: grid features, MLP rows and the logits, kept for the backward.
pub struct DensityEval {
    pub unit: Vec<[f32; 3]>,
    pub features: Vec<f32>,
    pub mlp: mlp::MlpForward,
    pub out_dim: usize,
}

impl DensityEval {
    pub fn logit(&self, i: usize) -> f32 {
        self.mlp.output[i * self.out_dim]
    }
}

/// Grid + MLP forward at scene-space positions (contracted here).
pub fn density_forward_cpu(
    grid: &HashGridConfig,
    mlp_cfg: &MlpConfig,
    grid_params: &[f32],
    mlp_params: &[f32],
    positions: &[[f32; 3]],
) -> Result<DensityEval, GpuError> {
    let unit: Vec<[f32; 3]> = positions.iter().map(|&p| contract_unit(p)).collect();
    density_forward_unit_cpu(grid, mlp_cfg, grid_params, mlp_params, unit)
}

/// Grid + MLP forward at positions already in the grid's [0, 1]³.
pub fn density_forward_unit_cpu(
    grid: &HashGridConfig,
    mlp_cfg: &MlpConfig,
    grid_params: &[f32],
    mlp_params: &[f32],
    unit: Vec<[f32; 3]>,
) -> Result<DensityEval, GpuError> {
    let features = hashgrid::encode_cpu(grid, grid_params, &unit)?;
    let mlp = mlp::forward_fast(mlp_cfg, mlp_params, &features)?;
    Ok(DensityEval {
        unit,
        features,
        mlp,
        out_dim: mlp_cfg.output,
    })
}

/// Backward of [`density_forward_cpu`] from dL/d(MLP output rows): (dL/dgrid, dL/dmlp).
pub fn density_backward_cpu(
    grid: &HashGridConfig,
    mlp_cfg: &MlpConfig,
    grid_params: &[f32],
    mlp_params: &[f32],
    eval: &DensityEval,
    d_output: &[f32],
) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
    let g = mlp::backward_fast(
        mlp_cfg,
        mlp_params,
        &eval.features,
        &eval.mlp.saved,
        d_output,
        true,
    )?;
    let d_features = g.input.expect("input gradients were requested");
    let gg = hashgrid::backward_cpu(grid, grid_params, &eval.unit, &d_features, false)?;
    Ok((gg.params, g.params))
}

/// The colour MLP's input row: SH(direction) ⊕ geometry features ⊕ appearance.
pub fn colour_input(dir: [f32; 3], geo: &[f32], appearance: &[f32], row: &mut [f32]) {
    row[..16].copy_from_slice(&sh4(dir));
    row[16..16 + geo.len()].copy_from_slice(geo);
    row[16 + geo.len()..].copy_from_slice(appearance);
}

/// σ and dσ/dlogit.
pub fn density_of(logit: f32) -> (f32, f32) {
    trunc_exp(logit)
}

/// The six finite-difference positions (±h on x, y, z) around a grid position, clamped to the cube.
pub fn fd_positions(unit: [f32; 3], h: f32) -> [[f32; 3]; 6] {
    let mut out = [unit; 6];
    for k in 0..3 {
        out[2 * k][k] = (unit[k] + h).min(1.0);
        out[2 * k + 1][k] = (unit[k] - h).max(0.0);
    }
    out
}

/// Density-gradient normal from the six logits: n = −normalize(∇logit); also |∇| (for the backward).
pub fn fd_normal(logits: [f32; 6], h: f32) -> ([f32; 3], f32) {
    let g = [0, 1, 2].map(|k| (logits[2 * k] - logits[2 * k + 1]) / (2.0 * h));
    let len = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
    if len > 1e-20 {
        (g.map(|v| -v / len), len)
    } else {
        ([0.0; 3], len)
    }
}

/// dL/dlogits of the six FD evaluations from dL/dn.
pub fn fd_normal_backward(n: [f32; 3], len: f32, h: f32, d_n: [f32; 3]) -> [f32; 6] {
    if len <= 1e-20 {
        return [0.0; 6];
    }
    let nd = n[0] * d_n[0] + n[1] * d_n[1] + n[2] * d_n[2];
    // n = −g/|g|  ⇒  dL/dg = −(dL/dn − n·(n·dL/dn))/|g|.
    let d_g = [0, 1, 2].map(|k| -(d_n[k] - n[k] * nd) / len);
    let mut out = [0.0; 6];
    for k in 0..3 {
        out[2 * k] = d_g[k] / (2.0 * h);
        out[2 * k + 1] = -d_g[k] / (2.0 * h);
    }
    out
}
