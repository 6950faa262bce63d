// The studio's point-cloud view (`viewer`): every point is an instance drawn as a screen-space square (or
// disc) of `size` pixels, coloured by its RGB, a colour-mapped scalar (a log10 std, an error in metres) or
// its layer's solid colour. The uncertainty filter runs here: a point whose filter value is not at most the
// threshold (NaN never is, as in the native `points_filtered.ply`) is moved outside the clip volume, so
// dragging the threshold costs one uniform write per frame, never a re-upload.

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) colour: vec3<f32>,
    @location(1) corner: vec2<f32>,
}

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
    if (filtered_out(filter_value)) {
        out.clip = vec4<f32>(2.0, 2.0, 2.0, 1.0);
        return out;
    }
    var clip = view.view_proj * vec4<f32>(position + view.offset.xyz, 1.0);
    // Half the point size in pixels, as a clip-space offset at this depth.
    clip = vec4<f32>(clip.xy + corner * view.offset.w * view.viewport.zw * clip.w, clip.zw);
    out.clip = clip;
    out.colour = point_colour(rgba, value);
    return out;
}

@fragment
fn fs(in: VertexOut) -> @location(0) vec4<f32> {
    if (view.mode.z != 0u && dot(in.corner, in.corner) > 1.0) {
        discard;
    }
    return vec4<f32>(in.colour, 1.0);
}
