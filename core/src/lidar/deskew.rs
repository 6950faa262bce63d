//! Motion undistortion: a spinning lidar reports each point in the sensor frame at its own firing time;
//! while the rig moves, a sweep is smeared by up to (speed x sweep period), ~14 cm at walking pace. Deskewing
//! re-expresses every point in the sensor frame at one reference time (the image time) using the
//! trajectory: `p_ref = T_world_lidar(t_ref)^-1 * T_world_lidar(t_i) * p_i`.

use glam::DVec3;

use crate::geometry::{Se3, Trajectory};

/// Why a sweep could not be deskewed.
#[derive(Debug, thiserror::Error)]
pub enum DeskewError {
    #[error("reference time {t} is outside the trajectory ({t0} .. {t1})")]
    ReferenceOutside { t: f64, t0: f64, t1: f64 },
    #[error("positions and times differ in length ({0} vs {1})")]
    Length(usize, usize),
}

/// Deskewed positions, the number of points dropped because a coordinate was not finite (those entries
/// are NaN, so indices still line up with the input), and the number whose time lay beyond the
/// trajectory's span: those are carried by the nearest pose (the span's end), never dropped silently —
/// the first and last sweeps of a recording straddle its trajectory's ends.
#[derive(Clone, Debug)]
pub struct Deskewed {
    pub positions: Vec<DVec3>,
    pub dropped: usize,
    pub clamped: usize,
}

/// Deskews `positions` (sensor frame at `times`) to `t_ref`. `trajectory` holds `T_world_lidar`.
/// Poses are looked up once per distinct time (a column of a spinning lidar shares one time).
pub fn deskew(
    positions: &[DVec3],
    times: &[f64],
    trajectory: &Trajectory,
    t_ref: f64,
) -> Result<Deskewed, DeskewError> {
    if positions.len() != times.len() {
        return Err(DeskewError::Length(positions.len(), times.len()));
    }
    let (t0, t1) = trajectory.span();
    let reference =
        trajectory
            .at(t_ref)
            .ok_or(DeskewError::ReferenceOutside { t: t_ref, t0, t1 })?;
    let inv_ref = reference.inverse();
    let mut cached: Option<(f64, Option<Se3>)> = None;
    let mut dropped = 0;
    let mut clamped = 0;
    let out = positions
        .iter()
        .zip(times)
        .map(|(p, &t)| {
            if t.is_finite() && (t < t0 || t > t1) && p.is_finite() {
                clamped += 1;
            }
            let t = if t.is_finite() { t.clamp(t0, t1) } else { t };
            let rel = match cached {
                Some((ct, rel)) if ct == t => rel,
                _ => {
                    let rel = trajectory.at(t).map(|pose| inv_ref * pose);
                    cached = Some((t, rel));
                    rel
                }
            };
            match rel {
                Some(rel) if p.is_finite() => rel.transform_point(*p),
                _ => {
                    dropped += 1;
                    DVec3::NAN
                }
            }
        })
        .collect();
    Ok(Deskewed {
        positions: out,
        dropped,
        clamped,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;

    /// A rig moving along +x at 1 m/s from t = 10 to 11 s.
    fn straight() -> Trajectory {
        let at = |t: f64| Se3::new(DQuat::IDENTITY, DVec3::new(t - 10.0, 0.0, 0.0));
        Trajectory::new(vec![10.0, 10.5, 11.0], vec![at(10.0), at(10.5), at(11.0)]).unwrap()
    }

    #[test]
    fn points_beyond_the_span_are_carried_by_the_nearest_pose_and_counted() {
        let p = DVec3::new(5.0, 0.0, 0.0);
        let (pos, times) = (vec![p, p, p, DVec3::NAN], vec![9.8, 10.5, 11.3, 10.5]);
        let d = deskew(&pos, &times, &straight(), 10.5).unwrap();
        // 9.8 s is carried by the pose at 10 s (0.5 m behind the reference), 11.3 s by the one at 11 s.
        assert!((d.positions[0] - DVec3::new(4.5, 0.0, 0.0)).length() < 1e-12);
        assert!((d.positions[1] - p).length() < 1e-12);
        assert!((d.positions[2] - DVec3::new(5.5, 0.0, 0.0)).length() < 1e-12);
        assert!(d.positions[3].is_nan());
        assert_eq!((d.clamped, d.dropped), (2, 1));
    }
}
