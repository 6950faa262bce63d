//! The lidar sweeps of a recording in time order, for lidar odometry (`silvr odometry INPUT`): a ROS 2
//! bag's PointCloud2 messages on one topic (with per-point times when the driver publishes them; MCAP,
//! ROS 1 or rosbag2), or a KITTI odometry sequence's `velodyne/` or raw drive's `velodyne_points/` (no
//! point times, with the ground truth or OXTS in the lidar frame when there is one). Bag sweeps that cannot be used (a bad cloud, no points, a time not after
//! the previous one) are counted by reason, not fatal.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::bag::{summarize, BagError, BagReader};
use super::kitti_import::{KittiImportError, KittiLidar};
use super::ros::RosMessage;
use crate::geometry::Se3;
use crate::odometry::{DeskewMode, Sweep};

#[derive(Debug, thiserror::Error)]
pub enum OdometryInputError {
    #[error(transparent)]
    Bag(#[from] BagError),
    #[error(transparent)]
    Kitti(#[from] KittiImportError),
    #[error("{file}: {reason}")]
    Invalid { file: String, reason: String },
}

/// A recording opened for odometry.
pub struct OdometryInput {
    /// `kitti` or `bag`.
    pub kind: &'static str,
    /// The lidar topic read (bags).
    pub topic: Option<String>,
    /// How its sweeps should be deskewed unless the user says otherwise: KITTI's are compensated.
    pub default_deskew: DeskewMode,
    /// Ground truth `T_lidar0_lidar` per sweep, by sweep index, and where it came from (KITTI).
    pub ground_truth: Option<(PathBuf, Vec<Se3>)>,
    pub sweeps: Box<dyn Iterator<Item = Result<Sweep, OdometryInputError>>>,
    /// Bag sweeps left out, by reason (filled as `sweeps` is consumed).
    pub dropped: Dropped,
}

/// Opens `input`: a KITTI odometry sequence folder (it has `velodyne/`), a KITTI raw drive (it has
/// `velodyne_points/`) or a bag (MCAP, ROS 1 `.bag`, rosbag2 folder), whose
/// lidar topic is `topic` or, when `None`, its only PointCloud2 topic.
pub fn open(input: &Path, topic: Option<&str>) -> Result<OdometryInput, OdometryInputError> {
    let name = input.display().to_string();
    let dropped = Dropped::default();
    // A KITTI sequence or raw drive; any other folder is taken as a rosbag2 bag (metadata.yaml + .db3).
    if input.join("velodyne").is_dir() || input.join("velodyne_points").is_dir() {
        let seq = KittiLidar::open(input)?;
        let ground_truth = seq.ground_truth.clone();
        let n = seq.frames.len();
        let sweeps = (0..n).map(move |k| seq.sweep(k).map_err(Into::into));
        return Ok(OdometryInput {
            kind: "kitti",
            topic: None,
            default_deskew: DeskewMode::Off,
            ground_truth,
            sweeps: Box::new(sweeps),
            dropped,
        });
    }
    let topic = match topic {
        Some(t) => t.to_string(),
        None => {
            let topics = lidar_topics(input)?;
            match topics.as_slice() {
                [(t, _)] => t.clone(),
                [] => {
                    return Err(OdometryInputError::Invalid {
                        file: name,
                        reason: "no sensor_msgs/msg/PointCloud2 topic".into(),
                    })
                }
                many => {
                    return Err(OdometryInputError::Invalid {
                        file: name,
                        reason: format!(
                            "several PointCloud2 topics; choose one with --lidar-topic ({})",
                            many.iter()
                                .map(|(t, n)| format!("{t}: {n} messages"))
                                .collect::<Vec<_>>()
                                .join(", ")
                        ),
                    })
                }
            }
        }
    };
    let bag = BagSweeps::open(input, &topic)?;
    let dropped = bag.dropped.clone();
    Ok(OdometryInput {
        kind: "bag",
        topic: Some(topic),
        default_deskew: DeskewMode::Auto,
        ground_truth: None,
        sweeps: Box::new(bag.map(|r| r.map_err(Into::into))),
        dropped,
    })
}

const POINTCLOUD2: &str = "sensor_msgs/msg/PointCloud2";

/// The bag's PointCloud2 topics with their message counts.
pub fn lidar_topics(bag: &Path) -> Result<Vec<(String, u64)>, BagError> {
    let s = summarize(bag)?;
    Ok(s.topics
        .into_iter()
        .filter(|(_, t)| t.schema_name == POINTCLOUD2)
        .map(|(name, t)| (name, t.messages))
        .collect())
}

/// Streams the sweeps of `topic`; unusable ones land in [`BagSweeps::dropped`].
pub struct BagSweeps {
    reader: BagReader,
    topic: String,
    last_stamp: f64,
    /// Sweeps left out, by reason; shared, so a caller that hands the iterator on can still read it.
    pub dropped: Dropped,
}

/// Counts of sweeps left out, by reason.
pub type Dropped = std::rc::Rc<std::cell::RefCell<BTreeMap<String, u64>>>;

impl BagSweeps {
    pub fn open(bag: &Path, topic: &str) -> Result<Self, BagError> {
        Ok(Self {
            reader: BagReader::open(bag)?,
            topic: topic.to_string(),
            last_stamp: f64::NEG_INFINITY,
            dropped: Dropped::default(),
        })
    }

    fn drop(&mut self, why: String) {
        *self.dropped.borrow_mut().entry(why).or_default() += 1;
    }
}

impl Iterator for BagSweeps {
    type Item = Result<Sweep, BagError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            let msg = match self.reader.next()? {
                Ok(m) => m,
                Err(e) => return Some(Err(e)),
            };
            if msg.topic() != self.topic {
                continue;
            }
            let scan = match msg.decode() {
                Ok(Ok(RosMessage::PointCloud2(pc))) => pc.to_scan(),
                Ok(Ok(_)) | Ok(Err(_)) => {
                    self.drop(format!("not a PointCloud2 ({})", msg.schema_name()));
                    continue;
                }
                Err(e) => Err(e),
            };
            let scan = match scan {
                Ok(s) => s,
                Err(e) => {
                    self.drop(format!("bad PointCloud2 ({e})"));
                    continue;
                }
            };
            if scan.positions.is_empty() {
                self.drop("no points".into());
                continue;
            }
            let stamp = scan.stamp.sec as f64 + scan.stamp.nanosec as f64 * 1e-9;
            let times = scan
                .times
                .map(|t| t.into_iter().map(|dt| stamp + dt).collect::<Vec<f64>>());
            let sweep = Sweep {
                stamp,
                points: scan.positions,
                times,
            };
            let t_ref = sweep.reference_time();
            if t_ref.partial_cmp(&self.last_stamp) != Some(std::cmp::Ordering::Greater) {
                self.drop("not after the previous sweep".into());
                continue;
            }
            self.last_stamp = t_ref;
            return Some(Ok(sweep));
        }
    }
}
