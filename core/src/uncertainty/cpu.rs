//! The uncertainty pass on the CPU: the referee of `shaders/uncertainty.wgsl` and the fallback where the
//! only adapter is a software one. Every step is written the plain way (a per-ray map of vertex
//! Jacobians, summed then squared) so that it checks the kernel's pairwise formulation independently.

use std::collections::BTreeMap;

use rayon::prelude::*;

use super::{contraction_vjp, PerturbationGrid};
use crate::field::encoding::contract_unit;
use crate::field::hashgrid;
use crate::field::mlp;
use crate::field::model::{
    colour_input, density_forward_unit_cpu, density_of, DensityEval, ModelConfig, Params, COLOUR,
    DENSITY, GRID,
};
use crate::gpu::GpuError;
use crate::render::{self, alpha, Background, Interval, RayBatch, RayOutput, Sample};
use crate::train::cpu::{appearance_row, expected_depth, intervals, mids, propose, TrainRay};

/// Rendered outputs a ray's Jacobian is taken of: colour R, G, B and the expected depth E.
pub const OUTPUTS: usize = 4;

/// Per final sample: the grid position and d(R, G, B, E)/d(world position).
#[derive(Clone, Debug, Default)]
pub struct SampleJacobians {
    pub samples_per_ray: usize,
    pub unit: Vec<[f32; 3]>,
    pub g: Vec<[[f32; 3]; OUTPUTS]>,
}

/// Below this accumulation a ray's expected depth is the far bound, a constant: no depth Jacobian.
pub const MIN_ACCUMULATION: f32 = 1e-4;

/// One ray's rendered outputs differentiated by each sample's density and colour, for
/// `Background::LastSample`: `d_sigma[i][k]` = dY_k/dσ_i and `colour_weight[i]` = dC_c/dc_{i,c}
/// (wᵢ, plus the remaining transmittance on the last sample, whose colour is the background).
pub fn ray_output_jacobian(
    samples: &[Sample],
    ivs: &[Interval],
    d_sigma: &mut [[f32; OUTPUTS]],
    colour_weight: &mut [f32],
) {
    let n = samples.len();
    let mut w = vec![0.0f32; n];
    let mut t_next = vec![0.0f32; n];
    let mut p = 0.0f32;
    let (mut acc, mut depth) = (0.0f32, 0.0f32);
    let mut last = None;
    for i in 0..n {
        let delta = (ivs[i].end - ivs[i].start).max(0.0);
        let tau = if delta > 0.0 {
            samples[i].density * delta
        } else {
            0.0
        };
        w[i] = (-p).exp() * alpha(tau);
        p += tau;
        t_next[i] = (-p).exp();
        acc += w[i];
        depth += w[i] * 0.5 * (ivs[i].start + ivs[i].end);
        if delta > 0.0 {
            last = Some(i);
        }
    }
    let t_end = (-p).exp();
    let bg = last.map_or([0.0; 3], |l| samples[l].rgb);
    let (near, far) = (ivs[0].start, ivs[n - 1].end);
    let e = if acc > MIN_ACCUMULATION {
        depth / acc
    } else {
        far
    };
    let depth_live = acc > MIN_ACCUMULATION && e >= near && e <= far;
    let mut s_c = [0.0f32; 3];
    let (mut s_a, mut s_d) = (0.0f32, 0.0f32);
    for i in (0..n).rev() {
        let delta = (ivs[i].end - ivs[i].start).max(0.0);
        let mid = 0.5 * (ivs[i].start + ivs[i].end);
        let c = samples[i].rgb;
        let mut out = [0.0f32; OUTPUTS];
        for k in 0..3 {
            out[k] = delta * (t_next[i] * c[k] - s_c[k] - t_end * bg[k]);
        }
        if depth_live {
            let d_a = t_next[i] - s_a;
            let d_d = t_next[i] * mid - s_d;
            out[3] = delta * (d_d - e * d_a) / acc;
        }
        for k in 0..3 {
            s_c[k] += w[i] * c[k];
        }
        s_a += w[i];
        s_d += w[i] * mid;
        d_sigma[i] = out;
        colour_weight[i] = w[i] + if last == Some(i) { t_end } else { 0.0 };
    }
}

/// The field evaluated at explicit world positions (`rays.len()·n` of them, ray-major).
struct FieldAt {
    eval: DensityEval,
    colour_in: Vec<f32>,
    colour: mlp::MlpForward,
    samples: Vec<Sample>,
}

fn field_at(
    cfg: &ModelConfig,
    params: &Params,
    rays: &[TrainRay],
    positions: &[[f32; 3]],
) -> Result<FieldAt, GpuError> {
    let n = cfg.sampler.samples;
    let unit: Vec<[f32; 3]> = positions.iter().map(|&p| contract_unit(p)).collect();
    let eval = density_forward_unit_cpu(
        &cfg.field.grid,
        &cfg.density_mlp(),
        &params.tensors[GRID],
        &params.tensors[DENSITY],
        unit,
    )?;
    let c_cfg = cfg.colour_mlp();
    let ci = c_cfg.input;
    let geo = cfg.field.geo_features;
    let mean = params.mean_appearance(cfg);
    let mut colour_in = vec![0.0f32; positions.len() * ci];
    colour_in
        .par_chunks_mut(ci)
        .enumerate()
        .with_min_len(256)
        .for_each(|(i, row)| {
            let ray = &rays[i / n];
            let out = &eval.mlp.output[i * eval.out_dim..(i + 1) * eval.out_dim];
            let app = appearance_row(cfg, params, &mean, ray.appearance);
            colour_input(ray.dir, &out[1..1 + geo], app, row);
        });
    let colour = mlp::forward_fast(&c_cfg, &params.tensors[COLOUR], &colour_in)?;
    let samples = (0..positions.len())
        .map(|i| Sample {
            rgb: [0, 1, 2].map(|c| colour.output[i * 3 + c]),
            density: density_of(eval.logit(i)).0,
        })
        .collect();
    Ok(FieldAt {
        eval,
        colour_in,
        colour,
        samples,
    })
}

/// The final-level sample edges of rays (no jitter, proposals fully annealed: as rendering).
pub fn final_edges(
    cfg: &ModelConfig,
    params: &Params,
    rays: &[TrainRay],
) -> Result<Vec<f32>, GpuError> {
    Ok(propose(cfg, params, rays, None, 1.0, false)?.2)
}

/// Renders rays with fixed final edges `t` at explicit (possibly displaced) sample positions: the forward
/// the Jacobian differentiates. Returns (R, G, B, E) per ray.
pub fn outputs_at(
    cfg: &ModelConfig,
    params: &Params,
    rays: &[TrainRay],
    t: &[f32],
    positions: &[[f32; 3]],
) -> Result<Vec<[f32; OUTPUTS]>, GpuError> {
    let n = cfg.sampler.samples;
    let fa = field_at(cfg, params, rays, positions)?;
    let ivs = intervals(t, rays.len(), n);
    let rb = RayBatch {
        samples_per_ray: n,
        samples: &fa.samples,
        intervals: &ivs,
        normals: None,
    };
    let out = render::render_cpu(&rb, Background::LastSample)?;
    Ok(out
        .rays
        .iter()
        .enumerate()
        .map(|(r, o): (usize, &RayOutput)| {
            let te = &t[r * (n + 1)..(r + 1) * (n + 1)];
            let e = if o.accumulation > MIN_ACCUMULATION {
                expected_depth(o, te)
            } else {
                te[n]
            };
            [o.rgb[0], o.rgb[1], o.rgb[2], e]
        })
        .collect())
}

/// d(R, G, B, E)/d(world position) of every final sample of `rays` (edges from [`final_edges`]).
pub fn sample_jacobians_cpu(
    cfg: &ModelConfig,
    params: &Params,
    rays: &[TrainRay],
    t: &[f32],
) -> Result<SampleJacobians, GpuError> {
    let n = cfg.sampler.samples;
    let r = rays.len();
    let rn = r * n;
    let pos = mids(rays, t, n);
    let fa = field_at(cfg, params, rays, &pos)?;
    let ivs = intervals(t, r, n);
    let mut d_sigma = vec![[0.0f32; OUTPUTS]; rn];
    let mut cw = vec![0.0f32; rn];
    d_sigma
        .par_chunks_mut(n)
        .zip(cw.par_chunks_mut(n))
        .enumerate()
        .for_each(|(ray, (ds, c))| {
            let s = ray * n..(ray + 1) * n;
            ray_output_jacobian(&fa.samples[s.clone()], &ivs[s], ds, c)
        });
    let d_cfg = cfg.density_mlp();
    let c_cfg = cfg.colour_mlp();
    let od = d_cfg.output;
    let geo = cfg.field.geo_features;
    let mut g = vec![[[0.0f32; 3]; OUTPUTS]; rn];
    for k in 0..OUTPUTS {
        let d_cin = if k < 3 {
            let mut d_rgb = vec![0.0f32; rn * 3];
            for i in 0..rn {
                d_rgb[3 * i + k] = cw[i];
            }
            mlp::input_gradient_fast(
                &c_cfg,
                &params.tensors[COLOUR],
                &fa.colour_in,
                &fa.colour.saved,
                &d_rgb,
            )?
        } else {
            vec![0.0f32; rn * c_cfg.input]
        };
        let mut d_out = vec![0.0f32; rn * od];
        for i in 0..rn {
            d_out[i * od] = d_sigma[i][k] * density_of(fa.eval.logit(i)).1;
            d_out[i * od + 1..i * od + 1 + geo]
                .copy_from_slice(&d_cin[i * c_cfg.input + 16..i * c_cfg.input + 16 + geo]);
        }
        let d_features = mlp::input_gradient_fast(
            &d_cfg,
            &params.tensors[DENSITY],
            &fa.eval.features,
            &fa.eval.mlp.saved,
            &d_out,
        )?;
        let d_unit = hashgrid::position_gradients_cpu(
            &cfg.field.grid,
            &params.tensors[GRID],
            &fa.eval.unit,
            &d_features,
        )?;
        for i in 0..rn {
            g[i][k] = contraction_vjp(pos[i], d_unit[i]);
        }
    }
    Ok(SampleJacobians {
        samples_per_ray: n,
        unit: fa.eval.unit,
        g,
    })
}

/// One ray's Jacobian with respect to each perturbation vertex it touches: J_v,k = Σᵢ βᵢᵥ gᵢₖ.
pub fn ray_vertex_jacobians(
    grid: PerturbationGrid,
    sj: &SampleJacobians,
    ray: usize,
) -> BTreeMap<usize, [[f64; 3]; OUTPUTS]> {
    let n = sj.samples_per_ray;
    let mut map: BTreeMap<usize, [[f64; 3]; OUTPUTS]> = BTreeMap::new();
    for i in ray * n..(ray + 1) * n {
        let (idx, w) = grid.corners(sj.unit[i]);
        for c in 0..8 {
            if w[c] == 0.0 {
                continue;
            }
            let e = map.entry(idx[c]).or_insert([[0.0; 3]; OUTPUTS]);
            for (ek, gk) in e.iter_mut().zip(&sj.g[i]) {
                for (ed, gd) in ek.iter_mut().zip(gk) {
                    *ed += w[c] as f64 * *gd as f64;
                }
            }
        }
    }
    map
}

/// Adds the rays' Fisher diagonals (colour: Σ over R, G, B) to `h_colour`, `h_depth`, each ray to the
/// accumulators its flags select ([`super::COLOUR_RAY`], [`super::DEPTH_RAY`]): per ray the vertex
/// Jacobians are summed over samples, then squared.
pub fn accumulate_fisher_cpu(
    grid: PerturbationGrid,
    sj: &SampleJacobians,
    flags: &[u32],
    h_colour: &mut [f64],
    h_depth: &mut [f64],
) {
    let per_ray: Vec<Vec<(usize, f64, f64)>> = (0..flags.len())
        .into_par_iter()
        .map(|ray| {
            ray_vertex_jacobians(grid, sj, ray)
                .into_iter()
                .map(|(v, j)| {
                    let sq = |k: usize| j[k].iter().map(|x| x * x).sum::<f64>();
                    let f = flags[ray];
                    let hc = if f & super::COLOUR_RAY != 0 {
                        sq(0) + sq(1) + sq(2)
                    } else {
                        0.0
                    };
                    let hd = if f & super::DEPTH_RAY != 0 {
                        sq(3)
                    } else {
                        0.0
                    };
                    (v, hc, hd)
                })
                .collect()
        })
        .collect();
    for (v, hc, hd) in per_ray.into_iter().flatten() {
        h_colour[v] += hc;
        h_depth[v] += hd;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    pub(crate) fn setup(seed: u64, r: usize) -> (ModelConfig, Params, Vec<TrainRay>) {
        let cfg = ModelConfig::tiny();
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed);
        let mut params = Params::init(&cfg, seed).unwrap();
        for t in &mut params.tensors {
            for v in t.iter_mut() {
                *v += rng.random_range(-0.3..0.3f32);
            }
        }
        let rays = crate::train::cpu::random_rays(&mut rng, r);
        (cfg, params, rays)
    }

    /// The per-ray Jacobian of (R, G, B, E) with respect to one perturbation vertex's offset against
    /// central differences of the displaced render (the offsets move every sample touching the vertex
    /// by βᵢᵥ·h along one axis).
    #[test]
    fn per_ray_vertex_jacobian_matches_finite_differences() {
        let (cfg, params, rays) = setup(3, 5);
        let grid = PerturbationGrid { cells: 8 };
        let t = final_edges(&cfg, &params, &rays).unwrap();
        let sj = sample_jacobians_cpu(&cfg, &params, &rays, &t).unwrap();
        let n = cfg.sampler.samples;
        let pos = mids(&rays, &t, n);
        let mut checked = 0;
        for ray in 0..rays.len() {
            let jac = ray_vertex_jacobians(grid, &sj, ray);
            // The vertex with the largest colour Jacobian on this ray.
            let (&v, j) = jac
                .iter()
                .max_by(|a, b| {
                    let m = |j: &[[f64; 3]; OUTPUTS]| {
                        j[..3].iter().flatten().map(|x| x.abs()).sum::<f64>()
                    };
                    m(a.1).total_cmp(&m(b.1))
                })
                .unwrap();
            let one = [rays[ray]];
            let te = &t[ray * (n + 1)..(ray + 1) * (n + 1)];
            for d in 0..3 {
                let h = 1e-3f32;
                let shifted = |s: f32| -> Vec<[f32; 3]> {
                    (0..n)
                        .map(|i| {
                            let gi = ray * n + i;
                            let (idx, w) = grid.corners(sj.unit[gi]);
                            let mut p = pos[gi];
                            for c in 0..8 {
                                if idx[c] == v {
                                    p[d] += s * w[c];
                                }
                            }
                            p
                        })
                        .collect()
                };
                let up = outputs_at(&cfg, &params, &one, te, &shifted(h)).unwrap()[0];
                let down = outputs_at(&cfg, &params, &one, te, &shifted(-h)).unwrap()[0];
                for k in 0..OUTPUTS {
                    let fd = (up[k] - down[k]) as f64 / (2.0 * h as f64);
                    let an = j[k][d];
                    assert!(
                        (fd - an).abs() <= 0.03 * an.abs().max(fd.abs()) + 2e-3,
                        "ray {ray} vertex {v} axis {d} output {k}: analytic {an} vs differences {fd}"
                    );
                    if an.abs() > 1e-2 {
                        checked += 1;
                    }
                }
            }
        }
        assert!(
            checked >= 10,
            "only {checked} non-trivial Jacobian entries checked"
        );
    }

    #[test]
    fn render_jacobian_matches_differences_of_the_renderer() {
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(11);
        let n = 12;
        let mut edges: Vec<f32> = (0..=n).map(|_| rng.random_range(0.2..4.0f32)).collect();
        edges.sort_by(f32::total_cmp);
        edges[4] = edges[3]; // a zero-length interval
        let ivs: Vec<Interval> = (0..n)
            .map(|i| Interval {
                start: edges[i],
                end: edges[i + 1],
            })
            .collect();
        let samples: Vec<Sample> = (0..n)
            .map(|_| Sample {
                rgb: [rng.random(), rng.random(), rng.random()],
                density: rng.random_range(0.0..1.5),
            })
            .collect();
        let render = |s: &[Sample]| -> [f32; OUTPUTS] {
            let rb = RayBatch {
                samples_per_ray: n,
                samples: s,
                intervals: &ivs,
                normals: None,
            };
            let o = render::render_cpu(&rb, Background::LastSample)
                .unwrap()
                .rays[0];
            [o.rgb[0], o.rgb[1], o.rgb[2], expected_depth(&o, &edges)]
        };
        let mut ds = vec![[0.0f32; OUTPUTS]; n];
        let mut cw = vec![0.0f32; n];
        ray_output_jacobian(&samples, &ivs, &mut ds, &mut cw);
        for i in 0..n {
            let h = 1e-3;
            let mut up = samples.clone();
            up[i].density += h;
            let mut down = samples.clone();
            down[i].density -= h;
            let (a, b) = (render(&up), render(&down));
            for k in 0..OUTPUTS {
                let fd = (a[k] - b[k]) / (2.0 * h);
                assert!(
                    (fd - ds[i][k]).abs() <= 1e-2 * fd.abs().max(ds[i][k].abs()) + 1e-3,
                    "sample {i} output {k}: {} vs {fd}",
                    ds[i][k]
                );
            }
            let mut up = samples.clone();
            up[i].rgb[1] += h;
            let fd = (render(&up)[1] - render(&samples)[1]) / h;
            assert!(
                (fd - cw[i]).abs() < 1e-3,
                "colour weight {i}: {} vs {fd}",
                cw[i]
            );
        }
    }

    /// More lidar rays through a region → more depth information there: repeating one lidar ray adds its
    /// squared Jacobian once per copy to exactly the vertices it touches (lower posterior variance there),
    /// leaves every other vertex and the colour Fisher of depth-only rays alone.
    #[test]
    fn more_lidar_rays_lower_depth_variance_only_where_they_pass() {
        use super::super::{COLOUR_RAY, DEPTH_RAY};
        let (cfg, params, rays) = setup(5, 6);
        let grid = PerturbationGrid { cells: 8 };
        let nv = grid.vertices();
        let fisher = |rays: &[TrainRay], flags: &[u32]| {
            let t = final_edges(&cfg, &params, rays).unwrap();
            let sj = sample_jacobians_cpu(&cfg, &params, rays, &t).unwrap();
            let (mut hc, mut hd) = (vec![0.0; nv], vec![0.0; nv]);
            accumulate_fisher_cpu(grid, &sj, flags, &mut hc, &mut hd);
            (hc, hd)
        };
        let flags = vec![COLOUR_RAY | DEPTH_RAY; rays.len()];
        let (hc1, hd1) = fisher(&rays, &flags);
        // Three more lidar returns along ray 0 (depth only).
        let mut more = rays.clone();
        more.extend([rays[0]; 3]);
        let mut more_flags = flags.clone();
        more_flags.extend([DEPTH_RAY; 3]);
        let (hc2, hd2) = fisher(&more, &more_flags);
        let t0 = final_edges(&cfg, &params, &rays[..1]).unwrap();
        let sj0 = sample_jacobians_cpu(&cfg, &params, &rays[..1], &t0).unwrap();
        let touched: BTreeMap<usize, f64> = ray_vertex_jacobians(grid, &sj0, 0)
            .into_iter()
            .map(|(v, j)| (v, j[3].iter().map(|x| x * x).sum::<f64>()))
            .collect();
        let mut lowered = 0;
        for v in 0..nv {
            assert_eq!(
                hc1[v], hc2[v],
                "vertex {v}: depth-only rays changed the colour Fisher"
            );
            let own = touched.get(&v).copied().unwrap_or(0.0);
            let want = hd1[v] + 3.0 * own;
            assert!(
                (hd2[v] - want).abs() <= 1e-9 * want.abs().max(1e-12),
                "vertex {v}: {} vs {want}",
                hd2[v]
            );
            if own > 1e-12 {
                lowered += 1;
                // Posterior variance 1/(H/N + λ) falls wherever the extra rays pass.
                assert!(1.0 / (hd2[v] + 1e-4) < 1.0 / (hd1[v] + 1e-4));
            } else {
                assert_eq!(hd1[v], hd2[v], "vertex {v} untouched by ray 0 changed");
            }
        }
        assert!(
            lowered >= 8,
            "ray 0 touched only {lowered} vertices with depth information"
        );
    }
}
