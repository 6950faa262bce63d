//! The uncertainty pass on the device: the trainer's forward of a batch (no jitter), then per rendered
//! output (R, G, B, E) the render Jacobian, the colour and density MLPs' and the hash grid's backward to
//! the sample positions (the trainer's kernels, input gradients only), the contraction's Jacobian, and the
//! Fisher accumulation (`shaders/uncertainty.wgsl`). The accumulators stay on the device across batches;
//! one readback at the end. Async throughout: the same code runs in the browser worker.

use bytemuck::{Pod, Zeroable};

use super::PerturbationGrid;
use crate::field::hashgrid::{self, GpuPositions, HashGridLayout};
use crate::field::mlp::{self, BackwardBuffers};
use crate::field::model::{COLOUR, DENSITY, GRID};
use crate::gpu::{GpuError, Kernel};
use crate::shaders;
use crate::train::cpu::TrainRay;
use crate::train::gpu::GpuEngine;

const KERNEL: Kernel = Kernel {
    name: "uncertainty",
    source: shaders::UNCERTAINTY,
    workgroup_size: 64,
};

/// `Params` of uncertainty.wgsl.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct Uniform {
    count: u32,
    n: u32,
    k: u32,
    out_dim: u32,
    geo: u32,
    c_in: u32,
    cells: u32,
    _pad: u32,
}

struct Work {
    rays: usize,
    flags: wgpu::Buffer,
    jac: wgpu::Buffer,
    cw: wgpu::Buffer,
    d_rgb: wgpu::Buffer,
    d_cin: wgpu::Buffer,
    d_out: wgpu::Buffer,
    d_features: wgpu::Buffer,
    d_pos: wgpu::Buffer,
    g: wgpu::Buffer,
}

/// The Fisher accumulators on the device and the batch work buffers.
pub struct GpuFisher {
    pub grid: PerturbationGrid,
    h_colour: wgpu::Buffer,
    h_depth: wgpu::Buffer,
    work: Option<Work>,
}

fn u32_of(n: usize, what: &str) -> Result<u32, GpuError> {
    u32::try_from(n).map_err(|_| GpuError::InvalidInput(format!("uncertainty: {n} {what}")))
}

impl GpuFisher {
    /// Zeroed accumulators for `grid` on the engine's device.
    pub async fn new(engine: &GpuEngine, grid: PerturbationGrid) -> Result<Self, GpuError> {
        let gpu = &engine.gpu;
        let nv = grid.vertices();
        let f = GpuFisher {
            grid,
            h_colour: gpu.output("fisher colour", nv)?,
            h_depth: gpu.output("fisher depth", nv)?,
            work: None,
        };
        let mut enc = gpu.encoder("clear fisher");
        let u = Uniform {
            count: u32_of(nv, "vertices")?,
            ..Default::default()
        };
        let ub = gpu.uniform("uncertainty.params", &u);
        gpu.dispatch(
            &mut enc,
            &KERNEL,
            "clear_fisher",
            &[(0, &ub), (15, &f.h_colour), (16, &f.h_depth)],
            u.count,
        )
        .await?;
        gpu.queue.submit([enc.finish()]);
        Ok(f)
    }

    fn ensure(&mut self, engine: &GpuEngine, rays: usize) -> Result<(), GpuError> {
        if self.work.as_ref().is_some_and(|w| w.rays >= rays) {
            return Ok(());
        }
        let g = &engine.gpu;
        let c = engine.model();
        let rn = rays * c.sampler.samples;
        let cm = c.colour_mlp();
        let dm = c.density_mlp();
        self.work = Some(Work {
            rays,
            flags: g.output("ray flags", rays)?,
            jac: g.output("dY/dsigma", rn * 4)?,
            cw: g.output("colour weights", rn)?,
            d_rgb: g.output("dY/drgb", rn * 3)?,
            d_cin: g.output("dY/dcolour input", rn * cm.input)?,
            d_out: g.output("dY/ddensity out", rn * dm.output)?,
            d_features: g.output("dY/dfeatures", rn * c.field.grid.output_dim())?,
            d_pos: g.output("dY/dgrid position", rn * 3)?,
            g: g.output("dY/dposition", rn * 12)?,
        });
        Ok(())
    }

    async fn run(
        &self,
        engine: &GpuEngine,
        enc: &mut wgpu::CommandEncoder,
        entry: &str,
        u: &Uniform,
        bindings: &[(u32, &wgpu::Buffer)],
    ) -> Result<(), GpuError> {
        if u.count == 0 {
            return Ok(());
        }
        let ub = engine.gpu.uniform("uncertainty.params", u);
        let mut all: Vec<(u32, &wgpu::Buffer)> = vec![(0, &ub)];
        all.extend_from_slice(bindings);
        engine
            .gpu
            .dispatch(enc, &KERNEL, entry, &all, u.count)
            .await
    }

    /// Adds one batch of rays to the accumulators their flags select ([`super::COLOUR_RAY`],
    /// [`super::DEPTH_RAY`]). Rays beyond the engine's batch limit are split. Submits without waiting.
    pub async fn accumulate(
        &mut self,
        engine: &mut GpuEngine,
        rays: &[TrainRay],
        flags: &[u32],
    ) -> Result<(), GpuError> {
        if rays.len() != flags.len() {
            return Err(GpuError::InvalidInput(format!(
                "uncertainty batch: {} rays, {} flags",
                rays.len(),
                flags.len()
            )));
        }
        let chunk = engine.max_rays(false).max(1);
        for (r, f) in rays.chunks(chunk).zip(flags.chunks(chunk)) {
            self.accumulate_chunk(engine, r, f).await?;
        }
        Ok(())
    }

    async fn accumulate_chunk(
        &mut self,
        engine: &mut GpuEngine,
        rays: &[TrainRay],
        flags: &[u32],
    ) -> Result<(), GpuError> {
        let r = rays.len();
        if r == 0 {
            return Ok(());
        }
        engine.prepare_rays(rays).await?;
        self.ensure(engine, r)?;
        let w = self.work.as_ref().expect("work buffers");
        engine
            .gpu
            .queue
            .write_buffer(&w.flags, 0, bytemuck::cast_slice(flags));
        let engine = &*engine;
        let c = engine.model();
        let n = c.sampler.samples;
        let rn = u32_of(r * n, "samples")?;
        let mut enc = engine.gpu.encoder("uncertainty batch");
        engine.record_final_forward(&mut enc, r).await?;
        engine.gpu.profile_scope("uncertainty");
        let f = engine.final_forward();
        let w = self.work.as_ref().expect("work buffers");
        let cm = c.colour_mlp();
        let dm = c.density_mlp();
        let base = Uniform {
            n: n as u32,
            out_dim: dm.output as u32,
            geo: c.field.geo_features as u32,
            c_in: cm.input as u32,
            cells: self.grid.cells,
            ..Default::default()
        };
        let per_ray = Uniform {
            count: u32_of(r, "rays")?,
            ..base
        };
        self.run(
            engine,
            &mut enc,
            "output_jacobian",
            &per_ray,
            &[(1, f.samples), (2, f.intervals), (3, &w.jac), (4, &w.cw)],
        )
        .await?;
        let layout = HashGridLayout::new(&c.field.grid)?;
        for k in 0..4u32 {
            let u = Uniform {
                count: rn,
                k,
                ..base
            };
            if k < 3 {
                self.run(
                    engine,
                    &mut enc,
                    "seed_colour",
                    &u,
                    &[(4, &w.cw), (5, &w.d_rgb)],
                )
                .await?;
                mlp::record_backward(
                    &engine.gpu,
                    &mut enc,
                    &cm,
                    rn,
                    &BackwardBuffers {
                        params: &f.params[COLOUR],
                        input: f.colour_in,
                        saved: f.colour_saved,
                        d_output: &w.d_rgb,
                        scratch: f.colour_scratch,
                        d_params: None,
                        d_input: Some(&w.d_cin),
                    },
                    false,
                )
                .await?;
            }
            self.run(
                engine,
                &mut enc,
                "density_seed",
                &u,
                &[(3, &w.jac), (6, f.out), (7, &w.d_cin), (8, &w.d_out)],
            )
            .await?;
            mlp::record_backward(
                &engine.gpu,
                &mut enc,
                &dm,
                rn,
                &BackwardBuffers {
                    params: &f.params[DENSITY],
                    input: f.features,
                    saved: f.saved,
                    d_output: &w.d_out,
                    scratch: f.density_scratch,
                    d_params: None,
                    d_input: Some(&w.d_features),
                },
                false,
            )
            .await?;
            hashgrid::record_backward_positions(
                &engine.gpu,
                &mut enc,
                &layout,
                &f.params[GRID],
                GpuPositions {
                    buffer: f.pos,
                    n: rn,
                },
                &w.d_features,
                &w.d_pos,
            )
            .await?;
            self.run(
                engine,
                &mut enc,
                "store_output",
                &u,
                &[(9, f.rays), (10, f.t), (11, &w.d_pos), (12, &w.g)],
            )
            .await?;
        }
        self.run(
            engine,
            &mut enc,
            "fisher",
            &per_ray,
            &[
                (12, &w.g),
                (13, f.pos),
                (14, &w.flags),
                (15, &self.h_colour),
                (16, &self.h_depth),
            ],
        )
        .await?;
        engine.gpu.queue.submit([enc.finish()]);
        Ok(())
    }

    /// d(R, G, B, E)/d(world position) of the last batch's first `samples` samples (12 f32 each): for the
    /// CPU-vs-GPU tests.
    pub async fn download_sample_jacobians(
        &self,
        engine: &GpuEngine,
        samples: usize,
    ) -> Result<Vec<f32>, GpuError> {
        let w = self.work.as_ref().ok_or_else(|| {
            GpuError::InvalidInput("uncertainty: no batch accumulated yet".into())
        })?;
        let enc = engine.gpu.encoder("download g");
        let mut out = engine
            .gpu
            .finish_and_read::<f32>(enc, &[(&w.g, samples * 12)])
            .await?;
        Ok(out.pop().unwrap_or_default())
    }

    /// The accumulated Fisher diagonals (colour, depth), waiting for every queued batch.
    pub async fn download(&self, engine: &GpuEngine) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        let nv = self.grid.vertices();
        let enc = engine.gpu.encoder("download fisher");
        let mut out = engine
            .gpu
            .finish_and_read::<f32>(enc, &[(&self.h_colour, nv), (&self.h_depth, nv)])
            .await?
            .into_iter();
        Ok((
            out.next().unwrap_or_default(),
            out.next().unwrap_or_default(),
        ))
    }
}
