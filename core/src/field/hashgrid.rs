//! The multi-resolution hash-grid encoding of Instant-NGP, as tiny-cuda-nn's `HashGrid` with linear
//! interpolation (what nerfacto's fields use), on the GPU (`shaders/hashgrid.wgsl`) and on the CPU (the
//! reference, same f32 arithmetic in the same order).
//!
//! Layout rules, all taken from tcnn so a grid means the same thing here and there:
//! - growth factor b = exp((ln finest − ln base) / (L − 1)) (nerfstudio's `growth_factor`, 1 for one level);
//! - level l: scale = 2^(l·log2 b)·base − 1, resolution = ceil(scale) + 1 vertices per axis;
//! - a position x ∈ [0, 1]³ maps to x·scale + 0.5 (the half-vertex offset staggers the levels); its cell is the
//!   floor, the trilinear weights come from the fraction;
//! - level size = min(res³ rounded up to a multiple of 8, T) entries, T = 2^log2_table_size;
//! - a level is **dense** when res³ ≤ its size: vertex (x, y, z) → (x + y·res + z·res²) mod size (the offset
//!   lets a coordinate reach res, which wraps, as in tcnn); otherwise **hashed**:
//!   (x·1 ⊕ y·2654435761 ⊕ z·805459861) mod T, with wrapping u32 products;
//! - parameters: levels one after another, F features per entry: `params[(offset_l + entry)·F + f]`;
//! - features out: one row of L·F per position, level-major within the row.
//!
//! Deviations, deliberate: the scale is evaluated in f64 and rounded to f32 (tcnn uses f32 `exp2f`), so the
//! layout is identical on every platform, the browser included; positions are clamped to [0, 1]³ (tcnn
//! does not clamp; contracted positions never leave the cube), and dL/dx is zero along a clamped axis.
//!
//! Kernels: `encode` runs one thread per (level, position), level-major so a workgroup shares one level's
//! metadata and dense/hashed branch; `backward_params` one thread per (level, [`MERGE_RUN`] consecutive
//! positions), summing what they add to a cell before its atomic adds; `backward_pos` runs one thread per position over all
//! levels, so dL/dx needs no atomics. GPU parameter gradients are summed with compare-exchange float adds
//! (WebGPU has no `atomic<f32>`), so their order, and with it the last bits, varies from run to run; the
//! CPU reference is deterministic. [`encode_gpu`] and [`backward_gpu`] take host slices; the `record_*`
//! functions record into the caller's encoder over the caller's buffers, so a trainer chains passes
//! without readbacks.

use std::ops::Range;

use bytemuck::{Pod, Zeroable};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::gpu::{wgpu, Gpu, GpuError, Kernel};
use crate::shaders;

/// Most levels a grid may have (the WGSL uniform holds a fixed array of this many).
pub const MAX_LEVELS: u32 = 32;
/// Most features per entry (the position-gradient kernel keeps one level's dL/dfeatures in registers).
pub const MAX_FEATURES_PER_LEVEL: u32 = 8;
/// tcnn's spatial-hash primes for x, y, z.
pub const PRIMES: [u32; 3] = [1, 2_654_435_761, 805_459_861];
/// tcnn's initialisation range for the table: U(−1e-4, 1e-4).
pub const INIT_RANGE: f32 = 1e-4;

const WORKGROUP: u32 = 64;

const KERNEL: Kernel = Kernel {
    name: "hashgrid",
    source: shaders::HASHGRID,
    workgroup_size: WORKGROUP,
};

/// The shape of a hash grid. Defaults are nerfacto's base field (16 levels × 2 features, 2^19 entries per
/// level, vertices per axis from 16 to 2048).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct HashGridConfig {
    pub levels: u32,
    pub features_per_level: u32,
    pub log2_table_size: u32,
    pub base_resolution: u32,
    pub finest_resolution: u32,
}

impl Default for HashGridConfig {
    fn default() -> Self {
        Self {
            levels: 16,
            features_per_level: 2,
            log2_table_size: 19,
            base_resolution: 16,
            finest_resolution: 2048,
        }
    }
}

impl HashGridConfig {
    /// nerfacto's proposal-network grid: 5 levels, 2^17 entries, resolutions 16 to `finest` (128, 256).
    pub fn proposal(finest_resolution: u32) -> Self {
        Self {
            levels: 5,
            features_per_level: 2,
            log2_table_size: 17,
            base_resolution: 16,
            finest_resolution,
        }
    }

    /// Per-level growth factor b of the resolution.
    pub fn per_level_scale(&self) -> f64 {
        if self.levels <= 1 {
            return 1.0;
        }
        let span = (self.finest_resolution as f64).ln() - (self.base_resolution as f64).ln();
        (span / (self.levels - 1) as f64).exp()
    }

    /// Entries per level before the dense clamp: T = 2^log2_table_size.
    pub fn table_size(&self) -> u32 {
        1u32 << self.log2_table_size
    }

    /// Features per position: levels × features per level.
    pub fn output_dim(&self) -> usize {
        (self.levels * self.features_per_level) as usize
    }

    fn validate(&self) -> Result<(), GpuError> {
        let bad = |what: String| Err(GpuError::InvalidInput(format!("hash grid: {what}")));
        if self.levels == 0 || self.levels > MAX_LEVELS {
            return bad(format!(
                "levels must be 1..={MAX_LEVELS}, got {}",
                self.levels
            ));
        }
        if self.features_per_level == 0 || self.features_per_level > MAX_FEATURES_PER_LEVEL {
            return bad(format!(
                "features_per_level must be 1..={MAX_FEATURES_PER_LEVEL}, got {}",
                self.features_per_level
            ));
        }
        // ≥ 3 keeps T a multiple of 8 (tcnn's alignment); ≤ 30 keeps u32 index arithmetic exact.
        if !(3..=30).contains(&self.log2_table_size) {
            return bad(format!(
                "log2_table_size must be 3..=30, got {}",
                self.log2_table_size
            ));
        }
        if self.base_resolution < 2 || self.finest_resolution < self.base_resolution {
            return bad(format!(
                "resolutions must satisfy 2 <= base <= finest, got base {} finest {}",
                self.base_resolution, self.finest_resolution
            ));
        }
        // Keeps x·scale exact enough in f32 and hashed coordinates far from u32 overflow.
        if self.finest_resolution > 1 << 20 {
            return bad(format!(
                "finest_resolution must be at most 2^20, got {}",
                self.finest_resolution
            ));
        }
        Ok(())
    }
}

/// One level of a grid, as the kernels see it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LevelInfo {
    /// Position multiplier: x·scale + 0.5 is the position in vertex units.
    pub scale: f32,
    /// Vertices per axis, ceil(scale) + 1.
    pub resolution: u32,
    /// First entry of this level in the table.
    pub offset: u32,
    /// Entries of this level.
    pub size: u32,
    /// res³ ≤ size: one entry per vertex, no collisions (but see the wrap-around in the module docs).
    pub dense: bool,
}

impl LevelInfo {
    /// Entry (within this level) of grid vertex `g`.
    pub fn index(&self, g: [u32; 3]) -> u32 {
        if self.dense {
            dense_index(g, self.resolution, self.size)
        } else {
            hash_index(g, self.size)
        }
    }

    /// The lower vertex of `x`'s cell and the fraction within it (x already clamped to [0, 1]).
    fn locate(&self, x: [f32; 3]) -> ([u32; 3], [f32; 3]) {
        let mut base = [0u32; 3];
        let mut t = [0.0f32; 3];
        for d in 0..3 {
            let pos = x[d] * self.scale + 0.5;
            let fl = pos.floor();
            base[d] = fl as u32;
            t[d] = pos - fl;
        }
        (base, t)
    }

    /// The 8 corners of `x`'s cell: entry within the level and trilinear weight. Corner c has bit d set
    /// for the upper vertex along axis d; the order is tcnn's and the kernels'.
    fn corners(&self, x: [f32; 3]) -> ([u32; 8], [f32; 8]) {
        let (base, t) = self.locate(x);
        let mut entry = [0u32; 8];
        let mut weight = [0.0f32; 8];
        for c in 0..8 {
            let b = corner_bits(c);
            let w3 = corner_factors(t, b);
            weight[c] = w3[0] * w3[1] * w3[2];
            entry[c] = self.index([base[0] + b[0], base[1] + b[1], base[2] + b[2]]);
        }
        (entry, weight)
    }
}

fn corner_bits(c: usize) -> [u32; 3] {
    [c as u32 & 1, (c as u32 >> 1) & 1, (c as u32 >> 2) & 1]
}

fn corner_factors(t: [f32; 3], b: [u32; 3]) -> [f32; 3] {
    let f = |d: usize| if b[d] == 1 { t[d] } else { 1.0 - t[d] };
    [f(0), f(1), f(2)]
}

/// Dense vertex index, (x + y·res + z·res²) mod size, in wrapping u32 arithmetic like the kernel.
pub fn dense_index(g: [u32; 3], resolution: u32, size: u32) -> u32 {
    g[0].wrapping_add(g[1].wrapping_mul(resolution))
        .wrapping_add(g[2].wrapping_mul(resolution.wrapping_mul(resolution)))
        % size
}

/// tcnn's coherent prime hash, (x·1 ⊕ y·2654435761 ⊕ z·805459861) mod size.
pub fn hash_index(g: [u32; 3], size: u32) -> u32 {
    (g[0].wrapping_mul(PRIMES[0]) ^ g[1].wrapping_mul(PRIMES[1]) ^ g[2].wrapping_mul(PRIMES[2]))
        % size
}

/// A validated config with its per-level table layout; the CPU functions and the `record_*` kernels take it.
#[derive(Clone, Debug, PartialEq)]
pub struct HashGridLayout {
    pub config: HashGridConfig,
    pub levels: Vec<LevelInfo>,
    /// Entries over all levels.
    pub entries: u32,
}

impl HashGridLayout {
    pub fn new(config: &HashGridConfig) -> Result<Self, GpuError> {
        config.validate()?;
        let log2_b = config.per_level_scale().log2();
        let table = config.table_size() as u64;
        let mut levels = Vec::with_capacity(config.levels as usize);
        let mut offset = 0u64;
        for l in 0..config.levels {
            // f64 then one rounding: the same layout on every platform (see the module docs).
            let scale = ((l as f64 * log2_b).exp2() * config.base_resolution as f64 - 1.0) as f32;
            let resolution = scale.ceil() as u32 + 1;
            let dense_entries = (resolution as u64).pow(3);
            // Multiples of 8 (T is one too): tcnn's alignment, and whole vec4s for the gradient clear.
            let size = dense_entries.next_multiple_of(8).min(table);
            levels.push(LevelInfo {
                scale,
                resolution,
                offset: offset as u32,
                size: size as u32,
                dense: dense_entries <= size,
            });
            offset += size;
        }
        if offset * config.features_per_level as u64 > u32::MAX as u64 {
            return Err(GpuError::InvalidInput(format!(
                "hash grid: {offset} entries × {} features do not fit 32-bit indices",
                config.features_per_level
            )));
        }
        Ok(Self {
            config: *config,
            levels,
            entries: offset as u32,
        })
    }

    /// Parameter count (f32 words): entries × features per level.
    pub fn n_params(&self) -> usize {
        self.entries as usize * self.config.features_per_level as usize
    }

    /// Features per position: levels × features per level.
    pub fn output_dim(&self) -> usize {
        self.config.output_dim()
    }

    /// The parameter words of level `l`.
    pub fn level_params(&self, l: usize) -> Range<usize> {
        let f = self.config.features_per_level as usize;
        let lv = &self.levels[l];
        lv.offset as usize * f..(lv.offset + lv.size) as usize * f
    }

    /// A table initialised like tcnn's, U(−1e-4, 1e-4), reproducibly from `seed`.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed);
        (0..self.n_params())
            .map(|_| rng.random_range(-INIT_RANGE..INIT_RANGE))
            .collect()
    }

    fn check_params(&self, len: usize) -> Result<(), GpuError> {
        if len != self.n_params() {
            return Err(GpuError::InvalidInput(format!(
                "hash grid expects {} parameters, got {len}",
                self.n_params()
            )));
        }
        Ok(())
    }

    fn check_d_features(&self, n: usize, len: usize) -> Result<(), GpuError> {
        if len != n * self.output_dim() {
            return Err(GpuError::InvalidInput(format!(
                "hash grid: dL/dfeatures for {n} positions must hold {} values, got {len}",
                n * self.output_dim()
            )));
        }
        Ok(())
    }

    /// One position's features (a row of L·F).
    fn encode_point(&self, params: &[f32], x: [f32; 3], row: &mut [f32]) {
        let nf = self.config.features_per_level as usize;
        let x = clamp01(x);
        for (l, lv) in self.levels.iter().enumerate() {
            let (entry, weight) = lv.corners(x);
            for f in 0..nf {
                let mut acc = 0.0f32;
                for c in 0..8 {
                    acc += weight[c] * params[(lv.offset + entry[c]) as usize * nf + f];
                }
                row[l * nf + f] = acc;
            }
        }
    }

    /// dL/dx of one position, given its row of dL/dfeatures.
    fn position_grad(&self, params: &[f32], raw: [f32; 3], g_row: &[f32]) -> [f32; 3] {
        let nf = self.config.features_per_level as usize;
        let x = clamp01(raw);
        let mut dx = [0.0f32; 3];
        for (l, lv) in self.levels.iter().enumerate() {
            let g = &g_row[l * nf..(l + 1) * nf];
            let (base, t) = lv.locate(x);
            let mut dt = [0.0f32; 3];
            for c in 0..8 {
                let b = corner_bits(c);
                let entry = (lv.offset + lv.index([base[0] + b[0], base[1] + b[1], base[2] + b[2]]))
                    as usize
                    * nf;
                let mut v = 0.0f32;
                for f in 0..nf {
                    v += params[entry + f] * g[f];
                }
                let w3 = corner_factors(t, b);
                let others = [w3[1] * w3[2], w3[0] * w3[2], w3[0] * w3[1]];
                for d in 0..3 {
                    let sign = if b[d] == 1 { 1.0 } else { -1.0 };
                    dt[d] += v * sign * others[d];
                }
            }
            for d in 0..3 {
                dx[d] += dt[d] * lv.scale;
            }
        }
        for d in 0..3 {
            if !(0.0..=1.0).contains(&raw[d]) {
                dx[d] = 0.0;
            }
        }
        dx
    }
}

fn clamp01(x: [f32; 3]) -> [f32; 3] {
    x.map(|v| v.clamp(0.0, 1.0))
}

/// Parameter gradients, and position gradients when asked for.
#[derive(Clone, Debug, PartialEq)]
pub struct HashGridGradients {
    /// dL/dparams, laid out like the parameters.
    pub params: Vec<f32>,
    /// dL/dx per position (for density-gradient normals), if requested.
    pub positions: Option<Vec<[f32; 3]>>,
}

/// CPU reference forward: n positions → n rows of L·F features.
pub fn encode_cpu(
    config: &HashGridConfig,
    params: &[f32],
    positions: &[[f32; 3]],
) -> Result<Vec<f32>, GpuError> {
    let layout = HashGridLayout::new(config)?;
    layout.check_params(params.len())?;
    let d = layout.output_dim();
    let mut out = vec![0.0f32; positions.len() * d];
    out.par_chunks_mut(d)
        .zip(positions.par_iter())
        .with_min_len(256)
        .for_each(|(row, &x)| layout.encode_point(params, x, row));
    Ok(out)
}

/// CPU reference backward: dL/dparams (parallel over levels, which own disjoint slices of the table, so the
/// sums are deterministic) and, if `position_grads`, dL/dx (parallel over positions).
pub fn backward_cpu(
    config: &HashGridConfig,
    params: &[f32],
    positions: &[[f32; 3]],
    d_features: &[f32],
    position_grads: bool,
) -> Result<HashGridGradients, GpuError> {
    let layout = HashGridLayout::new(config)?;
    layout.check_params(params.len())?;
    layout.check_d_features(positions.len(), d_features.len())?;
    let nf = config.features_per_level as usize;
    let d = layout.output_dim();
    let mut grad = vec![0.0f32; layout.n_params()];
    let mut slices = Vec::with_capacity(layout.levels.len());
    let mut rest = grad.as_mut_slice();
    for lv in &layout.levels {
        let (head, tail) = rest.split_at_mut(lv.size as usize * nf);
        slices.push(head);
        rest = tail;
    }
    slices
        .into_par_iter()
        .zip(layout.levels.par_iter())
        .enumerate()
        .for_each(|(l, (slice, lv))| {
            for (p, &x) in positions.iter().enumerate() {
                let (entry, weight) = lv.corners(clamp01(x));
                for f in 0..nf {
                    let g = d_features[p * d + l * nf + f];
                    if g == 0.0 {
                        continue;
                    }
                    for c in 0..8 {
                        let v = weight[c] * g;
                        if v != 0.0 {
                            slice[entry[c] as usize * nf + f] += v;
                        }
                    }
                }
            }
        });
    let positions = position_grads.then(|| {
        positions
            .par_iter()
            .zip(d_features.par_chunks(d.max(1)))
            .with_min_len(64)
            .map(|(&x, g)| layout.position_grad(params, x, g))
            .collect()
    });
    Ok(HashGridGradients {
        params: grad,
        positions,
    })
}

/// dL/dposition only (no table gradients), for passes through a frozen field.
pub fn position_gradients_cpu(
    config: &HashGridConfig,
    params: &[f32],
    positions: &[[f32; 3]],
    d_features: &[f32],
) -> Result<Vec<[f32; 3]>, GpuError> {
    let layout = HashGridLayout::new(config)?;
    layout.check_params(params.len())?;
    layout.check_d_features(positions.len(), d_features.len())?;
    let d = layout.output_dim();
    Ok(positions
        .par_iter()
        .zip(d_features.par_chunks(d.max(1)))
        .with_min_len(64)
        .map(|(&x, g)| layout.position_grad(params, x, g))
        .collect())
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct LevelGpu {
    scale: f32,
    res: u32,
    offset: u32,
    size: u32,
    dense: u32,
    pad: [u32; 3],
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct GridUniform {
    /// n, levels, features, parameter words.
    dims: [u32; 4],
    /// backward_params' merge window (points per thread), padding.
    run: [u32; 4],
    levels: [LevelGpu; MAX_LEVELS as usize],
}

/// Consecutive points one `backward_params` thread sums before its atomic adds: consecutive samples of a
/// ray share cells at the coarse levels, where every thread of the batch would otherwise contend.
pub const MERGE_RUN: u32 = 8;

/// The WGSL prelude of a grid's pipelines: features per level as a constant.
fn prelude(layout: &HashGridLayout) -> String {
    format!("const NF: u32 = {}u;\n", layout.config.features_per_level)
}

fn uniform_for(layout: &HashGridLayout, n: u32) -> GridUniform {
    let mut u = GridUniform {
        dims: [
            n,
            layout.config.levels,
            layout.config.features_per_level,
            layout.n_params() as u32,
        ],
        run: [MERGE_RUN, 0, 0, 0],
        levels: [LevelGpu::zeroed(); MAX_LEVELS as usize],
    };
    for (dst, lv) in u.levels.iter_mut().zip(&layout.levels) {
        *dst = LevelGpu {
            scale: lv.scale,
            res: lv.resolution,
            offset: lv.offset,
            size: lv.size,
            dense: lv.dense as u32,
            pad: [0; 3],
        };
    }
    u
}

/// Positions already on the GPU: `n` points, 3 f32 each (x, y, z interleaved), in a caller-owned buffer
/// that may be larger than needed (reused across batches).
#[derive(Clone, Copy, Debug)]
pub struct GpuPositions<'a> {
    pub buffer: &'a wgpu::Buffer,
    pub n: u32,
}

fn need(buffer: &wgpu::Buffer, words: usize, what: &str) -> Result<(), GpuError> {
    let bytes = words as u64 * 4;
    if buffer.size() < bytes {
        return Err(GpuError::InvalidInput(format!(
            "hash grid: {what} buffer holds {} bytes, {bytes} needed",
            buffer.size()
        )));
    }
    Ok(())
}

/// Threads for one (level, point) pass; the folded dispatch takes up to 2^32 − 1 of them.
fn level_point_threads(layout: &HashGridLayout, n: u32) -> Result<u32, GpuError> {
    let threads = n as u64 * layout.config.levels as u64;
    u32::try_from(threads).map_err(|_| {
        GpuError::InvalidInput(format!(
            "hash grid: {n} positions × {} levels is too many for one dispatch",
            layout.config.levels
        ))
    })
}

/// Records the forward pass into `encoder`: `features` (n·L·F f32) ← grid(`params`, positions).
/// All buffers are the caller's, so passes chain without readbacks.
pub async fn record_encode(
    gpu: &Gpu,
    encoder: &mut wgpu::CommandEncoder,
    layout: &HashGridLayout,
    params: &wgpu::Buffer,
    positions: GpuPositions<'_>,
    features: &wgpu::Buffer,
) -> Result<(), GpuError> {
    let n = positions.n;
    let threads = level_point_threads(layout, n)?;
    need(params, layout.n_params(), "parameter")?;
    need(positions.buffer, n as usize * 3, "position")?;
    need(features, n as usize * layout.output_dim(), "feature")?;
    if n == 0 {
        return Ok(());
    }
    let u = gpu.uniform("hashgrid.grid", &uniform_for(layout, n));
    gpu.dispatch_variant(
        encoder,
        &KERNEL,
        &prelude(layout),
        "encode",
        &[(0, &u), (1, params), (2, positions.buffer), (3, features)],
        threads,
    )
    .await
}

/// Records dL/dparams into `d_params` (n_params words, f32 bits): cleared first unless `accumulate`, then
/// one atomic float add per (position, level, corner, feature) with a non-zero contribution.
pub async fn record_backward_params(
    gpu: &Gpu,
    encoder: &mut wgpu::CommandEncoder,
    layout: &HashGridLayout,
    positions: GpuPositions<'_>,
    d_features: &wgpu::Buffer,
    d_params: &wgpu::Buffer,
    accumulate: bool,
) -> Result<(), GpuError> {
    let n = positions.n;
    level_point_threads(layout, n)?;
    need(positions.buffer, n as usize * 3, "position")?;
    need(d_features, n as usize * layout.output_dim(), "dL/dfeatures")?;
    need(d_params, layout.n_params(), "dL/dparams")?;
    let u = gpu.uniform("hashgrid.grid", &uniform_for(layout, n));
    if !accumulate {
        gpu.dispatch_variant(
            encoder,
            &KERNEL,
            &prelude(layout),
            "clear_grad",
            &[(0, &u), (7, d_params)],
            layout.n_params() as u32 / 4,
        )
        .await?;
    }
    if n == 0 {
        return Ok(());
    }
    let threads = n.div_ceil(MERGE_RUN) * layout.config.levels;
    gpu.dispatch_variant(
        encoder,
        &KERNEL,
        &prelude(layout),
        "backward_params",
        &[
            (0, &u),
            (2, positions.buffer),
            (4, d_features),
            (5, d_params),
        ],
        threads,
    )
    .await
}

/// Records dL/dx into `d_positions` (3n f32): one thread per position over all levels, no atomics.
pub async fn record_backward_positions(
    gpu: &Gpu,
    encoder: &mut wgpu::CommandEncoder,
    layout: &HashGridLayout,
    params: &wgpu::Buffer,
    positions: GpuPositions<'_>,
    d_features: &wgpu::Buffer,
    d_positions: &wgpu::Buffer,
) -> Result<(), GpuError> {
    let n = positions.n;
    need(params, layout.n_params(), "parameter")?;
    need(positions.buffer, n as usize * 3, "position")?;
    need(d_features, n as usize * layout.output_dim(), "dL/dfeatures")?;
    need(d_positions, n as usize * 3, "dL/dx")?;
    if n == 0 {
        return Ok(());
    }
    let u = gpu.uniform("hashgrid.grid", &uniform_for(layout, n));
    gpu.dispatch_variant(
        encoder,
        &KERNEL,
        &prelude(layout),
        "backward_pos",
        &[
            (0, &u),
            (1, params),
            (2, positions.buffer),
            (4, d_features),
            (6, d_positions),
        ],
        n,
    )
    .await
}

fn position_count(positions: &[[f32; 3]]) -> Result<u32, GpuError> {
    u32::try_from(positions.len()).map_err(|_| {
        GpuError::InvalidInput(format!(
            "hash grid: {} positions is more than one call takes",
            positions.len()
        ))
    })
}

/// The WGSL forward on host data: uploads, one dispatch, one readback. Same result as [`encode_cpu`] up
/// to f32 rounding.
pub async fn encode_gpu(
    gpu: &Gpu,
    config: &HashGridConfig,
    params: &[f32],
    positions: &[[f32; 3]],
) -> Result<Vec<f32>, GpuError> {
    let layout = HashGridLayout::new(config)?;
    layout.check_params(params.len())?;
    let n = position_count(positions)?;
    let words = positions.len() * layout.output_dim();
    let b_params = gpu.upload("hashgrid params", params)?;
    let b_pos = gpu.upload("hashgrid positions", positions)?;
    let b_out = gpu.output("hashgrid features", words)?;
    let mut enc = gpu.encoder("hashgrid encode");
    let pos = GpuPositions { buffer: &b_pos, n };
    record_encode(gpu, &mut enc, &layout, &b_params, pos, &b_out).await?;
    let mut out = gpu.finish_and_read::<f32>(enc, &[(&b_out, words)]).await?;
    Ok(out.pop().unwrap_or_default())
}

/// The WGSL backward on host data: dL/dparams (and dL/dx if `position_grads`) in one submit.
pub async fn backward_gpu(
    gpu: &Gpu,
    config: &HashGridConfig,
    params: &[f32],
    positions: &[[f32; 3]],
    d_features: &[f32],
    position_grads: bool,
) -> Result<HashGridGradients, GpuError> {
    let layout = HashGridLayout::new(config)?;
    layout.check_params(params.len())?;
    layout.check_d_features(positions.len(), d_features.len())?;
    let n = position_count(positions)?;
    let b_pos = gpu.upload("hashgrid positions", positions)?;
    let b_dfeat = gpu.upload("hashgrid dL/dfeatures", d_features)?;
    let b_dparams = gpu.output("hashgrid dL/dparams", layout.n_params())?;
    let pos = GpuPositions { buffer: &b_pos, n };
    let mut enc = gpu.encoder("hashgrid backward");
    record_backward_params(gpu, &mut enc, &layout, pos, &b_dfeat, &b_dparams, false).await?;
    let mut reads = vec![(&b_dparams, layout.n_params())];
    let b_dpos;
    if position_grads {
        let b_params = gpu.upload("hashgrid params", params)?;
        b_dpos = gpu.output("hashgrid dL/dx", positions.len() * 3)?;
        record_backward_positions(gpu, &mut enc, &layout, &b_params, pos, &b_dfeat, &b_dpos)
            .await?;
        reads.push((&b_dpos, positions.len() * 3));
    }
    let mut out = gpu.finish_and_read::<f32>(enc, &reads).await?.into_iter();
    let params = out.next().unwrap_or_default();
    let positions = out.next().map(|d| {
        d.chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect::<Vec<_>>()
    });
    Ok(HashGridGradients { params, positions })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nerfacto_default_levels_follow_tcnn() {
        let cfg = HashGridConfig::default();
        let layout = HashGridLayout::new(&cfg).unwrap();
        assert!((cfg.per_level_scale() - 1.381_912_879_967_712).abs() < 1e-12);
        let l0 = layout.levels[0];
        // scale = base − 1, res = base: `base_resolution` counts vertices, not cells.
        assert_eq!(
            (l0.scale, l0.resolution, l0.size, l0.dense),
            (15.0, 16, 4096, true)
        );
        let last = layout.levels[15];
        assert_eq!((last.scale, last.resolution), (2047.0, 2048));
        assert!(!last.dense);
        assert_eq!(last.size, 1 << 19);
        // Level 1: 16·b − 1 = 21.11 → 23 vertices, 23³ = 12167 → 12168 entries (multiple of 8).
        let l1 = layout.levels[1];
        assert!((l1.scale - 21.110_606).abs() < 1e-4, "{}", l1.scale);
        assert_eq!((l1.resolution, l1.size, l1.dense), (23, 12_168, true));
        // Dense while res³ ≤ 2^19 (res ≤ 80).
        for lv in &layout.levels {
            assert_eq!(lv.dense, (lv.resolution as u64).pow(3) <= 1 << 19, "{lv:?}");
            assert_eq!(lv.size % 8, 0);
            assert_eq!(
                lv.resolution,
                lv.scale.ceil() as u32 + 1,
                "res = ceil(scale) + 1"
            );
        }
        let dense = layout.levels.iter().filter(|l| l.dense).count();
        assert_eq!(dense, 5, "{:?}", layout.levels);
        // Offsets are the running sum of sizes.
        let mut off = 0;
        for lv in &layout.levels {
            assert_eq!(lv.offset, off);
            off += lv.size;
        }
        assert_eq!(layout.entries, off);
        assert_eq!(layout.n_params(), off as usize * 2);
        assert_eq!(layout.output_dim(), 32);
        // Resolutions grow geometrically: res_l ≈ 16·b^l.
        for (l, lv) in layout.levels.iter().enumerate() {
            let ideal = 16.0 * cfg.per_level_scale().powi(l as i32) - 1.0;
            assert!((lv.scale as f64 - ideal).abs() < 1e-3 * ideal, "{l}");
        }
    }

    #[test]
    fn proposal_grids_and_single_level() {
        let layout = HashGridLayout::new(&HashGridConfig::proposal(128)).unwrap();
        let res: Vec<u32> = layout.levels.iter().map(|l| l.resolution).collect();
        assert_eq!(res.first(), Some(&16));
        assert_eq!(res.last(), Some(&128));
        let one = HashGridConfig {
            levels: 1,
            ..HashGridConfig::default()
        };
        let layout = HashGridLayout::new(&one).unwrap();
        assert_eq!(one.per_level_scale(), 1.0);
        assert_eq!(layout.levels[0].resolution, 16);
    }

    #[test]
    fn hash_and_dense_indices_match_hand_computed_values() {
        let g = [3u32, 5, 7];
        let h =
            (3u64 ^ ((5u64 * 2_654_435_761) & 0xffff_ffff) ^ ((7u64 * 805_459_861) & 0xffff_ffff))
                % 1024;
        assert_eq!(hash_index(g, 1024) as u64, h);
        // Wrapping products, as the u32 arithmetic of tcnn and WGSL.
        let big = [70_000u32, 90_000, 123_456];
        let expect = (70_000u32
            ^ 90_000u32.wrapping_mul(2_654_435_761)
            ^ 123_456u32.wrapping_mul(805_459_861))
            % (1 << 19);
        assert_eq!(hash_index(big, 1 << 19), expect);
        assert_eq!(dense_index([1, 2, 3], 10, 1000), 321);
        // The +0.5 offset lets a coordinate reach res; it wraps into the next row, then modulo the size.
        assert_eq!(dense_index([10, 0, 0], 10, 1000), 10);
        assert_eq!(dense_index([10, 10, 10], 10, 1000), 110);
        let dense = LevelInfo {
            scale: 9.0,
            resolution: 10,
            offset: 0,
            size: 1000,
            dense: true,
        };
        assert_eq!(dense.index([1, 2, 3]), 321);
        let hashed = LevelInfo {
            dense: false,
            size: 1024,
            ..dense
        };
        assert_eq!(hashed.index(g) as u64, h);
    }

    #[test]
    fn small_configs_mix_dense_and_hashed_levels() {
        let cfg = HashGridConfig {
            levels: 6,
            features_per_level: 2,
            log2_table_size: 11,
            base_resolution: 4,
            finest_resolution: 64,
        };
        let layout = HashGridLayout::new(&cfg).unwrap();
        let sizes: Vec<(u32, u32, bool)> = layout
            .levels
            .iter()
            .map(|l| (l.resolution, l.size, l.dense))
            .collect();
        // scale 4·16^(l/5) − 1 = 3, 5.96, 11.1, 20.1, 35.8, 63: levels 0-1 dense, 2-5 hashed.
        assert_eq!(sizes[0], (4, 64, true));
        assert_eq!(sizes[1], (7, 344, true), "7³ = 343 rounded up to 344");
        assert!(sizes.iter().any(|s| s.2) && sizes.iter().any(|s| !s.2));
        for s in &sizes {
            assert_eq!(s.2, (s.0 as u64).pow(3) <= 2048);
            if !s.2 {
                assert_eq!(s.1, 2048);
            }
        }
    }

    #[test]
    fn constant_table_interpolates_to_the_constant_everywhere() {
        let cfg = HashGridConfig {
            levels: 4,
            features_per_level: 2,
            log2_table_size: 10,
            base_resolution: 3,
            finest_resolution: 40,
        };
        let layout = HashGridLayout::new(&cfg).unwrap();
        let params = vec![0.75f32; layout.n_params()];
        let pts = [
            [0.0, 0.0, 0.0],
            [1.0, 1.0, 1.0],
            [0.3, 0.71, 0.05],
            [2.0, -1.0, 0.5],
        ];
        let out = encode_cpu(&cfg, &params, &pts).unwrap();
        assert!(out.iter().all(|&v| (v - 0.75).abs() < 1e-6), "{out:?}");
        // The weights are a partition of unity, so dL/dx of a constant field is zero.
        let g = vec![1.0f32; out.len()];
        let grads = backward_cpu(&cfg, &params, &pts, &g, true).unwrap();
        for d in grads.positions.unwrap() {
            assert!(d.iter().all(|v| v.abs() < 1e-3), "{d:?}");
        }
        // Each position puts total weight 1 per level and feature into the table.
        let total: f32 = grads.params.iter().sum();
        assert!((total - (pts.len() * layout.output_dim()) as f32).abs() < 1e-3);
    }

    #[test]
    fn vertex_positions_read_exactly_one_entry() {
        // scale = 4 (base 5): x = (2k − 1)/8 lands exactly on vertex k of the only level.
        let cfg = HashGridConfig {
            levels: 1,
            features_per_level: 1,
            log2_table_size: 10,
            base_resolution: 5,
            finest_resolution: 5,
        };
        let layout = HashGridLayout::new(&cfg).unwrap();
        assert_eq!(layout.levels[0].size, 128, "5³ = 125 rounded up to 128");
        let params: Vec<f32> = (0..layout.n_params()).map(|i| i as f32).collect();
        let out = encode_cpu(&cfg, &params, &[[0.375, 0.625, 0.125]]).unwrap();
        assert_eq!(out, vec![(2 + 3 * 5 + 25) as f32]);
    }

    #[test]
    fn invalid_configs_and_lengths_are_errors() {
        let base = HashGridConfig::default();
        for cfg in [
            HashGridConfig { levels: 0, ..base },
            HashGridConfig { levels: 33, ..base },
            HashGridConfig {
                features_per_level: 9,
                ..base
            },
            HashGridConfig {
                log2_table_size: 2,
                ..base
            },
            HashGridConfig {
                base_resolution: 1,
                ..base
            },
            HashGridConfig {
                finest_resolution: 8,
                ..base
            },
        ] {
            assert!(
                matches!(HashGridLayout::new(&cfg), Err(GpuError::InvalidInput(_))),
                "{cfg:?}"
            );
        }
        let err = encode_cpu(&base, &[0.0; 3], &[[0.5; 3]]).unwrap_err();
        assert!(err.to_string().contains("parameters"), "{err}");
    }

    #[test]
    fn init_is_small_uniform_and_reproducible() {
        let layout = HashGridLayout::new(&HashGridConfig::proposal(128)).unwrap();
        let a = layout.init_params(7);
        assert_eq!(a, layout.init_params(7));
        assert_eq!(a.len(), layout.n_params());
        assert!(a.iter().all(|v| v.abs() <= INIT_RANGE));
        let mean = a.iter().map(|&v| v as f64).sum::<f64>() / a.len() as f64;
        assert!(mean.abs() < 1e-6);
    }
}
