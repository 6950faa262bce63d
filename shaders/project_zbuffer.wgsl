// Lidar points -> one camera's pixels, keeping the nearest point per pixel (a z-buffer on range).
//
// Three passes over the same bindings (CPU reference: core/src/lidar/project.rs):
//   clear    one thread per pixel: key = winner = NONE.
//   project  one thread per point: transform into the camera, apply the lens model, write the point's
//            (u, v, range) and pixel, then atomicMin the pixel's range key. A positive f32's bits order like
//            the float, so atomicMin on the u32 bit pattern picks the nearest range without float atomics.
//   resolve  one thread per point: a point whose key equals its pixel's minimum competes with atomicMin on
//            its index, so exact ties go to the lowest index and the result never depends on thread order.
//
// Conventions: OpenCV camera frame and pixel centres (pixel (0,0) covers u in [-0.5, 0.5)).
// Dispatches may be folded into 2-D: index = (wg.y * nwg.x + wg.x) * 64 + local index.

const WG: u32 = 64u;
const NONE: u32 = 0xffffffffu;
const MODEL_PINHOLE: u32 = 0u;
const MODEL_RADTAN: u32 = 1u;
const MODEL_FISHEYE: u32 = 2u;

struct Params {
    // fx, fy, cx, cy
    intrinsics: vec4<f32>,
    // pinhole: unused; radtan: k1, k2, p1, p2; fisheye: k1, k2, k3, k4
    dist: vec4<f32>,
    // x: radtan k3; y: largest valid angle from the optical axis (rad); z: nearest valid range (m); w: unused
    extra: vec4<f32>,
    // rows of the 3x4 transform camera <- points
    r0: vec4<f32>,
    r1: vec4<f32>,
    r2: vec4<f32>,
    // width, height, model, point count
    dims: vec4<u32>,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> pixel_key: array<atomic<u32>>;
@group(0) @binding(3) var<storage, read_write> pixel_winner: array<atomic<u32>>;
@group(0) @binding(4) var<storage, read_write> point_pixel: array<u32>;
@group(0) @binding(5) var<storage, read_write> point_proj: array<vec4<f32>>;

fn linear_index(wg: vec3<u32>, nwg: vec3<u32>, li: u32) -> u32 {
    return (wg.y * nwg.x + wg.x) * WG + li;
}

// Pixel coordinates of a camera-frame point; w = 1 when the lens model accepts it, 0 otherwise.
fn lens_project(p: vec3<f32>) -> vec3<f32> {
    let fx = params.intrinsics.x;
    let fy = params.intrinsics.y;
    let cx = params.intrinsics.z;
    let cy = params.intrinsics.w;
    let model = params.dims.z;
    let r = sqrt(p.x * p.x + p.y * p.y);
    let theta = atan2(r, p.z);
    if (theta > params.extra.y) {
        return vec3<f32>(0.0, 0.0, 0.0);
    }
    var xd: f32;
    var yd: f32;
    if (model == MODEL_FISHEYE) {
        let k = params.dist;
        let t2 = theta * theta;
        let thetad = theta * (1.0 + t2 * (k.x + t2 * (k.y + t2 * (k.z + t2 * k.w))));
        // theta_d / r tends to 1 / z on the axis.
        var s = 1.0 / p.z;
        if (r > 1e-12) {
            s = thetad / r;
        }
        xd = p.x * s;
        yd = p.y * s;
    } else {
        if (p.z <= 0.0) {
            return vec3<f32>(0.0, 0.0, 0.0);
        }
        let xn = p.x / p.z;
        let yn = p.y / p.z;
        xd = xn;
        yd = yn;
        if (model == MODEL_RADTAN) {
            let k1 = params.dist.x;
            let k2 = params.dist.y;
            let p1 = params.dist.z;
            let p2 = params.dist.w;
            let k3 = params.extra.x;
            let r2 = xn * xn + yn * yn;
            let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn);
            yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn;
        }
    }
    return vec3<f32>(fx * xd + cx, fy * yd + cy, 1.0);
}

@compute @workgroup_size(64)
fn clear(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) li: u32) {
    let i = linear_index(wg, nwg, li);
    if (i >= params.dims.x * params.dims.y) {
        return;
    }
    atomicStore(&pixel_key[i], NONE);
    atomicStore(&pixel_winner[i], NONE);
}

@compute @workgroup_size(64)
fn project(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) li: u32) {
    let i = linear_index(wg, nwg, li);
    if (i >= params.dims.w) {
        return;
    }
    // w = 0 marks a point the host found non-finite (NaN/Inf cannot be tested reliably in WGSL).
    let q = points[i].xyz;
    let usable = points[i].w != 0.0;
    let p = vec3<f32>(
        dot(params.r0.xyz, q) + params.r0.w,
        dot(params.r1.xyz, q) + params.r1.w,
        dot(params.r2.xyz, q) + params.r2.w,
    );
    let range = length(p);
    let uvw = lens_project(p);
    let w = f32(params.dims.x);
    let h = f32(params.dims.y);
    let ok = usable && uvw.z > 0.5 && range >= params.extra.z && range > 0.0
        && uvw.x >= -0.5 && uvw.x < w - 0.5 && uvw.y >= -0.5 && uvw.y < h - 0.5;
    if (!ok) {
        point_pixel[i] = NONE;
        point_proj[i] = vec4<f32>(uvw.x, uvw.y, range, 0.0);
        return;
    }
    let px = min(u32(floor(uvw.x + 0.5)), params.dims.x - 1u);
    let py = min(u32(floor(uvw.y + 0.5)), params.dims.y - 1u);
    let pix = py * params.dims.x + px;
    point_pixel[i] = pix;
    point_proj[i] = vec4<f32>(uvw.x, uvw.y, range, 1.0);
    atomicMin(&pixel_key[pix], bitcast<u32>(range));
}

@compute @workgroup_size(64)
fn resolve(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) li: u32) {
    let i = linear_index(wg, nwg, li);
    if (i >= params.dims.w) {
        return;
    }
    let pix = point_pixel[i];
    if (pix == NONE) {
        return;
    }
    let key = bitcast<u32>(point_proj[i].z);
    if (atomicLoad(&pixel_key[pix]) == key) {
        atomicMin(&pixel_winner[pix], i);
    }
}
