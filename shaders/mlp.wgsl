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
// index = (wg.y * nwg.x + wg.x) * 64 + local index). Each pipeline is specialised to one layer's shape by
// the prelude the engine compiles in front of this file (see below). lavapipe (the CPU driver) runs 8 lanes
// per SIMD vector and pays dearly for per-lane loads from storage, while a workgroup-memory load whose
// address is the same on every lane is one scalar load and a broadcast, but only outside all control flow
// (inside a loop or branch it also goes lane by lane); the kernels are shaped around that, and around its
// coroutine barriers (no barrier inside a loop that keeps per-row arrays alive: one dispatch per layer).
//   forward_layer    one thread per row: the layer's weights are staged in workgroup memory as
//                    [fan_out][ceil(fan_in / 4)] vec4 rows (zero-padded; the padding lives only there), the
//                    row's input sits in a private vec4 array; the product is the prelude's straight-line
//                    layer_dense. Input from `input` (layer 0) or `saved`; output to `saved` (hidden) or
//                    `output` (last).
//   backward_layer   one thread per row, last layer first: the layer's output gradient (from dL/doutput for
//                    the last layer, else from scratch), times the transposed weights (staged as
//                    [fan_in][ceil(fan_out / 4)]; the prelude's layer_dense_t), masked by the ReLU below,
//                    into the scratch slot of the layer below, or into dL/dinput for layer 0.
//   backward_weights one workgroup per (chunk of rows, block of WB input columns) of one layer, one lane
//                    per output j: sum over the chunk's rows of delta_j * a_k, the first block also of
//                    delta_j (the bias), 64-row tiles of inputs staged in workgroup memory; one partial
//                    per chunk. Skipped, with reduce_grads, when only dL/dinput is wanted.
//   forward_fused    inference (nothing saved): every layer in one dispatch, one thread per row, all the
//                    layers' weights and biases staged at once (the engine picks it on lavapipe when they
//                    fit in 16 KiB: the proposal and density heads), the prelude's straight-line
//                    fused_forward; the hidden rows never leave the lane. Input from `input`, out to `output`.
//   reduce_grads     one thread per parameter: the chunk partials summed in chunk order (deterministic),
//                    written over d_params, or added to it when accumulating. No float atomics anywhere.

const WG: u32 = 64u;
// Rows of the input tile backward_weights stages: its whole chunk (CHUNK, from the prelude); and per step
// of backward_weights_rows (ROWS_TILE, from the prelude).
const TILE_ROWS: u32 = CHUNK;

const FLAG_D_INPUT: u32 = 1u;
const FLAG_ACCUMULATE: u32 = 2u;

struct Mlp {
    n: u32,
    flags: u32,
    n_params: u32,
    // First scratch word of the partial parameter gradients.
    partial_offset: u32,
    chunk_rows: u32,
    chunks: u32,
    _pad0: u32,
    _pad1: u32,
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

// One layer's weights, staged by forward_layer and backward_layer (at most 64 x 64 f32 = 16 KiB, the
// portable limit), or every layer's weights and biases for forward_fused; sized by the prelude (WS_LEN) to
// what the pipeline stages, because WebGPU zero-fills workgroup memory in every workgroup.
var<workgroup> ws: array<vec4<f32>, WS_LEN>;
// Layer inputs staged by backward_weights (TILE_ROWS x WB, 16 KiB, the portable limit) or
// backward_weights_rows (ROWS_TILE x WB): the prelude's STAGED_ROWS is the layer's kernel's. Sized to it
// because WebGPU zero-fills workgroup memory at the start of every workgroup (16 KiB for a 4-column tile
// cost Chromium's SwiftShader ~15 % of a training step).
var<workgroup> tile: array<vec4<f32>, STAGED_ROWS * WB4>;

fn group_index(wg: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return wg.y * nwg.x + wg.x;
}

// The layer a forward_layer / backward_layer pipeline is specialised to comes from the prelude the engine
// compiles in front of this file (field/mlp.rs layer_prelude): L_IN, L_OUT (fan-in, fan-out), L_W, L_B
// (first weight, first bias), L_SAVED (its output's offset in a saved row), L_DELTA (its pre-activation
// gradient's offset in a scratch row), L_FIRST, L_LAST, L_SIGMOID, L_BELOW_SAVED / L_BELOW_DELTA (the same
// offsets of the layer below), SAVED_STRIDE, DELTA_STRIDE. Constant loop bounds let the driver unroll the
// per-row loops and keep the row in registers: with bounds from the uniform, lavapipe kept the private
// arrays in per-lane scratch memory (and a GPU keeps them in local memory).
const K4: u32 = max((L_IN + 3u) / 4u, 1u);
const M4: u32 = max((L_OUT + 3u) / 4u, 1u);
// Lengths of the prelude's layer_dense / layer_dense_t results (a WGSL array cannot be empty).
const O_N: u32 = max(L_OUT, 1u);
const I_N: u32 = max(L_IN, 1u);

fn w_at(j: u32, k: u32) -> f32 {
    if (j < L_OUT && k < L_IN) {
        return params[L_W + j * L_IN + k];
    }
    return 0.0;
}

// ws[j * K4 + q] = W[j][4q .. 4q + 4], zero past fan_in. Lane j stages row j (fan_out <= 64 lanes).
fn stage_weights(li: u32) {
    if (li >= L_OUT) {
        return;
    }
    let dst = li * K4;
    for (var q = 0u; q < K4; q++) {
        let k = 4u * q;
        ws[dst + q] = vec4<f32>(w_at(li, k), w_at(li, k + 1u), w_at(li, k + 2u), w_at(li, k + 3u));
    }
}

// ws[k * M4 + q] = (W[4q][k], .., W[4q + 3][k]), zero past fan_out. Lane k stages row k of the transpose.
fn stage_weights_transposed(li: u32) {
    if (li >= L_IN) {
        return;
    }
    let dst = li * M4;
    for (var q = 0u; q < M4; q++) {
        let j = 4u * q;
        ws[dst + q] = vec4<f32>(w_at(j, li), w_at(j + 1u, li), w_at(j + 2u, li), w_at(j + 3u, li));
    }
}

fn sigmoid1(z: f32) -> f32 {
    return 1.0 / (1.0 + exp(-z));
}

// Input k of row r (the network input, or the saved outputs of the layer below), zero past fan_in.
fn in_at(r: u32, k: u32) -> f32 {
    if (k >= L_IN) {
        return 0.0;
    }
    if (L_FIRST) {
        return input[r * L_IN + k];
    }
    return saved[r * SAVED_STRIDE + L_BELOW_SAVED + k];
}

// Row r's input to the layer, four at a time: a loop of at most 16 that the driver unrolls (a loop over
// single words, up to 64, stayed a loop on lavapipe and left the row in per-lane scratch memory).
fn layer_row(r: u32) -> array<vec4<f32>, K4> {
    var a: array<vec4<f32>, K4>;
    for (var q = 0u; q < K4; q++) {
        let k = 4u * q;
        a[q] = vec4<f32>(in_at(r, k), in_at(r, k + 1u), in_at(r, k + 2u), in_at(r, k + 3u));
    }
    return a;
}

// The loop form's row loader: one word at a time.
fn layer_row_loop(r: u32) -> array<vec4<f32>, K4> {
    var a: array<vec4<f32>, K4>;
    for (var k = 0u; k < L_IN; k++) {
        a[k / 4u][k & 3u] = in_at(r, k);
    }
    return a;
}

// Row r's pre-activation gradient of output j (zero past fan_out): from dL/doutput for the last layer
// (times y (1 - y) under the sigmoid), else from scratch.
fn delta_at(r: u32, j: u32) -> f32 {
    if (j >= L_OUT) {
        return 0.0;
    }
    if (L_LAST) {
        var v = d_output[r * L_OUT + j];
        if (L_SIGMOID) {
            let y = saved[r * SAVED_STRIDE + L_SAVED + j];
            v *= y * (1.0 - y);
        }
        return v;
    }
    return scratch[r * DELTA_STRIDE + L_DELTA + j];
}

// Both per-row kernels come in two forms, picked by the prelude's STRAIGHT (Gpu::straight_line_kernels):
// - straight (lavapipe): the matrix product outside all control flow, the prelude's generated layer_dense /
//   layer_dense_t (see layer_products in field/mlp.rs); no early return, a lane past the batch (or in a whole
//   workgroup past it, the tail of a folded dispatch) works on the last row and stores nothing. The engine
//   never dispatches them for n = 0.
// - loops (every other adapter): lanes past the batch leave early, the product runs one output at a time and
//   is stored as it goes. GPUs unroll these loops themselves; Chromium's SwiftShader ran the straight form's
//   shape (array-returning products, no early return) at half speed even with loops inside.
@compute @workgroup_size(64)
fn forward_layer(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) li: u32) {
    let n = mlp.n;
    let first = group_index(wg, nwg) * WG;
    if (!STRAIGHT && first >= n) {
        // Whole workgroups past the batch leave before the barrier.
        return;
    }
    stage_weights(li);
    workgroupBarrier();
    if (STRAIGHT) {
        let live = first + li < n;
        let r = min(first + li, n - 1u);
        let z = layer_dense(layer_row(r));
        if (!live) {
            return;
        }
        for (var j = 0u; j < L_OUT; j++) {
            store_output(r, j, params[L_B + j] + z[j]);
        }
    } else {
        let r = first + li;
        if (r >= n) {
            return;
        }
        let a = layer_row_loop(r);
        // One output at a time: a private row of inputs against one broadcast weight row.
        for (var j = 0u; j < L_OUT; j++) {
            var acc = vec4<f32>(0.0);
            for (var q = 0u; q < K4; q++) {
                acc += a[q] * ws[j * K4 + q];
            }
            store_output(r, j, params[L_B + j] + (acc.x + acc.y) + (acc.z + acc.w));
        }
    }
}

// Output j of row r, pre-activation z: through the ReLU into saved (hidden layers), or through the output
// activation into output (and saved under a sigmoid, for its derivative).
fn store_output(r: u32, j: u32, z: f32) {
    var y = z;
    if (!L_LAST) {
        y = max(y, 0.0);
        saved[r * SAVED_STRIDE + L_SAVED + j] = y;
    } else {
        if (L_SIGMOID) {
            y = sigmoid1(y);
            saved[r * SAVED_STRIDE + L_SAVED + j] = y;
        }
        output[r * L_OUT + j] = y;
    }
}

@compute @workgroup_size(64)
fn backward_layer(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) li: u32) {
    let n = mlp.n;
    let first = group_index(wg, nwg) * WG;
    if (!STRAIGHT && first >= n) {
        return;
    }
    // Layer 0's transposed product is dL/dinput: not computed (loops) or not stored (straight) when not
    // asked for.
    let product = !L_FIRST || (mlp.flags & FLAG_D_INPUT) != 0u;
    if (product) {
        stage_weights_transposed(li);
    }
    workgroupBarrier();
    if (STRAIGHT) {
        let live = first + li < n;
        let r = min(first + li, n - 1u);
        var g: array<vec4<f32>, M4>;
        for (var q = 0u; q < M4; q++) {
            let j = 4u * q;
            g[q] = vec4<f32>(delta_at(r, j), delta_at(r, j + 1u), delta_at(r, j + 2u), delta_at(r, j + 3u));
        }
        let d = layer_dense_t(g);
        if (!live) {
            return;
        }
        if (L_LAST) {
            // The output layer's deltas, kept for backward_weights.
            for (var j = 0u; j < L_OUT; j++) {
                scratch[r * DELTA_STRIDE + L_DELTA + j] = g[j / 4u][j & 3u];
            }
        }
        if (!product) {
            return;
        }
        for (var k = 0u; k < L_IN; k++) {
            store_input_delta(r, k, d[k]);
        }
    } else {
        let r = first + li;
        if (r >= n) {
            return;
        }
        var g: array<vec4<f32>, M4>;
        for (var j = 0u; j < L_OUT; j++) {
            let v = delta_at(r, j);
            g[j / 4u][j & 3u] = v;
            if (L_LAST) {
                // The output layer's deltas, kept for backward_weights.
                scratch[r * DELTA_STRIDE + L_DELTA + j] = v;
            }
        }
        if (!product) {
            return;
        }
        for (var k = 0u; k < L_IN; k++) {
            var acc = vec4<f32>(0.0);
            for (var q = 0u; q < M4; q++) {
                acc += g[q] * ws[k * M4 + q];
            }
            store_input_delta(r, k, (acc.x + acc.y) + (acc.z + acc.w));
        }
    }
}

// Inference through every layer at once (see the header; the prelude is layer 0's plus the fused
// stage_fused / fused_forward and F_OUT, the network's output width). Same shape as the straight
// forward_layer: no early return before the products.
@compute @workgroup_size(64)
fn forward_fused(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) li: u32) {
    let n = mlp.n;
    let first = group_index(wg, nwg) * WG;
    stage_fused(li);
    workgroupBarrier();
    let live = first + li < n;
    let r = min(first + li, n - 1u);
    let y = fused_forward(layer_row(r));
    if (!live) {
        return;
    }
    for (var j = 0u; j < F_OUT; j++) {
        output[r * F_OUT + j] = y[j];
    }
}

// Parameter word `at` (a weight or bias of some layer), or 0 where `ok` is false (padding).
fn param_or_zero(at: u32, ok: bool) -> f32 {
    if (ok) {
        return params[at];
    }
    return 0.0;
}

// Row r's gradient of input k, v: masked by the ReLU below into its scratch slot, or dL/dinput for layer 0.
fn store_input_delta(r: u32, k: u32, v: f32) {
    if (!L_FIRST) {
        // ReLU': the unit was active iff its saved output is positive. select, not a product, so a dead
        // unit's gradient is exactly 0 even if the sum overflowed.
        scratch[r * DELTA_STRIDE + L_BELOW_DELTA + k] =
            select(0.0, v, saved[r * SAVED_STRIDE + L_BELOW_SAVED + k] > 0.0);
    } else {
        d_input[r * L_IN + k] = v;
    }
}

// Input columns per backward_weights workgroup (WB, from the prelude), and the layer's blocks of them.
const WB4: u32 = WB / 4u;
const NB: u32 = max((L_IN + WB - 1u) / WB, 1u);

// Row r's inputs kb + 4q .. kb + 4q + 4 (the network input or the saved outputs below), zero past fan_in.
fn input4(r: u32, k: u32) -> vec4<f32> {
    var v = vec4<f32>(0.0);
    for (var c = 0u; c < 4u; c++) {
        if (k + c < L_IN) {
            if (L_FIRST) {
                v[c] = input[r * L_IN + k + c];
            } else {
                v[c] = saved[r * SAVED_STRIDE + L_BELOW_SAVED + k + c];
            }
        }
    }
    return v;
}

// Lane j's partial gradients of one chunk: weights j, kb .. kb + WB (those that exist), and the bias from
// the first block.
fn store_partials(chunk: u32, kb: u32, j: u32, w: array<vec4<f32>, WB4>, bias: f32) {
    let out = mlp.partial_offset + chunk * mlp.n_params;
    for (var c = 0u; c < WB; c++) {
        let k = kb + c;
        if (k < L_IN) {
            scratch[out + L_W + j * L_IN + k] = w[c / 4u][c & 3u];
        }
    }
    if (kb == 0u) {
        scratch[out + L_B + j] = bias;
    }
}

// The chunk's rows staged at once (TILE_ROWS = CHUNK), the sums over them the prelude's straight-line
// weight_sums (one lane-uniform tile load per four columns and row, outside all control flow: see
// layer_products in field/mlp.rs); rows past the batch are zeros in the tile and in the deltas.
fn delta_or_zero(row: u32, j: u32) -> f32 {
    let v = scratch[min(row, mlp.n - 1u) * DELTA_STRIDE + L_DELTA + min(j, O_N - 1u)];
    return select(0.0, v, row < mlp.n);
}

@compute @workgroup_size(64)
fn backward_weights(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                    @builtin(local_invocation_index) li: u32) {
    // A folded dispatch's tail repeats the last workgroup's sums and stores nothing (no early return: it
    // would put the sums inside control flow).
    let groups = mlp.chunks * NB;
    let live_group = group_index(wg, nwg) < groups;
    let gi = min(group_index(wg, nwg), groups - 1u);
    let chunk = gi / NB;
    let kb = (gi - chunk * NB) * WB;
    let j = li;
    let r0 = chunk * TILE_ROWS;
    // tile[row * WB4 + q] = inputs kb + 4q .. kb + 4q + 4 of row r0 + row: the same for every lane, so
    // the sums read them as broadcasts.
    for (var s = li; s < TILE_ROWS * WB4; s += WG) {
        let row = s / WB4;
        let q = s - row * WB4;
        let r = r0 + row;
        tile[s] = select(vec4<f32>(0.0), input4(min(r, mlp.n - 1u), kb + 4u * q), r < mlp.n);
    }
    workgroupBarrier();
    let sums = weight_sums(r0, j);
    if (!live_group || j >= L_OUT) {
        return;
    }
    var w: array<vec4<f32>, WB4>;
    for (var q = 0u; q < WB4; q++) {
        w[q] = sums[q];
    }
    store_partials(chunk, kb, j, w, sums[WB4].x);
}

// backward_weights for a narrow layer (fewer than 32 outputs, as the engine picks): the same sums in loops
// over 64-row tiles, where only the lanes of live outputs run them (the straight-line sums would run all
// 64 lanes for a handful of outputs).
@compute @workgroup_size(64)
fn backward_weights_rows(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                         @builtin(local_invocation_index) li: u32) {
    let gi = group_index(wg, nwg);
    if (gi >= mlp.chunks * NB) {
        return;
    }
    let chunk = gi / NB;
    let kb = (gi - chunk * NB) * WB;
    let j = li;
    let lane_live = j < L_OUT;
    let r0 = chunk * mlp.chunk_rows;
    let r1 = min(r0 + mlp.chunk_rows, mlp.n);
    var acc: array<vec4<f32>, WB4>;
    var bias = 0.0;
    for (var t = r0; t < r1; t += ROWS_TILE) {
        let rows = min(ROWS_TILE, r1 - t);
        workgroupBarrier();
        for (var s = li; s < rows * WB4; s += WG) {
            let row = s / WB4;
            let q = s - row * WB4;
            tile[s] = input4(t + row, kb + 4u * q);
        }
        workgroupBarrier();
        if (lane_live) {
            for (var rr = 0u; rr < rows; rr++) {
                let dv = scratch[(t + rr) * DELTA_STRIDE + L_DELTA + j];
                bias += dv;
                for (var q = 0u; q < WB4; q++) {
                    acc[q] += dv * tile[rr * WB4 + q];
                }
            }
        }
    }
    if (!lane_live) {
        return;
    }
    store_partials(chunk, kb, j, acc, bias);
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
