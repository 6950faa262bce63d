//! The poses stage (the paper's §Large-scale Pose Trajectory Estimation): the SLAM trajectory
//! bootstraps structure from motion instead of COLMAP's search from scratch.
//!
//! 1. SIFT features per image ([`super::features`]), masked to the lens's valid circle and off the sky;
//! 2. candidate pairs from the prior ([`super::pairs`]), matched under the prior's epipolar gate
//!    ([`super::matching`]); on a walk long enough for loops, only pairs near each other along it;
//! 3. tracks ([`super::tracks`]), triangulated from the prior poses ([`super::triangulate`]);
//! 4. bundle adjustment ([`super::ba`]) of one pose per keyframe (the rig's extrinsics fixed), the points,
//!    and the SLAM odometry between consecutive keyframes as prior terms, in rounds: re-triangulate with
//!    the refined poses under a tighter reprojection gate, adjust again;
//! 5. loop closure: revisits found from the images ([`super::places`]), verified in 3-D against the
//!    adjusted map and closed by a pose graph ([`super::loops`]); the pairs far apart along the walk are
//!    then matched under the closed poses and step 4 runs again with the loops as constraints. A drifting
//!    prior puts a revisit's two passes metres apart, so its gate cannot match them (campus: ATE 75x
//!    below the prior's with this, 1.1x without; BENCHMARKS.md);
//! 6. a Sim(3) (Umeyama, trimmed) from the refined keyframe centres to the prior's restores the SLAM's
//!    metric frame.
//!
//! The rig: frames that share a `keyframe` index were taken at one instant by cameras whose relative
//! poses are the calibration; the keyframe's pose is its first camera's (the reference camera), the
//! others hang off it by `T_ref_cam`, read from the prior (SLAM moves the rig as one body). Frames
//! without a keyframe index are each their own keyframe.

use std::collections::BTreeMap;

use glam::{DVec2, DVec3};
use rayon::prelude::*;
use serde::Serialize;

use super::ba::{self, AbsolutePrior, BaOptions, BaProblem, BaReport, Observation, RelativePrior};
use super::features::{self, Features, SiftOptions};
use super::loops::{self, Landmarks, LoopOptions, LoopReport};
use super::matching::{self, EpipolarGate, MatchOptions};
use super::pairs::{self, PairOptions};
use super::tracks::{self, FeatureRef, PairMatches, TrackStats};
use super::triangulate::{self, TriangulateOptions, View};
use crate::camera::CameraModel;
use crate::geometry::{Se3, Sim3};

/// One image of the problem: its name (for messages and outputs), camera, prior pose and rig slot.
#[derive(Clone, Debug)]
pub struct PoseFrame {
    pub name: String,
    pub model: CameraModel,
    /// OpenCV-axes `T_world_cam` from the SLAM prior.
    pub prior: Se3,
    pub keyframe: Option<usize>,
    pub camera: Option<String>,
}

/// A decoded image for feature extraction: grey in [0, 1] and the usable-pixel mask (not sky).
pub struct GrayImage {
    pub width: u32,
    pub height: u32,
    pub gray: Vec<f32>,
    pub sky: Option<Vec<bool>>,
}

/// Pixels of the working image the poses stage aims for when the user names no downscale: about a
/// megapixel. Its thresholds (SIFT's scale range, the reprojection gates in pixels, the Huber scale) are
/// tuned at that size; on the fox capture at its own 1080×1920 with a drifting prior, full size left the
/// rotations 1.3x better than the prior's, half size 6.9x (BENCHMARKS.md, poses at a working resolution).
pub const WORKING_PIXELS: u64 = 1 << 20;

/// The smallest integer downscale that brings the largest image (`width`, `height` in pixels) within
/// [`WORKING_PIXELS`]: 1 for images of a megapixel or less, 2 for 1080p, 3 up to 9 MP.
pub fn working_downscale(width: u32, height: u32) -> u32 {
    let px = width as u64 * height as u64;
    let mut f = 1u64;
    while px > WORKING_PIXELS * f * f {
        f += 1;
    }
    f as u32
}

/// Settings of every stage.
#[derive(Clone, Debug)]
pub struct PosesOptions {
    pub sift: SiftOptions,
    pub pairs: PairOptions,
    pub matching: MatchOptions,
    /// Reprojection gate (px) of the triangulate ↔ adjust rounds: loose while the poses are the prior's
    /// (its gross errors are several pixels), then tighter as they improve.
    pub rounds_px: Vec<f64>,
    pub min_angle_deg: f64,
    /// The SLAM odometry's 1-σ between consecutive keyframes.
    pub odometry_sigma_m: f64,
    pub odometry_sigma_deg: f64,
    /// A weak pull of each keyframe towards its prior pose: fixes the gauge in the SLAM frame.
    pub absolute_sigma_m: f64,
    pub absolute_sigma_deg: f64,
    pub huber_px: f64,
    /// An image counts as registered with at least this many inlier observations.
    pub min_observations: usize,
    pub refine_extrinsics: bool,
    pub loops: LoopOptions,
}

impl Default for PosesOptions {
    fn default() -> Self {
        PosesOptions {
            // COLMAP's peak threshold (0.02 / 3) is tuned for photographs; on 360x270 renders of the
            // synthetic street it kept ~250 features per image and left the poses 4x better than the
            // prior; 0.0025 keeps ~650 and 12x (BENCHMARKS.md, poses).
            sift: SiftOptions {
                peak_threshold: 0.0025,
                ..SiftOptions::default()
            },
            pairs: PairOptions::default(),
            matching: MatchOptions::default(),
            rounds_px: vec![8.0, 4.0, 2.0],
            min_angle_deg: 1.5,
            odometry_sigma_m: 0.03,
            odometry_sigma_deg: 0.3,
            absolute_sigma_m: 1.0,
            absolute_sigma_deg: 10.0,
            huber_px: 2.0,
            min_observations: 15,
            refine_extrinsics: false,
            loops: LoopOptions::default(),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum PosesError {
    #[error("{0}")]
    Image(String),
    #[error("features of {image}: {detail}")]
    Features { image: String, detail: String },
    #[error("rig: {0}")]
    Rig(String),
    #[error("nothing to adjust: {0}")]
    Empty(String),
    /// `images`: the images of the keyframes the failure points at (empty when it names none).
    #[error("bundle adjustment, round {round}: {source}{}", name_images(images))]
    Ba {
        round: usize,
        images: Vec<String>,
        source: ba::BaError,
    },
    #[error("Sim(3) alignment to the prior: {0}")]
    Align(String),
}

impl PosesError {
    /// An `Empty` error without a message gets `detail`.
    fn or_empty(self, detail: String) -> PosesError {
        match self {
            PosesError::Empty(m) if m.is_empty() => PosesError::Empty(detail),
            e => e,
        }
    }
}

fn name_images(images: &[String]) -> String {
    const SHOWN: usize = 6;
    if images.is_empty() {
        return String::new();
    }
    let mut s = format!(
        "; the images concerned: {}",
        images[..images.len().min(SHOWN)].join(", ")
    );
    if images.len() > SHOWN {
        s += &format!(" and {} more", images.len() - SHOWN);
    }
    s
}

/// The images of the keyframes a BA failure names (`frames` in input order, `keyframe_of` per frame).
fn ba_failure(
    round: usize,
    source: ba::BaError,
    frames: &[PoseFrame],
    keyframe_of: &[usize],
) -> PosesError {
    let poses: &[usize] = match &source {
        ba::BaError::Diverged { poses, .. } | ba::BaError::Singular { poses, .. } => poses,
        _ => &[],
    };
    let images = poses
        .iter()
        .flat_map(|&k| (0..frames.len()).filter(move |&i| keyframe_of[i] == k))
        .map(|i| frames[i].name.clone())
        .collect();
    PosesError::Ba {
        round: round + 1,
        images,
        source,
    }
}

/// One stage's wall time.
#[derive(Clone, Debug, Serialize)]
pub struct StageTime {
    pub stage: String,
    pub seconds: f64,
}

/// Per-image outcome.
#[derive(Clone, Debug, Serialize)]
pub struct ImageReport {
    pub name: String,
    pub features: usize,
    pub observations: usize,
    pub registered: bool,
    /// Its keyframe's part of the match graph (0 .. components, numbered in keyframe order).
    pub part: usize,
    /// Why not, when not.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

/// What the poses stage did and how well.
#[derive(Clone, Debug, Serialize)]
pub struct PosesReport {
    pub images: usize,
    pub keyframes: usize,
    pub registered: usize,
    pub registered_fraction: f64,
    pub candidate_pairs: usize,
    pub matched_pairs: usize,
    pub matches: usize,
    pub tracks: TrackStats,
    pub points: usize,
    pub observations: usize,
    pub observations_per_image_mean: f64,
    pub observations_per_image_min: usize,
    /// Reprojection RMSE (px) of the first round's points on the prior poses, and at the end.
    pub rmse_prior_px: f64,
    pub rmse_px: f64,
    pub rounds: Vec<BaReport>,
    /// Refined → prior frame (scale ≈ 1: the odometry priors already carry metric scale).
    pub sim3_scale: f64,
    pub sim3_inliers: usize,
    /// Connected parts of the match graph over keyframes (1: every keyframe tied to the rest by
    /// features; more: only the odometry holds them together).
    pub components: usize,
    /// Loop closure: the revisits found, verified and closed.
    pub loops: LoopReport,
    /// The map's scale against the lidar (`lidar_scale`), when the frames have lidar depth.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lidar_scale: Option<LidarScale>,
    pub stages: Vec<StageTime>,
    pub per_image: Vec<ImageReport>,
}

/// The refined problem.
pub struct PosesResult {
    /// OpenCV-axes `T_world_cam` per frame, in the input's order (unregistered images keep the prior's
    /// pose carried by their keyframe's correction where the keyframe registered).
    pub poses: Vec<Se3>,
    pub points: Vec<DVec3>,
    /// Each point's observations: (frame index, pixel).
    pub tracks: Vec<Vec<(usize, DVec2)>>,
    pub features: Vec<Features>,
    pub report: PosesReport,
}

/// A stage's progress: (stage, done, total).
pub type ProgressFn<'a> = &'a (dyn Fn(&str, usize, usize) + Sync);

/// The rig structure of the frames: keyframe and camera slot of each frame, the camera models, and
/// each slot's `T_ref_cam` from the prior.
struct Rig {
    keyframe_of: Vec<usize>,
    camera_of: Vec<usize>,
    models: Vec<CameraModel>,
    extrinsics: Vec<Se3>,
    /// Prior `T_world_ref` per keyframe.
    prior_base: Vec<Se3>,
    /// Keyframe order along the path (for odometry), as given by the keyframe indices.
    keyframes: usize,
}

fn rig_of(frames: &[PoseFrame]) -> Result<Rig, PosesError> {
    let n = frames.len();
    let rig_mode = frames
        .iter()
        .all(|f| f.keyframe.is_some() && f.camera.is_some());
    let mut camera_names: Vec<String> = Vec::new();
    let mut keyframe_ids: BTreeMap<usize, usize> = BTreeMap::new();
    let mut keyframe_of = vec![0; n];
    let mut camera_of = vec![0; n];
    if rig_mode {
        for f in frames {
            let c = f.camera.clone().unwrap_or_default();
            if !camera_names.contains(&c) {
                camera_names.push(c);
            }
            let next = keyframe_ids.len();
            keyframe_ids.entry(f.keyframe.unwrap_or(0)).or_insert(next);
        }
        // Keyframes in path order (their indices), not file order.
        for (k, v) in keyframe_ids.values_mut().enumerate() {
            *v = k;
        }
        for (i, f) in frames.iter().enumerate() {
            keyframe_of[i] = keyframe_ids[&f.keyframe.unwrap_or(0)];
            let c = f.camera.as_deref().unwrap_or_default();
            camera_of[i] = camera_names.iter().position(|x| x == c).unwrap_or(0);
        }
    } else {
        keyframe_of = (0..n).collect();
    }
    let keyframes = if rig_mode { keyframe_ids.len() } else { n };
    let ncam = if rig_mode { camera_names.len() } else { 0 };
    // Models: one per rig camera (must agree), or one per distinct model without a rig.
    let mut models: Vec<CameraModel> = Vec::new();
    if rig_mode {
        models = vec![frames[0].model; ncam];
        let mut seen = vec![false; ncam];
        for (i, f) in frames.iter().enumerate() {
            let c = camera_of[i];
            if !seen[c] {
                models[c] = f.model;
                seen[c] = true;
            } else if models[c] != f.model {
                return Err(PosesError::Rig(format!(
                    "{} has other intrinsics than the rest of camera {:?}",
                    f.name, camera_names[c]
                )));
            }
        }
    } else {
        for (i, f) in frames.iter().enumerate() {
            camera_of[i] = match models.iter().position(|m| *m == f.model) {
                Some(c) => c,
                None => {
                    models.push(f.model);
                    models.len() - 1
                }
            };
        }
    }
    let ncam = models.len();
    // Reference slot per keyframe: camera 0 when present. Extrinsics from the first keyframe that has
    // both the reference camera and the other one.
    let mut by_key: Vec<Vec<usize>> = vec![Vec::new(); keyframes];
    for i in 0..n {
        by_key[keyframe_of[i]].push(i);
    }
    let mut extrinsics = vec![Se3::IDENTITY; ncam];
    if rig_mode {
        let mut found = vec![false; ncam];
        found[0] = true;
        for members in &by_key {
            let Some(&r) = members.iter().find(|&&i| camera_of[i] == 0) else {
                continue;
            };
            for &i in members {
                if !found[camera_of[i]] {
                    extrinsics[camera_of[i]] = frames[r].prior.inverse() * frames[i].prior;
                    found[camera_of[i]] = true;
                }
            }
        }
        if let Some(c) = found.iter().position(|f| !f) {
            return Err(PosesError::Rig(format!(
                "camera {:?} never appears at a keyframe together with {:?}: its place on the rig is unknown",
                camera_names[c], camera_names[0]
            )));
        }
    }
    let prior_base: Vec<Se3> = by_key
        .iter()
        .map(|members| {
            let i = members[0];
            frames[i].prior * extrinsics[camera_of[i]].inverse()
        })
        .collect();
    Ok(Rig {
        keyframe_of,
        camera_of,
        models,
        extrinsics,
        prior_base,
        keyframes,
    })
}

/// The mask of pixels whose ray the lens model can invert (the fisheye's circle), 2 px in from its edge.
pub fn lens_mask(model: &CameraModel) -> Vec<bool> {
    let (w, h) = (model.width as usize, model.height as usize);
    let amax = model.valid_angle();
    // Whether each pixel unprojects, on the image grown by 2 px each side (one Newton solve per pixel),
    // then the five lookups per pixel.
    const M: usize = 2;
    let (gw, gh) = (w + 2 * M, h + 2 * M);
    let valid: Vec<bool> = (0..gw * gh)
        .into_par_iter()
        .map(|k| {
            let p = DVec2::new((k % gw) as f64 - M as f64, (k / gw) as f64 - M as f64);
            model.unproject_within(p, amax).is_some()
        })
        .collect();
    let mut mask = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            let (gx, gy) = (x + M, y + M);
            mask[y * w + x] = [(0, 0), (M, 0), (0, M)]
                .iter()
                .flat_map(|&(dx, dy)| [(gx + dx, gy + dy), (gx - dx, gy - dy)])
                .all(|(u, v)| valid[v * gw + u]);
        }
    }
    mask
}

/// Refines the prior poses of `frames`. `load(i)` decodes image i (grey, optional sky mask).
pub fn refine_poses(
    frames: &[PoseFrame],
    load: &(dyn Fn(usize) -> Result<GrayImage, String> + Sync),
    opts: &PosesOptions,
    progress: ProgressFn,
) -> Result<PosesResult, PosesError> {
    let clock = web_time::Instant::now();
    let mut stages: Vec<StageTime> = Vec::new();
    let mut lap = {
        let mut last = 0.0;
        move |stages: &mut Vec<StageTime>, name: &str| {
            let now = clock.elapsed().as_secs_f64();
            stages.push(StageTime {
                stage: name.into(),
                seconds: now - last,
            });
            last = now;
        }
    };
    let n = frames.len();
    if n < 2 {
        return Err(PosesError::Empty(format!("{n} image(s); need at least 2")));
    }
    let rig = rig_of(frames)?;

    // 1. Features.
    let masks: Vec<Vec<bool>> = rig.models.par_iter().map(lens_mask).collect();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let features: Vec<Features> = (0..n)
        .into_par_iter()
        .map(|i| {
            let img = load(i).map_err(PosesError::Image)?;
            let m = &frames[i].model;
            if (img.width, img.height) != (m.width, m.height) {
                return Err(PosesError::Features {
                    image: frames[i].name.clone(),
                    detail: format!(
                        "image is {}x{}, its camera {}x{}",
                        img.width, img.height, m.width, m.height
                    ),
                });
            }
            let mut mask = masks[rig.camera_of[i]].clone();
            if let Some(sky) = &img.sky {
                for (k, s) in mask.iter_mut().zip(sky) {
                    *k &= !*s;
                }
            }
            let f = features::extract(img.width, img.height, &img.gray, Some(&mask), &opts.sift)
                .map_err(|e| PosesError::Features {
                    image: frames[i].name.clone(),
                    detail: e.to_string(),
                })?;
            let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress("features", d, n);
            Ok(f)
        })
        .collect::<Result<_, _>>()?;
    lap(&mut stages, "features");

    // Each feature's ray in its camera frame.
    let rays: Vec<Vec<Option<DVec3>>> = features
        .par_iter()
        .enumerate()
        .map(|(i, f)| {
            let m = &frames[i].model;
            let amax = m.valid_angle();
            f.keypoints
                .iter()
                .map(|k| {
                    m.unproject_within(DVec2::new(k.x as f64, k.y as f64), amax)
                        .map(|d| d.normalize())
                })
                .collect()
        })
        .collect();

    // 2. Pairs and matches.
    let cams: Vec<(CameraModel, Se3)> = frames.iter().map(|f| (f.model, f.prior)).collect();
    let candidates = pairs::candidate_pairs(&cams, &opts.pairs);
    // On a walk long enough for loops, pairs far apart along it are left to after loop closure: the
    // prior's drift between them (metres on a campus) makes its epipolar gate pick wrong matches, which
    // chain the two passes into tracks that bend the adjustment instead of closing the loop.
    let path_m = path_lengths(&rig.prior_base);
    let search_loops =
        opts.loops.enabled && path_m.last().copied().unwrap_or(0.0) >= opts.loops.min_path_m;
    let far = |i: usize, j: usize| {
        search_loops
            && (path_m[rig.keyframe_of[i]] - path_m[rig.keyframe_of[j]]).abs()
                >= opts.loops.min_path_m
    };
    let near: Vec<pairs::Pair> = candidates
        .iter()
        .filter(|p| !far(p.i, p.j))
        .cloned()
        .collect();
    let prior_cams: Vec<Se3> = frames.iter().map(|f| f.prior).collect();
    let mut matches = match_pairs(&near, &prior_cams, &features, &rays, opts, progress);
    let mut match_count: usize = matches.iter().map(|(_, m)| m.len()).sum();
    let mut matched_pairs = matches.len();
    let mut candidate_count = near.len();
    lap(&mut stages, "matching");

    // 3. Tracks.
    let counts: Vec<usize> = features.iter().map(Features::len).collect();
    let (mut tracks, mut track_stats) = tracks::build_tracks(&counts, &matches);
    let mut part_of_keyframe = components(rig.keyframes, &matches, &rig.keyframe_of);
    lap(&mut stages, "tracks");

    // 4. Triangulate ↔ adjust rounds along the path.
    let mut problem = BaProblem {
        cameras: rig.models.clone(),
        extrinsics: rig.extrinsics.clone(),
        poses: rig.prior_base.clone(),
        points: Vec::new(),
        observations: Vec::new(),
        relative_priors: odometry(&rig.prior_base, opts),
        absolute_priors: absolute(&rig.prior_base, opts),
    };
    let input = RoundInput {
        frames,
        rig: &rig,
        features: &features,
        opts,
        progress,
    };
    let empty = |tracks: usize, matched: usize, candidates: usize| {
        format!(
            "no track could be triangulated ({tracks} tracks from {matched} matched pairs of {candidates} candidates; are the images textureless, or the prior far off?)"
        )
    };
    let first = adjust_rounds(&input, &mut problem, &tracks, 0)
        .map_err(|e| e.or_empty(empty(tracks.len(), matches.len(), candidates.len())))?;
    let rmse_prior = first.rmse_first;
    let mut rounds = first.rounds;
    let obs_feature = first.obs_feature;
    lap(&mut stages, "adjust");

    // 5. Loop closure: revisits the prior's drift hides, found from the images, verified in 3-D, closed by
    // a pose graph; then the pairs far apart along the path are matched under the closed poses and the
    // rounds run again with the loops as constraints.
    let landmarks = landmarks_of(&input, &problem, &obs_feature);
    let mut closure = loops::close_loops(
        &landmarks,
        &rig.keyframe_of,
        &problem.poses,
        &path_m,
        &rig.models,
        &rig.extrinsics,
        &opts.loops,
    );
    drop(landmarks);
    for e in &mut closure.report.edges {
        e.names = [
            frames[e.image_a].name.clone(),
            frames[e.image_b].name.clone(),
        ];
    }
    lap(&mut stages, "loops");
    if search_loops {
        problem.poses = closure.poses.clone();
        let closed: Vec<Se3> = (0..n)
            .map(|i| problem.poses[rig.keyframe_of[i]] * problem.extrinsics[rig.camera_of[i]])
            .collect();
        let closed_cams: Vec<(CameraModel, Se3)> = frames
            .iter()
            .zip(&closed)
            .map(|(f, p)| (f.model, *p))
            .collect();
        let far_candidates: Vec<pairs::Pair> = pairs::candidate_pairs(&closed_cams, &opts.pairs)
            .into_iter()
            .filter(|p| far(p.i, p.j))
            .collect();
        let far_matches = match_pairs(&far_candidates, &closed, &features, &rays, opts, progress);
        candidate_count = near.len() + far_candidates.len();
        matches.extend(far_matches);
        matches.sort_by_key(|(p, _)| *p);
        match_count = matches.iter().map(|(_, m)| m.len()).sum();
        matched_pairs = matches.len();
        (tracks, track_stats) = tracks::build_tracks(&counts, &matches);
        part_of_keyframe = components(rig.keyframes, &matches, &rig.keyframe_of);
        problem.relative_priors = odometry(&rig.prior_base, opts);
        problem
            .relative_priors
            .extend(closure.constraints.iter().copied());
        problem.absolute_priors = absolute(&closure.poses, opts);
        lap(&mut stages, "matching after loops");
        let second = adjust_rounds(&input, &mut problem, &tracks, rounds.len())
            .map_err(|e| e.or_empty(empty(tracks.len(), matched_pairs, candidate_count)))?;
        rounds.extend(second.rounds);
        lap(&mut stages, "adjust after loops");
    }
    let components = part_of_keyframe.iter().max().map_or(0, |&p| p + 1);

    // Final inlier gate: drop observations beyond the last round's gate and recount.
    let last_gate = opts.rounds_px.last().copied().unwrap_or(4.0);
    let errs = ba::reprojection_errors(&problem);
    let mut obs_per_image = vec![0usize; n];
    let mut point_tracks: Vec<Vec<(usize, DVec2)>> = vec![Vec::new(); problem.points.len()];
    // Map (keyframe, camera) → frame index.
    let mut frame_of: BTreeMap<(usize, usize), usize> = BTreeMap::new();
    for i in 0..n {
        frame_of.insert((rig.keyframe_of[i], rig.camera_of[i]), i);
    }
    let mut final_errs = Vec::new();
    for (o, e) in problem.observations.iter().zip(&errs) {
        if e.is_some_and(|e| e <= last_gate) {
            if let Some(&i) = frame_of.get(&(o.pose, o.camera)) {
                final_errs.push(*e);
                obs_per_image[i] += 1;
                point_tracks[o.point].push((i, o.uv));
            }
        }
    }
    lap(&mut stages, "inlier gate");

    // 5. Sim(3) to the prior's keyframe centres (trimmed Umeyama).
    let (sim, inliers) = align_to_prior(&problem.poses, &rig.prior_base)?;
    let base: Vec<Se3> = problem
        .poses
        .iter()
        .map(|p| sim.transform_pose(p))
        .collect();
    let points: Vec<DVec3> = problem
        .points
        .iter()
        .map(|&p| sim.transform_point(p))
        .collect();
    lap(&mut stages, "align");

    let poses: Vec<Se3> = (0..n)
        .map(|i| {
            let e = problem.extrinsics[rig.camera_of[i]];
            // The extrinsic is metric; the Sim(3) scale is the SLAM frame's, ≈ 1.
            base[rig.keyframe_of[i]] * e
        })
        .collect();
    let per_image: Vec<ImageReport> = (0..n)
        .map(|i| {
            let registered = obs_per_image[i] >= opts.min_observations;
            ImageReport {
                name: frames[i].name.clone(),
                features: features[i].len(),
                observations: obs_per_image[i],
                registered,
                part: part_of_keyframe[rig.keyframe_of[i]],
                reason: (!registered).then(|| {
                    if features[i].len() < opts.min_observations {
                        format!(
                            "{} features (textureless, or masked out)",
                            features[i].len()
                        )
                    } else {
                        format!(
                            "{} observations after adjustment (fewer than {}): its matches did not survive",
                            obs_per_image[i], opts.min_observations
                        )
                    }
                }),
            }
        })
        .collect();
    let registered = per_image.iter().filter(|r| r.registered).count();
    let total_obs: usize = obs_per_image.iter().sum();
    let report = PosesReport {
        images: n,
        keyframes: rig.keyframes,
        registered,
        registered_fraction: registered as f64 / n as f64,
        candidate_pairs: candidate_count,
        matched_pairs,
        matches: match_count,
        tracks: track_stats,
        points: point_tracks.iter().filter(|t| t.len() >= 2).count(),
        observations: total_obs,
        observations_per_image_mean: total_obs as f64 / n as f64,
        observations_per_image_min: obs_per_image.iter().copied().min().unwrap_or(0),
        rmse_prior_px: rmse_prior,
        rmse_px: rmse(&final_errs),
        rounds,
        sim3_scale: sim.scale,
        sim3_inliers: inliers,
        components,
        loops: closure.report,
        lidar_scale: None,
        stages,
        per_image,
    };
    Ok(PosesResult {
        poses,
        points,
        tracks: point_tracks,
        features,
        report,
    })
}

/// The map's scale against the lidar: the SfM points' ranges from the cameras that observe them against
/// the lidar returns at the same pixels. The refined map takes its scale from the prior (the Sim(3) back to
/// its frame), and a SLAM prior's scale drifts (the synthetic one by 0.5 %); the lidar's ranges are metric
/// and are what training fits the field to, so a map whose cameras are 0.5 % too far apart puts the field's
/// surfaces centimetres off (measured on the ci world: median error 3.2 → 4.7 cm for a pure 0.65 % scale).
#[derive(Clone, Debug, Serialize)]
pub struct LidarScale {
    /// Median of lidar range / SfM range over the samples (1 = metric).
    pub ratio: f64,
    /// Standard error of that median (1.2533 · 1.4826 · MAD / √n).
    pub std_error: f64,
    pub samples: usize,
    /// Whether the map was rescaled by `ratio` (about its cameras' centroid): enough samples and a ratio
    /// beyond three standard errors and 0.05 % of 1.
    pub applied: bool,
}

/// Samples a scale needs before it is trusted.
const LIDAR_SCALE_MIN_SAMPLES: usize = 100;

/// Measures the map's scale against lidar depth: `range(frame, pixel)` is the lidar range (metres, from
/// that camera's centre) at a track's pixel, when one is there. Points seen closer than 0.5 m or with a
/// ratio off by more than 20 % (a return of another surface at that pixel) are left out.
pub fn lidar_scale(
    poses: &[Se3],
    points: &[DVec3],
    tracks: &[Vec<(usize, DVec2)>],
    range: &dyn Fn(usize, DVec2) -> Option<f64>,
) -> Option<LidarScale> {
    let mut ratios = Vec::new();
    for (point, obs) in points.iter().zip(tracks) {
        if obs.len() < 2 || !point.is_finite() {
            continue;
        }
        for &(i, uv) in obs {
            let Some(pose) = poses.get(i) else { continue };
            let sfm = (*point - pose.trans).length();
            if sfm < 0.5 {
                continue;
            }
            if let Some(r) = range(i, uv) {
                let q = r / sfm;
                if (0.8..1.25).contains(&q) {
                    ratios.push(q);
                }
            }
        }
    }
    if ratios.is_empty() {
        return None;
    }
    let n = ratios.len();
    let median = crate::eval::metrics::median(&ratios);
    let dev: Vec<f64> = ratios.iter().map(|q| (q - median).abs()).collect();
    let mad = crate::eval::metrics::median(&dev);
    let std_error = 1.2533 * 1.4826 * mad / (n as f64).sqrt();
    let applied =
        n >= LIDAR_SCALE_MIN_SAMPLES && (median - 1.0).abs() > (3.0 * std_error).max(5e-4);
    Some(LidarScale {
        ratio: median,
        std_error,
        samples: n,
        applied,
    })
}

/// Scales a map by `s` about the centroid of its camera centres: poses and points.
pub fn rescale(poses: &mut [Se3], points: &mut [DVec3], s: f64) {
    if poses.is_empty() {
        return;
    }
    let c = poses.iter().map(|p| p.trans).sum::<DVec3>() / poses.len() as f64;
    for p in poses.iter_mut() {
        p.trans = c + (p.trans - c) * s;
    }
    for x in points.iter_mut() {
        *x = c + (*x - c) * s;
    }
}

fn rmse(errs: &[Option<f64>]) -> f64 {
    let v: Vec<f64> = errs.iter().flatten().copied().collect();
    if v.is_empty() {
        return f64::NAN;
    }
    (v.iter().map(|e| e * e).sum::<f64>() / v.len() as f64).sqrt()
}

/// Matches of each candidate pair under the epipolar gate of `world_cam` (each image's `T_world_cam`:
/// the prior's, or the loop-closed poses'); pairs with too few matches are dropped.
fn match_pairs(
    candidates: &[pairs::Pair],
    world_cam: &[Se3],
    features: &[Features],
    rays: &[Vec<Option<DVec3>>],
    opts: &PosesOptions,
    progress: ProgressFn,
) -> Vec<PairMatches> {
    let done = std::sync::atomic::AtomicUsize::new(0);
    let total = candidates.len();
    candidates
        .par_iter()
        .map(|p| {
            let gate = EpipolarGate::new(&world_cam[p.i], &world_cam[p.j], &opts.matching);
            let m = matching::match_features(
                &features[p.i].descriptors,
                &rays[p.i],
                &features[p.j].descriptors,
                &rays[p.j],
                Some(&gate),
                &opts.matching,
            );
            let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            if d.is_multiple_of(16) || d == total {
                progress("matching", d, total);
            }
            ((p.i, p.j), m)
        })
        .filter(|(_, m)| m.len() >= opts.matching.min_matches)
        .collect()
}

/// The weak pull of each keyframe towards `base` (the gauge).
fn absolute(base: &[Se3], opts: &PosesOptions) -> Vec<AbsolutePrior> {
    base.iter()
        .enumerate()
        .map(|(k, p)| AbsolutePrior {
            pose: k,
            t_world_base: *p,
            sigma_m: opts.absolute_sigma_m,
            sigma_rad: opts.absolute_sigma_deg.to_radians(),
        })
        .collect()
}

/// Distance walked to each keyframe along `base` (m).
fn path_lengths(base: &[Se3]) -> Vec<f64> {
    let mut out = Vec::with_capacity(base.len());
    let mut d = 0.0;
    for (k, p) in base.iter().enumerate() {
        if k > 0 {
            d += p.trans.distance(base[k - 1].trans);
        }
        out.push(d);
    }
    out
}

/// What the triangulate ↔ adjust rounds read.
struct RoundInput<'a> {
    frames: &'a [PoseFrame],
    rig: &'a Rig,
    features: &'a [Features],
    opts: &'a PosesOptions,
    progress: ProgressFn<'a>,
}

/// What the rounds leave besides the adjusted problem.
struct Adjusted {
    rounds: Vec<BaReport>,
    /// Reprojection RMSE of the first round's points before its adjustment.
    rmse_first: f64,
    /// The feature (in its image) behind each of `problem.observations`.
    obs_feature: Vec<u32>,
}

/// Triangulates `tracks` from the problem's poses and adjusts, once per gate of `opts.rounds_px`
/// (`first_round`: how many rounds ran before, for messages). No triangulated track is
/// `PosesError::Empty("")`, for the caller to explain.
fn adjust_rounds(
    input: &RoundInput,
    problem: &mut BaProblem,
    tracks: &[Vec<FeatureRef>],
    first_round: usize,
) -> Result<Adjusted, PosesError> {
    let RoundInput {
        frames,
        rig,
        features,
        opts,
        progress,
    } = *input;
    let n = frames.len();
    let amax: Vec<f64> = rig.models.iter().map(|m| m.valid_angle()).collect();
    let mut rounds = Vec::new();
    let mut rmse_first = f64::NAN;
    let mut obs_feature = Vec::new();
    let nrounds = opts.rounds_px.len();
    for (round, &gate_px) in opts.rounds_px.iter().enumerate() {
        let world_cam: Vec<Se3> = (0..n)
            .map(|i| problem.poses[rig.keyframe_of[i]] * problem.extrinsics[rig.camera_of[i]])
            .collect();
        let topts = TriangulateOptions {
            max_error_px: gate_px,
            min_angle_deg: opts.min_angle_deg,
        };
        let tri: Vec<Option<(DVec3, Vec<usize>)>> = tracks
            .par_iter()
            .map(|t| {
                let views: Vec<View> = t
                    .iter()
                    .filter_map(|r| {
                        let i = r.image as usize;
                        let k = &features[i].keypoints[r.feature as usize];
                        let c = rig.camera_of[i];
                        View::new(
                            &rig.models[c],
                            amax[c],
                            &world_cam[i],
                            DVec2::new(k.x as f64, k.y as f64),
                        )
                    })
                    .collect();
                // Views that unproject, in the track's order (image ids) for the inlier flags.
                let ids: Vec<usize> = t
                    .iter()
                    .filter(|r| {
                        let i = r.image as usize;
                        let k = &features[i].keypoints[r.feature as usize];
                        rig.models[rig.camera_of[i]]
                            .unproject_within(
                                DVec2::new(k.x as f64, k.y as f64),
                                amax[rig.camera_of[i]],
                            )
                            .is_some()
                    })
                    .map(|r| r.image as usize)
                    .collect();
                let out = triangulate::triangulate(&views, &topts)?;
                let inl: Vec<usize> = ids
                    .iter()
                    .zip(&out.inliers)
                    .filter(|(_, &k)| k)
                    .map(|(&i, _)| i)
                    .collect();
                Some((out.point, inl))
            })
            .collect();
        problem.points.clear();
        problem.observations.clear();
        obs_feature.clear();
        for (ti, t) in tri.into_iter().enumerate() {
            let Some((x, images)) = t else { continue };
            let pid = problem.points.len();
            problem.points.push(x);
            for &i in &images {
                let r = tracks[ti].iter().find(|r| r.image as usize == i).copied();
                let Some(FeatureRef { feature, .. }) = r else {
                    continue;
                };
                let k = &features[i].keypoints[feature as usize];
                problem.observations.push(Observation {
                    pose: rig.keyframe_of[i],
                    camera: rig.camera_of[i],
                    point: pid,
                    uv: DVec2::new(k.x as f64, k.y as f64),
                });
                obs_feature.push(feature);
            }
        }
        if problem.observations.is_empty() {
            return Err(PosesError::Empty(String::new()));
        }
        if round == 0 {
            rmse_first = rmse(&ba::reprojection_errors(problem));
        }
        let bopts = BaOptions {
            huber_px: opts.huber_px.min(gate_px),
            refine_extrinsics: opts.refine_extrinsics,
            ..BaOptions::default()
        };
        let rep = ba::solve(problem, &bopts)
            .map_err(|e| ba_failure(first_round + round, e, frames, &rig.keyframe_of))?;
        rounds.push(rep);
        progress("adjust", round + 1, nrounds);
    }
    Ok(Adjusted {
        rounds,
        rmse_first,
        obs_feature,
    })
}

/// Each image's triangulated features within the last round's gate, for loop verification: their
/// descriptors and adjusted points, and the camera's centre.
fn landmarks_of(input: &RoundInput, problem: &BaProblem, obs_feature: &[u32]) -> Vec<Landmarks> {
    let rig = input.rig;
    let n = input.frames.len();
    let last_gate = input.opts.rounds_px.last().copied().unwrap_or(4.0);
    let mut frame_of: BTreeMap<(usize, usize), usize> = BTreeMap::new();
    for i in 0..n {
        frame_of.insert((rig.keyframe_of[i], rig.camera_of[i]), i);
    }
    let mut out: Vec<Landmarks> = (0..n)
        .map(|i| Landmarks {
            centre: (problem.poses[rig.keyframe_of[i]] * problem.extrinsics[rig.camera_of[i]])
                .trans,
            ..Landmarks::default()
        })
        .collect();
    let errs = ba::reprojection_errors(problem);
    for ((o, e), &f) in problem.observations.iter().zip(&errs).zip(obs_feature) {
        if !e.is_some_and(|e| e <= last_gate) {
            continue;
        }
        let Some(&i) = frame_of.get(&(o.pose, o.camera)) else {
            continue;
        };
        let d = &input.features[i].descriptors[f as usize * 128..(f as usize + 1) * 128];
        out[i].descriptors.extend_from_slice(d);
        out[i].points.push(problem.points[o.point]);
    }
    out
}

/// SLAM odometry terms between consecutive keyframes.
fn odometry(base: &[Se3], opts: &PosesOptions) -> Vec<RelativePrior> {
    RelativePrior::chain(
        base,
        opts.odometry_sigma_m,
        opts.odometry_sigma_deg.to_radians(),
    )
}

/// Connected components of the keyframe graph whose edges are matched pairs: each keyframe's part,
/// numbered 0.. in the order of their first keyframe.
fn components(keyframes: usize, matches: &[PairMatches], keyframe_of: &[usize]) -> Vec<usize> {
    let mut parent: Vec<usize> = (0..keyframes).collect();
    fn find(p: &mut [usize], mut x: usize) -> usize {
        while p[x] != x {
            p[x] = p[p[x]];
            x = p[x];
        }
        x
    }
    for ((i, j), _) in matches {
        let (a, b) = (
            find(&mut parent, keyframe_of[*i]),
            find(&mut parent, keyframe_of[*j]),
        );
        if a != b {
            parent[a] = b;
        }
    }
    let mut label: BTreeMap<usize, usize> = BTreeMap::new();
    (0..keyframes)
        .map(|k| {
            let root = find(&mut parent, k);
            let next = label.len();
            *label.entry(root).or_insert(next)
        })
        .collect()
}

/// The Sim(3) from the refined keyframe poses to the prior's. First the robust fit `silvr eval-poses`
/// uses (centres and 1 m axis tips, refitted on the keyframes within 3 robust σ, so a prior's gross errors
/// do not tilt the frame); then its rotation is refitted with centres and orientations each weighted by
/// how well the prior holds it ([`weighted_alignment`]). A short drive's drifted centres would otherwise
/// set its pitch and yaw: on a KITTI drive (6.7 m, 1 % drift) the equal-weight fit tilted the refined map
/// 0.3° where the prior's orientations averaged to 0.13°.
fn align_to_prior(refined: &[Se3], prior: &[Se3]) -> Result<(Sim3, usize), PosesError> {
    if refined.len() < 3 {
        // Too few centres to fix a similarity: keep the adjusted frame (the absolute priors hold it).
        return Ok((Sim3::from_se3(Se3::IDENTITY), refined.len()));
    }
    let e = crate::eval::poses::pose_errors(refined, prior)
        .map_err(|e| PosesError::Align(e.to_string()))?;
    let sim = e.alignment;
    // The inliers of the robust fit, as it judged them (3 robust σ of the centre residuals).
    let r: Vec<f64> = refined
        .iter()
        .zip(prior)
        .map(|(a, b)| sim.transform_point(a.trans).distance(b.trans))
        .collect();
    let mut sorted = r.clone();
    sorted.sort_by(f64::total_cmp);
    let cut = (3.0 * 1.4826 * sorted[sorted.len() / 2]).max(1e-9);
    let keep: Vec<usize> = (0..r.len()).filter(|&k| r[k] <= cut).collect();
    if keep.len() < 3 {
        return Ok((sim, e.inliers));
    }
    let (a, b): (Vec<Se3>, Vec<Se3>) = keep.iter().map(|&k| (refined[k], prior[k])).unzip();
    Ok((weighted_alignment(&a, &b, &sim).unwrap_or(sim), keep.len()))
}

/// The similarity `b ≈ sim(a)` whose rotation maximises
/// tr(Rᵀ (s/σ_c² Σ (b_i − b̄)(a_i − ā)ᵀ + 1/(2σ_θ²) Σ R_b,i R_a,iᵀ)): the joint likelihood of the centres
/// (isotropic noise σ_c per axis) and the orientations (σ_θ per axis); then scale and translation from
/// the centres. σ_c is the centres' residual under `fit` (their best rigid fit); σ_θ the scatter of the
/// rotations R_b,i R_a,iᵀ about their mean — what no single rotation explains, not what `fit`'s rotation
/// leaves (that would keep any tilt it has). Floors: 0.1 mm and 0.001°. Over a long loop with drifting
/// yaw the centres' lever arms dominate, over a short straight drive the orientations do. `None` where
/// the problem is degenerate (`fit` stands).
fn weighted_alignment(a: &[Se3], b: &[Se3], fit: &Sim3) -> Option<Sim3> {
    use nalgebra::{Matrix3, Vector3};
    let n = a.len() as f64;
    let m = |q: glam::DQuat| {
        let r = glam::DMat3::from_quat(q);
        Matrix3::from_column_slice(&r.to_cols_array())
    };
    // The rotation nearest a 3×3 sum (its polar factor, proper).
    let nearest = |h: Matrix3<f64>| -> Option<glam::DQuat> {
        if !h.iter().all(|x| x.is_finite()) {
            return None;
        }
        let svd = nalgebra::SVD::try_new(h, true, true, f64::EPSILON, 0)?;
        let (u, v_t) = (svd.u?, svd.v_t?);
        let mut d = Matrix3::identity();
        if u.determinant() * v_t.determinant() < 0.0 {
            d[(2, 2)] = -1.0;
        }
        Some(crate::geometry::quat_from_matrix(&(u * d * v_t)))
    };
    let rel: Vec<glam::DQuat> = a
        .iter()
        .zip(b)
        .map(|(x, y)| y.rot * x.rot.conjugate())
        .collect();
    let mean = nearest(rel.iter().map(|&q| m(q)).sum())?;
    let t2: f64 = rel
        .iter()
        .map(|&q| {
            Se3::new(q, DVec3::ZERO)
                .angle_to(&Se3::new(mean, DVec3::ZERO))
                .powi(2)
        })
        .sum();
    let c2: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| fit.transform_point(x.trans).distance_squared(y.trans))
        .sum();
    let var_c = (c2 / (3.0 * n)).max(1e-8);
    let var_t = (t2 / (3.0 * n)).max(1e-3f64.to_radians().powi(2));
    let ma = a.iter().map(|p| p.trans).sum::<DVec3>() / n;
    let mb = b.iter().map(|p| p.trans).sum::<DVec3>() / n;
    let v = |d: DVec3| Vector3::new(d.x, d.y, d.z);
    let mut h = Matrix3::<f64>::zeros();
    let mut var_a = 0.0;
    for (x, y) in a.iter().zip(b) {
        let (da, db) = (x.trans - ma, y.trans - mb);
        var_a += da.length_squared();
        h += v(db) * v(da).transpose() * (fit.scale / var_c);
        h += m(y.rot) * m(x.rot).transpose() / (2.0 * var_t);
    }
    if var_a.is_nan() || var_a <= 0.0 {
        return None;
    }
    let rot = nearest(h)?;
    let num: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| (y.trans - mb).dot(rot * (x.trans - ma)))
        .sum();
    let scale = num / var_a;
    if !(scale.is_finite() && scale > 0.0) {
        return None;
    }
    Some(Sim3 {
        scale,
        rot,
        trans: mb - scale * (rot * ma),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;

    #[test]
    fn working_resolution_is_about_a_megapixel() {
        assert_eq!(working_downscale(360, 270), 1);
        assert_eq!(working_downscale(1241, 376), 1); // KITTI
        assert_eq!(working_downscale(1024, 1024), 1);
        assert_eq!(working_downscale(1025, 1024), 2);
        assert_eq!(working_downscale(1080, 1920), 2); // the fox, 1080p
        assert_eq!(working_downscale(1936, 1216), 2); // DGP
        assert_eq!(working_downscale(4000, 3000), 4);
        assert_eq!(working_downscale(0, 0), 1);
    }

    fn frame(
        name: &str,
        key: Option<usize>,
        cam: Option<&str>,
        model: CameraModel,
        x: f64,
    ) -> PoseFrame {
        PoseFrame {
            name: name.into(),
            model,
            prior: Se3::new(DQuat::from_rotation_y(0.1 * x), DVec3::new(x, 0.0, 0.0)),
            keyframe: key,
            camera: cam.map(String::from),
        }
    }

    /// A map 1 % too large against lidar ranges reads a ratio of 1/1.01 and is rescaled to metric; a
    /// metric one is kept; returns of another surface (ratios off by > 20 %) do not move the median.
    /// A straight 6.3 m drive whose prior centres bend 5 cm up by its end (drift) while its orientations
    /// hold to 0.02°: the Sim(3) back to the prior follows the orientations (the map stays level),
    /// where the equal-weight fit of centres and 1 m axis tips tilts it by the bend.
    #[test]
    fn alignment_to_a_drifted_straight_prior_follows_its_orientations() {
        let look = DQuat::from_rotation_y(std::f64::consts::FRAC_PI_2);
        let exact: Vec<Se3> = (0..10)
            .map(|i| Se3::new(look, DVec3::new(0.7 * i as f64, 0.0, 1.5)))
            .collect();
        let prior: Vec<Se3> = exact
            .iter()
            .enumerate()
            .map(|(i, e)| {
                let t = i as f64 / 9.0;
                let wobble = DQuat::from_rotation_x(
                    (0.02f64 * if i % 2 == 0 { 1.0 } else { -1.0 }).to_radians(),
                );
                Se3::new(wobble * e.rot, e.trans + DVec3::new(0.0, 0.0, 0.05 * t * t))
            })
            .collect();
        // The refined trajectory: the exact one in an arbitrary frame and scale.
        let frame = Sim3 {
            scale: 0.4,
            rot: DQuat::from_axis_angle(DVec3::new(1.0, 2.0, 3.0).normalize(), 0.5),
            trans: DVec3::new(3.0, -1.0, 2.0),
        };
        let refined: Vec<Se3> = exact.iter().map(|p| frame.transform_pose(p)).collect();
        let tilt = |sim: &Sim3| {
            Se3::new(sim.rot * frame.rot, DVec3::ZERO)
                .angle_to(&Se3::IDENTITY)
                .to_degrees()
        };
        let (sim, inliers) = align_to_prior(&refined, &prior).unwrap();
        assert_eq!(inliers, 10);
        let equal = crate::eval::poses::pose_errors(&refined, &prior)
            .unwrap()
            .alignment;
        assert!(tilt(&sim) < 0.03, "weighted: {:.4}°", tilt(&sim));
        assert!(tilt(&equal) > 0.1, "equal weights: {:.4}°", tilt(&equal));
        assert!(
            (sim.scale * frame.scale - 1.0).abs() < 0.01,
            "scale {}",
            sim.scale
        );
    }

    #[test]
    fn lidar_scale_measures_the_map_against_the_returns() {
        let poses: Vec<Se3> = (0..4)
            .map(|i| Se3::new(DQuat::IDENTITY, DVec3::new(i as f64, 0.0, 0.0)))
            .collect();
        let points: Vec<DVec3> = (0..200)
            .map(|k| DVec3::new((k % 20) as f64 * 0.3, 5.0 + (k / 20) as f64 * 0.4, 1.0))
            .collect();
        let tracks: Vec<Vec<(usize, DVec2)>> = (0..200)
            .map(|k| {
                (0..4)
                    .map(|i| (i, DVec2::new(k as f64, i as f64)))
                    .collect()
            })
            .collect();
        let true_range = |map_scale: f64| {
            let (poses, points) = (poses.clone(), points.clone());
            move |i: usize, uv: DVec2| -> Option<f64> {
                let k = uv.x as usize;
                if k % 10 == 3 {
                    // A return of the background at this pixel.
                    return Some(40.0);
                }
                Some((points[k] - poses[i].trans).length() / map_scale)
            }
        };
        let s = lidar_scale(&poses, &points, &tracks, &true_range(1.01)).unwrap();
        assert!((s.ratio - 1.0 / 1.01).abs() < 1e-9, "{s:?}");
        assert!(s.applied && s.samples == 720, "{s:?}");
        let (mut p2, mut x2) = (poses.clone(), points.clone());
        rescale(&mut p2, &mut x2, s.ratio);
        // The same returns against the rescaled map: metric now.
        let after = lidar_scale(&p2, &x2, &tracks, &true_range(1.01)).unwrap();
        assert!(
            (after.ratio - 1.0).abs() < 1e-9 && !after.applied,
            "rescaling about the cameras' centroid scales every range: {after:?}"
        );
        let metric = lidar_scale(&poses, &points, &tracks, &true_range(1.0)).unwrap();
        assert!((metric.ratio - 1.0).abs() < 1e-12 && !metric.applied);
        assert!(lidar_scale(&poses, &points, &tracks, &|_, _| None).is_none());
    }

    /// A BA failure names the images of the keyframes it points at (a few, then a count), and the round.
    #[test]
    fn ba_failures_name_their_images() {
        let m = CameraModel::pinhole(64, 48, 50.0, 50.0, 31.5, 23.5);
        let frames: Vec<PoseFrame> = (0..12)
            .map(|i| {
                frame(
                    &format!("cam{}/{:05}.png", i % 3, i / 3),
                    Some(i / 3),
                    None,
                    m,
                    i as f64,
                )
            })
            .collect();
        let keyframe_of: Vec<usize> = (0..12).map(|i| i / 3).collect();
        let diverged = ba::BaError::Diverged {
            detail: "the initial cost is not finite (inf)".into(),
            poses: vec![2],
        };
        let e = ba_failure(0, diverged, &frames, &keyframe_of).to_string();
        assert!(
            e.starts_with("bundle adjustment, round 1: diverged")
                && e.contains("cam0/00002.png, cam1/00002.png, cam2/00002.png")
                && !e.contains("00001"),
            "{e}"
        );
        let singular = ba::BaError::Singular {
            lambda: 1e16,
            poses: vec![0, 1, 3],
        };
        let e = ba_failure(2, singular, &frames, &keyframe_of).to_string();
        assert!(e.contains("round 3") && e.contains("and 3 more"), "{e}");
        let other = ba::BaError::Invalid("x".into());
        let e = ba_failure(0, other, &frames, &keyframe_of).to_string();
        assert!(!e.contains("images concerned"), "{e}");
    }

    /// The rig read from the prior: one pose per keyframe (in keyframe order, not file order), each
    /// camera's place from a keyframe that has it beside the reference camera; the prior's base pose
    /// composed with the extrinsic gives back each frame's prior. Inconsistent intrinsics, and a camera
    /// never seen with the reference, are errors naming them; without keyframes every image is its own.
    #[test]
    fn rig_from_the_prior() {
        let a = CameraModel::pinhole(64, 48, 50.0, 50.0, 31.5, 23.5);
        let b = CameraModel::pinhole(64, 48, 60.0, 60.0, 31.5, 23.5);
        let mut frames = vec![
            frame("k1/front", Some(1), Some("front"), a, 1.0),
            frame("k1/left", Some(1), Some("left"), b, 1.3),
            frame("k0/front", Some(0), Some("front"), a, 0.0),
            frame("k0/left", Some(0), Some("left"), b, 0.3),
        ];
        // Keep the rig rigid: the left camera sits at the same offset from the front one at both instants.
        let off = frames[2].prior.inverse() * frames[3].prior;
        frames[1].prior = frames[0].prior * off;
        let rig = rig_of(&frames).unwrap();
        assert_eq!(rig.keyframes, 2);
        assert_eq!(rig.keyframe_of, vec![1, 1, 0, 0]);
        assert_eq!(rig.camera_of, vec![0, 1, 0, 1]);
        for (i, f) in frames.iter().enumerate() {
            let t = rig.prior_base[rig.keyframe_of[i]] * rig.extrinsics[rig.camera_of[i]];
            assert!(
                t.distance_to(&f.prior) < 1e-12 && t.angle_to(&f.prior) < 1e-9,
                "{i}"
            );
        }
        let mut bad = frames.clone();
        bad[3].model = a;
        let e = rig_of(&bad).err().unwrap().to_string();
        assert!(e.contains("k0/left") && e.contains("intrinsics"), "{e}");
        let lonely = vec![
            frame("f", Some(0), Some("front"), a, 0.0),
            frame("l", Some(1), Some("left"), b, 1.0),
        ];
        let e = rig_of(&lonely).err().unwrap().to_string();
        assert!(e.contains("\"left\"") && e.contains("never"), "{e}");
        let free: Vec<PoseFrame> = frames
            .iter()
            .map(|f| PoseFrame {
                keyframe: None,
                ..f.clone()
            })
            .collect();
        let rig = rig_of(&free).unwrap();
        assert_eq!(rig.keyframes, 4);
        assert_eq!(rig.models.len(), 2);
        assert!(rig.extrinsics.iter().all(|e| *e == Se3::IDENTITY));
    }

    /// Too few images, or images that match nothing (flat grey), end in an error that says so.
    #[test]
    fn nothing_to_adjust_is_an_error() {
        let a = CameraModel::pinhole(64, 48, 50.0, 50.0, 31.5, 23.5);
        let one = vec![frame("only", None, None, a, 0.0)];
        let load = |_: usize| -> Result<GrayImage, String> {
            Ok(GrayImage {
                width: 64,
                height: 48,
                gray: vec![0.5; 64 * 48],
                sky: None,
            })
        };
        let quiet = |_: &str, _: usize, _: usize| {};
        let e = refine_poses(&one, &load, &PosesOptions::default(), &quiet);
        assert!(matches!(e, Err(PosesError::Empty(_))));
        let two = vec![
            frame("a", None, None, a, 0.0),
            frame("b", None, None, a, 0.2),
        ];
        let e = refine_poses(&two, &load, &PosesOptions::default(), &quiet)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("no track"), "{e}");
        // A loader failure names the image.
        let fail =
            |i: usize| -> Result<GrayImage, String> { Err(format!("image {i}: truncated PNG")) };
        let e = refine_poses(&two, &fail, &PosesOptions::default(), &quiet)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("truncated"), "{e}");
    }
}
