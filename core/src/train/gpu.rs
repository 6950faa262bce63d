//! The training step and the renderer in WGSL: the same chain as [`super::cpu`] (its referee), kernel for
//! kernel, recorded into one command buffer per step with the parameters, gradients and Adam moments
//! resident on the device. One small readback per step (per-ray loss terms); parameters come back only
//! for checkpoints ([`GpuEngine::download`]). Nothing here blocks: the browser worker runs it as is.

use bytemuck::{Pod, Zeroable};

use super::adam::AdamConfig;
use super::cpu::{Batch, RenderedRay, StepSchedule, StepStats, TrainRay};
use crate::field::hashgrid::{self, GpuPositions, HashGridLayout};
use crate::field::mlp::{self, BackwardBuffers, ForwardBuffers};
use crate::field::model::{ModelConfig, Params, APPEARANCE, COLOUR, DENSITY, GRID, PROPOSAL};
use crate::gpu::{Gpu, GpuError, Kernel};
use crate::render::{self, Background, GpuRayBatch, Losses, RayLoss, RayOutput};
use crate::sampler::Spacing;
use crate::shaders;

/// `shaders/train.wgsl`.
pub const KERNEL: Kernel = Kernel {
    name: "train",
    source: shaders::TRAIN,
    workgroup_size: 64,
};

/// The kernels' uniform (`Params` in train.wgsl), 32 words.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct Uniform {
    count: u32,
    n_rays: u32,
    n_in: u32,
    n_out: u32,
    n_levels: u32,
    level: u32,
    use_jitter: u32,
    out_dim: u32,
    geo: u32,
    app_dim: u32,
    images: u32,
    c_in: u32,
    normal_rays: u32,
    scratch_stride: u32,
    stat_col: u32,
    stat_stride: u32,
    g_near: f32,
    g_span: f32,
    anneal: f32,
    padding: f32,
    normal_step: f32,
    scale_a: f32,
    scale_b: f32,
    scale_c: f32,
    inv_two_var: f32,
    adam_a: f32,
    adam_c: f32,
    beta1: f32,
    beta2: f32,
    eps: f32,
    _pad0: u32,
    _pad1: u32,
}

/// One proposal level's batch buffers.
struct LevelBufs {
    n: usize,
    s: wgpu::Buffer,
    t: wgpu::Buffer,
    pos: wgpu::Buffer,
    features: wgpu::Buffer,
    out: wgpu::Buffer,
    saved: wgpu::Buffer,
    weights: wgpu::Buffer,
    density: wgpu::Buffer,
    d_out: wgpu::Buffer,
    d_features: wgpu::Buffer,
    mlp_scratch: wgpu::Buffer,
}

/// Batch-sized buffers for up to `rays` rays of which up to `normal_rays` have normals.
struct Work {
    rays: usize,
    normal_rays: usize,
    b_rays: wgpu::Buffer,
    targets: wgpu::Buffer,
    jitter: wgpu::Buffer,
    levels: Vec<LevelBufs>,
    s: wgpu::Buffer,
    t: wgpu::Buffer,
    pos: wgpu::Buffer,
    features: wgpu::Buffer,
    out: wgpu::Buffer,
    saved: wgpu::Buffer,
    colour_in: wgpu::Buffer,
    colour_out: wgpu::Buffer,
    colour_saved: wgpu::Buffer,
    samples: wgpu::Buffer,
    intervals: wgpu::Buffer,
    normals: wgpu::Buffer,
    grad_len: wgpu::Buffer,
    losses: wgpu::Buffer,
    d_samples: wgpu::Buffer,
    d_normals: wgpu::Buffer,
    d_rgb: wgpu::Buffer,
    d_cin: wgpu::Buffer,
    colour_scratch: wgpu::Buffer,
    d_out: wgpu::Buffer,
    d_features: wgpu::Buffer,
    density_scratch: wgpu::Buffer,
    w_fin: wgpu::Buffer,
    mean_app: wgpu::Buffer,
    scratch: wgpu::Buffer,
    ray_stats: wgpu::Buffer,
    rays_out: wgpu::Buffer,
    /// Inference's colour selection: per-ray counts and offsets, selected samples, per-sample rows.
    sel_count: wgpu::Buffer,
    sel_offset: wgpu::Buffer,
    sel_list: wgpu::Buffer,
    sel_index: wgpu::Buffer,
}

/// Borrowed final-level buffers of a recorded forward (see [`GpuEngine::final_forward`]).
pub(crate) struct FinalForward<'a> {
    pub rays: &'a wgpu::Buffer,
    pub t: &'a wgpu::Buffer,
    pub pos: &'a wgpu::Buffer,
    pub features: &'a wgpu::Buffer,
    pub out: &'a wgpu::Buffer,
    pub saved: &'a wgpu::Buffer,
    pub colour_in: &'a wgpu::Buffer,
    pub colour_saved: &'a wgpu::Buffer,
    pub samples: &'a wgpu::Buffer,
    pub intervals: &'a wgpu::Buffer,
    pub colour_scratch: &'a wgpu::Buffer,
    pub density_scratch: &'a wgpu::Buffer,
    pub params: &'a [wgpu::Buffer],
}

/// The WGSL engine: the model's tensors, their gradients and Adam moments on one device.
pub struct GpuEngine {
    pub gpu: Gpu,
    cfg: ModelConfig,
    sizes: Vec<usize>,
    params: Vec<wgpu::Buffer>,
    grads: Vec<wgpu::Buffer>,
    m: Vec<wgpu::Buffer>,
    v: Vec<wgpu::Buffer>,
    work: Option<Work>,
}

/// Per-ray statistics columns: distortion, then (interlevel, depth, sky) per proposal level.
fn stat_stride(cfg: &ModelConfig) -> usize {
    1 + 3 * cfg.proposals.len()
}

fn scratch_stride(cfg: &ModelConfig) -> usize {
    let max_n = cfg
        .sampler
        .proposal_samples
        .iter()
        .copied()
        .chain([cfg.sampler.samples])
        .max()
        .unwrap_or(1);
    2 * (max_n + 1)
}

fn u32_of(n: usize, what: &str) -> Result<u32, GpuError> {
    u32::try_from(n)
        .map_err(|_| GpuError::InvalidInput(format!("training: {n} {what} is too many")))
}

impl GpuEngine {
    /// Uploads `params` and the Adam moments `m`, `v` (same shapes) to `gpu`.
    pub fn new(
        gpu: Gpu,
        cfg: &ModelConfig,
        params: &Params,
        m: &[Vec<f32>],
        v: &[Vec<f32>],
    ) -> Result<Self, GpuError> {
        params.check(cfg)?;
        let sizes: Vec<usize> = params.tensors.iter().map(Vec::len).collect();
        let mut e = GpuEngine {
            gpu,
            cfg: cfg.clone(),
            sizes,
            params: Vec::new(),
            grads: Vec::new(),
            m: Vec::new(),
            v: Vec::new(),
            work: None,
        };
        for (i, t) in params.tensors.iter().enumerate() {
            let name = &params.names[i];
            e.params.push(e.gpu.upload(name, t)?);
            e.m.push(e.gpu.upload(&format!("{name}.m"), &m[i])?);
            e.v.push(e.gpu.upload(&format!("{name}.v"), &v[i])?);
            e.grads
                .push(e.gpu.output(&format!("{name}.grad"), t.len())?);
        }
        Ok(e)
    }

    /// Parameters and Adam moments back on the host (for checkpoints and the CPU referee).
    pub async fn download(
        &self,
    ) -> Result<(Vec<Vec<f32>>, Vec<Vec<f32>>, Vec<Vec<f32>>), GpuError> {
        let mut reads = Vec::new();
        for i in 0..self.sizes.len() {
            reads.push((&self.params[i], self.sizes[i]));
            reads.push((&self.m[i], self.sizes[i]));
            reads.push((&self.v[i], self.sizes[i]));
        }
        let enc = self.gpu.encoder("download");
        let out = self.gpu.finish_and_read::<f32>(enc, &reads).await?;
        let (mut p, mut m, mut v) = (Vec::new(), Vec::new(), Vec::new());
        for (k, t) in out.into_iter().enumerate() {
            match k % 3 {
                0 => p.push(t),
                1 => m.push(t),
                _ => v.push(t),
            }
        }
        Ok((p, m, v))
    }

    pub fn model(&self) -> &ModelConfig {
        &self.cfg
    }

    /// Uploads rays for a forward pass without jitter (uncertainty).
    pub(crate) async fn prepare_rays(&mut self, rays: &[TrainRay]) -> Result<(), GpuError> {
        self.ensure_work(rays.len(), 0).await?;
        self.write_rays(rays, None);
        Ok(())
    }

    /// Records the forward of the `rays` prepared rays (no jitter, proposals fully annealed, no normals).
    pub(crate) async fn record_final_forward(
        &self,
        enc: &mut wgpu::CommandEncoder,
        rays: usize,
    ) -> Result<(), GpuError> {
        self.record_forward(enc, rays, 0, false, 1.0).await
    }

    /// The final level's buffers after [`Self::record_final_forward`], for passes that differentiate
    /// the trained field.
    pub(crate) fn final_forward(&self) -> FinalForward<'_> {
        let w = self.work.as_ref().expect("work buffers");
        FinalForward {
            rays: &w.b_rays,
            t: &w.t,
            pos: &w.pos,
            features: &w.features,
            out: &w.out,
            saved: &w.saved,
            colour_in: &w.colour_in,
            colour_saved: &w.colour_saved,
            samples: &w.samples,
            intervals: &w.intervals,
            colour_scratch: &w.colour_scratch,
            density_scratch: &w.density_scratch,
            params: &self.params,
        }
    }

    /// The latest gradients (after [`Self::step`]), for the CPU-vs-GPU tests.
    pub async fn download_grads(&self) -> Result<Vec<Vec<f32>>, GpuError> {
        let reads: Vec<_> = self
            .grads
            .iter()
            .zip(&self.sizes)
            .map(|(b, &n)| (b, n))
            .collect();
        let enc = self.gpu.encoder("download grads");
        self.gpu.finish_and_read::<f32>(enc, &reads).await
    }

    /// Words of the widest buffer an MLP of `m` with `input` features per row needs over `rows` rows
    /// (activations, saved values, and the scratch with its per-chunk partial gradients).
    fn mlp_words(m: &crate::field::mlp::MlpConfig, input: usize, rows: usize) -> usize {
        (rows * m.saved_per_row().max(input).max(m.output).max(4)).max(m.scratch_words(rows))
    }

    /// The largest single work buffer of a batch of `rays` rays, `normal_rays` of them with normals:
    /// (what it holds, 32-bit words). The binding limit applies per buffer.
    fn largest_work_buffer(&self, rays: usize, normal_rays: usize) -> (&'static str, usize) {
        let c = &self.cfg;
        let n = c.sampler.samples;
        let dm = c.density_mlp();
        let cm = c.colour_mlp();
        let rows = rays * n + 6 * normal_rays * n;
        let mut best = (
            "density buffer",
            Self::mlp_words(&dm, c.field.grid.output_dim(), rows),
        );
        let colour = Self::mlp_words(&cm, cm.input, rays * n);
        if colour > best.1 {
            best = ("colour buffer", colour);
        }
        for (l, &nl) in c.sampler.proposal_samples.iter().enumerate() {
            let pm = c.proposal_mlp(l);
            let w = Self::mlp_words(&pm, c.proposals[l].grid.output_dim(), rays * nl);
            if w > best.1 {
                best = ("proposal buffer", w);
            }
        }
        best
    }

    /// Refuses a training batch of `rays` rays whose largest work buffer passes the binding limit even
    /// with no normal rays (a lower bound; the exact check is at allocation), so a run asked for an
    /// impossible batch fails before its first step builds one.
    pub fn check_batch(&self, rays: usize) -> Result<(), GpuError> {
        self.check_fits(rays.max(1), 0)
    }

    /// [`GpuError::BufferTooLarge`] when the largest work buffer of a batch of `rays` rays
    /// (`normal_rays` with normals) passes the device's binding limit.
    fn check_fits(&self, rays: usize, normal_rays: usize) -> Result<(), GpuError> {
        let max = self.gpu.max_binding_bytes();
        let (what, words) = self.largest_work_buffer(rays, normal_rays);
        if words as u64 * 4 > max {
            return Err(GpuError::BufferTooLarge {
                what: format!("the largest {what} of a {rays}-ray batch"),
                bytes: words as u64 * 4,
                max,
            });
        }
        Ok(())
    }

    /// The most rays one inference batch may hold before a work buffer would pass the device's binding
    /// limit (a tenth of headroom for the per-ray buffers the estimate leaves out).
    pub fn max_rays(&self, normals: bool) -> usize {
        const PROBE: usize = 4096;
        let words = self
            .largest_work_buffer(PROBE, if normals { PROBE } else { 0 })
            .1;
        let budget = (self.gpu.max_binding_bytes() / 4) as usize * 9 / 10;
        (budget * PROBE / words.max(1)).max(1)
    }

    /// Batch buffers for `rays` rays (`normal_rays` with normals), grown when a batch needs more. An
    /// allocation the device cannot satisfy is [`GpuError::OutOfMemory`] naming the batch and the limit.
    async fn ensure_work(&mut self, rays: usize, normal_rays: usize) -> Result<(), GpuError> {
        if let Some(w) = &self.work {
            if w.rays >= rays && w.normal_rays >= normal_rays {
                return Ok(());
            }
        }
        // Grow, never shrink, unless the grown shape (the most rays of one call with the most normals of
        // another) would not fit where this batch alone does; the old buffers go first, so a grown batch
        // does not need both at once.
        let max = self.gpu.max_binding_bytes();
        let fits = |s: &Self, r: usize, nm: usize| s.largest_work_buffer(r, nm).1 as u64 * 4 <= max;
        let (asked, asked_nm) = (rays.max(1), normal_rays);
        let mut rays = asked.max(self.work.as_ref().map_or(0, |w| w.rays));
        let mut normal_rays = asked_nm.max(self.work.as_ref().map_or(0, |w| w.normal_rays));
        if !fits(self, rays, normal_rays) {
            (rays, normal_rays) = (asked, asked_nm);
        }
        // Refuse a batch whose largest buffer cannot be bound before allocating any of them (a browser's
        // GPU process may not survive gigabytes of buffers allocated on the way to the one that fails).
        self.check_fits(rays, normal_rays)?;
        self.work = None;
        let scope = self
            .gpu
            .device
            .push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let bytes = self.alloc_work(rays, normal_rays)?;
        if let Some(e) = scope.pop().await {
            self.work = None;
            return Err(GpuError::OutOfMemory {
                adapter: self.gpu.report().name.clone(),
                what: format!("the work buffers of a {rays}-ray batch ({e})"),
                bytes,
                max_buffer: self.gpu.report().max_buffer_size,
            });
        }
        Ok(())
    }

    /// Allocates the batch buffers; returns the bytes asked for.
    fn alloc_work(&mut self, rays: usize, nm: usize) -> Result<u64, GpuError> {
        let gpu = &self.gpu;
        let mut bytes = 0u64;
        let mut out = |label: &str, words: usize| {
            bytes += words.max(1) as u64 * 4;
            gpu.output(label, words)
        };
        let c = &self.cfg;
        let nl = c.proposals.len() + 1;
        let mut levels = Vec::new();
        for (l, &n) in c.sampler.proposal_samples.iter().enumerate() {
            let f = c.proposals[l].grid.output_dim();
            let m = c.proposal_mlp(l);
            let rows = rays * n;
            levels.push(LevelBufs {
                n,
                s: out("level s", rays * (n + 1))?,
                t: out("level t", rays * (n + 1))?,
                pos: out("level positions", rows * 3)?,
                features: out("level features", rows * f)?,
                out: out("level logits", rows)?,
                saved: out("level saved", rows * m.saved_per_row())?,
                weights: out("level weights", rows)?,
                density: out("level density", rows)?,
                d_out: out("level dL/dlogit", rows)?,
                d_features: out("level dL/dfeatures", rows * f)?,
                mlp_scratch: out("level mlp scratch", m.scratch_words(rows))?,
            });
        }
        let n = c.sampler.samples;
        let rn = rays * n;
        let rows = rn + 6 * nm * n;
        let f = c.field.grid.output_dim();
        let dm = c.density_mlp();
        let cm = c.colour_mlp();
        self.work = Some(Work {
            rays,
            normal_rays: nm,
            b_rays: out("rays", rays * 8)?,
            targets: out("targets", rays * 8)?,
            jitter: out("jitter", rays * nl)?,
            levels,
            s: out("final s", rays * (n + 1))?,
            t: out("final t", rays * (n + 1))?,
            pos: out("final positions", rows * 3)?,
            features: out("final features", rows * f)?,
            out: out("density mlp out", rows * dm.output)?,
            saved: out("density mlp saved", rows * dm.saved_per_row())?,
            colour_in: out("colour input", rn * cm.input)?,
            colour_out: out("colour out", rn * 3)?,
            colour_saved: out("colour saved", rn * cm.saved_per_row())?,
            samples: out("samples", rn * 4)?,
            intervals: out("intervals", rn * 2)?,
            normals: out("normals", rn * 3)?,
            grad_len: out("grad len", nm * n)?,
            losses: out("ray losses", rays * 4)?,
            d_samples: out("dL/dsamples", rn * 4)?,
            d_normals: out("dL/dnormals", rn * 3)?,
            d_rgb: out("dL/drgb", rn * 3)?,
            d_cin: out("dL/dcolour input", rn * cm.input)?,
            colour_scratch: out("colour scratch", cm.scratch_words(rn))?,
            d_out: out("dL/ddensity out", rows * dm.output)?,
            d_features: out("dL/dfeatures", rows * f)?,
            density_scratch: out("density scratch", dm.scratch_words(rows))?,
            w_fin: out("final weights", rn)?,
            mean_app: out("mean appearance", c.field.appearance_dim)?,
            scratch: out("ray scratch", rays * scratch_stride(c))?,
            ray_stats: out("ray stats", rays * stat_stride(c))?,
            rays_out: out("rays out", rays * 8)?,
            sel_count: out("colour selection counts", rays)?,
            sel_offset: out("colour selection offsets", rays)?,
            sel_list: out("colour selection", rn)?,
            sel_index: out("colour selection rows", rn)?,
        });
        Ok(bytes)
    }

    fn base_uniform(&self, rays: usize, normal_rays: usize) -> Uniform {
        let c = &self.cfg;
        let sp = Spacing::new(c.sampler.near, c.sampler.far);
        Uniform {
            n_rays: rays as u32,
            n_levels: (c.proposals.len() + 1) as u32,
            out_dim: c.density_mlp().output as u32,
            geo: c.field.geo_features as u32,
            app_dim: c.field.appearance_dim as u32,
            images: c.images as u32,
            c_in: c.colour_mlp().input as u32,
            normal_rays: normal_rays as u32,
            scratch_stride: scratch_stride(c) as u32,
            stat_stride: stat_stride(c) as u32,
            g_near: sp.g_near(),
            g_span: sp.g_span(),
            padding: c.sampler.histogram_padding,
            normal_step: c.normal_step,
            ..Default::default()
        }
    }

    async fn run(
        &self,
        enc: &mut wgpu::CommandEncoder,
        entry: &str,
        u: &Uniform,
        bindings: &[(u32, &wgpu::Buffer)],
    ) -> Result<(), GpuError> {
        if u.count == 0 {
            return Ok(());
        }
        let ub = self.gpu.uniform("train.params", u);
        let mut all: Vec<(u32, &wgpu::Buffer)> = vec![(0, &ub)];
        all.extend_from_slice(bindings);
        self.gpu.dispatch(enc, &KERNEL, entry, &all, u.count).await
    }

    /// Uploads the rays (and targets, jitter) of a batch into the work buffers.
    fn write_rays(&self, rays: &[TrainRay], jitter: Option<&[f32]>) {
        let w = self.work.as_ref().expect("work buffers");
        let packed: Vec<f32> = rays
            .iter()
            .flat_map(|r| {
                [
                    r.origin[0],
                    r.origin[1],
                    r.origin[2],
                    r.dir[0],
                    r.dir[1],
                    r.dir[2],
                    f32::from_bits(r.appearance),
                    0.0,
                ]
            })
            .collect();
        self.gpu
            .queue
            .write_buffer(&w.b_rays, 0, bytemuck::cast_slice(&packed));
        let nl = self.cfg.proposals.len() + 1;
        let zeros;
        let j = match jitter {
            Some(j) => j,
            None => {
                zeros = vec![0.0f32; rays.len() * nl];
                &zeros
            }
        };
        self.gpu
            .queue
            .write_buffer(&w.jitter, 0, bytemuck::cast_slice(j));
    }

    /// Records the forward chain: proposal levels, final samples (+ FD normals for the first
    /// `normal_rays` rays), the field, and the render inputs.
    async fn record_forward(
        &self,
        enc: &mut wgpu::CommandEncoder,
        rays: usize,
        normal_rays: usize,
        jitter: bool,
        anneal: f32,
    ) -> Result<(), GpuError> {
        self.record_density(enc, rays, normal_rays, jitter, anneal, false)
            .await?;
        self.record_colour(enc, rays, normal_rays, None).await
    }

    /// The forward up to the field's density: proposal levels, final samples (+ FD positions), the hash
    /// grid and the density MLP, and the mean appearance embedding. `inference`: no backward follows, so
    /// the MLPs may skip their saved activations (`mlp::record_inference`).
    async fn record_density(
        &self,
        enc: &mut wgpu::CommandEncoder,
        rays: usize,
        normal_rays: usize,
        jitter: bool,
        anneal: f32,
        inference: bool,
    ) -> Result<(), GpuError> {
        let w = self.work.as_ref().expect("work buffers");
        let c = &self.cfg;
        let base = self.base_uniform(rays, normal_rays);
        let r32 = u32_of(rays, "rays")?;
        let n = c.sampler.samples;
        // First level's edges.
        let first = &w.levels[0];
        self.gpu.profile_scope("forward proposal 0");
        let u = Uniform {
            count: r32,
            n_out: first.n as u32,
            use_jitter: jitter as u32,
            ..base
        };
        self.run(
            enc,
            "init_edges",
            &u,
            &[
                (1, &w.b_rays),
                (2, &w.jitter),
                (6, &first.s),
                (7, &first.t),
                (8, &first.pos),
            ],
        )
        .await?;
        for (l, lv) in w.levels.iter().enumerate() {
            self.gpu.profile_scope(&format!("forward proposal {l}"));
            let rows = u32_of(rays * lv.n, "samples")?;
            let layout = HashGridLayout::new(&c.proposals[l].grid)?;
            let pos = GpuPositions {
                buffer: &lv.pos,
                n: rows,
            };
            hashgrid::record_encode(
                &self.gpu,
                enc,
                &layout,
                &self.params[PROPOSAL + 2 * l],
                pos,
                &lv.features,
            )
            .await?;
            self.mlp_forward(
                enc,
                &c.proposal_mlp(l),
                rows,
                inference,
                &ForwardBuffers {
                    params: &self.params[PROPOSAL + 2 * l + 1],
                    input: &lv.features,
                    output: &lv.out,
                    saved: &lv.saved,
                },
            )
            .await?;
            let u = Uniform {
                count: r32,
                n_in: lv.n as u32,
                out_dim: 1,
                ..base
            };
            self.run(
                enc,
                "level_weights",
                &u,
                &[
                    (4, &lv.t),
                    (5, &lv.out),
                    (9, &lv.weights),
                    (10, &lv.density),
                ],
            )
            .await?;
            let (s_next, t_next, p_next, n_next) = match w.levels.get(l + 1) {
                Some(nx) => (&nx.s, &nx.t, &nx.pos, nx.n),
                None => (&w.s, &w.t, &w.pos, n),
            };
            let u = Uniform {
                count: r32,
                n_in: lv.n as u32,
                n_out: n_next as u32,
                level: (l + 1) as u32,
                use_jitter: jitter as u32,
                anneal,
                ..base
            };
            self.run(
                enc,
                "resample",
                &u,
                &[
                    (1, &w.b_rays),
                    (2, &w.jitter),
                    (3, &lv.s),
                    (33, &lv.weights),
                    (11, &w.scratch),
                    (6, s_next),
                    (7, t_next),
                    (8, p_next),
                ],
            )
            .await?;
        }
        self.gpu.profile_scope("forward field");
        let nm = normal_rays * n;
        let u = Uniform {
            count: u32_of(nm, "normal samples")?,
            n_in: n as u32,
            ..base
        };
        self.run(enc, "fd_positions", &u, &[(8, &w.pos)]).await?;
        let rows = u32_of(rays * n + 6 * nm, "field rows")?;
        let layout = HashGridLayout::new(&c.field.grid)?;
        hashgrid::record_encode(
            &self.gpu,
            enc,
            &layout,
            &self.params[GRID],
            GpuPositions {
                buffer: &w.pos,
                n: rows,
            },
            &w.features,
        )
        .await?;
        self.mlp_forward(
            enc,
            &c.density_mlp(),
            rows,
            inference,
            &ForwardBuffers {
                params: &self.params[DENSITY],
                input: &w.features,
                output: &w.out,
                saved: &w.saved,
            },
        )
        .await?;
        let ad = c.field.appearance_dim;
        let u = Uniform {
            count: ad as u32,
            ..base
        };
        self.run(
            enc,
            "mean_appearance",
            &u,
            &[(18, &self.params[APPEARANCE]), (19, &w.mean_app)],
        )
        .await
    }

    /// One MLP's forward: for a backward to follow, or inference only (`mlp::record_inference`).
    async fn mlp_forward(
        &self,
        enc: &mut wgpu::CommandEncoder,
        cfg: &mlp::MlpConfig,
        rows: u32,
        inference: bool,
        b: &ForwardBuffers<'_>,
    ) -> Result<(), GpuError> {
        if inference {
            mlp::record_inference(&self.gpu, enc, cfg, rows, b).await
        } else {
            mlp::record_forward(&self.gpu, enc, cfg, rows, b).await
        }
    }

    /// The rest of the forward after [`Self::record_density`]: the colour MLP and the render inputs.
    /// `selected`: `None` colours every sample (training); `Some(m)` only inference's `m` selected
    /// samples (listed by `colour_select`), the rest black.
    async fn record_colour(
        &self,
        enc: &mut wgpu::CommandEncoder,
        rays: usize,
        normal_rays: usize,
        selected: Option<u32>,
    ) -> Result<(), GpuError> {
        let w = self.work.as_ref().expect("work buffers");
        let c = &self.cfg;
        let base = self.base_uniform(rays, normal_rays);
        let n = c.sampler.samples;
        let rn = u32_of(rays * n, "samples")?;
        let per_sample = Uniform {
            count: rn,
            n_in: n as u32,
            ..base
        };
        let rows = selected.unwrap_or(rn);
        let mut inputs = vec![
            (1, &w.b_rays),
            (5, &w.out),
            (18, &self.params[APPEARANCE]),
            (19, &w.mean_app),
            (17, &w.colour_in),
        ];
        let (input_entry, shade_entry) = match selected {
            None => ("colour_input", "shade"),
            Some(_) => {
                inputs.push((38, &w.sel_list));
                ("colour_input_selected", "shade_selected")
            }
        };
        let u = Uniform {
            count: rows,
            ..per_sample
        };
        self.run(enc, input_entry, &u, &inputs).await?;
        self.mlp_forward(
            enc,
            &c.colour_mlp(),
            rows,
            selected.is_some(),
            &ForwardBuffers {
                params: &self.params[COLOUR],
                input: &w.colour_in,
                output: &w.colour_out,
                saved: &w.colour_saved,
            },
        )
        .await?;
        let mut bind = vec![
            (12, &w.colour_out),
            (5, &w.out),
            (4, &w.t),
            (13, &w.samples),
            (14, &w.intervals),
            (15, &w.normals),
            (16, &w.grad_len),
        ];
        if selected.is_some() {
            bind.push((39, &w.sel_index));
        }
        self.run(enc, shade_entry, &per_sample, &bind).await
    }

    fn ray_batch<'a>(&self, w: &'a Work, rays: usize, normals: bool) -> GpuRayBatch<'a> {
        GpuRayBatch {
            rays: rays as u32,
            samples_per_ray: self.cfg.sampler.samples as u32,
            samples: &w.samples,
            intervals: &w.intervals,
            normals: normals.then_some(&w.normals),
        }
    }

    /// One training step: forward, losses, backward, Adam (update `adam_t`, 1-based, at learning rate `lr`).
    /// Returns the step's loss terms (read back after the update is queued).
    pub async fn step(
        &mut self,
        batch: &Batch,
        sch: &StepSchedule,
        adam: &AdamConfig,
        lr: f32,
        adam_t: u32,
        update: bool,
    ) -> Result<StepStats, GpuError> {
        let r = batch.rays.len();
        let nl = self.cfg.proposals.len() + 1;
        if r == 0 || batch.targets.len() != r || batch.jitter.len() != r * nl {
            return Err(GpuError::InvalidInput(format!(
                "training batch: {r} rays, {} targets, {} jitters (need {})",
                batch.targets.len(),
                batch.jitter.len(),
                r * nl
            )));
        }
        let nm = if sch.normals { batch.normal_rays } else { 0 };
        self.ensure_work(r, nm).await?;
        self.write_rays(&batch.rays, Some(&batch.jitter));
        let w = self.work.as_ref().expect("work buffers");
        self.gpu
            .queue
            .write_buffer(&w.targets, 0, bytemuck::cast_slice(&batch.targets));
        let mut enc = self.gpu.encoder("train step");
        self.record_forward(&mut enc, r, nm, true, sch.anneal)
            .await?;
        let c = &self.cfg;
        let n = c.sampler.samples;
        let base = self.base_uniform(r, nm);
        let r32 = r as u32;
        self.gpu.profile_scope("render + losses");
        render::record_render_backward(
            &self.gpu,
            &mut enc,
            self.ray_batch(w, r, nm > 0),
            Background::LastSample,
            &sch.losses,
            &w.targets,
            &w.losses,
            &w.d_samples,
            (nm > 0).then_some(&w.d_normals),
        )
        .await?;
        // Final level: weights, distortion, dL/dσ (in place) and dL/drgb.
        self.gpu.profile_scope("backward field");
        let u = Uniform {
            count: r32,
            n_in: n as u32,
            scale_a: sch.distortion / r as f32,
            stat_col: 0,
            ..base
        };
        self.run(
            &mut enc,
            "final_backward",
            &u,
            &[
                (4, &w.t),
                (26, &w.s),
                (13, &w.samples),
                (9, &w.w_fin),
                (11, &w.scratch),
                (20, &w.d_samples),
                (24, &w.ray_stats),
                (35, &w.d_rgb),
            ],
        )
        .await?;
        let cm = c.colour_mlp();
        let rn = (r * n) as u32;
        mlp::record_backward(
            &self.gpu,
            &mut enc,
            &cm,
            rn,
            &BackwardBuffers {
                params: &self.params[COLOUR],
                input: &w.colour_in,
                saved: &w.colour_saved,
                d_output: &w.d_rgb,
                scratch: &w.colour_scratch,
                d_params: Some(&self.grads[COLOUR]),
                d_input: Some(&w.d_cin),
            },
            false,
        )
        .await?;
        let u = Uniform {
            count: rn,
            n_in: n as u32,
            ..base
        };
        self.run(
            &mut enc,
            "assemble_d_out",
            &u,
            &[
                (20, &w.d_samples),
                (5, &w.out),
                (22, &w.d_cin),
                (15, &w.normals),
                (21, &w.d_normals),
                (16, &w.grad_len),
                (23, &w.d_out),
            ],
        )
        .await?;
        let rows = (r * n + 6 * nm * n) as u32;
        mlp::record_backward(
            &self.gpu,
            &mut enc,
            &c.density_mlp(),
            rows,
            &BackwardBuffers {
                params: &self.params[DENSITY],
                input: &w.features,
                saved: &w.saved,
                d_output: &w.d_out,
                scratch: &w.density_scratch,
                d_params: Some(&self.grads[DENSITY]),
                d_input: Some(&w.d_features),
            },
            false,
        )
        .await?;
        hashgrid::record_backward_params(
            &self.gpu,
            &mut enc,
            &HashGridLayout::new(&c.field.grid)?,
            GpuPositions {
                buffer: &w.pos,
                n: rows,
            },
            &w.d_features,
            &self.grads[GRID],
            false,
        )
        .await?;
        let ad = c.field.appearance_dim;
        if self.sizes[APPEARANCE] > 0 {
            let u = Uniform {
                count: self.sizes[APPEARANCE] as u32,
                ..base
            };
            self.run(&mut enc, "clear_app", &u, &[(28, &self.grads[APPEARANCE])])
                .await?;
            let u = Uniform {
                count: (r * ad) as u32,
                n_in: n as u32,
                ..base
            };
            self.run(
                &mut enc,
                "appearance_grad",
                &u,
                &[
                    (1, &w.b_rays),
                    (22, &w.d_cin),
                    (28, &self.grads[APPEARANCE]),
                ],
            )
            .await?;
        }
        let inv2 = sch.losses.inv_two_var();
        for (l, lv) in w.levels.iter().enumerate() {
            self.gpu.profile_scope(&format!("backward proposal {l}"));
            let u = Uniform {
                count: r32,
                n_in: lv.n as u32,
                n_out: n as u32,
                scale_a: sch.interlevel / (r * n) as f32,
                scale_b: sch.proposal_depth / r as f32,
                scale_c: sch.proposal_sky / r as f32,
                inv_two_var: inv2,
                stat_col: (1 + 3 * l) as u32,
                ..base
            };
            self.run(
                &mut enc,
                "proposal_dw",
                &u,
                &[
                    (3, &lv.s),
                    (4, &lv.t),
                    (33, &lv.weights),
                    (26, &w.s),
                    (27, &w.w_fin),
                    (25, &w.targets),
                    (11, &w.scratch),
                    (24, &w.ray_stats),
                ],
            )
            .await?;
            let u = Uniform {
                count: r32,
                n_in: lv.n as u32,
                out_dim: 1,
                ..base
            };
            self.run(
                &mut enc,
                "proposal_d_out",
                &u,
                &[
                    (4, &lv.t),
                    (34, &lv.density),
                    (33, &lv.weights),
                    (5, &lv.out),
                    (11, &w.scratch),
                    (23, &lv.d_out),
                ],
            )
            .await?;
            let rows = (r * lv.n) as u32;
            mlp::record_backward(
                &self.gpu,
                &mut enc,
                &c.proposal_mlp(l),
                rows,
                &BackwardBuffers {
                    params: &self.params[PROPOSAL + 2 * l + 1],
                    input: &lv.features,
                    saved: &lv.saved,
                    d_output: &lv.d_out,
                    scratch: &lv.mlp_scratch,
                    d_params: Some(&self.grads[PROPOSAL + 2 * l + 1]),
                    d_input: Some(&lv.d_features),
                },
                false,
            )
            .await?;
            hashgrid::record_backward_params(
                &self.gpu,
                &mut enc,
                &HashGridLayout::new(&c.proposals[l].grid)?,
                GpuPositions {
                    buffer: &lv.pos,
                    n: rows,
                },
                &lv.d_features,
                &self.grads[PROPOSAL + 2 * l],
                false,
            )
            .await?;
        }
        if update {
            self.gpu.profile_scope("adam");
            let (a, cc) = adam.corrections(lr, adam_t);
            for i in 0..self.sizes.len() {
                let u = Uniform {
                    count: self.sizes[i] as u32,
                    adam_a: a,
                    adam_c: cc,
                    beta1: adam.beta1,
                    beta2: adam.beta2,
                    eps: adam.eps,
                    ..base
                };
                self.run(
                    &mut enc,
                    "adam",
                    &u,
                    &[
                        (29, &self.params[i]),
                        (30, &self.m[i]),
                        (31, &self.v[i]),
                        (32, &self.grads[i]),
                    ],
                )
                .await?;
            }
        }
        let ss = stat_stride(c);
        let mut out = self
            .gpu
            .finish_and_read::<f32>(enc, &[(&w.losses, r * 4), (&w.ray_stats, r * ss)])
            .await?
            .into_iter();
        let per_ray: Vec<RayLoss> = out
            .next()
            .unwrap_or_default()
            .chunks_exact(4)
            .map(|q| RayLoss {
                rgb: q[0],
                depth: q[1],
                normal: q[2],
                sky: q[3],
            })
            .collect();
        let stats_rows = out.next().unwrap_or_default();
        let losses = Losses::from_per_ray(per_ray, &sch.losses);
        Ok(stats_from(&losses, &stats_rows, ss, sch, r, n))
    }

    /// Renders rays with the current parameters (no jitter, proposals fully annealed), `chunk` at a time.
    pub async fn render(
        &mut self,
        rays: &[TrainRay],
        normals: bool,
        chunk: usize,
    ) -> Result<Vec<RenderedRay>, GpuError> {
        let n = self.cfg.sampler.samples;
        let chunk = chunk.min(self.max_rays(normals)).max(1);
        let mut out = Vec::with_capacity(rays.len());
        for part in rays.chunks(chunk) {
            let r = part.len();
            let nm = if normals { r } else { 0 };
            self.ensure_work(r, nm).await?;
            self.write_rays(part, None);
            let w = self.work.as_ref().expect("work buffers");
            // Density first; the colour MLP then runs only where inference needs colour
            // (train::cpu::INFERENCE_MIN_WEIGHT): per-ray counts come back, their prefix goes up.
            let mut enc = self.gpu.encoder("render density");
            self.record_density(&mut enc, r, nm, false, 1.0, true)
                .await?;
            let base = self.base_uniform(r, nm);
            let per_ray = Uniform {
                count: u32_of(r, "rays")?,
                n_in: n as u32,
                ..base
            };
            self.run(
                &mut enc,
                "colour_count",
                &per_ray,
                &[(4, &w.t), (5, &w.out), (36, &w.sel_count)],
            )
            .await?;
            let counts = self
                .gpu
                .finish_and_read::<u32>(enc, &[(&w.sel_count, r)])
                .await?
                .pop()
                .unwrap_or_default();
            let mut offsets = Vec::with_capacity(r);
            let mut m = 0u32;
            for &k in &counts {
                offsets.push(m);
                m += k;
            }
            self.gpu
                .queue
                .write_buffer(&w.sel_offset, 0, bytemuck::cast_slice(&offsets));
            let mut enc = self.gpu.encoder("render");
            self.run(
                &mut enc,
                "colour_select",
                &per_ray,
                &[
                    (4, &w.t),
                    (5, &w.out),
                    (37, &w.sel_offset),
                    (38, &w.sel_list),
                    (39, &w.sel_index),
                ],
            )
            .await?;
            self.record_colour(&mut enc, r, nm, Some(m)).await?;
            render::record_render(
                &self.gpu,
                &mut enc,
                self.ray_batch(w, r, normals),
                Background::LastSample,
                &w.w_fin,
                &w.rays_out,
            )
            .await?;
            let mut back = self
                .gpu
                .finish_and_read::<f32>(
                    enc,
                    &[(&w.rays_out, r * 8), (&w.t, r * (n + 1)), (&w.w_fin, r * n)],
                )
                .await?
                .into_iter();
            let ro: Vec<RayOutput> =
                bytemuck::cast_slice(&back.next().unwrap_or_default()).to_vec();
            let t = back.next().unwrap_or_default();
            let wf = back.next().unwrap_or_default();
            for (ray, o) in ro.into_iter().enumerate() {
                let te = &t[ray * (n + 1)..(ray + 1) * (n + 1)];
                out.push(RenderedRay::new(o, &wf[ray * n..(ray + 1) * n], te));
            }
        }
        Ok(out)
    }
}

/// The step's statistics from the per-ray rows, summed as [`super::cpu::train_step`] sums them.
fn stats_from(
    losses: &Losses,
    rows: &[f32],
    stride: usize,
    sch: &StepSchedule,
    r: usize,
    n: usize,
) -> StepStats {
    let mut s = StepStats {
        rgb_mse: losses.rgb,
        depth: losses.depth,
        normal: losses.normal,
        sky: losses.sky,
        loss: losses.total,
        ..Default::default()
    };
    let col = |c: usize| -> f64 { rows.chunks_exact(stride).map(|q| q[c] as f64).sum() };
    s.distortion = col(0) / r as f64;
    s.loss += sch.distortion as f64 * s.distortion;
    for l in 0..(stride - 1) / 3 {
        let il = col(1 + 3 * l) / (r * n) as f64;
        s.interlevel += il;
        s.loss += sch.interlevel as f64 * il
            + sch.proposal_depth as f64 * col(2 + 3 * l) / r as f64
            + sch.proposal_sky as f64 * col(3 + 3 * l) / r as f64;
    }
    s
}
