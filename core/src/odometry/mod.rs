//! Lidar odometry: a trajectory from the lidar sweeps alone, for recordings that carry no SLAM system's
//! (issue 34). Everything downstream (keyframes, deskew, the SfM prior, submaps) takes it as it takes an
//! external one.
//!
//! The method is KISS-ICP's (Vizzo et al., "KISS-ICP: In Defense of Point-to-Point ICP", RA-L 2023), per
//! sweep:
//! 1. **deskew** with the constant-velocity motion of the last two poses: per-point time where the driver
//!    gives it, else the sweep's azimuth order, or not at all for clouds already motion-compensated;
//! 2. **crop** to `[min_range, max_range]` and **down-sample** twice: one point per voxel of `v/2` for the
//!    map, of `1.5 v` for registration (`v` = `voxel_size`, 1/100 of the range by default);
//! 3. **predict** the pose by constant velocity and **register** the sweep to the local map by
//!    point-to-point ICP ([`icp`]) with correspondences within 3σ and a Geman-McClure kernel of scale σ, where
//!    σ is the **adaptive threshold**: the RMS of the deviations between prediction and result seen so far
//!    (of those above `min_motion`), `initial_threshold` until there is one;
//! 4. **update** the voxel-hash local map ([`voxel_map`]: ≤ `max_points_per_voxel` a voxel) and forget
//!    voxels beyond `max_range` of the sensor.
//!
//! Deterministic and pure Rust (builds for wasm32). Poses are `T_world_lidar` with the world the first
//! sweep's lidar frame, stamped at each sweep's reference time (the middle of its point times when it has
//! them, its stamp otherwise).

pub mod icp;
pub mod voxel_map;

use glam::DVec3;
use serde::Serialize;

use crate::geometry::Se3;
use icp::IcpSettings;
use voxel_map::{voxel_downsample, VoxelHashMap};

/// How a sweep's points are placed in time for deskewing.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DeskewMode {
    /// Per-point times where the sweep has them, else azimuth order.
    Auto,
    /// Points already motion-compensated (KITTI's `.bin` sweeps, most processed releases): no deskew.
    Off,
}

/// Settings; the defaults are KISS-ICP's (which it does not tune per dataset).
#[derive(Clone, Debug, Serialize, serde::Deserialize)]
pub struct OdometryConfig {
    /// Points beyond this range (m) are dropped; also the local map's radius.
    pub max_range: f64,
    /// Points nearer than this (m, the rig itself) are dropped.
    pub min_range: f64,
    /// Voxel side (m) of the local map; `None`: `max_range / 100`.
    pub voxel_size: Option<f64>,
    pub max_points_per_voxel: usize,
    /// σ (m) before the first deviation above `min_motion` is seen.
    pub initial_threshold: f64,
    /// Deviations (m) below this do not update σ (a standing sensor would shrink it to nothing).
    pub min_motion: f64,
    pub max_iterations: usize,
    pub convergence: f64,
    pub deskew: DeskewMode,
}

impl Default for OdometryConfig {
    fn default() -> Self {
        Self {
            max_range: 100.0,
            min_range: 0.0,
            voxel_size: None,
            max_points_per_voxel: 20,
            initial_threshold: 2.0,
            min_motion: 0.1,
            max_iterations: 500,
            convergence: 1e-4,
            deskew: DeskewMode::Auto,
        }
    }
}

impl OdometryConfig {
    pub fn voxel(&self) -> f64 {
        self.voxel_size.unwrap_or(self.max_range / 100.0)
    }
}

/// One lidar sweep in its sensor frame.
#[derive(Clone, Debug, Default)]
pub struct Sweep {
    /// The sweep's stamp (s); its reference time when it has no point times.
    pub stamp: f64,
    pub points: Vec<DVec3>,
    /// Per-point times (s, same clock as `stamp`), when the driver gives them.
    pub times: Option<Vec<f64>>,
}

impl Sweep {
    /// The time its pose is at: the middle of its finite point times (KISS-ICP deskews to mid-sweep), else
    /// its stamp.
    pub fn reference_time(&self) -> f64 {
        let Some(times) = &self.times else {
            return self.stamp;
        };
        let (lo, hi) = times
            .iter()
            .filter(|x| x.is_finite())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
                (a.min(x), b.max(x))
            });
        if lo.is_finite() {
            0.5 * (lo + hi)
        } else {
            self.stamp
        }
    }
}

/// What odometry did with one sweep.
#[derive(Clone, Debug, Serialize)]
pub struct SweepReport {
    /// The time the pose is at (s).
    pub stamp: f64,
    /// Points registered (after crop and down-sampling).
    pub source_points: usize,
    pub correspondences: usize,
    pub iterations: usize,
    /// The adaptive threshold σ used (m).
    pub sigma: f64,
    /// Map points after the update.
    pub map_points: usize,
    /// Time this sweep took (s): deskew, down-sampling, registration and the map update (not reading it).
    pub seconds: f64,
    /// ICP's last step was below the convergence threshold.
    pub converged: bool,
    /// How well the matched surfaces pin the translation, smallest / largest eigenvalue of Σ n nᵀ
    /// ([`icp::translation_constraint`]; 0 in a corridor), and the least constrained direction (sensor
    /// frame of the first sweep).
    pub constraint: Option<f64>,
    pub weak_direction: Option<[f64; 3]>,
    /// What the user should know about this sweep's pose (too few points, no convergence, a jump beyond
    /// the motion model, a degenerate scene).
    pub warnings: Vec<String>,
}

/// Fewer registration points than this and the sweep is not registered (its pose is the prediction).
pub const MIN_POINTS: usize = 50;
/// Below this [`SweepReport::constraint`] the sweep is reported as degenerate.
pub const MIN_CONSTRAINT: f64 = 0.02;

#[derive(Debug, thiserror::Error)]
pub enum OdometryError {
    #[error("sweep {index} (t = {stamp:.6} s): {problem}")]
    BadSweep {
        index: usize,
        stamp: f64,
        problem: String,
    },
    #[error("invalid odometry settings: {0}")]
    Config(String),
    /// A sweep could not be read (the source's own message, naming its file).
    #[error("{0}")]
    Input(String),
}

/// Lidar odometry state: feed sweeps in time order with [`Odometry::register`].
pub struct Odometry {
    config: OdometryConfig,
    map: VoxelHashMap,
    poses: Vec<Se3>,
    stamps: Vec<f64>,
    /// Sum of squared model deviations above `min_motion`, and their count.
    sse: f64,
    samples: usize,
    /// The first two sweeps' cropped points and times, until a velocity can deskew them.
    early: Vec<(Vec<DVec3>, Vec<f64>)>,
}

/// Points moved to the reference time: `exp(dt · ξ) p` for the body-frame velocity ξ = (ρ, φ).
fn deskew(points: &[DVec3], dts: &[f64], rho: DVec3, phi: DVec3) -> Vec<DVec3> {
    if rho == DVec3::ZERO && phi == DVec3::ZERO {
        return points.to_vec();
    }
    points
        .iter()
        .zip(dts)
        .map(|(&p, &dt)| Se3::exp(rho * dt, phi * dt).transform_point(p))
        .collect()
}

impl Odometry {
    pub fn new(config: OdometryConfig) -> Result<Self, OdometryError> {
        let v = config.voxel();
        let ok = config.max_range.is_finite()
            && config.max_range > 0.0
            && config.min_range >= 0.0
            && config.min_range < config.max_range
            && v.is_finite()
            && v > 0.0
            && config.initial_threshold > 0.0
            && config.max_points_per_voxel > 0;
        if !ok {
            return Err(OdometryError::Config(format!(
                "need 0 <= min_range < max_range, voxel > 0, initial_threshold > 0 (got {config:?})"
            )));
        }
        Ok(Self {
            map: VoxelHashMap::new(v, config.max_points_per_voxel),
            config,
            poses: Vec::new(),
            stamps: Vec::new(),
            sse: 0.0,
            samples: 0,
            early: Vec::new(),
        })
    }

    /// The adaptive threshold σ (m).
    pub fn sigma(&self) -> f64 {
        if self.samples == 0 {
            self.config.initial_threshold
        } else {
            (self.sse / self.samples as f64).sqrt()
        }
    }

    /// Poses so far (`T_world_lidar`) and their stamps.
    pub fn trajectory(&self) -> (&[f64], &[Se3]) {
        (&self.stamps, &self.poses)
    }

    /// The motion per second of the last two poses as a twist (ρ, φ); zero before two poses.
    fn velocity(&self) -> (DVec3, DVec3) {
        let n = self.poses.len();
        if n < 2 {
            return (DVec3::ZERO, DVec3::ZERO);
        }
        let dt = self.stamps[n - 1] - self.stamps[n - 2];
        if dt <= 0.0 {
            return (DVec3::ZERO, DVec3::ZERO);
        }
        let (rho, phi) = (self.poses[n - 2].inverse() * self.poses[n - 1]).log();
        (rho / dt, phi / dt)
    }

    /// Registers the next sweep (stamps strictly increasing) and returns its pose and report.
    pub fn register(
        &mut self,
        index: usize,
        sweep: &Sweep,
    ) -> Result<(Se3, SweepReport), OdometryError> {
        let clock = web_time::Instant::now();
        let bad = |problem: String| OdometryError::BadSweep {
            index,
            stamp: sweep.stamp,
            problem,
        };
        if !sweep.stamp.is_finite() {
            return Err(bad("the stamp is not finite".into()));
        }
        if let Some(times) = &sweep.times {
            if times.len() != sweep.points.len() {
                return Err(bad(format!(
                    "{} point times for {} points",
                    times.len(),
                    sweep.points.len()
                )));
            }
        }
        let t_ref = sweep.reference_time();
        if let Some(&last) = self.stamps.last() {
            if t_ref <= last {
                return Err(bad(format!(
                    "its time {t_ref:.6} s is not after the previous sweep's {last:.6} s"
                )));
            }
        }
        let (v_rho, v_phi) = self.velocity();
        let period = match self.stamps.len() {
            0 => 0.0,
            n => t_ref - self.stamps[n - 1],
        };

        // 1. Crop, and place each point in time relative to t_ref; deskew with the constant velocity.
        let (lo, hi) = (self.config.min_range, self.config.max_range);
        let azimuth_period = self.typical_period();
        let mut raw = Vec::with_capacity(sweep.points.len());
        let mut dts = Vec::with_capacity(sweep.points.len());
        for (i, &p) in sweep.points.iter().enumerate() {
            if !p.is_finite() {
                continue;
            }
            let r = p.length();
            if r < lo || r > hi {
                continue;
            }
            raw.push(p);
            dts.push(match &sweep.times {
                Some(t) if t[i].is_finite() => t[i] - t_ref,
                Some(_) => 0.0,
                // Azimuth order (a spinning lidar turning clockwise seen from above, as Velodyne and
                // Ouster do): fraction s in [0, 1) of the turn, centred on mid-sweep.
                None => {
                    let s = 0.5 * (-p.y.atan2(p.x) / std::f64::consts::PI + 1.0);
                    (s - 0.5) * azimuth_period
                }
            });
        }
        let deskewing = self.config.deskew == DeskewMode::Auto;
        let frame = if deskewing {
            deskew(&raw, &dts, v_rho, v_phi)
        } else {
            raw.clone()
        };
        let v = self.config.voxel();
        let frame_map = voxel_downsample(&frame, 0.5 * v);
        let source = voxel_downsample(&frame_map, 1.5 * v);

        // 3. Predict and register.
        let prediction = match self.poses.last() {
            Some(last) => *last * Se3::exp(v_rho * period, v_phi * period),
            None => Se3::IDENTITY,
        };
        let sigma = self.sigma();
        let settings = IcpSettings {
            max_correspondence: 3.0 * sigma,
            // KISS-ICP 1.x passes σ itself as the scale (m²): broad enough to pull a sweep in from a
            // metre off. (σ/3)² was 20 % better on KITTI and lost the default world at its first turn.
            kernel: sigma,
            max_iterations: self.config.max_iterations,
            convergence: self.config.convergence,
        };
        let mut warnings = Vec::new();
        let (pose, rep) = if source.len() < MIN_POINTS && !self.map.is_empty() {
            warnings.push(format!(
                "only {} points within {lo}-{hi} m after down-sampling (fewer than {MIN_POINTS}): not \
                 registered, the pose is the constant-velocity prediction",
                source.len()
            ));
            (prediction, icp::IcpReport::default())
        } else {
            icp::register(&source, &self.map, prediction, &settings)
        };
        if !rep.converged && rep.iterations > 0 {
            warnings.push(format!(
                "ICP did not converge in {} iterations ({} correspondences)",
                rep.iterations, rep.correspondences
            ));
        }
        let constraint = if self.map.is_empty() {
            None
        } else {
            icp::translation_constraint(&source, &pose, &self.map, settings.max_correspondence)
        };
        if let Some((c, dir)) = constraint.filter(|(c, _)| *c < MIN_CONSTRAINT) {
            warnings.push(format!(
                "degenerate: the surfaces matched barely constrain motion along ({:.2}, {:.2}, {:.2}) \
                 (constraint {c:.4} < {MIN_CONSTRAINT}; a corridor or open ground): the pose along it is \
                 the motion model's",
                dir.x, dir.y, dir.z
            ));
        }

        // Adaptive threshold: how far the result moved from the prediction, rotation counted as the
        // displacement it causes at the range's edge.
        let dev = prediction.inverse() * pose;
        let theta = dev.angle_to(&Se3::IDENTITY);
        // KISS-ICP takes the configured max range as the lever arm; the sweep's own reach is what a
        // rotation error actually displaces (a 20 m street seen with a 100 m setting inflated σ fivefold).
        let reach = {
            let mut r: Vec<f64> = source.iter().map(|p| p.length()).collect();
            r.sort_by(f64::total_cmp);
            r.get(r.len() / 2).copied().unwrap_or(0.0)
        };
        let model_error = dev.trans.length() + 2.0 * reach * (0.5 * theta).sin();
        if self.samples >= 5 && model_error > 3.0 * sigma {
            warnings.push(format!(
                "jump: {:.3} m and {:.2}° away from the constant-velocity prediction (beyond 3σ = {:.3} m)",
                dev.trans.length(),
                theta.to_degrees(),
                3.0 * sigma
            ));
        }
        if model_error > self.config.min_motion {
            self.sse += model_error * model_error;
            self.samples += 1;
        }

        // 4. Update the local map.
        let world: Vec<DVec3> = frame_map.iter().map(|&p| pose.transform_point(p)).collect();
        self.map.add(&world);
        self.map.remove_far(pose.trans, self.config.max_range);
        self.poses.push(pose);
        self.stamps.push(t_ref);
        // The first two sweeps went into the map without a velocity to deskew them by (a recording that
        // starts mid-drive smears them by the distance covered in a sweep, and every later sweep would
        // register against that smear): once two poses give one, the map is rebuilt from them deskewed.
        if deskewing && self.poses.len() <= 2 {
            self.early.push((raw, dts));
            if self.poses.len() == 2 {
                let (r, p) = self.velocity();
                self.map = VoxelHashMap::new(v, self.config.max_points_per_voxel);
                for (k, (pts, dts)) in std::mem::take(&mut self.early).into_iter().enumerate() {
                    let fixed = voxel_downsample(&deskew(&pts, &dts, r, p), 0.5 * v);
                    let pose = self.poses[k];
                    let world: Vec<DVec3> =
                        fixed.iter().map(|&q| pose.transform_point(q)).collect();
                    self.map.add(&world);
                }
            }
        }
        Ok((
            pose,
            SweepReport {
                stamp: t_ref,
                source_points: source.len(),
                correspondences: rep.correspondences,
                iterations: rep.iterations,
                sigma,
                map_points: self.map.len(),
                seconds: clock.elapsed().as_secs_f64(),
                converged: rep.converged,
                constraint: constraint.map(|c| c.0),
                weak_direction: constraint.map(|c| c.1.to_array()),
                warnings,
            },
        ))
    }

    /// The median interval between sweeps so far (a sweep's duration for azimuth deskewing); 0.1 s (a
    /// 10 Hz lidar) before there are two.
    fn typical_period(&self) -> f64 {
        let mut d: Vec<f64> = self.stamps.windows(2).map(|w| w[1] - w[0]).collect();
        if d.is_empty() {
            return 0.1;
        }
        d.sort_by(f64::total_cmp);
        d[d.len() / 2]
    }
}

/// The whole trajectory of a sequence of sweeps, with a report per sweep.
#[derive(Clone, Debug, Serialize)]
pub struct OdometryRun {
    pub stamps: Vec<f64>,
    pub poses: Vec<Se3>,
    pub sweeps: Vec<SweepReport>,
}

/// Runs odometry over `sweeps` in order; `progress(i)` after each.
pub fn run(
    config: &OdometryConfig,
    sweeps: impl IntoIterator<Item = Result<Sweep, OdometryError>>,
    mut progress: impl FnMut(usize, &SweepReport),
) -> Result<OdometryRun, OdometryError> {
    let mut odo = Odometry::new(config.clone())?;
    let mut reports = Vec::new();
    for (i, sweep) in sweeps.into_iter().enumerate() {
        let (_, rep) = odo.register(i, &sweep?)?;
        progress(i, &rep);
        reports.push(rep);
    }
    let (stamps, poses) = odo.trajectory();
    Ok(OdometryRun {
        stamps: stamps.to_vec(),
        poses: poses.to_vec(),
        sweeps: reports,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;

    /// A street of boxes: two walls with piers every 4 m (0.6 m deep), posts every 10 m, the ground.
    fn boxes() -> Vec<(DVec3, DVec3)> {
        let mut b = Vec::new();
        for side in [-1.0f64, 1.0] {
            let wall = |y0: f64, y1: f64| (y0.min(y1), y0.max(y1));
            let (y0, y1) = wall(side * 7.6, side * 10.0);
            b.push((DVec3::new(-100.0, y0, -3.0), DVec3::new(100.0, y1, 12.0)));
            let (p0, p1) = wall(side * 7.0, side * 7.6);
            for k in -10..15 {
                let x = 4.0 * k as f64 + if side > 0.0 { 0.0 } else { 1.3 };
                b.push((DVec3::new(x, p0, -3.0), DVec3::new(x + 2.0, p1, 12.0)));
            }
            for k in -4..6 {
                let c = DVec3::new(10.0 * k as f64 + 3.0, side * 5.0, 0.0);
                b.push((c - DVec3::new(0.2, 0.2, 3.0), c + DVec3::new(0.2, 0.2, 1.0)));
            }
        }
        // Clutter along the kerbs (parked cars, bins, cabinets): what gives real streets their grip.
        let mut state = 7u64;
        let mut u = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..80 {
            let side = if u() < 0.5 { -1.0 } else { 1.0 };
            let c = DVec3::new(-30.0 + 80.0 * u(), side * (3.0 + 3.5 * u()), -1.8);
            let h = DVec3::new(0.2 + 1.2 * u(), 0.2 + 0.8 * u(), 0.0);
            b.push((c - h, c + h + DVec3::new(0.0, 0.0, 0.5 + 2.0 * u())));
        }
        b
    }

    fn scene_hit(origin: DVec3, dir: DVec3, boxes: &[(DVec3, DVec3)]) -> Option<f64> {
        let mut best: Option<f64> = None;
        let mut consider = |t: f64| {
            if t > 0.5 && best.is_none_or(|b| t < b) {
                best = Some(t);
            }
        };
        if dir.z < -1e-9 {
            consider((-1.8 - origin.z) / dir.z);
        }
        for &(lo, hi) in boxes {
            let mut t0: f64 = 0.0;
            let mut t1 = f64::INFINITY;
            for a in 0..3 {
                if dir[a].abs() < 1e-12 {
                    if origin[a] < lo[a] || origin[a] > hi[a] {
                        t1 = -1.0;
                    }
                    continue;
                }
                let (ta, tb) = ((lo[a] - origin[a]) / dir[a], (hi[a] - origin[a]) / dir[a]);
                t0 = t0.max(ta.min(tb));
                t1 = t1.min(ta.max(tb));
            }
            if t1 >= t0 {
                consider(t0);
            }
        }
        best.filter(|&t| t < 60.0)
    }

    /// Pose of the sensor at time t: driving along x at 8 m/s, weaving, turning slowly.
    fn truth(t: f64) -> Se3 {
        let yaw = 0.5 * (0.8 * t).sin();
        Se3::new(
            DQuat::from_rotation_z(yaw),
            DVec3::new(8.0 * t - 20.0, 0.8 * (0.5 * t).sin(), 0.05 * t),
        )
    }

    fn sweep(t0: f64, with_times: bool) -> Sweep {
        let mut s = Sweep {
            stamp: t0,
            ..Default::default()
        };
        let mut times = Vec::new();
        let (n_az, beams) = (1024, 32);
        let scene = boxes();
        for a in 0..n_az {
            let dt = 0.1 * a as f64 / n_az as f64;
            let pose = truth(t0 + dt);
            // Clockwise seen from above, starting behind.
            let az = std::f64::consts::PI - std::f64::consts::TAU * a as f64 / n_az as f64;
            for b in 0..beams {
                // Elevations dithered per ray (as a non-repetitive scanner's are): a spinning lidar's
                // exact rings on perfectly flat ground pull point-to-point ICP (ours and KISS-ICP alike,
                // measured) towards standing still and upwards, which no real ground does this much.
                let jitter = (((a * 7919 + b * 104729 + (t0 * 1e3) as usize * 31) % 1000) as f64
                    / 1000.0
                    - 0.5)
                    * 1.2;
                let el = (-25.0 + 1.25 * b as f64 + jitter).to_radians();
                let d_s = DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
                let o = pose.trans;
                let d = pose.transform_vector(d_s);
                if let Some(r) = scene_hit(o, d, &scene) {
                    s.points.push(d_s * r);
                    times.push(t0 + dt);
                }
            }
        }
        if with_times {
            s.times = Some(times);
        }
        s
    }

    fn drive(cfg: &OdometryConfig, with_times: bool) -> (Vec<Se3>, Vec<Se3>) {
        let sweeps: Vec<Sweep> = (0..30).map(|k| sweep(0.1 * k as f64, with_times)).collect();
        let run = run(cfg, sweeps.into_iter().map(Ok), |_, _| {}).unwrap();
        let first = truth(run.stamps[0]);
        let gt: Vec<Se3> = run
            .stamps
            .iter()
            .map(|&t| first.inverse() * truth(t))
            .collect();
        (run.poses, gt)
    }

    fn worst(est: &[Se3], gt: &[Se3]) -> f64 {
        est.iter()
            .zip(gt)
            .map(|(e, g)| e.distance_to(g))
            .fold(0.0, f64::max)
    }

    #[test]
    fn a_drive_is_tracked_and_deskewing_with_point_times_matters() {
        let cfg = OdometryConfig {
            max_range: 60.0,
            ..Default::default()
        };
        // 24 m in 3 s, turning ±0.4 rad/s: each sweep smeared by 0.8 m and up to 2.3°.
        let (est, gt) = drive(&cfg, true);
        let err = worst(&est, &gt);
        // Measured 0.12 m (0.5 % of the path; KISS-ICP drifts about as much on such a street).
        assert!(err < 0.2, "deskewed with point times: worst error {err} m");
        // The same sweeps taken as motion-compensated (they are not): measured 0.22 m.
        let off = OdometryConfig {
            deskew: DeskewMode::Off,
            ..cfg.clone()
        };
        let (est_off, _) = drive(&off, true);
        let err_off = worst(&est_off, &gt);
        assert!(err_off > 1.5 * err, "no deskew {err_off} vs deskew {err}");
        // Without point times the azimuth order stands in for them.
        let (est_az, _) = drive(&cfg, false);
        let err_az = worst(&est_az, &gt);
        assert!(
            err_az < 0.5 * (err + err_off),
            "azimuth {err_az} vs times {err}, none {err_off}"
        );
    }

    #[test]
    fn deskew_brings_each_point_to_the_reference_time() {
        // A sensor turning at 1 rad/s and moving at 10 m/s sees a fixed point at different places
        // through the sweep; moved by exp(dt ξ) each lands where the sensor at t_ref sees it.
        let (rho, phi) = (DVec3::new(10.0, 0.0, 0.0), DVec3::new(0.0, 0.0, 1.0));
        let world = DVec3::new(20.0, 5.0, -1.0);
        let (mut pts, mut dts) = (Vec::new(), Vec::new());
        for k in 0..11 {
            let dt = -0.05 + 0.01 * k as f64;
            // The sensor at t_ref + dt is T(dt) = exp(dt ξ) (t_ref at the origin).
            pts.push(
                Se3::exp(rho * dt, phi * dt)
                    .inverse()
                    .transform_point(world),
            );
            dts.push(dt);
        }
        for q in deskew(&pts, &dts, rho, phi) {
            assert!(q.distance(world) < 1e-9, "{q} vs {world}");
        }
        // Without motion nothing moves.
        assert_eq!(deskew(&pts, &dts, DVec3::ZERO, DVec3::ZERO), pts);
    }

    #[test]
    fn results_do_not_depend_on_the_thread_count() {
        let cfg = OdometryConfig {
            max_range: 60.0,
            ..Default::default()
        };
        let sweeps: Vec<Sweep> = (0..6).map(|k| sweep(0.1 * k as f64, true)).collect();
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(|| run(&cfg, sweeps.clone().into_iter().map(Ok), |_, _| {}).unwrap());
        let many = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap()
            .install(|| run(&cfg, sweeps.into_iter().map(Ok), |_, _| {}).unwrap());
        assert_eq!(one.poses, many.poses);
    }

    #[test]
    fn bad_sweeps_and_settings_are_named() {
        let mut odo = Odometry::new(OdometryConfig::default()).unwrap();
        let s = Sweep {
            stamp: 1.0,
            points: vec![DVec3::X; 3],
            times: Some(vec![1.0; 2]),
        };
        let e = odo.register(4, &s).unwrap_err().to_string();
        assert!(
            e.contains("sweep 4") && e.contains("2 point times for 3 points"),
            "{e}"
        );
        let ok = Sweep {
            stamp: 1.0,
            points: vec![DVec3::X],
            times: None,
        };
        odo.register(0, &ok).unwrap();
        let e = odo.register(1, &ok).unwrap_err().to_string();
        assert!(e.contains("not after"), "{e}");
        let bad = OdometryConfig {
            min_range: 200.0,
            ..Default::default()
        };
        assert!(Odometry::new(bad).is_err());
    }
}
