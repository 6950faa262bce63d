//! Sensor rig: a lidar and cameras with named frames and their extrinsics.
//!
//! The rig stores the calibration in the direction the maths uses (`T_lidar_cam`: camera → lidar,
//! `T_base_lidar`: lidar → base) so that chaining is a plain product:
//! `T_world_cam = T_world_base * T_base_lidar * T_lidar_cam`. Calibration files usually give the opposite
//! direction (Spires lists `T_cam_lidar`); constructors invert at the boundary.

use crate::camera::{CameraError, CameraModel, Distortion};
use crate::geometry::Se3;
use glam::{DQuat, DVec3};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// One camera of a rig.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RigCamera {
    /// Frame and display name, e.g. `cam_front`.
    pub name: String,
    pub model: CameraModel,
    /// Camera → lidar (`p_lidar = t_lidar_cam * p_cam`), OpenCV camera axes.
    pub t_lidar_cam: Se3,
}

/// A lidar-centred rig: `base_frame` ← `lidar_frame` ← cameras.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Rig {
    pub base_frame: String,
    pub lidar_frame: String,
    /// Lidar → base.
    pub t_base_lidar: Se3,
    pub cameras: Vec<RigCamera>,
}

/// Why a [`Rig`] is unusable.
#[derive(Clone, Debug, PartialEq, Error)]
pub enum RigError {
    #[error("frame names must be non-empty")]
    EmptyFrameName,
    #[error("frame name {0:?} is used more than once")]
    DuplicateFrame(String),
    #[error("transform {0} is not finite or its rotation is not a unit quaternion")]
    BadTransform(String),
    #[error("camera {name:?}: {source}")]
    Camera {
        name: String,
        #[source]
        source: CameraError,
    },
}

fn check_se3(t: &Se3, what: &str) -> Result<(), RigError> {
    if !t.is_finite() || (t.rot.length() - 1.0).abs() > 1e-9 {
        return Err(RigError::BadTransform(what.to_string()));
    }
    Ok(())
}

impl Rig {
    /// Camera by frame name.
    pub fn camera(&self, name: &str) -> Option<&RigCamera> {
        self.cameras.iter().find(|c| c.name == name)
    }

    /// Index of a camera by frame name.
    pub fn camera_index(&self, name: &str) -> Option<usize> {
        self.cameras.iter().position(|c| c.name == name)
    }

    /// Camera `i` → base, `None` if there is no camera `i`.
    pub fn t_base_cam(&self, i: usize) -> Option<Se3> {
        self.cameras
            .get(i)
            .map(|c| self.t_base_lidar * c.t_lidar_cam)
    }

    /// Checks frame names (non-empty, unique), transforms (finite, unit rotation) and every camera model.
    pub fn validate(&self) -> Result<(), RigError> {
        let mut names: Vec<&str> = vec![&self.base_frame, &self.lidar_frame];
        names.extend(self.cameras.iter().map(|c| c.name.as_str()));
        for (i, n) in names.iter().enumerate() {
            if n.is_empty() {
                return Err(RigError::EmptyFrameName);
            }
            if names[..i].contains(n) {
                return Err(RigError::DuplicateFrame(n.to_string()));
            }
        }
        check_se3(&self.t_base_lidar, "t_base_lidar")?;
        for c in &self.cameras {
            check_se3(&c.t_lidar_cam, &format!("t_lidar_cam of {}", c.name))?;
            c.model.validate().map_err(|source| RigError::Camera {
                name: c.name.clone(),
                source,
            })?;
        }
        Ok(())
    }

    /// The Oxford Spires / Frontier rig at full resolution (3 × 1440×1080 OPENCV_FISHEYE Alphasense
    /// cameras around a Hesai QT64), numbers from `ori-drs/oxford_spires_dataset` `configs/sensor.yaml`.
    /// The file gives `T_cam_lidar` with quaternions in xyzw order; they are inverted here.
    pub fn oxford_spires() -> Rig {
        // (name, fx, fy, cx, cy, k1..k4, T_cam_lidar translation, T_cam_lidar quaternion xyzw)
        #[allow(clippy::type_complexity)]
        const CAMS: [(&str, [f64; 4], [f64; 4], [f64; 3], [f64; 4]); 3] = [
            (
                "cam_front",
                [698.169, 698.515, 712.765, 560.575],
                [-0.041142, -0.002422, 0.003400, -0.001852],
                [0.00035, -0.07957, -0.05383],
                [0.50347, 0.50033, -0.49475, 0.50140],
            ),
            (
                "cam_left",
                [697.491, 696.917, 719.172, 543.740],
                [-0.044178, 0.006234, -0.002815, -0.000565],
                [0.00003, -0.07994, -0.05600],
                [0.00522, 0.70787, -0.70631, 0.00325],
            ),
            (
                "cam_right",
                [698.459, 699.394, 708.647, 533.739],
                [-0.042477, -0.004215, 0.006942, -0.003408],
                [-0.00061, -0.07992, -0.05480],
                [0.70662, -0.00117, 0.00160, 0.70759],
            ),
        ];
        let cameras = CAMS
            .iter()
            .map(
                |&(name, [fx, fy, cx, cy], [k1, k2, k3, k4], t, [qx, qy, qz, qw])| {
                    // Se3::new normalises: the file's quaternions are rounded to 5 decimals.
                    let t_cam_lidar =
                        Se3::new(DQuat::from_xyzw(qx, qy, qz, qw), DVec3::from_array(t));
                    RigCamera {
                        name: name.to_string(),
                        model: CameraModel {
                            width: 1440,
                            height: 1080,
                            fx,
                            fy,
                            cx,
                            cy,
                            distortion: Distortion::Fisheye { k1, k2, k3, k4 },
                        },
                        t_lidar_cam: t_cam_lidar.inverse(),
                    }
                },
            )
            .collect();
        Rig {
            base_frame: "base_link".to_string(),
            lidar_frame: "lidar".to_string(),
            // 180° yaw, lidar 12.4 cm above base.
            t_base_lidar: Se3::new(
                DQuat::from_xyzw(0.0, 0.0, 1.0, 0.0),
                DVec3::new(0.0, 0.0, 0.124),
            ),
            cameras,
        }
    }

    /// The Spires rig with every camera resized by `factor` ([`CameraModel::scaled`]): 0.5 gives the
    /// 720×540 default of the synthetic dataset, 0.25 the 360×270 CI size. Extrinsics are unchanged.
    ///
    /// # Panics
    /// If `factor` is not finite and positive.
    pub fn oxford_spires_scaled(factor: f64) -> Rig {
        let mut rig = Self::oxford_spires();
        for c in &mut rig.cameras {
            c.model = c.model.scaled(factor);
        }
        rig
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    const DEG: f64 = PI / 180.0;

    #[test]
    fn rig_spires_geometry() {
        let rig = Rig::oxford_spires();
        rig.validate().unwrap();
        assert_eq!(rig.cameras.len(), 3);
        let axis = |name: &str| {
            let i = rig.camera_index(name).unwrap();
            rig.t_base_cam(i).unwrap().transform_vector(DVec3::Z)
        };
        let (f, l, r) = (axis("cam_front"), axis("cam_left"), axis("cam_right"));
        println!("optical axes in base: front {f:.4}, left {l:.4}, right {r:.4}");
        // All three look (nearly) horizontally ...
        for a in [f, l, r] {
            assert!(a.z.abs() < 0.05, "{a}");
        }
        // ... along base +x, +y and -y (x forward, y left: ROS REP-103), i.e. front, left, right.
        assert!(f.angle_between(DVec3::X) < 3.0 * DEG, "{f}");
        assert!(l.angle_between(DVec3::Y) < 3.0 * DEG, "{l}");
        assert!(r.angle_between(-DVec3::Y) < 3.0 * DEG, "{r}");
        for (a, b) in [(f, l), (f, r)] {
            assert!((a.angle_between(b) - 90.0 * DEG).abs() < 3.0 * DEG);
        }
        // Image "down" (camera +y) points down in the base frame for all three cameras (upright mounting).
        for i in 0..3 {
            let down = rig.t_base_cam(i).unwrap().transform_vector(DVec3::Y);
            assert!(down.z < -0.99, "camera {i}: {down}");
        }
        // Camera centres sit a few cm from the lidar, above the base by about 0.124 + 0.05 m.
        for i in 0..3 {
            let c = rig.t_base_cam(i).unwrap().trans;
            assert!(
                c.length() < 0.25 && (c.z - 0.124).abs() < 0.1,
                "camera {i} centre {c}"
            );
        }
        // The stored transform is the inverse of the file's T_cam_lidar.
        let front = rig.camera("cam_front").unwrap();
        let t_cam_lidar = front.t_lidar_cam.inverse();
        assert!((t_cam_lidar.trans - DVec3::new(0.00035, -0.07957, -0.05383)).length() < 1e-12);
        assert!(rig.camera("cam_rear").is_none());
        assert!(rig.t_base_cam(3).is_none());
    }

    #[test]
    fn rig_scaled_and_validate() {
        let half = Rig::oxford_spires_scaled(0.5);
        let quarter = Rig::oxford_spires_scaled(0.25);
        let full = Rig::oxford_spires();
        for ((h, q), f) in half.cameras.iter().zip(&quarter.cameras).zip(&full.cameras) {
            assert_eq!((h.model.width, h.model.height), (720, 540));
            assert_eq!((q.model.width, q.model.height), (360, 270));
            assert_eq!(h.t_lidar_cam, f.t_lidar_cam);
            assert!((h.model.fx - f.model.fx / 2.0).abs() < 1e-12);
            assert!((q.model.cx - ((f.model.cx + 0.5) / 4.0 - 0.5)).abs() < 1e-12);
        }
        half.validate().unwrap();

        let mut bad = full.clone();
        bad.cameras[1].name = "cam_front".into();
        assert_eq!(
            bad.validate(),
            Err(RigError::DuplicateFrame("cam_front".into()))
        );
        let mut bad = full.clone();
        bad.lidar_frame.clear();
        assert_eq!(bad.validate(), Err(RigError::EmptyFrameName));
        let mut bad = full.clone();
        bad.cameras[2].model.fx = 0.0;
        assert!(
            matches!(bad.validate(), Err(RigError::Camera { ref name, .. }) if name == "cam_right")
        );
        let mut bad = full.clone();
        bad.t_base_lidar.trans.x = f64::NAN;
        assert!(matches!(bad.validate(), Err(RigError::BadTransform(_))));
        let mut bad = full;
        bad.cameras[0].t_lidar_cam.rot = DQuat::from_xyzw(0.0, 0.0, 0.0, 2.0);
        assert!(matches!(bad.validate(), Err(RigError::BadTransform(_))));
    }

    #[test]
    fn rig_serde_round_trip() {
        let rig = Rig::oxford_spires_scaled(0.5);
        let json = serde_json::to_string_pretty(&rig).unwrap();
        let back: Rig = serde_json::from_str(&json).unwrap();
        back.validate().unwrap();
        assert_eq!(back.base_frame, rig.base_frame);
        assert_eq!(back.lidar_frame, rig.lidar_frame);
        assert_eq!(back.cameras.len(), 3);
        assert!(back.t_base_lidar.angle_to(&rig.t_base_lidar) < 1e-12);
        for (a, b) in back.cameras.iter().zip(&rig.cameras) {
            assert_eq!(a.name, b.name);
            assert_eq!(a.model.colmap_name(), b.model.colmap_name());
            for (x, y) in a.model.colmap_params().iter().zip(b.model.colmap_params()) {
                assert!((x - y).abs() <= 1e-14 * y.abs().max(1.0));
            }
            assert!(a.t_lidar_cam.angle_to(&b.t_lidar_cam) < 1e-12);
            assert!(a.t_lidar_cam.distance_to(&b.t_lidar_cam) < 1e-15);
        }
    }
}
