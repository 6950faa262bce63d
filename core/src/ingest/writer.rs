//! Writes ROS 2 bags as MCAP: the `mcap` crate's writer for the container (zstd chunks, summary, indexes),
//! our CDR encoders ([`super::ros`]) for the payloads, and the `ros2msg` schema texts ROS 2 itself records,
//! so Foxglove, `ros2 bag` and the Python `mcap-ros2-support` decoder read what we write.
//!
//! The file is written under a temporary name and renamed by [`BagWriter::finish`]: an interrupted write
//! never leaves a bag that looks complete.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use super::bag::BagError;
use super::ros::Time;

/// Separator between a schema's own definition and each of its dependencies (rosbag2's layout).
const SEP: &str =
    "================================================================================\nMSG: ";

const HEADER: &str = "std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n";
const TIME: &str = "builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n";
const VECTOR3: &str = "geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n";
const POINT: &str = "geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z\n";
const QUATERNION: &str =
    "geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n";

/// The `ros2msg` schema text of a message type we write: its definition, then every type it uses.
pub fn schema_text(type_name: &str) -> Option<String> {
    let (top, deps): (&str, Vec<&str>) = match type_name {
        "sensor_msgs/msg/PointCloud2" => (
            "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\n\
             bool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n",
            vec![
                HEADER,
                TIME,
                "sensor_msgs/PointField\nuint8 INT8 = 1\nuint8 UINT8 = 2\nuint8 INT16 = 3\n\
                 uint8 UINT16 = 4\nuint8 INT32 = 5\nuint8 UINT32 = 6\nuint8 FLOAT32 = 7\n\
                 uint8 FLOAT64 = 8\nstring name\nuint32 offset\nuint8 datatype\nuint32 count\n",
            ],
        ),
        "sensor_msgs/msg/Image" => (
            "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n\
             uint8 is_bigendian\nuint32 step\nuint8[] data\n",
            vec![HEADER, TIME],
        ),
        "sensor_msgs/msg/CompressedImage" => (
            "std_msgs/Header header\nstring format\nuint8[] data\n",
            vec![HEADER, TIME],
        ),
        "sensor_msgs/msg/CameraInfo" => (
            "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n\
             float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\n\
             uint32 binning_y\nRegionOfInterest roi\n",
            vec![
                HEADER,
                TIME,
                "sensor_msgs/RegionOfInterest\nuint32 x_offset\nuint32 y_offset\nuint32 height\n\
                 uint32 width\nbool do_rectify\n",
            ],
        ),
        "tf2_msgs/msg/TFMessage" => (
            "geometry_msgs/TransformStamped[] transforms\n",
            vec![
                "geometry_msgs/TransformStamped\nstd_msgs/Header header\nstring child_frame_id\n\
                 Transform transform\n",
                HEADER,
                TIME,
                "geometry_msgs/Transform\nVector3 translation\nQuaternion rotation\n",
                VECTOR3,
                QUATERNION,
            ],
        ),
        "nav_msgs/msg/Odometry" => (
            "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n\
             geometry_msgs/TwistWithCovariance twist\n",
            vec![
                HEADER,
                TIME,
                "geometry_msgs/PoseWithCovariance\nPose pose\nfloat64[36] covariance\n",
                "geometry_msgs/Pose\nPoint position\nQuaternion orientation\n",
                POINT,
                QUATERNION,
                "geometry_msgs/TwistWithCovariance\nTwist twist\nfloat64[36] covariance\n",
                "geometry_msgs/Twist\nVector3 linear\nVector3 angular\n",
                VECTOR3,
            ],
        ),
        _ => return None,
    };
    let mut text = top.to_string();
    for d in deps {
        text.push_str(SEP);
        text.push_str(d);
    }
    Some(text)
}

/// A ROS 2 time from seconds (nanoseconds rounded to nearest).
pub fn ros_time(seconds: f64) -> Time {
    let ns = (seconds * 1e9).round() as i64;
    Time {
        sec: ns.div_euclid(1_000_000_000) as i32,
        nanosec: ns.rem_euclid(1_000_000_000) as u32,
    }
}

/// Streams messages into a new MCAP file (ROS 2 profile, zstd chunks).
pub struct BagWriter {
    file: String,
    target: PathBuf,
    partial: PathBuf,
    inner: Option<mcap::Writer<BufWriter<File>>>,
    channels: BTreeMap<String, (u16, String)>,
    sequence: u32,
}

impl BagWriter {
    /// Creates `path` (replacing it only when `finish` succeeds).
    pub fn create(path: &Path) -> Result<Self, BagError> {
        let file = path.display().to_string();
        let name = path
            .file_name()
            .map_or_else(|| "bag.mcap".into(), |n| n.to_string_lossy().into_owned());
        let partial = path.with_file_name(format!(".{name}.partial-{}", std::process::id()));
        let f = File::create(&partial).map_err(|source| BagError::Io {
            file: partial.display().to_string(),
            source,
        })?;
        let options = mcap::WriteOptions::new()
            .profile("ros2")
            .library(concat!("silvr-studio ", env!("CARGO_PKG_VERSION")))
            .compression(Some(mcap::Compression::Zstd));
        let inner = options
            .create(BufWriter::new(f))
            .map_err(|source| container(&file, source))?;
        Ok(Self {
            file,
            target: path.to_path_buf(),
            partial,
            inner: Some(inner),
            channels: BTreeMap::new(),
            sequence: 0,
        })
    }

    /// Writes one CDR payload of type `type_name` on `topic` (the channel and its schema are added on first
    /// use; a topic keeps one type). `time` is both the log and the publish time.
    pub fn write(
        &mut self,
        topic: &str,
        type_name: &str,
        time: Time,
        payload: &[u8],
    ) -> Result<(), BagError> {
        let file = self.file.clone();
        let w = self.inner.as_mut().ok_or_else(|| BagError::Invalid {
            file: file.clone(),
            reason: "the bag was already finished".into(),
        })?;
        let channel = match self.channels.get(topic) {
            Some((id, ty)) if ty == type_name => *id,
            Some((_, ty)) => {
                return Err(BagError::Invalid {
                    file,
                    reason: format!("topic {topic} already carries {ty}, not {type_name}"),
                })
            }
            None => {
                let text = schema_text(type_name).ok_or_else(|| BagError::Invalid {
                    file: file.clone(),
                    reason: format!("no schema text for {type_name}"),
                })?;
                let schema = w
                    .add_schema(type_name, "ros2msg", text.as_bytes())
                    .map_err(|e| container(&file, e))?;
                let id = w
                    .add_channel(schema, topic, "cdr", &BTreeMap::new())
                    .map_err(|e| container(&file, e))?;
                self.channels
                    .insert(topic.to_string(), (id, type_name.to_string()));
                id
            }
        };
        let ns = u64::try_from(time.nanos()).map_err(|_| BagError::Invalid {
            file: file.clone(),
            reason: format!("negative time {time:?} on {topic}"),
        })?;
        self.sequence = self.sequence.wrapping_add(1);
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: self.sequence,
            log_time: ns,
            publish_time: ns,
        };
        w.write_to_known_channel(&header, payload)
            .map_err(|e| container(&file, e))
    }

    /// Writes the summary and moves the file to its name.
    pub fn finish(mut self) -> Result<PathBuf, BagError> {
        let file = self.file.clone();
        if let Some(mut w) = self.inner.take() {
            w.finish().map_err(|e| container(&file, e))?;
            let mut buf = w.into_inner();
            std::io::Write::flush(&mut buf).map_err(|source| BagError::Io {
                file: file.clone(),
                source,
            })?;
        }
        std::fs::rename(&self.partial, &self.target).map_err(|source| BagError::Io {
            file: file.clone(),
            source,
        })?;
        Ok(self.target.clone())
    }
}

impl Drop for BagWriter {
    fn drop(&mut self) {
        // Not finished: remove the partial file (the writer's own drop may still flush into it first).
        if let Some(w) = self.inner.take() {
            drop(w);
            let _ = std::fs::remove_file(&self.partial);
        }
    }
}

fn container(file: &str, source: mcap::McapError) -> BagError {
    BagError::Write {
        file: file.to_string(),
        source,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Se3;
    use crate::ingest::bag::BagReader;
    use crate::ingest::ros::{Header, RosMessage, TfMessage, TransformStamped};
    use glam::{DQuat, DVec3};

    #[test]
    fn ros_time_rounds_and_splits() {
        assert_eq!(
            ros_time(1.5),
            Time {
                sec: 1,
                nanosec: 500_000_000
            }
        );
        assert_eq!(
            ros_time(1_700_000_000.000_000_001),
            Time {
                sec: 1_700_000_000,
                nanosec: 0
            }
        );
        assert_eq!(ros_time(2.000_000_000_4), Time { sec: 2, nanosec: 0 });
        assert_eq!(
            ros_time(-0.25),
            Time {
                sec: -1,
                nanosec: 750_000_000
            }
        );
    }

    #[test]
    fn every_schema_lists_its_dependencies() {
        for ty in [
            "sensor_msgs/msg/PointCloud2",
            "sensor_msgs/msg/Image",
            "sensor_msgs/msg/CompressedImage",
            "sensor_msgs/msg/CameraInfo",
            "tf2_msgs/msg/TFMessage",
            "nav_msgs/msg/Odometry",
        ] {
            let text = schema_text(ty).unwrap();
            // Every non-primitive field type used must be defined after a separator.
            for line in text.lines() {
                let Some(field_ty) = line.split_whitespace().next() else {
                    continue;
                };
                let base = field_ty.trim_end_matches("[]");
                let base = base.split('[').next().unwrap();
                let primitive = matches!(
                    base,
                    "bool" | "uint8" | "int32" | "uint32" | "float64" | "string" | "MSG:"
                ) || base.starts_with("=====");
                if primitive {
                    continue;
                }
                let short = base.rsplit('/').next().unwrap();
                assert!(
                    text.lines()
                        .any(|l| l.starts_with("MSG: ") && l.ends_with(&format!("/{short}"))),
                    "{ty}: {base} is used but not defined"
                );
            }
        }
        assert!(schema_text("std_msgs/msg/String").is_none());
    }

    #[test]
    fn written_bag_reads_back_and_partial_files_never_remain() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.mcap");
        let tf = TfMessage {
            transforms: vec![TransformStamped {
                header: Header {
                    stamp: ros_time(1.0),
                    frame_id: "base_link".into(),
                },
                child_frame_id: "lidar".into(),
                transform: Se3::new(DQuat::from_rotation_z(0.5), DVec3::new(0.0, 0.0, 0.124)),
            }],
        };
        let mut w = BagWriter::create(&path).unwrap();
        w.write("/tf_static", TfMessage::MSG, ros_time(1.0), &tf.encode())
            .unwrap();
        // A topic keeps its type.
        assert!(w
            .write("/tf_static", "nav_msgs/msg/Odometry", ros_time(1.0), &[])
            .is_err());
        assert!(!path.exists(), "the bag only appears when finished");
        w.finish().unwrap();
        let msgs: Vec<_> = BagReader::open(&path)
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(msgs.len(), 1);
        assert_eq!(msgs[0].log_time(), 1_000_000_000);
        match msgs[0].decode().unwrap().unwrap() {
            RosMessage::Tf(back) => assert_eq!(back, tf),
            other => panic!("{other:?}"),
        }
        // Dropped unfinished: nothing is left behind.
        let w = BagWriter::create(&dir.path().join("u.mcap")).unwrap();
        drop(w);
        let left: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(left, vec![std::ffi::OsString::from("t.mcap")], "{left:?}");
    }

    /// The messages of the MCAP fuzz target's seeds: a static transform and an odometry message.
    fn seed_messages() -> Vec<(&'static str, &'static str, Vec<u8>)> {
        use crate::ingest::ros::Odometry;
        let header = |t: f64, frame: &str| Header {
            stamp: ros_time(t),
            frame_id: frame.into(),
        };
        let tf = TfMessage {
            transforms: vec![TransformStamped {
                header: header(1.0, "base_link"),
                child_frame_id: "lidar".into(),
                transform: Se3::new(DQuat::from_rotation_z(0.5), DVec3::new(0.0, 0.0, 0.124)),
            }],
        };
        let odo = Odometry {
            header: header(1.5, "odom"),
            child_frame_id: "base_link".into(),
            pose: Se3::new(DQuat::IDENTITY, DVec3::new(1.0, 2.0, 3.0)),
            pose_covariance: [0.0; 36],
            linear: DVec3::X,
            angular: DVec3::Z,
            twist_covariance: [0.0; 36],
        };
        vec![
            ("/tf_static", TfMessage::MSG, tf.encode()),
            ("/odom", Odometry::MSG, odo.encode()),
        ]
    }

    fn seed_dir() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/seeds/mcap")
    }

    /// Writes the MCAP fuzz target's seeds: `zstd.mcap` by [`BagWriter`] (zstd chunks, summary, indexes)
    /// and `plain.mcap` by the `mcap` crate without chunks or compression (records the fuzzer can
    /// mutate directly). Regenerate with
    /// `cargo test -p silvr-core --lib write_mcap_fuzz_seeds -- --ignored`.
    #[test]
    #[ignore]
    fn write_mcap_fuzz_seeds() {
        std::fs::create_dir_all(seed_dir()).unwrap();
        let mut w = BagWriter::create(&seed_dir().join("zstd.mcap")).unwrap();
        for (k, (topic, ty, payload)) in seed_messages().iter().enumerate() {
            w.write(topic, ty, ros_time(1.0 + k as f64), payload)
                .unwrap();
        }
        w.finish().unwrap();
        let mut plain = mcap::WriteOptions::new()
            .profile("ros2")
            .use_chunks(false)
            .compression(None)
            .create(std::io::Cursor::new(Vec::new()))
            .unwrap();
        for (k, (topic, ty, payload)) in seed_messages().iter().enumerate() {
            let text = schema_text(ty).unwrap();
            let schema = plain.add_schema(ty, "ros2msg", text.as_bytes()).unwrap();
            let channel = plain
                .add_channel(schema, topic, "cdr", &BTreeMap::new())
                .unwrap();
            let t = 1_000_000_000 * (k as u64 + 1);
            let header = mcap::records::MessageHeader {
                channel_id: channel,
                sequence: k as u32,
                log_time: t,
                publish_time: t,
            };
            plain.write_to_known_channel(&header, payload).unwrap();
        }
        plain.finish().unwrap();
        std::fs::write(
            seed_dir().join("plain.mcap"),
            plain.into_inner().into_inner(),
        )
        .unwrap();
    }

    /// The seeds are small, read as bags, and hold the messages they were written with.
    #[test]
    fn the_mcap_fuzz_seeds_are_current_bags() {
        for name in ["zstd.mcap", "plain.mcap"] {
            let bytes = std::fs::read(seed_dir().join(name)).unwrap();
            assert!(bytes.len() < 8 << 10, "{name}: {} bytes", bytes.len());
            let n = bytes.len() as u64;
            let msgs: Vec<_> = BagReader::from_reader(name, std::io::Cursor::new(bytes), n)
                .collect::<Result<_, _>>()
                .unwrap();
            let want = seed_messages();
            assert_eq!(msgs.len(), want.len(), "{name}");
            for (m, (topic, ty, payload)) in msgs.iter().zip(&want) {
                assert_eq!(
                    (m.topic(), m.schema_name(), m.data()),
                    (*topic, *ty, &payload[..])
                );
                assert!(matches!(m.decode(), Ok(Ok(_))), "{name}: {topic}");
            }
        }
    }
}
