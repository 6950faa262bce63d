//! KITTI's files: velodyne scans (`velodyne/NNNNNN.bin`, and nuScenes lidar sweeps `*.pcd.bin`, the same
//! headerless little-endian `f32` records, one per point), and the text files beside them: calibration
//! (`calib.txt`, `calib_*.txt`: `KEY: numbers` lines) and `times.txt` (one stamp per line). The text
//! parsers work on `&str` (browser included); errors name the file and the line.
//!
//! KITTI (<https://www.cvlibs.net/datasets/kitti/eval_odometry.php>) writes 4 floats per point, `x y z
//! reflectance` in the sensor frame; nuScenes writes 5, `x y z intensity ring`. Both are selected with a
//! `stride` ([`KITTI_STRIDE`], [`NUSCENES_STRIDE`]). With no header, the length is the only check the file
//! allows, so a length that is not a whole number of records is refused rather than truncated: it means the
//! wrong stride or a cut-off download. Points with a non-finite coordinate carry no geometry and are
//! skipped (and counted), unlike organised PCD/PLY clouds where a NaN holds a pixel's place.

use std::path::Path;

use glam::{DMat3, DVec3};
use thiserror::Error;

use crate::dataset::{write_atomic, DatasetError};
use crate::geometry::Se3;
use crate::pointcloud::PointCloud;

/// Floats per point of a KITTI `.bin`: x, y, z, reflectance.
pub const KITTI_STRIDE: usize = 4;
/// Floats per point of a nuScenes `.pcd.bin`: x, y, z, intensity, ring.
pub const NUSCENES_STRIDE: usize = 5;

/// `.bin` cloud errors; every variant names the file.
#[derive(Debug, Error)]
pub enum BinCloudError {
    #[error("{file}: {source}")]
    Io {
        file: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{file}: stride {stride} is not 4 (KITTI x y z reflectance) or 5 (nuScenes x y z intensity ring)")]
    BadStride { file: String, stride: usize },
    #[error("{file}: {bytes} bytes is not a whole number of {record}-byte points ({stride} little-endian f32 each); wrong stride or a truncated file")]
    BadLength {
        file: String,
        bytes: usize,
        record: usize,
        stride: usize,
    },
    #[error(transparent)]
    Write(#[from] DatasetError),
}

/// A decoded scan: positions, an `intensity` scalar (KITTI reflectance or nuScenes intensity) and, for
/// nuScenes, a `ring` scalar.
#[derive(Clone, Debug, PartialEq)]
pub struct BinScan {
    pub cloud: PointCloud,
    /// Records dropped for a NaN or infinite x, y or z.
    pub skipped: usize,
}

fn check_stride(file: &str, stride: usize) -> Result<(), BinCloudError> {
    if stride == KITTI_STRIDE || stride == NUSCENES_STRIDE {
        Ok(())
    } else {
        Err(BinCloudError::BadStride {
            file: file.to_string(),
            stride,
        })
    }
}

/// Decodes `.bin` bytes with `stride` floats per point; `name` is used in errors.
pub fn read_bin_bytes(bytes: &[u8], name: &str, stride: usize) -> Result<BinScan, BinCloudError> {
    check_stride(name, stride)?;
    let record = 4 * stride;
    if !bytes.len().is_multiple_of(record) {
        return Err(BinCloudError::BadLength {
            file: name.to_string(),
            bytes: bytes.len(),
            record,
            stride,
        });
    }
    let n = bytes.len() / record;
    let mut positions = Vec::with_capacity(n);
    let mut intensity = Vec::with_capacity(n);
    let mut ring = Vec::with_capacity(if stride == NUSCENES_STRIDE { n } else { 0 });
    let mut skipped = 0;
    let mut values = [0f32; NUSCENES_STRIDE];
    for rec in bytes.chunks_exact(record) {
        for (v, b) in values.iter_mut().zip(rec.chunks_exact(4)) {
            *v = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        }
        let [x, y, z, i, r] = values;
        let p = DVec3::new(x as f64, y as f64, z as f64);
        if !p.is_finite() {
            skipped += 1;
            continue;
        }
        positions.push(p);
        intensity.push(i);
        if stride == NUSCENES_STRIDE {
            ring.push(r);
        }
    }
    let mut cloud = PointCloud::from_positions(positions);
    cloud.set_scalar("intensity", intensity);
    if stride == NUSCENES_STRIDE {
        cloud.set_scalar("ring", ring);
    }
    Ok(BinScan { cloud, skipped })
}

/// Reads a KITTI (`stride` 4) or nuScenes (`stride` 5) `.bin` scan.
pub fn read_bin(path: &Path, stride: usize) -> Result<BinScan, BinCloudError> {
    let file = path.display().to_string();
    check_stride(&file, stride)?;
    let bytes = std::fs::read(path).map_err(|source| BinCloudError::Io {
        file: file.clone(),
        source,
    })?;
    read_bin_bytes(&bytes, &file, stride)
}

/// Encodes a cloud as `.bin` records: positions narrowed to `f32` (values beyond its range become
/// infinite), `intensity` and (stride 5) `ring` from the cloud's scalars, 0 where absent.
pub fn write_bin_bytes(cloud: &PointCloud, stride: usize) -> Result<Vec<u8>, BinCloudError> {
    check_stride("(bin writer)", stride)?;
    let intensity = cloud.scalar("intensity").unwrap_or(&[]);
    let ring = cloud.scalar("ring").unwrap_or(&[]);
    let mut out = Vec::with_capacity(cloud.len() * 4 * stride);
    for (k, p) in cloud.positions.iter().enumerate() {
        let i = intensity.get(k).copied().unwrap_or(0.0);
        let r = ring.get(k).copied().unwrap_or(0.0);
        let record = [p.x as f32, p.y as f32, p.z as f32, i, r];
        for v in record.iter().take(stride) {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    Ok(out)
}

/// Writes a `.bin` scan through a temporary file and a rename.
pub fn write_bin(path: &Path, cloud: &PointCloud, stride: usize) -> Result<(), BinCloudError> {
    check_stride(&path.display().to_string(), stride)?;
    write_atomic(path, &write_bin_bytes(cloud, stride)?)?;
    Ok(())
}

/// Errors of KITTI's text files (`calib.txt`, `calib_*.txt`, `times.txt`); every variant names the file,
/// and the line where there is one.
#[derive(Debug, Error, PartialEq)]
pub enum KittiTextError {
    #[error("{file}, line {line}: {reason}")]
    Line {
        file: String,
        line: usize,
        reason: String,
    },
    #[error("{file}: {reason}")]
    Invalid { file: String, reason: String },
}

fn line_err(file: &str, line: usize, reason: impl Into<String>) -> KittiTextError {
    KittiTextError::Line {
        file: file.to_string(),
        line,
        reason: reason.into(),
    }
}

/// Non-blank lines with their 1-based numbers, a leading byte-order mark removed.
fn text_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.strip_prefix('\u{feff}')
        .unwrap_or(text)
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty())
}

/// One `KEY: value` line of a calibration file.
#[derive(Clone, Debug, PartialEq)]
pub struct CalibEntry {
    pub key: String,
    /// 1-based line number, for errors about the value.
    pub line: usize,
    /// The text after the colon, trimmed. Numbers are parsed when asked for ([`Calib::numbers`]), because
    /// the raw release also keeps text there (`calib_time: 09-Jan-2012 13:57:47`).
    pub value: String,
}

/// A KITTI calibration file: the odometry `calib.txt` (`P0`…`P3`, `Tr`) or the raw release's
/// `calib_cam_to_cam.txt` / `calib_velo_to_cam.txt` / `calib_imu_to_velo.txt`, all `KEY: numbers` lines.
#[derive(Clone, Debug, PartialEq)]
pub struct Calib {
    /// The file's name, for errors.
    pub file: String,
    pub entries: Vec<CalibEntry>,
}

/// A rectified camera's projection `P = K · [I | t]` (KITTI's `P2`, `P_rect_02`): its pinhole intrinsics
/// and `t`, where the camera sits relative to the reference (rectified cam0) frame: `p_cam = p_ref + t`.
/// For the colour cameras `t.x` is minus the baseline to cam0 (≈ +0.06 m for cam2, −0.47 m for cam3).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Projection {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub t: DVec3,
}

/// Parses calibration text; `name` is used in errors. Every non-blank line must be `KEY: value` with a
/// key of letters, digits and `_`, each key once (a repeated key would make the file ambiguous).
pub fn parse_calib(text: &str, name: &str) -> Result<Calib, KittiTextError> {
    let mut entries: Vec<CalibEntry> = Vec::new();
    for (n, line) in text_lines(text) {
        let Some((key, value)) = line.split_once(':') else {
            return Err(line_err(name, n, "expected 'KEY: values' (no colon)"));
        };
        let key = key.trim();
        if key.is_empty() || !key.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
            let shown: String = key.chars().take(40).collect();
            return Err(line_err(
                name,
                n,
                format!("'{shown}' is not a calibration key (letters, digits and _)"),
            ));
        }
        if let Some(first) = entries.iter().find(|e| e.key == key) {
            return Err(line_err(
                name,
                n,
                format!("{key} repeats the entry of line {}", first.line),
            ));
        }
        entries.push(CalibEntry {
            key: key.to_string(),
            line: n,
            value: value.trim().to_string(),
        });
    }
    if entries.is_empty() {
        return Err(KittiTextError::Invalid {
            file: name.to_string(),
            reason: "no 'KEY: values' lines (empty calibration file)".into(),
        });
    }
    Ok(Calib {
        file: name.to_string(),
        entries,
    })
}

impl Calib {
    /// The entry of `key`, if the file has one.
    pub fn get(&self, key: &str) -> Option<&CalibEntry> {
        self.entries.iter().find(|e| e.key == key)
    }

    fn entry(&self, key: &str) -> Result<&CalibEntry, KittiTextError> {
        self.get(key).ok_or_else(|| KittiTextError::Invalid {
            file: self.file.clone(),
            reason: format!(
                "no '{key}:' line (keys present: {})",
                self.entries
                    .iter()
                    .map(|e| e.key.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        })
    }

    /// The finite numbers of `key`.
    pub fn numbers(&self, key: &str) -> Result<Vec<f64>, KittiTextError> {
        let e = self.entry(key)?;
        e.value
            .split_whitespace()
            .enumerate()
            .map(|(i, tok)| match tok.parse::<f64>() {
                Ok(v) if v.is_finite() => Ok(v),
                Ok(_) => Err(line_err(
                    &self.file,
                    e.line,
                    format!("{key}: value {} '{tok}' is not finite", i + 1),
                )),
                Err(_) => Err(line_err(
                    &self.file,
                    e.line,
                    format!(
                        "{key}: value {} '{}' is not a number",
                        i + 1,
                        tok.chars().take(40).collect::<String>()
                    ),
                )),
            })
            .collect()
    }

    /// Exactly `n` numbers of `key` (`what` says what they are, for the error).
    pub fn exactly(&self, key: &str, n: usize, what: &str) -> Result<Vec<f64>, KittiTextError> {
        let v = self.numbers(key)?;
        if v.len() != n {
            return Err(line_err(
                &self.file,
                self.entry(key)?.line,
                format!("{key} has {} numbers; {what} needs {n}", v.len()),
            ));
        }
        Ok(v)
    }

    /// `key` as a rectified projection `K · [I | t]` (3 × 4, row-major): zero skew, positive focal
    /// lengths, last row `0 0 1 t_z`.
    pub fn projection(&self, key: &str) -> Result<Projection, KittiTextError> {
        let p = self.exactly(key, 12, "a 3 × 4 projection matrix")?;
        let line = self.entry(key)?.line;
        let bad = |reason: String| line_err(&self.file, line, format!("{key}: {reason}"));
        let (fx, s, cx) = (p[0], p[1], p[2]);
        let (z, fy, cy) = (p[4], p[5], p[6]);
        if !(fx > 0.0 && fy > 0.0) {
            return Err(bad(format!(
                "focal lengths must be positive (fx = {fx}, fy = {fy})"
            )));
        }
        let tiny = 1e-9 * fx;
        if s.abs() > 1e-6 * fx
            || z.abs() > tiny
            || p[8].abs() > tiny
            || p[9].abs() > tiny
            || (p[10] - 1.0).abs() > 1e-9
        {
            return Err(bad(
                "not a rectified pinhole projection K·[I|t] (expected fx 0 cx · 0 fy cy · 0 0 1 ·)"
                    .into(),
            ));
        }
        // P · (X, 1) = K X + (p03, p13, p23): the fourth column is K t.
        let tz = p[11];
        let ty = (p[7] - cy * tz) / fy;
        let tx = (p[3] - s * ty - cx * tz) / fx;
        Ok(Projection {
            fx,
            fy,
            cx,
            cy,
            t: DVec3::new(tx, ty, tz),
        })
    }

    /// `key` as a rigid transform `[R | t]` (3 × 4, row-major; `Tr` of the odometry `calib.txt`), the
    /// rotation block checked and projected onto the nearest rotation as for KITTI poses.
    pub fn rigid(&self, key: &str) -> Result<Se3, KittiTextError> {
        let m = self.exactly(key, 12, "a 3 × 4 [R | t] matrix")?;
        let r = [m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]];
        self.rotation_translation(key, &r, DVec3::new(m[3], m[7], m[11]))
    }

    /// The raw release's split form: `r_key` (3 × 3, row-major) and `t_key` (3) as one rigid transform.
    pub fn rigid_rt(&self, r_key: &str, t_key: &str) -> Result<Se3, KittiTextError> {
        let r = self.exactly(r_key, 9, "a 3 × 3 rotation")?;
        let t = self.exactly(t_key, 3, "a translation")?;
        let r: [f64; 9] = r.try_into().expect("nine numbers");
        self.rotation_translation(r_key, &r, DVec3::new(t[0], t[1], t[2]))
    }

    fn rotation_translation(
        &self,
        key: &str,
        r: &[f64; 9],
        t: DVec3,
    ) -> Result<Se3, KittiTextError> {
        let m = DMat3::from_cols(
            DVec3::new(r[0], r[3], r[6]),
            DVec3::new(r[1], r[4], r[7]),
            DVec3::new(r[2], r[5], r[8]),
        );
        let line = self.entry(key)?.line;
        let q = super::poses::nearest_rotation(m)
            .map_err(|reason| line_err(&self.file, line, format!("{key}: {reason}")))?;
        Ok(Se3::new(q, t))
    }
}

/// Parses a KITTI `times.txt`: one stamp (seconds, finite) per non-blank line, strictly increasing (a
/// repeated or backwards stamp means a corrupted or concatenated file; the error names both lines).
/// Returns the stamps in line order: entry i belongs to frame i.
pub fn parse_times(text: &str, name: &str) -> Result<Vec<f64>, KittiTextError> {
    let mut stamps: Vec<f64> = Vec::new();
    let mut last_line = 0;
    for (n, line) in text_lines(text) {
        let mut toks = line.split_whitespace();
        let (Some(tok), None) = (toks.next(), toks.next()) else {
            return Err(line_err(name, n, "expected one number (seconds) per line"));
        };
        let t = match tok.parse::<f64>() {
            Ok(v) if v.is_finite() => v,
            Ok(_) => return Err(line_err(name, n, format!("stamp '{tok}' is not finite"))),
            Err(_) => {
                let shown: String = tok.chars().take(40).collect();
                return Err(line_err(
                    name,
                    n,
                    format!("stamp '{shown}' is not a number"),
                ));
            }
        };
        if let Some(&prev) = stamps.last() {
            if t <= prev {
                return Err(line_err(
                    name,
                    n,
                    format!(
                        "stamp {t} is not after {prev} (line {last_line}); stamps must increase"
                    ),
                ));
            }
        }
        stamps.push(t);
        last_line = n;
    }
    if stamps.is_empty() {
        return Err(KittiTextError::Invalid {
            file: name.to_string(),
            reason: "no stamps (empty times file)".into(),
        });
    }
    Ok(stamps)
}

/// Parses a KITTI raw `timestamps.txt` (`2011-09-26 13:02:25.964389445`, one per line, UTC as the
/// recorder wrote it) into seconds after the first line, so that the frame times keep their nanoseconds
/// (seconds since 1970 as `f64` would keep ~0.2 µs). Stamps must increase, as in [`parse_times`].
pub fn parse_datetimes(text: &str, name: &str) -> Result<Vec<f64>, KittiTextError> {
    let mut first: Option<(i64, f64)> = None;
    let mut stamps: Vec<f64> = Vec::new();
    let mut last_line = 0;
    for (n, line) in text_lines(text) {
        let shown = || line.chars().take(40).collect::<String>();
        let bad = || {
            line_err(
                name,
                n,
                format!(
                    "'{}' is not a stamp like 2011-09-26 13:02:25.964389445",
                    shown()
                ),
            )
        };
        let (date, time) = line.split_once(' ').ok_or_else(bad)?;
        let d: Vec<&str> = date.split('-').collect();
        let t: Vec<&str> = time.trim().split(':').collect();
        let (&[y, mo, da], &[h, mi, se]) = (d.as_slice(), t.as_slice()) else {
            return Err(bad());
        };
        let int = |s: &str, lo: i64, hi: i64| {
            s.parse::<i64>()
                .ok()
                .filter(|v| (lo..=hi).contains(v) && s.bytes().all(|b| b.is_ascii_digit()))
        };
        let (Some(y), Some(mo), Some(da), Some(h), Some(mi)) = (
            int(y, 1970, 9999),
            int(mo, 1, 12),
            int(da, 1, 31),
            int(h, 0, 23),
            int(mi, 0, 59),
        ) else {
            return Err(bad());
        };
        let sec = se
            .parse::<f64>()
            .ok()
            .filter(|v| {
                (0.0..61.0).contains(v) && se.bytes().all(|b| b.is_ascii_digit() || b == b'.')
            })
            .ok_or_else(bad)?;
        // Whole seconds since 1970 by days from the civil date (proleptic Gregorian), the fraction apart.
        let day = days_from_civil(y, mo, da);
        let whole = day * 86_400 + h * 3_600 + mi * 60;
        let (w0, s0) = *first.get_or_insert((whole, sec));
        let stamp = (whole - w0) as f64 + (sec - s0);
        if let Some(&prev) = stamps.last() {
            if stamp <= prev {
                return Err(line_err(
                    name,
                    n,
                    format!(
                        "stamp '{}' is not after line {last_line}'s; stamps must increase",
                        shown()
                    ),
                ));
            }
        }
        stamps.push(stamp);
        last_line = n;
    }
    if stamps.is_empty() {
        return Err(KittiTextError::Invalid {
            file: name.to_string(),
            reason: "no stamps (empty timestamps file)".into(),
        });
    }
    Ok(stamps)
}

/// Days from 1970-01-01 to a civil date (Howard Hinnant's algorithm).
fn days_from_civil(y: i64, m: i64, d: i64) -> i64 {
    let y = if m <= 2 { y - 1 } else { y };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (m + 9) % 12;
    let doy = (153 * mp + 2) / 5 + d - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

/// One OXTS record of the raw release (`oxts/data/NNNNNNNNNN.txt`): the GPS/IMU's position and attitude
/// (the first 6 of its 30 numbers; the velocities, accelerations and accuracies are not used).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Oxts {
    /// Degrees, WGS84.
    pub lat: f64,
    pub lon: f64,
    /// Metres above sea level.
    pub alt: f64,
    /// Radians: roll about x (forward), pitch about y (left), yaw (heading) about z (up), east = 0.
    pub roll: f64,
    pub pitch: f64,
    pub yaw: f64,
}

/// Parses an OXTS record: one line of 30 numbers (the devkit's `dataformat.txt`), every one finite.
pub fn parse_oxts(text: &str, name: &str) -> Result<Oxts, KittiTextError> {
    let mut lines = text_lines(text);
    let Some((n, line)) = lines.next() else {
        return Err(KittiTextError::Invalid {
            file: name.to_string(),
            reason: "empty OXTS record".into(),
        });
    };
    let v: Vec<f64> = line
        .split_whitespace()
        .enumerate()
        .map(|(i, tok)| match tok.parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            _ => Err(line_err(
                name,
                n,
                format!(
                    "value {} '{}' is not a finite number",
                    i + 1,
                    tok.chars().take(40).collect::<String>()
                ),
            )),
        })
        .collect::<Result<_, _>>()?;
    if v.len() != 30 {
        return Err(line_err(
            name,
            n,
            format!("{} numbers; an OXTS record has 30", v.len()),
        ));
    }
    if let Some((n, _)) = lines.next() {
        return Err(line_err(name, n, "an OXTS record is one line"));
    }
    if v[0].abs() > 90.0 || v[1].abs() > 180.0 {
        return Err(line_err(
            name,
            n,
            format!("latitude {} / longitude {} out of range", v[0], v[1]),
        ));
    }
    Ok(Oxts {
        lat: v[0],
        lon: v[1],
        alt: v[2],
        roll: v[3],
        pitch: v[4],
        yaw: v[5],
    })
}

/// Earth radius of the devkit's Mercator projection (m).
const OXTS_EARTH_RADIUS: f64 = 6_378_137.0;

/// The GPS/IMU's pose of each record in a local metric frame (x east, y north, z up), as the KITTI devkit
/// computes it (`convertOxtsToPose`): a Mercator projection scaled by the cosine of the first record's
/// latitude, and the attitude `Rz(yaw) · Ry(pitch) · Rx(roll)`. Not normalised to the first record.
pub fn oxts_poses(records: &[Oxts]) -> Vec<Se3> {
    let Some(first) = records.first() else {
        return Vec::new();
    };
    let scale = first.lat.to_radians().cos();
    records
        .iter()
        .map(|o| {
            let x = scale * OXTS_EARTH_RADIUS * o.lon.to_radians();
            let y = scale
                * OXTS_EARTH_RADIUS
                * ((90.0 + o.lat) * std::f64::consts::PI / 360.0).tan().ln();
            let q = glam::DQuat::from_rotation_z(o.yaw)
                * glam::DQuat::from_rotation_y(o.pitch)
                * glam::DQuat::from_rotation_x(o.roll);
            Se3::new(q, DVec3::new(x, y, o.alt))
        })
        .collect()
}

/// The inverse of [`oxts_poses`]' projection for one pose, given the first record's latitude (for tests
/// and for writing OXTS records of a known trajectory).
pub fn oxts_from_pose(pose: &Se3, lat0: f64) -> Oxts {
    let scale = lat0.to_radians().cos();
    let t = pose.trans;
    let lon = (t.x / (scale * OXTS_EARTH_RADIUS)).to_degrees();
    let lat = 2.0
        * (t.y / (scale * OXTS_EARTH_RADIUS))
            .exp()
            .atan()
            .to_degrees()
        - 90.0;
    let (yaw, pitch, roll) = pose.rot.to_euler(glam::EulerRot::ZYX);
    Oxts {
        lat,
        lon,
        alt: t.z,
        roll,
        pitch,
        yaw,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn raw_timestamps_are_seconds_after_the_first_across_midnight_and_months() {
        let t = parse_datetimes(
            "2011-09-26 13:02:25.964389445\n2011-09-26 13:02:26.068074849\n2011-09-30 23:59:59.5\n2011-10-01 00:00:00.25\n",
            "timestamps.txt",
        )
        .unwrap();
        assert!((t[1] - 0.103685404).abs() < 1e-9, "{t:?}");
        let to_30th =
            4.0 * 86_400.0 + (23.0 - 13.0) * 3_600.0 + (59.0 - 2.0) * 60.0 + 59.5 - 25.964389445;
        assert!((t[2] - to_30th).abs() < 1e-6, "{t:?}");
        assert!((t[3] - t[2] - 0.75).abs() < 1e-9, "{t:?}");
        for bad in [
            "2011-09-26 13:02:25.9\n2011-09-26 13:02:25.9\n",
            "2011-13-26 13:02:25.9\n",
            "2011-09-26T13:02:25.9\n",
            "13:02:25.9\n",
            "2011-09-26 13:02:-5\n",
            "",
        ] {
            let e = parse_datetimes(bad, "image_02/timestamps.txt")
                .unwrap_err()
                .to_string();
            assert!(e.contains("image_02/timestamps.txt"), "{bad:?}: {e}");
        }
    }

    #[test]
    fn oxts_records_parse_and_project_as_the_devkit_and_invert() {
        // 2011_09_26_drive_0001's first record.
        let rec = "49.015003823272 8.4342971002335 116.43032836914 0.035752 0.00903 -2.6087069803847 -7.3874582988118 7.2834701230779 10.37416206183 -0.17004600225342 -0.046891081961614 0.42018270050397 0.7893624111408 9.7998458934587 -0.051012051999397 0.40905316838493 9.8003713154212 -0.015016062324513 0.018157625071025 0.024021981040087 -0.014620598719226 0.019080598225069 0.023746622811066 0.77373859283445 0.19416152518153 4 10 4 4 0\n";
        let o = parse_oxts(rec, "0000000000.txt").unwrap();
        assert_eq!((o.lat, o.yaw), (49.015003823272, -2.6087069803847));
        let p = oxts_poses(&[
            o,
            Oxts {
                lat: o.lat + 1e-5,
                ..o
            },
        ]);
        // One hundred-thousandth of a degree of latitude is ~1.11 m north, scaled by nothing else.
        let d = p[1].trans - p[0].trans;
        assert!(d.x.abs() < 1e-9 && (d.y - 1.1132).abs() < 2e-3, "{d:?}");
        let back = oxts_from_pose(&p[0], o.lat);
        for (a, b) in [(back.lat, o.lat), (back.lon, o.lon), (back.alt, o.alt)] {
            assert!((a - b).abs() < 1e-9, "{back:?}");
        }
        for (a, b) in [
            (back.roll, o.roll),
            (back.pitch, o.pitch),
            (back.yaw, o.yaw),
        ] {
            assert!((a - b).abs() < 1e-12, "{back:?}");
        }
        for bad in [
            "",
            "1 2 3\n",
            &rec.replace("116.43", "nan"),
            &format!("{rec}{rec}"),
            &rec.replacen("49.01", "99.01", 1),
        ] {
            let e = parse_oxts(bad, "oxts/data/0000000000.txt")
                .unwrap_err()
                .to_string();
            assert!(e.contains("oxts/data/0000000000.txt"), "{e}");
        }
    }

    fn floats(v: &[f32]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_le_bytes()).collect()
    }

    /// Sequence 00's calib.txt as released (P0, P1 trimmed to what the tests need).
    const CALIB_00: &str = "P0: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 0.000000000000e+00 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P2: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 4.538225000000e+01 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 -1.130887000000e-01 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 3.779761000000e-03
P3: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.372877000000e+02 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 2.369057000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 4.915215000000e-03
Tr: 4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 -7.210626507497e-03 8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 9.999738645903e-01 4.859485810390e-04 -7.206933692422e-03 -2.921968648686e-01
";

    #[test]
    fn calib_gives_projections_and_the_velodyne_transform() {
        let c = parse_calib(CALIB_00, "00/calib.txt").unwrap();
        assert_eq!(c.entries.len(), 4);
        assert_eq!(c.get("Tr").unwrap().line, 4);
        let p2 = c.projection("P2").unwrap();
        assert_eq!(
            (p2.fx, p2.fy, p2.cx, p2.cy),
            (718.856, 718.856, 607.1928, 185.2157)
        );
        // The projection P2 maps a point exactly as K (X + t) does.
        let x = DVec3::new(1.5, -0.7, 12.0);
        let p = c.exactly("P2", 12, "P").unwrap();
        let u = (p[0] * x.x + p[1] * x.y + p[2] * x.z + p[3])
            / (p[8] * x.x + p[9] * x.y + p[10] * x.z + p[11]);
        let v = (p[4] * x.x + p[5] * x.y + p[6] * x.z + p[7])
            / (p[8] * x.x + p[9] * x.y + p[10] * x.z + p[11]);
        let xc = x + p2.t;
        assert!((p2.fx * xc.x / xc.z + p2.cx - u).abs() < 1e-9, "{u}");
        assert!((p2.fy * xc.y / xc.z + p2.cy - v).abs() < 1e-9, "{v}");
        // cam2 sits ~6 cm left of cam0, cam3 ~47 cm right: the stereo baseline is ~0.54 m.
        let p3 = c.projection("P3").unwrap();
        assert!(
            (p2.t.x - 0.0599).abs() < 1e-3 && (p3.t.x + 0.4733).abs() < 1e-3,
            "{p2:?} {p3:?}"
        );
        assert_eq!(c.projection("P0").unwrap().t, DVec3::ZERO);
        // Tr: velodyne → cam0; the lidar's forward axis (+x) is the camera's +z.
        let tr = c.rigid("Tr").unwrap();
        let fwd = tr.rot * DVec3::X;
        assert!((fwd - DVec3::Z).length() < 0.02, "{fwd}");
        assert!((tr.trans - DVec3::new(-0.01198, -0.05404, -0.29220)).length() < 1e-4);
    }

    #[test]
    fn raw_calib_files_with_text_and_split_rotations() {
        let text = "calib_time: 15-Mar-2012 11:37:16\nR: 7.533745e-03 -9.999714e-01 -6.166020e-04 1.480249e-02 7.280733e-04 -9.998902e-01 9.998621e-01 7.523790e-03 1.480755e-02\nT: -4.069766e-03 -7.631618e-02 -2.717806e-01\ndelta_f: 0.000000e+00 0.000000e+00\n";
        let c = parse_calib(text, "calib_velo_to_cam.txt").unwrap();
        assert_eq!(c.get("calib_time").unwrap().value, "15-Mar-2012 11:37:16");
        let t = c.rigid_rt("R", "T").unwrap();
        assert!((t.trans.z + 0.2717806).abs() < 1e-12);
        // Text is refused only where numbers are asked for, naming the line.
        let e = c.numbers("calib_time").unwrap_err().to_string();
        assert_eq!(
            e,
            "calib_velo_to_cam.txt, line 1: calib_time: value 1 '15-Mar-2012' is not a number"
        );
    }

    #[test]
    fn corrupt_calib_is_refused_with_file_and_line() {
        let err = |text: &str| parse_calib(text, "calib.txt").unwrap_err().to_string();
        assert_eq!(
            err(""),
            "calib.txt: no 'KEY: values' lines (empty calibration file)"
        );
        assert_eq!(
            err("P0: 1 2\n\nP1 1 2 3\n"),
            "calib.txt, line 3: expected 'KEY: values' (no colon)"
        );
        assert!(err("P 0: 1\n").starts_with("calib.txt, line 1: 'P 0' is not a calibration key"));
        assert_eq!(
            err("P0: 1\nTr: 2\nP0: 3\n"),
            "calib.txt, line 3: P0 repeats the entry of line 1"
        );

        let with = |line: &str| {
            let text = CALIB_00.replace(CALIB_00.lines().nth(1).unwrap(), line);
            parse_calib(&text, "seq/calib.txt").unwrap()
        };
        let e = with("P2: 1 0 2 0 0 1 2 0 0 0 1")
            .projection("P2")
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            "seq/calib.txt, line 2: P2 has 11 numbers; a 3 × 4 projection matrix needs 12"
        );
        let e = with("P2: 700 0 600 0 0 700 NaN 0 0 0 1 0")
            .projection("P2")
            .unwrap_err()
            .to_string();
        assert_eq!(e, "seq/calib.txt, line 2: P2: value 7 'NaN' is not finite");
        let e = with("P2: 700 0 600 0 0 700 x 0 0 0 1 0")
            .projection("P2")
            .unwrap_err()
            .to_string();
        assert_eq!(e, "seq/calib.txt, line 2: P2: value 7 'x' is not a number");
        let e = with("P2: 700 0 600 0 0 -700 180 0 0 0 1 0")
            .projection("P2")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("seq/calib.txt, line 2: P2: focal lengths must be positive"),
            "{e}"
        );
        let e = with("P2: 700 3 600 0 0 700 180 0 0 0 1 0")
            .projection("P2")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("seq/calib.txt, line 2: P2: not a rectified pinhole"),
            "{e}"
        );
        let e = with("P2: 700 0 600 0 0 700 180 0 0.1 0 1 0")
            .projection("P2")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("seq/calib.txt, line 2: P2: not a rectified pinhole"),
            "{e}"
        );
        // A scaled rotation block in Tr is not a rigid transform.
        let c = parse_calib("Tr: 2 0 0 0 0 2 0 0 0 0 2 0\n", "calib.txt").unwrap();
        let e = c.rigid("Tr").unwrap_err().to_string();
        assert!(
            e.starts_with("calib.txt, line 1: Tr: rotation block is not orthonormal"),
            "{e}"
        );
        let e = c.projection("P2").unwrap_err().to_string();
        assert_eq!(e, "calib.txt: no 'P2:' line (keys present: Tr)");
    }

    #[test]
    fn times_parse_and_corrupt_times_name_the_line() {
        let t = parse_times(
            "\u{feff}0.000000e+00\n1.037359e-01\n\n2.073381e-01\n",
            "times.txt",
        )
        .unwrap();
        assert_eq!(t, vec![0.0, 0.1037359, 0.2073381]);
        let err = |text: &str| parse_times(text, "00/times.txt").unwrap_err().to_string();
        assert_eq!(err(""), "00/times.txt: no stamps (empty times file)");
        assert_eq!(
            err("0\n0.1 0.2\n"),
            "00/times.txt, line 2: expected one number (seconds) per line"
        );
        assert_eq!(
            err("0\n0.1\nabc\n"),
            "00/times.txt, line 3: stamp 'abc' is not a number"
        );
        assert_eq!(
            err("0\ninf\n"),
            "00/times.txt, line 2: stamp 'inf' is not finite"
        );
        assert_eq!(
            err("0\n0.2\n\n0.1\n"),
            "00/times.txt, line 4: stamp 0.1 is not after 0.2 (line 2); stamps must increase"
        );
        assert!(err("0\n0\n").contains("line 2: stamp 0 is not after 0 (line 1)"));
    }

    #[test]
    fn reads_kitti_records() {
        let bytes = floats(&[1.0, 2.0, 3.0, 0.25, -4.5, 0.0, 1e-3, 1.0]);
        let scan = read_bin_bytes(&bytes, "000000.bin", KITTI_STRIDE).unwrap();
        assert_eq!(scan.skipped, 0);
        assert_eq!(
            scan.cloud.positions,
            vec![
                DVec3::new(1.0, 2.0, 3.0),
                DVec3::new(-4.5, 0.0, 1e-3f32 as f64)
            ]
        );
        assert_eq!(scan.cloud.scalar("intensity").unwrap(), &[0.25, 1.0]);
        assert!(scan.cloud.scalar("ring").is_none());
        assert!(scan.cloud.validate().is_ok());
    }

    #[test]
    fn round_trips_both_strides() {
        let mut cloud = PointCloud::from_positions(vec![
            DVec3::new(0.1, -2.5, 30.0),
            DVec3::new(-80.123456, 0.0, -1.75),
            DVec3::ZERO,
        ]);
        cloud.set_scalar("intensity", vec![0.5, 255.0, 0.0]);
        cloud.set_scalar("ring", vec![0.0, 31.0, 7.0]);
        for stride in [KITTI_STRIDE, NUSCENES_STRIDE] {
            let bytes = write_bin_bytes(&cloud, stride).unwrap();
            assert_eq!(bytes.len(), 3 * 4 * stride);
            let back = read_bin_bytes(&bytes, "x.bin", stride).unwrap();
            assert_eq!(back.skipped, 0);
            for (a, b) in back.cloud.positions.iter().zip(&cloud.positions) {
                // f64 → f32: relative error below 2^-24.
                assert!((*a - *b).abs().max_element() <= 6e-8 * b.abs().max_element().max(1.0));
            }
            assert_eq!(back.cloud.scalar("intensity"), cloud.scalar("intensity"));
            let ring = back.cloud.scalar("ring");
            if stride == NUSCENES_STRIDE {
                assert_eq!(ring, cloud.scalar("ring"));
            } else {
                assert!(ring.is_none());
            }
            // Writing what was read reproduces the bytes.
            assert_eq!(write_bin_bytes(&back.cloud, stride).unwrap(), bytes);
        }
        // Without scalars the extra columns are zero.
        let bare = PointCloud::from_positions(vec![DVec3::new(1.0, 2.0, 3.0)]);
        assert_eq!(
            write_bin_bytes(&bare, NUSCENES_STRIDE).unwrap(),
            floats(&[1.0, 2.0, 3.0, 0.0, 0.0])
        );
    }

    #[test]
    fn odd_lengths_and_strides_are_named_errors() {
        let bytes = floats(&[1.0, 2.0, 3.0, 0.5, 9.0]);
        let e = read_bin_bytes(&bytes, "seq/000042.bin", KITTI_STRIDE)
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("seq/000042.bin: 20 bytes") && e.contains("16-byte"),
            "{e}"
        );
        // The same 20 bytes are one nuScenes point.
        assert_eq!(
            read_bin_bytes(&bytes, "n.pcd.bin", NUSCENES_STRIDE)
                .unwrap()
                .cloud
                .len(),
            1
        );
        for len in [1, 3, 15, 17, 33] {
            assert!(read_bin_bytes(&vec![0u8; len], "a.bin", KITTI_STRIDE).is_err());
        }
        let e = read_bin_bytes(&bytes, "a.bin", 3).unwrap_err().to_string();
        assert!(e.starts_with("a.bin: stride 3"), "{e}");
        assert!(write_bin_bytes(&PointCloud::new(), 6).is_err());
    }

    #[test]
    fn non_finite_points_are_skipped_and_counted() {
        let bytes = floats(&[
            f32::NAN,
            0.0,
            0.0,
            1.0,
            1.0,
            2.0,
            3.0,
            0.5,
            0.0,
            f32::INFINITY,
            0.0,
            1.0,
            4.0,
            5.0,
            6.0,
            f32::NAN, // a NaN intensity keeps the point
        ]);
        let scan = read_bin_bytes(&bytes, "a.bin", KITTI_STRIDE).unwrap();
        assert_eq!(scan.skipped, 2);
        assert_eq!(
            scan.cloud.positions,
            vec![DVec3::new(1.0, 2.0, 3.0), DVec3::new(4.0, 5.0, 6.0)]
        );
        let i = scan.cloud.scalar("intensity").unwrap();
        assert_eq!(i[0], 0.5);
        assert!(i[1].is_nan());
    }

    #[test]
    fn empty_file_is_an_empty_scan() {
        for stride in [KITTI_STRIDE, NUSCENES_STRIDE] {
            let scan = read_bin_bytes(&[], "empty.bin", stride).unwrap();
            assert!(scan.cloud.is_empty());
            assert_eq!(scan.skipped, 0);
            assert_eq!(scan.cloud.scalar("intensity").unwrap().len(), 0);
        }
    }

    #[test]
    fn native_files() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("velodyne/000000.bin");
        let mut cloud = PointCloud::from_positions(vec![DVec3::new(1.0, 2.0, 3.0)]);
        cloud.set_scalar("intensity", vec![0.75]);
        write_bin(&path, &cloud, KITTI_STRIDE).unwrap();
        assert_eq!(std::fs::metadata(&path).unwrap().len(), 16);
        assert_eq!(read_bin(&path, KITTI_STRIDE).unwrap().cloud, cloud);
        let e = read_bin(&dir.path().join("nope.bin"), KITTI_STRIDE)
            .unwrap_err()
            .to_string();
        assert!(e.contains("nope.bin"), "{e}");
    }
}
