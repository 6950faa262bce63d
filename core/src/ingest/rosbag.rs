//! A ROS 1 or ROS 2 bag (any container [`super::bag`] reads) → the project's dataset (`DATASET.md`), the path real data takes into training.
//!
//! Two streaming passes over the MCAP, so memory holds only the keyframes being assembled:
//! 1. **Index**: per-topic counts; `/tf_static`; CameraInfo; the trajectory messages; the stamp and frame
//!    of every image; every sweep's time span, beams and azimuth step.
//! 2. **Assemble**: image sets (one image per camera within `camera_sync`), each with a trajectory pose
//!    and a sweep that covers its time, thinned to keyframes by distance and angle; their images and
//!    sweeps are decoded on the second pass, and each keyframe goes through the same lidar code as the
//!    synthetic world (deskew to the image time, Newell normals on the range image, GPU projection, sky
//!    mask — [`crate::lidar::products`]).
//!
//! Everything is written into a staging folder that is renamed only at the end ([`DatasetWriter`]).
//! Calibration comes from the rig file when it has it, else from the bag (CameraInfo, `/tf_static`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::DVec3;
use serde::Serialize;

use super::bag::{BagError, BagReader};
use super::config::{se3_from_t_xyz_q_xyzw, ConfigError, RigConfig};
use super::ros::{self, CameraInfo, LidarScan, RgbImage, RosMessage};
use super::tf::TfGraph;
use crate::camera::CameraModel;
use crate::dataset::{self, DatasetError, DatasetWriter, NsFrame};
use crate::geometry::{Se3, Trajectory};
use crate::gpu::{Gpu, GpuError};
use crate::lidar::{deskew, normals, products};
use crate::pointcloud::{write_ply_bytes, PointCloud};
use crate::rig::{Rig, RigCamera};

/// Version of this writer, recorded in the manifest.
pub const INGEST_VERSION: &str = "silvr-ingest 1";

/// Why an ingest failed. Every message names the file it is about.
#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    #[error(transparent)]
    Bag(#[from] BagError),
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error("GPU: {0}")]
    Gpu(#[from] GpuError),
    /// The bag and rig file together do not give what a dataset needs.
    #[error("{file}: {reason}")]
    Unusable { file: String, reason: String },
}

/// Progress of a long step.
#[derive(Clone, Debug)]
pub struct Progress<'a> {
    pub stage: &'a str,
    pub done: u64,
    pub total: u64,
}

/// Messages of one topic.
#[derive(Clone, Debug, Default, Serialize)]
pub struct TopicCount {
    pub schema: String,
    pub messages: u64,
    /// Messages this ingest used (decoded and part of a keyframe or calibration).
    pub used: u64,
}

/// What an ingest read and wrote.
#[derive(Clone, Debug, Serialize)]
pub struct IngestSummary {
    pub path: PathBuf,
    pub bag: String,
    pub keyframes: usize,
    pub images: usize,
    pub lidar_points: usize,
    /// First and last log time (s) of the bag.
    pub time_span: (f64, f64),
    pub topics: BTreeMap<String, TopicCount>,
    /// Why data was left out, with counts.
    pub dropped: BTreeMap<String, u64>,
    /// Beams and columns of the lidar range image, and where they came from.
    pub lidar_beams: usize,
    pub lidar_columns: usize,
    /// Where the trajectory came from: a topic, a file, or `lidar odometry (topic)`.
    pub trajectory: String,
    /// What the user should know about choices made for them (e.g. odometry standing in for a missing
    /// trajectory).
    pub notices: Vec<String>,
}

/// One sweep as seen in pass 1.
#[derive(Clone, Debug)]
struct SweepRef {
    index: u64,
    /// Absolute time of its first and last point (s); for a cloud without per-point time, the time span
    /// it stands for (its stamp ± half the sweep period, set after pass 1).
    start: f64,
    end: f64,
    /// Whether its points carry their own times.
    timed: bool,
}

/// One image as seen in pass 1.
#[derive(Clone, Debug)]
struct ImageRef {
    index: u64,
    time: f64,
}

/// A keyframe chosen in pass 1 and filled in pass 2.
struct Pending {
    k: usize,
    time: f64,
    sweep: u64,
    /// Per camera: the message index and its time.
    images: Vec<ImageRef>,
    got_images: Vec<Option<RgbImage>>,
    got_sweep: Option<LidarScan>,
}

/// Everything pass 1 learns.
#[derive(Default)]
struct Index {
    topics: BTreeMap<String, TopicCount>,
    time_span: Option<(f64, f64)>,
    tf_static: TfGraph,
    infos: Vec<(String, CameraInfo)>,
    /// Trajectory samples (stamp, pose) and the frames they relate.
    trajectory: Vec<(f64, Se3)>,
    trajectory_child: Option<String>,
    images: Vec<Vec<ImageRef>>,
    image_frames: Vec<Option<String>>,
    sweeps: Vec<SweepRef>,
    lidar_frame: Option<String>,
    max_ring: Option<u16>,
    column_estimates: Vec<usize>,
    dropped: BTreeMap<String, u64>,
    /// Sweeps without per-point time (treated as motion-compensated to their stamp) and without `ring`
    /// (beams from an angular grid).
    untimed: u64,
    ringless: u64,
}

fn secs(t: ros::Time) -> f64 {
    t.sec as f64 + t.nanosec as f64 * 1e-9
}

fn drop_count(d: &mut BTreeMap<String, u64>, why: impl Into<String>) {
    *d.entry(why.into()).or_insert(0) += 1;
}

/// Reads `bag` with `cfg` (the rig file, its folder in `cfg_dir` for relative paths) and writes the
/// dataset to `out`.
pub async fn ingest_bag(
    bag: &Path,
    cfg: &RigConfig,
    cfg_dir: &Path,
    out: &Path,
    overwrite: bool,
    gpu: &Gpu,
    progress: &mut dyn FnMut(Progress),
) -> Result<IngestSummary, IngestError> {
    let file = bag.display().to_string();
    let unusable = |reason: String| IngestError::Unusable {
        file: file.clone(),
        reason,
    };
    let ing = &cfg.ingest;
    let cams = &cfg.sensor.cameras;
    let bytes = super::bag::bag_bytes(bag)?;
    // Refuse early, before reading a possibly huge bag, when the output cannot be written.
    let writer = DatasetWriter::create(out, overwrite)?;

    // ---- pass 1: index --------------------------------------------------------------------------
    let mut ix = Index {
        images: vec![Vec::new(); cams.len()],
        image_frames: vec![None; cams.len()],
        ..Index::default()
    };
    let cam_of_topic: BTreeMap<&str, usize> = cams
        .iter()
        .enumerate()
        .map(|(i, c)| (c.topic.as_str(), i))
        .collect();
    let mut reader = BagReader::open(bag)?;
    let mut n = 0u64;
    for msg in reader.by_ref() {
        let msg = msg?;
        n += 1;
        if n.is_multiple_of(2000) {
            progress(Progress {
                stage: "index",
                done: n,
                total: 0,
            });
        }
        let t_log = msg.log_time() as f64 * 1e-9;
        ix.time_span = Some(match ix.time_span {
            None => (t_log, t_log),
            Some((a, b)) => (a.min(t_log), b.max(t_log)),
        });
        let topic = msg.topic().to_string();
        let entry = ix.topics.entry(topic.clone()).or_default();
        entry.schema = msg.schema_name().to_string();
        entry.messages += 1;
        let decoded = match msg.decode() {
            Ok(Ok(m)) => m,
            Ok(Err(_skip)) => continue,
            Err(e) => {
                // A broken message on a topic we need is dropped and counted; elsewhere it is ignored.
                let relevant = topic == ing.lidar_topic
                    || cam_of_topic.contains_key(topic.as_str())
                    || ing.trajectory_topic.as_deref() == Some(topic.as_str());
                if relevant {
                    drop_count(
                        &mut ix.dropped,
                        format!("{topic}: undecodable message ({e})"),
                    );
                }
                continue;
            }
        };
        let mut used = false;
        match decoded {
            RosMessage::Tf(tf) if topic == "/tf_static" => {
                for t in &tf.transforms {
                    if t.transform.is_finite() && t.transform.rot.length() > 0.5 {
                        ix.tf_static
                            .insert(&t.header.frame_id, &t.child_frame_id, t.transform);
                    }
                }
                used = true;
            }
            RosMessage::Tf(tf)
                if ing.trajectory_topic.as_deref() == Some(topic.as_str())
                    && ing.trajectory_file.is_none() =>
            {
                // A TF topic as the trajectory: the one edge whose child is the trajectory frame
                // (`odom` → `base_link` from an odometry node), in the parent's frame.
                let child = ing.trajectory_frame.as_deref().unwrap_or(&ing.base_frame);
                for t in tf.transforms.iter().filter(|t| t.child_frame_id == child) {
                    ix.trajectory_child.get_or_insert_with(|| child.to_string());
                    ix.trajectory.push((secs(t.header.stamp), t.transform));
                    used = true;
                }
            }
            RosMessage::CameraInfo(info) => {
                ix.infos.push((topic.clone(), *info));
                used = true;
            }
            RosMessage::PointCloud2(pc) if topic == ing.lidar_topic => match pc.to_scan() {
                Ok(scan) => {
                    let stamp = secs(scan.stamp);
                    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
                    for &t in scan.times.iter().flatten() {
                        lo = lo.min(t);
                        hi = hi.max(t);
                    }
                    if scan.positions.is_empty() {
                        drop_count(&mut ix.dropped, format!("{topic}: sweep without points"));
                    } else {
                        let timed = scan.times.is_some();
                        if !timed {
                            (lo, hi) = (0.0, 0.0);
                            ix.untimed += 1;
                        }
                        if scan.rings.is_none() {
                            ix.ringless += 1;
                        }
                        ix.lidar_frame.get_or_insert_with(|| scan.frame_id.clone());
                        if let Some(r) = scan
                            .rings
                            .as_ref()
                            .and_then(|r| r.iter().copied().filter(|&v| v != u16::MAX).max())
                        {
                            ix.max_ring = Some(ix.max_ring.map_or(r, |m| m.max(r)));
                        }
                        if ix.column_estimates.len() < 16 {
                            if let Some(c) = scan
                                .rings
                                .as_ref()
                                .and_then(|r| normals::columns_from_azimuths(&scan.positions, r))
                            {
                                ix.column_estimates.push(c);
                            }
                        }
                        ix.sweeps.push(SweepRef {
                            index: msg.index,
                            start: stamp + lo,
                            end: stamp + hi,
                            timed,
                        });
                        used = true;
                    }
                }
                Err(e) => drop_count(&mut ix.dropped, format!("{topic}: bad PointCloud2 ({e})")),
            },
            RosMessage::Image(ros::Image { header, .. })
            | RosMessage::CompressedImage(ros::CompressedImage { header, .. })
                if cam_of_topic.contains_key(topic.as_str()) =>
            {
                let c = cam_of_topic[topic.as_str()];
                ix.image_frames[c].get_or_insert_with(|| header.frame_id.clone());
                ix.images[c].push(ImageRef {
                    index: msg.index,
                    time: secs(header.stamp),
                });
                used = true;
            }
            m if ing.trajectory_topic.as_deref() == Some(topic.as_str())
                && ing.trajectory_file.is_none() =>
            {
                used = true;
                match m {
                    RosMessage::Odometry(o) => {
                        ix.trajectory_child
                            .get_or_insert_with(|| o.child_frame_id.clone());
                        ix.trajectory.push((secs(o.header.stamp), o.pose));
                    }
                    RosMessage::PoseStamped(p) => {
                        ix.trajectory.push((secs(p.header.stamp), p.pose))
                    }
                    RosMessage::PoseWithCovarianceStamped(p) => {
                        ix.trajectory.push((secs(p.header.stamp), p.pose))
                    }
                    RosMessage::Path(p) => {
                        // A Path is republished whole; the last one is the final trajectory.
                        ix.trajectory = p
                            .poses
                            .iter()
                            .map(|q| (secs(q.header.stamp), q.pose))
                            .collect();
                    }
                    other => {
                        used = false;
                        drop_count(
                            &mut ix.dropped,
                            format!("{topic}: {} is not a trajectory type", other_type(&other)),
                        );
                    }
                }
            }
            _ => {}
        }
        if used {
            ix.topics.get_mut(&topic).expect("inserted above").used += 1;
        }
    }
    progress(Progress {
        stage: "index",
        done: n,
        total: n,
    });

    // ---- calibration ----------------------------------------------------------------------------
    let lidar_frame = ix.lidar_frame.clone().ok_or_else(|| {
        unusable(format!(
            "no usable sweeps on the lidar topic '{}' (topics: {})",
            ing.lidar_topic,
            ix.topics.keys().cloned().collect::<Vec<_>>().join(", ")
        ))
    })?;
    let t_base_lidar = match &cfg.sensor.t_base_lidar {
        Some(v) => se3_from_t_xyz_q_xyzw(v).map_err(|e| unusable(format!("T_base_lidar: {e}")))?,
        None => ix.tf_static.lookup(&ing.base_frame, &lidar_frame).ok_or_else(|| {
            unusable(format!(
                "no T_base_lidar: the rig file has no T_base_lidar_t_xyz_q_xyzw and /tf_static does not \
                 connect '{}' to the lidar frame '{lidar_frame}'",
                ing.base_frame
            ))
        })?,
    };
    let mut rig_cams = Vec::with_capacity(cams.len());
    for (i, c) in cams.iter().enumerate() {
        if ix.images[i].is_empty() {
            return Err(unusable(format!(
                "camera {}: no images on '{}'",
                c.label, c.topic
            )));
        }
        let frame = ix.image_frames[i].clone().unwrap_or_default();
        let model: CameraModel = if c.intrinsics.is_some() {
            cfg.camera_model(c)
                .map_err(|e| unusable(format!("camera {}: {e}", c.label)))?
        } else {
            let info = ix
                .infos
                .iter()
                .find(|(t, info)| match &c.camera_info_topic {
                    Some(want) => t == want,
                    None => info.header.frame_id == frame,
                })
                .map(|(_, info)| info)
                .ok_or_else(|| {
                    unusable(format!(
                        "camera {}: no intrinsics in the rig file and no CameraInfo {}",
                        c.label,
                        c.camera_info_topic
                            .as_ref()
                            .map_or(format!("with frame_id '{frame}'"), |t| format!("on '{t}'"))
                    ))
                })?;
            info.camera_model()
                .map_err(|e| unusable(format!("camera {}: CameraInfo: {e}", c.label)))?
        };
        let t_lidar_cam = match &c.t_cam_lidar {
            Some(v) => se3_from_t_xyz_q_xyzw(v)
                .map_err(|e| unusable(format!("camera {}: {e}", c.label)))?
                .inverse(),
            None => ix.tf_static.lookup(&lidar_frame, &frame).ok_or_else(|| {
                unusable(format!(
                    "camera {}: no T_cam_lidar in the rig file and /tf_static does not connect the \
                     lidar frame '{lidar_frame}' to the image frame '{frame}'",
                    c.label
                ))
            })?,
        };
        rig_cams.push(RigCamera {
            name: c.label.clone(),
            model,
            t_lidar_cam,
        });
    }
    let rig = Rig {
        base_frame: ing.base_frame.clone(),
        lidar_frame: lidar_frame.clone(),
        t_base_lidar,
        cameras: rig_cams,
    };
    rig.validate().map_err(|e| unusable(format!("rig: {e}")))?;

    // ---- trajectory: T_world_lidar ----------------------------------------------------------------
    let mut notices = Vec::new();
    let missing = ing.trajectory_file.is_none() && ix.trajectory.len() < 2;
    if missing && !ing.trajectory_from_lidar {
        notices.push(format!(
            "no trajectory in the bag ({} pose(s) on '{}'): using lidar odometry over '{}' \
             (silvr ingest --trajectory lidar says so explicitly; a SLAM trajectory is better where you have one)",
            ix.trajectory.len(),
            ing.trajectory_topic.as_deref().unwrap_or(""),
            ing.lidar_topic
        ));
    }
    let (samples, traj_frame, traj_source) = if ing.trajectory_from_lidar || missing {
        let mut sweeps = super::odometry_input::BagSweeps::open(bag, &ing.lidar_topic)?;
        let config = crate::odometry::OdometryConfig::default();
        let mut err = None;
        let run = crate::odometry::run(
            &config,
            sweeps.by_ref().map_while(|s| match s {
                Ok(s) => Some(Ok(s)),
                Err(e) => {
                    err = Some(e);
                    None
                }
            }),
            |i, _| {
                progress(Progress {
                    stage: "lidar odometry",
                    done: i as u64 + 1,
                    total: ix.sweeps.len() as u64,
                })
            },
        )
        .map_err(|e| unusable(format!("lidar odometry over '{}': {e}", ing.lidar_topic)))?;
        if let Some(e) = err {
            return Err(e.into());
        }
        let s: Vec<(f64, Se3)> = run.stamps.into_iter().zip(run.poses).collect();
        (
            s,
            lidar_frame.clone(),
            format!("lidar odometry ({})", ing.lidar_topic),
        )
    } else if let Some(f) = &ing.trajectory_file {
        let path = cfg_dir.join(f);
        // TUM, KITTI (+ times.txt), Spires slam-poses.csv or EuRoC, detected from the file.
        let t = super::poses::read_trajectory(&path).map_err(|e| IngestError::Unusable {
            file: path.display().to_string(),
            reason: e.to_string(),
        })?;
        let s: Vec<(f64, Se3)> = t
            .stamps()
            .iter()
            .copied()
            .zip(t.poses().iter().copied())
            .collect();
        let frame = ing
            .trajectory_frame
            .clone()
            .unwrap_or_else(|| ing.base_frame.clone());
        (s, frame, path.display().to_string())
    } else {
        let topic = ing.trajectory_topic.clone().unwrap_or_default();
        let frame = ing
            .trajectory_frame
            .clone()
            .or_else(|| ix.trajectory_child.clone().filter(|s| !s.is_empty()))
            .unwrap_or_else(|| ing.base_frame.clone());
        (std::mem::take(&mut ix.trajectory), frame, topic)
    };
    let t_traj_lidar = if traj_frame == lidar_frame {
        Se3::IDENTITY
    } else if traj_frame == ing.base_frame {
        t_base_lidar
    } else {
        ix.tf_static.lookup(&traj_frame, &lidar_frame).ok_or_else(|| {
            unusable(format!(
                "the trajectory poses frame '{traj_frame}', which /tf_static does not connect to the lidar \
                 frame '{lidar_frame}' (set ingest.trajectory_frame)"
            ))
        })?
    };
    let mut samples: Vec<(f64, Se3)> = samples
        .into_iter()
        .filter(|(t, p)| t.is_finite() && p.is_finite() && p.rot.length() > 0.5)
        .map(|(t, p)| (t, Se3::new(p.rot.normalize(), p.trans) * t_traj_lidar))
        .collect();
    samples.sort_by(|a, b| a.0.total_cmp(&b.0));
    samples.dedup_by(|b, a| b.0 <= a.0);
    if samples.len() < 2 {
        return Err(unusable(format!(
            "the trajectory ({traj_source}) has {} usable poses; at least 2 are needed",
            samples.len()
        )));
    }
    let (stamps, poses): (Vec<f64>, Vec<Se3>) = samples.into_iter().unzip();
    let trajectory =
        Trajectory::new(stamps, poses).map_err(|e| unusable(format!("trajectory: {e}")))?;
    let mut max_pose_gap = cfg.sensor.max_time_diff_camera_and_pose.unwrap_or(0.05);
    if traj_source.starts_with("lidar odometry") {
        // One pose per sweep: an image between two sweeps is interpolated along the constant-velocity
        // motion the odometry assumed anyway, so the gap allowed is half the sweep interval at least.
        let mut d: Vec<f64> = trajectory
            .stamps()
            .windows(2)
            .map(|w| w[1] - w[0])
            .collect();
        d.sort_by(f64::total_cmp);
        if let Some(&mid) = d.get(d.len() / 2) {
            max_pose_gap = max_pose_gap.max(0.6 * mid);
        }
    }

    // ---- clouds as they come: without per-point time, without ring ---------------------------------
    // Set when untimed clouds are timed from their azimuth: seconds per turn.
    let mut azimuth_period = None;
    if ix.untimed > 0 {
        // A cloud without per-point times stands for the sweep period around its stamp: the median
        // interval between stamps.
        let mut stamps: Vec<f64> = ix
            .sweeps
            .iter()
            .filter(|s| !s.timed)
            .map(|s| s.start)
            .collect();
        stamps.sort_by(f64::total_cmp);
        let mut d: Vec<f64> = stamps
            .windows(2)
            .map(|w| w[1] - w[0])
            .filter(|&d| d > 0.0)
            .collect();
        d.sort_by(f64::total_cmp);
        let median = d.get(d.len() / 2).copied().unwrap_or(0.1);
        match &ing.azimuth_timing {
            None => {
                for s in ix.sweeps.iter_mut().filter(|s| !s.timed) {
                    (s.start, s.end) = (s.start - 0.5 * median, s.start + 0.5 * median);
                }
                notices.push(format!(
                    "{} of {} sweeps on '{}' have no per-point time: taken as already motion-compensated \
                     to their header stamp (deskewing moves them rigidly to each image's time); each stands \
                     for {:.3} s around its stamp (the median interval); a spinning lidar's points can be \
                     timed from their azimuth instead (ingest.azimuth_timing in the rig file)",
                    ix.untimed,
                    ix.sweeps.len(),
                    ing.lidar_topic,
                    median
                ));
            }
            Some(a) => {
                let period = a.period.unwrap_or(median);
                azimuth_period = Some(period);
                for s in ix.sweeps.iter_mut().filter(|s| !s.timed) {
                    s.end = s.start + period;
                }
                notices.push(format!(
                    "{} of {} sweeps on '{}' have no per-point time: each point timed from its azimuth \
                     (ingest.azimuth_timing: turning {} from {}° at the header stamp, {:.4} s a turn{})",
                    ix.untimed,
                    ix.sweeps.len(),
                    ing.lidar_topic,
                    match a.spin {
                        super::config::Spin::Ccw => "counter-clockwise",
                        super::config::Spin::Cw => "clockwise",
                    },
                    a.start_azimuth_deg,
                    period,
                    match a.period {
                        Some(_) => ", as the rig file says",
                        // Slower than any common spinning lidar: the bag likely keeps only some sweeps.
                        None if median > 0.25 => {
                            ": the median interval between stamps, longer than common lidars turn; set \
                             ingest.azimuth_timing.period if the bag keeps only some sweeps"
                        }
                        None => ": the median interval between stamps",
                    }
                ));
            }
        }
    }
    if ix.ringless > 0 {
        notices.push(format!(
            "{} of {} sweeps on '{}' have no 'ring' field: their range image (normals, sky) is an angular \
             grid of elevation and azimuth fitted to each sweep, as for KITTI .bin and DGP sweeps",
            ix.ringless,
            ix.sweeps.len(),
            ing.lidar_topic
        ));
    }

    // ---- lidar geometry ---------------------------------------------------------------------------
    // The range image of sweeps with rings: beams from the largest ring, columns from the azimuth step.
    let ring_grid = match ix.max_ring {
        None => None,
        Some(r) => {
            let columns = match ing.lidar_columns {
                Some(c) => c as usize,
                None => {
                    let mut s = ix.column_estimates.clone();
                    if s.is_empty() {
                        return Err(unusable(
                            "cannot estimate the lidar's azimuth step (set ingest.lidar_columns)"
                                .into(),
                        ));
                    }
                    let mid = s.len() / 2;
                    *s.select_nth_unstable(mid).1
                }
            };
            Some((r as usize + 1, columns))
        }
    };

    // ---- keyframes --------------------------------------------------------------------------------
    let mut dropped = std::mem::take(&mut ix.dropped);
    for imgs in &mut ix.images {
        imgs.sort_by(|a, b| a.time.total_cmp(&b.time));
    }
    ix.sweeps.sort_by(|a, b| a.start.total_cmp(&b.start));
    let mut chosen: Vec<Pending> = Vec::new();
    let mut last: Option<Se3> = None;
    for lead in &ix.images[0] {
        let t = lead.time;
        if ing.start.is_some_and(|s| t < s) || ing.end.is_some_and(|e| t > e) {
            drop_count(&mut dropped, "image set outside ingest.start/end");
            continue;
        }
        if ing.max_keyframes.is_some_and(|m| chosen.len() >= m) {
            break;
        }
        // One image per camera, nearest in time.
        let mut set = vec![lead.clone()];
        for imgs in &ix.images[1..] {
            let j = imgs.partition_point(|r| r.time < t);
            let best = [j.wrapping_sub(1), j]
                .into_iter()
                .filter_map(|j| imgs.get(j))
                .min_by(|a, b| (a.time - t).abs().total_cmp(&(b.time - t).abs()));
            match best {
                Some(r) if (r.time - t).abs() <= ing.camera_sync => set.push(r.clone()),
                _ => break,
            }
        }
        if set.len() < cams.len() {
            drop_count(
                &mut dropped,
                "image set: a camera has no image within camera_sync",
            );
            continue;
        }
        // A pose, with a trajectory sample close by.
        let stamps = trajectory.stamps();
        let j = stamps.partition_point(|&s| s < t);
        let gap = [j.wrapping_sub(1), j]
            .into_iter()
            .filter_map(|j| stamps.get(j))
            .map(|&s| (s - t).abs())
            .fold(f64::INFINITY, f64::min);
        let Some(pose) = trajectory.at(t).filter(|_| gap <= max_pose_gap) else {
            drop_count(
                &mut dropped,
                "image set: no trajectory pose within max_time_diff_camera_and_pose",
            );
            continue;
        };
        // A sweep that covers the image time.
        let Some(sweep) = ix
            .sweeps
            .iter()
            .find(|s| s.start - 1e-3 <= t && t <= s.end + 1e-3)
        else {
            drop_count(&mut dropped, "image set: no sweep covers its time");
            continue;
        };
        if let Some(prev) = last {
            let moved = prev.distance_to(&pose);
            let turned = prev.angle_to(&pose).to_degrees();
            if moved < ing.keyframe_distance && turned < ing.keyframe_angle_deg {
                drop_count(&mut dropped, "image set: not a keyframe (moved too little)");
                continue;
            }
        }
        last = Some(pose);
        chosen.push(Pending {
            k: chosen.len(),
            time: t,
            sweep: sweep.index,
            got_images: vec![None; set.len()],
            images: set,
            got_sweep: None,
        });
    }
    if chosen.is_empty() {
        return Err(unusable(format!(
            "no keyframe: no image set has all cameras, a trajectory pose and a covering sweep (dropped: {dropped:?})"
        )));
    }

    // ---- pass 2: assemble and write ---------------------------------------------------------------
    let out = writer;
    let mut want_image: BTreeMap<u64, Vec<(usize, usize)>> = BTreeMap::new();
    let mut want_sweep: BTreeMap<u64, Vec<usize>> = BTreeMap::new();
    for (p, kf) in chosen.iter().enumerate() {
        for (c, r) in kf.images.iter().enumerate() {
            want_image.entry(r.index).or_default().push((p, c));
        }
        want_sweep.entry(kf.sweep).or_default().push(p);
    }
    let total = chosen.len() as u64;
    let mut slots: Vec<Option<Pending>> = chosen.into_iter().map(Some).collect();
    let mut state = WriteState::default();
    let reader = BagReader::open(bag)?;
    for msg in reader {
        let msg = msg?;
        let mut touched = Vec::new();
        if let Some(targets) = want_image.get(&msg.index) {
            let decoded = match msg.decode() {
                Ok(Ok(RosMessage::Image(img))) => img.to_rgb(),
                Ok(Ok(RosMessage::CompressedImage(img))) => img.to_rgb(),
                other => {
                    return Err(unusable(format!(
                        "message #{} on '{}' changed between passes: {other:?}",
                        msg.index,
                        msg.topic()
                    )))
                }
            };
            let rgb = decoded.map_err(|e| reader_decode(&file, &msg, e))?;
            for &(p, c) in targets {
                if let Some(kf) = slots[p].as_mut() {
                    kf.got_images[c] = Some(rgb.clone());
                    touched.push(p);
                }
            }
        }
        if let Some(targets) = want_sweep.get(&msg.index) {
            let scan = match msg.decode() {
                Ok(Ok(RosMessage::PointCloud2(pc))) => {
                    pc.to_scan().map_err(|e| reader_decode(&file, &msg, e))?
                }
                other => {
                    return Err(unusable(format!(
                        "message #{} on '{}' changed between passes: {other:?}",
                        msg.index,
                        msg.topic()
                    )))
                }
            };
            for &p in targets {
                if let Some(kf) = slots[p].as_mut() {
                    kf.got_sweep = Some(scan.clone());
                    touched.push(p);
                }
            }
        }
        for p in touched {
            let done = slots[p].as_ref().is_some_and(|kf| {
                kf.got_sweep.is_some() && kf.got_images.iter().all(Option::is_some)
            });
            if done {
                let kf = slots[p].take().expect("checked");
                write_keyframe(
                    &out,
                    &mut state,
                    gpu,
                    &rig,
                    &trajectory,
                    kf,
                    ring_grid,
                    ing.min_range,
                    ing.azimuth_timing.as_ref().zip(azimuth_period),
                    &file,
                )
                .await?;
                progress(Progress {
                    stage: "keyframes",
                    done: state.records.len() as u64,
                    total,
                });
            }
        }
    }
    if let Some(kf) = slots.iter().flatten().next() {
        return Err(unusable(format!(
            "keyframe {}: its messages were not found on the second pass",
            kf.k
        )));
    }

    // ---- poses, calibration, transforms, manifest ----------------------------------------------
    let WriteState {
        mut frames,
        records,
        lidar_points,
        times,
        base_poses,
        lidar_poses,
        cam_poses,
        grids,
        clamped,
        not_finite,
    } = state;
    if clamped > 0 {
        notices.push(format!(
            "{clamped} of {lidar_points} lidar points were fired beyond the trajectory's time span (the first \
             and last sweeps straddle its ends): carried by the nearest pose, not dropped"
        ));
    }
    if not_finite > 0 {
        *dropped
            .entry("lidar points: coordinates not finite".into())
            .or_insert(0) += not_finite as u64;
    }
    // The range image's size: the rings' when the clouds have them, else the first keyframe's grid.
    let (beams, columns) = ring_grid.or(grids.first().copied()).unwrap_or((0, 0));
    // Keyframes complete in bag order, which need not be time order: sort everything by keyframe.
    let mut order: Vec<usize> = (0..records.len()).collect();
    order.sort_by_key(|&i| records[i].index);
    let pick = |v: &[Se3]| order.iter().map(|&i| v[i]).collect::<Vec<_>>();
    let (base_poses, lidar_poses) = (pick(&base_poses), pick(&lidar_poses));
    let cam_poses: Vec<Vec<Se3>> = cam_poses.iter().map(|v| pick(v)).collect();
    let times: Vec<f64> = order.iter().map(|&i| times[i]).collect();
    let records: Vec<KeyframeRecord> = order.iter().map(|&i| records[i].clone()).collect();
    frames.sort_by_key(|f| f.keyframe);
    out.write_poses(
        &times,
        &base_poses,
        &lidar_poses,
        &rig,
        &cam_poses,
        &trajectory,
    )?;
    let lidar = LidarCalib {
        topic: ing.lidar_topic.clone(),
        frame: lidar_frame.clone(),
        beams,
        columns,
        range_image: if ring_grid.is_some() {
            "beams from the clouds' ring field, columns from the azimuth step"
        } else {
            "an angular grid fitted to each sweep (the clouds have no ring field); beams x columns of the first"
        },
        min_range: ing.min_range,
    };
    out.write_json("calib/lidar.json", &lidar)?;
    let n_images = frames.len();
    let transforms = products::transforms(frames, products::every_tenth_keyframe);
    out.write_json("transforms.json", &transforms)?;
    let mut summary = IngestSummary {
        path: out.target.clone(),
        bag: file.clone(),
        keyframes: records.len(),
        images: n_images,
        lidar_points,
        time_span: ix.time_span.unwrap_or((0.0, 0.0)),
        topics: ix.topics,
        dropped,
        lidar_beams: beams,
        lidar_columns: columns,
        trajectory: traj_source.clone(),
        notices,
    };
    let manifest = Manifest {
        layout_version: dataset::LAYOUT_VERSION,
        generator: INGEST_VERSION,
        source: Source {
            bag: file.clone(),
            bytes,
            trajectory: traj_source,
            trajectory_frame: traj_frame,
        },
        config: cfg,
        keyframes: &records,
        cameras: rig.cameras.iter().map(|c| c.name.as_str()).collect(),
        summary: &summary,
        encodings: encodings(),
        files: out.files(),
    };
    out.write_json("manifest.json", &manifest)?;
    summary.path = out.commit()?;
    Ok(summary)
}

fn other_type(m: &RosMessage) -> &'static str {
    match m {
        RosMessage::PointCloud2(_) => "PointCloud2",
        RosMessage::Image(_) => "Image",
        RosMessage::CompressedImage(_) => "CompressedImage",
        RosMessage::CameraInfo(_) => "CameraInfo",
        RosMessage::Tf(_) => "TFMessage",
        RosMessage::Odometry(_) => "Odometry",
        RosMessage::Path(_) => "Path",
        RosMessage::PoseStamped(_) => "PoseStamped",
        RosMessage::PoseWithCovarianceStamped(_) => "PoseWithCovarianceStamped",
    }
}

fn reader_decode(file: &str, msg: &super::bag::BagMessage, e: ros::DecodeError) -> IngestError {
    IngestError::Bag(BagError::Decode {
        file: file.to_string(),
        index: msg.index,
        topic: msg.topic().to_string(),
        log_time: msg.log_time(),
        source: Box::new(e),
    })
}

#[derive(Default)]
struct WriteState {
    frames: Vec<NsFrame>,
    records: Vec<KeyframeRecord>,
    lidar_points: usize,
    times: Vec<f64>,
    base_poses: Vec<Se3>,
    lidar_poses: Vec<Se3>,
    cam_poses: Vec<Vec<Se3>>,
    /// Range-image size of each keyframe whose cloud has no ring (an angular grid per sweep).
    grids: Vec<(usize, usize)>,
    /// Lidar points carried by the nearest pose (fired beyond the trajectory) and dropped (not finite).
    clamped: usize,
    not_finite: usize,
}

/// Per-keyframe record in the manifest (same keys as the synthetic generator's).
#[derive(Clone, Debug, Serialize)]
struct KeyframeRecord {
    index: usize,
    sweep_start: f64,
    image_time: f64,
    raw_points: usize,
    deskewed_dropped: usize,
}

#[derive(Serialize)]
struct LidarCalib {
    topic: String,
    frame: String,
    beams: usize,
    columns: usize,
    range_image: &'static str,
    min_range: f64,
}

#[derive(Serialize)]
struct Source {
    bag: String,
    bytes: u64,
    trajectory: String,
    trajectory_frame: String,
}

#[derive(Serialize)]
struct Manifest<'a> {
    layout_version: u32,
    generator: &'a str,
    source: Source,
    config: &'a RigConfig,
    keyframes: &'a [KeyframeRecord],
    cameras: Vec<&'a str>,
    summary: &'a IngestSummary,
    encodings: BTreeMap<&'static str, &'static str>,
    files: BTreeMap<String, u64>,
}

fn encodings() -> BTreeMap<&'static str, &'static str> {
    BTreeMap::from([
        ("images", "8-bit RGB PNG as decoded from the bag"),
        ("lidar_depth", "16-bit PNG, Euclidean range from the camera centre x 256 (m), 0 = no return, 65535 = sky"),
        ("lidar_normals", "8-bit RGB PNG, (n + 1) / 2 x 255, unit normal in the OpenCV camera frame facing the camera, 128 = none"),
        ("sky_mask", "8-bit PNG, 255 = sky (from lidar no-returns and the image)"),
        ("lidar/raw", "PLY, points in the sensor frame at their firing time; time_offset (s) from the header stamp"),
        ("lidar/deskewed", "PLY, points in the sensor frame at the keyframe's image time"),
        ("poses", "TUM: t tx ty tz qx qy qz qw (bag time, s), T_world_<frame>; odometry = the trajectory used"),
        ("transforms.json", "nerfstudio: c2w in OpenGL axes, cx/cy with pixel centres at +0.5"),
    ])
}

#[allow(clippy::too_many_arguments)]
async fn write_keyframe(
    out: &DatasetWriter,
    st: &mut WriteState,
    gpu: &Gpu,
    rig: &Rig,
    trajectory: &Trajectory,
    kf: Pending,
    ring_grid: Option<(usize, usize)>,
    min_range: f64,
    azimuth_timing: Option<(&super::config::AzimuthTiming, f64)>,
    file: &str,
) -> Result<(), IngestError> {
    let k = kf.k;
    let name = format!("{k:05}");
    let scan = kf.got_sweep.expect("complete");
    let stamp = secs(scan.stamp);
    // A cloud without per-point time is timed from its azimuth where the rig file says how the lidar
    // turns, else taken as motion-compensated to its stamp.
    let rel_times = scan.times.clone().unwrap_or_else(|| match azimuth_timing {
        Some((a, period)) => scan
            .positions
            .iter()
            .map(|&p| a.offset(p, period))
            .collect(),
        None => vec![0.0; scan.positions.len()],
    });
    let abs_times: Vec<f64> = rel_times.iter().map(|&r| stamp + r).collect();
    // Beam and column of each point: the cloud's rings and the rig's azimuth step, or, for a cloud
    // without rings, an angular grid fitted to this sweep.
    let (rings, column, beams, columns) = match (&scan.rings, ring_grid) {
        (Some(r), Some((beams, columns))) => {
            let column = scan
                .positions
                .iter()
                .map(|&p| normals::column_of(p, columns))
                .collect();
            (r.clone(), column, beams, columns)
        }
        _ => {
            let grid = normals::angular_grid(&scan.positions);
            st.grids.push((grid.2, grid.3));
            grid
        }
    };
    let desk = deskew::deskew(&scan.positions, &abs_times, trajectory, kf.time).map_err(|e| {
        IngestError::Unusable {
            file: file.to_string(),
            reason: format!("keyframe {k}: {e}"),
        }
    })?;
    let cloud = |positions: &[DVec3]| {
        let mut pc = PointCloud::from_positions(positions.to_vec());
        let n = positions.len();
        pc.set_scalar(
            "intensity",
            scan.intensities.clone().unwrap_or_else(|| vec![0.0; n]),
        );
        pc.set_scalar("ring", rings.iter().map(|&r| r as f32).collect());
        pc.set_scalar("column", column.iter().map(|&c| c as f32).collect());
        pc.set_scalar("time_offset", rel_times.iter().map(|&t| t as f32).collect());
        pc
    };
    let ply = |pc: &PointCloud, rel: &str| {
        write_ply_bytes(pc).map_err(|e| IngestError::Unusable {
            file: file.to_string(),
            reason: format!("{rel}: {e}"),
        })
    };
    let rel = format!("lidar/raw/{name}.ply");
    out.write(&rel, &ply(&cloud(&scan.positions), &rel)?)?;
    let rel = format!("lidar/deskewed/{name}.ply");
    out.write(&rel, &ply(&cloud(&desk.positions), &rel)?)?;

    let t_world_lidar = trajectory
        .at(kf.time)
        .expect("checked when choosing keyframes");
    let rgbs: Vec<RgbImage> = kf
        .got_images
        .into_iter()
        .map(|i| i.expect("complete"))
        .collect();
    for (c, img) in rig.cameras.iter().zip(&rgbs) {
        if (img.width, img.height) != (c.model.width, c.model.height) {
            return Err(IngestError::Unusable {
                file: file.to_string(),
                reason: format!(
                    "camera {}: image is {}x{}, the calibration says {}x{}",
                    c.name, img.width, img.height, c.model.width, c.model.height
                ),
            });
        }
    }
    let sweep = products::SweepInput {
        positions: &desk.positions,
        ring: &rings,
        column: &column,
        beams,
        columns,
        min_range,
        t_world_lidar,
    };
    let cams_rgb: Vec<(&RigCamera, &[[u8; 3]])> = rig
        .cameras
        .iter()
        .zip(&rgbs)
        .map(|(c, i)| (c, i.pixels.as_slice()))
        .collect();
    let made = products::keyframe_products(gpu, &sweep, &cams_rgb).await?;
    if st.cam_poses.is_empty() {
        st.cam_poses = vec![Vec::new(); rig.cameras.len()];
    }
    for (ci, ((cam, p), img)) in rig.cameras.iter().zip(made).zip(&rgbs).enumerate() {
        // Each camera at its own trigger time (within camera_sync of the set's).
        let t_cam = kf.images[ci].time;
        let t_world_cam = trajectory.at(t_cam).unwrap_or(t_world_lidar) * cam.t_lidar_cam;
        st.cam_poses[ci].push(t_world_cam);
        st.frames.push(products::write_camera(
            out,
            cam,
            k,
            t_cam,
            &t_world_cam,
            &img.pixels,
            &p,
        )?);
    }
    st.records.push(KeyframeRecord {
        index: k,
        sweep_start: stamp,
        image_time: kf.time,
        raw_points: scan.positions.len(),
        deskewed_dropped: desk.dropped,
    });
    st.clamped += desk.clamped;
    st.not_finite += desk.dropped;
    st.lidar_points += scan.positions.len();
    st.times.push(kf.time);
    st.lidar_poses.push(t_world_lidar);
    st.base_poses
        .push(t_world_lidar * rig.t_base_lidar.inverse());
    Ok(())
}
