// The uncertainty pass (paper §Epistemic uncertainty; BayesRays' Fisher diagonal, extended to lidar depth):
// the Jacobian of each ray's rendered colour (R, G, B) and expected depth E with respect to a perturbation
// grid of offsets added to the frozen field's world-space sample positions, summed over the ray's samples
// and squared into per-vertex Fisher diagonals. CPU reference: core/src/uncertainty/cpu.rs. The field's
// own backward (colour MLP, density MLP, hash grid → position) runs between these entries with the
// trainer's kernels (core/src/uncertainty/gpu.rs records the chain).
//
// Layouts, ray-major as train.wgsl: n samples per ray, n + 1 edges; samples vec4 (rgb, sigma); intervals
// vec2 (start, end); rays 8 f32; grid positions 3 f32 in [0, 1]^3;
// g 12 f32 per sample: d(R, G, B, E)/d(world position), output-major.
//
// One thread per ray or per sample (64 per workgroup, dispatch possibly folded into 2-D). At most 8
// storage buffers per entry (WebGPU's default limit).

const WG: u32 = 64u;
const MAX_LOGIT: f32 = 15.0;
const MIN_ACCUMULATION: f32 = 1e-4;

struct Params {
    count: u32,
    // Samples per ray.
    n: u32,
    // Output this dispatch differentiates (0..3 = R, G, B; 3 = E).
    k: u32,
    // Density-MLP output width, geometry features, colour-MLP input width.
    out_dim: u32,
    geo: u32,
    c_in: u32,
    // Perturbation cells per axis.
    cells: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> prm: Params;
@group(0) @binding(1) var<storage, read> samples: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> intervals: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read_write> jac: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> cw: array<f32>;
@group(0) @binding(5) var<storage, read_write> d_rgb: array<f32>;
@group(0) @binding(6) var<storage, read> logits: array<f32>;
@group(0) @binding(7) var<storage, read> d_cin: array<f32>;
@group(0) @binding(8) var<storage, read_write> d_out: array<f32>;
@group(0) @binding(9) var<storage, read> rays: array<f32>;
@group(0) @binding(10) var<storage, read> t_edges: array<f32>;
@group(0) @binding(11) var<storage, read> d_pos: array<f32>;
@group(0) @binding(12) var<storage, read_write> g: array<f32>;
@group(0) @binding(13) var<storage, read> pos: array<f32>;
// Per ray: bit 0 = accumulate colour, bit 1 = accumulate depth (a lidar return).
@group(0) @binding(14) var<storage, read> flags: array<u32>;
@group(0) @binding(15) var<storage, read_write> h_colour: array<atomic<u32>>;
@group(0) @binding(16) var<storage, read_write> h_depth: array<atomic<u32>>;

fn thread_index(wg: vec3<u32>, nwg: vec3<u32>, li: u32) -> u32 {
    return (wg.y * nwg.x + wg.x) * WG + li;
}

// 1 - exp(-tau) by its series below 0.125, as render.wgsl.
fn alpha(tau: f32) -> f32 {
    if (tau < 0.125) {
        return tau * (1.0 - tau * (0.5 - tau * (1.0 / 6.0 - tau * (1.0 / 24.0 - tau * (1.0 / 120.0)))));
    }
    return 1.0 - exp(-tau);
}

// Per ray: jac[i] = dY/dsigma_i for Y = (R, G, B, E) and cw[i] = dC_c/dc_{i,c} (the weight, plus the
// remaining transmittance on the last sample, whose colour is LastSample's background). Forward
// quantities are parked in the outputs between the two loops (cw = w, jac.w = T_{i+1}).
@compute @workgroup_size(64)
fn output_jacobian(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(local_invocation_index) li: u32) {
    let r = thread_index(wg, nwg, li);
    if (r >= prm.count) {
        return;
    }
    let n = prm.n;
    let d0 = r * n;
    var p = 0.0;
    var acc = 0.0;
    var depth = 0.0;
    var last = n;
    for (var i = 0u; i < n; i++) {
        let iv = intervals[d0 + i];
        let delta = max(iv.y - iv.x, 0.0);
        var tau = 0.0;
        if (delta > 0.0) {
            tau = samples[d0 + i].w * delta;
            last = i;
        }
        let w = exp(-p) * alpha(tau);
        p += tau;
        cw[d0 + i] = w;
        jac[d0 + i] = vec4<f32>(0.0, 0.0, 0.0, exp(-p));
        acc += w;
        depth += w * 0.5 * (iv.x + iv.y);
    }
    let t_end = exp(-p);
    var bg = vec3<f32>(0.0);
    if (last < n) {
        bg = samples[d0 + last].xyz;
    }
    let near = intervals[d0].x;
    let far = intervals[d0 + n - 1u].y;
    var e = far;
    if (acc > MIN_ACCUMULATION) {
        e = depth / acc;
    }
    let depth_live = acc > MIN_ACCUMULATION && e >= near && e <= far;
    var s_c = vec3<f32>(0.0);
    var s_a = 0.0;
    var s_d = 0.0;
    for (var ii = 0u; ii < n; ii++) {
        let i = n - 1u - ii;
        let iv = intervals[d0 + i];
        let delta = max(iv.y - iv.x, 0.0);
        let mid = 0.5 * (iv.x + iv.y);
        let c = samples[d0 + i].xyz;
        let w = cw[d0 + i];
        let t_next = jac[d0 + i].w;
        let dc = delta * (t_next * c - s_c - t_end * bg);
        var de = 0.0;
        if (depth_live) {
            de = delta * ((t_next * mid - s_d) - e * (t_next - s_a)) / acc;
        }
        s_c += w * c;
        s_a += w;
        s_d += w * mid;
        jac[d0 + i] = vec4<f32>(dc, de);
        var cwi = w;
        if (i == last) {
            cwi += t_end;
        }
        cw[d0 + i] = cwi;
    }
}

// Per sample: the colour-MLP output gradient of output k (e_k * cw for a colour channel, 0 for depth).
@compute @workgroup_size(64)
fn seed_colour(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
               @builtin(local_invocation_index) li: u32) {
    let i = thread_index(wg, nwg, li);
    if (i >= prm.count) {
        return;
    }
    for (var c = 0u; c < 3u; c++) {
        d_rgb[3u * i + c] = select(0.0, cw[i], c == prm.k);
    }
}

// Per sample: the density-MLP output gradient of output k: the logit column through trunc_exp, the
// geometry columns from the colour MLP's input gradient.
@compute @workgroup_size(64)
fn density_seed(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) li: u32) {
    let i = thread_index(wg, nwg, li);
    if (i >= prm.count) {
        return;
    }
    let od = prm.out_dim;
    let j = jac[i];
    let d_sigma = select(select(select(j.w, j.z, prm.k == 2u), j.y, prm.k == 1u), j.x, prm.k == 0u);
    let l = logits[i * od];
    d_out[i * od] = d_sigma * exp(clamp(l, -MAX_LOGIT, MAX_LOGIT));
    // Depth has no colour path: the colour MLP's backward is skipped for it and d_cin is stale.
    for (var c = 0u; c < prm.geo; c++) {
        d_out[i * od + 1u + c] = select(0.0, d_cin[i * prm.c_in + 16u + c], prm.k < 3u);
    }
}

// dY/dx (world) from dY/du through the L-inf contraction and (x + 2) / 4.
fn contraction_vjp(x: vec3<f32>, du: vec3<f32>) -> vec3<f32> {
    let ax = abs(x);
    let m = max(ax.x, max(ax.y, ax.z));
    if (!(m > 1.0) || !(m <= 3.0e38)) {
        return 0.25 * du;
    }
    let k = 2.0 / m - 1.0 / (m * m);
    let dk = -2.0 / (m * m) + 2.0 / (m * m * m);
    let gx = dot(du, x);
    var out = 0.25 * k * du;
    if (ax.x >= ax.y && ax.x >= ax.z) {
        out.x += 0.25 * gx * dk * sign(x.x);
    } else if (ax.y >= ax.z) {
        out.y += 0.25 * gx * dk * sign(x.y);
    } else {
        out.z += 0.25 * gx * dk * sign(x.z);
    }
    return out;
}

// Per sample: g[k] = dY_k/d(world position) from the hash grid's position gradient.
@compute @workgroup_size(64)
fn store_output(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) li: u32) {
    let i = thread_index(wg, nwg, li);
    if (i >= prm.count) {
        return;
    }
    let n = prm.n;
    let r = i / n;
    let e = r * (n + 1u) + i % n;
    let mid = 0.5 * (t_edges[e] + t_edges[e + 1u]);
    let o = vec3<f32>(rays[8u * r], rays[8u * r + 1u], rays[8u * r + 2u]);
    let d = vec3<f32>(rays[8u * r + 3u], rays[8u * r + 4u], rays[8u * r + 5u]);
    let du = vec3<f32>(d_pos[3u * i], d_pos[3u * i + 1u], d_pos[3u * i + 2u]);
    let gx = contraction_vjp(o + d * mid, du);
    let b = 12u * i + 3u * prm.k;
    g[b] = gx.x;
    g[b + 1u] = gx.y;
    g[b + 2u] = gx.z;
}

struct Cell {
    base: vec3<u32>,
    t: vec3<f32>,
}

fn locate(u: vec3<f32>) -> Cell {
    let l = f32(prm.cells);
    let x = clamp(u, vec3<f32>(0.0), vec3<f32>(1.0)) * l;
    let base = min(vec3<u32>(floor(x)), vec3<u32>(prm.cells - 1u));
    return Cell(base, x - vec3<f32>(base));
}

fn sample_cell(i: u32) -> Cell {
    return locate(vec3<f32>(pos[3u * i], pos[3u * i + 1u], pos[3u * i + 2u]));
}

fn corner_weight(t: vec3<f32>, b: vec3<u32>) -> f32 {
    let f = select(vec3<f32>(1.0) - t, t, b == vec3<u32>(1u));
    return f.x * f.y * f.z;
}

fn vertex_index(v: vec3<u32>) -> u32 {
    let s = prm.cells + 1u;
    return (v.x * s + v.y) * s + v.z;
}

fn g_row(i: u32, k: u32) -> vec3<f32> {
    let b = 12u * i + 3u * k;
    return vec3<f32>(g[b], g[b + 1u], g[b + 2u]);
}

fn add_colour(i: u32, v: f32) {
    var old = atomicLoad(&h_colour[i]);
    loop {
        let r = atomicCompareExchangeWeak(&h_colour[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (r.exchanged) {
            break;
        }
        old = r.old_value;
    }
}

fn add_depth(i: u32, v: f32) {
    var old = atomicLoad(&h_depth[i]);
    loop {
        let r = atomicCompareExchangeWeak(&h_depth[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (r.exchanged) {
            break;
        }
        old = r.old_value;
    }
}

// Per ray: H_v += ||sum_i beta_iv g_i||^2 without materialising the per-vertex sums: expanded into
// sum_i beta_iv^2 |g_i|^2 + 2 sum_{i<j} beta_iv beta_jv g_i.g_j, where only samples in the same or an
// adjacent cell share a vertex. Each (sample, corner) adds its share once (colour: R, G, B summed), to
// the accumulators the ray's flags select.
@compute @workgroup_size(64)
fn fisher(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
          @builtin(local_invocation_index) li: u32) {
    let r = thread_index(wg, nwg, li);
    if (r >= prm.count) {
        return;
    }
    let n = prm.n;
    let d0 = r * n;
    let use_colour = (flags[r] & 1u) != 0u;
    let use_depth = (flags[r] & 2u) != 0u;
    if (!use_colour && !use_depth) {
        return;
    }
    for (var i = 0u; i < n; i++) {
        let ci = sample_cell(d0 + i);
        let gi0 = g_row(d0 + i, 0u);
        let gi1 = g_row(d0 + i, 1u);
        let gi2 = g_row(d0 + i, 2u);
        let gi3 = g_row(d0 + i, 3u);
        let own_c = dot(gi0, gi0) + dot(gi1, gi1) + dot(gi2, gi2);
        let own_d = dot(gi3, gi3);
        var acc_c: array<f32, 8>;
        var acc_d: array<f32, 8>;
        var beta: array<f32, 8>;
        for (var c = 0u; c < 8u; c++) {
            let b = vec3<u32>((c >> 2u) & 1u, (c >> 1u) & 1u, c & 1u);
            let w = corner_weight(ci.t, b);
            beta[c] = w;
            acc_c[c] = w * w * own_c;
            acc_d[c] = w * w * own_d;
        }
        for (var j = i + 1u; j < n; j++) {
            let cj = sample_cell(d0 + j);
            let off = vec3<i32>(ci.base) - vec3<i32>(cj.base);
            // ci + b - cj must be a corner of j's cell for some b in {0,1}^3: off in {-1, 0, 1}^3.
            if (any(off < vec3<i32>(-1)) || any(off > vec3<i32>(1))) {
                continue;
            }
            let dot_c = dot(gi0, g_row(d0 + j, 0u)) + dot(gi1, g_row(d0 + j, 1u))
                + dot(gi2, g_row(d0 + j, 2u));
            let dot_d = dot(gi3, g_row(d0 + j, 3u));
            for (var c = 0u; c < 8u; c++) {
                let b = vec3<i32>(i32((c >> 2u) & 1u), i32((c >> 1u) & 1u), i32(c & 1u));
                let o = off + b;
                if (any(o < vec3<i32>(0)) || any(o > vec3<i32>(1))) {
                    continue;
                }
                let bj = corner_weight(cj.t, vec3<u32>(o));
                let s = 2.0 * beta[c] * bj;
                acc_c[c] += s * dot_c;
                acc_d[c] += s * dot_d;
            }
        }
        for (var c = 0u; c < 8u; c++) {
            if (beta[c] == 0.0) {
                continue;
            }
            let b = vec3<u32>((c >> 2u) & 1u, (c >> 1u) & 1u, c & 1u);
            let v = vertex_index(ci.base + b);
            if (use_colour && acc_c[c] != 0.0) {
                add_colour(v, acc_c[c]);
            }
            if (use_depth && acc_d[c] != 0.0) {
                add_depth(v, acc_d[c]);
            }
        }
    }
}

// Zeroes the Fisher accumulators (count = vertices).
@compute @workgroup_size(64)
fn clear_fisher(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) li: u32) {
    let i = thread_index(wg, nwg, li);
    if (i >= prm.count) {
        return;
    }
    atomicStore(&h_colour[i], 0u);
    atomicStore(&h_depth[i], 0u);
}
