// Per-ray volume rendering (nerfstudio / nerfacto) and SiLVR's ray losses, forward and backward.
// CPU reference, layouts and the loss definitions: core/src/render/mod.rs.
//
// R rays of S samples each, ray-major (sample i of ray r is element r * S + i). Per sample: colour and
// density (already activated), the interval [t_start, t_end] along the ray, and optionally a normal.
// Padding samples have t_end = t_start: their weight is exactly 0 and they get zero gradients.
//
//   tau_i = sigma_i * delta_i,  delta_i = max(t_end - t_start, 0)
//   P_i   = sum_{j<i} tau_j     (exclusive prefix, accumulated in order in f32)
//   T_i   = exp(-P_i),  alpha_i = 1 - exp(-tau_i) (a short series for small tau: see alpha()),  w_i = T_i alpha_i
//
// Entry points (one thread per ray, 64 per workgroup, dispatch possibly folded into 2-D:
// ray = (wg.y * nwg.x + wg.x) * 64 + local index):
//   render         weights and the rendered colour, accumulation, normal and depth.
//   loss_backward  per-ray loss terms and dL/d(colour, density, normal) of every sample. Recomputes the
//                  forward (same arithmetic, same weights) instead of reading them: it needs inputs only.

const WG: u32 = 64u;
// DS-NeRF's epsilon inside the log.
const LOG_EPS: f32 = 1e-7;
// |sum w n| below this renders no normal (and gives no normal gradient).
const NORMAL_EPS: f32 = 1e-20;

struct Params {
    n_rays: u32,
    n_samples: u32,
    // 1 when per-sample normals are bound.
    has_normals: u32,
    // 0: black, 1: constant colour (bg), 2: colour of the last sample with delta > 0 (nerfacto's last_sample).
    background: u32,
    bg: vec4<f32>,
    // Loss weights with the batch means folded in: lambda_rgb / (3R), lambda_depth / R, lambda_normal / R,
    // lambda_sky / R.
    scale_rgb: f32,
    scale_depth: f32,
    scale_normal: f32,
    scale_sky: f32,
    // 1 / (2 sigma^2) of the DS-NeRF Gaussian, sigma a standard deviation in ray-distance units.
    inv_two_var: f32,
    _pad0: f32,
    _pad1: f32,
    _pad2: f32,
}

struct Sample {
    rgb: vec3<f32>,
    density: f32,
}

struct Target {
    rgb: vec3<f32>,
    // Lidar range along the ray; <= 0: no lidar return.
    depth: f32,
    // Lidar normal, any length; zero: none.
    normal: vec3<f32>,
    // Non-zero: sky ray.
    sky: u32,
}

struct RayOut {
    rgb: vec3<f32>,
    acc: f32,
    normal: vec3<f32>,
    depth: f32,
}

@group(0) @binding(0) var<uniform> prm: Params;
@group(0) @binding(1) var<storage, read> samples: array<Sample>;
@group(0) @binding(2) var<storage, read> intervals: array<vec2<f32>>;
// 3 f32 per sample, x y z interleaved.
@group(0) @binding(3) var<storage, read> normals: array<f32>;
@group(0) @binding(4) var<storage, read> targets: array<Target>;
@group(0) @binding(5) var<storage, read_write> weights: array<f32>;
@group(0) @binding(6) var<storage, read_write> rays_out: array<RayOut>;
// Per ray: (colour MSE, DS-NeRF depth term, normal term, sky term), unweighted.
@group(0) @binding(7) var<storage, read_write> losses: array<vec4<f32>>;
// dL/d(rgb, density) per sample; its density slot holds P_i between the two loops of loss_backward.
@group(0) @binding(8) var<storage, read_write> d_samples: array<Sample>;
@group(0) @binding(9) var<storage, read_write> d_normals: array<f32>;

fn linear_index(wg: vec3<u32>, nwg: vec3<u32>, li: u32) -> u32 {
    return (wg.y * nwg.x + wg.x) * WG + li;
}

fn delta_of(iv: vec2<f32>) -> f32 {
    return max(iv.y - iv.x, 0.0);
}

// sigma * delta, 0 for an empty interval even when sigma is infinite.
fn tau_of(density: f32, delta: f32) -> f32 {
    return select(0.0, density * delta, delta > 0.0);
}

// 1 - exp(-tau). In f32 the subtraction loses most digits for thin samples (tau = 1e-4 keeps ~3), and
// DS-NeRF's log(w) would amplify that, so small tau use the series (truncation < 1e-7 relative).
fn alpha(tau: f32) -> f32 {
    if (tau < 0.125) {
        return tau * (1.0 - tau * (0.5 - tau * (1.0 / 6.0 - tau * (1.0 / 24.0 - tau * (1.0 / 120.0)))));
    }
    return 1.0 - exp(-tau);
}

fn load_normal(k: u32) -> vec3<f32> {
    return vec3<f32>(normals[3u * k], normals[3u * k + 1u], normals[3u * k + 2u]);
}

fn midpoint(iv: vec2<f32>) -> f32 {
    return 0.5 * (iv.x + iv.y);
}

// Background colour for a ray whose last non-empty sample is `last` (S when there is none).
fn background_colour(base: u32, last: u32) -> vec3<f32> {
    if (prm.background == 1u) {
        return prm.bg.xyz;
    }
    if (prm.background == 2u && last < prm.n_samples) {
        return samples[base + last].rgb;
    }
    return vec3<f32>(0.0);
}

@compute @workgroup_size(64)
fn render(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
          @builtin(local_invocation_index) li: u32) {
    let r = linear_index(wg, nwg, li);
    if (r >= prm.n_rays) {
        return;
    }
    let s = prm.n_samples;
    let base = r * s;
    var p = 0.0;
    var rgb = vec3<f32>(0.0);
    var acc = 0.0;
    var depth = 0.0;
    var nsum = vec3<f32>(0.0);
    var last = s;
    for (var i = 0u; i < s; i++) {
        let k = base + i;
        let smp = samples[k];
        let iv = intervals[k];
        let delta = delta_of(iv);
        let tau = tau_of(smp.density, delta);
        let w = exp(-p) * alpha(tau);
        p += tau;
        weights[k] = w;
        rgb += w * smp.rgb;
        acc += w;
        depth += w * midpoint(iv);
        if (prm.has_normals != 0u) {
            nsum += w * load_normal(k);
        }
        if (delta > 0.0) {
            last = i;
        }
    }
    // The background's share 1 - acc, as the final transmittance: equal in exact arithmetic, and free of
    // the cancellation of 1 - sum w on nearly opaque rays.
    rgb += background_colour(base, last) * exp(-p);
    let len = length(nsum);
    let n = select(vec3<f32>(0.0), nsum / len, len > NORMAL_EPS);
    rays_out[r] = RayOut(rgb, acc, n, depth);
}

// Backward, per ray. With g_i = dL/dw_i (through the colour, the normal, and the depth and sky terms),
// w_i = T_i (1 - exp(-tau_i)), T_i = exp(-sum_{j<i} tau_j):
//   dw_i/dtau_k = -w_i (k < i),  T_{i+1} (k = i),  0 (k > i)
// so dL/dtau_k = g_k T_{k+1} - sum_{i>k} g_i w_i, a reverse scan, and dL/dsigma_k = delta_k dL/dtau_k.
// Colour: C = sum w_i c_i + b T_S (T_S = exp(-sum tau) = 1 - acc), so g_i += dL/dC . c_i,
// dL/dc_i = w_i dL/dC, dL/dtau_k gets -T_S dL/dC . b directly (dT_S/dtau_k = -T_S), and with last_sample
// (b = c_last) dL/dc_last also gets T_S dL/dC. Normal: N = v / |v|, v = sum w_i n_i,
// dL/dv = (I - N N^T) dL/dN / |v|, g_i += n_i . dL/dv, dL/dn_i = w_i dL/dv.
@compute @workgroup_size(64)
fn loss_backward(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) li: u32) {
    let r = linear_index(wg, nwg, li);
    if (r >= prm.n_rays) {
        return;
    }
    let s = prm.n_samples;
    let base = r * s;
    let tgt = targets[r];
    let sky = tgt.sky != 0u;
    let lidar = !sky && tgt.depth > 0.0;
    let tn_len = length(tgt.normal);
    let use_normal = prm.has_normals != 0u && tn_len > 0.0;

    // Forward, keeping P_i in the gradient buffer for the reverse loop.
    var p = 0.0;
    var rgb = vec3<f32>(0.0);
    var nsum = vec3<f32>(0.0);
    var last = s;
    var l_depth = 0.0;
    var l_sky = 0.0;
    for (var i = 0u; i < s; i++) {
        let k = base + i;
        let smp = samples[k];
        let iv = intervals[k];
        let delta = delta_of(iv);
        let tau = tau_of(smp.density, delta);
        let w = exp(-p) * alpha(tau);
        d_samples[k].density = p;
        p += tau;
        rgb += w * smp.rgb;
        if (use_normal) {
            nsum += w * load_normal(k);
        }
        if (delta > 0.0) {
            last = i;
        }
        if (lidar) {
            let e = midpoint(iv) - tgt.depth;
            l_depth -= log(w + LOG_EPS) * exp(-e * e * prm.inv_two_var) * delta;
        }
        if (sky) {
            l_sky += w * w;
        }
    }
    let bg = background_colour(base, last);
    let t_final = exp(-p);
    rgb += bg * t_final;
    let err = rgb - tgt.rgb;
    let l_rgb = dot(err, err) / 3.0;
    let d_rgb = 2.0 * prm.scale_rgb * err;

    var l_normal = 0.0;
    var d_v = vec3<f32>(0.0);
    if (use_normal) {
        let tn = tgt.normal / tn_len;
        let len = length(nsum);
        let n = select(vec3<f32>(0.0), nsum / len, len > NORMAL_EPS);
        let dn = n - tn;
        l_normal = abs(dn.x) + abs(dn.y) + abs(dn.z) + 1.0 - dot(n, tn);
        if (len > NORMAL_EPS) {
            let d_n = prm.scale_normal * (sign(dn) - tn);
            d_v = (d_n - n * dot(n, d_n)) / len;
        }
    }
    losses[r] = vec4<f32>(l_rgb, l_depth, l_normal, l_sky);
    let d_tau_bg = t_final * dot(d_rgb, bg);

    // Reverse scan: `suffix` = sum_{i>k} g_i w_i, `t_next` = T_{k+1} (the previous iteration's T_i).
    var suffix = 0.0;
    var t_next = t_final;
    for (var j = 0u; j < s; j++) {
        let i = s - 1u - j;
        let k = base + i;
        let smp = samples[k];
        let iv = intervals[k];
        let delta = delta_of(iv);
        let tau = tau_of(smp.density, delta);
        let t_i = exp(-d_samples[k].density);
        let w = t_i * alpha(tau);
        var g = dot(d_rgb, smp.rgb);
        var n_i = vec3<f32>(0.0);
        if (use_normal) {
            n_i = load_normal(k);
            g += dot(d_v, n_i);
        }
        if (lidar) {
            let e = midpoint(iv) - tgt.depth;
            g -= prm.scale_depth * exp(-e * e * prm.inv_two_var) * delta / (w + LOG_EPS);
        }
        if (sky) {
            g += prm.scale_sky * 2.0 * w;
        }
        let d_sigma = delta * (g * t_next - suffix - d_tau_bg);
        suffix += g * w;
        t_next = t_i;
        var d_c = d_rgb * w;
        if (prm.background == 2u && i == last) {
            d_c += d_rgb * t_final;
        }
        d_samples[k] = Sample(d_c, d_sigma);
        if (prm.has_normals != 0u) {
            let d_n = d_v * w;
            d_normals[3u * k] = d_n.x;
            d_normals[3u * k + 1u] = d_n.y;
            d_normals[3u * k + 2u] = d_n.z;
        }
    }
}
