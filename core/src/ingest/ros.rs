//! Hand-written decoders (and encoders, for round trips and our own bags) of the ROS 2 messages the ingest
//! needs, over the CDR cursor in [`super::cdr`].
//!
//! Why hand-written: the set is small and stable (common_interfaces), a generic `.msg` interpreter would
//! copy every `uint8[]`, and the interesting work — turning a driver's PointCloud2 field set into points
//! with per-point times, or an Image encoding into RGB — is type-specific anyway. Every decode error names
//! the message type and what is wrong.

use glam::{DQuat, DVec3};
use thiserror::Error;

use super::cdr::{CdrError, CdrReader, CdrWriter, Endian};
use crate::camera::{CameraModel, Distortion};
use crate::geometry::Se3;
use crate::pointcloud::PointCloud;

/// A message that could not be decoded: the ROS type and the reason.
#[derive(Clone, Debug, PartialEq, Error)]
pub enum DecodeError {
    #[error("{msg_type}: {source}")]
    Cdr {
        msg_type: &'static str,
        #[source]
        source: CdrError,
    },
    #[error("{msg_type}: {reason}")]
    Invalid {
        msg_type: &'static str,
        reason: String,
    },
    /// A ROS 1 message that could not be rewritten as CDR from its bag's message definition.
    #[error("ROS 1 message: {0}")]
    Ros1(String),
}

fn invalid(msg_type: &'static str, reason: impl Into<String>) -> DecodeError {
    DecodeError::Invalid {
        msg_type,
        reason: reason.into(),
    }
}

/// Runs a decode body against a fresh reader and tags CDR errors with the message type.
fn decode_with<'a, T>(
    msg_type: &'static str,
    payload: &'a [u8],
    body: impl FnOnce(&mut CdrReader<'a>) -> Result<T, CdrError>,
) -> Result<T, DecodeError> {
    let wrap = |source| DecodeError::Cdr { msg_type, source };
    let mut r = CdrReader::new(payload).map_err(wrap)?;
    body(&mut r).map_err(wrap)
}

// ---------------------------------------------------------------------------------------------------
// builtin_interfaces / std_msgs / geometry_msgs
// ---------------------------------------------------------------------------------------------------

/// builtin_interfaces/Time.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    pub const MSG: &'static str = "builtin_interfaces/msg/Time";

    pub fn read(r: &mut CdrReader) -> Result<Self, CdrError> {
        Ok(Self {
            sec: r.i32()?,
            nanosec: r.u32()?,
        })
    }

    pub fn write(&self, w: &mut CdrWriter) {
        w.i32(self.sec).u32(self.nanosec);
    }

    /// Seconds as f64 (sub-microsecond precision at today's UNIX times).
    pub fn seconds(&self) -> f64 {
        self.sec as f64 + self.nanosec as f64 * 1e-9
    }

    /// Exact nanoseconds.
    pub fn nanos(&self) -> i64 {
        self.sec as i64 * 1_000_000_000 + self.nanosec as i64
    }

    pub fn decode(payload: &[u8]) -> Result<Self, DecodeError> {
        decode_with(Self::MSG, payload, Self::read)
    }

    /// Little endian (CDR_LE), as ROS 2 writes.
    pub fn encode(&self) -> Vec<u8> {
        self.encode_with(Endian::Little)
    }

    pub fn encode_with(&self, endian: Endian) -> Vec<u8> {
        let mut w = CdrWriter::with_endian(endian);
        self.write(&mut w);
        w.finish()
    }
}

/// std_msgs/Header.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

impl Header {
    pub const MSG: &'static str = "std_msgs/msg/Header";

    pub fn read(r: &mut CdrReader) -> Result<Self, CdrError> {
        Ok(Self {
            stamp: Time::read(r)?,
            frame_id: r.string()?.to_string(),
        })
    }

    pub fn write(&self, w: &mut CdrWriter) {
        self.stamp.write(w);
        w.string(&self.frame_id);
    }

    pub fn decode(payload: &[u8]) -> Result<Self, DecodeError> {
        decode_with(Self::MSG, payload, Self::read)
    }

    /// Little endian (CDR_LE), as ROS 2 writes.
    pub fn encode(&self) -> Vec<u8> {
        self.encode_with(Endian::Little)
    }

    pub fn encode_with(&self, endian: Endian) -> Vec<u8> {
        let mut w = CdrWriter::with_endian(endian);
        self.write(&mut w);
        w.finish()
    }
}

fn read_vec3(r: &mut CdrReader) -> Result<DVec3, CdrError> {
    Ok(DVec3::new(r.f64()?, r.f64()?, r.f64()?))
}

fn write_vec3(w: &mut CdrWriter, v: DVec3) {
    w.f64(v.x).f64(v.y).f64(v.z);
}

/// geometry_msgs/Quaternion, kept as written (not normalised) so callers can check it.
fn read_quat(r: &mut CdrReader) -> Result<DQuat, CdrError> {
    Ok(DQuat::from_xyzw(r.f64()?, r.f64()?, r.f64()?, r.f64()?))
}

fn write_quat(w: &mut CdrWriter, q: DQuat) {
    w.f64(q.x).f64(q.y).f64(q.z).f64(q.w);
}

/// geometry_msgs/Pose or Transform (same layout: Vector3/Point then Quaternion) as an [`Se3`] whose
/// quaternion is exactly as stored.
fn read_pose(r: &mut CdrReader) -> Result<Se3, CdrError> {
    let trans = read_vec3(r)?;
    let rot = read_quat(r)?;
    Ok(Se3 { rot, trans })
}

fn write_pose(w: &mut CdrWriter, p: &Se3) {
    write_vec3(w, p.trans);
    write_quat(w, p.rot);
}

/// geometry_msgs/PoseStamped.
#[derive(Clone, Debug, PartialEq)]
pub struct PoseStamped {
    pub header: Header,
    /// `T_frame_body`: the pose of the body in `header.frame_id`.
    pub pose: Se3,
}

impl PoseStamped {
    pub const MSG: &'static str = "geometry_msgs/msg/PoseStamped";

    fn read(r: &mut CdrReader) -> Result<Self, CdrError> {
        Ok(Self {
            header: Header::read(r)?,
            pose: read_pose(r)?,
        })
    }

    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        write_pose(w, &self.pose);
    }

    pub fn decode(payload: &[u8]) -> Result<Self, DecodeError> {
        decode_with(Self::MSG, payload, Self::read)
    }

    /// Little endian (CDR_LE), as ROS 2 writes.
    pub fn encode(&self) -> Vec<u8> {
        self.encode_with(Endian::Little)
    }

    pub fn encode_with(&self, endian: Endian) -> Vec<u8> {
        let mut w = CdrWriter::with_endian(endian);
        self.write(&mut w);
        w.finish()
    }
}

/// geometry_msgs/PoseWithCovarianceStamped (e.g. `/amcl_pose`).
#[derive(Clone, Debug, PartialEq)]
pub struct PoseWithCovarianceStamped {
    pub header: Header,
    pub pose: Se3,
    /// Row-major 6×6 over (x, y, z, rot x, rot y, rot z).
    pub covariance: [f64; 36],
}

impl PoseWithCovarianceStamped {
    pub const MSG: &'static str = "geometry_msgs/msg/PoseWithCovarianceStamped";

    pub fn decode(payload: &[u8]) -> Result<Self, DecodeError> {
        decode_with(Self::MSG, payload, |r| {
            Ok(Self {
                header: Header::read(r)?,
                pose: read_pose(r)?,
                covariance: r.f64_array()?,
            })
        })
    }

    /// Little endian (CDR_LE), as ROS 2 writes.
    pub fn encode(&self) -> Vec<u8> {
        self.encode_with(Endian::Little)
    }

    pub fn encode_with(&self, endian: Endian) -> Vec<u8> {
        let mut w = CdrWriter::with_endian(endian);
        self.header.write(&mut w);
        write_pose(&mut w, &self.pose);
        w.f64_array(&self.covariance);
        w.finish()
    }
}

/// geometry_msgs/TransformStamped: `transform` maps points of `child_frame_id` into `header.frame_id`
/// (`T_parent_child`).
#[derive(Clone, Debug, PartialEq)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Se3,
}

/// tf2_msgs/TFMessage (`/tf` and `/tf_static`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TfMessage {
    pub transforms: Vec<TransformStamped>,
}

impl TfMessage {
    pub const MSG: &'static str = "tf2_msgs/msg/TFMessage";

    pub fn decode(payload: &[u8]) -> Result<Self, DecodeError> {
        decode_with(Self::MSG, payload, |r| {
            // Each TransformStamped is at least 4+4+4+4+7*8 bytes.
            let n = r.seq_len(72, "transforms")?;
            let mut transforms = Vec::with_capacity(n);
            for _ in 0..n {
                transforms.push(TransformStamped {
                    header: Header::read(r)?,
                    child_frame_id: r.string()?.to_string(),
                    transform: read_pose(r)?,
                });
            }
            Ok(Self { transforms })
        })
    }

    /// Little endian (CDR_LE), as ROS 2 writes.
    pub fn encode(&self) -> Vec<u8> {
        self.encode_with(Endian::Little)
    }

    pub fn encode_with(&self, endian: Endian) -> Vec<u8> {
        let mut w = CdrWriter::with_endian(endian);
        w.seq_len(self.transforms.len());
        for t in &self.transforms {
            t.header.write(&mut w);
            w.string(&t.child_frame_id);
            write_pose(&mut w, &t.transform);
        }
        w.finish()
    }
}

/// nav_msgs/Odometry.
#[derive(Clone, Debug, PartialEq)]
pub struct Odometry {
    pub header: Header,
    pub child_frame_id: String,
    /// `T_frame_child`.
    pub pose: Se3,
    pub pose_covariance: [f64; 36],
    /// Twist in `child_frame_id`.
    pub linear: DVec3,
    pub angular: DVec3,
    pub twist_covariance: [f64; 36],
}

impl Odometry {
    pub const MSG: &'static str = "nav_msgs/msg/Odometry";

    pub fn decode(payload: &[u8]) -> Result<Self, DecodeError> {
        decode_with(Self::MSG, payload, |r| {
            Ok(Self {
                header: Header::read(r)?,
                child_frame_id: r.string()?.to_string(),
                pose: read_pose(r)?,
                pose_covariance: r.f64_array()?,
                linear: read_vec3(r)?,
                angular: read_vec3(r)?,
                twist_covariance: r.f64_array()?,
            })
        })
    }

    /// Little endian (CDR_LE), as ROS 2 writes.
    pub fn encode(&self) -> Vec<u8> {
        self.encode_with(Endian::Little)
    }

    pub fn encode_with(&self, endian: Endian) -> Vec<u8> {
        let mut w = CdrWriter::with_endian(endian);
        self.header.write(&mut w);
        w.string(&self.child_frame_id);
        write_pose(&mut w, &self.pose);
        w.f64_array(&self.pose_covariance);
        write_vec3(&mut w, self.linear);
        write_vec3(&mut w, self.angular);
        w.f64_array(&self.twist_covariance);
        w.finish()
    }
}

/// nav_msgs/Path.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Path {
    pub header: Header,
    pub poses: Vec<PoseStamped>,
}

impl Path {
    pub const MSG: &'static str = "nav_msgs/msg/Path";

    pub fn decode(payload: &[u8]) -> Result<Self, DecodeError> {
        decode_with(Self::MSG, payload, |r| {
            let header = Header::read(r)?;
            // Header (>= 12 bytes) + Pose (56).
            let n = r.seq_len(68, "poses")?;
            let mut poses = Vec::with_capacity(n);
            for _ in 0..n {
                poses.push(PoseStamped::read(r)?);
            }
            Ok(Self { header, poses })
        })
    }

    /// Little endian (CDR_LE), as ROS 2 writes.
    pub fn encode(&self) -> Vec<u8> {
        self.encode_with(Endian::Little)
    }

    pub fn encode_with(&self, endian: Endian) -> Vec<u8> {
        let mut w = CdrWriter::with_endian(endian);
        self.header.write(&mut w);
        w.seq_len(self.poses.len());
        for p in &self.poses {
            p.write(&mut w);
        }
        w.finish()
    }
}

// ---------------------------------------------------------------------------------------------------
// sensor_msgs/PointCloud2
// ---------------------------------------------------------------------------------------------------

/// sensor_msgs/PointField.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PointField {
    pub name: String,
    pub offset: u32,
    /// 1 INT8, 2 UINT8, 3 INT16, 4 UINT16, 5 INT32, 6 UINT32, 7 FLOAT32, 8 FLOAT64.
    pub datatype: u8,
    pub count: u32,
}

impl PointField {
    pub const INT8: u8 = 1;
    pub const UINT8: u8 = 2;
    pub const INT16: u8 = 3;
    pub const UINT16: u8 = 4;
    pub const INT32: u8 = 5;
    pub const UINT32: u8 = 6;
    pub const FLOAT32: u8 = 7;
    pub const FLOAT64: u8 = 8;

    pub fn new(name: &str, offset: u32, datatype: u8) -> Self {
        Self {
            name: name.to_string(),
            offset,
            datatype,
            count: 1,
        }
    }

    /// Bytes of one element; `None` for an unknown datatype.
    pub fn size(&self) -> Option<usize> {
        match self.datatype {
            1 | 2 => Some(1),
            3 | 4 => Some(2),
            5..=7 => Some(4),
            8 => Some(8),
            _ => None,
        }
    }
}

/// sensor_msgs/PointCloud2 with `data` borrowed from the payload.
#[derive(Clone, Debug, PartialEq)]
pub struct PointCloud2<'a> {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub fields: Vec<PointField>,
    pub is_bigendian: bool,
    pub point_step: u32,
    pub row_step: u32,
    pub data: &'a [u8],
    pub is_dense: bool,
}

/// How a cloud stamps its points, from the time field's name, datatype and magnitude (§2.4 of the
/// formats notes): Hesai/Livox write absolute times, Ouster and Velodyne offsets from the scan stamp.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PointTimeKind {
    /// No recognised time field.
    None,
    /// f64 absolute UNIX seconds (Hesai `timestamp`).
    AbsoluteSeconds,
    /// f64 absolute UNIX nanoseconds (Livox `timestamp`).
    AbsoluteNanos,
    /// Integer nanoseconds since the header stamp (Ouster `t`, Livox `offset_time`).
    RelativeNanos,
    /// Float seconds since the header stamp (Velodyne `time`).
    RelativeSeconds,
}

/// Names drivers use for the per-point time, in order of preference.
const TIME_FIELDS: [&str; 5] = ["timestamp", "t", "time", "time_stamp", "offset_time"];

/// Points of one PointCloud2 in the sensor frame.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LidarScan {
    pub frame_id: String,
    /// Header stamp (seconds); the reference of [`Self::times`].
    pub stamp: Time,
    pub positions: Vec<DVec3>,
    /// Per-point intensity when the cloud has an `intensity` field.
    pub intensities: Option<Vec<f32>>,
    /// Per-point time in seconds relative to `stamp`, when the cloud has a time field.
    pub times: Option<Vec<f64>>,
    /// Per-point beam index when the cloud has a `ring` (Hesai, Ouster, Velodyne) or `line` (Livox) field.
    pub rings: Option<Vec<u16>>,
    /// The convention the time field was read with (`None` when there is none).
    pub time_kind: Option<PointTimeKind>,
    /// Points dropped because a coordinate was NaN or infinite.
    pub skipped_nonfinite: usize,
    /// Points dropped because they were exactly (0, 0, 0) (Ouster's "no return" in organised clouds).
    pub skipped_zero: usize,
}

impl LidarScan {
    /// As a [`PointCloud`] with `intensity` and `time` (relative seconds, f32) scalars when present.
    pub fn to_point_cloud(&self) -> PointCloud {
        let mut pc = PointCloud::from_positions(self.positions.clone());
        if let Some(i) = &self.intensities {
            pc.scalars.push(("intensity".into(), i.clone()));
        }
        if let Some(t) = &self.times {
            pc.scalars
                .push(("time".into(), t.iter().map(|&v| v as f32).collect()));
        }
        pc
    }
}

/// Reads element 0 of a numeric field at `at` as f64. The caller guarantees bounds.
fn read_number(data: &[u8], at: usize, datatype: u8, big: bool) -> f64 {
    macro_rules! get {
        ($t:ty, $n:expr) => {{
            let mut a = [0u8; $n];
            a.copy_from_slice(&data[at..at + $n]);
            if big {
                <$t>::from_be_bytes(a) as f64
            } else {
                <$t>::from_le_bytes(a) as f64
            }
        }};
    }
    match datatype {
        1 => data[at] as i8 as f64,
        2 => data[at] as f64,
        3 => get!(i16, 2),
        4 => get!(u16, 2),
        5 => get!(i32, 4),
        6 => get!(u32, 4),
        7 => get!(f32, 4),
        _ => get!(f64, 8),
    }
}

impl<'a> PointCloud2<'a> {
    pub const MSG: &'static str = "sensor_msgs/msg/PointCloud2";

    pub fn decode(payload: &'a [u8]) -> Result<Self, DecodeError> {
        decode_with(Self::MSG, payload, |r| {
            let header = Header::read(r)?;
            let height = r.u32()?;
            let width = r.u32()?;
            // PointField: name (>= 5) + offset + datatype + count >= 13 bytes.
            let n = r.seq_len(13, "fields")?;
            let mut fields = Vec::with_capacity(n);
            for _ in 0..n {
                fields.push(PointField {
                    name: r.string()?.to_string(),
                    offset: r.u32()?,
                    datatype: r.u8()?,
                    count: r.u32()?,
                });
            }
            Ok(Self {
                header,
                height,
                width,
                fields,
                is_bigendian: r.bool()?,
                point_step: r.u32()?,
                row_step: r.u32()?,
                data: r.byte_seq("data")?,
                is_dense: r.bool()?,
            })
        })
    }

    pub fn encode_with(&self, endian: Endian) -> Vec<u8> {
        let mut w = CdrWriter::with_endian(endian);
        self.header.write(&mut w);
        w.u32(self.height).u32(self.width);
        w.seq_len(self.fields.len());
        for f in &self.fields {
            w.string(&f.name).u32(f.offset).u8(f.datatype).u32(f.count);
        }
        w.bool(self.is_bigendian)
            .u32(self.point_step)
            .u32(self.row_step)
            .byte_seq(self.data)
            .bool(self.is_dense);
        w.finish()
    }

    pub fn encode(&self) -> Vec<u8> {
        self.encode_with(Endian::Little)
    }

    pub fn field(&self, name: &str) -> Option<&PointField> {
        self.fields.iter().find(|f| f.name == name)
    }

    /// A numeric field that fits inside one point, or why not.
    fn checked_field(&self, name: &str) -> Result<Option<&PointField>, DecodeError> {
        let Some(f) = self.field(name) else {
            return Ok(None);
        };
        let size = f.size().ok_or_else(|| {
            invalid(
                Self::MSG,
                format!("field '{name}' has unknown datatype {}", f.datatype),
            )
        })?;
        if f.offset as u64 + size as u64 > self.point_step as u64 {
            return Err(invalid(
                Self::MSG,
                format!(
                    "field '{name}' at offset {} ({size} bytes) does not fit in point_step {}",
                    f.offset, self.point_step
                ),
            ));
        }
        Ok(Some(f))
    }

    /// The points (x/y/z of any numeric type), intensity and per-point time relative to the header stamp.
    /// Non-finite and all-zero points are skipped and counted.
    pub fn to_scan(&self) -> Result<LidarScan, DecodeError> {
        let err = |reason: String| invalid(Self::MSG, reason);
        let mut xyz = [None; 3];
        for (slot, name) in xyz.iter_mut().zip(["x", "y", "z"]) {
            *slot = self.checked_field(name)?;
        }
        let [Some(fx), Some(fy), Some(fz)] = xyz else {
            return Err(err("no x, y and z fields".into()));
        };
        let fi = self.checked_field("intensity")?;
        let fr = match self.checked_field("ring")? {
            Some(f) => Some(f),
            None => self.checked_field("line")?,
        };
        let mut ft = None;
        for name in TIME_FIELDS {
            if let Some(f) = self.checked_field(name)? {
                ft = Some(f);
                break;
            }
        }
        let step = self.point_step as u64;
        let (w, h) = (self.width as u64, self.height as u64);
        if step == 0 && w * h > 0 {
            return Err(err("point_step is 0".into()));
        }
        if h > 1 && (self.row_step as u64) < w * step {
            return Err(err(format!(
                "row_step {} is less than width {w} x point_step {step}",
                self.row_step
            )));
        }
        let need = if w * h == 0 {
            0
        } else {
            (h - 1) * self.row_step as u64 + w * step
        };
        if need > self.data.len() as u64 {
            return Err(err(format!(
                "data has {} bytes, but {h} rows x {w} points (point_step {step}, row_step {}) need {need}",
                self.data.len(),
                self.row_step
            )));
        }
        // Bounded by the data size checked above.
        let n = (w * h) as usize;
        let big = self.is_bigendian;
        let data = self.data;
        let stamp = self.header.stamp;
        let mut positions = Vec::with_capacity(n);
        let mut intensities = fi.map(|_| Vec::with_capacity(n));
        let mut raw_times = ft.map(|_| Vec::with_capacity(n));
        let mut rings = fr.map(|_| Vec::with_capacity(n));
        let (mut skipped_nonfinite, mut skipped_zero) = (0, 0);
        // With no columns there is nothing to read: the rows are not walked (a width of 0 passes the size
        // check with any height, up to 2^32 empty rows; the cdr fuzz target found it).
        let rows = if w == 0 { 0 } else { h as usize };
        for row in 0..rows {
            let row_base = row * self.row_step as usize;
            for col in 0..w as usize {
                let base = row_base + col * step as usize;
                let p = DVec3::new(
                    read_number(data, base + fx.offset as usize, fx.datatype, big),
                    read_number(data, base + fy.offset as usize, fy.datatype, big),
                    read_number(data, base + fz.offset as usize, fz.datatype, big),
                );
                if !p.is_finite() {
                    skipped_nonfinite += 1;
                    continue;
                }
                if p == DVec3::ZERO {
                    skipped_zero += 1;
                    continue;
                }
                positions.push(p);
                if let (Some(f), Some(v)) = (fi, intensities.as_mut()) {
                    v.push(read_number(data, base + f.offset as usize, f.datatype, big) as f32);
                }
                if let (Some(f), Some(v)) = (ft, raw_times.as_mut()) {
                    v.push(read_number(data, base + f.offset as usize, f.datatype, big));
                }
                if let (Some(f), Some(v)) = (fr, rings.as_mut()) {
                    let r = read_number(data, base + f.offset as usize, f.datatype, big);
                    // Beam indices are small non-negative integers; anything else reads as "no ring".
                    v.push(if (0.0..65535.0).contains(&r) {
                        r as u16
                    } else {
                        u16::MAX
                    });
                }
            }
        }
        let (times, time_kind) = match (ft, raw_times) {
            (Some(f), Some(raw)) => {
                let kind = time_kind(f, &raw);
                let stamp_ns = stamp.nanos() as f64;
                let rel = raw
                    .iter()
                    .map(|&v| match kind {
                        PointTimeKind::AbsoluteSeconds => {
                            // Split the stamp so the subtraction keeps nanoseconds.
                            (v - stamp.sec as f64) - stamp.nanosec as f64 * 1e-9
                        }
                        PointTimeKind::AbsoluteNanos => (v - stamp_ns) * 1e-9,
                        PointTimeKind::RelativeNanos => v * 1e-9,
                        PointTimeKind::RelativeSeconds | PointTimeKind::None => v,
                    })
                    .collect();
                (Some(rel), Some(kind))
            }
            _ => (None, None),
        };
        Ok(LidarScan {
            frame_id: self.header.frame_id.clone(),
            stamp,
            positions,
            intensities,
            times,
            time_kind,
            rings,
            skipped_nonfinite,
            skipped_zero,
        })
    }
}

/// The unit of a time field: integers are relative nanoseconds, f32 relative seconds, and f64 by
/// magnitude (≥ 1e14 absolute ns, ≥ 1e6 absolute s — no scan lasts 11 days — else relative s).
fn time_kind(f: &PointField, raw: &[f64]) -> PointTimeKind {
    match f.datatype {
        PointField::FLOAT64 => {
            let mag = raw
                .iter()
                .copied()
                .find(|v| v.is_finite())
                .unwrap_or(0.0)
                .abs();
            if mag >= 1e14 {
                PointTimeKind::AbsoluteNanos
            } else if mag >= 1e6 {
                PointTimeKind::AbsoluteSeconds
            } else {
                PointTimeKind::RelativeSeconds
            }
        }
        PointField::FLOAT32 => PointTimeKind::RelativeSeconds,
        _ => PointTimeKind::RelativeNanos,
    }
}

// ---------------------------------------------------------------------------------------------------
// Images
// ---------------------------------------------------------------------------------------------------

/// An 8-bit RGB image, row-major (the layout [`crate::dataset::png_rgb`] writes).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RgbImage {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<[u8; 3]>,
}

/// sensor_msgs/Image with `data` borrowed.
#[derive(Clone, Debug, PartialEq)]
pub struct Image<'a> {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub is_bigendian: u8,
    pub step: u32,
    pub data: &'a [u8],
}

/// Bayer colour-filter layouts: the channel (0 R, 1 G, 2 B) at (even row, even col), (even, odd),
/// (odd, even), (odd, odd).
fn bayer_pattern(encoding: &str) -> Option<[usize; 4]> {
    Some(match encoding {
        "bayer_rggb8" => [0, 1, 1, 2],
        "bayer_bggr8" => [2, 1, 1, 0],
        "bayer_gbrg8" => [1, 2, 0, 1],
        "bayer_grbg8" => [1, 0, 2, 1],
        _ => return None,
    })
}

/// Simple bilinear-style demosaic: each output channel is the mean of that channel's samples in the
/// 3×3 neighbourhood (the pixel's own sample for its own channel). Good enough for previews and
/// colour supervision at the resolutions we train on.
fn demosaic(
    width: usize,
    height: usize,
    raw: impl Fn(usize, usize) -> u8,
    cfa: [usize; 4],
) -> Vec<[u8; 3]> {
    let mut out = Vec::with_capacity(width * height);
    for y in 0..height {
        for x in 0..width {
            let own = cfa[(y & 1) * 2 + (x & 1)];
            let mut sum = [0u32; 3];
            let mut cnt = [0u32; 3];
            for yy in y.saturating_sub(1)..(y + 2).min(height) {
                for xx in x.saturating_sub(1)..(x + 2).min(width) {
                    let c = cfa[(yy & 1) * 2 + (xx & 1)];
                    sum[c] += raw(xx, yy) as u32;
                    cnt[c] += 1;
                }
            }
            let mut px = [0u8; 3];
            for c in 0..3 {
                px[c] = if c == own {
                    raw(x, y)
                } else {
                    // A 3×3 window always holds every channel unless the image is 1 pixel wide/high.
                    (sum[c] + cnt[c] / 2).checked_div(cnt[c]).unwrap_or(0) as u8
                };
            }
            out.push(px);
        }
    }
    out
}

impl<'a> Image<'a> {
    pub const MSG: &'static str = "sensor_msgs/msg/Image";

    pub fn decode(payload: &'a [u8]) -> Result<Self, DecodeError> {
        decode_with(Self::MSG, payload, |r| {
            Ok(Self {
                header: Header::read(r)?,
                height: r.u32()?,
                width: r.u32()?,
                encoding: r.string()?.to_string(),
                is_bigendian: r.u8()?,
                step: r.u32()?,
                data: r.byte_seq("data")?,
            })
        })
    }

    pub fn encode_with(&self, endian: Endian) -> Vec<u8> {
        let mut w = CdrWriter::with_endian(endian);
        self.header.write(&mut w);
        w.u32(self.height)
            .u32(self.width)
            .string(&self.encoding)
            .u8(self.is_bigendian)
            .u32(self.step)
            .byte_seq(self.data);
        w.finish()
    }

    pub fn encode(&self) -> Vec<u8> {
        self.encode_with(Endian::Little)
    }

    /// Converts to RGB8. Supports rgb8, bgr8, rgba8, bgra8, mono8 (8UC1), mono16 (16UC1, scaled to 8
    /// bits) and the four 8-bit Bayer layouts.
    pub fn to_rgb(&self) -> Result<RgbImage, DecodeError> {
        let err = |reason: String| invalid(Self::MSG, reason);
        let enc = self.encoding.as_str();
        let bpp = match enc {
            "rgb8" | "bgr8" | "8UC3" => 3,
            "rgba8" | "bgra8" | "8UC4" => 4,
            "mono8" | "8UC1" => 1,
            "mono16" | "16UC1" => 2,
            _ if bayer_pattern(enc).is_some() => 1,
            _ => return Err(err(format!("unsupported image encoding '{enc}'"))),
        };
        let (w, h, step) = (self.width as u64, self.height as u64, self.step as u64);
        if step < w * bpp {
            return Err(err(format!(
                "step {step} is less than width {w} x {bpp} bytes ({enc})"
            )));
        }
        // An image without pixels is refused here: with a width of 0 the row loop below would still
        // run `height` times (up to 2^32; the fuzzer found one).
        if w * h == 0 {
            return Err(err(format!("{w}x{h} {enc}: the image has no pixels")));
        }
        let need = (h - 1) * step + w * bpp;
        if need > self.data.len() as u64 {
            return Err(err(format!(
                "data has {} bytes, but {w}x{h} {enc} with step {step} needs {need}",
                self.data.len()
            )));
        }
        let (w, h, step, bpp) = (w as usize, h as usize, step as usize, bpp as usize);
        let d = self.data;
        let at = |x: usize, y: usize| y * step + x * bpp;
        let pixels = if let Some(cfa) = bayer_pattern(enc) {
            demosaic(w, h, |x, y| d[at(x, y)], cfa)
        } else {
            let big = self.is_bigendian != 0;
            let mut out = Vec::with_capacity(w * h);
            for y in 0..h {
                for x in 0..w {
                    let i = at(x, y);
                    out.push(match enc {
                        "rgb8" | "rgba8" | "8UC3" | "8UC4" => [d[i], d[i + 1], d[i + 2]],
                        "bgr8" | "bgra8" => [d[i + 2], d[i + 1], d[i]],
                        "mono8" | "8UC1" => [d[i]; 3],
                        _ => {
                            let v = if big {
                                u16::from_be_bytes([d[i], d[i + 1]])
                            } else {
                                u16::from_le_bytes([d[i], d[i + 1]])
                            };
                            [(v >> 8) as u8; 3]
                        }
                    });
                }
            }
            out
        };
        Ok(RgbImage {
            width: self.width,
            height: self.height,
            pixels,
        })
    }
}

/// sensor_msgs/CompressedImage with `data` borrowed.
#[derive(Clone, Debug, PartialEq)]
pub struct CompressedImage<'a> {
    pub header: Header,
    pub format: String,
    pub data: &'a [u8],
}

impl<'a> CompressedImage<'a> {
    pub const MSG: &'static str = "sensor_msgs/msg/CompressedImage";

    pub fn decode(payload: &'a [u8]) -> Result<Self, DecodeError> {
        decode_with(Self::MSG, payload, |r| {
            Ok(Self {
                header: Header::read(r)?,
                format: r.string()?.to_string(),
                data: r.byte_seq("data")?,
            })
        })
    }

    /// Little endian (CDR_LE), as ROS 2 writes.
    pub fn encode(&self) -> Vec<u8> {
        self.encode_with(Endian::Little)
    }

    pub fn encode_with(&self, endian: Endian) -> Vec<u8> {
        let mut w = CdrWriter::with_endian(endian);
        self.header.write(&mut w);
        w.string(&self.format).byte_seq(self.data);
        w.finish()
    }

    /// Decodes JPEG or PNG (detected from the bytes; `format` is free text such as "bgr8; jpeg compressed
    /// bgr8") to RGB8. `compressedDepth` images are refused: their PNG carries a depth header.
    pub fn to_rgb(&self) -> Result<RgbImage, DecodeError> {
        let err = |reason: String| invalid(Self::MSG, reason);
        if self.format.contains("compressedDepth") {
            return Err(err(format!(
                "format '{}' (compressedDepth) is not a colour image",
                self.format
            )));
        }
        let fmt = image::guess_format(self.data).map_err(|e| {
            err(format!(
                "format '{}': cannot identify image data: {e}",
                self.format
            ))
        })?;
        if !matches!(fmt, image::ImageFormat::Jpeg | image::ImageFormat::Png) {
            return Err(err(format!(
                "format '{}': {fmt:?} images are not supported (jpeg, png)",
                self.format
            )));
        }
        let img = image::load_from_memory_with_format(self.data, fmt)
            .map_err(|e| err(format!("format '{}': {e}", self.format)))?
            .to_rgb8();
        let (width, height) = img.dimensions();
        let pixels = img
            .into_raw()
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect();
        Ok(RgbImage {
            width,
            height,
            pixels,
        })
    }
}

// ---------------------------------------------------------------------------------------------------
// sensor_msgs/CameraInfo
// ---------------------------------------------------------------------------------------------------

/// sensor_msgs/RegionOfInterest.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RegionOfInterest {
    pub x_offset: u32,
    pub y_offset: u32,
    pub height: u32,
    pub width: u32,
    pub do_rectify: bool,
}

/// sensor_msgs/CameraInfo.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraInfo {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub distortion_model: String,
    pub d: Vec<f64>,
    pub k: [f64; 9],
    pub r: [f64; 9],
    pub p: [f64; 12],
    pub binning_x: u32,
    pub binning_y: u32,
    pub roi: RegionOfInterest,
}

impl CameraInfo {
    pub const MSG: &'static str = "sensor_msgs/msg/CameraInfo";

    pub fn decode(payload: &[u8]) -> Result<Self, DecodeError> {
        decode_with(Self::MSG, payload, |r| {
            Ok(Self {
                header: Header::read(r)?,
                height: r.u32()?,
                width: r.u32()?,
                distortion_model: r.string()?.to_string(),
                d: r.f64_seq("d")?,
                k: r.f64_array()?,
                r: r.f64_array()?,
                p: r.f64_array()?,
                binning_x: r.u32()?,
                binning_y: r.u32()?,
                roi: RegionOfInterest {
                    x_offset: r.u32()?,
                    y_offset: r.u32()?,
                    height: r.u32()?,
                    width: r.u32()?,
                    do_rectify: r.bool()?,
                },
            })
        })
    }

    pub fn encode_with(&self, endian: Endian) -> Vec<u8> {
        let mut w = CdrWriter::with_endian(endian);
        self.header.write(&mut w);
        w.u32(self.height)
            .u32(self.width)
            .string(&self.distortion_model)
            .f64_seq(&self.d)
            .f64_array(&self.k)
            .f64_array(&self.r)
            .f64_array(&self.p)
            .u32(self.binning_x)
            .u32(self.binning_y)
            .u32(self.roi.x_offset)
            .u32(self.roi.y_offset)
            .u32(self.roi.height)
            .u32(self.roi.width)
            .bool(self.roi.do_rectify);
        w.finish()
    }

    pub fn encode(&self) -> Vec<u8> {
        self.encode_with(Endian::Little)
    }

    /// Our [`CameraModel`] (raw, unrectified image: K and D). `plumb_bob` → rad-tan, `equidistant` →
    /// fisheye, `rational_polynomial` → rad-tan when k4..k6 are zero (our model has no denominator
    /// terms; refusing beats silently mis-projecting). An empty or all-zero D is a pinhole.
    pub fn camera_model(&self) -> Result<CameraModel, DecodeError> {
        let err = |reason: String| invalid(Self::MSG, reason);
        let d = &self.d;
        let model = self.distortion_model.as_str();
        let expect = |n: usize| -> Result<(), DecodeError> {
            if d.len() == n {
                Ok(())
            } else {
                Err(err(format!(
                    "distortion model '{model}' needs {n} coefficients, D has {}",
                    d.len()
                )))
            }
        };
        let distortion = if d.iter().all(|&v| v == 0.0) {
            Distortion::None
        } else {
            match model {
                "plumb_bob" => {
                    expect(5)?;
                    Distortion::RadTan {
                        k1: d[0],
                        k2: d[1],
                        p1: d[2],
                        p2: d[3],
                        k3: d[4],
                    }
                }
                "rational_polynomial" => {
                    expect(8)?;
                    if d[5..8].iter().any(|&v| v != 0.0) {
                        return Err(err(format!(
                            "rational_polynomial with non-zero k4..k6 {:?} is not supported",
                            &d[5..8]
                        )));
                    }
                    Distortion::RadTan {
                        k1: d[0],
                        k2: d[1],
                        p1: d[2],
                        p2: d[3],
                        k3: d[4],
                    }
                }
                "equidistant" => {
                    expect(4)?;
                    Distortion::Fisheye {
                        k1: d[0],
                        k2: d[1],
                        k3: d[2],
                        k4: d[3],
                    }
                }
                other => return Err(err(format!("unknown distortion model '{other}'"))),
            }
        };
        let k = &self.k;
        if k[1] != 0.0 {
            log::warn!("CameraInfo K has skew {}; ignored", k[1]);
        }
        let cam = CameraModel {
            width: self.width,
            height: self.height,
            fx: k[0],
            fy: k[4],
            cx: k[2],
            cy: k[5],
            distortion,
        };
        cam.validate().map_err(|e| err(e.to_string()))?;
        Ok(cam)
    }
}

// ---------------------------------------------------------------------------------------------------
// Dispatch
// ---------------------------------------------------------------------------------------------------

/// A decoded message of a type the ingest understands (the large fixed-size ones boxed, so the enum
/// stays small when iterating a bag).
#[derive(Clone, Debug, PartialEq)]
pub enum RosMessage<'a> {
    PointCloud2(PointCloud2<'a>),
    Image(Image<'a>),
    CompressedImage(CompressedImage<'a>),
    CameraInfo(Box<CameraInfo>),
    Tf(TfMessage),
    Odometry(Box<Odometry>),
    Path(Path),
    PoseStamped(PoseStamped),
    PoseWithCovarianceStamped(Box<PoseWithCovarianceStamped>),
}

/// The canonical ROS 2 name (`pkg/msg/Type`) of a schema name, accepting the ROS 1 spelling `pkg/Type`.
pub fn canonical_type(name: &str) -> String {
    // ROS 1's `tf` package had its own TF message with the same layout as tf2's.
    if name == "tf/tfMessage" || name == "tf/msg/tfMessage" {
        return "tf2_msgs/msg/TFMessage".into();
    }
    match name.split_once('/') {
        Some((pkg, ty)) if !ty.contains('/') => format!("{pkg}/msg/{ty}"),
        _ => name.to_string(),
    }
}

/// Whether [`decode`] knows this schema name.
pub fn is_known_type(schema_name: &str) -> bool {
    KNOWN_TYPES.contains(&canonical_type(schema_name).as_str())
}

/// Message types [`decode`] handles.
pub const KNOWN_TYPES: [&str; 9] = [
    PointCloud2::MSG,
    Image::MSG,
    CompressedImage::MSG,
    CameraInfo::MSG,
    TfMessage::MSG,
    Odometry::MSG,
    Path::MSG,
    PoseStamped::MSG,
    PoseWithCovarianceStamped::MSG,
];

/// Decodes a CDR payload by schema name; `None` for a type we do not decode.
pub fn decode<'a>(
    schema_name: &str,
    payload: &'a [u8],
) -> Option<Result<RosMessage<'a>, DecodeError>> {
    let ty = canonical_type(schema_name);
    Some(match ty.as_str() {
        PointCloud2::MSG => PointCloud2::decode(payload).map(RosMessage::PointCloud2),
        Image::MSG => Image::decode(payload).map(RosMessage::Image),
        CompressedImage::MSG => CompressedImage::decode(payload).map(RosMessage::CompressedImage),
        CameraInfo::MSG => CameraInfo::decode(payload).map(|m| RosMessage::CameraInfo(Box::new(m))),
        TfMessage::MSG => TfMessage::decode(payload).map(RosMessage::Tf),
        Odometry::MSG => Odometry::decode(payload).map(|m| RosMessage::Odometry(Box::new(m))),
        Path::MSG => Path::decode(payload).map(RosMessage::Path),
        PoseStamped::MSG => PoseStamped::decode(payload).map(RosMessage::PoseStamped),
        PoseWithCovarianceStamped::MSG => PoseWithCovarianceStamped::decode(payload)
            .map(|m| RosMessage::PoseWithCovarianceStamped(Box::new(m))),
        _ => return None,
    })
}

#[cfg(test)]
#[path = "ros_tests.rs"]
mod tests;
