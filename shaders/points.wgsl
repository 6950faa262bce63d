// The studio's point-cloud view (`viewer`): every point is an instance drawn as a screen-space square (or
// disc) of `size` pixels, coloured by its RGB, a colour-mapped scalar (a log10 std, an error in metres) or
// its layer's solid colour. The uncertainty filter runs here: a point whose filter value is not at most the
// threshold (NaN never is, as in the native `points_filtered.ply`) is moved outside the clip volume, so
// dragging the threshold costs one uniform write per frame, never a re-upload.

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

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) colour: vec3<f32>,
    @location(1) corner: vec2<f32>,
}

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

@vertex
fn vs(
    @builtin(vertex_index) vi: u32,
    @location(0) position: vec3<f32>,
    @location(1) rgba: vec4<f32>,
    @location(2) value: f32,
    @location(3) filter_value: f32,
) -> VertexOut {
    var out: VertexOut;
    let corner = vec2<f32>(f32(vi & 1u) * 2.0 - 1.0, f32(vi >> 1u) * 2.0 - 1.0);
    out.corner = corner;
    out.colour = vec3<f32>(0.0);
    // Filtered out: outside the clip volume (every corner, so the whole quad is clipped).
    // NaN is never kept (tested by its bits: a compiler may assume comparisons never see NaN).
    let nan = (bitcast<u32>(filter_value) & 0x7fffffffu) > 0x7f800000u;
    if (view.mode.y != 0u && (nan || !(filter_value <= view.range.z))) {
        out.clip = vec4<f32>(2.0, 2.0, 2.0, 1.0);
        return out;
    }
    var clip = view.view_proj * vec4<f32>(position + view.offset.xyz, 1.0);
    // Half the point size in pixels, as a clip-space offset at this depth.
    clip = vec4<f32>(clip.xy + corner * view.offset.w * view.viewport.zw * clip.w, clip.zw);
    out.clip = clip;
    switch view.mode.x {
        case 0u: {
            out.colour = rgba.rgb;
        }
        case 1u: {
            if (non_finite(value)) {
                out.colour = NO_VALUE;
            } else if (value >= view.range.w) {
                out.colour = UNCONSTRAINED;
            } else {
                let span = view.range.y - view.range.x;
                var t = 0.5;
                if (span != 0.0) {
                    t = (value - view.range.x) / span;
                }
                out.colour = turbo(t);
            }
        }
        default: {
            out.colour = view.solid.rgb;
        }
    }
    return out;
}

@fragment
fn fs(in: VertexOut) -> @location(0) vec4<f32> {
    if (view.mode.z != 0u && dot(in.corner, in.corner) > 1.0) {
        discard;
    }
    return vec4<f32>(in.colour, 1.0);
}
