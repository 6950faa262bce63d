//! The synthetic world as a ROS 2 bag, recorded the way the Frontier rig records (Oxford Spires topic names,
//! Hesai PointCloud2 layout with absolute per-point times), plus the rig file that `silvr ingest` reads it
//! with. `silvr ingest` of the pair reproduces the dataset `silvr synth` writes — the round-trip test of
//! the whole ingest path.
//!
//! Bag clock: simulation time + [`EPOCH`] (UNIX seconds), because real drivers stamp absolute time and the
//! per-point time heuristics depend on it. Images go in as lossless PNG CompressedImage messages on the
//! Spires topics (Spires itself records JPEG; lossless keeps the round trip exact).

use std::path::Path;

use super::generate::SensorRecorder;
use super::sensors::Sweep;
use super::Preset;
use crate::dataset::png_rgb;
use crate::geometry::{Se3, Trajectory};
use crate::ingest::bag::BagError;
use crate::ingest::config::{IngestSection, RigConfig};
use crate::ingest::ros::{
    CameraInfo, CompressedImage, Header, Odometry, PointCloud2, PointField, RegionOfInterest,
    TfMessage, TransformStamped,
};
use crate::ingest::writer::{ros_time, BagWriter};

/// Bag time of simulation time 0: 2023-11-14 22:13:20 UTC.
pub const EPOCH: f64 = 1_700_000_000.0;
pub const LIDAR_TOPIC: &str = "/hesai/pandar";
pub const ODOMETRY_TOPIC: &str = "/odometry";
pub const WORLD_FRAME: &str = "odom";

/// Spires' image topic of camera `i`.
pub fn image_topic(i: usize) -> String {
    format!("/alphasense_driver_ros/cam{i}/debayered/image/compressed")
}

/// The CameraInfo topic beside it.
pub fn camera_info_topic(i: usize) -> String {
    format!("/alphasense_driver_ros/cam{i}/debayered/camera_info")
}

/// The rig file for a bag of `preset`: the Spires `sensor.yaml` schema with this rig's calibration, and an
/// `ingest:` block that keeps every keyframe (the synthetic keyframes are already spaced).
pub fn rig_config(preset: &Preset) -> RigConfig {
    let mut cfg = RigConfig::from_rig(&preset.rig, image_topic);
    cfg.ingest = IngestSection {
        lidar_topic: LIDAR_TOPIC.into(),
        trajectory_topic: Some(ODOMETRY_TOPIC.into()),
        base_frame: preset.rig.base_frame.clone(),
        keyframe_distance: 0.0,
        keyframe_angle_deg: 0.0,
        min_range: preset.lidar.min_range,
        lidar_columns: None,
        ..IngestSection::default()
    };
    cfg
}

/// The Hesai ROS 2 driver's point layout: x y z intensity (f32), ring (u16), timestamp (f64, absolute s,
/// unaligned at byte 18) — 26 bytes a point.
pub fn hesai_fields() -> Vec<PointField> {
    vec![
        PointField::new("x", 0, PointField::FLOAT32),
        PointField::new("y", 4, PointField::FLOAT32),
        PointField::new("z", 8, PointField::FLOAT32),
        PointField::new("intensity", 12, PointField::FLOAT32),
        PointField::new("ring", 16, PointField::UINT16),
        PointField::new("timestamp", 18, PointField::FLOAT64),
    ]
}

/// One sweep as the Hesai driver publishes it: `header.stamp` = sweep start, frame `lidar_frame`.
pub fn hesai_cloud(sweep: &Sweep, lidar_frame: &str) -> Vec<u8> {
    const STEP: usize = 26;
    let mut data = Vec::with_capacity(sweep.points.len() * STEP);
    for p in &sweep.points {
        for v in [p.position.x, p.position.y, p.position.z] {
            data.extend_from_slice(&(v as f32).to_le_bytes());
        }
        data.extend_from_slice(&p.intensity.to_le_bytes());
        data.extend_from_slice(&p.ring.to_le_bytes());
        data.extend_from_slice(&(p.time + EPOCH).to_le_bytes());
    }
    PointCloud2 {
        header: Header {
            stamp: ros_time(sweep.t0 + EPOCH),
            frame_id: lidar_frame.to_string(),
        },
        height: 1,
        width: sweep.points.len() as u32,
        fields: hesai_fields(),
        is_bigendian: false,
        point_step: STEP as u32,
        row_step: (sweep.points.len() * STEP) as u32,
        data: &data,
        is_dense: true,
    }
    .encode()
}

/// Writes the recording into a bag (see the module docs).
pub struct BagRecorder {
    writer: Option<BagWriter>,
    preset: Option<Preset>,
    /// Odometry of the base (T_world_base) not yet written, in time order.
    odometry: Vec<(f64, Se3)>,
    next_odometry: usize,
}

impl BagRecorder {
    pub fn create(path: &Path) -> Result<Self, BagError> {
        Ok(Self {
            writer: Some(BagWriter::create(path)?),
            preset: None,
            odometry: Vec::new(),
            next_odometry: 0,
        })
    }

    fn writer(&mut self) -> Result<&mut BagWriter, String> {
        self.writer
            .as_mut()
            .ok_or_else(|| "bag already finished".to_string())
    }

    /// Writes odometry messages stamped up to `t` (simulation seconds), keeping the bag in time order.
    fn flush_odometry(&mut self, t: f64) -> Result<(), String> {
        let base = self
            .preset
            .as_ref()
            .map(|p| p.rig.base_frame.clone())
            .unwrap_or_default();
        while let Some(&(stamp, pose)) = self.odometry.get(self.next_odometry) {
            if stamp > t {
                break;
            }
            let msg = Odometry {
                header: Header {
                    stamp: ros_time(stamp + EPOCH),
                    frame_id: WORLD_FRAME.into(),
                },
                child_frame_id: base.clone(),
                pose,
                pose_covariance: [0.0; 36],
                linear: glam::DVec3::ZERO,
                angular: glam::DVec3::ZERO,
                twist_covariance: [0.0; 36],
            };
            self.writer()?
                .write(
                    ODOMETRY_TOPIC,
                    Odometry::MSG,
                    ros_time(stamp + EPOCH),
                    &msg.encode(),
                )
                .map_err(|e| e.to_string())?;
            self.next_odometry += 1;
        }
        Ok(())
    }
}

impl SensorRecorder for BagRecorder {
    fn begin(&mut self, preset: &Preset, odometry: &Trajectory) -> Result<(), String> {
        let t_lidar_base = preset.rig.t_base_lidar.inverse();
        self.odometry = odometry
            .stamps()
            .iter()
            .zip(odometry.poses())
            .map(|(&t, &t_world_lidar)| (t, t_world_lidar * t_lidar_base))
            .collect();
        self.next_odometry = 0;
        self.preset = Some(preset.clone());
        let t0 = odometry.span().0 + EPOCH;
        let header = |frame: &str| Header {
            stamp: ros_time(t0),
            frame_id: frame.to_string(),
        };
        let rig = &preset.rig;
        let mut transforms = vec![TransformStamped {
            header: header(&rig.base_frame),
            child_frame_id: rig.lidar_frame.clone(),
            transform: rig.t_base_lidar,
        }];
        for c in &rig.cameras {
            transforms.push(TransformStamped {
                header: header(&rig.lidar_frame),
                child_frame_id: c.name.clone(),
                transform: c.t_lidar_cam,
            });
        }
        let tf = TfMessage { transforms }.encode();
        self.writer()?
            .write("/tf_static", TfMessage::MSG, ros_time(t0), &tf)
            .map_err(|e| e.to_string())
    }

    fn image(
        &mut self,
        _k: usize,
        camera: usize,
        time: f64,
        rgb: &[[u8; 3]],
    ) -> Result<(), String> {
        self.flush_odometry(time)?;
        let preset = self.preset.clone().ok_or("image before begin")?;
        let cam = preset.rig.cameras.get(camera).ok_or("no such camera")?;
        let m = &cam.model;
        let header = Header {
            stamp: ros_time(time + EPOCH),
            frame_id: cam.name.clone(),
        };
        let png = png_rgb(m.width, m.height, rgb);
        let img = CompressedImage {
            header: header.clone(),
            format: "rgb8; png compressed rgb8".into(),
            data: &png,
        };
        let (model, d) = match m.distortion {
            crate::camera::Distortion::None => ("plumb_bob", vec![0.0; 5]),
            crate::camera::Distortion::RadTan { k1, k2, p1, p2, k3 } => {
                ("plumb_bob", vec![k1, k2, p1, p2, k3])
            }
            crate::camera::Distortion::Fisheye { k1, k2, k3, k4 } => {
                ("equidistant", vec![k1, k2, k3, k4])
            }
        };
        let info = CameraInfo {
            header,
            height: m.height,
            width: m.width,
            distortion_model: model.into(),
            d,
            k: [m.fx, 0.0, m.cx, 0.0, m.fy, m.cy, 0.0, 0.0, 1.0],
            r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            p: [
                m.fx, 0.0, m.cx, 0.0, 0.0, m.fy, m.cy, 0.0, 0.0, 0.0, 1.0, 0.0,
            ],
            binning_x: 0,
            binning_y: 0,
            roi: RegionOfInterest::default(),
        };
        let t = ros_time(time + EPOCH);
        let w = self.writer()?;
        w.write(
            &camera_info_topic(camera),
            CameraInfo::MSG,
            t,
            &info.encode(),
        )
        .map_err(|e| e.to_string())?;
        w.write(&image_topic(camera), CompressedImage::MSG, t, &img.encode())
            .map_err(|e| e.to_string())
    }

    fn sweep(&mut self, _k: usize, sweep: &Sweep) -> Result<(), String> {
        let preset = self.preset.clone().ok_or("sweep before begin")?;
        // The driver publishes a revolution when it is complete.
        let end = sweep.t0 + preset.lidar.sweep_duration();
        self.flush_odometry(end)?;
        let payload = hesai_cloud(sweep, &preset.rig.lidar_frame);
        self.writer()?
            .write(
                LIDAR_TOPIC,
                PointCloud2::MSG,
                ros_time(end + EPOCH),
                &payload,
            )
            .map_err(|e| e.to_string())
    }

    fn finish(&mut self) -> Result<(), String> {
        self.flush_odometry(f64::INFINITY)?;
        let w = self.writer.take().ok_or("bag already finished")?;
        w.finish().map(|_| ()).map_err(|e| e.to_string())
    }
}
