//! Camera models: pinhole, OpenCV radial-tangential and OpenCV fisheye (Kannala-Brandt).
//!
//! All maths is f64 and follows the OpenCV conventions of the crate (x right, y down, z forward; the centre
//! of the top-left pixel is (0, 0)), so the numbers match `cv2.projectPoints` / `cv2.fisheye.projectPoints`
//! for the same intrinsics.
//!
//! **Valid angle.** Every model has a largest accepted angle θ between a ray and the optical axis
//! ([`CameraModel::valid_angle`]). Beyond it a distortion polynomial can fold back onto the image and map
//! far-away rays onto valid pixels (the classic "ghost points" of projecting lidar through a fitted
//! fisheye), so [`CameraModel::project`] rejects such points and [`CameraModel::unproject`] never returns
//! them. `project`, `unproject` and `project_jacobian` recompute the limit on each call (no cache fits in
//! the plain-data [`CameraModel`]); hot loops should compute `valid_angle()` once and call the `*_within`
//! variants.

use glam::{DMat4, DVec2, DVec3, DVec4};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Lens distortion of a [`CameraModel`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "model", rename_all = "snake_case")]
pub enum Distortion {
    /// Ideal pinhole (COLMAP `PINHOLE`).
    None,
    /// OpenCV radial-tangential (COLMAP `OPENCV` + k3, ROS `plumb_bob`).
    RadTan {
        k1: f64,
        k2: f64,
        p1: f64,
        p2: f64,
        k3: f64,
    },
    /// OpenCV fisheye / Kannala-Brandt equidistant (COLMAP `OPENCV_FISHEYE`, ROS `equidistant`).
    Fisheye { k1: f64, k2: f64, k3: f64, k4: f64 },
}

/// Intrinsics of one camera, OpenCV pixel convention (top-left pixel centre at (0, 0)).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraModel {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub distortion: Distortion,
}

/// Why a [`CameraModel`] is unusable.
#[derive(Clone, Debug, PartialEq, Error)]
pub enum CameraError {
    #[error("image size must be non-zero, got {width}x{height}")]
    ZeroSize { width: u32, height: u32 },
    #[error("focal lengths must be finite and positive, got fx={fx}, fy={fy}")]
    BadFocalLength { fx: f64, fy: f64 },
    #[error("principal point must be finite, got cx={cx}, cy={cy}")]
    BadPrincipalPoint { cx: f64, cy: f64 },
    #[error("distortion coefficients must be finite: {0:?}")]
    BadDistortion(Distortion),
}

/// Cap (b) for pinhole and rad-tan: the perspective division blows up at 90°.
pub const PERSPECTIVE_MAX_ANGLE: f64 = 89.9 * std::f64::consts::PI / 180.0;
/// Cap (b) for the fisheye: the equidistant model is defined up to 180°, where the azimuth is undefined.
pub const FISHEYE_MAX_ANGLE: f64 = 179.0 * std::f64::consts::PI / 180.0;
/// Margin (c) added to the widest border ray, so points just outside the image still project (useful for
/// splats and for Jacobians at the border) without admitting the folded region far outside it.
pub const BORDER_MARGIN: f64 = 5.0 * std::f64::consts::PI / 180.0;
/// Grid steps of the monotonicity scan (a); the crossing is then refined by bisection.
const MONOTONIC_SCAN_STEPS: usize = 2000;
/// Samples per image edge (corners included) for the border angle (c).
const BORDER_SAMPLES_PER_EDGE: usize = 8;
/// Iteration cap of the distortion inversions.
const MAX_ITERS: usize = 100;

/// 2x3 Jacobian d(u, v)/d(X, Y, Z), row-major.
pub type Jacobian2x3 = [[f64; 3]; 2];

impl CameraModel {
    /// Ideal pinhole camera.
    pub fn pinhole(width: u32, height: u32, fx: f64, fy: f64, cx: f64, cy: f64) -> Self {
        Self {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            distortion: Distortion::None,
        }
    }

    /// Pixel coordinates of a camera-frame point, or `None` when it lies outside the model's valid angle.
    pub fn project(&self, p: DVec3) -> Option<DVec2> {
        self.project_within(p, self.valid_angle())
    }

    /// [`Self::project`] with a caller-supplied angle limit (normally a hoisted `valid_angle()`; larger
    /// values are only meaningful up to [`Self::invertible_angle`]).
    pub fn project_within(&self, p: DVec3, max_angle: f64) -> Option<DVec2> {
        let d = self.distort(p, max_angle, false)?.0;
        Some(DVec2::new(self.fx * d.x + self.cx, self.fy * d.y + self.cy))
    }

    /// Projection and its analytic Jacobian d(u, v)/d(X, Y, Z) (rows u, v), used for ray footprints and
    /// Gaussian-splat covariance projection. `None` where [`Self::project`] is `None`.
    pub fn project_jacobian(&self, p: DVec3) -> Option<(DVec2, Jacobian2x3)> {
        self.project_jacobian_within(p, self.valid_angle())
    }

    /// [`Self::project_jacobian`] with a caller-supplied angle limit.
    pub fn project_jacobian_within(
        &self,
        p: DVec3,
        max_angle: f64,
    ) -> Option<(DVec2, Jacobian2x3)> {
        let (d, jd) = self.distort(p, max_angle, true)?;
        let uv = DVec2::new(self.fx * d.x + self.cx, self.fy * d.y + self.cy);
        let j = [
            [self.fx * jd[0][0], self.fx * jd[0][1], self.fx * jd[0][2]],
            [self.fy * jd[1][0], self.fy * jd[1][1], self.fy * jd[1][2]],
        ];
        Some((uv, j))
    }

    /// Unit ray direction (camera frame) through pixel `px`, or `None` if the distortion cannot be inverted
    /// there within the valid angle.
    pub fn unproject(&self, px: DVec2) -> Option<DVec3> {
        self.unproject_within(px, self.valid_angle())
    }

    /// [`Self::unproject`] with a caller-supplied angle limit (normally a hoisted `valid_angle()`).
    pub fn unproject_within(&self, px: DVec2, max_angle: f64) -> Option<DVec3> {
        if !px.is_finite() || max_angle.is_nan() || max_angle < 0.0 {
            return None;
        }
        let xd = (px.x - self.cx) / self.fx;
        let yd = (px.y - self.cy) / self.fy;
        match self.distortion {
            Distortion::None => perspective_ray(xd, yd, max_angle),
            Distortion::RadTan { .. } => {
                let (x, y) = self.undistort_radtan(xd, yd)?;
                perspective_ray(x, y, max_angle)
            }
            Distortion::Fisheye { k1, k2, k3, k4 } => {
                let theta_d = xd.hypot(yd);
                if theta_d == 0.0 {
                    return Some(DVec3::Z);
                }
                let theta =
                    invert_fisheye(theta_d, max_angle.min(FISHEYE_MAX_ANGLE), [k1, k2, k3, k4])?;
                let (s, c) = theta.sin_cos();
                Some(DVec3::new(s * xd / theta_d, s * yd / theta_d, c))
            }
        }
    }

    /// Largest accepted angle between a ray and the optical axis, in radians.
    ///
    /// Rule: the minimum of
    /// - (a) the first angle where the radial mapping stops being monotonic (fisheye: dθd/dθ ≤ 0; rad-tan:
    ///   d(r·radial(r))/dr ≤ 0 with r = tan θ, tangential terms ignored), found by a fixed
    ///   [`MONOTONIC_SCAN_STEPS`]-step scan refined by bisection. Past it two rays share a pixel.
    /// - (b) a per-model cap: [`PERSPECTIVE_MAX_ANGLE`] (89.9°) for pinhole/rad-tan, [`FISHEYE_MAX_ANGLE`]
    ///   (179°) for the fisheye.
    /// - (c) the widest ray through the image border (edges sampled at pixel coordinates -0.5 and
    ///   size-0.5, corners included) plus [`BORDER_MARGIN`] (5°); skipped when some border pixel is already
    ///   beyond (a)/(b).
    ///
    /// Deterministic and f64 only. It costs ~13 µs (Spires fisheye, release build), so hot loops hoist it and
    /// call the `*_within` variants.
    pub fn valid_angle(&self) -> f64 {
        let invertible = self.invertible_angle();
        match self.border_angle(invertible) {
            Some(b) => (b + BORDER_MARGIN).min(invertible),
            None => invertible,
        }
    }

    /// Limits (a) and (b) of [`Self::valid_angle`]: the angle up to which the distortion is invertible.
    pub fn invertible_angle(&self) -> f64 {
        let cap = self.model_max_angle();
        let step = cap / MONOTONIC_SCAN_STEPS as f64;
        for i in 1..=MONOTONIC_SCAN_STEPS {
            let theta = step * i as f64;
            let slope = self.radial_slope(theta);
            if slope.is_nan() || slope <= 0.0 {
                // The slope is positive at theta - step; bisect to the crossing, keeping the positive side.
                let (mut lo, mut hi) = (step * (i - 1) as f64, theta);
                for _ in 0..60 {
                    let mid = 0.5 * (lo + hi);
                    if self.radial_slope(mid) > 0.0 {
                        lo = mid;
                    } else {
                        hi = mid;
                    }
                }
                return lo;
            }
        }
        cap
    }

    /// Largest angle of a ray through the image border, or `None` if some border pixel cannot be
    /// unprojected within `limit`.
    pub fn border_angle(&self, limit: f64) -> Option<f64> {
        let (w, h) = (self.width as f64, self.height as f64);
        let n = BORDER_SAMPLES_PER_EDGE;
        let mut max_angle: f64 = 0.0;
        for i in 0..=n {
            let t = i as f64 / n as f64;
            let u = -0.5 + t * w;
            let v = -0.5 + t * h;
            for px in [
                DVec2::new(u, -0.5),
                DVec2::new(u, h - 0.5),
                DVec2::new(-0.5, v),
                DVec2::new(w - 0.5, v),
            ] {
                let ray = self.unproject_within(px, limit)?;
                max_angle = max_angle.max(ray_angle(ray));
            }
        }
        Some(max_angle)
    }

    /// Whether `uv` falls inside the image: `-0.5 <= u < width - 0.5`, same for v.
    pub fn in_image(&self, uv: DVec2) -> bool {
        uv.x >= -0.5
            && uv.x < self.width as f64 - 0.5
            && uv.y >= -0.5
            && uv.y < self.height as f64 - 0.5
    }

    /// Integer pixel containing `uv`: `(floor(u + 0.5), floor(v + 0.5))`, or `None` outside the image.
    pub fn pixel_of(&self, uv: DVec2) -> Option<(u32, u32)> {
        if !self.in_image(uv) {
            return None;
        }
        // The min() guards against u + 0.5 rounding up to `width` right at the border.
        let i = ((uv.x + 0.5).floor() as u32).min(self.width - 1);
        let j = ((uv.y + 0.5).floor() as u32).min(self.height - 1);
        Some((i, j))
    }

    /// The same camera after resizing the image by `factor` (0.5: half resolution). Sizes are rounded; the
    /// intrinsics use the per-axis ratios actually achieved (`width' / width`), with the OpenCV pixel-centre
    /// mapping `c' = (c + 0.5) * s - 0.5`, which is what `cv2.resize` does to pixel positions. Distortion
    /// coefficients act on normalised coordinates and are unchanged.
    ///
    /// # Panics
    /// If `factor` is not finite and positive.
    pub fn scaled(&self, factor: f64) -> CameraModel {
        assert!(
            factor.is_finite() && factor > 0.0,
            "scale factor must be finite and positive, got {factor}"
        );
        let width = ((self.width as f64 * factor).round() as u32).max(1);
        let height = ((self.height as f64 * factor).round() as u32).max(1);
        let sx = width as f64 / self.width as f64;
        let sy = height as f64 / self.height as f64;
        CameraModel {
            width,
            height,
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: (self.cx + 0.5) * sx - 0.5,
            cy: (self.cy + 0.5) * sy - 0.5,
            distortion: self.distortion,
        }
    }

    /// The camera of an image downscaled by the integer `f` the way the loader and `silvr pack` do it:
    /// each output pixel stands for an f×f block and the last `width mod f` columns (rows) are dropped, so
    /// the size is ⌊width / f⌋ and the mapping is exactly `c' = (c + 0.5) / f − 0.5` (a rounded size with
    /// [`Self::scaled`]'s achieved ratio would shift every ray of an image whose width is not a multiple).
    pub fn downscaled(&self, f: u32) -> CameraModel {
        let f = f.max(1);
        let s = 1.0 / f as f64;
        CameraModel {
            width: (self.width / f).max(1),
            height: (self.height / f).max(1),
            fx: self.fx * s,
            fy: self.fy * s,
            cx: (self.cx + 0.5) * s - 0.5,
            cy: (self.cy + 0.5) * s - 0.5,
            distortion: self.distortion,
        }
    }

    /// Checks that the intrinsics are usable (finite positive focal lengths, non-zero size, finite principal
    /// point and coefficients).
    pub fn validate(&self) -> Result<(), CameraError> {
        if self.width == 0 || self.height == 0 {
            return Err(CameraError::ZeroSize {
                width: self.width,
                height: self.height,
            });
        }
        if !(self.fx.is_finite() && self.fy.is_finite() && self.fx > 0.0 && self.fy > 0.0) {
            return Err(CameraError::BadFocalLength {
                fx: self.fx,
                fy: self.fy,
            });
        }
        if !(self.cx.is_finite() && self.cy.is_finite()) {
            return Err(CameraError::BadPrincipalPoint {
                cx: self.cx,
                cy: self.cy,
            });
        }
        let finite = match self.distortion {
            Distortion::None => true,
            Distortion::RadTan { k1, k2, p1, p2, k3 } => {
                [k1, k2, p1, p2, k3].iter().all(|c| c.is_finite())
            }
            Distortion::Fisheye { k1, k2, k3, k4 } => {
                [k1, k2, k3, k4].iter().all(|c| c.is_finite())
            }
        };
        if !finite {
            return Err(CameraError::BadDistortion(self.distortion));
        }
        Ok(())
    }

    /// COLMAP camera model name. COLMAP `OPENCV` has no k3, so rad-tan with `k3 != 0` needs `FULL_OPENCV`.
    pub fn colmap_name(&self) -> &'static str {
        match self.distortion {
            Distortion::None => "PINHOLE",
            Distortion::RadTan { k3, .. } if k3 != 0.0 => "FULL_OPENCV",
            Distortion::RadTan { .. } => "OPENCV",
            Distortion::Fisheye { .. } => "OPENCV_FISHEYE",
        }
    }

    /// COLMAP parameter list for [`Self::colmap_name`], with the principal point shifted by +0.5 because
    /// COLMAP puts the top-left pixel centre at (0.5, 0.5).
    pub fn colmap_params(&self) -> Vec<f64> {
        let mut p = vec![self.fx, self.fy, self.cx + 0.5, self.cy + 0.5];
        match self.distortion {
            Distortion::None => {}
            Distortion::RadTan { k1, k2, p1, p2, k3 } if k3 != 0.0 => {
                p.extend([k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]);
            }
            Distortion::RadTan { k1, k2, p1, p2, .. } => p.extend([k1, k2, p1, p2]),
            Distortion::Fisheye { k1, k2, k3, k4 } => p.extend([k1, k2, k3, k4]),
        }
        p
    }

    /// Cap (b) of [`Self::valid_angle`].
    fn model_max_angle(&self) -> f64 {
        match self.distortion {
            Distortion::None | Distortion::RadTan { .. } => PERSPECTIVE_MAX_ANGLE,
            Distortion::Fisheye { .. } => FISHEYE_MAX_ANGLE,
        }
    }

    /// Derivative of the radial mapping at ray angle `theta`; only its sign matters.
    fn radial_slope(&self, theta: f64) -> f64 {
        match self.distortion {
            Distortion::None => 1.0,
            Distortion::RadTan { k1, k2, k3, .. } => {
                let r2 = theta.tan().powi(2);
                1.0 + r2 * (3.0 * k1 + r2 * (5.0 * k2 + r2 * 7.0 * k3))
            }
            Distortion::Fisheye { k1, k2, k3, k4 } => fisheye_poly(theta, [k1, k2, k3, k4]).1,
        }
    }

    /// Normalised distorted coordinates (before fx, fy, cx, cy) and, if `with_jacobian`, their 2x3 Jacobian.
    fn distort(
        &self,
        p: DVec3,
        max_angle: f64,
        with_jacobian: bool,
    ) -> Option<(DVec2, Jacobian2x3)> {
        if !p.is_finite() {
            return None;
        }
        let r = p.x.hypot(p.y);
        match self.distortion {
            Distortion::None | Distortion::RadTan { .. } => {
                if p.z <= 0.0 || r.atan2(p.z) > max_angle {
                    return None;
                }
                let inv_z = 1.0 / p.z;
                let (x, y) = (p.x * inv_z, p.y * inv_z);
                let (d, j) = self.radtan(x, y);
                if !with_jacobian {
                    return Some((d, [[0.0; 3]; 2]));
                }
                // Chain rule through x = X/Z, y = Y/Z.
                let row = |a: f64, b: f64| [a * inv_z, b * inv_z, -(a * x + b * y) * inv_z];
                Some((d, [row(j[0][0], j[0][1]), row(j[1][0], j[1][1])]))
            }
            Distortion::Fisheye { k1, k2, k3, k4 } => {
                if r == 0.0 && p.z <= 0.0 {
                    return None; // origin, or straight behind where the azimuth is undefined
                }
                let theta = r.atan2(p.z);
                if theta > max_angle {
                    return None;
                }
                let ks = [k1, k2, k3, k4];
                let (g_over_theta, dg) = fisheye_poly(theta, ks);
                // theta / r, with the on-axis limit 1/Z (the series term keeps it exact to ~1e-32).
                let theta_over_r = if r > 1e-8 * p.z {
                    theta / r
                } else {
                    (1.0 - (r / p.z).powi(2) / 3.0) / p.z
                };
                // x_d = f * X, y_d = f * Y with f = theta_d / r.
                let f = theta_over_r * g_over_theta;
                let d = DVec2::new(f * p.x, f * p.y);
                if !with_jacobian {
                    return Some((d, [[0.0; 3]; 2]));
                }
                let rho2 = r * r + p.z * p.z;
                // h = (df/dr) / r. Near the axis the closed form cancels (and would divide by r^3), so use its
                // limit 2 (k1 - 1/3) / Z^3, accurate to O((r/Z)^2) in a term that is itself O(r^2).
                let h = if r > 1e-6 * p.z {
                    let g = theta * g_over_theta;
                    (dg * p.z * r / rho2 - g) / (r * r * r)
                } else {
                    2.0 * (k1 - 1.0 / 3.0) / p.z.powi(3)
                };
                let dz = -dg / rho2; // df/dZ
                let j = [
                    [f + p.x * p.x * h, p.x * p.y * h, p.x * dz],
                    [p.x * p.y * h, f + p.y * p.y * h, p.y * dz],
                ];
                Some((d, j))
            }
        }
    }

    /// OpenCV rad-tan distortion of normalised (x, y) and its 2x2 Jacobian (identity for the pinhole).
    fn radtan(&self, x: f64, y: f64) -> (DVec2, [[f64; 2]; 2]) {
        let (k1, k2, p1, p2, k3) = match self.distortion {
            Distortion::RadTan { k1, k2, p1, p2, k3 } => (k1, k2, p1, p2, k3),
            _ => return (DVec2::new(x, y), [[1.0, 0.0], [0.0, 1.0]]),
        };
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let dradial = k1 + r2 * (2.0 * k2 + r2 * 3.0 * k3); // d radial / d r2
        let xy = x * y;
        let d = DVec2::new(
            x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy,
        );
        let off = 2.0 * xy * dradial + 2.0 * p1 * x + 2.0 * p2 * y;
        let j = [
            [
                radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x,
                off,
            ],
            [
                off,
                radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x,
            ],
        ];
        (d, j)
    }

    /// Inverts the rad-tan distortion by damped Newton (no closed form exists). `None` when it does not
    /// converge or lands where the mapping is folded (non-positive Jacobian determinant).
    fn undistort_radtan(&self, xd: f64, yd: f64) -> Option<(f64, f64)> {
        let target = DVec2::new(xd, yd);
        let tol = 1e-14 * (1.0 + target.length());
        let mut x = target;
        let (d0, mut j) = self.radtan(x.x, x.y);
        let mut err = d0 - target;
        for _ in 0..MAX_ITERS {
            let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
            if err.length() <= tol {
                return (det > 0.0).then_some((x.x, x.y));
            }
            if !det.is_finite() || det <= 0.0 {
                return None;
            }
            let step = DVec2::new(
                -(j[1][1] * err.x - j[0][1] * err.y) / det,
                -(-j[1][0] * err.x + j[0][0] * err.y) / det,
            );
            // Backtrack until the residual shrinks, so a bad start far out cannot diverge.
            let mut alpha = 1.0;
            let mut accepted = false;
            for _ in 0..40 {
                let cand = x + alpha * step;
                let (dc, jc) = self.radtan(cand.x, cand.y);
                let ec = dc - target;
                if ec.length() < err.length() || ec.length() <= tol {
                    (x, j, err) = (cand, jc, ec);
                    accepted = true;
                    break;
                }
                alpha *= 0.5;
            }
            if !accepted {
                return None;
            }
        }
        None
    }
}

/// `(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸, dθd/dθ)` of the Kannala-Brandt polynomial, θd = θ·first.
fn fisheye_poly(theta: f64, [k1, k2, k3, k4]: [f64; 4]) -> (f64, f64) {
    let t2 = theta * theta;
    let g_over_theta = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)));
    let dg = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)));
    (g_over_theta, dg)
}

/// Solves θd = θ(1 + k1θ² + …) for θ in [0, max_theta] by Newton safeguarded with bisection, so it always
/// converges when a root is bracketed. `None` if θd lies beyond the image of `max_theta`.
fn invert_fisheye(theta_d: f64, max_theta: f64, ks: [f64; 4]) -> Option<f64> {
    let g = |t: f64| t * fisheye_poly(t, ks).0;
    let g_max = g(max_theta);
    if g_max.is_nan() || g_max < theta_d {
        return None;
    }
    let (mut lo, mut hi) = (0.0, max_theta);
    let mut theta = theta_d.min(max_theta);
    for _ in 0..MAX_ITERS {
        let (p, dg) = fisheye_poly(theta, ks);
        let f = theta * p - theta_d;
        if f == 0.0 {
            return Some(theta);
        }
        if f < 0.0 {
            lo = theta;
        } else {
            hi = theta;
        }
        let mut next = theta - f / dg;
        if !(next > lo && next < hi) {
            next = 0.5 * (lo + hi);
        }
        if (next - theta).abs() <= 2.0 * f64::EPSILON * theta || hi - lo <= 2.0 * f64::EPSILON * hi
        {
            return Some(next);
        }
        theta = next;
    }
    None
}

/// Unit ray through normalised undistorted coordinates (x, y), if within `max_angle` of the axis.
fn perspective_ray(x: f64, y: f64, max_angle: f64) -> Option<DVec3> {
    if x.hypot(y).atan() > max_angle {
        return None;
    }
    Some(DVec3::new(x, y, 1.0).normalize())
}

/// Angle between a (not necessarily unit) direction and the optical axis.
fn ray_angle(d: DVec3) -> f64 {
    d.x.hypot(d.y).atan2(d.z)
}

/// Converts a camera-to-world matrix between OpenCV camera axes (x right, y down, z forward) and OpenGL /
/// nerfstudio axes (x right, y up, z back) by negating the camera y and z columns. The flip is its own
/// inverse, so the same function converts back.
pub fn opencv_to_opengl_c2w(c2w: DMat4) -> DMat4 {
    c2w * DMat4::from_diagonal(DVec4::new(1.0, -1.0, -1.0, 1.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_xoshiro::Xoshiro256PlusPlus;
    use std::f64::consts::{FRAC_PI_2, PI};

    const DEG: f64 = PI / 180.0;

    /// Oxford Spires cam_front (cam0), 1440x1080 OPENCV_FISHEYE.
    fn spires_front() -> CameraModel {
        CameraModel {
            width: 1440,
            height: 1080,
            fx: 698.169,
            fy: 698.515,
            cx: 712.765,
            cy: 560.575,
            distortion: Distortion::Fisheye {
                k1: -0.041142,
                k2: -0.002422,
                k3: 0.003400,
                k4: -0.001852,
            },
        }
    }

    fn radtan_cam() -> CameraModel {
        CameraModel {
            width: 640,
            height: 480,
            fx: 500.0,
            fy: 505.0,
            cx: 322.3,
            cy: 237.8,
            distortion: Distortion::RadTan {
                k1: -0.28,
                k2: 0.07,
                p1: 1e-4,
                p2: -2e-4,
                k3: 0.0,
            },
        }
    }

    fn pinhole_cam() -> CameraModel {
        CameraModel::pinhole(640, 480, 500.0, 498.0, 319.5, 239.5)
    }

    /// Wide fisheye whose image corners are ~114° off axis, to exercise rays behind the camera.
    fn wide_fisheye() -> CameraModel {
        CameraModel {
            width: 1280,
            height: 960,
            fx: 400.0,
            fy: 400.0,
            cx: 639.5,
            cy: 479.5,
            distortion: Distortion::Fisheye {
                k1: 0.01,
                k2: -0.002,
                k3: 0.0,
                k4: 0.0,
            },
        }
    }

    fn angle_between(a: DVec3, b: DVec3) -> f64 {
        a.cross(b).length().atan2(a.dot(b))
    }

    fn rng(seed: u64) -> Xoshiro256PlusPlus {
        Xoshiro256PlusPlus::seed_from_u64(seed)
    }

    /// Random direction at angle `theta` from the axis, random azimuth.
    fn dir_at(theta: f64, phi: f64) -> DVec3 {
        DVec3::new(
            theta.sin() * phi.cos(),
            theta.sin() * phi.sin(),
            theta.cos(),
        )
    }

    /// Dense pixel grid over the whole image, both border lines (-0.5 and size-0.5) and corners included.
    /// Returns (max ray angle error, max pixel error).
    fn grid_round_trip(cam: &CameraModel, nu: usize, nv: usize) -> (f64, f64) {
        let lim = cam.valid_angle();
        let (mut max_ang, mut max_px) = (0.0f64, 0.0f64);
        for i in 0..=nu {
            for j in 0..=nv {
                let px = DVec2::new(
                    -0.5 + cam.width as f64 * i as f64 / nu as f64,
                    -0.5 + cam.height as f64 * j as f64 / nv as f64,
                );
                let ray = cam
                    .unproject_within(px, lim)
                    .unwrap_or_else(|| panic!("unproject failed at {px}"));
                assert!((ray.length() - 1.0).abs() < 1e-14);
                let px2 = cam
                    .project_within(ray, lim)
                    .unwrap_or_else(|| panic!("project failed at {px}"));
                max_px = max_px.max((px2 - px).length());
                let ray2 = cam.unproject_within(px2, lim).unwrap();
                max_ang = max_ang.max(angle_between(ray, ray2));
                // A scaled ray is the same ray.
                let px3 = cam.project_within(ray * 7.25, lim).unwrap();
                max_px = max_px.max((px3 - px).length());
            }
        }
        (max_ang, max_px)
    }

    /// Random points within the valid angle: project, unproject, compare with the original direction.
    fn random_round_trip(cam: &CameraModel, seed: u64) -> f64 {
        let lim = cam.valid_angle();
        let mut r = rng(seed);
        let mut max_ang = 0.0f64;
        for _ in 0..5000 {
            let d = dir_at(r.random_range(0.0..lim), r.random_range(-PI..PI));
            let p = d * r.random_range(0.1..80.0);
            let px = cam.project_within(p, lim).unwrap();
            let back = cam.unproject_within(px, lim).unwrap();
            max_ang = max_ang.max(angle_between(d, back));
        }
        max_ang
    }

    #[test]
    fn camera_round_trip_fisheye_spires() {
        let cam = spires_front();
        let (ang, px) = grid_round_trip(&cam, 360, 270);
        let rnd = random_round_trip(&cam, 11);
        println!("spires fisheye: grid max angle err {ang:.3e} rad, max pixel err {px:.3e} px; random {rnd:.3e} rad");
        assert!(ang < 1e-6 && px < 1e-6 && rnd < 1e-6);
        // The public wrappers agree with the hoisted-limit variants.
        for px in [
            DVec2::new(-0.5, -0.5),
            DVec2::new(1439.5, 1079.5),
            DVec2::new(700.0, 500.0),
        ] {
            assert_eq!(
                cam.unproject(px),
                cam.unproject_within(px, cam.valid_angle())
            );
        }
    }

    #[test]
    fn camera_round_trip_radtan_and_pinhole() {
        for (name, cam) in [("radtan", radtan_cam()), ("pinhole", pinhole_cam())] {
            let (ang, px) = grid_round_trip(&cam, 320, 240);
            let rnd = random_round_trip(&cam, 12);
            println!("{name}: grid max angle err {ang:.3e} rad, max pixel err {px:.3e} px; random {rnd:.3e} rad");
            assert!(ang < 1e-6 && px < 1e-6 && rnd < 1e-6, "{name}");
        }
    }

    #[test]
    fn camera_round_trip_behind_wide_fisheye() {
        let cam = wide_fisheye();
        assert!(
            cam.valid_angle() > 115.0 * DEG,
            "{}",
            cam.valid_angle() / DEG
        );
        let (ang, px) = grid_round_trip(&cam, 320, 240);
        println!("wide fisheye: grid max angle err {ang:.3e} rad, max pixel err {px:.3e} px");
        assert!(ang < 1e-6 && px < 1e-6);
        // The image corners are behind the camera.
        assert!(cam.unproject(DVec2::new(-0.5, -0.5)).unwrap().z < 0.0);
    }

    #[test]
    fn camera_matches_opencv_formulas() {
        // Hand-evaluated OpenCV formulas at one point, so a convention slip (e.g. swapped p1/p2) fails.
        let cam = radtan_cam();
        let p = DVec3::new(0.3, -0.2, 1.5);
        let (x, y) = (0.2, -0.2 / 1.5);
        let r2: f64 = x * x + y * y;
        let radial = 1.0 - 0.28 * r2 + 0.07 * r2 * r2;
        let xd = x * radial + 2.0 * 1e-4 * x * y + (-2e-4) * (r2 + 2.0 * x * x);
        let yd = y * radial + 1e-4 * (r2 + 2.0 * y * y) + 2.0 * (-2e-4) * x * y;
        let uv = cam.project(p).unwrap();
        assert!((uv - DVec2::new(500.0 * xd + 322.3, 505.0 * yd + 237.8)).length() < 1e-12);

        let cam = spires_front();
        let p = DVec3::new(-1.0, 0.5, 2.0);
        let r = p.x.hypot(p.y);
        let t = r.atan2(p.z);
        let td = t
            * (1.0 - 0.041142 * t.powi(2) - 0.002422 * t.powi(4) + 0.0034 * t.powi(6)
                - 0.001852 * t.powi(8));
        let uv = cam.project(p).unwrap();
        let expect = DVec2::new(
            698.169 * td * p.x / r + 712.765,
            698.515 * td * p.y / r + 560.575,
        );
        assert!((uv - expect).length() < 1e-12);
        // On-axis points hit the principal point.
        assert!(
            (cam.project(DVec3::Z * 3.0).unwrap() - DVec2::new(cam.cx, cam.cy)).length() < 1e-12
        );
    }

    #[test]
    fn camera_jacobian_matches_finite_differences() {
        fn check(cam: &CameraModel, p: DVec3, lim: f64, worst: &mut f64) {
            let (uv, j) = cam
                .project_jacobian_within(p, lim)
                .unwrap_or_else(|| panic!("no projection for {p}"));
            assert!((uv - cam.project_within(p, lim).unwrap()).length() < 1e-12);
            let h = 1e-5 * p.length();
            for k in 0..3 {
                let mut e = DVec3::ZERO;
                e[k] = h;
                let fd = (cam.project_within(p + e, lim).unwrap()
                    - cam.project_within(p - e, lim).unwrap())
                    / (2.0 * h);
                for (row, fdv) in [fd.x, fd.y].into_iter().enumerate() {
                    let err = (fdv - j[row][k]).abs() / j[row][k].abs().max(1.0);
                    *worst = worst.max(err);
                    assert!(
                        err <= 1e-5,
                        "p {p}: J[{row}][{k}] = {} vs fd {fdv}",
                        j[row][k]
                    );
                }
            }
        }
        let mut r = rng(21);
        for (name, cam) in [
            ("spires", spires_front()),
            ("radtan", radtan_cam()),
            ("pinhole", pinhole_cam()),
            ("wide", wide_fisheye()),
        ] {
            let lim = cam.valid_angle();
            let mut worst = 0.0f64;
            for _ in 0..2000 {
                let d = dir_at(
                    r.random_range(0.0..0.95 * lim.min(FRAC_PI_2)),
                    r.random_range(-PI..PI),
                );
                check(&cam, d * r.random_range(0.3..50.0), lim, &mut worst);
            }
            // On and extremely close to the axis (series branch of the fisheye Jacobian).
            for p in [
                DVec3::new(0.0, 0.0, 2.0),
                DVec3::new(1e-9, -2e-9, 2.0),
                DVec3::new(3e-7, 1e-7, 0.5),
            ] {
                check(&cam, p, lim, &mut worst);
            }
            println!("{name}: worst relative Jacobian error (front) {worst:.3e}");
        }
        // Behind the camera (theta > 90°): wide fisheye up to its valid angle, and Spires up to its fold.
        let mut worst = 0.0f64;
        let cam = wide_fisheye();
        let lim = cam.valid_angle();
        for _ in 0..2000 {
            let d = dir_at(
                r.random_range(91.0 * DEG..lim - 1.0 * DEG),
                r.random_range(-PI..PI),
            );
            check(&cam, d * r.random_range(0.3..50.0), lim, &mut worst);
        }
        let cam = spires_front();
        let lim = cam.invertible_angle();
        for _ in 0..500 {
            let d = dir_at(
                r.random_range(90.5 * DEG..lim - 1.0 * DEG),
                r.random_range(-PI..PI),
            );
            check(&cam, d * r.random_range(0.3..50.0), lim, &mut worst);
        }
        println!("fisheye behind camera: worst relative Jacobian error {worst:.3e}");
    }

    #[test]
    fn camera_fisheye_jacobian_near_axis_is_continuous() {
        // The fisheye Jacobian switches to its on-axis limit below r = 1e-6 Z. Finite differences cannot see
        // that O(r^2) term, so check continuity across the switch instead: a wrong limit shows up as ~3e-13.
        for cam in [spires_front(), wide_fisheye()] {
            for z in [0.7, 3.0] {
                let lim = cam.valid_angle();
                let below = cam
                    .project_jacobian_within(DVec3::new(0.999e-6 * z, 0.0, z), lim)
                    .unwrap()
                    .1;
                let above = cam
                    .project_jacobian_within(DVec3::new(1.001e-6 * z, 0.0, z), lim)
                    .unwrap()
                    .1;
                let scale = cam.fx / z;
                // Columns X and Y carry the switched term; column Z (-X g'/rho^2) is exact in both branches.
                for r in 0..2 {
                    for c in 0..2 {
                        assert!(
                            (below[r][c] - above[r][c]).abs() < 2e-14 * scale,
                            "{below:?} vs {above:?}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn camera_valid_angle() {
        // Pinhole: exactly the widest corner ray + 5°.
        let cam = pinhole_cam();
        let corner = [(-0.5, -0.5), (639.5, -0.5), (-0.5, 479.5), (639.5, 479.5)]
            .iter()
            .map(|&(u, v): &(f64, f64)| ((u - cam.cx) / cam.fx).hypot((v - cam.cy) / cam.fy).atan())
            .fold(0.0, f64::max);
        assert!((cam.valid_angle() - (corner + BORDER_MARGIN)).abs() < 1e-12);
        assert_eq!(cam.invertible_angle(), PERSPECTIVE_MAX_ANGLE);
        assert!(cam.project(DVec3::new(0.0, 0.0, -1.0)).is_none());
        assert!(cam.project(DVec3::new(1.0, 0.0, 0.0)).is_none());
        assert!(cam.project(dir_at(cam.valid_angle() + 1e-6, 0.3)).is_none());
        assert!(cam.project(dir_at(cam.valid_angle() - 1e-6, 0.3)).is_some());

        // Spires cam_front: the reference quotes HFOV ≈ 124°, VFOV ≈ 91°, half-diagonal ≈ 81°.
        let cam = spires_front();
        let ks = [-0.041142, -0.002422, 0.0034, -0.001852];
        let va = cam.valid_angle();
        let inv = cam.invertible_angle();
        let border = cam.border_angle(inv).unwrap();
        let h = ray_angle(cam.unproject(DVec2::new(-0.5, cam.cy)).unwrap())
            + ray_angle(cam.unproject(DVec2::new(1439.5, cam.cy)).unwrap());
        let v = ray_angle(cam.unproject(DVec2::new(cam.cx, -0.5)).unwrap())
            + ray_angle(cam.unproject(DVec2::new(cam.cx, 1079.5)).unwrap());
        println!(
            "spires: valid {:.3}°, invertible {:.3}°, border {:.3}°, HFOV {:.2}°, VFOV {:.2}°",
            va / DEG,
            inv / DEG,
            border / DEG,
            h / DEG,
            v / DEG
        );
        assert!(va >= 80.0 * DEG);
        // The reference's ~81° is the centred half-diagonal (900 px); the principal point is off-centre, so
        // the widest corner (top-right) is ~84.3°. For a radial model the widest border ray is at a corner.
        let corners = [
            (-0.5, -0.5),
            (1439.5, -0.5),
            (-0.5, 1079.5),
            (1439.5, 1079.5),
        ]
        .map(|(u, v)| ray_angle(cam.unproject(DVec2::new(u, v)).unwrap()));
        assert!((border - corners.iter().copied().fold(0.0, f64::max)).abs() < 1e-15);
        assert!((border / DEG - 84.3).abs() < 0.1, "{}", border / DEG);
        let half_diag = invert_fisheye(900.0 / 698.342, inv, ks).unwrap();
        assert!((half_diag / DEG - 81.8).abs() < 0.2, "{}", half_diag / DEG);
        assert!((va - (border + BORDER_MARGIN)).abs() < 1e-12);
        assert!((h / DEG - 124.0).abs() < 1.5 && (v / DEG - 91.0).abs() < 1.5);
        // Past the fold the polynomial is decreasing.
        assert!(inv > va && inv < FISHEYE_MAX_ANGLE);
        assert!(fisheye_poly(inv - 1e-9, ks).1 > 0.0 && fisheye_poly(inv + 1e-9, ks).1 <= 0.0);

        // A strongly barrel fisheye folds at theta = 1/sqrt(0.6) inside its (large) image: the fold wins.
        let fold = CameraModel {
            distortion: Distortion::Fisheye {
                k1: -0.2,
                k2: 0.0,
                k3: 0.0,
                k4: 0.0,
            },
            ..spires_front()
        };
        let expect = (1.0f64 / 0.6).sqrt();
        assert!(
            (fold.valid_angle() - expect).abs() < 1e-12,
            "{}",
            fold.valid_angle()
        );
        assert!(fold.border_angle(fold.invertible_angle()).is_none());
        assert!(fold.project(dir_at(expect + 1e-3, 1.0)).is_none());
        assert!(fold.project(dir_at(expect - 1e-3, 1.0)).is_some());
        // Pixels beyond the fold's image cannot be unprojected.
        assert!(fold.unproject(DVec2::new(-0.5, -0.5)).is_none());

        // Rad-tan with k1 = -0.5 folds at r = 1/sqrt(1.5).
        let fold = CameraModel {
            distortion: Distortion::RadTan {
                k1: -0.5,
                k2: 0.0,
                p1: 0.0,
                p2: 0.0,
                k3: 0.0,
            },
            ..CameraModel::pinhole(2000, 2000, 500.0, 500.0, 999.5, 999.5)
        };
        let expect = (1.0f64 / 1.5).sqrt().atan();
        assert!(
            (fold.valid_angle() - expect).abs() < 1e-12,
            "{}",
            fold.valid_angle()
        );
        assert!(fold.unproject(DVec2::new(-0.5, -0.5)).is_none());

        // Wide fisheye: capped by the border, and behind-the-camera rays project.
        let cam = wide_fisheye();
        assert!(cam.project(dir_at(100.0 * DEG, 0.2)).is_some());
        assert!(cam.project(dir_at(cam.valid_angle() + 1e-6, 0.2)).is_none());
        assert!(cam.project(DVec3::new(0.0, 0.0, -1.0)).is_none());
        assert!(cam.project(DVec3::ZERO).is_none());
    }

    #[test]
    fn camera_pixels_and_scaling() {
        let cam = pinhole_cam();
        assert!(cam.in_image(DVec2::new(-0.5, -0.5)));
        assert!(!cam.in_image(DVec2::new(-0.5000001, 0.0)));
        assert!(!cam.in_image(DVec2::new(639.5, 0.0)));
        assert!(cam.in_image(DVec2::new(639.4999, 479.4999)));
        assert_eq!(cam.pixel_of(DVec2::new(-0.5, -0.5)), Some((0, 0)));
        assert_eq!(cam.pixel_of(DVec2::new(0.49, 0.5)), Some((0, 1)));
        assert_eq!(
            cam.pixel_of(DVec2::new(639.5 - 1e-12, 479.5 - 1e-12)),
            Some((639, 479))
        );
        assert_eq!(cam.pixel_of(DVec2::new(639.5, 3.0)), None);
        assert_eq!(cam.pixel_of(DVec2::new(f64::NAN, 3.0)), None);

        let full = spires_front();
        let half = full.scaled(0.5);
        assert_eq!((half.width, half.height), (720, 540));
        assert!((half.fx - 349.0845).abs() < 1e-12 && (half.fy - 349.2575).abs() < 1e-12);
        assert!((half.cx - 356.1325).abs() < 1e-12 && (half.cy - 280.0375).abs() < 1e-12);
        let quarter = full.scaled(0.25);
        assert_eq!((quarter.width, quarter.height), (360, 270));
        // Resizing maps pixel positions by u' = (u + 0.5) s - 0.5, for every ray.
        let mut r = rng(31);
        for _ in 0..200 {
            let p = dir_at(r.random_range(0.0..1.3), r.random_range(-PI..PI));
            let a = full.project(p).unwrap();
            let b = quarter.project(p).unwrap();
            assert!(((a + 0.5) * 0.25 - 0.5 - b).length() < 1e-9);
        }
        let same = full.scaled(1.0);
        assert_eq!(
            (same.width, same.height, same.fx, same.fy),
            (full.width, full.height, full.fx, full.fy)
        );
        assert!((same.cx - full.cx).abs() < 1e-12 && (same.cy - full.cy).abs() < 1e-12);

        assert_eq!(full.validate(), Ok(()));
        assert!(matches!(
            CameraModel { width: 0, ..full }.validate(),
            Err(CameraError::ZeroSize { .. })
        ));
        assert!(matches!(
            CameraModel { fx: -1.0, ..full }.validate(),
            Err(CameraError::BadFocalLength { .. })
        ));
        assert!(matches!(
            CameraModel {
                fy: f64::NAN,
                ..full
            }
            .validate(),
            Err(CameraError::BadFocalLength { .. })
        ));
        assert!(matches!(
            CameraModel {
                cy: f64::INFINITY,
                ..full
            }
            .validate(),
            Err(CameraError::BadPrincipalPoint { .. })
        ));
        let bad = CameraModel {
            distortion: Distortion::Fisheye {
                k1: 0.0,
                k2: f64::NAN,
                k3: 0.0,
                k4: 0.0,
            },
            ..full
        };
        assert!(matches!(bad.validate(), Err(CameraError::BadDistortion(_))));
    }

    #[test]
    fn camera_colmap_and_serde() {
        assert_eq!(pinhole_cam().colmap_name(), "PINHOLE");
        assert_eq!(radtan_cam().colmap_name(), "OPENCV");
        assert_eq!(spires_front().colmap_name(), "OPENCV_FISHEYE");
        let full = CameraModel {
            distortion: Distortion::RadTan {
                k1: 0.1,
                k2: 0.0,
                p1: 0.0,
                p2: 0.0,
                k3: 0.01,
            },
            ..radtan_cam()
        };
        assert_eq!(full.colmap_name(), "FULL_OPENCV");
        assert_eq!(full.colmap_params().len(), 12);
        assert_eq!(radtan_cam().colmap_params().len(), 8);
        let p = spires_front().colmap_params();
        assert_eq!(p[..4], [698.169, 698.515, 713.265, 561.075]);

        for cam in [pinhole_cam(), radtan_cam(), spires_front()] {
            let json = serde_json::to_string(&cam).unwrap();
            let back: CameraModel = serde_json::from_str(&json).unwrap();
            // Tolerance: serde_json's default float parser is not guaranteed to round-trip to the last bit.
            assert_eq!(
                (back.width, back.height, back.colmap_name()),
                (cam.width, cam.height, cam.colmap_name())
            );
            for (a, b) in back.colmap_params().iter().zip(cam.colmap_params()) {
                assert!((a - b).abs() <= 1e-14 * b.abs().max(1.0), "{json}");
            }
        }
        assert!(serde_json::to_string(&spires_front())
            .unwrap()
            .contains("\"model\":\"fisheye\""));
    }

    #[test]
    fn camera_opengl_flip() {
        let c2w = DMat4::from_rotation_translation(
            glam::DQuat::from_euler(glam::EulerRot::ZYX, 0.3, -0.2, 1.1),
            DVec3::new(1.0, 2.0, 3.0),
        );
        let gl = opencv_to_opengl_c2w(c2w);
        assert!(opencv_to_opengl_c2w(gl).abs_diff_eq(c2w, 0.0));
        // Camera forward is +z in OpenCV and -z in OpenGL; "up" is -y in OpenCV and +y in OpenGL.
        assert!(
            (gl.transform_vector3(-DVec3::Z) - c2w.transform_vector3(DVec3::Z)).length() < 1e-15
        );
        assert!(
            (gl.transform_vector3(DVec3::Y) - c2w.transform_vector3(-DVec3::Y)).length() < 1e-15
        );
        assert_eq!(gl.w_axis, c2w.w_axis);
        assert!((gl.determinant() - 1.0).abs() < 1e-12);
    }
}
