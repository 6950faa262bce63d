//! A SLAM-like prior trajectory for the synthetic world: the exact keyframe poses corrupted the way a
//! lidar SLAM system's poses are (the paper's §Large-scale Pose Trajectory Estimation starts from them).
//!
//! Three kinds of error, each set by [`PriorParams`]:
//! - **drift** that accumulates along the path: every keyframe-to-keyframe motion is integrated with a
//!   scale error, a yaw error proportional to the distance travelled, and a random walk of translation
//!   (odometry's errors compound; nothing corrects them, as with no loop closure);
//! - **per-frame noise**: an independent small translation and rotation on each keyframe (scan-matching
//!   jitter);
//! - **gross errors**: a few keyframes off by decimetres and degrees (a bad scan match), independent of
//!   their neighbours, which a robust alignment must ignore.
//!
//! Defaults (documented in DATASET.md): 1 % drift (0.5 % scale, 0.5 % random walk per step), 0.05°/m of
//! yaw drift, 2 cm / 0.2° noise, one gross error (30 cm / 3°) per 40 keyframes. The whole rig moves with
//! its base, so all cameras of a keyframe share the error (their extrinsics are exact).

use glam::{DQuat, DVec3};
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

use super::sensors::gaussian;
use crate::geometry::Se3;

/// How wrong the prior is.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PriorParams {
    /// Scale error of the integrated motion (0.005: every metre travelled counts as 1.005 m).
    pub scale_error: f64,
    /// Random walk of translation per step, as a fraction of the step's length (1 σ, each axis).
    pub walk_per_m: f64,
    /// Yaw drift, degrees per metre travelled.
    pub yaw_deg_per_m: f64,
    /// Per-keyframe noise: translation (m, 1 σ per axis) and rotation (degrees, 1 σ per axis).
    pub noise_m: f64,
    pub noise_deg: f64,
    /// One gross error per this many keyframes (0: none), of this size (m along a random direction,
    /// degrees about a random axis).
    pub gross_every: usize,
    pub gross_m: f64,
    pub gross_deg: f64,
}

impl Default for PriorParams {
    fn default() -> Self {
        PriorParams {
            scale_error: 0.005,
            walk_per_m: 0.005,
            yaw_deg_per_m: 0.05,
            noise_m: 0.02,
            noise_deg: 0.2,
            gross_every: 40,
            gross_m: 0.3,
            gross_deg: 3.0,
        }
    }
}

impl PriorParams {
    /// No error at all (the prior equals the exact poses).
    pub fn exact() -> Self {
        PriorParams {
            scale_error: 0.0,
            walk_per_m: 0.0,
            yaw_deg_per_m: 0.0,
            noise_m: 0.0,
            noise_deg: 0.0,
            gross_every: 0,
            gross_m: 0.0,
            gross_deg: 0.0,
        }
    }
}

/// The prior of `exact` keyframe base poses (`T_world_base`, in path order): the first pose is exact
/// (SLAM's map frame starts there), later ones carry the accumulated drift, noise, and gross errors on
/// the keyframes listed in the second value. Deterministic in `seed`.
pub fn prior_trajectory(exact: &[Se3], p: &PriorParams, seed: u64) -> (Vec<Se3>, Vec<usize>) {
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed ^ 0x5EED_D21F_7000_0001);
    let mut gauss = || gaussian(&mut rng);
    let Some(first) = exact.first() else {
        return (Vec::new(), Vec::new());
    };
    // Drifted chain: each exact relative motion, scaled, walked and yawed, composed onto the last.
    let mut chain = vec![*first];
    for w in exact.windows(2) {
        let rel = w[0].inverse() * w[1];
        let d = rel.trans.length();
        let walk = DVec3::new(gauss(), gauss(), gauss()) * (p.walk_per_m * d);
        let yaw = (p.yaw_deg_per_m * d).to_radians();
        let step = Se3::new(rel.rot, rel.trans * (1.0 + p.scale_error) + walk);
        let last = *chain.last().expect("the chain starts with the first pose");
        // Yaw about the world's up axis, applied to the accumulated pose (heading error compounds).
        let drifted = last * step;
        let yawed = Se3::new(
            DQuat::from_rotation_z(yaw) * drifted.rot,
            last.trans + DQuat::from_rotation_z(yaw) * (drifted.trans - last.trans),
        );
        chain.push(yawed);
    }
    // Per-keyframe noise on top of the chain (not accumulated).
    let mut out: Vec<Se3> = chain
        .iter()
        .enumerate()
        .map(|(k, pose)| {
            if k == 0 {
                return *pose;
            }
            let dt = DVec3::new(gauss(), gauss(), gauss()) * p.noise_m;
            let dr = DVec3::new(gauss(), gauss(), gauss()) * p.noise_deg.to_radians();
            Se3::new(DQuat::from_scaled_axis(dr) * pose.rot, pose.trans + dt)
        })
        .collect();
    let mut gross = Vec::new();
    if p.gross_every > 0 && exact.len() > 2 {
        let count = exact.len() / p.gross_every;
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed ^ 0x6105_5E44_0000_0002);
        while gross.len() < count {
            let k = rng.random_range(1..exact.len());
            if gross.contains(&k) {
                continue;
            }
            gross.push(k);
            let dir = unit(&mut rng);
            let axis = unit(&mut rng);
            let pose = out[k];
            out[k] = Se3::new(
                DQuat::from_axis_angle(axis, p.gross_deg.to_radians()) * pose.rot,
                pose.trans + dir * p.gross_m,
            );
        }
        gross.sort_unstable();
    }
    (out, gross)
}

/// A uniformly random unit vector.
fn unit(rng: &mut impl Rng) -> DVec3 {
    loop {
        let v = DVec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        let l = v.length();
        if l > 1e-3 && l <= 1.0 {
            return v / l;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn straight(n: usize, step: f64) -> Vec<Se3> {
        (0..n)
            .map(|k| Se3::new(DQuat::IDENTITY, DVec3::new(k as f64 * step, 0.0, 0.0)))
            .collect()
    }

    #[test]
    fn exact_params_give_the_exact_path_and_errors_grow_with_distance() {
        let path = straight(60, 0.7);
        let (same, gross) = prior_trajectory(&path, &PriorParams::exact(), 1);
        assert!(gross.is_empty());
        for (a, b) in same.iter().zip(&path) {
            assert!(a.distance_to(b) < 1e-12 && a.angle_to(b) < 1e-12);
        }
        let p = PriorParams {
            gross_every: 0,
            noise_m: 0.0,
            noise_deg: 0.0,
            ..Default::default()
        };
        let (drifted, _) = prior_trajectory(&path, &p, 1);
        let err: Vec<f64> = drifted
            .iter()
            .zip(&path)
            .map(|(a, b)| a.distance_to(b))
            .collect();
        assert_eq!(err[0], 0.0);
        // 41 m travelled at ~1 % drift: decimetres at the end, far less early on.
        let travelled = 59.0 * 0.7;
        assert!(
            err[59] > 0.003 * travelled && err[59] < 0.05 * travelled,
            "{}",
            err[59]
        );
        assert!(err[10] < err[59]);
        // Same seed, same prior; another seed, another.
        assert_eq!(prior_trajectory(&path, &p, 1).0, drifted);
        assert_ne!(prior_trajectory(&path, &p, 2).0, drifted);
    }

    #[test]
    fn gross_errors_land_where_reported_with_the_size_asked() {
        let path = straight(80, 0.5);
        let p = PriorParams {
            scale_error: 0.0,
            walk_per_m: 0.0,
            yaw_deg_per_m: 0.0,
            noise_m: 0.0,
            noise_deg: 0.0,
            ..Default::default()
        };
        let (prior, gross) = prior_trajectory(&path, &p, 3);
        assert_eq!(gross.len(), 2);
        for (k, (a, b)) in prior.iter().zip(&path).enumerate() {
            let (dt, dr) = (a.distance_to(b), a.angle_to(b).to_degrees());
            if gross.contains(&k) {
                assert!(
                    (dt - 0.3).abs() < 1e-9 && (dr - 3.0).abs() < 1e-6,
                    "{k}: {dt} {dr}"
                );
            } else {
                assert!(dt < 1e-9 && dr < 1e-6, "{k}: {dt} {dr}");
            }
        }
    }
}
