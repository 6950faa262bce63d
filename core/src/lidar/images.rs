//! The encodings of the per-camera lidar images, identical to the Oxford Spires tools that SiLVR reads:
//! - depth: 16-bit PNG, value = floor(range_m x 256) (Euclidean range from the camera centre), 0 = no
//!   return; [`SKY_DEPTH`] (65535, i.e. >= 250 m, SiLVR's sky threshold) marks sky pixels;
//! - normals: 8-bit RGB PNG, value = (n + 1) / 2 x 255 with n the unit normal in the camera's OpenCV frame
//!   facing the camera; (128, 128, 128) = none.

use glam::DVec3;

use super::project::{Projection, NONE};
use crate::geometry::Se3;

/// Depth units per metre.
pub const DEPTH_SCALE: f32 = 256.0;
/// The depth value that marks sky.
pub const SKY_DEPTH: u16 = u16::MAX;
/// The normal pixel that marks "no normal".
pub const NO_NORMAL: [u8; 3] = [128, 128, 128];

/// Encodes a range (m) as a depth pixel; ranges that do not fit (>= 255.996 m) or are not positive give 0.
pub fn encode_depth(range: f32) -> u16 {
    let v = (range * DEPTH_SCALE).floor();
    if range > 0.0 && v < SKY_DEPTH as f32 {
        v as u16
    } else {
        0
    }
}

/// Decodes a depth pixel: `None` for no return or sky.
pub fn decode_depth(v: u16) -> Option<f32> {
    (v != 0 && v != SKY_DEPTH).then(|| v as f32 / DEPTH_SCALE)
}

/// Encodes a unit normal; non-finite or zero normals give [`NO_NORMAL`].
pub fn encode_normal(n: DVec3) -> [u8; 3] {
    if !n.is_finite() || n.length_squared() < 0.25 {
        return NO_NORMAL;
    }
    // A unit vector cannot encode to the sentinel: that needs all three components near 0.
    n.normalize()
        .to_array()
        .map(|c| ((c + 1.0) * 0.5 * 255.0).round().clamp(0.0, 255.0) as u8)
}

/// Decodes a normal pixel (unit length), or `None` for [`NO_NORMAL`].
pub fn decode_normal(px: [u8; 3]) -> Option<DVec3> {
    if px == NO_NORMAL {
        return None;
    }
    let n = DVec3::from_array(px.map(|c| c as f64 / 255.0 * 2.0 - 1.0));
    (n.length() > 1e-6).then(|| n.normalize())
}

/// Sparse depth and normal images of one camera from a projection of the (deskewed) sweep `points`.
/// `normals` are per-point normals in the points' frame; `t_cam_points` maps that frame into the camera.
/// Normals are flipped to face the camera (the sensor-facing lidar normal can face away from a camera
/// mounted a few centimetres off the lidar only at grazing angles, but the loss expects camera-facing).
pub fn lidar_images(
    proj: &Projection,
    points: &[DVec3],
    normals: &[DVec3],
    t_cam_points: &Se3,
) -> (Vec<u16>, Vec<[u8; 3]>) {
    let mut depth = vec![0u16; proj.winner.len()];
    let mut normal = vec![NO_NORMAL; proj.winner.len()];
    for (pix, &w) in proj.winner.iter().enumerate() {
        if w == NONE {
            continue;
        }
        depth[pix] = encode_depth(proj.range[pix]);
        if depth[pix] == 0 {
            continue;
        }
        let (Some(n), Some(p)) = (normals.get(w as usize), points.get(w as usize)) else {
            continue;
        };
        let mut nc = t_cam_points.transform_vector(*n);
        if nc.dot(t_cam_points.transform_point(*p)) > 0.0 {
            nc = -nc;
        }
        normal[pix] = encode_normal(nc);
    }
    (depth, normal)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_and_normal_encodings_round_trip() {
        assert_eq!(encode_depth(0.0), 0);
        assert_eq!(encode_depth(-1.0), 0);
        assert_eq!(encode_depth(1.0), 256);
        assert_eq!(encode_depth(300.0), 0, "beyond the encodable range");
        assert_eq!(
            decode_depth(encode_depth(12.3456)).unwrap(),
            (12.3456f32 * 256.0).floor() / 256.0
        );
        assert_eq!(decode_depth(SKY_DEPTH), None);
        let n = DVec3::new(0.3, -0.5, -0.8).normalize();
        let back = decode_normal(encode_normal(n)).unwrap();
        assert!(back.angle_between(n) < 0.01);
        assert_eq!(encode_normal(DVec3::NAN), NO_NORMAL);
        assert_eq!(decode_normal(NO_NORMAL), None);
    }
}
