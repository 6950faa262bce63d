//! Small fully-connected networks: the building block of nerfacto's density head (32 → 64 → 16) and colour
//! head (63 → 64 → 64 → 3, sigmoid), forward and backward, on the GPU (`shaders/mlp.wgsl`) and on the CPU
//! (the reference, same f32 sums in the same order up to the GPU's fused multiply-adds).
//!
//! Layout rules, shared by both:
//! - linear layer l maps `fan_in` → `fan_out`: input → hidden, hidden → hidden (`hidden_layers − 1` times),
//!   hidden → output; with `hidden_layers = 0` a single input → output layer. Every width is 1..=64
//!   ([`MAX_WIDTH`]); no padding is visible outside the kernels (they pad rows to whole vec4s in workgroup
//!   memory and registers only), so any width, e.g. 63 or 7, is stored densely;
//! - parameters: one flat f32 vector, layer after layer, each its weights **row-major `[fan_out][fan_in]`**
//!   (PyTorch's `nn.Linear.weight`) followed by its `fan_out` biases ([`LayerInfo`] has the offsets);
//! - rows: input `[n][input]`, output `[n][output]`, dL/doutput and dL/dinput likewise, all dense;
//! - ReLU after every hidden layer; the output activation is None or Sigmoid (nerfacto's trunc_exp on the
//!   density logit is left to the caller: it touches one output);
//! - **saved** `[n][saved_per_row]`: the post-ReLU activations of every hidden layer, then the outputs again
//!   when the output activation is Sigmoid (y(1 − y) is its derivative). The forward passes activations
//!   from layer to layer through it (so inference needs it too); the backward reads its layer inputs and
//!   ReLU masks (`a > 0`) from it;
//! - **scratch** (backward only), [`MlpConfig::scratch_words`]: every layer's pre-activation gradient per row,
//!   then one partial parameter gradient per chunk of [`CHUNK_ROWS`] rows.
//!
//! Initialisation as tiny-cuda-nn: Xavier-uniform weights U(±√(6 / (fan_in + fan_out))) and zero biases (tcnn
//! has no biases; zero ones give the same function at step 0), reproducibly from a seed.
//!
//! Kernels (lavapipe-measured choices; see `shaders/mlp.wgsl`): one dispatch per layer for the forward and
//! for the backward to the pre-activation gradients and dL/dinput, one thread per row, the layer's weights
//! staged in workgroup memory so every lane reads the same address (a broadcast on CPU drivers such as
//! lavapipe, where per-lane gathers are slow and a barrier inside a per-layer loop cost ~30%), the product
//! generated as straight-line code per layer shape (`layer_products`). Parameter
//! gradients are reduced over the batch without float atomics: one workgroup per (chunk of rows, layer,
//! block of 16 input columns) sums δ_j·a_k over its chunk into a partial, then one thread per parameter
//! adds the partials in chunk order (under 1% of the backward on lavapipe), so GPU gradients are
//! deterministic run to run. [`forward_gpu`] and [`backward_gpu`] take host slices; the `record_*`
//! functions record into the caller's encoder over the caller's buffers, for the trainer.

use bytemuck::{Pod, Zeroable};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::gpu::{wgpu, Gpu, GpuError, Kernel};
use crate::shaders;

/// Widest layer (input, hidden or output) the kernels take: one 64 × 64 f32 weight matrix is exactly the
/// 16 KiB of workgroup memory the portable baseline grants.
pub const MAX_WIDTH: usize = 64;
/// Most hidden layers (a bound on the pipelines one MLP compiles: one per layer and kernel).
pub const MAX_HIDDEN_LAYERS: usize = 8;
/// Rows per partial parameter gradient in the backward: the batch is cut into chunks of this many rows,
/// each summed by its own workgroups, then the partials are added in order.
pub const CHUNK_ROWS: usize = 256;

const WORKGROUP: u32 = 64;
/// Most input columns per parameter-gradient workgroup (`WB` in mlp.wgsl): 16 for the straight-line sums
/// of a wide layer (its 256-row input tile then fills the 16 KiB of workgroup memory), 32 for the loops of
/// a narrow one (16 and 64 were slower there on lavapipe: more passes over the deltas, or accumulators
/// spilled).
const BLOCK: usize = 16;
const BLOCK_NARROW: usize = 32;
/// Rows per input tile of `backward_weights_rows` (`ROWS_TILE` in mlp.wgsl).
const ROWS_TILE: usize = 64;
/// Layers with fewer outputs take `backward_weights_rows`, whose loops run only the live outputs' lanes.
const NARROW_OUTPUTS: usize = 32;

fn narrow(layer: &LayerInfo) -> bool {
    layer.fan_out < NARROW_OUTPUTS
}

const KERNEL: Kernel = Kernel {
    name: "mlp",
    source: shaders::MLP,
    workgroup_size: WORKGROUP,
};

/// Element-wise activation after a layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Activation {
    None,
    Relu,
    Sigmoid,
}

/// The shape of a network. Hidden layers use ReLU (the only hidden activation supported); the output
/// activation is None or Sigmoid.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct MlpConfig {
    /// Input width, 1..=64.
    pub input: usize,
    /// Width of every hidden layer, 1..=64 (unused, but still validated, with no hidden layers).
    pub hidden: usize,
    /// Hidden layers, 0..=8 (nerfstudio's `num_layers` is this + 1).
    pub hidden_layers: usize,
    /// Output width, 1..=64.
    pub output: usize,
    pub hidden_activation: Activation,
    pub output_activation: Activation,
}

/// Where one linear layer lives in the parameter vector, in a saved row and in a scratch row.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LayerInfo {
    pub fan_in: usize,
    pub fan_out: usize,
    /// First weight; `W[j][k]` is at `weights + j·fan_in + k`.
    pub weights: usize,
    /// First bias; `b[j]` is at `bias + j`.
    pub bias: usize,
    /// Offset of this layer's output in a saved row (hidden layers, and the output layer under Sigmoid).
    pub saved: usize,
    /// Offset of this layer's pre-activation gradient in a scratch row.
    pub delta: usize,
}

impl MlpConfig {
    /// nerfacto's density head: 16 levels × 2 hash features → 64 (ReLU) → 1 density logit + 15 geo features.
    pub fn nerfacto_density() -> Self {
        Self {
            input: 32,
            hidden: 64,
            hidden_layers: 1,
            output: 16,
            hidden_activation: Activation::Relu,
            output_activation: Activation::None,
        }
    }

    /// nerfacto's colour head: 16 SH coefficients ⊕ 15 geo features ⊕ 32 appearance → 64 → 64 → RGB (sigmoid).
    pub fn nerfacto_colour() -> Self {
        Self {
            input: 63,
            hidden: 64,
            hidden_layers: 2,
            output: 3,
            hidden_activation: Activation::Relu,
            output_activation: Activation::Sigmoid,
        }
    }

    /// Linear layers: hidden layers + 1.
    pub fn n_layers(&self) -> usize {
        self.hidden_layers + 1
    }

    /// The layers in order, with their offsets.
    pub fn layers(&self) -> Vec<LayerInfo> {
        let mut out = Vec::with_capacity(self.n_layers());
        let (mut p, mut delta) = (0, 0);
        for l in 0..self.n_layers() {
            let fan_in = if l == 0 { self.input } else { self.hidden };
            let fan_out = if l == self.hidden_layers {
                self.output
            } else {
                self.hidden
            };
            out.push(LayerInfo {
                fan_in,
                fan_out,
                weights: p,
                bias: p + fan_in * fan_out,
                saved: l * self.hidden,
                delta,
            });
            p += (fan_in + 1) * fan_out;
            delta += fan_out;
        }
        out
    }

    /// Parameter count (f32 words): Σ (fan_in + 1)·fan_out.
    pub fn n_params(&self) -> usize {
        self.layers()
            .iter()
            .map(|l| (l.fan_in + 1) * l.fan_out)
            .sum()
    }

    /// Words per row of the saved activations: every hidden layer's, plus the outputs under Sigmoid.
    pub fn saved_per_row(&self) -> usize {
        let sig = self.output_activation == Activation::Sigmoid;
        self.hidden_layers * self.hidden + if sig { self.output } else { 0 }
    }

    /// Words per row of pre-activation gradients in the scratch: every layer's outputs.
    pub fn delta_per_row(&self) -> usize {
        self.hidden_layers * self.hidden + self.output
    }

    /// Chunks of [`CHUNK_ROWS`] rows in a batch of `n`: one partial parameter gradient each.
    pub fn chunks(n: usize) -> usize {
        n.div_ceil(CHUNK_ROWS)
    }

    /// Scratch words the backward needs for `n` rows: deltas, then per-chunk partial gradients.
    pub fn scratch_words(&self, n: usize) -> usize {
        n * self.delta_per_row() + Self::chunks(n) * self.n_params()
    }

    /// Xavier-uniform weights U(±√(6/(fan_in + fan_out))) as tcnn, zero biases, reproducibly from `seed`.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed);
        let mut params = vec![0.0f32; self.n_params()];
        for l in self.layers() {
            let a = (6.0 / (l.fan_in + l.fan_out) as f64).sqrt() as f32;
            for w in &mut params[l.weights..l.bias] {
                *w = rng.random_range(-a..a);
            }
        }
        params
    }

    /// Widths and activations the kernels support ([`GpuError::InvalidInput`] naming the field otherwise).
    pub fn validate(&self) -> Result<(), GpuError> {
        let bad = |what: String| Err(GpuError::InvalidInput(format!("MLP: {what}")));
        for (name, v) in [
            ("input", self.input),
            ("hidden", self.hidden),
            ("output", self.output),
        ] {
            if v == 0 || v > MAX_WIDTH {
                return bad(format!("{name} width must be 1..={MAX_WIDTH}, got {v}"));
            }
        }
        if self.hidden_layers > MAX_HIDDEN_LAYERS {
            return bad(format!(
                "hidden_layers must be 0..={MAX_HIDDEN_LAYERS}, got {}",
                self.hidden_layers
            ));
        }
        if self.hidden_activation != Activation::Relu {
            return bad(format!(
                "hidden activation must be Relu, got {:?}",
                self.hidden_activation
            ));
        }
        if self.output_activation == Activation::Relu {
            return bad("output activation must be None or Sigmoid, got Relu".into());
        }
        Ok(())
    }

    fn check_len(&self, what: &str, len: usize, want: usize) -> Result<(), GpuError> {
        if len != want {
            return Err(GpuError::InvalidInput(format!(
                "MLP: {what} must hold {want} values, got {len}"
            )));
        }
        Ok(())
    }

    /// Rows in `input` (validates the config and the lengths of params and input).
    fn rows(&self, params: &[f32], input: &[f32]) -> Result<usize, GpuError> {
        self.validate()?;
        self.check_len("parameters", params.len(), self.n_params())?;
        if !input.len().is_multiple_of(self.input) {
            return Err(GpuError::InvalidInput(format!(
                "MLP: input length {} is not a multiple of the input width {}",
                input.len(),
                self.input
            )));
        }
        Ok(input.len() / self.input)
    }
}

/// The forward's results: outputs `[n][output]` and the activations the backward needs
/// `[n][saved_per_row]`.
#[derive(Clone, Debug, PartialEq)]
pub struct MlpForward {
    pub output: Vec<f32>,
    pub saved: Vec<f32>,
}

/// The backward's results.
#[derive(Clone, Debug, PartialEq)]
pub struct MlpGradients {
    /// dL/dparams, laid out like the parameters.
    pub params: Vec<f32>,
    /// dL/dinput `[n][input]`, if requested (to chain into the encoding that produced the input).
    pub input: Option<Vec<f32>>,
}

/// Σ_q (x[4q]·w[4q] + … + x[4q+3]·w[4q+3]) after `acc`: the kernels' vec4 `dot` grouping.
fn dot_quads(mut acc: f32, x: &[f32], w: impl Fn(usize) -> f32) -> f32 {
    for (q, xs) in x.chunks(4).enumerate() {
        let mut s = 0.0f32;
        for (c, &v) in xs.iter().enumerate() {
            s += v * w(4 * q + c);
        }
        acc += s;
    }
    acc
}

fn sigmoid(z: f32) -> f32 {
    1.0 / (1.0 + (-z).exp())
}

/// One row through the network: the output and the saved activations. Stack buffers: tiny layers would
/// otherwise spend their time in the allocator.
fn forward_row(
    cfg: &MlpConfig,
    layers: &[LayerInfo],
    params: &[f32],
    x: &[f32],
    out: &mut [f32],
    saved: &mut [f32],
) {
    let mut a = [0.0f32; MAX_WIDTH];
    let mut z = [0.0f32; MAX_WIDTH];
    a[..x.len()].copy_from_slice(x);
    for (l, ly) in layers.iter().enumerate() {
        let last = l + 1 == layers.len();
        for (j, zj) in z[..ly.fan_out].iter_mut().enumerate() {
            let w = &params[ly.weights + j * ly.fan_in..][..ly.fan_in];
            let v = dot_quads(params[ly.bias + j], &a[..ly.fan_in], |k| w[k]);
            *zj = if !last {
                v.max(0.0)
            } else if cfg.output_activation == Activation::Sigmoid {
                sigmoid(v)
            } else {
                v
            };
        }
        let z = &z[..ly.fan_out];
        if !last || cfg.output_activation == Activation::Sigmoid {
            saved[ly.saved..ly.saved + ly.fan_out].copy_from_slice(z);
        }
        if last {
            out.copy_from_slice(z);
        }
        a[..ly.fan_out].copy_from_slice(z);
    }
}

/// CPU reference forward: `input` holds n rows of `config.input` values.
pub fn forward_cpu(
    config: &MlpConfig,
    params: &[f32],
    input: &[f32],
) -> Result<MlpForward, GpuError> {
    let n = config.rows(params, input)?;
    let layers = config.layers();
    let ss = config.saved_per_row();
    let mut output = vec![0.0f32; n * config.output];
    let mut saved = vec![0.0f32; n * ss];
    let rows = output
        .par_chunks_mut(config.output)
        .zip(input.par_chunks(config.input));
    if ss == 0 {
        rows.with_min_len(64)
            .for_each(|(out, x)| forward_row(config, &layers, params, x, out, &mut []));
    } else {
        rows.zip(saved.par_chunks_mut(ss))
            .with_min_len(64)
            .for_each(|((out, x), s)| forward_row(config, &layers, params, x, out, s));
    }
    Ok(MlpForward { output, saved })
}

/// One row's backward: its pre-activation gradients (all layers, a scratch row) and, if `dx` is not
/// empty, dL/dinput.
fn delta_row(
    cfg: &MlpConfig,
    layers: &[LayerInfo],
    params: &[f32],
    saved: &[f32],
    dy: &[f32],
    deltas: &mut [f32],
    dx: &mut [f32],
) {
    let lo = layers[layers.len() - 1];
    let mut g = [0.0f32; MAX_WIDTH];
    let mut h = [0.0f32; MAX_WIDTH];
    for (j, (gj, &v)) in g.iter_mut().zip(dy).enumerate() {
        *gj = if cfg.output_activation == Activation::Sigmoid {
            let y = saved[lo.saved + j];
            v * (y * (1.0 - y))
        } else {
            v
        };
    }
    deltas[lo.delta..lo.delta + lo.fan_out].copy_from_slice(&g[..lo.fan_out]);
    for l in (0..layers.len()).rev() {
        let ly = layers[l];
        if l == 0 && dx.is_empty() {
            break;
        }
        // δ_below[k] = Σ_j W[j][k]·δ[j], masked by the ReLU of the layer below (none for the input).
        for (k, hk) in h[..ly.fan_in].iter_mut().enumerate() {
            let v = dot_quads(0.0, &g[..ly.fan_out], |j| {
                params[ly.weights + j * ly.fan_in + k]
            });
            *hk = if l > 0 && saved[layers[l - 1].saved + k] <= 0.0 {
                0.0
            } else {
                v
            };
        }
        let h = &h[..ly.fan_in];
        if l > 0 {
            let below = layers[l - 1];
            deltas[below.delta..below.delta + below.fan_out].copy_from_slice(h);
        } else {
            dx.copy_from_slice(h);
        }
        g[..ly.fan_in].copy_from_slice(h);
    }
}

/// CPU reference backward, given the forward's `saved` activations and dL/doutput: dL/dparams and, if
/// `input_grads`, dL/dinput. Sums as the kernels: per chunk of [`CHUNK_ROWS`] rows (parallel), rows in
/// order, then the chunks in order; deterministic.
pub fn backward_cpu(
    config: &MlpConfig,
    params: &[f32],
    input: &[f32],
    saved: &[f32],
    d_output: &[f32],
    input_grads: bool,
) -> Result<MlpGradients, GpuError> {
    let n = config.rows(params, input)?;
    let ss = config.saved_per_row();
    config.check_len("saved activations", saved.len(), n * ss)?;
    config.check_len("dL/doutput", d_output.len(), n * config.output)?;
    let layers = config.layers();
    let np = config.n_params();
    let (ni, ds) = (config.input, config.delta_per_row());
    // Without input gradients, one row-sized buffer per chunk stands in (and stays empty for delta_row).
    let mut d_input = vec![0.0f32; if input_grads { n * ni } else { 0 }];
    let mut chunks: Vec<&mut [f32]> = if input_grads {
        d_input.chunks_mut(CHUNK_ROWS * ni).collect()
    } else {
        Vec::new()
    };
    chunks.resize_with(MlpConfig::chunks(n), Default::default);
    let partials: Vec<Vec<f32>> = chunks
        .into_par_iter()
        .enumerate()
        .map(|(c, dx_chunk)| {
            let mut part = vec![0.0f32; np];
            let mut deltas = vec![0.0f32; ds];
            let rows = CHUNK_ROWS.min(n - c * CHUNK_ROWS);
            for i in 0..rows {
                let r = c * CHUNK_ROWS + i;
                let dx: &mut [f32] = if input_grads {
                    &mut dx_chunk[i * ni..(i + 1) * ni]
                } else {
                    &mut []
                };
                let srow = &saved[r * ss..(r + 1) * ss];
                let dy = &d_output[r * config.output..(r + 1) * config.output];
                delta_row(config, &layers, params, srow, dy, &mut deltas, dx);
                for (l, ly) in layers.iter().enumerate() {
                    let a = if l == 0 {
                        &input[r * ni..(r + 1) * ni]
                    } else {
                        let below = layers[l - 1];
                        &srow[below.saved..below.saved + below.fan_out]
                    };
                    for j in 0..ly.fan_out {
                        let d = deltas[ly.delta + j];
                        let w = &mut part[ly.weights + j * ly.fan_in..][..ly.fan_in];
                        for (wk, &ak) in w.iter_mut().zip(a) {
                            *wk += d * ak;
                        }
                        part[ly.bias + j] += d;
                    }
                }
            }
            part
        })
        .collect();
    let mut grad = vec![0.0f32; np];
    for part in &partials {
        for (g, p) in grad.iter_mut().zip(part) {
            *g += p;
        }
    }
    Ok(MlpGradients {
        params: grad,
        input: input_grads.then_some(d_input),
    })
}

/// The forward of [`forward_cpu`] written for speed (the CPU training fallback and renderer): per chunk of
/// rows, one `matrixmultiply::sgemm` per layer (bias rows first, then C += A·Wᵀ, read straight from the
/// parameter layout through strides), hidden outputs written into the saved rows in place. Same layout and
/// results up to summation order.
pub fn forward_fast(
    config: &MlpConfig,
    params: &[f32],
    input: &[f32],
) -> Result<MlpForward, GpuError> {
    const CHUNK: usize = 256;
    let n = config.rows(params, input)?;
    let layers = config.layers();
    let ss = config.saved_per_row();
    let no = config.output;
    let ni = config.input;
    let mut output = vec![0.0f32; n * no];
    let mut saved = vec![0.0f32; n * ss];
    let sig = config.output_activation == Activation::Sigmoid;
    let body = |x: &[f32], out: &mut [f32], sv: &mut [f32]| {
        let rows = x.len() / ni;
        for (l, ly) in layers.iter().enumerate() {
            let last = l + 1 == layers.len();
            let fo = ly.fan_out;
            // Destination: the saved rows (hidden layers; the output layer under Sigmoid) or the output.
            let (dst_off, dst_stride) = if !last || sig {
                (ly.saved, ss)
            } else {
                (0, no)
            };
            // Source: the input rows, or the previous layer's saved rows.
            let (src, src_stride): (&[f32], usize) = if l == 0 {
                (x, ni)
            } else {
                (&sv[layers[l - 1].saved..], ss)
            };
            let mut c = vec![0.0f32; rows * fo];
            for r in 0..rows {
                c[r * fo..(r + 1) * fo].copy_from_slice(&params[ly.bias..ly.bias + fo]);
            }
            let w = &params[ly.weights..ly.weights + fo * ly.fan_in];
            // SAFETY: the pointers cover rows × fan_in (A, row stride src_stride), fan_in × fan_out (B = Wᵀ:
            // element (k, j) at j·fan_in + k) and rows × fan_out (C, contiguous), all inside their slices.
            unsafe {
                matrixmultiply::sgemm(
                    rows,
                    ly.fan_in,
                    fo,
                    1.0,
                    src.as_ptr(),
                    src_stride as isize,
                    1,
                    w.as_ptr(),
                    1,
                    ly.fan_in as isize,
                    1.0,
                    c.as_mut_ptr(),
                    fo as isize,
                    1,
                );
            }
            let dst: &mut [f32] = if !last || sig { &mut *sv } else { &mut *out };
            for r in 0..rows {
                let d = &mut dst[r * dst_stride + dst_off..r * dst_stride + dst_off + fo];
                for (dj, &cj) in d.iter_mut().zip(&c[r * fo..(r + 1) * fo]) {
                    *dj = if !last {
                        cj.max(0.0)
                    } else if sig {
                        sigmoid(cj)
                    } else {
                        cj
                    };
                }
            }
            if last && sig {
                for r in 0..rows {
                    out[r * no..(r + 1) * no]
                        .copy_from_slice(&sv[r * ss + ly.saved..r * ss + ly.saved + no]);
                }
            }
        }
    };
    if ss == 0 {
        output
            .par_chunks_mut(no * CHUNK)
            .zip(input.par_chunks(ni * CHUNK))
            .for_each(|(o, x)| body(x, o, &mut []));
    } else {
        output
            .par_chunks_mut(no * CHUNK)
            .zip(input.par_chunks(ni * CHUNK))
            .zip(saved.par_chunks_mut(ss * CHUNK))
            .for_each(|((o, x), s)| body(x, o, s));
    }
    Ok(MlpForward { output, saved })
}

/// The backward of [`backward_cpu`] written for speed: per chunk of rows a partial gradient from GEMMs
/// (dW += Gᵀ·A, dL/dinput = G·W, `matrixmultiply::sgemm`); the partials are added in chunk order
/// (deterministic).
pub fn backward_fast(
    config: &MlpConfig,
    params: &[f32],
    input: &[f32],
    saved: &[f32],
    d_output: &[f32],
    input_grads: bool,
) -> Result<MlpGradients, GpuError> {
    backward_chunked(config, params, input, saved, d_output, true, input_grads)
}

/// dL/dinput only (no parameter gradients: half the GEMMs), for passes through a frozen field.
pub fn input_gradient_fast(
    config: &MlpConfig,
    params: &[f32],
    input: &[f32],
    saved: &[f32],
    d_output: &[f32],
) -> Result<Vec<f32>, GpuError> {
    Ok(
        backward_chunked(config, params, input, saved, d_output, false, true)?
            .input
            .unwrap_or_default(),
    )
}

fn backward_chunked(
    config: &MlpConfig,
    params: &[f32],
    input: &[f32],
    saved: &[f32],
    d_output: &[f32],
    param_grads: bool,
    input_grads: bool,
) -> Result<MlpGradients, GpuError> {
    let n = config.rows(params, input)?;
    let ss = config.saved_per_row();
    config.check_len("saved activations", saved.len(), n * ss)?;
    config.check_len("dL/doutput", d_output.len(), n * config.output)?;
    let layers = config.layers();
    let np = config.n_params();
    let ni = config.input;
    let no = config.output;
    let sig = config.output_activation == Activation::Sigmoid;
    const CH: usize = 1024;
    let mut d_input = vec![0.0f32; if input_grads { n * ni } else { 0 }];
    let mut dx_chunks: Vec<&mut [f32]> = if input_grads {
        d_input.chunks_mut(CH * ni).collect()
    } else {
        Vec::new()
    };
    let nch = n.div_ceil(CH);
    dx_chunks.resize_with(nch, Default::default);
    let partials: Vec<Vec<f32>> = dx_chunks
        .into_par_iter()
        .enumerate()
        .map(|(c, dx_chunk)| {
            let mut part = vec![0.0f32; if param_grads { np } else { 0 }];
            let r0 = c * CH;
            let rows = (n - r0).min(CH);
            // G: dL/d(pre-activation) of the current layer, rows × fan_out; H: dL/d(its input).
            let lo = layers[layers.len() - 1];
            let mut g = vec![0.0f32; rows * no];
            for i in 0..rows {
                let r = r0 + i;
                for j in 0..no {
                    let v = d_output[r * no + j];
                    g[i * no + j] = if sig {
                        let y = saved[r * ss + lo.saved + j];
                        v * y * (1.0 - y)
                    } else {
                        v
                    };
                }
            }
            for l in (0..layers.len()).rev() {
                let ly = layers[l];
                let (fi, fo) = (ly.fan_in, ly.fan_out);
                // This layer's input rows: the MLP input, or the previous layer's saved output.
                let (a, a_stride): (&[f32], usize) = if l == 0 {
                    (&input[r0 * ni..], ni)
                } else {
                    (&saved[r0 * ss + layers[l - 1].saved..], ss)
                };
                if param_grads {
                    for i in 0..rows {
                        for (pb, gj) in part[ly.bias..ly.bias + fo].iter_mut().zip(&g[i * fo..]) {
                            *pb += gj;
                        }
                    }
                }
                let w = &params[ly.weights..ly.weights + fo * fi];
                let need_h = l > 0 || input_grads;
                let mut h = vec![0.0f32; if need_h { rows * fi } else { 0 }];
                // SAFETY: every operand lies inside its slice: G is rows × fo (contiguous), A is rows × fi
                // at row stride a_stride (a holds at least (rows − 1)·a_stride + fi values), the weight
                // gradient and W are fo × fi row-major, H is rows × fi.
                unsafe {
                    // dW += Gᵀ·A.
                    if param_grads {
                        matrixmultiply::sgemm(
                            fo,
                            rows,
                            fi,
                            1.0,
                            g.as_ptr(),
                            1,
                            fo as isize,
                            a.as_ptr(),
                            a_stride as isize,
                            1,
                            1.0,
                            part[ly.weights..].as_mut_ptr(),
                            fi as isize,
                            1,
                        );
                    }
                    if need_h {
                        // H = G·W.
                        matrixmultiply::sgemm(
                            rows,
                            fo,
                            fi,
                            1.0,
                            g.as_ptr(),
                            fo as isize,
                            1,
                            w.as_ptr(),
                            fi as isize,
                            1,
                            0.0,
                            h.as_mut_ptr(),
                            fi as isize,
                            1,
                        );
                    }
                }
                if l > 0 {
                    // Through the previous layer's ReLU: its saved output is > 0 where it passed.
                    for i in 0..rows {
                        for k in 0..fi {
                            if a[i * a_stride + k] <= 0.0 {
                                h[i * fi + k] = 0.0;
                            }
                        }
                    }
                    g = h;
                } else if input_grads {
                    dx_chunk[..rows * ni].copy_from_slice(&h);
                }
            }
            part
        })
        .collect();
    let mut grad = vec![0.0f32; if param_grads { np } else { 0 }];
    for part in &partials {
        for (g, p) in grad.iter_mut().zip(part) {
            *g += p;
        }
    }
    Ok(MlpGradients {
        params: grad,
        input: input_grads.then_some(d_input),
    })
}

const FLAG_D_INPUT: u32 = 1;
const FLAG_ACCUMULATE: u32 = 2;

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct MlpUniform {
    /// n, flags, n_params, partial offset, chunk rows, chunks, padding (the layer's shape is in the
    /// pipeline's prelude, [`layer_prelude`]).
    head: [u32; 8],
}

/// Whether `layer`'s parameter gradients take `backward_weights_rows` (loops) rather than the straight-line
/// `backward_weights`: on every adapter but lavapipe ([`Gpu::straight_line_kernels`]), and there for
/// narrow layers.
fn rows_kernel(layer: &LayerInfo, straight: bool) -> bool {
    !straight || narrow(layer)
}

/// Input columns per parameter-gradient workgroup of `layer`: [`BLOCK`] or [`BLOCK_NARROW`], or fewer (a
/// multiple of 4) for a narrower layer, so no workgroup sums columns that do not exist.
fn layer_block(layer: &LayerInfo, straight: bool) -> usize {
    let most = if rows_kernel(layer, straight) {
        BLOCK_NARROW
    } else {
        BLOCK
    };
    most.min(layer.fan_in.next_multiple_of(4)).max(4)
}

/// Parameter-gradient workgroups for one layer and chunk: its input columns [`layer_block`] at a time
/// (the first also sums the bias).
fn layer_blocks(layer: &LayerInfo, straight: bool) -> usize {
    layer.fan_in.div_ceil(layer_block(layer, straight)).max(1)
}

fn uniform_for(cfg: &MlpConfig, n: u32, flags: u32) -> MlpUniform {
    let chunks = MlpConfig::chunks(n as usize);
    MlpUniform {
        head: [
            n as usize,
            flags as usize,
            cfg.n_params(),
            n as usize * cfg.delta_per_row(),
            CHUNK_ROWS,
            chunks,
            0,
            0,
        ]
        .map(|v| v as u32),
    }
}

/// WGSL constants that specialise `forward_layer` / `backward_layer` to layer `l` of `cfg` (see the header
/// of mlp.wgsl); `None` gives the neutral prelude the shape-independent entry points compile with.
fn layer_prelude(cfg: &MlpConfig, l: Option<usize>, straight: bool) -> String {
    let ly = l.map(|l| cfg.layers()[l]);
    let ws_len = ly.map_or(1, |ly| {
        (ly.fan_out * ly.fan_in.div_ceil(4).max(1)).max(ly.fan_in * ly.fan_out.div_ceil(4).max(1))
    });
    layer_consts(cfg, l, straight, ws_len)
        + "const F_OUT: u32 = 1u;\nfn stage_fused(li: u32) {}\n\
           fn fused_forward(a: array<vec4<f32>, K4>) -> array<f32, F_OUT> {\n    var o: array<f32, F_OUT>;\n    return o;\n}\n"
}

/// The constants and products of layer `l`'s pipelines (see [`layer_prelude`]), `ws_len` vec4 words of
/// staged weights.
fn layer_consts(cfg: &MlpConfig, l: Option<usize>, straight: bool, ws_len: usize) -> String {
    let layers = cfg.layers();
    let (ly, below) = match l {
        Some(l) => (layers[l], l.checked_sub(1).map(|b| layers[b])),
        None => (
            LayerInfo {
                fan_in: 0,
                fan_out: 0,
                weights: 0,
                bias: 0,
                saved: 0,
                delta: 0,
            },
            None,
        ),
    };
    let last = l == Some(cfg.n_layers() - 1);
    format!(
        "const L_IN: u32 = {}u;\nconst L_OUT: u32 = {}u;\nconst L_W: u32 = {}u;\nconst L_B: u32 = {}u;\n\
         const L_SAVED: u32 = {}u;\nconst L_DELTA: u32 = {}u;\nconst L_FIRST: bool = {};\nconst L_LAST: bool = {};\n\
         const L_SIGMOID: bool = {};\nconst L_BELOW_SAVED: u32 = {}u;\nconst L_BELOW_DELTA: u32 = {}u;\n\
         const SAVED_STRIDE: u32 = {}u;\nconst DELTA_STRIDE: u32 = {}u;\nconst WB: u32 = {}u;\nconst CHUNK: u32 = {}u;\n\
         const ROWS_TILE: u32 = {ROWS_TILE}u;\nconst STAGED_ROWS: u32 = {}u;\nconst WS_LEN: u32 = {}u;\n",
        ly.fan_in,
        ly.fan_out,
        ly.weights,
        ly.bias,
        ly.saved,
        ly.delta,
        l == Some(0),
        last,
        last && cfg.output_activation == Activation::Sigmoid,
        below.map_or(0, |b| b.saved),
        below.map_or(0, |b| b.delta),
        cfg.saved_per_row(),
        cfg.delta_per_row(),
        layer_block(&ly, straight),
        CHUNK_ROWS,
        if rows_kernel(&ly, straight) {
            ROWS_TILE
        } else {
            CHUNK_ROWS
        },
        ws_len.max(1),
    ) + &layer_products(
        ly.fan_in,
        ly.fan_out,
        layer_block(&ly, straight),
        straight,
        !rows_kernel(&ly, straight),
    )
}

/// The layer's matrix products as straight-line WGSL, one block per output (`layer_dense`, forward) and per
/// input (`layer_dense_t`, transposed, backward), each an unrolled dot product against the weights staged
/// in workgroup memory. Why generated: lavapipe (Mesa's CPU driver) loads a workgroup word whose address
/// is the same on every lane as one scalar load and a broadcast only outside all control flow; inside any
/// loop it loads lane by lane. With a loop over the outputs the forward of a 64 × 64 layer took 50 ms for
/// 49 k rows, straight-line 14-20 ms (2026-12-03). Other adapters get the same products as loops
/// (`straight` false, `STRAIGHT` in the WGSL): the kernels then run their own loops, GPUs unroll them
/// themselves, and Chromium's SwiftShader ran the straight form's shape at half speed even with loops inside.
fn layer_products(
    fan_in: usize,
    fan_out: usize,
    block: usize,
    straight: bool,
    sums: bool,
) -> String {
    if !straight {
        // The kernels' loop form runs its own loops (mlp.wgsl, under `!STRAIGHT`); these only compile.
        return "const STRAIGHT: bool = false;\n\
                fn layer_dense(a: array<vec4<f32>, K4>) -> array<f32, O_N> {\n    var o: array<f32, O_N>;\n    return o;\n}\n\
                fn layer_dense_t(g: array<vec4<f32>, M4>) -> array<f32, I_N> {\n    var o: array<f32, I_N>;\n    return o;\n}\n\
                fn weight_sums(r0: u32, j: u32) -> array<vec4<f32>, WB4 + 1u> {\n    \
                var o: array<vec4<f32>, WB4 + 1u>;\n    return o;\n}\n"
            .to_string();
    }
    let mut s = String::from(
        "const STRAIGHT: bool = true;\n\
         fn layer_dense(a: array<vec4<f32>, K4>) -> array<f32, O_N> {\n    var o: array<f32, O_N>;\n",
    );
    for j in 0..fan_out {
        s += &format!(
            "    {{ var acc = vec4<f32>(0.0); for (var q = 0u; q < K4; q++) {{ acc += a[q] * ws[{j}u * K4 + q]; }} \
             o[{j}] = (acc.x + acc.y) + (acc.z + acc.w); }}\n"
        );
    }
    s += "    return o;\n}\nfn layer_dense_t(g: array<vec4<f32>, M4>) -> array<f32, I_N> {\n    var o: array<f32, I_N>;\n";
    for k in 0..fan_in {
        s += &format!(
            "    {{ var acc = vec4<f32>(0.0); for (var q = 0u; q < M4; q++) {{ acc += g[q] * ws[{k}u * M4 + q]; }} \
             o[{k}] = (acc.x + acc.y) + (acc.z + acc.w); }}\n"
        );
    }
    s += "    return o;\n}\n";
    // backward_weights: lane j's sums over the staged chunk of δ_j · a_k for the block's columns (one
    // vec4 per four), and of δ_j (the bias) in the last entry's x.
    let b4 = block / 4;
    s += &format!(
        "fn weight_sums(r0: u32, j: u32) -> array<vec4<f32>, {}> {{\n    var o: array<vec4<f32>, {}>;\n\
         var d: array<f32, CHUNK>;\n    for (var r = 0u; r < CHUNK; r++) {{ d[r] = delta_or_zero(r0 + r, j); }}\n",
        b4 + 1,
        b4 + 1
    );
    // A narrow layer's sums are backward_weights_rows' loops: no straight-line ones (its 256 x 32 input
    // tile would not fit).
    for r in (0..CHUNK_ROWS).filter(|_| sums) {
        s += &format!("    o[{b4}].x += d[{r}];");
        for q in 0..b4 {
            s += &format!(" o[{q}] += d[{r}] * tile[{}u];", r * b4 + q);
        }
        s += "\n";
    }
    s + "    return o;\n}\n"
}

/// What [`fused_prelude`] stages in workgroup memory, within `vec4s` words: each layer's weights
/// `[fan_out][⌈fan_in/4⌉]`, layer after layer while they fit (a later layer that does not, such as the
/// colour head's last behind its two 64 × 64 ones in 32 KiB, is read from `params` at lane-uniform
/// addresses, like every bias). Returns the words staged and each layer's offset if staged.
fn fused_layout(cfg: &MlpConfig, vec4s: usize) -> (usize, Vec<Option<usize>>) {
    let mut at = 0;
    let offsets = cfg
        .layers()
        .iter()
        .map(|ly| {
            let words = ly.fan_out * ly.fan_in.div_ceil(4).max(1);
            (at + words <= vec4s).then(|| {
                at += words;
                at - words
            })
        })
        .collect();
    (at, offsets)
}

/// Vec4 words of workgroup memory `gpu` gives a workgroup (lavapipe: 32 KiB).
fn workgroup_vec4s(gpu: &Gpu) -> usize {
    gpu.device.limits().max_compute_workgroup_storage_size as usize / 16
}

/// The prelude of `forward_fused`: layer 0's (its input row loader) plus the whole network's staging and
/// straight-line forward, each hidden row kept in the lane (one vec4 array per layer, constant indices).
fn fused_prelude(cfg: &MlpConfig, vec4s: usize) -> String {
    let (len, offsets) = fused_layout(cfg, vec4s);
    let layers = cfg.layers();
    let last = layers.len() - 1;
    let mut s = layer_consts(cfg, Some(0), true, len.max(1));
    s += &format!(
        "const F_OUT: u32 = {}u;\nfn stage_fused(li: u32) {{\n",
        cfg.output
    );
    for (ly, w) in layers.iter().zip(&offsets) {
        let Some(w) = w else { continue };
        let k4 = ly.fan_in.div_ceil(4).max(1);
        let (fi, fo) = (ly.fan_in, ly.fan_out);
        let word = |c: usize| {
            format!(
                "param_or_zero({}u + j * {fi}u + k + {c}u, k + {c}u < {fi}u)",
                ly.weights
            )
        };
        s += &format!(
            "    for (var s = li; s < {}u; s += WG) {{\n        let j = s / {k4}u;\n        let k = 4u * (s - j * {k4}u);\n        \
             ws[{w}u + s] = vec4<f32>({}, {}, {}, {});\n    }}\n",
            fo * k4,
            word(0),
            word(1),
            word(2),
            word(3)
        );
    }
    s += "}\nfn fused_forward(x0: array<vec4<f32>, K4>) -> array<f32, F_OUT> {\n    var o: array<f32, F_OUT>;\n";
    for (l, (ly, w)) in layers.iter().zip(&offsets).enumerate() {
        let k4 = ly.fan_in.div_ceil(4).max(1);
        let fi = ly.fan_in;
        if l < last {
            s += &format!(
                "    var x{}: array<vec4<f32>, {}>;\n",
                l + 1,
                ly.fan_out.div_ceil(4).max(1)
            );
        }
        for j in 0..ly.fan_out {
            let z = format!(
                "params[{}u] + ((acc.x + acc.y) + (acc.z + acc.w))",
                ly.bias + j
            );
            let store = if l < last {
                format!("x{}[{}][{}] = max({z}, 0.0);", l + 1, j / 4, j % 4)
            } else if cfg.output_activation == Activation::Sigmoid {
                format!("o[{j}] = sigmoid1({z});")
            } else {
                format!("o[{j}] = {z};")
            };
            let weights = match w {
                Some(w) => format!("ws[{}u + q]", w + j * k4),
                None => {
                    let at = ly.weights + j * fi;
                    let word = |c: usize| {
                        format!("param_or_zero({at}u + 4u * q + {c}u, 4u * q + {c}u < {fi}u)")
                    };
                    format!(
                        "vec4<f32>({}, {}, {}, {})",
                        word(0),
                        word(1),
                        word(2),
                        word(3)
                    )
                }
            };
            s += &format!(
                "    {{ var acc = vec4<f32>(0.0); for (var q = 0u; q < {k4}u; q++) {{ acc += x{l}[q] * {weights}; }} {store} }}\n"
            );
        }
    }
    s + "    return o;\n}\n"
}

fn need(buffer: &wgpu::Buffer, words: usize, what: &str) -> Result<(), GpuError> {
    let bytes = words as u64 * 4;
    if buffer.size() < bytes {
        return Err(GpuError::InvalidInput(format!(
            "MLP: {what} buffer holds {} bytes, {bytes} needed",
            buffer.size()
        )));
    }
    Ok(())
}

/// Refuses batches whose word indices would not fit the kernels' u32 arithmetic.
fn check_batch(cfg: &MlpConfig, n: u32) -> Result<(), GpuError> {
    cfg.validate()?;
    let widest = [cfg.input, cfg.output, cfg.saved_per_row()]
        .into_iter()
        .max()
        .unwrap_or(0);
    let words = (cfg.scratch_words(n as usize) as u64).max(n as u64 * widest as u64);
    if words > u32::MAX as u64 {
        return Err(GpuError::InvalidInput(format!(
            "MLP: a batch of {n} rows needs {words} words in one buffer, more than 32-bit indices reach"
        )));
    }
    Ok(())
}

/// The forward's buffers on the GPU, all the caller's.
#[derive(Clone, Copy, Debug)]
pub struct ForwardBuffers<'a> {
    /// [`MlpConfig::n_params`] words.
    pub params: &'a wgpu::Buffer,
    /// `[n][input]`.
    pub input: &'a wgpu::Buffer,
    /// `[n][output]`, written.
    pub output: &'a wgpu::Buffer,
    /// `[n][saved_per_row]`, written: the layers pass their outputs through it (inference too), and the
    /// backward reads it.
    pub saved: &'a wgpu::Buffer,
}

/// The backward's buffers on the GPU, all the caller's.
#[derive(Clone, Copy, Debug)]
pub struct BackwardBuffers<'a> {
    pub params: &'a wgpu::Buffer,
    /// The forward's input `[n][input]`.
    pub input: &'a wgpu::Buffer,
    /// The forward's saved activations `[n][saved_per_row]`.
    pub saved: &'a wgpu::Buffer,
    /// dL/doutput `[n][output]`.
    pub d_output: &'a wgpu::Buffer,
    /// [`MlpConfig::scratch_words`]`(n)` words, contents irrelevant.
    pub scratch: &'a wgpu::Buffer,
    /// dL/dparams, [`MlpConfig::n_params`] words: overwritten, or added to with `accumulate`; `None`
    /// skips the parameter gradients (the uncertainty pass wants dL/dinput only).
    pub d_params: Option<&'a wgpu::Buffer>,
    /// dL/dinput `[n][input]`, overwritten; `None` skips the input layer's transposed product.
    pub d_input: Option<&'a wgpu::Buffer>,
}

/// Records the forward over `n` rows into `encoder`: one dispatch per layer, one thread per row. (One
/// dispatch per layer rather than a fused loop: on lavapipe a barrier inside the layer loop cost ~30%.)
pub async fn record_forward(
    gpu: &Gpu,
    encoder: &mut wgpu::CommandEncoder,
    config: &MlpConfig,
    n: u32,
    buffers: &ForwardBuffers<'_>,
) -> Result<(), GpuError> {
    check_batch(config, n)?;
    let straight = gpu.straight_line_kernels();
    let rows = n as usize;
    need(buffers.params, config.n_params(), "parameter")?;
    need(buffers.input, rows * config.input, "input")?;
    need(buffers.output, rows * config.output, "output")?;
    need(
        buffers.saved,
        rows * config.saved_per_row(),
        "saved-activation",
    )?;
    if n == 0 {
        return Ok(());
    }
    for l in 0..config.n_layers() {
        let u = gpu.uniform("mlp.uniform", &uniform_for(config, n, 0));
        gpu.dispatch_variant(
            encoder,
            &KERNEL,
            &layer_prelude(config, Some(l), straight),
            "forward_layer",
            &[
                (0, &u),
                (1, buffers.params),
                (2, buffers.input),
                (3, buffers.output),
                (4, buffers.saved),
            ],
            n,
        )
        .await?;
    }
    Ok(())
}

/// Records an inference forward over `n` rows (no backward follows): [`record_forward`]'s outputs, but on
/// lavapipe in one `forward_fused` dispatch (the layers' weights staged while they fit in workgroup memory,
/// see [`fused_layout`]) whose hidden rows never leave the lane; `buffers.saved` is then not written.
/// (Not on the loop-form adapters: its products are generated straight-line code, and GPUs there have
/// not been measured with it.)
/// Elsewhere the same as [`record_forward`].
pub async fn record_inference(
    gpu: &Gpu,
    encoder: &mut wgpu::CommandEncoder,
    config: &MlpConfig,
    n: u32,
    buffers: &ForwardBuffers<'_>,
) -> Result<(), GpuError> {
    if !fuses_inference(gpu) {
        return record_forward(gpu, encoder, config, n, buffers).await;
    }
    check_batch(config, n)?;
    let rows = n as usize;
    need(buffers.params, config.n_params(), "parameter")?;
    need(buffers.input, rows * config.input, "input")?;
    need(buffers.output, rows * config.output, "output")?;
    if n == 0 {
        return Ok(());
    }
    let u = gpu.uniform("mlp.uniform", &uniform_for(config, n, 0));
    gpu.dispatch_variant(
        encoder,
        &KERNEL,
        &fused_prelude(config, workgroup_vec4s(gpu)),
        "forward_fused",
        // `saved` is bound (the shared row loader names it) but neither read nor written.
        &[
            (0, &u),
            (1, buffers.params),
            (2, buffers.input),
            (3, buffers.output),
            (4, buffers.saved),
        ],
        n,
    )
    .await
}

/// Records the backward over `n` rows: per layer, last first, the pre-activation gradients (one thread per
/// row; layer 0's gives dL/dinput); then per-chunk partial parameter gradients and their in-order sum into
/// `d_params` (added to it if `accumulate`, otherwise written over it, so no clear pass is needed).
/// Layers + 2 dispatches, no float atomics.
pub async fn record_backward(
    gpu: &Gpu,
    encoder: &mut wgpu::CommandEncoder,
    config: &MlpConfig,
    n: u32,
    buffers: &BackwardBuffers<'_>,
    accumulate: bool,
) -> Result<(), GpuError> {
    check_batch(config, n)?;
    let straight = gpu.straight_line_kernels();
    let rows = n as usize;
    need(buffers.params, config.n_params(), "parameter")?;
    need(buffers.input, rows * config.input, "input")?;
    need(
        buffers.saved,
        rows * config.saved_per_row(),
        "saved-activation",
    )?;
    need(buffers.d_output, rows * config.output, "dL/doutput")?;
    need(buffers.scratch, config.scratch_words(rows), "scratch")?;
    if let Some(d) = buffers.d_params {
        need(d, config.n_params(), "dL/dparams")?;
    }
    if let Some(d) = buffers.d_input {
        need(d, rows * config.input, "dL/dinput")?;
    }
    let mut flags = 0;
    if buffers.d_input.is_some() {
        flags |= FLAG_D_INPUT;
    }
    if accumulate {
        flags |= FLAG_ACCUMULATE;
    }
    let uniform = uniform_for(config, n, flags);
    let u = gpu.uniform("mlp.uniform", &uniform);
    if n > 0 {
        // The binding must exist even when dL/dinput is not wanted.
        let dummy;
        let d_input = match buffers.d_input {
            Some(d) => d,
            None => {
                dummy = gpu.output("mlp unused dL/dinput", 1)?;
                &dummy
            }
        };
        for l in (0..config.n_layers()).rev() {
            gpu.dispatch_variant(
                encoder,
                &KERNEL,
                &layer_prelude(config, Some(l), straight),
                "backward_layer",
                &[
                    (0, &u),
                    (1, buffers.params),
                    (4, buffers.saved),
                    (5, buffers.d_output),
                    (6, buffers.scratch),
                    (8, d_input),
                ],
                n,
            )
            .await?;
        }
        if buffers.d_params.is_none() {
            return Ok(());
        }
        for (l, ly) in config.layers().iter().enumerate() {
            let groups = MlpConfig::chunks(rows) as u32 * layer_blocks(ly, straight) as u32;
            gpu.dispatch_variant(
                encoder,
                &KERNEL,
                &layer_prelude(config, Some(l), straight),
                if rows_kernel(ly, straight) {
                    "backward_weights_rows"
                } else {
                    "backward_weights"
                },
                &[
                    (0, &u),
                    (2, buffers.input),
                    (4, buffers.saved),
                    (6, buffers.scratch),
                ],
                groups * WORKGROUP,
            )
            .await?;
        }
    }
    let Some(d_params) = buffers.d_params else {
        return Ok(());
    };
    gpu.dispatch_variant(
        encoder,
        &KERNEL,
        &layer_prelude(config, None, straight),
        "reduce_grads",
        &[(0, &u), (6, buffers.scratch), (7, d_params)],
        config.n_params() as u32,
    )
    .await
}

fn row_count(config: &MlpConfig, params: &[f32], input: &[f32]) -> Result<u32, GpuError> {
    let n = config.rows(params, input)?;
    u32::try_from(n)
        .map_err(|_| GpuError::InvalidInput(format!("MLP: {n} rows is more than one call takes")))
}

/// The WGSL forward on host data: uploads, one dispatch, one readback. Same result as [`forward_cpu`] up
/// to f32 rounding.
pub async fn forward_gpu(
    gpu: &Gpu,
    config: &MlpConfig,
    params: &[f32],
    input: &[f32],
) -> Result<MlpForward, GpuError> {
    let (output, saved) = forward_on_host(gpu, config, params, input, false).await?;
    Ok(MlpForward { output, saved })
}

/// Whether [`record_inference`] runs each MLP as one fused dispatch on `gpu` (whatever its shape: layers
/// beyond the workgroup memory are read from storage): with the straight-line kernels (lavapipe,
/// [`Gpu::straight_line_kernels`]).
pub fn fuses_inference(gpu: &Gpu) -> bool {
    gpu.straight_line_kernels()
}

/// The WGSL inference forward on host data ([`record_inference`]): the outputs only.
pub async fn inference_gpu(
    gpu: &Gpu,
    config: &MlpConfig,
    params: &[f32],
    input: &[f32],
) -> Result<Vec<f32>, GpuError> {
    Ok(forward_on_host(gpu, config, params, input, true).await?.0)
}

/// [`forward_gpu`] and [`inference_gpu`]: uploads, the forward ([`record_inference`] if `inference`, which
/// leaves the saved activations unread), one readback of the outputs and, for the forward, the saved rows.
async fn forward_on_host(
    gpu: &Gpu,
    config: &MlpConfig,
    params: &[f32],
    input: &[f32],
    inference: bool,
) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
    let n = row_count(config, params, input)?;
    let rows = n as usize;
    let b_params = gpu.upload("mlp params", params)?;
    let b_input = gpu.upload("mlp input", input)?;
    let b_out = gpu.output("mlp output", rows * config.output)?;
    let b_saved = gpu.output("mlp saved", rows * config.saved_per_row())?;
    let mut enc = gpu.encoder("mlp forward");
    let buffers = ForwardBuffers {
        params: &b_params,
        input: &b_input,
        output: &b_out,
        saved: &b_saved,
    };
    let mut reads = vec![(&b_out, rows * config.output)];
    if inference {
        record_inference(gpu, &mut enc, config, n, &buffers).await?;
    } else {
        record_forward(gpu, &mut enc, config, n, &buffers).await?;
        reads.push((&b_saved, rows * config.saved_per_row()));
    }
    let mut out = gpu.finish_and_read::<f32>(enc, &reads).await?.into_iter();
    Ok((
        out.next().unwrap_or_default(),
        out.next().unwrap_or_default(),
    ))
}

/// The WGSL backward on host data (the forward's `saved` from either forward): dL/dparams and, if
/// `input_grads`, dL/dinput, in one submit.
pub async fn backward_gpu(
    gpu: &Gpu,
    config: &MlpConfig,
    params: &[f32],
    input: &[f32],
    saved: &[f32],
    d_output: &[f32],
    input_grads: bool,
) -> Result<MlpGradients, GpuError> {
    let n = row_count(config, params, input)?;
    let rows = n as usize;
    config.check_len(
        "saved activations",
        saved.len(),
        rows * config.saved_per_row(),
    )?;
    config.check_len("dL/doutput", d_output.len(), rows * config.output)?;
    let b_params = gpu.upload("mlp params", params)?;
    let b_input = gpu.upload("mlp input", input)?;
    let b_saved = gpu.upload("mlp saved", saved)?;
    let b_dout = gpu.upload("mlp dL/doutput", d_output)?;
    let b_scratch = gpu.output("mlp scratch", config.scratch_words(rows))?;
    let b_dparams = gpu.output("mlp dL/dparams", config.n_params())?;
    let b_dinput = if input_grads {
        Some(gpu.output("mlp dL/dinput", rows * config.input)?)
    } else {
        None
    };
    let mut enc = gpu.encoder("mlp backward");
    let buffers = BackwardBuffers {
        params: &b_params,
        input: &b_input,
        saved: &b_saved,
        d_output: &b_dout,
        scratch: &b_scratch,
        d_params: Some(&b_dparams),
        d_input: b_dinput.as_ref(),
    };
    record_backward(gpu, &mut enc, config, n, &buffers, false).await?;
    let mut reads = vec![(&b_dparams, config.n_params())];
    if let Some(b) = &b_dinput {
        reads.push((b, rows * config.input));
    }
    let mut out = gpu.finish_and_read::<f32>(enc, &reads).await?.into_iter();
    Ok(MlpGradients {
        params: out.next().unwrap_or_default(),
        input: out.next(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 2 → 3 (ReLU) → 1 by hand: the parameter layout (row-major W, then b, layer by layer), the saved
    /// activations and every gradient, in exactly representable numbers.
    #[test]
    fn tiny_network_by_hand() {
        let c = MlpConfig {
            input: 2,
            hidden: 3,
            hidden_layers: 1,
            output: 1,
            hidden_activation: Activation::Relu,
            output_activation: Activation::None,
        };
        let layers = c.layers();
        assert_eq!((layers[0].weights, layers[0].bias), (0, 6));
        assert_eq!((layers[1].weights, layers[1].bias), (9, 12));
        assert_eq!((layers[1].saved, layers[1].delta), (3, 3));
        assert_eq!(
            (c.n_params(), c.saved_per_row(), c.delta_per_row()),
            (13, 3, 4)
        );
        // W0 = [[1, 2], [3, 4], [-5, -6]], b0 = [0.5, 0, 0]; W1 = [[1, -1, 2]], b1 = [0.25].
        let params = [
            1.0, 2.0, 3.0, 4.0, -5.0, -6.0, 0.5, 0.0, 0.0, 1.0, -1.0, 2.0, 0.25,
        ];
        let x = [1.0, 1.0];
        let f = forward_cpu(&c, &params, &x).unwrap();
        // z0 = [3.5, 7, −11] → a0 = [3.5, 7, 0]; y = 3.5 − 7 + 0.25.
        assert_eq!(f.saved, vec![3.5, 7.0, 0.0]);
        assert_eq!(f.output, vec![-3.25]);
        let g = backward_cpu(&c, &params, &x, &f.saved, &[1.0], true).unwrap();
        // δ1 = 1: dW1 = a0, db1 = 1; δ0 = W1ᵀδ1 masked = [1, −1, 0]: dW0 = δ0 ⊗ x, db0 = δ0; dx = W0ᵀδ0.
        let want = [
            1.0, 1.0, -1.0, -1.0, 0.0, 0.0, 1.0, -1.0, 0.0, 3.5, 7.0, 0.0, 1.0,
        ];
        assert_eq!(g.params, want);
        assert_eq!(g.input, Some(vec![-2.0, -2.0]));
    }

    #[test]
    fn scratch_and_chunks() {
        let c = MlpConfig::nerfacto_colour();
        assert_eq!(c.delta_per_row(), 64 + 64 + 3);
        assert_eq!(MlpConfig::chunks(0), 0);
        assert_eq!(MlpConfig::chunks(CHUNK_ROWS + 1), 2);
        assert_eq!(
            c.scratch_words(1000),
            1000 * 131 + 1000usize.div_ceil(CHUNK_ROWS) * c.n_params()
        );
        // With straight-line kernels (lavapipe) 16 input columns per parameter-gradient block of a wide
        // layer (≥ 32 outputs), 32 of a narrow one; with loops 32 everywhere (the first block also sums
        // the bias); a layer with fewer inputs has one block, its width rounded up to a multiple of 4.
        let blocks = |straight| -> Vec<usize> {
            c.layers()
                .iter()
                .map(|l| layer_blocks(l, straight))
                .collect()
        };
        assert_eq!(
            (blocks(true), blocks(false)),
            (vec![4, 4, 2], vec![2, 2, 2])
        );
        let widths = |straight| -> Vec<usize> {
            MlpConfig::nerfacto_density()
                .layers()
                .iter()
                .map(|l| layer_block(l, straight))
                .collect()
        };
        assert_eq!((widths(true), widths(false)), (vec![16, 32], vec![32, 32]));
        let narrow = LayerInfo {
            fan_in: 10,
            fan_out: 16,
            weights: 0,
            bias: 0,
            saved: 0,
            delta: 0,
        };
        for straight in [true, false] {
            assert_eq!(
                (
                    layer_block(&narrow, straight),
                    layer_blocks(&narrow, straight)
                ),
                (12, 1)
            );
        }
    }

    #[test]
    fn fast_paths_match_the_reference() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(7);
        for cfg in [MlpConfig::nerfacto_density(), MlpConfig::nerfacto_colour()] {
            let n = 1500;
            let params = cfg.init_params(3);
            let input: Vec<f32> = (0..n * cfg.input)
                .map(|_| rng.random_range(-1.0..1.0))
                .collect();
            let dy: Vec<f32> = (0..n * cfg.output)
                .map(|_| rng.random_range(-1.0..1.0))
                .collect();
            let a = forward_cpu(&cfg, &params, &input).unwrap();
            let b = forward_fast(&cfg, &params, &input).unwrap();
            let close = |x: &[f32], y: &[f32], what: &str| {
                let scale = x.iter().fold(1e-3f32, |m, v| m.max(v.abs()));
                for (i, (p, q)) in x.iter().zip(y).enumerate() {
                    assert!((p - q).abs() <= 1e-4 * scale, "{what}[{i}]: {p} vs {q}");
                }
            };
            close(&a.output, &b.output, "output");
            close(&a.saved, &b.saved, "saved");
            let ga = backward_cpu(&cfg, &params, &input, &a.saved, &dy, true).unwrap();
            let gb = backward_fast(&cfg, &params, &input, &b.saved, &dy, true).unwrap();
            close(&ga.params, &gb.params, "dparams");
            close(
                ga.input.as_ref().unwrap(),
                gb.input.as_ref().unwrap(),
                "dinput",
            );
        }
    }
}
