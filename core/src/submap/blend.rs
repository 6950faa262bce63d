//! Rendering across submaps (the paper's merging section, after Block-NeRF): a camera on a path is
//! rendered by the submap whose training cameras are nearest, and near a boundary blended in image space
//! with the second nearest, weighted by the two distances.
//!
//! Distances are 3-D, from the path camera's centre to the nearest training camera centre of each submap
//! (SiLVR's code measures them in the ground plane; 3-D is the same on a street and right between floors).

use glam::DVec3;
use serde::{Deserialize, Serialize};

/// SiLVR's blend radius (m): the second-nearest submap joins when its cameras are this close.
pub const BLEND_RADIUS_M: f64 = 2.0;

/// Block-NeRF's inverse-distance power.
pub const IDW_POWER: f64 = 4.0;

/// How the nearest submap's render is weighted against the second nearest's.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BlendRule {
    /// The nearest submap alone (SiLVR's default).
    Nearest,
    /// SiLVR's optional blend: α = (R − d₁ + 0.1) / (2R − d₁ − d₂ + 0.2) when d₂ < R.
    Silvr { radius: f64 },
    /// Block-NeRF's inverse-distance weights over the two nearest within `radius`: wᵢ ∝ dᵢ^−p.
    InverseDistance { radius: f64, power: f64 },
}

impl BlendRule {
    /// Weight α of the nearest render (the second nearest gets 1 − α), from the distances d₁ ≤ d₂ of the
    /// two nearest submaps; 1 when there is no second within the radius.
    pub fn alpha(self, d1: f64, d2: Option<f64>) -> f64 {
        let Some(d2) = d2.filter(|d| d.is_finite()) else {
            return 1.0;
        };
        match self {
            Self::Nearest => 1.0,
            Self::Silvr { radius } if d2 < radius => {
                (radius - d1 + 0.1) / (2.0 * radius - d1 - d2 + 0.2)
            }
            Self::InverseDistance { radius, power } if d2 < radius => {
                if d2 <= 0.0 {
                    0.5
                } else {
                    1.0 / (1.0 + (d1 / d2).powf(power))
                }
            }
            _ => 1.0,
        }
    }
}

/// Distance from `c` to the nearest of `cameras` (+∞ for none).
pub fn distance_to(cameras: &[DVec3], c: DVec3) -> f64 {
    cameras
        .iter()
        .map(|p| p.distance(c))
        .fold(f64::INFINITY, f64::min)
}

/// A submap and a distance to it (m).
pub type Near = (usize, f64);

/// The nearest submap of a camera at `c` and the second nearest; `None` when no submap has a camera.
/// Ties go to the lower index.
pub fn nearest_two(submaps: &[Vec<DVec3>], c: DVec3) -> Option<(Near, Option<Near>)> {
    let mut d: Vec<Near> = submaps
        .iter()
        .enumerate()
        .map(|(k, cams)| (k, distance_to(cams, c)))
        .filter(|(_, d)| d.is_finite())
        .collect();
    d.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
    let first = *d.first()?;
    Some((first, d.get(1).copied()))
}

/// α·a + (1 − α)·b per pixel, rounded.
pub fn blend_rgb(a: &[[u8; 3]], b: &[[u8; 3]], alpha: f64) -> Vec<[u8; 3]> {
    let alpha = alpha.clamp(0.0, 1.0) as f32;
    a.iter()
        .zip(b)
        .map(|(x, y)| {
            std::array::from_fn(|c| {
                (alpha * x[c] as f32 + (1.0 - alpha) * y[c] as f32)
                    .round()
                    .clamp(0.0, 255.0) as u8
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn silvr_weights_are_even_at_the_seam_and_favour_the_nearer_submap() {
        let r = BlendRule::Silvr { radius: 2.0 };
        assert!((r.alpha(0.7, Some(0.7)) - 0.5).abs() < 1e-12);
        // SiLVR's formula by hand: d1 = 0.5, d2 = 1.5 → (2 − 0.5 + 0.1)/(4 − 2 + 0.2) = 1.6/2.2.
        assert!((r.alpha(0.5, Some(1.5)) - 1.6 / 2.2).abs() < 1e-12);
        // Beyond the radius, or with no second submap, the nearest alone.
        assert_eq!(r.alpha(0.5, Some(2.5)), 1.0);
        assert_eq!(r.alpha(0.5, None), 1.0);
        assert_eq!(BlendRule::Nearest.alpha(0.5, Some(0.6)), 1.0);
        // Always in (0.5, 1] for d1 ≤ d2.
        for i in 0..20 {
            for j in i..20 {
                let (d1, d2) = (i as f64 * 0.1, j as f64 * 0.1);
                let a = r.alpha(d1, Some(d2));
                assert!((0.5 - 1e-12..=1.0).contains(&a), "{d1} {d2} {a}");
            }
        }
    }

    #[test]
    fn inverse_distance_weights_follow_block_nerf() {
        let r = BlendRule::InverseDistance {
            radius: 2.0,
            power: 4.0,
        };
        // w1/w2 = (d2/d1)^4 = 16 at d1 = 0.5, d2 = 1.
        let a = r.alpha(0.5, Some(1.0));
        assert!((a / (1.0 - a) - 16.0).abs() < 1e-9, "{a}");
        assert_eq!(r.alpha(0.0, Some(1.0)), 1.0);
        assert_eq!(r.alpha(0.0, Some(0.0)), 0.5);
        assert_eq!(r.alpha(0.5, Some(3.0)), 1.0);
    }

    #[test]
    fn nearest_two_orders_submaps_by_their_closest_camera() {
        let subs = vec![
            vec![DVec3::new(0.0, 0.0, 0.0), DVec3::new(1.0, 0.0, 0.0)],
            vec![DVec3::new(3.0, 0.0, 0.0)],
            vec![],
            vec![DVec3::new(1.5, 0.0, 0.0)],
        ];
        let ((k1, d1), second) = nearest_two(&subs, DVec3::new(1.2, 0.0, 0.0)).unwrap();
        let (k2, d2) = second.unwrap();
        assert_eq!((k1, k2), (0, 3));
        assert!((d1 - 0.2).abs() < 1e-12 && (d2 - 0.3).abs() < 1e-12);
        assert!(nearest_two(&[vec![]], DVec3::ZERO).is_none());
        let only = nearest_two(&subs[1..2], DVec3::ZERO).unwrap();
        assert!(only.1.is_none());
    }

    #[test]
    fn blend_is_the_weighted_mean_per_pixel() {
        let a = vec![[200, 0, 100], [10, 20, 30]];
        let b = vec![[0, 200, 100], [30, 20, 10]];
        assert_eq!(blend_rgb(&a, &b, 1.0), a);
        assert_eq!(blend_rgb(&a, &b, 0.0), b);
        assert_eq!(blend_rgb(&a, &b, 0.75), vec![[150, 50, 100], [15, 20, 25]]);
    }
}
