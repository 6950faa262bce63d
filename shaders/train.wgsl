// nerfacto's training glue around the hash grid, MLP and render kernels: proposal sampling, the field's
// parameter-free parts (L-inf contraction, SH view encoding, trunc_exp), finite-difference normals, the
// sampler losses (interlevel, distortion, SiLVR's depth / sky terms on proposal weights), the gradient
// plumbing between the kernels, and Adam. CPU references: core/src/sampler, core/src/field/encoding.rs,
// core/src/field/model.rs, core/src/train/cpu.rs (whose train_step chains the same steps in the same order)
// and core/src/train/adam.rs.
//
// Layouts, ray-major: a level with n samples per ray has n + 1 edges per ray (s normalised, t distance),
// positions 3 f32 per sample in the grid's [0, 1]^3; rays are 8 f32 (origin xyz, direction xyz,
// appearance row as u32 bits, pad). Density-MLP output rows are `out_dim` wide, column 0 the logit.
// Per-ray scratch is 2 * (max_n + 1) f32 at ray * scratch_stride.
//
// One thread per ray, per sample or per element (64 per workgroup, dispatch possibly folded into 2-D):
// index = (wg.y * nwg.x + wg.x) * 64 + local index, bounds-checked against the entry's count.
//
// WebGPU allows 8 storage buffers per stage by default, so each entry point uses at most 8.

const WG: u32 = 64u;
const MAX_LOGIT: f32 = 15.0;
const INTERLEVEL_EPS: f32 = 1.1920929e-7;
const LOG_EPS: f32 = 1e-7;
const NO_APPEARANCE: u32 = 0xffffffffu;
const NOT_SELECTED: u32 = 0xffffffffu;
// train::cpu::INFERENCE_MIN_WEIGHT.
const INFERENCE_MIN_WEIGHT: f32 = 1e-4;

struct Params {
    // Threads of this dispatch (rays, samples or elements).
    count: u32,
    n_rays: u32,
    // Samples per ray of the level read (n_in) and of the level written (n_out).
    n_in: u32,
    n_out: u32,
    // Jitter values per ray (levels), this dispatch's jitter column, and 1 to use jitter.
    n_levels: u32,
    level: u32,
    use_jitter: u32,
    // Density-MLP output width (1 + geometry features) and geometry feature count.
    out_dim: u32,
    geo: u32,
    app_dim: u32,
    images: u32,
    // Colour-MLP input width (16 + geo + app_dim).
    c_in: u32,
    // Rays (a prefix of the batch) whose final samples get FD normals.
    normal_rays: u32,
    scratch_stride: u32,
    // Column of ray_stats this dispatch writes, and the row width.
    stat_col: u32,
    stat_stride: u32,
    g_near: f32,
    g_span: f32,
    anneal: f32,
    padding: f32,
    normal_step: f32,
    // Gradient scales (loss weights with the batch means folded in).
    scale_a: f32,
    scale_b: f32,
    scale_c: f32,
    // 1 / (2 sigma^2) of the DS-NeRF Gaussian (scene units).
    inv_two_var: f32,
    // Adam: lr / (1 - b1^t), 1 / sqrt(1 - b2^t), b1, b2, eps.
    adam_a: f32,
    adam_c: f32,
    beta1: f32,
    beta2: f32,
    eps: f32,
    _pad0: u32,
    _pad1: u32,
}

struct Target {
    rgb: vec3<f32>,
    depth: f32,
    normal: vec3<f32>,
    sky: u32,
}

@group(0) @binding(0) var<uniform> prm: Params;
@group(0) @binding(1) var<storage, read> rays: array<f32>;
@group(0) @binding(2) var<storage, read> jitter: array<f32>;
@group(0) @binding(3) var<storage, read> s_in: array<f32>;
@group(0) @binding(4) var<storage, read> t_in: array<f32>;
@group(0) @binding(5) var<storage, read> logits: array<f32>;
@group(0) @binding(6) var<storage, read_write> s_out: array<f32>;
@group(0) @binding(7) var<storage, read_write> t_out: array<f32>;
@group(0) @binding(8) var<storage, read_write> pos_out: array<f32>;
@group(0) @binding(9) var<storage, read_write> weights: array<f32>;
@group(0) @binding(10) var<storage, read_write> density: array<f32>;
@group(0) @binding(11) var<storage, read_write> scratch: array<f32>;
@group(0) @binding(12) var<storage, read> colour_out: array<f32>;
@group(0) @binding(13) var<storage, read_write> samples: array<vec4<f32>>;
@group(0) @binding(14) var<storage, read_write> intervals: array<vec2<f32>>;
@group(0) @binding(15) var<storage, read_write> normals: array<f32>;
@group(0) @binding(16) var<storage, read_write> grad_len: array<f32>;
@group(0) @binding(17) var<storage, read_write> colour_in: array<f32>;
@group(0) @binding(18) var<storage, read> appearance: array<f32>;
@group(0) @binding(19) var<storage, read_write> mean_app: array<f32>;
@group(0) @binding(20) var<storage, read_write> d_samples: array<vec4<f32>>;
@group(0) @binding(21) var<storage, read> d_normals: array<f32>;
@group(0) @binding(22) var<storage, read> d_cin: array<f32>;
@group(0) @binding(23) var<storage, read_write> d_out: array<f32>;
@group(0) @binding(24) var<storage, read_write> ray_stats: array<f32>;
@group(0) @binding(25) var<storage, read> targets: array<Target>;
@group(0) @binding(26) var<storage, read> s_fin: array<f32>;
@group(0) @binding(27) var<storage, read> w_fin: array<f32>;
@group(0) @binding(28) var<storage, read_write> g_app: array<atomic<u32>>;
@group(0) @binding(29) var<storage, read_write> param: array<f32>;
@group(0) @binding(30) var<storage, read_write> adam_m: array<f32>;
@group(0) @binding(31) var<storage, read_write> adam_v: array<f32>;
@group(0) @binding(32) var<storage, read> grad: array<f32>;
@group(0) @binding(33) var<storage, read> w_in: array<f32>;
@group(0) @binding(34) var<storage, read> dens_in: array<f32>;
@group(0) @binding(35) var<storage, read_write> d_rgb: array<f32>;
// Inference's colour selection (colour_count, colour_select, colour_input with selection, shade):
// per-ray counts and offsets, the selected samples in order, and per sample its row or NOT_SELECTED.
@group(0) @binding(36) var<storage, read_write> sel_count: array<u32>;
@group(0) @binding(37) var<storage, read> sel_offset: array<u32>;
@group(0) @binding(38) var<storage, read_write> sel_list: array<u32>;
@group(0) @binding(39) var<storage, read_write> sel_index: array<u32>;

fn thread_index(wg: vec3<u32>, nwg: vec3<u32>, li: u32) -> u32 {
    return (wg.y * nwg.x + wg.x) * WG + li;
}

// ---- parameter-free field parts (core/src/field/encoding.rs) ----

fn contract_unit(x: vec3<f32>) -> vec3<f32> {
    let m = max(abs(x.x), max(abs(x.y), abs(x.z)));
    // NaN fails every comparison; inf is caught by the bound.
    if (!(m <= 3.0e38) || x.x != x.x || x.y != x.y || x.z != x.z) {
        return vec3<f32>(0.5);
    }
    var k = 1.0;
    if (m > 1.0) {
        k = (2.0 - 1.0 / m) / m;
    }
    return (x * k + 2.0) * 0.25;
}

fn sh4(d: vec3<f32>, i: u32) -> f32 {
    let x = d.x;
    let y = d.y;
    let z = d.z;
    let xx = x * x;
    let yy = y * y;
    let zz = z * z;
    switch (i) {
        case 0u: { return 0.2820948; }
        case 1u: { return -0.48860252 * y; }
        case 2u: { return 0.48860252 * z; }
        case 3u: { return -0.48860252 * x; }
        case 4u: { return 1.0925485 * (x * y); }
        case 5u: { return -1.0925485 * (y * z); }
        case 6u: { return 0.9461747 * zz - 0.31539157; }
        case 7u: { return -1.0925485 * (x * z); }
        case 8u: { return 0.54627424 * (xx - yy); }
        case 9u: { return 0.5900436 * y * (-3.0 * xx + yy); }
        case 10u: { return 2.8906114 * (x * y) * z; }
        case 11u: { return 0.4570458 * y * (1.0 - 5.0 * zz); }
        case 12u: { return 0.37317633 * z * (5.0 * zz - 3.0); }
        case 13u: { return 0.4570458 * x * (1.0 - 5.0 * zz); }
        case 14u: { return 1.4453057 * z * (xx - yy); }
        default: { return 0.5900436 * x * (-xx + 3.0 * yy); }
    }
}

// sigma = exp(min(logit, 15)).
fn density_of(logit: f32) -> f32 {
    return exp(min(logit, MAX_LOGIT));
}

// d sigma / d logit as nerfstudio's trunc_exp: exp(clamp(logit, -15, 15)).
fn d_density_of(logit: f32) -> f32 {
    return exp(clamp(logit, -MAX_LOGIT, MAX_LOGIT));
}

fn alpha(tau: f32) -> f32 {
    if (tau < 0.125) {
        return tau * (1.0 - tau * (0.5 - tau * (1.0 / 6.0 - tau * (1.0 / 24.0 - tau * (1.0 / 120.0)))));
    }
    return 1.0 - exp(-tau);
}

fn spacing_inv(g: f32) -> f32 {
    if (g < 0.5) {
        return 2.0 * g;
    }
    return 0.5 / max(1.0 - g, 1e-7);
}

fn to_t(s: f32) -> f32 {
    return spacing_inv(prm.g_near + s * prm.g_span);
}

fn ray_origin(r: u32) -> vec3<f32> {
    return vec3<f32>(rays[8u * r], rays[8u * r + 1u], rays[8u * r + 2u]);
}

fn ray_dir(r: u32) -> vec3<f32> {
    return vec3<f32>(rays[8u * r + 3u], rays[8u * r + 4u], rays[8u * r + 5u]);
}

fn ray_appearance(r: u32) -> u32 {
    return bitcast<u32>(rays[8u * r + 6u]);
}

// Writes t edges and contracted midpoints for ray r's n_out bins (s_out already written).
fn finish_level(r: u32) {
    let n = prm.n_out;
    let e0 = r * (n + 1u);
    for (var k = 0u; k <= n; k++) {
        t_out[e0 + k] = to_t(s_out[e0 + k]);
    }
    let o = ray_origin(r);
    let d = ray_dir(r);
    for (var i = 0u; i < n; i++) {
        let m = 0.5 * (t_out[e0 + i] + t_out[e0 + i + 1u]);
        let u = contract_unit(vec3<f32>(o.x + d.x * m, o.y + d.y * m, o.z + d.z * m));
        let p = 3u * (r * n + i);
        pos_out[p] = u.x;
        pos_out[p + 1u] = u.y;
        pos_out[p + 2u] = u.z;
    }
}

// ---- sampling (core/src/sampler) ----

// First level: stratified bins in s, one jitter per ray (training) or bin edges (evaluation).
@compute @workgroup_size(64)
fn init_edges(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) li: u32) {
    let r = thread_index(wg, nwg, li);
    if (r >= prm.count) {
        return;
    }
    let n = prm.n_out;
    let nf = f32(n);
    let e0 = r * (n + 1u);
    let j = jitter[r * prm.n_levels];
    for (var k = 0u; k <= n; k++) {
        if (prm.use_jitter == 0u) {
            s_out[e0 + k] = f32(k) / nf;
        } else {
            var lo = 0.0;
            if (k > 0u) {
                lo = (f32(k) - 0.5) / nf;
            }
            var hi = 1.0;
            if (k < n) {
                hi = (f32(k) + 0.5) / nf;
            }
            s_out[e0 + k] = lo + (hi - lo) * j;
        }
    }
    finish_level(r);
}

// Densities and volume-rendering weights of a level (n_in samples) from its MLP logits.
@compute @workgroup_size(64)
fn level_weights(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) li: u32) {
    let r = thread_index(wg, nwg, li);
    if (r >= prm.count) {
        return;
    }
    let n = prm.n_in;
    let e0 = r * (n + 1u);
    var p = 0.0;
    for (var i = 0u; i < n; i++) {
        let k = r * n + i;
        let sigma = density_of(logits[k * prm.out_dim]);
        density[k] = sigma;
        let delta = max(t_in[e0 + i + 1u] - t_in[e0 + i], 0.0);
        var tau = 0.0;
        if (delta > 0.0) {
            tau = sigma * delta;
        }
        weights[k] = exp(-p) * alpha(tau);
        p += tau;
    }
}

fn annealed(w: f32, e: f32) -> f32 {
    let x = max(w, 0.0);
    if (e == 1.0) {
        return x;
    }
    if (e == 0.0) {
        return 1.0;
    }
    if (x == 0.0) {
        return 0.0;
    }
    return pow(x, e);
}

// Resamples n_out bins from the (annealed, padded) weights of the n_in-bin level, as pdf_resample.
@compute @workgroup_size(64)
fn resample(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) li: u32) {
    let r = thread_index(wg, nwg, li);
    if (r >= prm.count) {
        return;
    }
    let n = prm.n_in;
    let e_in = r * (n + 1u);
    let w0 = r * n;
    let cdf0 = r * prm.scratch_stride;
    var sum = 0.0;
    for (var i = 0u; i < n; i++) {
        sum += annealed(w_in[w0 + i], prm.anneal) + prm.padding;
    }
    let extra = max(1e-5 - sum, 0.0);
    let per = extra / f32(n);
    sum += extra;
    scratch[cdf0] = 0.0;
    var acc = 0.0;
    for (var i = 0u; i < n; i++) {
        acc += (annealed(w_in[w0 + i], prm.anneal) + prm.padding + per) / sum;
        scratch[cdf0 + i + 1u] = min(acc, 1.0);
    }
    let nb = prm.n_out + 1u;
    let step = 1.0 / f32(nb);
    var offset = 0.5 * step;
    if (prm.use_jitter != 0u) {
        offset = jitter[r * prm.n_levels + prm.level] * step;
    }
    let e_out = r * nb;
    var idx = 0u;
    var prev = -1.0;
    for (var k = 0u; k < nb; k++) {
        let u = f32(k) * step + offset;
        while (idx <= n && scratch[cdf0 + idx] <= u) {
            idx++;
        }
        let below = min(select(idx - 1u, 0u, idx == 0u), n);
        let above = min(idx, n);
        let c0 = scratch[cdf0 + below];
        let c1 = scratch[cdf0 + above];
        let b0 = s_in[e_in + below];
        let b1 = s_in[e_in + above];
        let dc = c1 - c0;
        var f = 0.0;
        if (dc > 0.0) {
            f = clamp((u - c0) / dc, 0.0, 1.0);
        }
        var o = b0 + f * (b1 - b0);
        if (k > 0u && o < prev) {
            o = prev;
        }
        s_out[e_out + k] = o;
        prev = o;
    }
    finish_level(r);
}

// ---- the radiance field's glue (core/src/train/cpu.rs: shade) ----

// The six +-h positions around each final sample of the first normal_rays rays, after the n_rays * n_in
// sample positions.
@compute @workgroup_size(64)
fn fd_positions(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) li: u32) {
    let i = thread_index(wg, nwg, li);
    if (i >= prm.count) {
        return;
    }
    let h = prm.normal_step;
    let u = vec3<f32>(pos_out[3u * i], pos_out[3u * i + 1u], pos_out[3u * i + 2u]);
    let base = prm.n_rays * prm.n_in + 6u * i;
    for (var k = 0u; k < 3u; k++) {
        var up = u;
        var dn = u;
        up[k] = min(u[k] + h, 1.0);
        dn[k] = max(u[k] - h, 0.0);
        let a = 3u * (base + 2u * k);
        let b = 3u * (base + 2u * k + 1u);
        pos_out[a] = up.x;
        pos_out[a + 1u] = up.y;
        pos_out[a + 2u] = up.z;
        pos_out[b] = dn.x;
        pos_out[b + 1u] = dn.y;
        pos_out[b + 2u] = dn.z;
    }
}

// The mean appearance embedding, for held-out views.
@compute @workgroup_size(64)
fn mean_appearance(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(local_invocation_index) li: u32) {
    let d = thread_index(wg, nwg, li);
    if (d >= prm.count) {
        return;
    }
    let rows = max(prm.images, 1u);
    var m = 0.0;
    for (var a = 0u; a < rows; a++) {
        m += appearance[a * prm.app_dim + d] / f32(rows);
    }
    mean_app[d] = m;
}

// Whether inference colours sample i of a ray (edges from e0 in t_in, logits from k0): its weight is at
// least INFERENCE_MIN_WEIGHT, or it is the ray's last non-empty sample `last` (the background colour).
// Same rule and arithmetic as train::cpu::inference_colour_samples; called over a ray's samples in
// order, carrying the optical depth p.
fn colour_wanted(e0: u32, k0: u32, i: u32, last: u32, p: ptr<function, f32>) -> bool {
    let sigma = density_of(logits[(k0 + i) * prm.out_dim]);
    let delta = max(t_in[e0 + i + 1u] - t_in[e0 + i], 0.0);
    var tau = 0.0;
    if (delta > 0.0) {
        tau = sigma * delta;
    }
    let w = exp(-*p) * alpha(tau);
    *p += tau;
    return w >= INFERENCE_MIN_WEIGHT || i == last;
}

// The last sample of a ray with a non-empty interval (n_in when none is).
fn last_nonempty(e0: u32) -> u32 {
    var last = prm.n_in;
    for (var i = 0u; i < prm.n_in; i++) {
        if (t_in[e0 + i + 1u] - t_in[e0 + i] > 0.0) {
            last = i;
        }
    }
    return last;
}

// Inference, one thread per ray: how many of its samples get a colour.
@compute @workgroup_size(64)
fn colour_count(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) li: u32) {
    let r = thread_index(wg, nwg, li);
    if (r >= prm.count) {
        return;
    }
    let n = prm.n_in;
    let last = last_nonempty(r * (n + 1u));
    var p = 0.0;
    var c = 0u;
    for (var i = 0u; i < n; i++) {
        if (colour_wanted(r * (n + 1u), r * n, i, last, &p)) {
            c++;
        }
    }
    sel_count[r] = c;
}

// Inference, one thread per ray: its selected samples listed from sel_offset[r] (the exclusive prefix of
// the counts), and every sample's row in that list.
@compute @workgroup_size(64)
fn colour_select(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) li: u32) {
    let r = thread_index(wg, nwg, li);
    if (r >= prm.count) {
        return;
    }
    let n = prm.n_in;
    let last = last_nonempty(r * (n + 1u));
    var p = 0.0;
    var o = sel_offset[r];
    for (var i = 0u; i < n; i++) {
        var row = NOT_SELECTED;
        if (colour_wanted(r * (n + 1u), r * n, i, last, &p)) {
            row = o;
            sel_list[o] = r * n + i;
            o++;
        }
        sel_index[r * n + i] = row;
    }
}

// Colour-MLP input row of sample i: SH(direction) + geometry features + appearance (table row, or the
// mean), at `row`.
fn write_colour_input(i: u32, row: u32) {
    let r = i / prm.n_in;
    let d = ray_dir(r);
    for (var k = 0u; k < 16u; k++) {
        colour_in[row + k] = sh4(d, k);
    }
    for (var k = 0u; k < prm.geo; k++) {
        colour_in[row + 16u + k] = logits[i * prm.out_dim + 1u + k];
    }
    let a = ray_appearance(r);
    let in_table = a < prm.images && (a + 1u) * prm.app_dim <= arrayLength(&appearance);
    for (var k = 0u; k < prm.app_dim; k++) {
        var v = mean_app[k];
        if (in_table) {
            v = appearance[a * prm.app_dim + k];
        }
        colour_in[row + 16u + prm.geo + k] = v;
    }
}

// Colour-MLP input rows, one thread per sample (training: every sample).
@compute @workgroup_size(64)
fn colour_input(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) li: u32) {
    let i = thread_index(wg, nwg, li);
    if (i >= prm.count) {
        return;
    }
    write_colour_input(i, i * prm.c_in);
}

// Colour-MLP input rows of inference's selected samples, one thread per selected sample.
@compute @workgroup_size(64)
fn colour_input_selected(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                         @builtin(local_invocation_index) li: u32) {
    let k = thread_index(wg, nwg, li);
    if (k >= prm.count) {
        return;
    }
    write_colour_input(sel_list[k], k * prm.c_in);
}

// Render inputs per final sample: (colour, density), the interval, and the FD normal (zero for samples
// of rays without one) with |grad logit| for the backward.
fn shade_sample(i: u32, rgb: vec3<f32>) {
    let n = prm.n_in;
    let r = i / n;
    let e = r * (n + 1u) + i % n;
    samples[i] = vec4<f32>(rgb, density_of(logits[i * prm.out_dim]));
    intervals[i] = vec2<f32>(t_in[e], t_in[e + 1u]);
    var nv = vec3<f32>(0.0);
    var len = 0.0;
    if (i < prm.normal_rays * n) {
        let base = prm.n_rays * n + 6u * i;
        let h = prm.normal_step;
        var g = vec3<f32>(0.0);
        for (var k = 0u; k < 3u; k++) {
            g[k] = (logits[(base + 2u * k) * prm.out_dim] - logits[(base + 2u * k + 1u) * prm.out_dim])
                / (2.0 * h);
        }
        len = sqrt(g.x * g.x + g.y * g.y + g.z * g.z);
        if (len > 1e-20) {
            nv = -g / len;
        }
        grad_len[i] = len;
    }
    normals[3u * i] = nv.x;
    normals[3u * i + 1u] = nv.y;
    normals[3u * i + 2u] = nv.z;
}

@compute @workgroup_size(64)
fn shade(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) li: u32) {
    let i = thread_index(wg, nwg, li);
    if (i >= prm.count) {
        return;
    }
    shade_sample(i, vec3<f32>(colour_out[3u * i], colour_out[3u * i + 1u], colour_out[3u * i + 2u]));
}

// shade for inference: the colour of a selected sample from its row of the colour MLP, black otherwise.
@compute @workgroup_size(64)
fn shade_selected(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) li: u32) {
    let i = thread_index(wg, nwg, li);
    if (i >= prm.count) {
        return;
    }
    let k = sel_index[i];
    var rgb = vec3<f32>(0.0);
    if (k != NOT_SELECTED) {
        rgb = vec3<f32>(colour_out[3u * k], colour_out[3u * k + 1u], colour_out[3u * k + 2u]);
    }
    shade_sample(i, rgb);
}

// ---- backward ----

// Final level: weights (kept for the interlevel loss), distortion loss + its gradient through the weights
// into the density slot of d_samples (in place), distortion per ray into ray_stats, and dL/drgb copied
// out in the colour MLP's row layout.
@compute @workgroup_size(64)
fn final_backward(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) li: u32) {
    let r = thread_index(wg, nwg, li);
    if (r >= prm.count) {
        return;
    }
    let n = prm.n_in;
    let e0 = r * (n + 1u);
    let d0 = r * n;
    let sa = r * prm.scratch_stride;
    let sb = sa + prm.scratch_stride / 2u;
    // Forward: weights and transmittances T_i = exp(-P_i) (n + 1 of them).
    var p = 0.0;
    var w_tot = 0.0;
    var wm_tot = 0.0;
    for (var i = 0u; i < n; i++) {
        let delta = max(t_in[e0 + i + 1u] - t_in[e0 + i], 0.0);
        var tau = 0.0;
        if (delta > 0.0) {
            tau = samples[d0 + i].w * delta;
        }
        scratch[sb + i] = exp(-p);
        let w = exp(-p) * alpha(tau);
        weights[d0 + i] = w;
        p += tau;
        w_tot += w;
        wm_tot += w * 0.5 * (s_fin[e0 + i] + s_fin[e0 + i + 1u]);
    }
    scratch[sb + n] = exp(-p);
    // Distortion (O(n) with prefix sums); dL/dw into scratch region A.
    var loss = 0.0;
    var w_lo = 0.0;
    var wm_lo = 0.0;
    for (var i = 0u; i < n; i++) {
        let w = weights[d0 + i];
        let m = 0.5 * (s_fin[e0 + i] + s_fin[e0 + i + 1u]);
        let w_hi = w_tot - w_lo - w;
        let wm_hi = wm_tot - wm_lo - w * m;
        let s = m * w_lo - wm_lo + wm_hi - m * w_hi;
        let delta = s_fin[e0 + i + 1u] - s_fin[e0 + i];
        loss += w * s + w * w * delta / 3.0;
        scratch[sa + i] = prm.scale_a * (2.0 * s + 2.0 * w * delta / 3.0);
        w_lo += w;
        wm_lo += w * m;
    }
    ray_stats[r * prm.stat_stride + prm.stat_col] = loss;
    // Weights backward: dL/dtau_k = g_k T_{k+1} - sum_{i>k} g_i w_i.
    var suffix = 0.0;
    for (var kk = 0u; kk < n; kk++) {
        let k = n - 1u - kk;
        let delta = max(t_in[e0 + k + 1u] - t_in[e0 + k], 0.0);
        let g = scratch[sa + k];
        let d_tau = g * scratch[sb + k + 1u] - suffix;
        suffix += g * weights[d0 + k];
        var ds = d_samples[d0 + k];
        ds.w += delta * d_tau;
        d_samples[d0 + k] = ds;
        d_rgb[3u * (d0 + k)] = ds.x;
        d_rgb[3u * (d0 + k) + 1u] = ds.y;
        d_rgb[3u * (d0 + k) + 2u] = ds.z;
    }
}

// dL/d(density-MLP output) rows of the final level: the logit column from dL/dsigma, the geometry columns
// from dL/d(colour input); for samples with a normal, the six FD rows' logit columns (other columns 0).
@compute @workgroup_size(64)
fn assemble_d_out(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) li: u32) {
    let i = thread_index(wg, nwg, li);
    if (i >= prm.count) {
        return;
    }
    let od = prm.out_dim;
    d_out[i * od] = d_samples[i].w * d_density_of(logits[i * od]);
    for (var k = 0u; k < prm.geo; k++) {
        d_out[i * od + 1u + k] = d_cin[i * prm.c_in + 16u + k];
    }
    if (i < prm.normal_rays * prm.n_in) {
        let nv = vec3<f32>(normals[3u * i], normals[3u * i + 1u], normals[3u * i + 2u]);
        let dn = vec3<f32>(d_normals[3u * i], d_normals[3u * i + 1u], d_normals[3u * i + 2u]);
        let len = grad_len[i];
        var dg = vec3<f32>(0.0);
        if (len > 1e-20) {
            let nd = dot(nv, dn);
            dg = -(dn - nv * nd) / len;
        }
        let h2 = 2.0 * prm.normal_step;
        let base = prm.n_rays * prm.n_in + 6u * i;
        for (var k = 0u; k < 3u; k++) {
            let a = (base + 2u * k) * od;
            let b = (base + 2u * k + 1u) * od;
            d_out[a] = dg[k] / h2;
            d_out[b] = -dg[k] / h2;
            for (var c = 1u; c < od; c++) {
                d_out[a + c] = 0.0;
                d_out[b + c] = 0.0;
            }
        }
    }
}

fn search_right(e0: u32, m: u32, x: f32) -> u32 {
    // First index in s_in[e0 .. e0 + m] with value > x (partition point), m + 1 edges.
    var lo = 0u;
    var hi = m + 1u;
    while (lo < hi) {
        let mid = (lo + hi) / 2u;
        if (s_in[e0 + mid] <= x) {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    return lo;
}

// One proposal level (n_in bins; s_in/t_in its edges, w_in its weights) against the final level
// (n_out bins; s_fin, w_fin): interlevel loss, SiLVR's depth and sky terms on the proposal weights; their
// dL/dw into scratch region A, the three per-ray terms into ray_stats at stat_col..stat_col + 2.
// scale_a: interlevel weight / (R n_out), scale_b: depth weight / R, scale_c: sky weight / R.
@compute @workgroup_size(64)
fn proposal_dw(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
               @builtin(local_invocation_index) li: u32) {
    let r = thread_index(wg, nwg, li);
    if (r >= prm.count) {
        return;
    }
    let m = prm.n_in;
    let n = prm.n_out;
    let ep = r * (m + 1u);
    let ef = r * (n + 1u);
    let sa = r * prm.scratch_stride;
    let sb = sa + prm.scratch_stride / 2u;
    scratch[sb] = 0.0;
    for (var j = 0u; j < m; j++) {
        scratch[sb + j + 1u] = scratch[sb + j] + w_in[r * m + j];
        scratch[sa + j] = 0.0;
    }
    var il = 0.0;
    for (var i = 0u; i < n; i++) {
        let lo = u32(clamp(i32(search_right(ep, m, s_fin[ef + i])) - 1, 0, i32(m)));
        let hi = min(search_right(ep, m, s_fin[ef + i + 1u]), m);
        let lo2 = min(lo, hi);
        let outer = scratch[sb + hi] - scratch[sb + lo2];
        let w = w_fin[r * n + i];
        let rr = w - outer;
        if (rr > 0.0) {
            il += rr * rr / (w + INTERLEVEL_EPS);
            let dv = -2.0 * rr / (w + INTERLEVEL_EPS) * prm.scale_a;
            for (var j = lo2; j < hi; j++) {
                scratch[sa + j] += dv;
            }
        }
    }
    let tg = targets[r];
    let sky = tg.sky != 0u;
    let lidar = !sky && tg.depth > 0.0;
    var ld = 0.0;
    var ls = 0.0;
    for (var j = 0u; j < m; j++) {
        let w = w_in[r * m + j];
        let a = t_in[ep + j];
        let b = t_in[ep + j + 1u];
        if (lidar) {
            let e = 0.5 * (a + b) - tg.depth;
            let g = exp(-e * e * prm.inv_two_var) * max(b - a, 0.0);
            ld -= log(w + LOG_EPS) * g;
            scratch[sa + j] -= prm.scale_b * g / (w + LOG_EPS);
        }
        if (sky) {
            ls += w * w;
            scratch[sa + j] += prm.scale_c * 2.0 * w;
        }
    }
    let so = r * prm.stat_stride + prm.stat_col;
    ray_stats[so] = il;
    ray_stats[so + 1u] = ld;
    ray_stats[so + 2u] = ls;
}

// dL/dlogit of a proposal level (n_in bins) from dL/dw in scratch region A: weights backward, then
// trunc_exp's derivative. The MLP has one output column.
@compute @workgroup_size(64)
fn proposal_d_out(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) li: u32) {
    let r = thread_index(wg, nwg, li);
    if (r >= prm.count) {
        return;
    }
    let n = prm.n_in;
    let e0 = r * (n + 1u);
    let d0 = r * n;
    let sa = r * prm.scratch_stride;
    let sb = sa + prm.scratch_stride / 2u;
    var p = 0.0;
    for (var i = 0u; i < n; i++) {
        let delta = max(t_in[e0 + i + 1u] - t_in[e0 + i], 0.0);
        var tau = 0.0;
        if (delta > 0.0) {
            tau = dens_in[d0 + i] * delta;
        }
        scratch[sb + i] = exp(-p);
        p += tau;
    }
    scratch[sb + n] = exp(-p);
    var suffix = 0.0;
    for (var kk = 0u; kk < n; kk++) {
        let k = n - 1u - kk;
        let delta = max(t_in[e0 + k + 1u] - t_in[e0 + k], 0.0);
        let g = scratch[sa + k];
        let d_tau = g * scratch[sb + k + 1u] - suffix;
        suffix += g * w_in[d0 + k];
        d_out[(d0 + k) * prm.out_dim] = delta * d_tau * d_density_of(logits[(d0 + k) * prm.out_dim]);
    }
}

fn atomic_add_app(i: u32, v: f32) {
    var old = atomicLoad(&g_app[i]);
    loop {
        let r = atomicCompareExchangeWeak(&g_app[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (r.exchanged) {
            break;
        }
        old = r.old_value;
    }
}

// dL/d(appearance table): per (ray, dimension), the ray's samples summed, then one atomic add.
@compute @workgroup_size(64)
fn appearance_grad(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(local_invocation_index) li: u32) {
    let i = thread_index(wg, nwg, li);
    if (i >= prm.count) {
        return;
    }
    let r = i / prm.app_dim;
    let d = i % prm.app_dim;
    let a = ray_appearance(r);
    if (a >= prm.images) {
        return;
    }
    var sum = 0.0;
    for (var k = 0u; k < prm.n_in; k++) {
        sum += d_cin[(r * prm.n_in + k) * prm.c_in + 16u + prm.geo + d];
    }
    atomic_add_app(a * prm.app_dim + d, sum);
}

@compute @workgroup_size(64)
fn clear_app(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
             @builtin(local_invocation_index) li: u32) {
    let i = thread_index(wg, nwg, li);
    if (i >= prm.count) {
        return;
    }
    atomicStore(&g_app[i], 0u);
}

// ---- Adam (core/src/train/adam.rs: adam_element) ----

@compute @workgroup_size(64)
fn adam(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) li: u32) {
    let i = thread_index(wg, nwg, li);
    if (i >= prm.count) {
        return;
    }
    var g = grad[i];
    // Non-finite gradients (inf, NaN) count as zero, as the CPU update. An exponent test on the bits:
    // compilers may fold float comparisons with NaN, and Tint refuses f32::MAX written as a decimal.
    if ((bitcast<u32>(g) & 0x7f800000u) == 0x7f800000u) {
        g = 0.0;
    }
    let m = prm.beta1 * adam_m[i] + (1.0 - prm.beta1) * g;
    let v = prm.beta2 * adam_v[i] + (1.0 - prm.beta2) * g * g;
    adam_m[i] = m;
    adam_v[i] = v;
    param[i] = param[i] - prm.adam_a * m / (sqrt(v) * prm.adam_c + prm.eps);
}
