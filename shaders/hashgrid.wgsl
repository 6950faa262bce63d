// Multi-resolution hash-grid encoding (Instant-NGP; tiny-cuda-nn's HashGrid with linear interpolation),
// forward and backward. CPU reference and the exact layout rules: core/src/field/hashgrid.rs.
//
// Parameters: one f32 table, level after level; level l owns entries [offset, offset + size), each entry
// F features, so feature f of entry e of level l is params[(offset + e) * F + f].
// Positions: 3 f32 per point (x, y, z interleaved), expected in [0, 1]^3 (clamped there).
// Features: n rows of L * F f32, row-major: features[p * L * F + l * F + f].
//
// Per level, as tcnn: pos = x * scale + 0.5, cell = floor(pos), t = pos - cell; the 8 corners cell + b
// (b in {0,1}^3, bit d of the corner number is axis d) are indexed densely, (x + y * res + z * res^2) mod size,
// when res^3 <= size, else by the spatial hash (x * 1 ^ y * 2654435761 ^ z * 805459861) mod size.
//
// Entry points (all 64 threads per workgroup, dispatch possibly folded into 2-D:
// index = (wg.y * nwg.x + wg.x) * 64 + local index):
//   encode          one thread per (level, point), level-major (index = l * n + p) so a workgroup shares
//                   one level's metadata and hashing branch.
//   clear_grad      one thread per 4 parameter words: d_params = 0.
//   backward_params one thread per (level, run of `run` consecutive points): d_params[corner] += w_corner *
//                   dL/dfeature, as float adds built from a compare-exchange loop on atomic<u32> (WebGPU has
//                   no atomic<f32>). Consecutive points are consecutive samples of one ray (or the FD
//                   points of one sample), which at the coarse levels fall in the same cell: the thread sums
//                   their contributions and adds once per cell it leaves, so the dense coarse levels, which
//                   every sample of the batch hits, see a fraction of the atomics and of their contention.
//                   NF (features per level) comes from the prelude the engine compiles in front of this
//                   file, so the per-corner sums live in registers.
//   backward_pos    one thread per point, all levels: dL/dx = sum_l scale_l * sum_c dw_c/dt * <param_c, g_l>.
//                   Zero along an axis where the input was clamped (outside [0, 1]).

const WG: u32 = 64u;
const MAX_LEVELS: u32 = 32u;
const PRIME_Y: u32 = 2654435761u;
const PRIME_Z: u32 = 805459861u;

struct Level {
    scale: f32,
    res: u32,
    // First entry of the level in the table, and its entry count.
    offset: u32,
    size: u32,
    // 1: dense indexing, 0: hashed (size is then a power of two).
    dense: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

struct Grid {
    // Points in this batch.
    n: u32,
    levels: u32,
    features: u32,
    // Parameter words (entries * features).
    words: u32,
    // backward_params: consecutive points one thread handles (its merge window).
    run: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
    level: array<Level, MAX_LEVELS>,
}

@group(0) @binding(0) var<uniform> grid: Grid;
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read> positions: array<f32>;
@group(0) @binding(3) var<storage, read_write> features: array<f32>;
@group(0) @binding(4) var<storage, read> d_features: array<f32>;
@group(0) @binding(5) var<storage, read_write> d_params: array<atomic<u32>>;
@group(0) @binding(6) var<storage, read_write> d_positions: array<f32>;
// d_params again, for the clear only.
@group(0) @binding(7) var<storage, read_write> grad_words: array<vec4<u32>>;

fn linear_index(wg: vec3<u32>, nwg: vec3<u32>, li: u32) -> u32 {
    return (wg.y * nwg.x + wg.x) * WG + li;
}

fn raw_position(p: u32) -> vec3<f32> {
    return vec3<f32>(positions[3u * p], positions[3u * p + 1u], positions[3u * p + 2u]);
}

// Table entry (within its level) of grid vertex g.
fn vertex_index(lv: Level, g: vec3<u32>) -> u32 {
    if (lv.dense != 0u) {
        // The +0.5 offset lets a coordinate reach res; the modulo wraps it like tcnn does.
        return (g.x + g.y * lv.res + g.z * lv.res * lv.res) % lv.size;
    }
    return (g.x ^ (g.y * PRIME_Y) ^ (g.z * PRIME_Z)) & (lv.size - 1u);
}

// Scaled position split into the cell's lower vertex and the fraction inside the cell.
struct Cell {
    base: vec3<u32>,
    t: vec3<f32>,
}

fn locate(lv: Level, x: vec3<f32>) -> Cell {
    let pos = x * lv.scale + vec3<f32>(0.5);
    let fl = floor(pos);
    return Cell(vec3<u32>(fl), pos - fl);
}

fn corner_offset(c: u32) -> vec3<u32> {
    return vec3<u32>(c & 1u, (c >> 1u) & 1u, (c >> 2u) & 1u);
}

// Per-axis interpolation factors of corner b: t where the bit is set, 1 - t otherwise.
fn corner_factors(t: vec3<f32>, b: vec3<u32>) -> vec3<f32> {
    return select(vec3<f32>(1.0) - t, t, b == vec3<u32>(1u));
}

// The 8 corners of a cell: each one's first parameter index and its trilinear weight (shared by the
// forward pass and the table gradient, so both visit corners in the same order).
struct Corners {
    entry: array<u32, 8>,
    weight: array<f32, 8>,
}

fn cell_corners(lv: Level, cell: Cell, nf: u32) -> Corners {
    var out: Corners;
    for (var c = 0u; c < 8u; c++) {
        let b = corner_offset(c);
        let w3 = corner_factors(cell.t, b);
        out.weight[c] = w3.x * w3.y * w3.z;
        out.entry[c] = (lv.offset + vertex_index(lv, cell.base + b)) * nf;
    }
    return out;
}

@compute @workgroup_size(64)
fn encode(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
          @builtin(local_invocation_index) li: u32) {
    let i = linear_index(wg, nwg, li);
    let n = grid.n;
    if (i >= n * grid.levels) {
        return;
    }
    let l = i / n;
    let p = i - l * n;
    let nf = NF;
    let lv = grid.level[l];
    let cell = locate(lv, clamp(raw_position(p), vec3<f32>(0.0), vec3<f32>(1.0)));
    let corners = cell_corners(lv, cell, nf);
    let entry = corners.entry;
    let weight = corners.weight;
    let out = p * grid.levels * nf + l * nf;
    for (var f = 0u; f < nf; f++) {
        var acc = 0.0;
        for (var c = 0u; c < 8u; c++) {
            acc += weight[c] * params[entry[c] + f];
        }
        features[out + f] = acc;
    }
}

// The parameter count is a multiple of 8 (level sizes are), so the clear writes whole vec4s: plain stores
// through this second view of the gradient buffer run ~10x faster on CPU drivers than per-word atomicStore.
@compute @workgroup_size(64)
fn clear_grad(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) li: u32) {
    let i = linear_index(wg, nwg, li);
    if (i >= grid.words / 4u) {
        return;
    }
    grad_words[i] = vec4<u32>(0u);
}

// d_params[i] += v. Retries until no other thread changed the word between our load and our store.
fn atomic_add_f32(i: u32, v: f32) {
    var old = atomicLoad(&d_params[i]);
    loop {
        let r = atomicCompareExchangeWeak(&d_params[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (r.exchanged) {
            break;
        }
        old = r.old_value;
    }
}

// Adds a cell's summed contributions, corner by corner (zero sums are skipped: fewer atomics, and
// untouched words stay exactly zero).
fn flush_cell(entry: array<u32, 8>, acc: array<f32, 8 * NF>) {
    for (var c = 0u; c < 8u; c++) {
        for (var f = 0u; f < NF; f++) {
            let v = acc[c * NF + f];
            if (v != 0.0) {
                atomic_add_f32(entry[c] + f, v);
            }
        }
    }
}

@compute @workgroup_size(64)
fn backward_params(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(local_invocation_index) li: u32) {
    let i = linear_index(wg, nwg, li);
    let n = grid.n;
    let runs = (n + grid.run - 1u) / grid.run;
    if (i >= runs * grid.levels) {
        return;
    }
    let l = i / runs;
    let p0 = (i - l * runs) * grid.run;
    let p1 = min(p0 + grid.run, n);
    let lv = grid.level[l];
    var acc: array<f32, 8 * NF>;
    var entry: array<u32, 8>;
    var base = vec3<u32>(0xffffffffu);
    for (var p = p0; p < p1; p++) {
        let cell = locate(lv, clamp(raw_position(p), vec3<f32>(0.0), vec3<f32>(1.0)));
        let row = p * grid.levels * NF + l * NF;
        var g: array<f32, NF>;
        var live = false;
        for (var f = 0u; f < NF; f++) {
            g[f] = d_features[row + f];
            live = live || g[f] != 0.0;
        }
        if (!live) {
            continue;
        }
        if (any(cell.base != base)) {
            if (base.x != 0xffffffffu) {
                flush_cell(entry, acc);
            }
            base = cell.base;
            let corners = cell_corners(lv, cell, NF);
            entry = corners.entry;
            for (var k = 0u; k < 8u * NF; k++) {
                acc[k] = 0.0;
            }
        }
        for (var c = 0u; c < 8u; c++) {
            let b = corner_offset(c);
            let w3 = corner_factors(cell.t, b);
            let w = w3.x * w3.y * w3.z;
            for (var f = 0u; f < NF; f++) {
                acc[c * NF + f] += w * g[f];
            }
        }
    }
    if (base.x != 0xffffffffu) {
        flush_cell(entry, acc);
    }
}

@compute @workgroup_size(64)
fn backward_pos(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) li: u32) {
    let p = linear_index(wg, nwg, li);
    if (p >= grid.n) {
        return;
    }
    let nf = NF;
    let raw = raw_position(p);
    let x = clamp(raw, vec3<f32>(0.0), vec3<f32>(1.0));
    var dx = vec3<f32>(0.0);
    var g: array<f32, NF>;
    for (var l = 0u; l < grid.levels; l++) {
        let lv = grid.level[l];
        let row = p * grid.levels * nf + l * nf;
        for (var f = 0u; f < nf; f++) {
            g[f] = d_features[row + f];
        }
        let cell = locate(lv, x);
        var dt = vec3<f32>(0.0);
        for (var c = 0u; c < 8u; c++) {
            let b = corner_offset(c);
            let entry = (lv.offset + vertex_index(lv, cell.base + b)) * nf;
            // <param_c, dL/dfeatures_l>: how much this corner's value matters to the loss.
            var v = 0.0;
            for (var f = 0u; f < nf; f++) {
                v += params[entry + f] * g[f];
            }
            let w3 = corner_factors(cell.t, b);
            let sign = select(vec3<f32>(-1.0), vec3<f32>(1.0), b == vec3<u32>(1u));
            dt += v * sign * vec3<f32>(w3.y * w3.z, w3.x * w3.z, w3.x * w3.y);
        }
        dx += dt * lv.scale;
    }
    let clamped = (raw < vec3<f32>(0.0)) | (raw > vec3<f32>(1.0));
    dx = select(dx, vec3<f32>(0.0), clamped);
    d_positions[3u * p] = dx.x;
    d_positions[3u * p + 1u] = dx.y;
    d_positions[3u * p + 2u] = dx.z;
}
