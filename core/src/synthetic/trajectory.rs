//! The rig's path: a counter-clockwise loop around the central block along the ring road, walked like a
//! handheld rig (gait bob, sway, yaw and pitch/roll wobble). Analytic, so the pose at any instant is exact:
//! lidar points are cast from the pose at their own firing time.
//!
//! The loop is a rounded rectangle (straights joined by quarter circles): as smooth as a Catmull-Rom spline
//! through the corners (C1), and with an exact arc-length parametrisation, so speed is truly constant.

use std::f64::consts::{PI, TAU};

use glam::{DQuat, DVec2, DVec3, EulerRot};
use serde::{Deserialize, Serialize};

use crate::geometry::Se3;

/// Walking motion parameters.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct MotionParams {
    /// Half extents of the loop's centre line (the middle of the ring road).
    pub loop_half: [f64; 2],
    pub corner_radius: f64,
    /// Arc length at t = 0, measured from the middle of the south street (heading east).
    pub start_offset: f64,
    pub speed: f64,
    pub height: f64,
    /// Sideways offset from the road's centre line (positive = towards the block, on the left).
    pub lateral_offset: f64,
    pub bob_amplitude: f64,
    pub bob_hz: f64,
    pub sway_amplitude: f64,
    pub yaw_amplitude_deg: f64,
    pub tilt_amplitude_deg: f64,
}

impl Default for MotionParams {
    fn default() -> Self {
        Self {
            loop_half: [23.5, 15.5],
            corner_radius: 4.0,
            start_offset: -4.0,
            speed: 1.4,
            height: 1.6,
            lateral_offset: 0.0,
            bob_amplitude: 0.02,
            bob_hz: 1.8,
            sway_amplitude: 0.1,
            yaw_amplitude_deg: 3.0,
            tilt_amplitude_deg: 2.0,
        }
    }
}

impl MotionParams {
    /// Length of the closed loop.
    pub fn loop_length(&self) -> f64 {
        let [a, b] = self.loop_half;
        let r = self.corner_radius;
        4.0 * (a - r) + 4.0 * (b - r) + TAU * r
    }

    /// Position and unit heading on the loop's centre line at arc length `s` (wraps around).
    pub fn centerline(&self, s: f64) -> (DVec2, DVec2) {
        let [a, b] = self.loop_half;
        let r = self.corner_radius;
        let l = self.loop_length();
        // Start at (0, -b) heading +x; pieces: half south straight, SE arc, east, NE arc, north, NW arc, west,
        // SW arc, half south straight.
        let mut s = s.rem_euclid(l);
        let sx = 2.0 * (a - r);
        let sy = 2.0 * (b - r);
        let arc = 0.5 * PI * r;
        let pieces: [(f64, Piece); 9] = [
            (sx * 0.5, Piece::Line(DVec2::new(0.0, -b), DVec2::X)),
            (arc, Piece::Arc(DVec2::new(a - r, -b + r), -0.5 * PI)),
            (sy, Piece::Line(DVec2::new(a, -b + r), DVec2::Y)),
            (arc, Piece::Arc(DVec2::new(a - r, b - r), 0.0)),
            (sx, Piece::Line(DVec2::new(a - r, b), -DVec2::X)),
            (arc, Piece::Arc(DVec2::new(-a + r, b - r), 0.5 * PI)),
            (sy, Piece::Line(DVec2::new(-a, b - r), -DVec2::Y)),
            (arc, Piece::Arc(DVec2::new(-a + r, -b + r), PI)),
            (sx * 0.5, Piece::Line(DVec2::new(-a + r, -b), DVec2::X)),
        ];
        for (len, piece) in pieces {
            if s <= len {
                return match piece {
                    Piece::Line(p0, dir) => (p0 + dir * s, dir),
                    Piece::Arc(c, a0) => {
                        let ang = a0 + s / r;
                        let p = c + DVec2::new(ang.cos(), ang.sin()) * r;
                        (p, DVec2::new(-ang.sin(), ang.cos()))
                    }
                };
            }
            s -= len;
        }
        (DVec2::new(0.0, -b), DVec2::X)
    }

    /// `T_world_base` at time `t` (s). Base frame: x forward, y left, z up (ROS `base_link`).
    pub fn pose(&self, t: f64) -> Se3 {
        let s = self.start_offset + self.speed * t;
        let (p, heading) = self.centerline(s);
        let left = DVec2::new(-heading.y, heading.x);
        let sway = self.sway_amplitude * (TAU * 0.45 * t).sin();
        let xy = p + left * (self.lateral_offset + sway);
        let z = self.height + self.bob_amplitude * (TAU * self.bob_hz * t).sin();
        let yaw = heading.y.atan2(heading.x)
            + self.yaw_amplitude_deg.to_radians() * (TAU * 0.5 * t).sin();
        let tilt = self.tilt_amplitude_deg.to_radians();
        let pitch = tilt * (TAU * 0.9 * t + 0.3).sin();
        let roll = tilt * (TAU * 0.7 * t + 1.1).sin();
        Se3::new(
            DQuat::from_euler(EulerRot::ZYX, yaw, pitch, roll),
            DVec3::new(xy.x, xy.y, z),
        )
    }
}

#[derive(Clone, Copy)]
enum Piece {
    /// Start point and unit direction.
    Line(DVec2, DVec2),
    /// Centre and start angle; counter-clockwise.
    Arc(DVec2, f64),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn centerline_is_continuous_and_closes() {
        let m = MotionParams::default();
        let l = m.loop_length();
        let n = 20_000;
        let mut prev = m.centerline(0.0);
        for i in 1..=n {
            let s = l * i as f64 / n as f64;
            let cur = m.centerline(s);
            let step = (cur.0 - prev.0).length();
            assert!(
                (step - l / n as f64).abs() < 1e-6,
                "jump of {step} at s={s}"
            );
            assert!((cur.1 - prev.1).length() < 1e-2, "heading jump at s={s}");
            prev = cur;
        }
        assert!((m.centerline(l).0 - m.centerline(0.0).0).length() < 1e-9);
    }

    #[test]
    fn pose_moves_at_walking_speed_and_stays_upright() {
        let m = MotionParams::default();
        let a = m.pose(10.0);
        let b = m.pose(11.0);
        let d = (b.trans - a.trans).length();
        assert!((d - 1.4).abs() < 0.25, "moved {d} m in 1 s");
        let up = a.rot * DVec3::Z;
        assert!(up.z > 0.99);
        assert!((a.trans.z - 1.6).abs() < 0.03);
    }
}
