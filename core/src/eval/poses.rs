//! Pose accuracy against exact ground truth: absolute trajectory error (ATE) and relative pose error
//! (RPE) after a robust Sim(3) alignment (Umeyama), as in the TUM RGB-D / EuRoC protocol. The paper's
//! pose ablation compares the SLAM prior, the refined poses and the exact ones by these numbers.
//!
//! Alignment: Umeyama on every frame (its centre and the tips of its axes), then refit on the frames whose residual is within 3 robust
//! standard deviations (1.4826 × median) until the set stops changing, so a few gross errors do not
//! bend the fit; the errors are then reported over **all** frames (the gross ones included: they are
//! the prior's errors) with the median beside the RMSE.

use std::path::Path;

use glam::DVec3;
use serde::Serialize;

use super::metrics::median;
use crate::dataset::{self, DatasetError};
use crate::geometry::{GeometryError, Se3, Sim3};

/// Errors of an estimated trajectory against the exact one.
#[derive(Clone, Debug, PartialEq, Serialize, serde::Deserialize)]
pub struct PoseErrors {
    pub frames: usize,
    /// Frames the alignment kept (the rest are gross errors).
    pub inliers: usize,
    /// Scale of the Sim(3) alignment (estimate → ground truth).
    pub scale: f64,
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
    // centres, which a line does determine).
    let scale0 = Sim3::umeyama(&src, &dst, true)?.scale.max(1e-12);
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
        Sim3::umeyama(&s, &d, true)
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
        inliers: keep.iter().filter(|&&k| k).count(),
        scale: sim.scale,
        ate_rmse_m: rms(&ate),
        ate_median_m: median(&ate),
        ate_max_m: ate.iter().copied().fold(0.0, f64::max),
        rot_rmse_deg: rms(&rot),
        rot_median_deg: median(&rot),
        rpe_trans_rmse_m: rms(&rpe_t),
        rpe_rot_rmse_deg: rms(&rpe_r),
    })
}

/// Errors of the camera poses of one `transforms.json` against another's, frames matched by image path.
/// Consecutive pairs for RPE are consecutive frames of one camera (the file's order within a camera).
pub fn compare_transforms(est: &Path, gt: &Path) -> Result<PoseErrors, PoseEvalError> {
    let (e, _, _) = dataset::read_frames(est)?;
    let (g, _, _) = dataset::read_frames(gt)?;
    let exact: std::collections::HashMap<&str, &dataset::NsFrame> =
        g.iter().map(|f| (f.file_path.as_str(), f)).collect();
    // Group by camera so each pair of consecutive frames is one camera's motion.
    let mut by_camera: std::collections::BTreeMap<String, Vec<(Se3, Se3)>> = Default::default();
    for f in &e {
        let Some(x) = exact.get(f.file_path.as_str()) else {
            return Err(PoseEvalError::Mismatch {
                what: est.display().to_string(),
                detail: format!("frame {} is not in {}", f.file_path, gt.display()),
            });
        };
        let (_, pe) = f.camera(est)?;
        let (_, pg) = x.camera(gt)?;
        let cam = f.camera.clone().unwrap_or_else(|| {
            Path::new(&f.file_path)
                .parent()
                .map(|p| p.display().to_string())
                .unwrap_or_default()
        });
        by_camera.entry(cam).or_default().push((pe, pg));
    }
    let mut starts = Vec::new();
    let (mut est_poses, mut gt_poses) = (Vec::new(), Vec::new());
    for seq in by_camera.into_values() {
        starts.push(est_poses.len());
        for (e, g) in seq {
            est_poses.push(e);
            gt_poses.push(g);
        }
    }
    pose_errors_of_sequences(&est_poses, &gt_poses, &starts)
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
}
