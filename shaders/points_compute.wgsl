// The studio's compute rasteriser (`viewer::compute`): the point draw where triangles are slow. Each point
// is one invocation that projects itself and splats a footprint of `size` × `size` pixels (a disc when
// round) into two 32-bit words per pixel in storage buffers, after Schütz et al. (2021, 2022). WebGPU has
// no 64-bit atomics, so depth and colour cannot be packed into one atomic word at full precision; instead:
//
//   1. `depth_pass`: atomicMax of the point's depth key (the bits of its clip depth z in [0, 1), inverted,
//      so nearer is larger and 0 means "nothing here": buffers are cleared to zero) — full f32 precision;
//   2. `colour_pass`: every point whose key equals the pixel's winning key writes its packed RGBA8 colour
//      by atomicMax (equal depths: the larger colour wins, so the picture does not depend on thread order);
//   3. `resolve_vs` / `resolve_fs`: a full-screen triangle copies the words to the canvas (background where
//      the depth word is 0): canvases cannot be storage textures everywhere, a render target they always are.
//
// The footprint, the depth range kept (0 <= z < 1, as the quad path's clip volume and `Less` test against a
// cleared 1.0) and the colour and filter rules are the quad path's (`points.wgsl`, `points_common.wgsl`);
// `viewer::reference::rasterise` is the CPU reference of exactly this file.

// The chunk's points: positions as xyz f32 triplets (12-byte stride, as the vertex buffers hold them).
@group(0) @binding(1) var<storage, read> positions: array<f32>;
@group(0) @binding(2) var<storage, read> colours: array<u32>;
@group(0) @binding(3) var<storage, read> values: array<f32>;
@group(0) @binding(4) var<storage, read> filter_values: array<f32>;
// One word per pixel of the target (row-major, y down).
@group(0) @binding(5) var<storage, read_write> depth_words: array<atomic<u32>>;
@group(0) @binding(6) var<storage, read_write> colour_words: array<atomic<u32>>;

// Invocations per workgroup; dispatches are 2-D when a chunk needs more than 65,535 workgroups.
const GROUP: u32 = 256u;

struct Footprint {
    // The point's depth key (0: nothing to draw).
    key: u32,
    // Its centre in pixels (x right, y down, pixel centres at +0.5) and half its size.
    centre: vec2<f32>,
    half: f32,
    // The first and last pixel column/row its footprint covers (inclusive, within the target).
    lo: vec2<i32>,
    hi: vec2<i32>,
}

fn footprint(i: u32) -> Footprint {
    var f: Footprint;
    f.key = 0u;
    if (filtered_out(filter_values[i])) {
        return f;
    }
    let p = vec3<f32>(positions[3u * i], positions[3u * i + 1u], positions[3u * i + 2u]);
    let clip = view.view_proj * vec4<f32>(p + view.offset.xyz, 1.0);
    if (!(clip.w > 0.0)) {
        return f;
    }
    let ndc = clip.xyz / clip.w;
    if (!(ndc.z >= 0.0 && ndc.z < 1.0)) {
        return f;
    }
    let size = view.viewport.xy;
    f.centre = vec2<f32>((ndc.x * 0.5 + 0.5) * size.x, (0.5 - ndc.y * 0.5) * size.y);
    f.half = 0.5 * view.offset.w;
    // Pixels whose centre c has centre - half <= c < centre + half (the rasteriser's top-left rule on an
    // axis-aligned square), clamped in float first so a point far off screen cannot overflow i32.
    let lo = clamp(ceil(f.centre - f.half - 0.5), vec2<f32>(0.0), size);
    let hi = clamp(ceil(f.centre + f.half - 0.5) - 1.0, vec2<f32>(-1.0), size - 1.0);
    f.lo = vec2<i32>(lo);
    f.hi = vec2<i32>(hi);
    if (f.lo.x > f.hi.x || f.lo.y > f.hi.y) {
        return f;
    }
    // The bits of a non-negative float order as the float does; inverted, nearer is larger and never 0.
    f.key = ~(bitcast<u32>(ndc.z) & 0x7fffffffu);
    return f;
}

// Whether pixel (x, y) is inside a round point's disc (the quad path's `dot(corner, corner) <= 1`).
fn covers(f: Footprint, x: i32, y: i32) -> bool {
    if (view.mode.z == 0u) {
        return true;
    }
    let corner = (vec2<f32>(f32(x), f32(y)) + 0.5 - f.centre) / f.half;
    return dot(corner, corner) <= 1.0;
}

fn point_index(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * GROUP;
}

@compute @workgroup_size(256)
fn depth_pass(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = point_index(gid, groups);
    if (i >= arrayLength(&colours)) {
        return;
    }
    let f = footprint(i);
    if (f.key == 0u) {
        return;
    }
    let width = i32(view.viewport.x);
    for (var y = f.lo.y; y <= f.hi.y; y++) {
        for (var x = f.lo.x; x <= f.hi.x; x++) {
            if (covers(f, x, y)) {
                atomicMax(&depth_words[y * width + x], f.key);
            }
        }
    }
}

@compute @workgroup_size(256)
fn colour_pass(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = point_index(gid, groups);
    if (i >= arrayLength(&colours)) {
        return;
    }
    let f = footprint(i);
    if (f.key == 0u) {
        return;
    }
    let colour = pack4x8unorm(vec4<f32>(point_colour(unpack4x8unorm(colours[i]), values[i]), 1.0));
    let width = i32(view.viewport.x);
    for (var y = f.lo.y; y <= f.hi.y; y++) {
        for (var x = f.lo.x; x <= f.hi.x; x++) {
            let at = y * width + x;
            if (covers(f, x, y) && atomicLoad(&depth_words[at]) == f.key) {
                atomicMax(&colour_words[at], colour);
            }
        }
    }
}

// The resolve pass's own bindings (a render pipeline of its own layout; numbered apart from the passes
// above so the module never has two variables at one binding).
struct Resolve {
    background: vec4<f32>,
    // x: the target's width in pixels.
    size: vec4<u32>,
}

@group(0) @binding(7) var<uniform> resolve: Resolve;
@group(0) @binding(8) var<storage, read> resolved_depth: array<u32>;
@group(0) @binding(9) var<storage, read> resolved_colour: array<u32>;

@vertex
fn resolve_vs(@builtin(vertex_index) vi: u32) -> @builtin(position) vec4<f32> {
    // One triangle covering the target.
    let xy = vec2<f32>(f32((vi << 1u) & 2u), f32(vi & 2u));
    return vec4<f32>(xy * 2.0 - 1.0, 0.0, 1.0);
}

@fragment
fn resolve_fs(@builtin(position) at: vec4<f32>) -> @location(0) vec4<f32> {
    let i = u32(at.y) * resolve.size.x + u32(at.x);
    if (resolved_depth[i] == 0u) {
        return resolve.background;
    }
    return vec4<f32>(unpack4x8unorm(resolved_colour[i]).rgb, 1.0);
}
