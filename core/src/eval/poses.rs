//! Pose accuracy against exact ground truth: absolute trajectory error (ATE) and relative pose error
//! (RPE) after a robust Sim(3) alignment (Umeyama), as in the TUM RGB-D / EuRoC protocol. The paper's
//! pose ablation compares the SLAM prior, the refined poses and the exact ones by these numbers.
//!
//! Alignment: Umeyama on every frame (its centre and the tips of its axes), then refit on the frames whose residual is within 3 robust
//! standard deviations (1.4826 × median) until the set stops changing, so a few gross errors do not
//! bend the fit; the errors are then reported over **all** frames (the gross ones included: they are
//! the prior's errors) with the median beside the RMSE.
//!
//! The estimate is a `transforms.json` ([`compare_transforms`]) or a COLMAP text model ([`compare_colmap`],
//! the side-by-side peer of `scripts/bench-poses.sh`); either is matched to the exact frames by image path,
//! and exact frames the estimate lacks count as not registered: the errors are over the registered ones.

use std::path::Path;

use glam::DVec3;
use serde::Serialize;

use super::metrics::median;
use crate::dataset::{self, DatasetError};
use crate::geometry::{GeometryError, Se3, Sim3};
use crate::ingest::colmap::{self, ColmapError};

/// Errors of an estimated trajectory against the exact one.
#[derive(Clone, Debug, PartialEq, Serialize, serde::Deserialize)]
pub struct PoseErrors {
    /// Frames scored against: every exact frame when read from files ([`compare_transforms`],
    /// [`compare_colmap`]), the given poses otherwise.
    pub frames: usize,
    /// Of those, the frames the estimate has a pose for; every error below is over these.
    pub registered: usize,
    /// Frames the alignment kept (the rest are gross errors).
    pub inliers: usize,
    /// Scale of the Sim(3) alignment (estimate → ground truth).
    pub scale: f64,
    /// The whole alignment (estimate → ground truth): what maps a reconstruction made on the estimated
    /// poses into the ground truth's frame for scoring.
    #[serde(default)]
    pub alignment: Sim3,
    /// Camera-centre error after alignment (m).
    pub ate_rmse_m: f64,
    pub ate_median_m: f64,
    pub ate_max_m: f64,
    /// Orientation error after alignment (degrees).
    pub rot_rmse_deg: f64,
    pub rot_median_deg: f64,
    /// Error of consecutive relative motions (the estimate's scaled by the alignment): translation (m)
    /// and rotation (degrees), RMSE over pairs.
    pub rpe_trans_rmse_m: f64,
    pub rpe_rot_rmse_deg: f64,
}

#[derive(Debug, thiserror::Error)]
pub enum PoseEvalError {
    #[error("{0}")]
    Dataset(#[from] DatasetError),
    #[error("{0}")]
    Geometry(#[from] GeometryError),
    #[error("{0}")]
    Colmap(#[from] ColmapError),
    #[error("{what}: {detail}")]
    Mismatch { what: String, detail: String },
}

/// Errors of `est` against `gt` (same frames, same order; at least 3), one sequence.
pub fn pose_errors(est: &[Se3], gt: &[Se3]) -> Result<PoseErrors, PoseEvalError> {
    pose_errors_of_sequences(est, gt, &[])
}

/// As [`pose_errors`] over several sequences laid end to end (one per camera, say): `starts` are the
/// indices where a new one begins, so no RPE pair spans two.
pub fn pose_errors_of_sequences(
    est: &[Se3],
    gt: &[Se3],
    starts: &[usize],
) -> Result<PoseErrors, PoseEvalError> {
    aligned_errors(est, gt, starts, true)
}

/// As [`pose_errors`] for a trajectory that claims metric scale (lidar odometry): aligned by a rigid
/// SE(3), so a scale error counts against it (the KITTI / evo convention for lidar odometry).
pub fn pose_errors_se3(est: &[Se3], gt: &[Se3]) -> Result<PoseErrors, PoseEvalError> {
    aligned_errors(est, gt, &[], false)
}

fn aligned_errors(
    est: &[Se3],
    gt: &[Se3],
    starts: &[usize],
    with_scale: bool,
) -> Result<PoseErrors, PoseEvalError> {
    if est.len() != gt.len() || est.len() < 3 {
        return Err(PoseEvalError::Mismatch {
            what: "trajectories".into(),
            detail: format!(
                "{} estimated and {} exact poses (need the same number, at least 3)",
                est.len(),
                gt.len()
            ),
        });
    }
    let src: Vec<DVec3> = est.iter().map(|p| p.trans).collect();
    let dst: Vec<DVec3> = gt.iter().map(|p| p.trans).collect();
    let residuals = |s: &Sim3| -> Vec<f64> {
        src.iter()
            .zip(&dst)
            .map(|(&a, &b)| s.transform_point(a).distance(b))
            .collect()
    };
    // Camera centres alone leave a straight path's roll about its own axis to the noise (a street
    // walked in a line measured 5° of "rotation error" that way), so each frame also contributes the
    // tips of its axes, 1 m out in the exact frame and 1 m / scale in the estimate's (the scale from the
    // centres' spreads, which a line does determine; Umeyama on a line's centres has no rotation).
    let scale0 = if with_scale {
        let spread = |p: &[DVec3]| {
            let m = p.iter().copied().sum::<DVec3>() / p.len() as f64;
            p.iter().map(|x| x.distance_squared(m)).sum::<f64>()
        };
        let s = (spread(&dst) / spread(&src)).sqrt();
        if s.is_finite() && s > 0.0 {
            s
        } else {
            Sim3::umeyama(&src, &dst, true)?.scale.max(1e-12)
        }
    } else {
        1.0
    };
    let fit = |keep: &[bool]| -> Result<Sim3, GeometryError> {
        let (mut s, mut d) = (Vec::new(), Vec::new());
        for (k, (e, g)) in est.iter().zip(gt).enumerate() {
            if !keep[k] {
                continue;
            }
            s.push(e.trans);
            d.push(g.trans);
            for axis in [DVec3::X, DVec3::Y, DVec3::Z] {
                s.push(e.trans + e.rot * axis / scale0);
                d.push(g.trans + g.rot * axis);
            }
        }
        Sim3::umeyama(&s, &d, with_scale)
    };
    let mut keep: Vec<bool> = vec![true; src.len()];
    let mut sim = fit(&keep)?;
    for _ in 0..10 {
        let r = residuals(&sim);
        let sigma = 1.4826 * median(&r);
        let next: Vec<bool> = r.iter().map(|&x| x <= (3.0 * sigma).max(1e-9)).collect();
        if next == keep || next.iter().filter(|&&k| k).count() < 3 {
            break;
        }
        keep = next;
        sim = fit(&keep)?;
    }
    let ate = residuals(&sim);
    let rot: Vec<f64> = est
        .iter()
        .zip(gt)
        .map(|(e, g)| {
            let aligned = sim.rot * e.rot;
            Se3::new(aligned, DVec3::ZERO)
                .angle_to(&Se3::new(g.rot, DVec3::ZERO))
                .to_degrees()
        })
        .collect();
    let (mut rpe_t, mut rpe_r) = (Vec::new(), Vec::new());
    for k in (1..est.len()).filter(|k| !starts.contains(k)) {
        let re = est[k - 1].inverse() * est[k];
        let rg = gt[k - 1].inverse() * gt[k];
        rpe_t.push((re.trans * sim.scale).distance(rg.trans));
        rpe_r.push(
            Se3::new(re.rot, DVec3::ZERO)
                .angle_to(&Se3::new(rg.rot, DVec3::ZERO))
                .to_degrees(),
        );
    }
    Ok(PoseErrors {
        frames: est.len(),
        registered: est.len(),
        inliers: keep.iter().filter(|&&k| k).count(),
        scale: sim.scale,
        alignment: sim,
        ate_rmse_m: rms(&ate),
        ate_median_m: median(&ate),
        ate_max_m: ate.iter().copied().fold(0.0, f64::max),
        rot_rmse_deg: rms(&rot),
        rot_median_deg: median(&rot),
        rpe_trans_rmse_m: rms(&rpe_t),
        rpe_rot_rmse_deg: rms(&rpe_r),
    })
}

/// Pairs each pose of `est` with the exact pose at its time: the sample within `tolerance` seconds, else
/// the exact trajectory interpolated between its neighbours; poses outside its span are left out.
pub fn match_by_time(
    est: &crate::geometry::Trajectory,
    exact: &crate::geometry::Trajectory,
    tolerance: f64,
) -> (Vec<Se3>, Vec<Se3>) {
    let (mut e, mut g) = (Vec::new(), Vec::new());
    let ts = exact.stamps();
    for (&s, p) in est.stamps().iter().zip(est.poses()) {
        let k = ts.partition_point(|&x| x < s);
        let near = [k.saturating_sub(1), k]
            .into_iter()
            .filter(|&i| i < ts.len())
            .min_by(|&a, &b| (ts[a] - s).abs().total_cmp(&(ts[b] - s).abs()));
        let pose = match near.filter(|&i| (ts[i] - s).abs() <= tolerance) {
            Some(i) => Some(exact.poses()[i]),
            None => exact.at(s),
        };
        if let Some(pose) = pose {
            e.push(*p);
            g.push(pose);
        }
    }
    (e, g)
}

/// Errors of the camera poses of one `transforms.json` against another's, frames matched by image path:
/// the same `file_path`, or paths that name the same file from each one's folder (`silvr poses` writes
/// `../dataset/images/...`). Consecutive pairs for RPE are consecutive frames of one camera (the exact
/// file's order within a camera). Exact frames the estimate lacks are not registered; an estimated frame
/// the exact file lacks is an error.
pub fn compare_transforms(est: &Path, gt: &Path) -> Result<PoseErrors, PoseEvalError> {
    let (e, _, _) = dataset::read_frames(est)?;
    let mut poses = Vec::with_capacity(e.len());
    for f in &e {
        poses.push((f.file_path.clone(), f.camera(est)?.1));
    }
    compare_named(poses, Some(folder_of(est)), &est.display().to_string(), gt)
}

/// Errors of a COLMAP text model's poses (a folder holding `cameras.txt` and `images.txt`, COLMAP's
/// `sparse/0` after `model_converter --output_type TXT`) against an exact `transforms.json`. An image
/// matches the frame whose `file_path` is its NAME (COLMAP run with the dataset folder as `--image_path`),
/// or else the one frame whose path ends in `/NAME` (run on the `images` folder). Exact frames the model
/// lacks count as not registered, as in [`compare_transforms`].
pub fn compare_colmap(model_dir: &Path, gt: &Path) -> Result<PoseErrors, PoseEvalError> {
    let model = colmap::read_model(model_dir)?;
    let poses = model
        .images
        .iter()
        .map(|i| (i.name.clone(), i.t_world_cam()))
        .collect();
    compare_named(poses, None, &model_dir.display().to_string(), gt)
}

/// The folder a file's relative paths start from.
fn folder_of(file: &Path) -> &Path {
    file.parent().unwrap_or(Path::new(""))
}

/// `base/rel` made absolute (from the working directory) with `.` and `..` resolved by the text alone, so
/// two spellings of one file compare equal without the file having to exist.
fn resolved(base: &Path, rel: &str) -> std::path::PathBuf {
    use std::path::Component;
    let joined = base.join(rel);
    let joined = if joined.is_absolute() {
        joined
    } else {
        std::env::current_dir().unwrap_or_default().join(joined)
    };
    let mut out = std::path::PathBuf::new();
    for c in joined.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                out.pop();
            }
            other => out.push(other),
        }
    }
    out
}

/// Errors of named camera → world poses (OpenCV axes) against the frames of `gt`, matched by image path:
/// exactly; else, when `base` (the folder the names are relative to) is given, by the file both name;
/// else by a unique `/NAME` suffix. `est_name` names the estimate in errors.
pub fn compare_named(
    est: Vec<(String, Se3)>,
    base: Option<&Path>,
    est_name: &str,
    gt: &Path,
) -> Result<PoseErrors, PoseEvalError> {
    use std::collections::{BTreeMap, HashMap};
    let (g, _, _) = dataset::read_frames(gt)?;
    let exact: HashMap<&str, usize> = g
        .iter()
        .enumerate()
        .map(|(k, f)| (f.file_path.as_str(), k))
        .collect();
    let by_file: HashMap<std::path::PathBuf, usize> = match base {
        Some(_) => g
            .iter()
            .enumerate()
            .map(|(k, f)| (resolved(folder_of(gt), &f.file_path), k))
            .collect(),
        None => HashMap::new(),
    };
    let mismatch = |detail: String| PoseEvalError::Mismatch {
        what: est_name.to_string(),
        detail,
    };
    let mut pose_of: Vec<Option<Se3>> = vec![None; g.len()];
    for (name, pose) in est {
        let same_file = base.and_then(|b| by_file.get(&resolved(b, &name)));
        let k = match exact.get(name.as_str()).or(same_file) {
            Some(&k) => k,
            None => {
                // The name as a suffix; else its part from the dataset layout's `images/` on (a
                // `silvr poses` output of another copy of the same recording, e.g. one ingested again
                // with another trajectory, names `../other/images/cam/NNNNN.png`).
                let mut tail = format!("/{}", name.trim_start_matches("./"));
                if !g.iter().any(|f| f.file_path.ends_with(&tail)) {
                    if let Some(i) = name.rfind("images/") {
                        tail = name[i..].to_string();
                    }
                }
                let mut hits = g
                    .iter()
                    .enumerate()
                    .filter(|(_, f)| f.file_path.ends_with(&tail));
                match (hits.next(), hits.next()) {
                    (Some((k, _)), None) => k,
                    (None, _) => {
                        return Err(mismatch(format!("frame {name} is not in {}", gt.display())))
                    }
                    (Some(_), Some(_)) => {
                        return Err(mismatch(format!(
                            "image {name} matches several frames of {}",
                            gt.display()
                        )))
                    }
                }
            }
        };
        if pose_of[k].replace(pose).is_some() {
            return Err(mismatch(format!(
                "frame {} has two estimated poses",
                g[k].file_path
            )));
        }
    }
    // Group by camera so each pair of consecutive frames is one camera's motion; a frame the estimate
    // lacks breaks its camera's sequence, so no RPE pair spans it.
    let mut by_camera: BTreeMap<String, Vec<usize>> = Default::default();
    for (k, f) in g.iter().enumerate() {
        let cam = f.camera.clone().unwrap_or_else(|| {
            Path::new(&f.file_path)
                .parent()
                .map(|p| p.display().to_string())
                .unwrap_or_default()
        });
        by_camera.entry(cam).or_default().push(k);
    }
    let mut starts = Vec::new();
    let (mut est_poses, mut gt_poses) = (Vec::new(), Vec::new());
    for seq in by_camera.into_values() {
        let mut run = false;
        for k in seq {
            let Some(e) = pose_of[k] else {
                run = false;
                continue;
            };
            if !run {
                starts.push(est_poses.len());
                run = true;
            }
            est_poses.push(e);
            gt_poses.push(g[k].camera(gt)?.1);
        }
    }
    let mut errors = pose_errors_of_sequences(&est_poses, &gt_poses, &starts)?;
    errors.frames = g.len();
    Ok(errors)
}

fn rms(v: &[f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;

    fn path(n: usize) -> Vec<Se3> {
        (0..n)
            .map(|k| {
                let a = k as f64 * 0.1;
                Se3::new(
                    DQuat::from_rotation_z(a),
                    DVec3::new(5.0 * a.cos(), 5.0 * a.sin(), 0.1 * k as f64),
                )
            })
            .collect()
    }

    #[test]
    fn a_similarity_transform_of_the_truth_has_no_error() {
        let gt = path(30);
        let sim = Sim3::new(2.5, DQuat::from_rotation_y(0.3), DVec3::new(1.0, -4.0, 2.0));
        let est: Vec<Se3> = gt.iter().map(|p| sim.transform_pose(p)).collect();
        let e = pose_errors(&est, &gt).unwrap();
        assert!(e.ate_rmse_m < 1e-9 && e.rot_rmse_deg < 1e-6, "{e:?}");
        assert!(
            e.rpe_trans_rmse_m < 1e-9 && e.rpe_rot_rmse_deg < 1e-6,
            "{e:?}"
        );
        assert!((e.scale - 1.0 / 2.5).abs() < 1e-9);
        assert_eq!(e.inliers, 30);
    }

    #[test]
    fn gross_errors_are_left_out_of_the_fit_but_not_the_report() {
        let gt = path(40);
        let mut est = gt.clone();
        // Small noise everywhere, one frame 2 m off.
        for (k, p) in est.iter_mut().enumerate() {
            p.trans += DVec3::new(0.01 * ((k * 7) % 5) as f64 - 0.02, 0.0, 0.0);
        }
        est[17].trans += DVec3::new(0.0, 2.0, 0.0);
        let e = pose_errors(&est, &gt).unwrap();
        assert_eq!(e.inliers, 39, "{e:?}");
        assert!((e.scale - 1.0).abs() < 0.01, "{e:?}");
        assert!(e.ate_median_m < 0.03, "{e:?}");
        assert!((e.ate_max_m - 2.0).abs() < 0.05, "{e:?}");
        assert!(pose_errors(&est[..2], &gt[..2]).is_err());
    }

    /// A small two-camera world on disk: its exact `transforms.json` and the frames' names and poses.
    fn exact_world(dir: &Path) -> (std::path::PathBuf, Vec<(String, Se3)>) {
        use crate::camera::{CameraModel, Distortion};
        let model = CameraModel {
            width: 64,
            height: 48,
            fx: 50.0,
            fy: 50.0,
            cx: 31.5,
            cy: 23.5,
            distortion: Distortion::None,
        };
        let mut named = Vec::new();
        let mut frames = Vec::new();
        for (c, cam) in ["cam_a", "cam_b"].into_iter().enumerate() {
            for (k, p) in path(10).into_iter().enumerate() {
                let p = Se3::new(
                    p.rot * DQuat::from_rotation_y(c as f64 * 1.2),
                    p.trans + DVec3::new(0.0, 0.0, 0.3 * c as f64),
                );
                let name = format!("images/{cam}/{k:05}.png");
                let mut f = dataset::NsFrame::new(name.clone(), &model, &p);
                f.camera = Some(cam.to_string());
                frames.push(f);
                named.push((name, p));
            }
        }
        let gt = dir.join("transforms.json");
        let json = serde_json::json!({ "frames": frames });
        std::fs::write(&gt, serde_json::to_string(&json).unwrap()).unwrap();
        (gt, named)
    }

    /// A COLMAP text model of `poses` (camera → world) in `dir`, every image on one pinhole camera.
    fn write_colmap(dir: &Path, poses: &[(String, Se3)]) {
        use crate::camera::{CameraModel, Distortion};
        let cam = CameraModel {
            width: 64,
            height: 48,
            fx: 50.0,
            fy: 50.0,
            cx: 31.5,
            cy: 23.5,
            distortion: Distortion::None,
        };
        let model = colmap::ColmapModel {
            cameras: [(1, cam)].into_iter().collect(),
            images: poses
                .iter()
                .enumerate()
                .map(|(k, (name, p))| colmap::ColmapImage {
                    id: k as u32 + 1,
                    camera_id: 1,
                    name: name.clone(),
                    t_cam_world: p.inverse(),
                    points2d: Vec::new(),
                })
                .collect(),
            points: Vec::new(),
        };
        colmap::write_model(dir, &model).unwrap();
    }

    #[test]
    fn a_colmap_model_is_scored_by_image_name_and_missing_images_are_unregistered() {
        let tmp = tempfile::tempdir().unwrap();
        let (gt, named) = exact_world(tmp.path());
        // COLMAP's frame: a similarity away from ours, one image left out (not registered).
        let sim = Sim3::new(0.5, DQuat::from_rotation_x(0.7), DVec3::new(3.0, 1.0, -2.0));
        let est: Vec<(String, Se3)> = named
            .iter()
            .enumerate()
            .filter(|&(k, _)| k != 13)
            .map(|(_, (n, p))| (n.clone(), sim.transform_pose(p)))
            .collect();
        let exact_dir = tmp.path().join("exact");
        write_colmap(&exact_dir, &est);
        let e = compare_colmap(&exact_dir, &gt).unwrap();
        assert_eq!((e.frames, e.registered), (20, 19), "{e:?}");
        assert!(e.ate_rmse_m < 1e-6 && e.rot_rmse_deg < 1e-4, "{e:?}");
        assert!(
            e.rpe_trans_rmse_m < 1e-6 && e.rpe_rot_rmse_deg < 1e-4,
            "{e:?}"
        );
        assert!((e.scale - 2.0).abs() < 1e-6, "{e:?}");

        // Names relative to the images folder (COLMAP run on `images/`) match by suffix.
        let rel: Vec<(String, Se3)> = est
            .iter()
            .map(|(n, p)| (n.trim_start_matches("images/").to_string(), *p))
            .collect();
        let rel_dir = tmp.path().join("relative");
        write_colmap(&rel_dir, &rel);
        assert_eq!(compare_colmap(&rel_dir, &gt).unwrap(), e);

        // Every pose moved by a few centimetres and a fraction of a degree: the errors show it.
        let perturbed: Vec<(String, Se3)> = named
            .iter()
            .enumerate()
            .map(|(k, (n, p))| {
                let s = if k % 2 == 0 { 1.0 } else { -1.0 };
                let moved = Se3::new(
                    p.rot * DQuat::from_rotation_z(s * 0.01),
                    p.trans + DVec3::new(0.05 * s, 0.03 * ((k % 3) as f64 - 1.0), 0.0),
                );
                (n.clone(), sim.transform_pose(&moved))
            })
            .collect();
        let bad_dir = tmp.path().join("perturbed");
        write_colmap(&bad_dir, &perturbed);
        let b = compare_colmap(&bad_dir, &gt).unwrap();
        assert_eq!((b.frames, b.registered), (20, 20), "{b:?}");
        assert!(b.ate_rmse_m > 0.02 && b.rot_rmse_deg > 0.3, "{b:?}");
        assert!(b.rpe_trans_rmse_m > 0.02, "{b:?}");

        // An image the exact poses do not have is refused, naming it.
        let mut extra = est.clone();
        extra.push(("images/cam_c/00000.png".into(), Se3::IDENTITY));
        let extra_dir = tmp.path().join("extra");
        write_colmap(&extra_dir, &extra);
        let err = compare_colmap(&extra_dir, &gt).unwrap_err().to_string();
        assert!(err.contains("cam_c/00000.png"), "{err}");
    }

    #[test]
    fn transforms_missing_frames_are_unregistered() {
        let tmp = tempfile::tempdir().unwrap();
        let (gt, _) = exact_world(tmp.path());
        let (mut frames, _, _) = dataset::read_frames(&gt).unwrap();
        frames.retain(|f| !f.file_path.ends_with("00004.png"));
        // Written elsewhere, its paths pointing back at the same images (as `silvr poses` writes them).
        let name = tmp
            .path()
            .file_name()
            .unwrap()
            .to_str()
            .unwrap()
            .to_string();
        for f in &mut frames {
            f.file_path = format!("../../{name}/{}", f.file_path);
        }
        std::fs::create_dir_all(tmp.path().join("out")).unwrap();
        let est = tmp.path().join("out/transforms.json");
        let json = serde_json::json!({ "frames": frames });
        std::fs::write(&est, serde_json::to_string(&json).unwrap()).unwrap();
        let e = compare_transforms(&est, &gt).unwrap();
        assert_eq!((e.frames, e.registered), (20, 18), "{e:?}");
        assert!(e.ate_rmse_m < 1e-9 && e.rpe_trans_rmse_m < 1e-9, "{e:?}");
    }
}
