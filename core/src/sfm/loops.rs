//! Loop verification: whether two images that [`super::places`] retrieved really see the same place, and
//! where the second pass's map lies against the first's.
//!
//! After the adjustment along the path each stretch of the map is locally metric and right; what a
//! drifting prior leaves wrong is where one stretch lies against a much later one. So a loop is verified
//! in 3-D, not in the image: the features each image's adjustment triangulated are matched by descriptor
//! (no prior gate: the prior is what is wrong here), and a rigid transform `T_fix` that carries the later
//! pass's points onto the earlier pass's is fitted by RANSAC over 3-point samples. An inlier lies within
//! `inlier_m` plus `inlier_depth_fraction` of its range from the earlier camera (far points are less
//! certain). Enough inliers make the loop; `T_fix` is the correction that moves the later pass onto the
//! earlier one, which the pose graph then spreads along the path between them. Matching only triangulated
//! features (hundreds, not thousands) also makes verifying thousands of candidates cheap.

use glam::DVec3;
use rayon::prelude::*;
use serde::Serialize;

use super::ba::{self, BaOptions, BaProblem, RelativePrior};
use super::matching::{self, MatchOptions};
use super::places::{self, PlaceOptions, Vocabulary};
use crate::camera::CameraModel;
use crate::geometry::{Se3, Sim3};

/// Loop closure settings: retrieval, verification, what drift is plausible, and the constraints' weights.
#[derive(Clone, Debug)]
pub struct LoopOptions {
    pub enabled: bool,
    /// Two images are a loop candidate only this far apart along the prior's path (m): closer ones
    /// are the odometry's business.
    pub min_path_m: f64,
    pub places: PlaceOptions,
    /// The drift a verified loop may correct: `drift_m + drift_fraction · path` of the later pass's
    /// displacement and `drift_deg + drift_deg_per_m · path` of rotation, the path being the distance
    /// walked between the two passes. A larger correction is a false loop (a look-alike place).
    pub drift_m: f64,
    pub drift_fraction: f64,
    pub drift_deg: f64,
    pub drift_deg_per_m: f64,
    /// 1-σ of a loop constraint between the two keyframes.
    pub sigma_m: f64,
    pub sigma_deg: f64,
    /// 1-σ per step of the adjusted trajectory's own relative poses in the pose graph: how freely the
    /// path bends to close a loop.
    pub chain_sigma_m: f64,
    pub chain_sigma_deg: f64,
    /// After the pose graph, a loop whose constraint is still off by more than this (m) disagrees with
    /// the others: it is dropped and the graph solved again.
    pub max_residual_m: f64,
    pub inlier_m: f64,
    pub inlier_depth_fraction: f64,
    pub ransac_iterations: usize,
    /// A loop needs at least this many 3-D inliers.
    pub min_inliers: usize,
    /// Lowe's ratio of the unguided matching (stricter than the gated matcher's 0.8: nothing else
    /// prunes the candidates).
    pub ratio: f32,
}

impl Default for LoopOptions {
    fn default() -> Self {
        LoopOptions {
            enabled: true,
            min_path_m: 30.0,
            places: PlaceOptions::default(),
            drift_m: 1.0,
            drift_fraction: 0.03,
            drift_deg: 1.0,
            drift_deg_per_m: 0.02,
            sigma_m: 0.05,
            sigma_deg: 0.5,
            chain_sigma_m: 0.01,
            chain_sigma_deg: 0.05,
            max_residual_m: 0.5,
            inlier_m: 0.1,
            inlier_depth_fraction: 0.02,
            ransac_iterations: 300,
            min_inliers: 20,
            ratio: 0.75,
        }
    }
}

/// What one image brings: the features its adjustment triangulated (descriptors back to back, 128 floats
/// each) with their points in the current estimate's world frame, and the camera's centre.
#[derive(Clone, Debug, Default)]
pub struct Landmarks {
    pub descriptors: Vec<f32>,
    pub points: Vec<DVec3>,
    pub centre: DVec3,
}

/// A verified loop between an earlier image `a` and a later image `b`.
#[derive(Clone, Copy, Debug)]
pub struct Verified {
    /// Maps the later pass's world coordinates onto the earlier pass's (`p_a ≈ T_fix · p_b`).
    pub t_fix: Se3,
    pub matches: usize,
    pub inliers: usize,
    /// RMS distance (m) of the inliers after the fit.
    pub rms_m: f64,
}

/// Verifies the candidate loop between `a` (earlier) and `b` (later); `seed` makes the RANSAC
/// repeatable per pair.
pub fn verify(a: &Landmarks, b: &Landmarks, opts: &LoopOptions, seed: u64) -> Option<Verified> {
    let na = a.points.len();
    let nb = b.points.len();
    if na < opts.min_inliers || nb < opts.min_inliers {
        return None;
    }
    // Unguided mutual ratio matching; the rays only mark every feature as matchable.
    let any = |n: usize| vec![Some(DVec3::Z); n];
    let mopts = MatchOptions {
        ratio: opts.ratio,
        ..MatchOptions::default()
    };
    let m = matching::match_features(
        &a.descriptors,
        &any(na),
        &b.descriptors,
        &any(nb),
        None,
        &mopts,
    );
    if m.len() < opts.min_inliers {
        return None;
    }
    let pa: Vec<DVec3> = m.iter().map(|&(i, _, _)| a.points[i as usize]).collect();
    let pb: Vec<DVec3> = m.iter().map(|&(_, j, _)| b.points[j as usize]).collect();
    let tol: Vec<f64> = pa
        .iter()
        .map(|p| opts.inlier_m + opts.inlier_depth_fraction * p.distance(a.centre))
        .collect();
    let inliers_of = |t: &Se3| -> Vec<usize> {
        (0..m.len())
            .filter(|&k| t.transform_point(pb[k]).distance(pa[k]) <= tol[k])
            .collect()
    };
    let fit = |idx: &[usize]| -> Option<Se3> {
        let s: Vec<DVec3> = idx.iter().map(|&k| pb[k]).collect();
        let d: Vec<DVec3> = idx.iter().map(|&k| pa[k]).collect();
        Sim3::umeyama(&s, &d, false).ok().map(|t| t.rigid())
    };
    // A small xorshift: repeatable, and no RNG state shared between the parallel verifications.
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut next = |n: usize| {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state % n as u64) as usize
    };
    let mut best: Vec<usize> = Vec::new();
    for _ in 0..opts.ransac_iterations {
        let s = [next(m.len()), next(m.len()), next(m.len())];
        if s[0] == s[1] || s[1] == s[2] || s[0] == s[2] {
            continue;
        }
        // A sample in a line (or a point) fixes no rotation.
        let area = (pb[s[1]] - pb[s[0]]).cross(pb[s[2]] - pb[s[0]]).length();
        if area < 1e-2 {
            continue;
        }
        let Some(t) = fit(&s) else { continue };
        let inl = inliers_of(&t);
        if inl.len() > best.len() {
            best = inl;
        }
    }
    if best.len() < opts.min_inliers {
        return None;
    }
    // Refit on the inliers until the set settles (twice is enough in practice).
    let mut t_fix = fit(&best)?;
    for _ in 0..2 {
        let inl = inliers_of(&t_fix);
        if inl.len() < opts.min_inliers {
            return None;
        }
        t_fix = fit(&inl)?;
        best = inl;
    }
    let rms_m = (best
        .iter()
        .map(|&k| t_fix.transform_point(pb[k]).distance_squared(pa[k]))
        .sum::<f64>()
        / best.len() as f64)
        .sqrt();
    Some(Verified {
        t_fix,
        matches: m.len(),
        inliers: best.len(),
        rms_m,
    })
}

/// One loop constraint as the report lists it.
#[derive(Clone, Debug, Serialize)]
pub struct LoopEdge {
    pub image_a: usize,
    pub image_b: usize,
    /// The two images' names (filled by the caller, which knows them).
    pub names: [String; 2],
    pub keyframe_a: usize,
    pub keyframe_b: usize,
    /// Distance walked between them along the prior (m).
    pub path_m: f64,
    pub similarity: f32,
    pub matches: usize,
    pub inliers: usize,
    pub rms_m: f64,
    /// How far the verification moves the later keyframe onto the earlier pass (m, degrees).
    pub correction_m: f64,
    pub correction_deg: f64,
}

/// What loop closure found and did.
#[derive(Clone, Debug, Default, Serialize)]
pub struct LoopReport {
    /// Why it did not search, when it did not.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub skipped: Option<String>,
    /// Retrieved image pairs, and keyframe pairs verified from them.
    pub retrieved: usize,
    pub verified: usize,
    /// Verified, but a larger correction than the drift allows (look-alike places).
    pub beyond_drift: usize,
    /// Dropped after the pose graph for disagreeing with the other loops.
    pub inconsistent: usize,
    pub edges: Vec<LoopEdge>,
    /// Largest and mean displacement of a keyframe by the pose graph (m).
    pub max_shift_m: f64,
    pub mean_shift_m: f64,
}

/// The keyframe poses with the loops closed, and the loop constraints for the adjustment.
pub struct Closure {
    pub poses: Vec<Se3>,
    pub constraints: Vec<RelativePrior>,
    pub report: LoopReport,
}

/// Finds, verifies and closes the loops of an adjusted trajectory. `landmarks[i]`: image i's
/// triangulated features; `keyframe_of[i]` its keyframe; `poses` the keyframes' adjusted `T_world_base`
/// and `path_m[k]` the distance walked to keyframe k along the prior. The pose graph bends the adjusted
/// trajectory (its consecutive relative poses as the chain's constraints) to satisfy the loops, with
/// keyframe 0 held. With no loop kept the poses come back unchanged and there are no constraints.
pub fn close_loops(
    landmarks: &[Landmarks],
    keyframe_of: &[usize],
    poses: &[Se3],
    path_m: &[f64],
    cameras: &[CameraModel],
    extrinsics: &[Se3],
    opts: &LoopOptions,
) -> Closure {
    let unchanged = |report: LoopReport| Closure {
        poses: poses.to_vec(),
        constraints: Vec::new(),
        report,
    };
    let walked = path_m.last().copied().unwrap_or(0.0);
    if !opts.enabled {
        return unchanged(LoopReport {
            skipped: Some("loop closure off".into()),
            ..LoopReport::default()
        });
    }
    if walked < opts.min_path_m {
        return unchanged(LoopReport {
            skipped: Some(format!(
                "the path is {walked:.1} m, shorter than a loop ({} m)",
                opts.min_path_m
            )),
            ..LoopReport::default()
        });
    }
    let descs: Vec<&[f32]> = landmarks.iter().map(|l| l.descriptors.as_slice()).collect();
    let Some(voc) = Vocabulary::train(&descs, &opts.places) else {
        return unchanged(LoopReport {
            skipped: Some("too few triangulated features for a vocabulary".into()),
            ..LoopReport::default()
        });
    };
    let vlads: Vec<Vec<f32>> = landmarks
        .par_iter()
        .map(|l| voc.vlad(&l.descriptors))
        .collect();
    let gap = |i: usize, j: usize| (path_m[keyframe_of[i]] - path_m[keyframe_of[j]]).abs();
    let retrieved = places::retrieve(
        &vlads,
        &|i, j| gap(i, j) >= opts.min_path_m,
        opts.places.top_k,
    );

    // Verify every retrieved image pair (earlier image first); keep the best-supported per keyframe pair.
    let n = landmarks.len();
    let verified: Vec<(usize, usize, f32, Verified)> = retrieved
        .par_iter()
        .filter_map(|&(i, j, s)| {
            let (a, b) = if keyframe_of[i] <= keyframe_of[j] {
                (i, j)
            } else {
                (j, i)
            };
            verify(&landmarks[a], &landmarks[b], opts, (a * n + b) as u64).map(|v| (a, b, s, v))
        })
        .collect();
    let mut best: std::collections::BTreeMap<(usize, usize), (usize, usize, f32, Verified)> =
        Default::default();
    for v in verified {
        let key = (keyframe_of[v.0], keyframe_of[v.1]);
        if best.get(&key).is_none_or(|b| b.3.inliers < v.3.inliers) {
            best.insert(key, v);
        }
    }
    let mut report = LoopReport {
        retrieved: retrieved.len(),
        verified: best.len(),
        ..LoopReport::default()
    };
    let mut edges: Vec<(LoopEdge, RelativePrior)> = Vec::new();
    for (&(ka, kb), &(a, b, similarity, v)) in &best {
        let path = gap(a, b);
        let moved = v.t_fix.transform_point(poses[kb].trans) - poses[kb].trans;
        let correction_deg = v
            .t_fix
            .rot
            .angle_between(glam::DQuat::IDENTITY)
            .to_degrees();
        if moved.length() > opts.drift_m + opts.drift_fraction * path
            || correction_deg > opts.drift_deg + opts.drift_deg_per_m * path
        {
            report.beyond_drift += 1;
            continue;
        }
        edges.push((
            LoopEdge {
                image_a: a,
                image_b: b,
                names: Default::default(),
                keyframe_a: ka,
                keyframe_b: kb,
                path_m: path,
                similarity,
                matches: v.matches,
                inliers: v.inliers,
                rms_m: v.rms_m,
                correction_m: moved.length(),
                correction_deg,
            },
            RelativePrior {
                a: ka,
                b: kb,
                t_a_b: poses[ka].inverse() * v.t_fix * poses[kb],
                sigma_m: opts.sigma_m,
                sigma_rad: opts.sigma_deg.to_radians(),
            },
        ));
    }
    if edges.is_empty() {
        return unchanged(report);
    }
    // The pose graph; loops it cannot reconcile with the rest are dropped and it is solved again.
    let mut graph = poses.to_vec();
    for _ in 0..3 {
        graph = pose_graph(poses, &edges, cameras, extrinsics, opts);
        let before = edges.len();
        edges.retain(|(_, c)| {
            let t = graph[c.a].inverse() * graph[c.b];
            (c.t_a_b.inverse() * t).trans.length() <= opts.max_residual_m
        });
        report.inconsistent += before - edges.len();
        if edges.len() == before || edges.is_empty() {
            break;
        }
    }
    if edges.is_empty() {
        return unchanged(report);
    }
    let shifts: Vec<f64> = graph
        .iter()
        .zip(poses)
        .map(|(a, b)| a.trans.distance(b.trans))
        .collect();
    report.max_shift_m = shifts.iter().copied().fold(0.0, f64::max);
    report.mean_shift_m = shifts.iter().sum::<f64>() / shifts.len().max(1) as f64;
    let (list, constraints): (Vec<LoopEdge>, Vec<RelativePrior>) = edges.into_iter().unzip();
    report.edges = list;
    Closure {
        poses: graph,
        constraints,
        report,
    }
}

/// The adjusted trajectory bent to the loops: its consecutive relative poses and the loop constraints,
/// keyframe 0 held. On a solver failure the trajectory stays as it was.
fn pose_graph(
    poses: &[Se3],
    edges: &[(LoopEdge, RelativePrior)],
    cameras: &[CameraModel],
    extrinsics: &[Se3],
    opts: &LoopOptions,
) -> Vec<Se3> {
    let mut relative_priors =
        RelativePrior::chain(poses, opts.chain_sigma_m, opts.chain_sigma_deg.to_radians());
    relative_priors.extend(edges.iter().map(|(_, c)| *c));
    let mut problem = BaProblem {
        cameras: cameras.to_vec(),
        extrinsics: extrinsics.to_vec(),
        poses: poses.to_vec(),
        points: Vec::new(),
        observations: Vec::new(),
        relative_priors,
        absolute_priors: Vec::new(),
    };
    let bopts = BaOptions {
        fixed_poses: vec![0],
        max_iterations: 100,
        // Quadratic far out: a loop that survived verification and the drift test is trusted, and a
        // Huber corner of a few σ would leave a metres-long loop half closed after 100 steps.
        prior_huber: 1e6,
        ..BaOptions::default()
    };
    match ba::solve(&mut problem, &bopts) {
        Ok(_) => problem.poses,
        Err(_) => poses.to_vec(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;
    use rand::{Rng, SeedableRng};

    fn unit(rng: &mut impl Rng) -> Vec<f32> {
        let v: Vec<f32> = (0..128).map(|_| rng.random::<f32>() - 0.5).collect();
        let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        v.into_iter().map(|x| x / n).collect()
    }

    /// The same 120 landmarks seen by two passes whose maps are 6 m and 4° apart (drift), each with 2 cm
    /// of noise; 30 % of the second pass's descriptors belong to other things. The fit recovers the
    /// drift to centimetres; a pass over other landmarks with the same layout statistics is refused.
    #[test]
    fn a_revisit_is_verified_in_3d_and_its_drift_recovered_and_a_different_place_is_not() {
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(3);
        let world: Vec<DVec3> = (0..120)
            .map(|_| {
                DVec3::new(
                    rng.random_range(-10.0..10.0),
                    rng.random_range(3.0..12.0),
                    rng.random_range(0.0..6.0),
                )
            })
            .collect();
        let desc: Vec<Vec<f32>> = (0..120).map(|_| unit(&mut rng)).collect();
        let drift = Se3::new(
            DQuat::from_rotation_z(4f64.to_radians()),
            DVec3::new(5.0, -3.0, 0.4),
        );
        let jitter = |rng: &mut rand_xoshiro::Xoshiro256PlusPlus| {
            DVec3::new(
                rng.random_range(-0.02..0.02),
                rng.random_range(-0.02..0.02),
                rng.random_range(-0.02..0.02),
            )
        };
        let mut a = Landmarks::default();
        let mut b = Landmarks {
            centre: drift.inverse().transform_point(DVec3::ZERO),
            ..Landmarks::default()
        };
        for k in 0..120 {
            a.points.push(world[k] + jitter(&mut rng));
            a.descriptors.extend(&desc[k]);
            // The later pass's map sits at drift⁻¹ of the truth; some of its features are other things.
            let d = if k % 10 < 3 {
                unit(&mut rng)
            } else {
                desc[k].clone()
            };
            b.points
                .push(drift.inverse().transform_point(world[k]) + jitter(&mut rng));
            b.descriptors.extend(d);
        }
        let v = verify(&a, &b, &LoopOptions::default(), 1).expect("verified");
        assert!(v.inliers >= 80 && v.inliers <= 84, "{v:?}");
        let err = v.t_fix.inverse() * drift;
        assert!(err.trans.length() < 0.05, "{:?}", err.trans);
        assert!(err.rot.angle_between(DQuat::IDENTITY).to_degrees() < 0.3);
        assert!(v.rms_m < 0.05, "{v:?}");

        // Another place: the same descriptors (a repeated facade) on landmarks laid out differently.
        let mut c = b.clone();
        for p in c.points.iter_mut() {
            *p = DVec3::new(
                rng.random_range(-10.0..10.0),
                rng.random_range(3.0..12.0),
                rng.random_range(0.0..6.0),
            );
        }
        assert!(verify(&a, &c, &LoopOptions::default(), 1).is_none());
    }

    /// A rig walks twice around a 40 × 30 m block (keyframes every 2 m) past landmarks along its sides,
    /// each with its own descriptor. The adjusted trajectory it is given has drifted in yaw (0.02°/m)
    /// and heading, so the second lap's map is metres off the first's, and each image's landmarks carry
    /// that drift. Loop closure must find the laps' common places, and the pose graph must bring the second
    /// lap back onto the first: the keyframes' error against the truth falls tenfold.
    #[test]
    fn a_drifted_second_lap_is_found_and_brought_back_onto_the_first() {
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(5);
        // The block's perimeter, walked twice anticlockwise.
        let (w, h) = (40.0, 30.0);
        let perimeter = 2.0 * (w + h);
        let at = |s: f64| -> (DVec3, f64) {
            let s = s % perimeter;
            if s < w {
                (DVec3::new(s, 0.0, 0.0), 0.0)
            } else if s < w + h {
                (DVec3::new(w, s - w, 0.0), 90f64.to_radians())
            } else if s < 2.0 * w + h {
                (DVec3::new(w - (s - w - h), h, 0.0), 180f64.to_radians())
            } else {
                (
                    DVec3::new(0.0, h - (s - 2.0 * w - h), 0.0),
                    270f64.to_radians(),
                )
            }
        };
        let step = 2.0;
        let n = (2.0 * perimeter / step) as usize;
        let truth: Vec<Se3> = (0..n)
            .map(|k| {
                let (c, yaw) = at(k as f64 * step);
                Se3::new(DQuat::from_rotation_z(yaw), c)
            })
            .collect();
        // Drift: yaw accumulating at 0.02°/m about the walk's current position.
        let mut est = vec![truth[0]];
        for k in 1..n {
            let rel = truth[k - 1].inverse() * truth[k];
            let bend = Se3::new(
                DQuat::from_rotation_z((0.02 * step).to_radians()),
                DVec3::ZERO,
            );
            est.push(est[k - 1] * bend * rel);
        }
        // Landmarks: walls 4 m either side of the path, every 0.5 m, at heights 0.5–4 m.
        let mut points = Vec::new();
        let mut s = 0.0;
        while s < perimeter {
            let (c, yaw) = at(s);
            let side = DVec3::new(-yaw.sin(), yaw.cos(), 0.0);
            for off in [-4.0, 4.0] {
                points.push(c + side * off + DVec3::Z * rng.random_range(0.5..4.0));
            }
            s += 0.5;
        }
        let descs: Vec<Vec<f32>> = points.iter().map(|_| unit(&mut rng)).collect();
        // One image per keyframe (a camera with the base's axes), seeing landmarks within 8 m, each
        // placed where the drifted keyframe's map puts it.
        let landmarks: Vec<Landmarks> = (0..n)
            .map(|k| {
                let to_est = est[k] * truth[k].inverse();
                let mut l = Landmarks {
                    centre: est[k].trans,
                    ..Landmarks::default()
                };
                for (p, d) in points.iter().zip(&descs) {
                    if p.distance(truth[k].trans) < 8.0 {
                        l.points.push(to_est.transform_point(*p));
                        l.descriptors.extend(d);
                    }
                }
                l
            })
            .collect();
        let keyframe_of: Vec<usize> = (0..n).collect();
        let path: Vec<f64> = (0..n).map(|k| k as f64 * step).collect();
        let cam = CameraModel::pinhole(64, 48, 50.0, 50.0, 31.5, 23.5);
        let opts = LoopOptions {
            places: PlaceOptions {
                words: 16,
                ..PlaceOptions::default()
            },
            ..LoopOptions::default()
        };
        let err = |poses: &[Se3]| -> f64 {
            (poses
                .iter()
                .zip(&truth)
                .map(|(a, b)| a.trans.distance_squared(b.trans))
                .sum::<f64>()
                / n as f64)
                .sqrt()
        };
        let before = err(&est);
        let closure = close_loops(
            &landmarks,
            &keyframe_of,
            &est,
            &path,
            &[cam],
            &[Se3::IDENTITY],
            &opts,
        );
        let after = err(&closure.poses);
        let r = &closure.report;
        assert!(before > 1.0, "the drift must be a metre or more: {before}");
        assert!(r.edges.len() >= 10, "{r:?}");
        // Every kept loop joins the two laps at the same place.
        for e in &r.edges {
            let m = e.path_m % perimeter;
            let d = m.min(perimeter - m);
            assert!(
                d <= 2.0 * step + 1e-9,
                "a loop between places {} m apart along the walk: {e:?}",
                e.path_m
            );
        }
        assert!(
            after < before / 10.0,
            "RMS error {before:.2} m → {after:.2} m; {r:?}"
        );

        // With loop closure off, or a walk too short for a loop, nothing moves.
        let off = close_loops(
            &landmarks,
            &keyframe_of,
            &est,
            &path,
            &[cam],
            &[Se3::IDENTITY],
            &LoopOptions {
                enabled: false,
                ..opts.clone()
            },
        );
        assert!(off.constraints.is_empty() && off.report.skipped.is_some());
        assert_eq!(err(&off.poses), before);
    }
}
