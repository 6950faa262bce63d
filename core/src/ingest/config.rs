//! The rig file `silvr ingest --config` reads: the Oxford Spires `sensor.yaml` schema (cameras with topic,
//! `T_cam_lidar`, intrinsics and distortion; `T_base_lidar`), so users' existing calibrations work as they
//! are, plus an optional `ingest:` section with the topics and keyframe rules. Every calibration field may be
//! left out when the bag carries it (CameraInfo, `/tf_static`).
//!
//! ```yaml
//! sensor:
//!   cameras:
//!     - label: cam_front
//!       topic: /alphasense_driver_ros/cam0/debayered/image/compressed
//!       T_cam_lidar_t_xyz_q_xyzw: [0.00035, -0.07957, -0.05383, 0.50347, 0.50033, -0.49475, 0.50140]
//!       intrinsics: [698.169, 698.515, 712.765, 560.575]       # fx fy cx cy, OpenCV pixel centres
//!       extra_params: [-0.041142, -0.002422, 0.003400, -0.001852]
//!       image_height: 1080
//!       image_width: 1440
//!   camera_model: OPENCV_FISHEYE                                 # or OPENCV (k1 k2 p1 p2 [k3]), PINHOLE
//!   max_time_diff_camera_and_pose: 0.025
//!   T_base_lidar_t_xyz_q_xyzw: [0.0, 0.0, 0.124, 0.0, 0.0, 1.0, 0.0]
//! ingest:                                                        # every key optional; defaults shown
//!   lidar_topic: /hesai/pandar
//!   trajectory_topic: /odometry        # nav_msgs/Odometry, Path, PoseStamped or PoseWithCovarianceStamped
//!   keyframe_distance: 0.5             # m moved since the last keyframe ...
//!   keyframe_angle_deg: 10.0           # ... or degrees turned
//! ```

use std::path::Path;

use glam::{DQuat, DVec3};
use serde::{Deserialize, Serialize};

use crate::camera::{CameraModel, Distortion};
use crate::geometry::Se3;

/// Why a rig file is unusable. Every message names the file.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{file}: {source}")]
    Io {
        file: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{file}: not a valid rig file: {reason}")]
    Parse { file: String, reason: String },
    #[error("{file}: {reason}")]
    Invalid { file: String, reason: String },
}

/// The whole file.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigConfig {
    pub sensor: SensorSection,
    #[serde(default)]
    pub ingest: IngestSection,
}

/// Spires' `sensor:` block.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SensorSection {
    pub cameras: Vec<CameraEntry>,
    /// `OPENCV_FISHEYE`, `OPENCV` or `PINHOLE` (applies to every camera with intrinsics).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera_model: Option<String>,
    /// Spires drops points outside this field of view before projecting; kept for reference (our
    /// projection validates against the model's own monotonic range).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera_fov: Option<f64>,
    /// An image is used only if the trajectory has a sample at most this far (s) from its time.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_time_diff_camera_and_pose: Option<f64>,
    #[serde(
        rename = "T_base_lidar_t_xyz_q_xyzw",
        default,
        skip_serializing_if = "Option::is_none"
    )]
    pub t_base_lidar: Option<Vec<f64>>,
}

/// One camera of `sensor.cameras`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CameraEntry {
    /// Camera name in the dataset (`cam_front`).
    pub label: String,
    /// Image topic (sensor_msgs/Image or CompressedImage).
    pub topic: String,
    /// CameraInfo topic; by default any CameraInfo whose frame_id is the images' frame_id.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera_info_topic: Option<String>,
    #[serde(
        rename = "T_cam_lidar_t_xyz_q_xyzw",
        default,
        skip_serializing_if = "Option::is_none"
    )]
    pub t_cam_lidar: Option<Vec<f64>>,
    /// `T_cam_imu` and other Spires extras are accepted and ignored.
    #[serde(
        rename = "T_cam_imu_t_xyz_q_xyzw",
        default,
        skip_serializing_if = "Option::is_none"
    )]
    pub t_cam_imu: Option<Vec<f64>>,
    /// fx fy cx cy.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub intrinsics: Option<Vec<f64>>,
    /// Distortion coefficients of `camera_model`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub extra_params: Option<Vec<f64>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image_height: Option<u32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image_width: Option<u32>,
}

fn default_lidar_topic() -> String {
    "/hesai/pandar".into()
}
fn default_trajectory_topic() -> Option<String> {
    Some("/odometry".into())
}
fn default_keyframe_distance() -> f64 {
    0.5
}
fn default_keyframe_angle() -> f64 {
    10.0
}
fn default_camera_sync() -> f64 {
    0.005
}
fn default_min_range() -> f64 {
    0.1
}
fn default_base_frame() -> String {
    "base_link".into()
}

/// Our `ingest:` block.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IngestSection {
    /// sensor_msgs/PointCloud2 with per-point time.
    #[serde(default = "default_lidar_topic")]
    pub lidar_topic: String,
    /// The trajectory in the bag (nav_msgs/Odometry, nav_msgs/Path, PoseStamped, PoseWithCovarianceStamped,
    /// or a TF topic such as `/tf`, whose edge with child `trajectory_frame` (default: the base frame) is
    /// used); its child frame (Odometry's `child_frame_id`, else `trajectory_frame`) is looked up in the TF
    /// tree.
    #[serde(default = "default_trajectory_topic")]
    pub trajectory_topic: Option<String>,
    /// A trajectory file instead of a topic (relative to the rig file), e.g. a SLAM system's output: TUM,
    /// KITTI (+ times.txt), Oxford Spires slam-poses.csv or EuRoC data.csv, detected from the file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub trajectory_file: Option<String>,
    /// Frame the trajectory poses (`base_link` unless Odometry says otherwise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub trajectory_frame: Option<String>,
    /// The trajectory from lidar odometry over `lidar_topic` ([`crate::odometry`]) instead of a topic or
    /// file (`silvr ingest --trajectory lidar`). A bag with neither gets it anyway, with a notice.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub trajectory_from_lidar: bool,
    /// The rig's body frame in the TF tree.
    #[serde(default = "default_base_frame")]
    pub base_frame: String,
    /// A new keyframe once the rig moved this far (m) ...
    #[serde(default = "default_keyframe_distance")]
    pub keyframe_distance: f64,
    /// ... or turned this much (degrees) since the last one; 0 and 0 keep every image set.
    #[serde(default = "default_keyframe_angle")]
    pub keyframe_angle_deg: f64,
    /// Images of different cameras within this many seconds form one set.
    #[serde(default = "default_camera_sync")]
    pub camera_sync: f64,
    /// Lidar returns nearer than this (m) are ignored.
    #[serde(default = "default_min_range")]
    pub min_range: f64,
    /// Azimuth columns per revolution; estimated from the data when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lidar_columns: Option<u32>,
    /// Clouds without per-point time: time each point from its azimuth (a spinning lidar's firing order)
    /// instead of taking the cloud as motion-compensated to its stamp.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub azimuth_timing: Option<AzimuthTiming>,
    /// Only images in [start, end] (bag seconds) are considered.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub end: Option<f64>,
    /// Stop after this many keyframes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_keyframes: Option<usize>,
}

impl Default for IngestSection {
    fn default() -> Self {
        Self {
            lidar_topic: default_lidar_topic(),
            trajectory_topic: default_trajectory_topic(),
            trajectory_file: None,
            trajectory_frame: None,
            trajectory_from_lidar: false,
            base_frame: default_base_frame(),
            keyframe_distance: default_keyframe_distance(),
            keyframe_angle_deg: default_keyframe_angle(),
            camera_sync: default_camera_sync(),
            min_range: default_min_range(),
            lidar_columns: None,
            azimuth_timing: None,
            start: None,
            end: None,
            max_keyframes: None,
        }
    }
}

/// How a spinning lidar's points are timed from their azimuth (`ingest.azimuth_timing`), for drivers that
/// publish no per-point time: the sweep starts at `header.stamp` facing `start_azimuth_deg` (in the lidar
/// frame, from +x towards +y) and turns once in `period` seconds, `ccw` (azimuth increasing seen from
/// above, as Hesai and our synthetic lidar) or `cw` (Velodyne, Ouster).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AzimuthTiming {
    pub spin: Spin,
    #[serde(default)]
    pub start_azimuth_deg: f64,
    /// Seconds per turn; the median interval between the clouds' stamps when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub period: Option<f64>,
}

/// Which way a spinning lidar turns, seen from above (+z of its frame).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Spin {
    Ccw,
    Cw,
}

impl AzimuthTiming {
    /// Seconds after the sweep's start at which a point at `p` (lidar frame) was fired, for a turn of
    /// `period` s: in [0, period).
    pub fn offset(&self, p: glam::DVec3, period: f64) -> f64 {
        let az = p.y.atan2(p.x).to_degrees() - self.start_azimuth_deg;
        let turned = match self.spin {
            Spin::Ccw => az,
            Spin::Cw => -az,
        };
        turned.rem_euclid(360.0) / 360.0 * period
    }
}

/// `[tx, ty, tz, qx, qy, qz, qw]` → Se3 (quaternion normalised; calibration files round them).
pub fn se3_from_t_xyz_q_xyzw(v: &[f64]) -> Result<Se3, String> {
    if v.len() != 7 || v.iter().any(|x| !x.is_finite()) {
        return Err(format!(
            "expected 7 finite numbers [tx, ty, tz, qx, qy, qz, qw], got {v:?}"
        ));
    }
    let q = DQuat::from_xyzw(v[3], v[4], v[5], v[6]);
    if (q.length() - 1.0).abs() > 0.01 {
        return Err(format!("quaternion {:?} is not of unit length", &v[3..]));
    }
    Ok(Se3::new(q.normalize(), DVec3::new(v[0], v[1], v[2])))
}

/// Se3 → `[tx, ty, tz, qx, qy, qz, qw]`.
pub fn se3_to_t_xyz_q_xyzw(t: &Se3) -> Vec<f64> {
    vec![
        t.trans.x, t.trans.y, t.trans.z, t.rot.x, t.rot.y, t.rot.z, t.rot.w,
    ]
}

impl RigConfig {
    /// Reads and checks a rig file.
    pub fn read(path: &Path) -> Result<Self, ConfigError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            file: file.clone(),
            source,
        })?;
        Self::parse(&text, &file)
    }

    /// Parses rig-file text; `file` names it in errors.
    pub fn parse(text: &str, file: &str) -> Result<Self, ConfigError> {
        let cfg: RigConfig = serde_saphyr::from_str(text).map_err(|e| ConfigError::Parse {
            file: file.to_string(),
            reason: e.to_string(),
        })?;
        cfg.validate().map_err(|reason| ConfigError::Invalid {
            file: file.to_string(),
            reason,
        })?;
        Ok(cfg)
    }

    /// As YAML text.
    pub fn to_yaml(&self) -> String {
        serde_saphyr::to_string(self).expect("plain data serialises")
    }

    fn validate(&self) -> Result<(), String> {
        if self.sensor.cameras.is_empty() {
            return Err("sensor.cameras is empty".into());
        }
        let mut labels = std::collections::BTreeSet::new();
        for (i, c) in self.sensor.cameras.iter().enumerate() {
            let label = &c.label;
            if label.is_empty() || label.contains(['/', '\\']) || label.starts_with('.') {
                return Err(format!(
                    "camera {i}: label {label:?} is not a usable folder name"
                ));
            }
            if !labels.insert(label) {
                return Err(format!("camera label {label:?} is used twice"));
            }
            if let Some(t) = &c.t_cam_lidar {
                se3_from_t_xyz_q_xyzw(t)
                    .map_err(|e| format!("{label}: T_cam_lidar_t_xyz_q_xyzw: {e}"))?;
            }
            if c.intrinsics.is_some() {
                self.camera_model(c).map_err(|e| format!("{label}: {e}"))?;
            }
        }
        if let Some(t) = &self.sensor.t_base_lidar {
            se3_from_t_xyz_q_xyzw(t).map_err(|e| format!("T_base_lidar_t_xyz_q_xyzw: {e}"))?;
        }
        let i = &self.ingest;
        for (name, v) in [
            ("keyframe_distance", i.keyframe_distance),
            ("keyframe_angle_deg", i.keyframe_angle_deg),
            ("camera_sync", i.camera_sync),
            ("min_range", i.min_range),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("ingest.{name} must be finite and >= 0, got {v}"));
            }
        }
        if let Some(d) = self.sensor.max_time_diff_camera_and_pose {
            if !(d.is_finite() && d > 0.0) {
                return Err(format!(
                    "max_time_diff_camera_and_pose must be > 0, got {d}"
                ));
            }
        }
        if i.lidar_columns == Some(0) {
            return Err("ingest.lidar_columns must be > 0".into());
        }
        if let Some(a) = &i.azimuth_timing {
            if !a.start_azimuth_deg.is_finite() {
                return Err("ingest.azimuth_timing.start_azimuth_deg must be finite".into());
            }
            if let Some(p) = a.period {
                if !(p.is_finite() && p > 0.0 && p <= 10.0) {
                    return Err(format!(
                        "ingest.azimuth_timing.period must be in (0, 10] seconds, got {p}"
                    ));
                }
            }
        }
        Ok(())
    }

    /// The camera model given in the file for `c` (which must have `intrinsics`).
    pub fn camera_model(&self, c: &CameraEntry) -> Result<CameraModel, String> {
        let k = c.intrinsics.as_deref().ok_or("no intrinsics")?;
        let [fx, fy, cx, cy] = k else {
            return Err(format!("intrinsics must be [fx, fy, cx, cy], got {k:?}"));
        };
        let (Some(width), Some(height)) = (c.image_width, c.image_height) else {
            return Err("intrinsics need image_width and image_height".into());
        };
        let d = c.extra_params.as_deref().unwrap_or(&[]);
        let model = self
            .sensor
            .camera_model
            .as_deref()
            .unwrap_or("OPENCV_FISHEYE");
        let distortion = match (model, d) {
            (_, []) | ("PINHOLE", _) => Distortion::None,
            ("OPENCV_FISHEYE", &[k1, k2, k3, k4]) => Distortion::Fisheye { k1, k2, k3, k4 },
            ("OPENCV", &[k1, k2, p1, p2]) => Distortion::RadTan {
                k1,
                k2,
                p1,
                p2,
                k3: 0.0,
            },
            ("OPENCV", &[k1, k2, p1, p2, k3]) => Distortion::RadTan { k1, k2, p1, p2, k3 },
            (m @ ("OPENCV_FISHEYE" | "OPENCV"), d) => {
                return Err(format!(
                    "{m} takes 4 (OPENCV: 4 or 5) extra_params, got {}",
                    d.len()
                ))
            }
            (m, _) => {
                return Err(format!(
                    "camera_model {m:?} is not one of OPENCV_FISHEYE, OPENCV, PINHOLE"
                ))
            }
        };
        let m = CameraModel {
            width,
            height,
            fx: *fx,
            fy: *fy,
            cx: *cx,
            cy: *cy,
            distortion,
        };
        m.validate().map_err(|e| e.to_string())?;
        Ok(m)
    }

    /// The rig file of a [`Rig`]: its calibration in the Spires schema, camera `i` on `topic(i)`, the
    /// ingest block left at its defaults.
    pub fn from_rig(rig: &crate::rig::Rig, topic: impl Fn(usize) -> String) -> RigConfig {
        let cameras = rig
            .cameras
            .iter()
            .enumerate()
            .map(|(i, c)| CameraEntry {
                label: c.name.clone(),
                topic: topic(i),
                camera_info_topic: None,
                t_cam_lidar: Some(se3_to_t_xyz_q_xyzw(&c.t_lidar_cam.inverse())),
                t_cam_imu: None,
                intrinsics: Some(vec![c.model.fx, c.model.fy, c.model.cx, c.model.cy]),
                extra_params: Some(Self::model_fields(&c.model).1),
                image_height: Some(c.model.height),
                image_width: Some(c.model.width),
            })
            .collect();
        RigConfig {
            sensor: SensorSection {
                cameras,
                camera_model: rig
                    .cameras
                    .first()
                    .map(|c| Self::model_fields(&c.model).0.to_string()),
                camera_fov: None,
                max_time_diff_camera_and_pose: Some(0.025),
                t_base_lidar: Some(se3_to_t_xyz_q_xyzw(&rig.t_base_lidar)),
            },
            ingest: IngestSection {
                base_frame: rig.base_frame.clone(),
                ..IngestSection::default()
            },
        }
    }

    /// The file's model name and coefficients for a [`CameraModel`] (inverse of [`Self::camera_model`]).
    pub fn model_fields(m: &CameraModel) -> (&'static str, Vec<f64>) {
        match m.distortion {
            Distortion::None => ("PINHOLE", vec![]),
            Distortion::RadTan { k1, k2, p1, p2, k3 } => ("OPENCV", vec![k1, k2, p1, p2, k3]),
            Distortion::Fisheye { k1, k2, k3, k4 } => ("OPENCV_FISHEYE", vec![k1, k2, k3, k4]),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Oxford Spires `config/sensor.yaml` as published (two cameras shown, numbers abbreviated).
    const SPIRES: &str = "sensor:
  cameras:
    - label: cam_front
      topic: /alphasense_driver_ros/cam0/debayered/image/compressed
      T_cam_lidar_t_xyz_q_xyzw: [0.00035060884033447846, -0.079574053851818,
        -0.053826061545697405, 0.5034725628949727, 0.5003337192107279, -0.4947539264483171,
        0.5013981452864594]
      T_cam_imu_t_xyz_q_xyzw: [-0.0045,-0.0020,-0.0548,0.0067828148322833575,-0.7111602175046777,0.7029949006508702,0.0018188239395917287]
      intrinsics: [698.1692094914263, 698.5147584873237, 712.7646767255006, 560.5751284820508]
      extra_params: [-0.04114225009462773, -0.002421765984053725, 0.003400355152679783,
        -0.0018518822347983275]
      image_height: 1080
      image_width: 1440
    - label: cam_left
      topic: /alphasense_driver_ros/cam1/debayered/image/compressed
      T_cam_lidar_t_xyz_q_xyzw: [3.388762063794015e-05, -0.07994358595369325,
        -0.05600121569499821, 0.005222551021921984, 0.7078744176660065, -0.7063115244548896,
        0.0032502610734581453]
      intrinsics: [697.4908124760002, 696.9171455329763, 719.1718975625936, 543.7401536075661]
      extra_params: [-0.04417827343575797, 0.006234275291082348, -0.0028153029005502637,
        -0.0005652124301059104]
      image_height: 1080
      image_width: 1440
  camera_model: OPENCV_FISHEYE
  camera_fov: 160.0
  max_time_diff_camera_and_pose: 0.025
  T_base_lidar_t_xyz_q_xyzw: [0.0, 0.0, 0.124, 0.0, 0.0, 1.0, 0.0]
";

    #[test]
    fn reads_the_spires_sensor_yaml_unchanged() {
        let cfg = RigConfig::parse(SPIRES, "sensor.yaml").unwrap();
        assert_eq!(cfg.sensor.cameras.len(), 2);
        let front = &cfg.sensor.cameras[0];
        let m = cfg.camera_model(front).unwrap();
        assert_eq!((m.width, m.height), (1440, 1080));
        assert!(
            matches!(m.distortion, Distortion::Fisheye { k1, .. } if (k1 + 0.04114225009462773).abs() < 1e-15)
        );
        let t = se3_from_t_xyz_q_xyzw(front.t_cam_lidar.as_ref().unwrap()).unwrap();
        // The front camera looks along the base's +x: the lidar is yawed 180°, so along lidar -x.
        let axis_in_lidar = t.inverse().transform_vector(DVec3::Z);
        assert!(axis_in_lidar.x < -0.99, "{axis_in_lidar}");
        assert_eq!(cfg.ingest.lidar_topic, "/hesai/pandar");
        assert_eq!(cfg.sensor.max_time_diff_camera_and_pose, Some(0.025));
        // Round trip through our own YAML.
        let back = RigConfig::parse(&cfg.to_yaml(), "again.yaml").unwrap();
        assert_eq!(
            back.sensor.cameras[1].intrinsics,
            cfg.sensor.cameras[1].intrinsics
        );
        assert_eq!(back.sensor.t_base_lidar, cfg.sensor.t_base_lidar);
    }

    #[test]
    fn azimuth_timing_reads_and_times_a_turn() {
        let cfg = RigConfig::parse(
            "sensor:\n  cameras:\n    - {label: a, topic: /a}\ningest:\n  azimuth_timing: {spin: cw, start_azimuth_deg: 180}\n",
            "rig.yaml",
        )
        .unwrap();
        let a = cfg.ingest.azimuth_timing.unwrap();
        assert_eq!(
            (a.spin, a.start_azimuth_deg, a.period),
            (Spin::Cw, 180.0, None)
        );
        // Clockwise (azimuth decreasing) from -x: +y after a quarter of the turn, -y after three.
        let at = |x: f64, y: f64| a.offset(DVec3::new(x, y, 0.3), 0.1);
        assert!(at(-1.0, 0.0).abs() < 1e-12);
        assert!((at(0.0, 1.0) - 0.025).abs() < 1e-12 && (at(0.0, -1.0) - 0.075).abs() < 1e-12);
        let ccw = AzimuthTiming {
            spin: Spin::Ccw,
            ..a
        };
        assert!((ccw.offset(DVec3::new(0.0, 1.0, 0.0), 0.1) - 0.075).abs() < 1e-12);
    }

    #[test]
    fn bad_files_are_named_errors() {
        let cases = [
            ("sensor: [", "not a valid rig file"),
            ("sensor:\n  cameras: []\n", "sensor.cameras is empty"),
            ("other: 1\n", "not a valid rig file"),
            (
                "sensor:\n  cameras:\n    - {label: a, topic: /a, intrinsics: [1, 2, 3]}\n",
                "intrinsics must be",
            ),
            (
                "sensor:\n  cameras:\n    - {label: a, topic: /a}\n    - {label: a, topic: /b}\n",
                "used twice",
            ),
            (
                "sensor:\n  cameras:\n    - {label: ../x, topic: /a}\n",
                "usable folder name",
            ),
            (
                "sensor:\n  cameras:\n    - {label: a, topic: /a, T_cam_lidar_t_xyz_q_xyzw: [0, 0, 0, 0, 0, 0, 0]}\n",
                "not of unit length",
            ),
            (
                "sensor:\n  cameras:\n    - {label: a, topic: /a}\ningest:\n  keyframe_distance: -1\n",
                "keyframe_distance",
            ),
            (
                "sensor:\n  cameras:\n    - {label: a, topic: /a}\ningest:\n  lidar_topc: /x\n",
                "not a valid rig file",
            ),
            (
                "sensor:\n  cameras:\n    - {label: a, topic: /a}\ningest:\n  azimuth_timing: {spin: cw, period: 0}\n",
                "azimuth_timing.period",
            ),
            (
                "sensor:\n  cameras:\n    - {label: a, topic: /a}\ningest:\n  azimuth_timing: {spin: left}\n",
                "not a valid rig file",
            ),
            (
                "sensor:\n  camera_model: KB8\n  cameras:\n    - {label: a, topic: /a, intrinsics: [1, 1, 1, 1], extra_params: [0, 0], image_width: 4, image_height: 4}\n",
                "is not one of",
            ),
        ];
        for (text, want) in cases {
            let e = RigConfig::parse(text, "rig.yaml").unwrap_err().to_string();
            assert!(
                e.starts_with("rig.yaml: ") && e.contains(want),
                "{text:?} → {e}"
            );
        }
    }
}
