// Small fully-connected MLP (nerfacto's density and colour heads): forward, and backward to the input and
// to the parameters. CPU reference and the exact layouts: core/src/field/mlp.rs.
//
// Layers: linear layer l maps fan_in -> fan_out (every width <= 64); ReLU after every layer but the last,
// the last then None or Sigmoid. Parameters: one f32 array, layer after layer, each layer its weights
// row-major [fan_out][fan_in] (PyTorch's nn.Linear layout) followed by its fan_out biases.
// Rows (batch): input [n][in], output [n][out], d_output [n][out], d_input [n][in], all dense.
// saved [n][saved_stride]: the post-ReLU activations of every hidden layer (layer l at l * hidden), then the
//   sigmoid outputs when the output activation is Sigmoid. The forward chains its layers through it and
//   the backward reads its ReLU masks (a > 0) and layer inputs from it.
// scratch [scratch words]: [n][delta_stride] pre-activation gradients of every layer's outputs (layer l at
//   its delta offset), then [chunks][n_params] partial parameter gradients, one per chunk of rows.
//
// Entry points (64 threads per workgroup; dispatch possibly folded into 2-D:
// index = (wg.y * nwg.x + wg.x) * 64 + local index). lavapipe (the CPU driver) runs 8 lanes per SIMD
// vector and pays dearly for per-lane loads from storage, while a load whose address is the same on every
// lane is one load and a broadcast; the kernels are shaped around that, and around its coroutine barriers
// (no barrier inside a loop that keeps per-row arrays alive: one dispatch per layer instead).
//   forward_layer    layer `current`, one thread per row: the layer's weights are staged in workgroup memory
//                    as [fan_out][ceil(fan_in / 4)] vec4 rows (zero-padded; the padding lives only there),
//                    the row's input sits in a private vec4 array, eight outputs per pass. Input from
//                    `input` (layer 0) or `saved`; output to `saved` (hidden) or `output` (last).
//   backward_layer   layer `current`, one thread per row, last layer first: the layer's output gradient
//                    (from dL/doutput for the last layer, else from scratch), times the transposed weights
//                    (staged as [fan_in][ceil(fan_out / 4)]), masked by the ReLU below, into the scratch
//                    slot of the layer below, or into dL/dinput for layer 0.
//   backward_weights one workgroup per (chunk of rows, layer, block of 16 input columns), one lane per
//                    output j: sum over the chunk's rows of delta_j * a_k (a_k = 1 for the bias column),
//                    64-row tiles of inputs staged in workgroup memory; one partial per chunk.
//   reduce_grads     one thread per parameter: the chunk partials summed in chunk order (deterministic),
//                    written over d_params, or added to it when accumulating. No float atomics anywhere.

const WG: u32 = 64u;
// Rows of the input tile staged per step of backward_weights, and input columns per block.
const TILE_ROWS: u32 = 64u;
const BLOCK: u32 = 16u;

const FLAG_D_INPUT: u32 = 1u;
const FLAG_ACCUMULATE: u32 = 2u;
const ACT_SIGMOID: u32 = 1u;

struct Mlp {
    n: u32,
    layers: u32,
    output_act: u32,
    flags: u32,
    n_params: u32,
    saved_stride: u32,
    delta_stride: u32,
    // First scratch word of the partial parameter gradients.
    partial_offset: u32,
    chunk_rows: u32,
    chunks: u32,
    // backward_weights workgroups per chunk (blocks over all layers).
    blocks: u32,
    // The layer of a forward_layer / backward_layer dispatch.
    current: u32,
    // Per layer l: [2l] = (fan_in, fan_out, weight offset, bias offset),
    // [2l + 1] = (delta offset, saved offset of its output, first block, block count).
    layer: array<vec4<u32>, 18>,
}

@group(0) @binding(0) var<uniform> mlp: Mlp;
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read> input: array<f32>;
@group(0) @binding(3) var<storage, read_write> output: array<f32>;
@group(0) @binding(4) var<storage, read_write> saved: array<f32>;
@group(0) @binding(5) var<storage, read> d_output: array<f32>;
@group(0) @binding(6) var<storage, read_write> scratch: array<f32>;
@group(0) @binding(7) var<storage, read_write> d_params: array<f32>;
@group(0) @binding(8) var<storage, read_write> d_input: array<f32>;

// One layer's weights (64 x 64 f32 = 16 KiB, the portable limit): forward_layer and backward_layer.
var<workgroup> ws: array<vec4<f32>, 1024>;
// TILE_ROWS x BLOCK layer inputs: backward_weights.
var<workgroup> tile: array<vec4<f32>, 256>;

fn group_index(wg: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return wg.y * nwg.x + wg.x;
}

fn weight(l: u32, j: u32, k: u32) -> f32 {
    let d = mlp.layer[2u * l];
    if (j < d.y && k < d.x) {
        return params[d.z + j * d.x + k];
    }
    return 0.0;
}

fn bias4(l: u32, j: u32) -> vec4<f32> {
    let d = mlp.layer[2u * l];
    let o = d.w + j;
    if (j + 4u <= d.y) {
        return vec4<f32>(params[o], params[o + 1u], params[o + 2u], params[o + 3u]);
    }
    var b = vec4<f32>(0.0);
    for (var c = 0u; j + c < d.y; c++) {
        b[c] = params[o + c];
    }
    return b;
}

// ws[j * k4 + q] = W[j][4q .. 4q + 4], zero past fan_in (k4 = ceil(fan_in / 4)). Lane j stages row j
// (fan_out <= 64 lanes): no per-lane integer division, which CPU drivers run lane by lane.
fn stage_weights(l: u32, li: u32) {
    let d = mlp.layer[2u * l];
    let k_in = d.x;
    if (li >= d.y) {
        return;
    }
    let src = d.z + li * k_in;
    let dst = li * ((k_in + 3u) / 4u);
    var k = 0u;
    for (; k + 4u <= k_in; k += 4u) {
        let s = src + k;
        ws[dst + k / 4u] = vec4<f32>(params[s], params[s + 1u], params[s + 2u], params[s + 3u]);
    }
    if (k < k_in) {
        ws[dst + k / 4u] = vec4<f32>(weight(l, li, k), weight(l, li, k + 1u), weight(l, li, k + 2u), 0.0);
    }
}

// ws[k * m4 + q] = (W[4q][k], .., W[4q + 3][k]), zero past fan_out (m4 = ceil(fan_out / 4)). Lane k stages
// row k of the transpose.
fn stage_weights_transposed(l: u32, li: u32) {
    let d = mlp.layer[2u * l];
    let k_in = d.x;
    let m = d.y;
    if (li >= k_in) {
        return;
    }
    let src = d.z + li;
    let dst = li * ((m + 3u) / 4u);
    var j = 0u;
    for (; j + 4u <= m; j += 4u) {
        let s = src + j * k_in;
        ws[dst + j / 4u] = vec4<f32>(params[s], params[s + k_in], params[s + 2u * k_in], params[s + 3u * k_in]);
    }
    if (j < m) {
        ws[dst + j / 4u] = vec4<f32>(weight(l, j, li), weight(l, j + 1u, li), weight(l, j + 2u, li), 0.0);
    }
}

fn sigmoid(z: vec4<f32>) -> vec4<f32> {
    return vec4<f32>(1.0) / (vec4<f32>(1.0) + exp(-z));
}

// Row r's input to layer l (the network input, or the saved outputs of layer l - 1), zero past fan_in.
fn layer_row(l: u32, r: u32) -> array<vec4<f32>, 16> {
    var a: array<vec4<f32>, 16>;
    let k_in = mlp.layer[2u * l].x;
    var k = 0u;
    if (l == 0u) {
        let base = r * k_in;
        for (; k + 4u <= k_in; k += 4u) {
            let b = base + k;
            a[k / 4u] = vec4<f32>(input[b], input[b + 1u], input[b + 2u], input[b + 3u]);
        }
        for (; k < k_in; k++) {
            a[k / 4u][k & 3u] = input[base + k];
        }
    } else {
        let base = r * mlp.saved_stride + mlp.layer[2u * (l - 1u) + 1u].y;
        for (; k + 4u <= k_in; k += 4u) {
            let b = base + k;
            a[k / 4u] = vec4<f32>(saved[b], saved[b + 1u], saved[b + 2u], saved[b + 3u]);
        }
        for (; k < k_in; k++) {
            a[k / 4u][k & 3u] = saved[base + k];
        }
    }
    return a;
}

// Stores values ob .. ob + 8 (those below m) at base + ob: into saved, or into output.
fn store8(base: u32, ob: u32, m: u32, v0: vec4<f32>, v1: vec4<f32>, to_saved: bool) {
    let b = base + ob;
    if (ob + 8u <= m) {
        if (to_saved) {
            saved[b] = v0.x; saved[b + 1u] = v0.y; saved[b + 2u] = v0.z; saved[b + 3u] = v0.w;
            saved[b + 4u] = v1.x; saved[b + 5u] = v1.y; saved[b + 6u] = v1.z; saved[b + 7u] = v1.w;
        } else {
            output[b] = v0.x; output[b + 1u] = v0.y; output[b + 2u] = v0.z; output[b + 3u] = v0.w;
            output[b + 4u] = v1.x; output[b + 5u] = v1.y; output[b + 6u] = v1.z; output[b + 7u] = v1.w;
        }
        return;
    }
    let v = array<f32, 8>(v0.x, v0.y, v0.z, v0.w, v1.x, v1.y, v1.z, v1.w);
    for (var c = 0u; ob + c < m; c++) {
        if (to_saved) {
            saved[b + c] = v[c];
        } else {
            output[b + c] = v[c];
        }
    }
}

@compute @workgroup_size(64)
fn forward_layer(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) li: u32) {
    let n = mlp.n;
    // Whole workgroups past the batch (a folded dispatch's tail) leave before the barrier.
    let first = group_index(wg, nwg) * WG;
    if (first >= n) {
        return;
    }
    let l = mlp.current;
    stage_weights(l, li);
    workgroupBarrier();
    let r = first + li;
    if (r >= n) {
        return;
    }
    let d = mlp.layer[2u * l];
    let so = mlp.layer[2u * l + 1u].y;
    let k4 = (d.x + 3u) / 4u;
    let m = d.y;
    let last = l + 1u == mlp.layers;
    let ss = mlp.saved_stride;
    let a = layer_row(l, r);
    // Eight outputs at a time: two vec4 accumulators, one private vec4 of inputs and eight broadcast
    // weight vec4s per step.
    for (var ob = 0u; ob < m; ob += 8u) {
        var acc0 = bias4(l, ob);
        var acc1 = bias4(l, ob + 4u);
        for (var q = 0u; q < k4; q++) {
            let v = a[q];
            let w = ob * k4 + q;
            acc0.x += dot(v, ws[w]);
            acc0.y += dot(v, ws[w + k4]);
            acc0.z += dot(v, ws[w + 2u * k4]);
            acc0.w += dot(v, ws[w + 3u * k4]);
            acc1.x += dot(v, ws[w + 4u * k4]);
            acc1.y += dot(v, ws[w + 5u * k4]);
            acc1.z += dot(v, ws[w + 6u * k4]);
            acc1.w += dot(v, ws[w + 7u * k4]);
        }
        // Outputs past fan_out (stale weight rows) are never stored.
        if (!last) {
            store8(r * ss + so, ob, m, max(acc0, vec4<f32>(0.0)), max(acc1, vec4<f32>(0.0)), true);
        } else {
            if (mlp.output_act == ACT_SIGMOID) {
                acc0 = sigmoid(acc0);
                acc1 = sigmoid(acc1);
                store8(r * ss + so, ob, m, acc0, acc1, true);
            }
            store8(r * m, ob, m, acc0, acc1, false);
        }
    }
}

// Stores values kb .. kb + 8 (those below k_in) at base + kb: into the scratch deltas, or into dL/dinput.
fn store_delta8(base: u32, kb: u32, k_in: u32, v0: vec4<f32>, v1: vec4<f32>, to_scratch: bool) {
    let v = array<f32, 8>(v0.x, v0.y, v0.z, v0.w, v1.x, v1.y, v1.z, v1.w);
    let b = base + kb;
    for (var c = 0u; c < 8u && kb + c < k_in; c++) {
        if (to_scratch) {
            scratch[b + c] = v[c];
        } else {
            d_input[b + c] = v[c];
        }
    }
}

@compute @workgroup_size(64)
fn backward_layer(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) li: u32) {
    let n = mlp.n;
    let first = group_index(wg, nwg) * WG;
    if (first >= n) {
        return;
    }
    let l = mlp.current;
    let d = mlp.layer[2u * l];
    let e = mlp.layer[2u * l + 1u];
    // Layer 0's transposed product is dL/dinput: skipped when not asked for.
    let product = l > 0u || (mlp.flags & FLAG_D_INPUT) != 0u;
    if (product) {
        stage_weights_transposed(l, li);
    }
    workgroupBarrier();
    let r = first + li;
    if (r >= n) {
        return;
    }
    let k_in = d.x;
    let m = d.y;
    let ss = mlp.saved_stride;
    let ds = mlp.delta_stride;
    var g: array<vec4<f32>, 16>;
    if (l + 1u == mlp.layers) {
        // The output layer: delta = dL/dy * y (1 - y) under the sigmoid, dL/dy otherwise; kept for
        // backward_weights.
        for (var j = 0u; j < m; j++) {
            var v = d_output[r * m + j];
            if (mlp.output_act == ACT_SIGMOID) {
                let y = saved[r * ss + e.y + j];
                v *= y * (1.0 - y);
            }
            g[j / 4u][j & 3u] = v;
            scratch[r * ds + e.x + j] = v;
        }
    } else {
        let b = r * ds + e.x;
        var j = 0u;
        for (; j + 4u <= m; j += 4u) {
            g[j / 4u] = vec4<f32>(scratch[b + j], scratch[b + j + 1u], scratch[b + j + 2u], scratch[b + j + 3u]);
        }
        for (; j < m; j++) {
            g[j / 4u][j & 3u] = scratch[b + j];
        }
    }
    if (!product) {
        return;
    }
    let m4 = (m + 3u) / 4u;
    // The layer below: its saved outputs give the ReLU mask, its delta slot takes the result.
    var below = vec4<u32>(0u);
    if (l > 0u) {
        below = mlp.layer[2u * (l - 1u) + 1u];
    }
    for (var kb = 0u; kb < k_in; kb += 8u) {
        var acc0 = vec4<f32>(0.0);
        var acc1 = vec4<f32>(0.0);
        for (var q = 0u; q < m4; q++) {
            let v = g[q];
            let w = kb * m4 + q;
            acc0.x += dot(v, ws[w]);
            acc0.y += dot(v, ws[w + m4]);
            acc0.z += dot(v, ws[w + 2u * m4]);
            acc0.w += dot(v, ws[w + 3u * m4]);
            acc1.x += dot(v, ws[w + 4u * m4]);
            acc1.y += dot(v, ws[w + 5u * m4]);
            acc1.z += dot(v, ws[w + 6u * m4]);
            acc1.w += dot(v, ws[w + 7u * m4]);
        }
        if (l > 0u) {
            // ReLU': the unit was active iff its saved output is positive. select, not a product, so a
            // dead unit's gradient is exactly 0 even if the sum overflowed.
            let s = r * ss + below.y + kb;
            var on0 = vec4<bool>(false);
            var on1 = vec4<bool>(false);
            for (var c = 0u; c < 8u && kb + c < k_in; c++) {
                let on = saved[s + c] > 0.0;
                if (c < 4u) {
                    on0[c] = on;
                } else {
                    on1[c & 3u] = on;
                }
            }
            acc0 = select(vec4<f32>(0.0), acc0, on0);
            acc1 = select(vec4<f32>(0.0), acc1, on1);
            store_delta8(r * ds + below.x, kb, k_in, acc0, acc1, true);
        } else {
            store_delta8(r * k_in, kb, k_in, acc0, acc1, false);
        }
    }
}

// Input column k of layer l for row r, with the bias as column fan_in (constant 1) and zeros past it.
fn layer_input(l: u32, r: u32, k: u32) -> f32 {
    let k_in = mlp.layer[2u * l].x;
    if (k < k_in) {
        if (l == 0u) {
            return input[r * k_in + k];
        }
        return saved[r * mlp.saved_stride + mlp.layer[2u * (l - 1u) + 1u].y + k];
    }
    return select(0.0, 1.0, k == k_in);
}

@compute @workgroup_size(64)
fn backward_weights(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                    @builtin(local_invocation_index) li: u32) {
    let gi = group_index(wg, nwg);
    let blocks = mlp.blocks;
    if (gi >= mlp.chunks * blocks) {
        return;
    }
    let chunk = gi / blocks;
    let b = gi - chunk * blocks;
    var l = 0u;
    for (; l + 1u < mlp.layers; l++) {
        let e = mlp.layer[2u * l + 1u];
        if (b < e.z + e.w) {
            break;
        }
    }
    let d = mlp.layer[2u * l];
    let e = mlp.layer[2u * l + 1u];
    let k_in = d.x;
    let kb = (b - e.z) * BLOCK;
    let j = li;
    let lane_live = j < d.y;
    let r0 = chunk * mlp.chunk_rows;
    let r1 = min(r0 + mlp.chunk_rows, mlp.n);
    let ds = mlp.delta_stride;
    var acc0 = vec4<f32>(0.0);
    var acc1 = vec4<f32>(0.0);
    var acc2 = vec4<f32>(0.0);
    var acc3 = vec4<f32>(0.0);
    for (var t = r0; t < r1; t += TILE_ROWS) {
        let rows = min(TILE_ROWS, r1 - t);
        workgroupBarrier();
        // tile[row * 4 + q] = inputs kb + 4q .. kb + 4q + 4 of row t + row: the same for every lane, so
        // the sums below read them as broadcasts.
        for (var s = li; s < rows * 4u; s += WG) {
            let row = t + s / 4u;
            let k = kb + 4u * (s & 3u);
            tile[s] = vec4<f32>(layer_input(l, row, k), layer_input(l, row, k + 1u),
                                layer_input(l, row, k + 2u), layer_input(l, row, k + 3u));
        }
        workgroupBarrier();
        if (lane_live) {
            for (var rr = 0u; rr < rows; rr++) {
                let dv = scratch[(t + rr) * ds + e.x + j];
                let base = rr * 4u;
                acc0 += dv * tile[base];
                acc1 += dv * tile[base + 1u];
                acc2 += dv * tile[base + 2u];
                acc3 += dv * tile[base + 3u];
            }
        }
    }
    if (!lane_live) {
        return;
    }
    let out = mlp.partial_offset + chunk * mlp.n_params;
    let v = array<f32, 16>(acc0.x, acc0.y, acc0.z, acc0.w, acc1.x, acc1.y, acc1.z, acc1.w,
                           acc2.x, acc2.y, acc2.z, acc2.w, acc3.x, acc3.y, acc3.z, acc3.w);
    for (var c = 0u; c < BLOCK && kb + c <= k_in; c++) {
        let k = kb + c;
        if (k < k_in) {
            scratch[out + d.z + j * k_in + k] = v[c];
        } else {
            scratch[out + d.w + j] = v[c];
        }
    }
}

@compute @workgroup_size(64)
fn reduce_grads(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) li: u32) {
    let p = group_index(wg, nwg) * WG + li;
    let np = mlp.n_params;
    if (p >= np) {
        return;
    }
    var s = 0.0;
    for (var c = 0u; c < mlp.chunks; c++) {
        s += scratch[mlp.partial_offset + c * np + p];
    }
    if ((mlp.flags & FLAG_ACCUMULATE) != 0u) {
        s = d_params[p] + s;
    }
    d_params[p] = s;
}
