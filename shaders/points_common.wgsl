// Shared by the studio's two point draws (`points.wgsl`, instanced quads; `points_compute.wgsl`, the
// compute rasteriser): the per-layer view block, the colour modes and the uncertainty filter, so both draws
// colour and hide a point by the same code. Prepended to each at compile time (`core/src/shaders.rs`).

struct View {
    // World (relative to the view's reference point) to clip space.
    view_proj: mat4x4<f32>,
    // xyz: this layer's origin relative to the reference point; w: point size in pixels.
    offset: vec4<f32>,
    // Width, height, 1/width, 1/height of the target in pixels.
    viewport: vec4<f32>,
    // The layer's colour in `solid` mode (linear RGB, alpha unused).
    solid: vec4<f32>,
    // x, y: the colour map's range (value at blue, value at red); z: filter threshold; w: values at or
    // above it are "unconstrained" (an uncertainty that reads its prior), drawn apart from the map.
    range: vec4<f32>,
    // x: colour mode (0 RGB, 1 colour map, 2 solid); y: filter on; z: round points; w: unused.
    mode: vec4<u32>,
}

@group(0) @binding(0) var<uniform> view: View;

fn non_finite(v: f32) -> bool {
    // Bit test: `v != v` may be folded away by shader compilers that assume finite maths.
    return (bitcast<u32>(v) & 0x7f800000u) == 0x7f800000u;
}

// Google's Turbo colour map, polynomial approximation (the same coefficients as `viewer::turbo`).
fn turbo(t_in: f32) -> vec3<f32> {
    let t = clamp(t_in, 0.0, 1.0);
    let v4 = vec4<f32>(1.0, t, t * t, t * t * t);
    let v2 = v4.zw * v4.z;
    return clamp(vec3<f32>(
        dot(v4, vec4<f32>(0.13572138, 4.61539260, -42.66032258, 132.13108234)) + dot(v2, vec2<f32>(-152.94239396, 59.28637943)),
        dot(v4, vec4<f32>(0.09140261, 2.19418839, 4.84296658, -14.18503333)) + dot(v2, vec2<f32>(4.27729857, 2.82956604)),
        dot(v4, vec4<f32>(0.10667330, 12.64194608, -60.58204836, 110.36276771)) + dot(v2, vec2<f32>(-89.90310912, 27.34824973)),
    ), vec3<f32>(0.0), vec3<f32>(1.0));
}

// Grey for points whose scalar is missing or not finite (`viewer::NO_VALUE_COLOUR`).
const NO_VALUE: vec3<f32> = vec3<f32>(0.45, 0.45, 0.45);
// Lilac for values at or above `range.w` (`viewer::UNCONSTRAINED_COLOUR`).
const UNCONSTRAINED: vec3<f32> = vec3<f32>(0.85, 0.78, 0.95);

// Whether the layer's filter hides a point whose filter value is `v`: a value that is not at most the
// threshold is hidden, and NaN never is kept (tested by its bits: a compiler may assume comparisons never
// see NaN), as in the native `points_filtered.ply`.
fn filtered_out(v: f32) -> bool {
    let nan = (bitcast<u32>(v) & 0x7fffffffu) > 0x7f800000u;
    return view.mode.y != 0u && (nan || !(v <= view.range.z));
}

// The colour of a point in the layer's mode: its RGB, its scalar `value` through Turbo (grey when missing,
// lilac at or above "unconstrained"), or the layer's solid colour.
fn point_colour(rgba: vec4<f32>, value: f32) -> vec3<f32> {
    switch view.mode.x {
        case 0u: {
            return rgba.rgb;
        }
        case 1u: {
            if (non_finite(value)) {
                return NO_VALUE;
            } else if (value >= view.range.w) {
                return UNCONSTRAINED;
            }
            let span = view.range.y - view.range.x;
            var t = 0.5;
            if (span != 0.0) {
                t = (value - view.range.x) / span;
            }
            return turbo(t);
        }
        default: {
            return view.solid.rgb;
        }
    }
}
