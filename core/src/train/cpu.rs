//! The training step and the renderer on the CPU: the Rust references of every kernel chained, rayon over
//! rays. This is the referee of the WGSL engine and the fallback where the only adapter is a software one.

use rayon::prelude::*;

use crate::field::encoding::contract_unit;
use crate::field::mlp;
use crate::field::model::{
    colour_input, density_backward_cpu, density_forward_unit_cpu, density_of, fd_normal,
    fd_normal_backward, fd_positions, DensityEval, ModelConfig, Params, APPEARANCE, COLOUR,
    DENSITY, GRID, PROPOSAL,
};
use crate::gpu::GpuError;
use crate::render::{
    self, Background, Interval, LossConfig, RayBatch, RayOutput, RayTarget, Sample,
};
use crate::sampler::occupancy::OccupancyGrid;
use crate::sampler::{self, Spacing};

/// One ray in the scene frame: unit direction, appearance row (`u32::MAX` = the mean embedding).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TrainRay {
    pub origin: [f32; 3],
    pub dir: [f32; 3],
    pub appearance: u32,
}

/// A training batch. Rays with a lidar normal come first (`normal_rays` of them), so normals need only be
/// computed for a prefix. `jitter` holds one uniform per ray and sampling level, ray-major.
#[derive(Clone, Debug, Default)]
pub struct Batch {
    pub rays: Vec<TrainRay>,
    pub targets: Vec<RayTarget>,
    pub jitter: Vec<f32>,
    pub normal_rays: usize,
}

/// What changes from step to step.
#[derive(Clone, Copy, Debug)]
pub struct StepSchedule {
    pub step: u32,
    /// Exponent of the proposal weights before resampling.
    pub anneal: f32,
    /// Final-level losses: colour, depth and sky already divided by the level count where SiLVR averages
    /// over levels; σ in scene units.
    pub losses: LossConfig,
    /// Depth / sky weights on each proposal level.
    pub proposal_depth: f32,
    pub proposal_sky: f32,
    pub interlevel: f32,
    pub distortion: f32,
    pub normals: bool,
}

/// Batch means of the loss terms.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StepStats {
    pub loss: f64,
    pub rgb_mse: f64,
    pub depth: f64,
    pub normal: f64,
    pub sky: f64,
    pub interlevel: f64,
    pub distortion: f64,
}

impl StepStats {
    pub fn psnr(&self) -> f64 {
        -10.0 * self.rgb_mse.max(1e-12).log10()
    }
}

/// One sampling level of a batch.
pub(crate) struct Level {
    n: usize,
    /// Edges in normalised spacing, R·(n + 1).
    s: Vec<f32>,
    /// Edges in ray distance, R·(n + 1).
    t: Vec<f32>,
    weights: Vec<f32>,
    density: Vec<f32>,
    eval: Option<DensityEval>,
}

fn edges_to_t(sp: &Spacing, s: &[f32]) -> Vec<f32> {
    s.par_iter()
        .with_min_len(1024)
        .map(|&v| sp.to_t(v))
        .collect()
}

pub(crate) fn mids(rays: &[TrainRay], t: &[f32], n: usize) -> Vec<[f32; 3]> {
    rays.par_iter()
        .enumerate()
        .with_min_len(64)
        .flat_map_iter(|(r, ray)| {
            let te = &t[r * (n + 1)..(r + 1) * (n + 1)];
            (0..n).map(move |i| {
                let m = 0.5 * (te[i] + te[i + 1]);
                [0, 1, 2].map(|k| ray.origin[k] + ray.dir[k] * m)
            })
        })
        .collect()
}

/// How the final samples are placed: nerfacto's proposal networks (the product), or an Instant-NGP
/// occupancy grid (CPU only, for the comparison `silvr bench-sampler` records).
#[derive(Clone, Copy, Debug)]
pub enum Sampling<'a> {
    Proposal,
    Occupancy(&'a OccupancyGrid),
}

/// Candidate bins per ray checked against the occupancy grid.
pub const OCCUPANCY_CANDIDATES: usize = 256;

/// The proposal levels and the final level's edges (normalised s, distance t).
pub(crate) type Proposed = (Vec<Level>, Vec<f32>, Vec<f32>);

/// Runs the proposal levels: initial bins, each proposal field, resampling; returns the proposal levels
/// and the final level's edges (s, t).
pub(crate) fn propose(
    cfg: &ModelConfig,
    params: &Params,
    rays: &[TrainRay],
    jitter: Option<&[f32]>,
    anneal: f32,
    keep: bool,
) -> Result<Proposed, GpuError> {
    let sc = &cfg.sampler;
    let sp = Spacing::new(sc.near, sc.far);
    let nl = sc.proposal_samples.len() + 1;
    let r = rays.len();
    let jit = |ray: usize, level: usize| jitter.map(|j| j[ray * nl + level]);
    let n0 = sc.proposal_samples[0];
    let mut s = vec![0.0f32; r * (n0 + 1)];
    s.par_chunks_mut(n0 + 1)
        .enumerate()
        .for_each(|(ray, e)| sampler::initial_edges(jit(ray, 0), e));
    let mut levels: Vec<Level> = Vec::new();
    let mut n = n0;
    for l in 0..sc.proposal_samples.len() {
        let t = edges_to_t(&sp, &s);
        let pos = mids(rays, &t, n);
        let unit = pos.iter().map(|&p| contract_unit(p)).collect();
        let ev = density_forward_unit_cpu(
            &cfg.proposals[l].grid,
            &cfg.proposal_mlp(l),
            &params.tensors[PROPOSAL + 2 * l],
            &params.tensors[PROPOSAL + 2 * l + 1],
            unit,
        )?;
        let density: Vec<f32> = (0..r * n).map(|i| density_of(ev.logit(i)).0).collect();
        let mut weights = vec![0.0f32; r * n];
        weights.par_chunks_mut(n).enumerate().for_each(|(ray, w)| {
            let te = &t[ray * (n + 1)..(ray + 1) * (n + 1)];
            sampler::weights(&density[ray * n..(ray + 1) * n], te, w)
        });
        let next_n = if l + 1 < sc.proposal_samples.len() {
            sc.proposal_samples[l + 1]
        } else {
            sc.samples
        };
        let mut next = vec![0.0f32; r * (next_n + 1)];
        next.par_chunks_mut(next_n + 1)
            .enumerate()
            .for_each(|(ray, out)| {
                let mut cdf = vec![0.0f32; n + 1];
                sampler::pdf_resample(
                    &s[ray * (n + 1)..(ray + 1) * (n + 1)],
                    &weights[ray * n..(ray + 1) * n],
                    anneal,
                    sc.histogram_padding,
                    jit(ray, l + 1),
                    &mut cdf,
                    out,
                )
            });
        levels.push(Level {
            n,
            s,
            t,
            weights,
            density,
            eval: keep.then_some(ev),
        });
        s = next;
        n = next_n;
    }
    let t = edges_to_t(&sp, &s);
    Ok((levels, s, t))
}

/// [`propose`], or the occupancy grid's final edges (no proposal levels).
pub(crate) fn propose_with(
    sampling: Sampling,
    cfg: &ModelConfig,
    params: &Params,
    rays: &[TrainRay],
    jitter: Option<&[f32]>,
    anneal: f32,
    keep: bool,
) -> Result<Proposed, GpuError> {
    let Sampling::Occupancy(grid) = sampling else {
        return propose(cfg, params, rays, jitter, anneal, keep);
    };
    let sc = &cfg.sampler;
    let sp = Spacing::new(sc.near, sc.far);
    let nl = sc.proposal_samples.len() + 1;
    let n = sc.samples;
    let level = grid.level();
    let mut s = vec![0.0f32; rays.len() * (n + 1)];
    s.par_chunks_mut(n + 1).enumerate().for_each(|(r, out)| {
        grid.ray_edges(
            level,
            rays[r].origin,
            rays[r].dir,
            &sp,
            OCCUPANCY_CANDIDATES,
            sc.histogram_padding,
            jitter.map(|j| j[r * nl + nl - 1]),
            out,
        )
    });
    let t = edges_to_t(&sp, &s);
    Ok((Vec::new(), s, t))
}

/// Refreshes an occupancy grid from the radiance field's density at one random point per cell.
pub fn update_occupancy(
    cfg: &ModelConfig,
    params: &Params,
    grid: &mut OccupancyGrid,
    rng: &mut impl rand::Rng,
    decay: f32,
) -> Result<(), GpuError> {
    let pts = grid.cell_points(rng);
    let ev = density_forward_unit_cpu(
        &cfg.field.grid,
        &cfg.density_mlp(),
        &params.tensors[GRID],
        &params.tensors[DENSITY],
        pts,
    )?;
    let fresh: Vec<f32> = (0..ev.unit.len())
        .map(|i| density_of(ev.logit(i)).0)
        .collect();
    grid.update(&fresh, decay);
    Ok(())
}

/// The radiance field at the final samples: densities, colours, and (for the first `normal_rays` rays)
/// FD normals, with what the backward needs.
struct Shaded {
    eval: DensityEval,
    colour_in: Vec<f32>,
    colour: mlp::MlpForward,
    samples: Vec<Sample>,
    normals: Option<Vec<[f32; 3]>>,
    /// |∇logit| per normal sample.
    grad_len: Vec<f32>,
}

pub(crate) fn appearance_row<'a>(
    cfg: &ModelConfig,
    params: &'a Params,
    mean: &'a [f32],
    a: u32,
) -> &'a [f32] {
    let d = cfg.field.appearance_dim;
    let table = &params.tensors[APPEARANCE];
    let a = a as usize;
    if a < cfg.images && (a + 1) * d <= table.len() {
        &table[a * d..(a + 1) * d]
    } else {
        mean
    }
}

/// Inference evaluates the colour MLP only at samples whose volume-rendering weight is at least this,
/// and at each ray's last non-empty sample (the background colour): the others add < 1e-4 of their
/// colour each to the ray (at most 24 × 1e-4 = 0.6/255 in all, in practice far less). Both engines apply
/// the same rule. Training evaluates every sample (the colour loss differentiates through all of them).
pub const INFERENCE_MIN_WEIGHT: f32 = 1e-4;

/// Which samples (ray-major, `n` per ray) inference colours: [`INFERENCE_MIN_WEIGHT`].
pub fn inference_colour_samples(density: &[f32], t: &[f32], n: usize) -> Vec<bool> {
    let r = density.len() / n.max(1);
    let mut keep = vec![false; r * n];
    keep.par_chunks_mut(n.max(1))
        .enumerate()
        .for_each(|(ray, k)| {
            let te = &t[ray * (n + 1)..(ray + 1) * (n + 1)];
            let mut w = vec![0.0f32; n];
            sampler::weights(&density[ray * n..(ray + 1) * n], te, &mut w);
            let mut last = None;
            for i in 0..n {
                k[i] = w[i] >= INFERENCE_MIN_WEIGHT;
                if te[i + 1] - te[i] > 0.0 {
                    last = Some(i);
                }
            }
            if let Some(i) = last {
                k[i] = true;
            }
        });
    keep
}

fn shade(
    cfg: &ModelConfig,
    params: &Params,
    rays: &[TrainRay],
    t: &[f32],
    normal_rays: usize,
) -> Result<Shaded, GpuError> {
    shade_with(cfg, params, rays, t, normal_rays, false)
}

/// [`shade`]; with `inference`, colours only [`inference_colour_samples`] (the rest get black, and the
/// returned `colour_in` / `colour` hold the selected rows only: nothing differentiates them).
fn shade_with(
    cfg: &ModelConfig,
    params: &Params,
    rays: &[TrainRay],
    t: &[f32],
    normal_rays: usize,
    inference: bool,
) -> Result<Shaded, GpuError> {
    let n = cfg.sampler.samples;
    let r = rays.len();
    let pos = mids(rays, t, n);
    let mut unit: Vec<[f32; 3]> = pos.par_iter().map(|&p| contract_unit(p)).collect();
    let h = cfg.normal_step;
    let nm = normal_rays * n;
    for i in 0..nm {
        unit.extend_from_slice(&fd_positions(unit[i], h));
    }
    let d_cfg = cfg.density_mlp();
    let eval = density_forward_unit_cpu(
        &cfg.field.grid,
        &d_cfg,
        &params.tensors[GRID],
        &params.tensors[DENSITY],
        unit,
    )?;
    let c_cfg = cfg.colour_mlp();
    let ci = c_cfg.input;
    let geo = cfg.field.geo_features;
    let mean = params.mean_appearance(cfg);
    let density: Vec<f32> = (0..r * n).map(|i| density_of(eval.logit(i)).0).collect();
    // Rows of the colour MLP: every sample, or inference's selection.
    let rows: Vec<usize> = if inference {
        let keep = inference_colour_samples(&density, t, n);
        (0..r * n).filter(|&i| keep[i]).collect()
    } else {
        (0..r * n).collect()
    };
    let mut colour_in = vec![0.0f32; rows.len() * ci];
    colour_in
        .par_chunks_mut(ci)
        .enumerate()
        .with_min_len(256)
        .for_each(|(k, row)| {
            let i = rows[k];
            let ray = &rays[i / n];
            let out = &eval.mlp.output[i * eval.out_dim..(i + 1) * eval.out_dim];
            let app = appearance_row(cfg, params, &mean, ray.appearance);
            colour_input(ray.dir, &out[1..1 + geo], app, row);
        });
    let colour = mlp::forward_fast(&c_cfg, &params.tensors[COLOUR], &colour_in)?;
    let mut samples: Vec<Sample> = density
        .iter()
        .map(|&d| Sample {
            rgb: [0.0; 3],
            density: d,
        })
        .collect();
    for (k, &i) in rows.iter().enumerate() {
        samples[i].rgb = [0, 1, 2].map(|c| colour.output[k * 3 + c]);
    }
    let (normals, grad_len) = if normal_rays > 0 {
        let mut nv = vec![[0.0f32; 3]; r * n];
        let mut lens = vec![0.0f32; nm];
        for i in 0..nm {
            let base = r * n + 6 * i;
            let l = [0, 1, 2, 3, 4, 5].map(|k| eval.logit(base + k));
            let (nn, len) = fd_normal(l, h);
            nv[i] = nn;
            lens[i] = len;
        }
        (Some(nv), lens)
    } else {
        (None, Vec::new())
    };
    Ok(Shaded {
        eval,
        colour_in,
        colour,
        samples,
        normals,
        grad_len,
    })
}

pub(crate) fn intervals(t: &[f32], r: usize, n: usize) -> Vec<Interval> {
    let mut out = Vec::with_capacity(r * n);
    for ray in 0..r {
        let te = &t[ray * (n + 1)..(ray + 1) * (n + 1)];
        for i in 0..n {
            out.push(Interval {
                start: te[i],
                end: te[i + 1],
            });
        }
    }
    out
}

/// Gradients of the loss with respect to every parameter tensor, and the batch's loss terms.
pub fn train_step(
    cfg: &ModelConfig,
    params: &Params,
    batch: &Batch,
    sch: &StepSchedule,
) -> Result<(Vec<Vec<f32>>, StepStats), GpuError> {
    train_step_with(Sampling::Proposal, cfg, params, batch, sch)
}

/// [`train_step`] with the final samples placed by `sampling` (the proposal fields get zero gradients
/// under an occupancy grid).
pub fn train_step_with(
    sampling: Sampling,
    cfg: &ModelConfig,
    params: &Params,
    batch: &Batch,
    sch: &StepSchedule,
) -> Result<(Vec<Vec<f32>>, StepStats), GpuError> {
    let r = batch.rays.len();
    let nl = cfg.sampler.proposal_samples.len() + 1;
    if r == 0 || batch.targets.len() != r || batch.jitter.len() != r * nl {
        return Err(GpuError::InvalidInput(format!(
            "training batch: {r} rays, {} targets, {} jitters (need {})",
            batch.targets.len(),
            batch.jitter.len(),
            r * nl
        )));
    }
    let normal_rays = if sch.normals { batch.normal_rays } else { 0 };
    let (levels, s_final, t_final) = propose_with(
        sampling,
        cfg,
        params,
        &batch.rays,
        Some(&batch.jitter),
        sch.anneal,
        true,
    )?;
    let n = cfg.sampler.samples;
    let sh = shade(cfg, params, &batch.rays, &t_final, normal_rays)?;
    let ivs = intervals(&t_final, r, n);
    let rb = RayBatch {
        samples_per_ray: n,
        samples: &sh.samples,
        intervals: &ivs,
        normals: sh.normals.as_deref(),
    };
    let rg = render::backward_cpu(&rb, Background::LastSample, &batch.targets, &sch.losses)?;
    let mut stats = StepStats {
        rgb_mse: rg.losses.rgb,
        depth: rg.losses.depth,
        normal: rg.losses.normal,
        sky: rg.losses.sky,
        loss: rg.losses.total,
        ..Default::default()
    };

    // Final weights (held fixed by the interlevel loss; the distortion loss trains through them).
    let density: Vec<f32> = sh.samples.iter().map(|s| s.density).collect();
    let mut w_final = vec![0.0f32; r * n];
    w_final.par_chunks_mut(n).enumerate().for_each(|(ray, w)| {
        sampler::weights(
            &density[ray * n..(ray + 1) * n],
            &t_final[ray * (n + 1)..(ray + 1) * (n + 1)],
            w,
        )
    });
    let mut d_density: Vec<f32> = rg.samples.iter().map(|s| s.density).collect();
    let dist_scale = sch.distortion / r as f32;
    let dist: f64 = d_density
        .par_chunks_mut(n)
        .enumerate()
        .map(|(ray, dd)| {
            let s = &s_final[ray * (n + 1)..(ray + 1) * (n + 1)];
            let w = &w_final[ray * n..(ray + 1) * n];
            let mut dw = vec![0.0f32; n];
            let l = sampler::distortion(s, w, dist_scale, Some(&mut dw));
            sampler::weights_backward(
                &density[ray * n..(ray + 1) * n],
                &t_final[ray * (n + 1)..(ray + 1) * (n + 1)],
                &dw,
                dd,
            );
            l as f64
        })
        .sum();
    stats.distortion = dist / r as f64;
    stats.loss += sch.distortion as f64 * stats.distortion;

    // Radiance field backward: colour MLP → geometry features + appearance; density MLP → grid.
    let c_cfg = cfg.colour_mlp();
    let d_rgb: Vec<f32> = rg.samples.iter().flat_map(|s| s.rgb).collect();
    let cg = mlp::backward_fast(
        &c_cfg,
        &params.tensors[COLOUR],
        &sh.colour_in,
        &sh.colour.saved,
        &d_rgb,
        true,
    )?;
    let d_cin = cg.input.expect("requested");
    let geo = cfg.field.geo_features;
    let od = sh.eval.out_dim;
    let rows = sh.eval.unit.len();
    let mut d_out = vec![0.0f32; rows * od];
    for i in 0..r * n {
        let dl = d_density[i] * density_of(sh.eval.logit(i)).1;
        d_out[i * od] = dl;
        d_out[i * od + 1..i * od + 1 + geo]
            .copy_from_slice(&d_cin[i * c_cfg.input + 16..i * c_cfg.input + 16 + geo]);
    }
    if let Some(dn) = &rg.normals {
        let nv = sh.normals.as_ref().expect("normals were rendered");
        for i in 0..normal_rays * n {
            let dl = fd_normal_backward(nv[i], sh.grad_len[i], cfg.normal_step, dn[i]);
            for (k, v) in dl.iter().enumerate() {
                d_out[(r * n + 6 * i + k) * od] += v;
            }
        }
    }
    let (g_grid, g_density) = density_backward_cpu(
        &cfg.field.grid,
        &cfg.density_mlp(),
        &params.tensors[GRID],
        &params.tensors[DENSITY],
        &sh.eval,
        &d_out,
    )?;
    let ad = cfg.field.appearance_dim;
    let mut g_app = vec![0.0f32; params.tensors[APPEARANCE].len()];
    if ad > 0 {
        for i in 0..r * n {
            let a = batch.rays[i / n].appearance as usize;
            if a < cfg.images {
                let src = &d_cin[i * c_cfg.input + 16 + geo..(i + 1) * c_cfg.input];
                for (g, v) in g_app[a * ad..(a + 1) * ad].iter_mut().zip(src) {
                    *g += v;
                }
            }
        }
    }
    let mut grads = vec![g_grid, g_density, cg.params, g_app];

    // Proposal levels: interlevel (against the fixed final weights) + depth / sky on their weights.
    let inv2 = sch.losses.inv_two_var();
    let il_scale = sch.interlevel / (r * n) as f32;
    let (pd, ps) = (sch.proposal_depth / r as f32, sch.proposal_sky / r as f32);
    for (l, lv) in levels.iter().enumerate() {
        let m = lv.n;
        let mut d_dens = vec![0.0f32; r * m];
        let sums: (f64, f64, f64) = d_dens
            .par_chunks_mut(m)
            .enumerate()
            .map(|(ray, dd)| {
                let wp = &lv.weights[ray * m..(ray + 1) * m];
                let tp = &lv.t[ray * (m + 1)..(ray + 1) * (m + 1)];
                let mut dw = vec![0.0f32; m];
                let mut cum = vec![0.0f32; m + 1];
                let il = sampler::interlevel(
                    &s_final[ray * (n + 1)..(ray + 1) * (n + 1)],
                    &w_final[ray * n..(ray + 1) * n],
                    &lv.s[ray * (m + 1)..(ray + 1) * (m + 1)],
                    wp,
                    il_scale,
                    Some(&mut dw),
                    &mut cum,
                );
                let (ld, ls) =
                    render::weight_losses(wp, tp, &batch.targets[ray], inv2, pd, ps, &mut dw);
                sampler::weights_backward(&lv.density[ray * m..(ray + 1) * m], tp, &dw, dd);
                (il as f64, ld as f64, ls as f64)
            })
            .reduce(|| (0.0, 0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2));
        let il = sums.0 / (r * n) as f64;
        stats.interlevel += il;
        stats.loss += sch.interlevel as f64 * il
            + sch.proposal_depth as f64 * sums.1 / r as f64
            + sch.proposal_sky as f64 * sums.2 / r as f64;
        let ev = lv.eval.as_ref().expect("kept");
        let d_out: Vec<f32> = (0..r * m)
            .map(|i| d_dens[i] * density_of(ev.logit(i)).1)
            .collect();
        let (gg, gm) = density_backward_cpu(
            &cfg.proposals[l].grid,
            &cfg.proposal_mlp(l),
            &params.tensors[PROPOSAL + 2 * l],
            &params.tensors[PROPOSAL + 2 * l + 1],
            ev,
            &d_out,
        )?;
        grads.push(gg);
        grads.push(gm);
    }
    for t in &params.tensors[grads.len()..] {
        grads.push(vec![0.0; t.len()]);
    }
    if !stats.loss.is_finite() {
        return Err(GpuError::InvalidInput(format!(
            "training step {}: the loss became non-finite ({stats:?})",
            sch.step
        )));
    }
    Ok((grads, stats))
}

/// One rendered ray: the renderer's outputs plus SiLVR's expected depth (Σwt / Σw clipped to the
/// sampled range).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RenderedRay {
    pub out: RayOutput,
    pub expected_depth: f32,
    /// nerfacto's default depth: see [`median_depth`].
    pub median_depth: f32,
    /// How far along the ray its termination is spread: see [`depth_spread`].
    pub depth_spread: f32,
}

impl RenderedRay {
    /// A ray's rendered outputs with both depths from its final weights and sample edges.
    pub fn new(out: RayOutput, weights: &[f32], t_edges: &[f32]) -> Self {
        Self {
            out,
            expected_depth: expected_depth(&out, t_edges),
            median_depth: median_depth(weights, t_edges),
            depth_spread: depth_spread(weights, t_edges),
        }
    }
}

/// The standard deviation of where the ray terminates, √(Σ wᵢ((tᵢ − μ)² + Δᵢ²/12) / Σ wᵢ) with μ the
/// weighted mean, tᵢ and Δᵢ each interval's midpoint and length (its weight spread uniformly over it);
/// 0 without weight. A point placed at the expected depth of a ray whose weight is split between two
/// surfaces (a silhouette, foliage, glass) floats between them however well the field is constrained:
/// this is how far off such a point may be, in the ray's units.
pub fn depth_spread(weights: &[f32], t_edges: &[f32]) -> f32 {
    let (mut w0, mut w1) = (0.0f64, 0.0f64);
    for (i, &w) in weights.iter().enumerate() {
        let mid = 0.5 * (t_edges[i] + t_edges[i + 1]) as f64;
        w0 += w as f64;
        w1 += w as f64 * mid;
    }
    if w0 <= 0.0 {
        return 0.0;
    }
    let mu = w1 / w0;
    let var: f64 = weights
        .iter()
        .enumerate()
        .map(|(i, &w)| {
            let (a, b) = (t_edges[i] as f64, t_edges[i + 1] as f64);
            let mid = 0.5 * (a + b);
            w as f64 * ((mid - mu).powi(2) + (b - a).powi(2) / 12.0)
        })
        .sum::<f64>()
        / w0;
    var.max(0.0).sqrt() as f32
}

/// SiLVR's expected depth Σwt / Σw, clipped to the ray's sampled range `t_edges` (far end without weight).
pub fn expected_depth(o: &RayOutput, t_edges: &[f32]) -> f32 {
    let (near, far) = (t_edges[0], t_edges[t_edges.len() - 1]);
    if o.accumulation > 0.0 {
        (o.depth / o.accumulation).clamp(near, far)
    } else {
        far
    }
}

/// The median depth: where the cumulative weight reaches ½, interpolated linearly within the sample that
/// crosses it (the far end when the weight never reaches ½). Unlike the expected depth it never lands
/// between two surfaces a ray's weight is split across (an object's silhouette), where the expected depth
/// floats in free space. nerfacto returns the crossing sample's midpoint instead, which quantises distant
/// surfaces to their (long, contracted-space) intervals.
pub fn median_depth(weights: &[f32], t_edges: &[f32]) -> f32 {
    let mut c = 0.0;
    for (i, &w) in weights.iter().enumerate() {
        if c + w >= 0.5 && w > 0.0 {
            let f = ((0.5 - c) / w).clamp(0.0, 1.0);
            return t_edges[i] + f * (t_edges[i + 1] - t_edges[i]);
        }
        c += w;
    }
    t_edges[t_edges.len() - 1]
}

/// Renders rays (no jitter, fully annealed proposals) in chunks of `chunk`; normals on request.
pub fn render_rays(
    cfg: &ModelConfig,
    params: &Params,
    rays: &[TrainRay],
    normals: bool,
    chunk: usize,
) -> Result<Vec<RenderedRay>, GpuError> {
    render_rays_with(Sampling::Proposal, cfg, params, rays, normals, chunk)
}

/// [`render_rays`] with the final samples placed by `sampling`.
pub fn render_rays_with(
    sampling: Sampling,
    cfg: &ModelConfig,
    params: &Params,
    rays: &[TrainRay],
    normals: bool,
    chunk: usize,
) -> Result<Vec<RenderedRay>, GpuError> {
    let n = cfg.sampler.samples;
    let mut out = Vec::with_capacity(rays.len());
    for part in rays.chunks(chunk.max(1)) {
        let r = part.len();
        let (_, _, t) = propose_with(sampling, cfg, params, part, None, 1.0, false)?;
        let sh = shade_with(cfg, params, part, &t, if normals { r } else { 0 }, true)?;
        let ivs = intervals(&t, r, n);
        let rb = RayBatch {
            samples_per_ray: n,
            samples: &sh.samples,
            intervals: &ivs,
            normals: sh.normals.as_deref(),
        };
        let rendered = render::render_cpu(&rb, Background::LastSample)?;
        for (ray, o) in rendered.rays.into_iter().enumerate() {
            let te = &t[ray * (n + 1)..(ray + 1) * (n + 1)];
            let w = &rendered.weights[ray * n..(ray + 1) * n];
            out.push(RenderedRay::new(o, w, te));
        }
    }
    Ok(out)
}

/// Random rays for the CPU tests (origins near z = −0.5 looking along +z, appearance rows 0..3).
#[cfg(test)]
pub(crate) fn random_rays(rng: &mut impl rand::Rng, r: usize) -> Vec<TrainRay> {
    (0..r)
        .map(|i| {
            let d = [
                rng.random_range(-1.0..1.0f32),
                rng.random_range(-1.0..1.0),
                1.0,
            ];
            let l = (d[0] * d[0] + d[1] * d[1] + 1.0).sqrt();
            TrainRay {
                origin: [
                    rng.random_range(-0.3..0.3),
                    rng.random_range(-0.3..0.3),
                    -0.5,
                ],
                dir: d.map(|v| v / l),
                appearance: (i % 3) as u32,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn depth_spread_is_zero_on_one_thin_surface_and_half_the_gap_between_two() {
        let edges = [1.0, 2.0, 2.0, 4.0, 4.0, 6.0];
        // All the weight in a zero-length interval at 2: no spread.
        assert_eq!(depth_spread(&[0.0, 1.0, 0.0, 0.0, 0.0], &edges), 0.0);
        // Half at 2, half at 4: σ = 1 (the gap's half).
        assert_eq!(depth_spread(&[0.0, 0.5, 0.0, 0.5, 0.0], &edges), 1.0);
        // All in [4, 6]: uniform over 2, σ² = 4/12.
        let s = depth_spread(&[0.0, 0.0, 0.0, 0.0, 0.7], &edges);
        assert!((s - (4.0f32 / 12.0).sqrt()).abs() < 1e-6, "{s}");
        assert_eq!(depth_spread(&[0.0; 5], &edges), 0.0);
    }

    /// The median depth is where the cumulative weight reaches ½, interpolated within the crossing
    /// sample: on a ray whose weight is split between a near and a far surface it sits on one of them,
    /// while the expected depth floats between; without ½ of the weight it is the far end.
    #[test]
    fn median_depth_sits_on_a_surface() {
        let edges = [1.0, 2.0, 3.0, 4.0, 5.0];
        let split = [0.45, 0.0, 0.0, 0.5];
        assert_eq!(median_depth(&split, &edges), 4.1);
        let out = RayOutput {
            accumulation: 0.99,
            depth: 0.45 * 1.5 + 0.5 * 4.5,
            ..Default::default()
        };
        let e = expected_depth(&out, &edges);
        assert!(e > 2.9 && e < 3.2, "expected depth {e}");
        assert_eq!(median_depth(&[0.25, 0.25, 0.1, 0.0], &edges), 3.0);
        assert_eq!(median_depth(&[0.0, 0.5, 0.1, 0.0], &edges), 3.0);
        assert_eq!(median_depth(&[0.0, 0.8, 0.1, 0.0], &edges), 2.625);
        assert_eq!(median_depth(&[0.1, 0.1, 0.1, 0.1], &edges), 5.0);
    }

    /// Inference colours only the samples that matter: on a field dense enough to hide what lies behind
    /// its surfaces, some samples are skipped, and the render differs from colouring every sample by
    /// less than the skipped weight allows (n × INFERENCE_MIN_WEIGHT per channel).
    #[test]
    fn inference_colours_only_what_the_ray_shows() {
        let cfg = ModelConfig::tiny();
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(11);
        let mut params = Params::init(&cfg, 4).unwrap();
        for t in &mut params.tensors {
            for v in t.iter_mut() {
                *v += rng.random_range(-0.3..0.3f32);
            }
        }
        // A dense field: the density logit's bias high, so rays saturate within a few samples.
        let d = cfg.density_mlp();
        let last = d.layers()[d.n_layers() - 1];
        params.tensors[DENSITY][last.bias] = 6.0;
        let rays = random_rays(&mut rng, 200);
        let n = cfg.sampler.samples;
        let (_, _, t) = propose(&cfg, &params, &rays, None, 1.0, false).unwrap();
        let full = shade_with(&cfg, &params, &rays, &t, 0, false).unwrap();
        let part = shade_with(&cfg, &params, &rays, &t, 0, true).unwrap();
        let skipped = part.samples.len() - part.colour.output.len() / 3;
        assert!(skipped > 0, "nothing skipped");
        let ivs = intervals(&t, rays.len(), n);
        let render = |sh: &Shaded| {
            let rb = RayBatch {
                samples_per_ray: n,
                samples: &sh.samples,
                intervals: &ivs,
                normals: None,
            };
            render::render_cpu(&rb, Background::LastSample).unwrap()
        };
        let (a, b) = (render(&full), render(&part));
        let mut worst = 0.0f32;
        for (x, y) in a.rays.iter().zip(&b.rays) {
            for c in 0..3 {
                worst = worst.max((x.rgb[c] - y.rgb[c]).abs());
            }
            assert_eq!(x.accumulation, y.accumulation);
            assert_eq!(x.depth, y.depth);
        }
        assert!(
            worst <= n as f32 * INFERENCE_MIN_WEIGHT,
            "colour differs by {worst} with {skipped} of {} samples skipped",
            part.samples.len()
        );
    }

    /// The whole step's analytic gradient for the radiance field's tensors (grid, density MLP, colour MLP,
    /// appearance) against central differences of the step's loss. The interlevel term is off: nerfacto
    /// stops its gradient into the final weights, which differences would see.
    #[test]
    fn step_gradient_matches_finite_differences() {
        check_step_gradient(false);
    }

    /// The same with an occupancy grid (refreshed from the field) placing the samples: the field's
    /// gradients still match differences, and the unused proposal fields get exact zeros.
    #[test]
    fn occupancy_grid_step_gradient_matches_finite_differences() {
        check_step_gradient(true);
    }

    fn check_step_gradient(occupancy: bool) {
        // The tiny model with nerfacto's proposal grid depth (the shared tiny model uses 3 levels).
        let mut cfg = ModelConfig::tiny();
        for (p, d) in cfg
            .proposals
            .iter_mut()
            .zip(ModelConfig::nerfacto(3).proposals)
        {
            p.grid.levels = d.grid.levels;
        }
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(5);
        let mut params = Params::init(&cfg, 9).unwrap();
        // Larger than the init so densities and colours vary along the rays.
        for t in &mut params.tensors {
            for v in t.iter_mut() {
                *v += rng.random_range(-0.3..0.3f32);
            }
        }
        let r = 6;
        let rays = random_rays(&mut rng, r);
        let targets: Vec<RayTarget> = (0..r)
            .map(|i| RayTarget {
                rgb: [rng.random(), rng.random(), rng.random()],
                depth: if i < 4 {
                    rng.random_range(0.5..1.5)
                } else {
                    0.0
                },
                normal: if i < 2 { [0.2, -0.3, -1.0] } else { [0.0; 3] },
                sky: (i == 5) as u32,
            })
            .collect();
        let batch = Batch {
            rays,
            targets,
            jitter: (0..r * 3).map(|_| rng.random()).collect(),
            normal_rays: 2,
        };
        let sch = StepSchedule {
            step: 0,
            anneal: 1.0,
            losses: LossConfig {
                rgb: 1.0,
                depth: 0.5,
                normal: 0.1,
                sky: 0.5,
                depth_sigma: 0.3,
            },
            proposal_depth: 0.0,
            proposal_sky: 0.0,
            interlevel: 0.0,
            distortion: 0.01,
            normals: true,
        };
        let mut grid = OccupancyGrid::new(16);
        update_occupancy(&cfg, &params, &mut grid, &mut rng, 0.95).unwrap();
        // The random field is dense everywhere; mark only its denser half occupied.
        let mut d = grid.density.clone();
        d.sort_by(f32::total_cmp);
        grid.threshold = d[d.len() / 2];
        let occupied = grid.occupied_fraction();
        assert!(occupied > 0.0 && occupied < 1.0, "occupied {occupied}");
        let sampling = if occupancy {
            Sampling::Occupancy(&grid)
        } else {
            Sampling::Proposal
        };
        let (grads, _) = train_step_with(sampling, &cfg, &params, &batch, &sch).unwrap();
        assert_eq!(grads.len(), params.tensors.len());
        for (g, t) in grads.iter().zip(&params.tensors) {
            assert_eq!(g.len(), t.len());
        }
        if occupancy {
            assert!(grads[PROPOSAL..].iter().flatten().all(|&g| g == 0.0));
        }
        let loss = |p: &Params| {
            train_step_with(sampling, &cfg, p, &batch, &sch)
                .unwrap()
                .1
                .loss
        };
        for tensor in [GRID, DENSITY, COLOUR, APPEARANCE] {
            // The entries with the largest gradients (the rest are below f32 differencing noise); a
            // small step because ReLU kinks and the hash cells are only piecewise smooth.
            let mut idx: Vec<usize> = (0..grads[tensor].len()).collect();
            idx.sort_by(|&a, &b| grads[tensor][b].abs().total_cmp(&grads[tensor][a].abs()));
            for &i in &idx[..4] {
                let h = 3e-4f32;
                let mut p = params.clone();
                p.tensors[tensor][i] += h;
                let up = loss(&p);
                p.tensors[tensor][i] -= 2.0 * h;
                let down = loss(&p);
                let fd = (up - down) / (2.0 * h as f64);
                let an = grads[tensor][i] as f64;
                assert!(
                    (fd - an).abs() <= 0.05 * an.abs().max(fd.abs()) + 5e-4,
                    "{} [{i}]: analytic {an} vs differences {fd}",
                    params.names[tensor]
                );
            }
        }
    }
}
