//! The CPU reference of the point draws: the picture `shaders/points_compute.wgsl` makes, computed the
//! same way in f32 — projection, the footprint of `size` × `size` pixels (a disc when round), the kept
//! depth range, the nearest point winning (the larger colour on equal depths) and the colour and filter
//! rules of `points_common.wgsl`. The quad draw makes the same picture up to its rasteriser's sub-pixel
//! snapping on footprint edges (a test bounds the difference).

use glam::Vec3;

use crate::uncertainty::filter::keeps;

use super::{map_colour, Colouring, Frame, LayerParams, ViewCloud};

/// One layer of a reference frame.
pub struct ReferenceLayer<'a> {
    pub cloud: &'a ViewCloud,
    pub colouring: Colouring,
    pub filter: Option<(usize, f32)>,
}

/// RGBA8 pixels of `frame` (row-major, y down) with `layers` drawn, as the compute rasteriser draws them.
pub fn rasterise(frame: &Frame, layers: &[ReferenceLayer<'_>]) -> Vec<[u8; 4]> {
    let (w, h) = (frame.width.max(1), frame.height.max(1));
    let mut key = vec![0u32; (w * h) as usize];
    let mut colour = vec![0u32; (w * h) as usize];
    // Depth pass over every layer, then the colour pass, as on the GPU.
    for depth_pass in [true, false] {
        for l in layers {
            let p = LayerParams::of(l.colouring, l.filter, |i| i < l.cloud.scalars.len());
            let offset = (l.cloud.origin - frame.reference).as_vec3();
            for (i, &pos) in l.cloud.positions.iter().enumerate() {
                if let Some(t) = p.filter_scalar.map(|s| l.cloud.scalars[s].values[i]) {
                    if !keeps(t, p.threshold) {
                        continue;
                    }
                }
                let Some(f) = footprint(frame, offset, pos) else {
                    continue;
                };
                let c = pack(point_colour(&p, l.cloud, i));
                for y in f.lo[1]..=f.hi[1] {
                    for x in f.lo[0]..=f.hi[0] {
                        if frame.round && !f.covers(x, y) {
                            continue;
                        }
                        let at = (y * w as i32 + x) as usize;
                        if depth_pass {
                            key[at] = key[at].max(f.key);
                        } else if key[at] == f.key {
                            colour[at] = colour[at].max(c);
                        }
                    }
                }
            }
        }
    }
    let background = pack(frame.background.map(|v| v as f32));
    key.iter()
        .zip(&colour)
        .map(|(&k, &c)| {
            let mut px = if k == 0 { background } else { c }.to_le_bytes();
            px[3] = 255;
            px
        })
        .collect()
}

struct Footprint {
    key: u32,
    centre: [f32; 2],
    half: f32,
    lo: [i32; 2],
    hi: [i32; 2],
}

impl Footprint {
    fn covers(&self, x: i32, y: i32) -> bool {
        let cx = (x as f32 + 0.5 - self.centre[0]) / self.half;
        let cy = (y as f32 + 0.5 - self.centre[1]) / self.half;
        cx * cx + cy * cy <= 1.0
    }
}

fn footprint(frame: &Frame, offset: Vec3, p: [f32; 3]) -> Option<Footprint> {
    let clip = frame.view_proj * (Vec3::from_array(p) + offset).extend(1.0);
    if clip.w.is_nan() || clip.w <= 0.0 {
        return None;
    }
    let ndc = clip.truncate() / clip.w;
    if !(0.0..1.0).contains(&ndc.z) {
        return None;
    }
    let size = [frame.width.max(1) as f32, frame.height.max(1) as f32];
    let centre = [(ndc.x * 0.5 + 0.5) * size[0], (0.5 - ndc.y * 0.5) * size[1]];
    let half = 0.5 * frame.point_size.max(0.5);
    let mut lo = [0; 2];
    let mut hi = [0; 2];
    for a in 0..2 {
        lo[a] = (centre[a] - half - 0.5).ceil().clamp(0.0, size[a]) as i32;
        hi[a] = ((centre[a] + half - 0.5).ceil() - 1.0).clamp(-1.0, size[a] - 1.0) as i32;
        if lo[a] > hi[a] {
            return None;
        }
    }
    Some(Footprint {
        key: !(ndc.z.to_bits() & 0x7fff_ffff),
        centre,
        half,
        lo,
        hi,
    })
}

fn point_colour(p: &LayerParams, cloud: &ViewCloud, i: usize) -> [f32; 3] {
    match (p.mode, p.colour_scalar) {
        (0, _) => {
            let b = cloud.colours[i].to_le_bytes();
            [b[0], b[1], b[2]].map(|v| v as f32 / 255.0)
        }
        (1, Some(s)) => map_colour(cloud.scalars[s].values[i], p.lo, p.hi, p.above),
        _ => p.solid,
    }
}

/// WGSL's `pack4x8unorm` with alpha 1.
fn pack(c: [f32; 3]) -> u32 {
    let b = c.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8);
    u32::from_le_bytes([b[0], b[1], b[2], 255])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::viewer::turbo;

    #[test]
    fn pack_matches_wgsl_rounding() {
        assert_eq!(pack([0.0, 1.0, 0.5]).to_le_bytes(), [0, 255, 128, 255]);
        assert_eq!(
            pack([-1.0, 2.0, 1.0 / 255.0]).to_le_bytes(),
            [0, 255, 1, 255]
        );
        // turbo's ends are inside [0, 1] after its clamp.
        assert!(turbo(1.0).iter().all(|v| (0.0..=1.0).contains(v)));
    }
}
