//! The rig's path, walked like a handheld rig (gait bob, sway, yaw and pitch/roll wobble): in the town, a
//! counter-clockwise loop around the central block along the ring road; on the campus, a route through
//! the street grid given as waypoints. Analytic, so the pose at any instant is exact: lidar points are cast
//! from the pose at their own firing time.
//!
//! Both are straights joined by circular arcs (the loop is a rounded rectangle; a route's corners are
//! filleted): as smooth as a Catmull-Rom spline through the corners (C1), and with an exact arc-length
//! parametrisation, so speed is truly constant.

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
    /// When not empty, the walk follows these waypoints (x, y) instead of the loop, its corners filleted
    /// with `corner_radius` (or less where the legs are short); it goes on straight past the last.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub route: Vec<[f64; 2]>,
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
            route: Vec::new(),
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

    /// Length of the walk's path: the route's, or one lap of the loop.
    pub fn path_length(&self) -> f64 {
        if self.route.is_empty() {
            return self.loop_length();
        }
        let mut len = 0.0;
        self.route_pieces(|piece_len, _| {
            len += piece_len;
            false
        });
        len
    }

    /// Calls `f(length, piece)` for each piece of the filleted route in order until it returns true.
    fn route_pieces(&self, mut f: impl FnMut(f64, RoutePiece) -> bool) {
        let p = |k: usize| DVec2::from(self.route[k]);
        let n = self.route.len();
        if n < 2 {
            return;
        }
        // Tangent length of the fillet at each waypoint (0 at the ends), and its arc.
        let dir = |k: usize| (p(k + 1) - p(k)).normalize_or_zero();
        let turn = |k: usize| -> (f64, f64, f64) {
            // (tangent length, signed angle, radius) at interior waypoint k.
            let (d0, d1) = (dir(k - 1), dir(k));
            let ang = d0.perp_dot(d1).atan2(d0.dot(d1));
            let half = 0.5 * ang.abs();
            if half < 1e-9 {
                return (0.0, 0.0, 0.0);
            }
            let room = 0.5 * (p(k) - p(k - 1)).length().min((p(k + 1) - p(k)).length());
            let r = self.corner_radius.min(room / half.tan());
            (r * half.tan(), ang, r)
        };
        let mut prev_t = 0.0;
        for k in 0..n - 1 {
            let d = dir(k);
            let (t_end, ang, r) = if k + 2 < n {
                turn(k + 1)
            } else {
                (0.0, 0.0, 0.0)
            };
            let straight = (p(k + 1) - p(k)).length() - prev_t - t_end;
            if f(straight.max(0.0), RoutePiece::Line(p(k) + d * prev_t, d)) {
                return;
            }
            if r > 0.0
                && f(
                    r * ang.abs(),
                    RoutePiece::Fillet(p(k + 1) - d * t_end, d, r, ang.signum()),
                )
            {
                return;
            }
            prev_t = t_end;
        }
    }

    /// Position and unit heading on the walk's centre line at arc length `s`: the loop wraps around; a
    /// route runs straight on before its start and past its end.
    pub fn centerline(&self, s: f64) -> (DVec2, DVec2) {
        if !self.route.is_empty() {
            let mut rest = s;
            let mut out = None;
            let mut last = (DVec2::ZERO, DVec2::X, 0.0);
            let mut first = true;
            self.route_pieces(|len, piece| {
                let (start, heading) = piece.at(0.0);
                if first && rest < 0.0 {
                    out = Some((start + heading * rest, heading));
                    return true;
                }
                first = false;
                if rest <= len {
                    out = Some(piece.at(rest));
                    return true;
                }
                rest -= len;
                let (end, heading) = piece.at(len);
                last = (end, heading, rest);
                false
            });
            return out.unwrap_or((last.0 + last.1 * last.2, last.1));
        }
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

/// A piece of a route.
#[derive(Clone, Copy)]
enum RoutePiece {
    /// Start point and unit direction.
    Line(DVec2, DVec2),
    /// A corner: start point, unit heading there, radius, and turn sense (+1 left, -1 right).
    Fillet(DVec2, DVec2, f64, f64),
}

impl RoutePiece {
    /// Position and unit heading `s` along the piece.
    fn at(self, s: f64) -> (DVec2, DVec2) {
        match self {
            RoutePiece::Line(p0, dir) => (p0 + dir * s, dir),
            RoutePiece::Fillet(p0, d0, r, sense) => {
                let centre = p0 + d0.perp() * sense * r;
                let rot = DVec2::from_angle(sense * s / r);
                (centre + rot.rotate(p0 - centre), rot.rotate(d0))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Over `n` equal steps of arc length up to `l`: every step moves exactly that far (constant speed,
    /// no jump), the heading stays a unit vector and turns by less than 0.01 a step.
    fn assert_walked_smoothly(m: &MotionParams, l: f64, n: usize) {
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
            assert!((cur.1.length() - 1.0).abs() < 1e-9);
            prev = cur;
        }
    }

    #[test]
    fn centerline_is_continuous_and_closes() {
        let m = MotionParams::default();
        let l = m.loop_length();
        assert_walked_smoothly(&m, l, 20_000);
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

    #[test]
    fn a_route_is_walked_at_constant_speed_through_smooth_corners() {
        // Left and right right-angle turns, a 135-degree turn, and a leg too short for the full radius.
        let m = MotionParams {
            route: vec![
                [0.0, 0.0],
                [20.0, 0.0],
                [20.0, 15.0],
                [30.0, 15.0],
                [20.0, 25.0],
                [20.0, 28.0],
                [0.0, 28.0],
            ],
            corner_radius: 4.0,
            ..MotionParams::default()
        };
        let l = m.path_length();
        let legs = 20.0 + 15.0 + 10.0 + 200f64.sqrt() + 3.0 + 20.0;
        assert!(l < legs && l > legs - 15.0, "length {l} of {legs}");
        assert!((m.centerline(0.0).0 - DVec2::ZERO).length() < 1e-12);
        assert_walked_smoothly(&m, l, 40_000);
        // It ends on the last waypoint and walks straight on past it.
        assert!((m.centerline(l).0 - DVec2::new(0.0, 28.0)).length() < 1e-9);
        assert!((m.centerline(l + 2.0).0 - DVec2::new(-2.0, 28.0)).length() < 1e-9);
        assert!((m.centerline(-1.0).0 - DVec2::new(-1.0, 0.0)).length() < 1e-9);
    }
}
