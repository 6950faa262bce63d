//! Multi-view triangulation of a track from known (prior or refined) poses, with COLMAP's filters:
//! reprojection error, triangulation angle and cheirality.
//!
//! Rays rather than pixels: every camera model of the crate unprojects a pixel to a unit ray, so the
//! linear step (the point nearest all rays, least squares) is the same for fisheye and pinhole images.
//! Gauss–Newton on the reprojection error then refines the point in pixels. A track can hold a wrong
//! match, and the prior can hold a keyframe with a gross pose error, so the views are chosen by a small
//! exhaustive RANSAC over view pairs before the refit.

use glam::{DMat3, DVec2, DVec3};

use crate::camera::CameraModel;
use crate::geometry::Se3;

/// One observation of a track with its camera.
#[derive(Clone, Copy, Debug)]
pub struct View<'a> {
    pub model: &'a CameraModel,
    /// `model.valid_angle()`, hoisted by the caller.
    pub max_angle: f64,
    pub t_cam_world: Se3,
    pub uv: DVec2,
    /// Unit ray of `uv` in the world frame.
    pub ray: DVec3,
    /// Camera centre in the world frame.
    pub centre: DVec3,
}

impl<'a> View<'a> {
    /// `None` where the pixel does not unproject (outside the model's valid angle).
    pub fn new(
        model: &'a CameraModel,
        max_angle: f64,
        t_world_cam: &Se3,
        uv: DVec2,
    ) -> Option<Self> {
        let d = model.unproject_within(uv, max_angle)?.normalize();
        Some(View {
            model,
            max_angle,
            t_cam_world: t_world_cam.inverse(),
            uv,
            ray: t_world_cam.transform_vector(d),
            centre: t_world_cam.trans,
        })
    }

    /// Reprojection error (px) of `x`, `None` behind the camera or outside the valid angle.
    pub fn error(&self, x: DVec3) -> Option<f64> {
        let p = self.t_cam_world.transform_point(x);
        if p.z <= 0.0 && self.max_angle < std::f64::consts::FRAC_PI_2 {
            return None;
        }
        let uv = self.model.project_within(p, self.max_angle)?;
        Some(uv.distance(self.uv))
    }
}

/// Triangulation gates (COLMAP's mapper defaults).
#[derive(Clone, Debug)]
pub struct TriangulateOptions {
    pub max_error_px: f64,
    pub min_angle_deg: f64,
}

impl Default for TriangulateOptions {
    fn default() -> Self {
        TriangulateOptions {
            max_error_px: 4.0,
            min_angle_deg: 1.5,
        }
    }
}

/// The point nearest all rays in the least-squares sense; `None` when the rays are (nearly) parallel.
pub fn midpoint(views: &[View]) -> Option<DVec3> {
    let mut a = DMat3::ZERO;
    let mut b = DVec3::ZERO;
    for v in views {
        let d = v.ray;
        let m = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += m;
        b += m * v.centre;
    }
    let det = a.determinant();
    if !det.is_finite() || det.abs() < 1e-12 {
        return None;
    }
    let x = a.inverse() * b;
    x.is_finite().then_some(x)
}

/// Gauss–Newton on the reprojection error with the poses fixed (a few steps from the midpoint).
pub fn refine(mut x: DVec3, views: &[View]) -> DVec3 {
    for _ in 0..5 {
        let mut h = DMat3::ZERO;
        let mut g = DVec3::ZERO;
        let mut used = 0;
        for v in views {
            let p = v.t_cam_world.transform_point(x);
            let Some((uv, j)) = v.model.project_jacobian_within(p, v.max_angle) else {
                continue;
            };
            let r = uv - v.uv;
            let rot = v.t_cam_world.rotation_matrix();
            // d(uv)/d(x) = J_proj * R_cam_world, rows as vectors.
            let jr0 = rot.transpose() * DVec3::from_array(j[0]);
            let jr1 = rot.transpose() * DVec3::from_array(j[1]);
            h += DMat3::from_cols(jr0 * jr0.x, jr0 * jr0.y, jr0 * jr0.z)
                + DMat3::from_cols(jr1 * jr1.x, jr1 * jr1.y, jr1 * jr1.z);
            g += jr0 * r.x + jr1 * r.y;
            used += 1;
        }
        if used < 2 {
            break;
        }
        let det = h.determinant();
        if !det.is_finite() || det.abs() < 1e-18 {
            break;
        }
        let step = h.inverse() * g;
        if !step.is_finite() {
            break;
        }
        x -= step;
        if step.length() < 1e-9 * x.length().max(1.0) {
            break;
        }
    }
    x
}

/// Largest angle (degrees) between the rays from the views' centres to `x`.
pub fn triangulation_angle(x: DVec3, views: &[View]) -> f64 {
    let dirs: Vec<DVec3> = views.iter().map(|v| (x - v.centre).normalize()).collect();
    let mut best: f64 = 0.0;
    for i in 0..dirs.len() {
        for j in i + 1..dirs.len() {
            best = best.max(dirs[i].angle_between(dirs[j]));
        }
    }
    best.to_degrees()
}

/// A triangulated track: the point and which views agree with it.
#[derive(Clone, Debug)]
pub struct Triangulated {
    pub point: DVec3,
    pub inliers: Vec<bool>,
    pub mean_error_px: f64,
}

/// Triangulates one track: every pair of views (up to 12 views; the first 66 pairs beyond) proposes a
/// point, the one most views agree with (then the lowest error) is refitted on its inliers. `None` when
/// fewer than two views agree within `max_error_px` or their widest angle is below `min_angle_deg`.
pub fn triangulate(views: &[View], opts: &TriangulateOptions) -> Option<Triangulated> {
    if views.len() < 2 {
        return None;
    }
    let score = |x: DVec3| -> (usize, f64, Vec<bool>) {
        let mut n = 0;
        let mut sum = 0.0;
        let inl: Vec<bool> = views
            .iter()
            .map(|v| match v.error(x) {
                Some(e) if e <= opts.max_error_px => {
                    n += 1;
                    sum += e;
                    true
                }
                _ => false,
            })
            .collect();
        (n, sum, inl)
    };
    let cap = views.len().min(12);
    let mut best: Option<(usize, f64, Vec<bool>)> = None;
    for i in 0..cap {
        for j in i + 1..cap {
            let pair = [views[i], views[j]];
            if pair[0].ray.angle_between(pair[1].ray).to_degrees() < opts.min_angle_deg * 0.5 {
                continue;
            }
            let Some(x) = midpoint(&pair) else { continue };
            let s = score(x);
            let better = match &best {
                None => true,
                Some(b) => s.0 > b.0 || (s.0 == b.0 && s.1 < b.1),
            };
            if better {
                best = Some(s);
            }
        }
    }
    let (n, _, inl) = best?;
    if n < 2 {
        return None;
    }
    // Refit on the inliers, then take the final inlier set from the refined point.
    let mut inl = inl;
    let mut point = DVec3::ZERO;
    for _ in 0..2 {
        let chosen: Vec<View> = views
            .iter()
            .zip(&inl)
            .filter(|(_, &k)| k)
            .map(|(v, _)| *v)
            .collect();
        let x0 = midpoint(&chosen)?;
        point = refine(x0, &chosen);
        let (n, _, new_inl) = score(point);
        if n < 2 {
            return None;
        }
        if new_inl == inl {
            break;
        }
        inl = new_inl;
    }
    let chosen: Vec<View> = views
        .iter()
        .zip(&inl)
        .filter(|(_, &k)| k)
        .map(|(v, _)| *v)
        .collect();
    if chosen.len() < 2 || triangulation_angle(point, &chosen) < opts.min_angle_deg {
        return None;
    }
    let errs: Vec<f64> = chosen.iter().filter_map(|v| v.error(point)).collect();
    let mean_error_px = errs.iter().sum::<f64>() / errs.len().max(1) as f64;
    Some(Triangulated {
        point,
        inliers: inl,
        mean_error_px,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Distortion;
    use glam::DQuat;

    fn fisheye() -> CameraModel {
        CameraModel {
            width: 360,
            height: 270,
            fx: 175.0,
            fy: 175.0,
            cx: 179.5,
            cy: 134.5,
            distortion: Distortion::Fisheye {
                k1: -0.04,
                k2: -0.002,
                k3: 0.003,
                k4: -0.002,
            },
        }
    }

    /// Five fisheye views of a point along a path: exact pixels triangulate back to the point; one view
    /// with a wrong pixel is left out of the inliers; rays too parallel are refused.
    #[test]
    fn recovers_point_rejects_outlier_view_and_narrow_angles() {
        let m = fisheye();
        let amax = m.valid_angle();
        let x = DVec3::new(0.7, -0.4, 6.0);
        let poses: Vec<Se3> = (0..5)
            .map(|k| {
                Se3::new(
                    DQuat::from_rotation_y(0.05 * k as f64),
                    DVec3::new(0.4 * k as f64, 0.02 * k as f64, 0.0),
                )
            })
            .collect();
        let mut views: Vec<View> = poses
            .iter()
            .map(|p| {
                let uv = m.project(p.inverse().transform_point(x)).unwrap();
                View::new(&m, amax, p, uv).unwrap()
            })
            .collect();
        let t = triangulate(&views, &TriangulateOptions::default()).unwrap();
        assert!(t.point.distance(x) < 1e-6, "{:?}", t.point);
        assert!(t.inliers.iter().all(|&k| k));
        // Corrupt view 2 by 20 px.
        let p2 = poses[2];
        views[2] = View::new(&m, amax, &p2, views[2].uv + DVec2::new(20.0, 0.0)).unwrap();
        let t = triangulate(&views, &TriangulateOptions::default()).unwrap();
        assert_eq!(t.inliers, vec![true, true, false, true, true]);
        assert!(t.point.distance(x) < 1e-6, "{:?}", t.point);
        // Two views 1 cm apart seeing a point 6 m away: 0.1°, refused.
        let near = [
            poses[0],
            Se3::new(DQuat::IDENTITY, DVec3::new(0.01, 0.0, 0.0)),
        ];
        let v: Vec<View> = near
            .iter()
            .map(|p| {
                View::new(
                    &m,
                    amax,
                    p,
                    m.project(p.inverse().transform_point(x)).unwrap(),
                )
                .unwrap()
            })
            .collect();
        assert!(triangulate(&v, &TriangulateOptions::default()).is_none());
    }

    /// Gauss–Newton in pixels beats the midpoint when the pixels are noisy: the refined point's
    /// reprojection error is no larger than the midpoint's.
    #[test]
    fn refinement_lowers_reprojection_error() {
        let m = fisheye();
        let amax = m.valid_angle();
        let x = DVec3::new(-1.0, 0.3, 4.0);
        let noise = [
            DVec2::new(0.7, -0.3),
            DVec2::new(-0.5, 0.6),
            DVec2::new(0.2, 0.9),
        ];
        let views: Vec<View> = (0..3)
            .map(|k| {
                // Very different distances to the point: the midpoint weighs metres, not pixels.
                let c = [
                    DVec3::ZERO,
                    DVec3::new(0.5, 0.0, 2.8),
                    DVec3::new(1.0, 0.0, -4.0),
                ][k];
                let p = Se3::new(DQuat::IDENTITY, c);
                let uv = m.project(p.inverse().transform_point(x)).unwrap() + noise[k];
                View::new(&m, amax, &p, uv).unwrap()
            })
            .collect();
        let x0 = midpoint(&views).unwrap();
        let x1 = refine(x0, &views);
        let sse = |x: DVec3| {
            views
                .iter()
                .map(|v| v.error(x).unwrap().powi(2))
                .sum::<f64>()
        };
        assert!(sse(x1) <= sse(x0) + 1e-12, "{} vs {}", sse(x1), sse(x0));
        assert!(
            sse(x1) < 0.9 * sse(x0),
            "refinement should help: {} vs {}",
            sse(x1),
            sse(x0)
        );
    }
}
