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

/// Deskewed positions plus the number of points dropped because their time lay outside the trajectory or
/// a coordinate was not finite (those entries are NaN, so indices still line up with the input).
#[derive(Clone, Debug)]
pub struct Deskewed {
    pub positions: Vec<DVec3>,
    pub dropped: usize,
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
    let out = positions
        .iter()
        .zip(times)
        .map(|(p, &t)| {
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
    })
}
