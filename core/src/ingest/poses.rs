//! Trajectories from the pose files mapping tools write: TUM, KITTI odometry, Oxford Spires
//! `slam-poses.csv` and EuRoC ground truth, each read into a [`Trajectory`] of `T_world_sensor`.
//!
//! - **TUM** (`t tx ty tz qx qy qz qw`, whitespace separated): the crate's own trajectory format; the parser
//!   and writer live in [`crate::dataset`] and are wrapped here so every format answers to one error type.
//! - **KITTI odometry** (`poses/NN.txt`): one line of 12 numbers per frame, the row-major 3x4 `T_world_cam0`,
//!   with no time at all; stamps come from the sequence's `times.txt` (one number per line) or, when there
//!   is none, from frame index × a given period. The 3x3 blocks are printed with 6-9 digits, so they are
//!   projected onto the nearest rotation (a block farther than [`KITTI_ORTHONORMAL_TOLERANCE`] from
//!   orthonormal, or a reflection, is an error: it is not a pose).
//! - **Oxford Spires** (`slam-poses.csv`, the pose CSV of the Oxford DRS mapping tools): a `# counter, sec, nsec,
//!   x, y, z, qx, qy, qz, qw` header and comma-separated rows, time = sec + nsec·1e-9.
//! - **EuRoC** ground truth (`state_groundtruth_estimate0/data.csv`, Vicon/Leica `data.csv`):
//!   `#timestamp [ns], p_RS_R_x, p_RS_R_y, p_RS_R_z, q_RS_w, q_RS_x, q_RS_y, q_RS_z, ...` with the quaternion
//!   **w first**; velocity and bias columns are ignored.
//!
//! Quaternions are normalised and zero ones refused. Stamps must be finite and strictly increasing: an
//! unsorted or repeated stamp is an error naming both lines, because silently sorting would hide a
//! corrupted or concatenated file. Parsing works on `&str` (browser included); [`read_trajectory`] and the
//! `write_*` functions are thin native wrappers.

use std::path::{Path, PathBuf};

use glam::{DMat3, DQuat, DVec3};
use thiserror::Error;

use crate::dataset::{self, write_atomic, DatasetError};
use crate::geometry::{Se3, Trajectory};

/// Largest `max |RᵀR − I|` accepted for a KITTI rotation block before it is projected onto a rotation.
/// KITTI's own files print 7 significant digits (deviation ~1e-7); 1e-3 still admits hand-rounded files
/// but refuses scaled or sheared matrices.
pub const KITTI_ORTHONORMAL_TOLERANCE: f64 = 1e-3;

/// Trajectory read errors; every variant names the file.
#[derive(Debug, Error)]
pub enum PoseError {
    #[error("{file}: {source}")]
    Io {
        file: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{file}, line {line}: {reason}")]
    Line {
        file: String,
        line: usize,
        reason: String,
    },
    #[error("{file}: {reason}")]
    Invalid { file: String, reason: String },
    /// TUM parse errors (from [`crate::dataset::parse_tum`], already naming file and line) and write errors.
    #[error(transparent)]
    Dataset(#[from] DatasetError),
}

/// The pose file formats this module reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PoseFormat {
    Tum,
    Kitti,
    Spires,
    Euroc,
}

/// Where KITTI stamps come from.
#[derive(Clone, Copy, Debug)]
pub enum KittiTimes<'a> {
    /// The text of the sequence's `times.txt` (one number per line) and its name for errors.
    Text { text: &'a str, name: &'a str },
    /// No times file: frame `i` is at `i × period` seconds.
    Period(f64),
}

fn line_err(file: &str, line: usize, reason: String) -> PoseError {
    PoseError::Line {
        file: file.to_string(),
        line,
        reason,
    }
}

fn invalid(file: &str, reason: String) -> PoseError {
    PoseError::Invalid {
        file: file.to_string(),
        reason,
    }
}

/// Non-blank, non-`#` lines with their 1-based numbers, a leading byte-order mark removed.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.strip_prefix('\u{feff}')
        .unwrap_or(text)
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

fn finite(tok: &str, what: &str) -> Result<f64, String> {
    match tok.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        Ok(_) => Err(format!("{what} '{tok}' is not finite")),
        Err(_) => Err(format!("{what} '{tok}' is not a number")),
    }
}

/// Comma-separated fields of a CSV row, trimmed.
fn csv_fields(line: &str) -> Vec<&str> {
    line.split(',').map(str::trim).collect()
}

/// `q` normalised, or an error for a zero quaternion.
fn unit_quat(q: DQuat) -> Result<DQuat, String> {
    if q.length() < 1e-6 {
        return Err(format!(
            "zero quaternion (x={}, y={}, z={}, w={})",
            q.x, q.y, q.z, q.w
        ));
    }
    Ok(q.normalize())
}

/// Stamps checked as they are read, so the error names the offending line and the one before it.
struct Stamps {
    stamps: Vec<f64>,
    last_line: usize,
}

impl Stamps {
    fn new() -> Self {
        Self {
            stamps: Vec::new(),
            last_line: 0,
        }
    }

    fn push(&mut self, file: &str, line: usize, t: f64) -> Result<(), PoseError> {
        if let Some(&prev) = self.stamps.last() {
            if t <= prev {
                let what = if t == prev {
                    "repeats"
                } else {
                    "goes back from"
                };
                return Err(line_err(
                    file,
                    line,
                    format!(
                        "stamp {t} {what} {prev} (line {}); stamps must be strictly increasing",
                        self.last_line
                    ),
                ));
            }
        }
        self.stamps.push(t);
        self.last_line = line;
        Ok(())
    }
}

fn trajectory(file: &str, stamps: Vec<f64>, poses: Vec<Se3>) -> Result<Trajectory, PoseError> {
    if poses.is_empty() {
        return Err(invalid(file, "no poses in the file".into()));
    }
    Trajectory::new(stamps, poses).map_err(|e| invalid(file, e.to_string()))
}

/// Parses TUM text (`t tx ty tz qx qy qz qw`) with [`crate::dataset::parse_tum`]; `name` is used in
/// errors. An unsorted stamp is reported with its line before the full parse.
pub fn parse_tum(text: &str, name: &str) -> Result<Trajectory, PoseError> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut stamps = Stamps::new();
    for (n, line) in data_lines(text) {
        // Lines whose stamp does not parse are left to parse_tum's own message.
        let stamp = line
            .split_whitespace()
            .next()
            .and_then(|t| t.parse::<f64>().ok());
        if let Some(t) = stamp.filter(|t| t.is_finite()) {
            stamps.push(name, n, t)?;
        }
    }
    Ok(dataset::parse_tum(text, Path::new(name))?)
}

/// TUM text of a trajectory ([`crate::dataset::tum_string`]: nanosecond stamps, 9 decimals).
pub fn tum_string(traj: &Trajectory) -> String {
    dataset::tum_string(traj.stamps(), traj.poses())
}

fn max_abs(m: DMat3) -> f64 {
    m.to_cols_array().iter().fold(0.0, |a, v| a.max(v.abs()))
}

/// The rotation nearest (Frobenius) to an almost-orthonormal block, or why the block is not a rotation
/// (also used for KITTI's calibration matrices, [`super::kitti::Calib::rigid`]).
pub(crate) fn nearest_rotation(m: DMat3) -> Result<DQuat, String> {
    let dev = max_abs(m.transpose() * m - DMat3::IDENTITY);
    if dev > KITTI_ORTHONORMAL_TOLERANCE {
        return Err(format!(
            "rotation block is not orthonormal (max |RᵀR − I| = {dev:.3e} > {KITTI_ORTHONORMAL_TOLERANCE:e})"
        ));
    }
    let det = m.determinant();
    if det <= 0.0 {
        return Err(format!(
            "rotation block has determinant {det}: a reflection, not a rotation"
        ));
    }
    // Newton iteration towards the orthogonal polar factor, R ← (R + R⁻ᵀ)/2: quadratic convergence from
    // this close, and the polar factor is the nearest rotation when det > 0.
    let mut r = m;
    for _ in 0..8 {
        let next = (r + r.inverse().transpose()) * 0.5;
        let step = max_abs(next - r);
        r = next;
        if step < 1e-15 {
            break;
        }
    }
    Ok(DQuat::from_mat3(&r).normalize())
}

fn kitti_line(line: &str) -> Result<Se3, String> {
    let mut v = [0.0; 12];
    let mut toks = line.split_whitespace();
    for (i, slot) in v.iter_mut().enumerate() {
        let tok = toks
            .next()
            .ok_or_else(|| format!("{i} numbers, expected 12 (row-major 3x4 [R|t])"))?;
        *slot = finite(tok, &format!("value {}", i + 1))?;
    }
    if toks.next().is_some() {
        let n = 13 + toks.count();
        return Err(format!("{n} numbers, expected 12 (row-major 3x4 [R|t])"));
    }
    let [r00, r01, r02, tx, r10, r11, r12, ty, r20, r21, r22, tz] = v;
    let r = DMat3::from_cols(
        DVec3::new(r00, r10, r20),
        DVec3::new(r01, r11, r21),
        DVec3::new(r02, r12, r22),
    );
    Ok(Se3::new(nearest_rotation(r)?, DVec3::new(tx, ty, tz)))
}

/// Parses KITTI odometry poses (12 numbers per line, `T_world_cam0`, world = the first camera) with stamps
/// from `times`; `name` is used in errors. Blank and `#` lines are skipped.
pub fn parse_kitti(text: &str, name: &str, times: KittiTimes) -> Result<Trajectory, PoseError> {
    let mut poses = Vec::new();
    for (n, line) in data_lines(text) {
        poses.push(kitti_line(line).map_err(|r| line_err(name, n, r))?);
    }
    if poses.is_empty() {
        return Err(invalid(name, "no poses in the file".into()));
    }
    let stamps = match times {
        KittiTimes::Period(period) => {
            if !(period.is_finite() && period > 0.0) {
                return Err(invalid(
                    name,
                    format!("frame period {period} must be finite and positive"),
                ));
            }
            (0..poses.len()).map(|i| i as f64 * period).collect()
        }
        KittiTimes::Text {
            text: times_text,
            name: times_name,
        } => {
            let mut stamps = Stamps::new();
            for (n, line) in data_lines(times_text) {
                let mut toks = line.split_whitespace();
                let (Some(tok), None) = (toks.next(), toks.next()) else {
                    return Err(line_err(
                        times_name,
                        n,
                        "expected one number (seconds) per line".into(),
                    ));
                };
                let t = finite(tok, "stamp").map_err(|r| line_err(times_name, n, r))?;
                stamps.push(times_name, n, t)?;
                if stamps.stamps.len() > poses.len() {
                    break;
                }
            }
            if stamps.stamps.len() != poses.len() {
                let more = if stamps.stamps.len() > poses.len() {
                    "more"
                } else {
                    "fewer"
                };
                return Err(invalid(
                    times_name,
                    format!("{more} stamps than the {} poses of {name}", poses.len()),
                ));
            }
            stamps.stamps
        }
    };
    trajectory(name, stamps, poses)
}

/// KITTI pose text: one row-major 3x4 `[R|t]` per line, numbers in shortest round-trip `e` notation.
pub fn kitti_string(traj: &Trajectory) -> String {
    let mut s = String::new();
    for p in traj.poses() {
        let r = p.rotation_matrix();
        let t = p.trans;
        for (i, row) in [r.row(0), r.row(1), r.row(2)].iter().enumerate() {
            let sep = if i == 0 { "" } else { " " };
            s.push_str(&format!(
                "{sep}{:e} {:e} {:e} {:e}",
                row.x, row.y, row.z, t[i]
            ));
        }
        s.push('\n');
    }
    s
}

/// KITTI `times.txt` text: one stamp (seconds) per line.
pub fn kitti_times_string(traj: &Trajectory) -> String {
    traj.stamps().iter().map(|t| format!("{t:e}\n")).collect()
}

/// Seconds from whole seconds and nanoseconds, without losing the nanoseconds to a large sum first.
fn sec_nsec(sec: i64, nsec: u64) -> f64 {
    sec as f64 + nsec as f64 * 1e-9
}

fn spires_line(line: &str) -> Result<(f64, Se3), String> {
    let f = csv_fields(line);
    let Ok([_counter, sec, nsec, x, y, z, qx, qy, qz, qw]) = <[&str; 10]>::try_from(f.as_slice())
    else {
        return Err(format!(
            "{} fields, expected 10 (counter, sec, nsec, x, y, z, qx, qy, qz, qw)",
            f.len()
        ));
    };
    let sec = sec
        .parse::<i64>()
        .map_err(|_| format!("sec '{sec}' is not an integer"))?;
    let nsec = match nsec.parse::<u64>() {
        Ok(v) if v < 1_000_000_000 => v,
        _ => return Err(format!("nsec '{nsec}' is not an integer in 0..1e9")),
    };
    let q = DQuat::from_xyzw(
        finite(qx, "qx")?,
        finite(qy, "qy")?,
        finite(qz, "qz")?,
        finite(qw, "qw")?,
    );
    let trans = DVec3::new(finite(x, "x")?, finite(y, "y")?, finite(z, "z")?);
    Ok((sec_nsec(sec, nsec), Se3::new(unit_quat(q)?, trans)))
}

/// Parses an Oxford Spires `slam-poses.csv` (`counter, sec, nsec, x, y, z, qx, qy, qz, qw`); the counter
/// is not used. `name` is used in errors.
pub fn parse_spires(text: &str, name: &str) -> Result<Trajectory, PoseError> {
    let mut stamps = Stamps::new();
    let mut poses = Vec::new();
    for (n, line) in data_lines(text) {
        let (t, pose) = spires_line(line).map_err(|r| line_err(name, n, r))?;
        stamps.push(name, n, t)?;
        poses.push(pose);
    }
    trajectory(name, stamps.stamps, poses)
}

/// Oxford Spires CSV text with its header. Stamps are split into whole seconds and rounded nanoseconds, so
/// stamps closer than a nanosecond would collide.
pub fn spires_string(traj: &Trajectory) -> String {
    let mut s = String::from("# counter, sec, nsec, x, y, z, qx, qy, qz, qw\n");
    for (i, (t, p)) in traj.stamps().iter().zip(traj.poses()).enumerate() {
        let mut sec = t.floor();
        let mut nsec = ((t - sec) * 1e9).round();
        if nsec >= 1e9 {
            sec += 1.0;
            nsec -= 1e9;
        }
        let (q, x) = (p.rot, p.trans);
        s.push_str(&format!(
            "{i}, {}, {}, {}, {}, {}, {}, {}, {}, {}\n",
            sec as i64, nsec as u64, x.x, x.y, x.z, q.x, q.y, q.z, q.w
        ));
    }
    s
}

fn euroc_line(line: &str) -> Result<(f64, Se3), String> {
    let f = csv_fields(line);
    let Some([ns, x, y, z, qw, qx, qy, qz]) = f.first_chunk::<8>() else {
        return Err(format!(
            "{} fields, expected at least 8 (timestamp [ns], p x y z, q w x y z)",
            f.len()
        ));
    };
    let ns = ns
        .parse::<u64>()
        .map_err(|_| format!("timestamp '{ns}' is not an integer of nanoseconds"))?;
    let q = DQuat::from_xyzw(
        finite(qx, "q_x")?,
        finite(qy, "q_y")?,
        finite(qz, "q_z")?,
        finite(qw, "q_w")?,
    );
    let trans = DVec3::new(finite(x, "p_x")?, finite(y, "p_y")?, finite(z, "p_z")?);
    let t = sec_nsec((ns / 1_000_000_000) as i64, ns % 1_000_000_000);
    Ok((t, Se3::new(unit_quat(q)?, trans)))
}

/// Parses a EuRoC ground-truth `data.csv` (`timestamp [ns], p x y z, q w x y z, ...`; extra columns
/// ignored) into `T_R_S` (sensor body in the reference frame). `name` is used in errors.
pub fn parse_euroc(text: &str, name: &str) -> Result<Trajectory, PoseError> {
    let mut stamps = Stamps::new();
    let mut poses = Vec::new();
    for (n, line) in data_lines(text) {
        let (t, pose) = euroc_line(line).map_err(|r| line_err(name, n, r))?;
        stamps.push(name, n, t)?;
        poses.push(pose);
    }
    trajectory(name, stamps.stamps, poses)
}

/// Guesses the format from the leading `#` header, then the file name, then the shape of the first data
/// line (comma-separated: 10 fields Spires, 8 or more EuRoC; whitespace-separated: 8 numbers TUM, 12 KITTI).
/// `None` when nothing fits.
pub fn detect_format(name: &str, text: &str) -> Option<PoseFormat> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let header = text
        .lines()
        .map(str::trim)
        .take_while(|l| l.is_empty() || l.starts_with('#'))
        .take(64);
    for line in header {
        let l = line.to_ascii_lowercase();
        if l.contains("counter") && l.contains("nsec") {
            return Some(PoseFormat::Spires);
        }
        if l.contains("p_rs_r") || l.contains("q_rs_w") || l.contains("timestamp [ns]") {
            return Some(PoseFormat::Euroc);
        }
        if l.contains("tx ty tz qx qy qz qw") {
            return Some(PoseFormat::Tum);
        }
    }
    let base = name
        .rsplit(['/', '\\'])
        .next()
        .unwrap_or(name)
        .to_ascii_lowercase();
    match base.as_str() {
        "slam-poses.csv" | "slam_poses.csv" => return Some(PoseFormat::Spires),
        "data.csv" => return Some(PoseFormat::Euroc),
        b if b.ends_with(".tum") => return Some(PoseFormat::Tum),
        _ => {}
    }
    let (_, first) = data_lines(text).next()?;
    if first.contains(',') {
        match first.split(',').count() {
            10 => Some(PoseFormat::Spires),
            n if n >= 8 => Some(PoseFormat::Euroc),
            _ => None,
        }
    } else {
        match first.split_whitespace().count() {
            8 => Some(PoseFormat::Tum),
            12 => Some(PoseFormat::Kitti),
            _ => None,
        }
    }
}

fn read_text(path: &Path) -> Result<String, PoseError> {
    std::fs::read_to_string(path).map_err(|source| PoseError::Io {
        file: path.display().to_string(),
        source,
    })
}

/// The `times.txt` of a KITTI pose file: next to it, or where the odometry layout puts it
/// (`poses/NN.txt` → `sequences/NN/times.txt`).
pub fn kitti_times_path(poses: &Path) -> Option<PathBuf> {
    let beside = poses.with_file_name("times.txt");
    if beside.is_file() {
        return Some(beside);
    }
    let stem = poses.file_stem()?;
    let layout = poses
        .parent()?
        .parent()?
        .join("sequences")
        .join(stem)
        .join("times.txt");
    layout.is_file().then_some(layout)
}

/// Reads KITTI poses with stamps from [`kitti_times_path`], or from `period` (seconds per frame) when no
/// `times.txt` is found; neither is an error, since inventing a rate silently would mis-time every frame.
pub fn read_kitti(poses: &Path, period: Option<f64>) -> Result<Trajectory, PoseError> {
    let name = poses.display().to_string();
    let text = read_text(poses)?;
    match (kitti_times_path(poses), period) {
        (Some(times), _) => {
            let times_name = times.display().to_string();
            let times_text = read_text(&times)?;
            parse_kitti(
                &text,
                &name,
                KittiTimes::Text {
                    text: &times_text,
                    name: &times_name,
                },
            )
        }
        (None, Some(period)) => parse_kitti(&text, &name, KittiTimes::Period(period)),
        (None, None) => Err(invalid(
            &name,
            "KITTI poses carry no stamps and no times.txt was found next to them or in \
             ../sequences/<name>/; give a frame period"
                .into(),
        )),
    }
}

/// Reads a trajectory file in any of the formats, chosen by [`detect_format`] (KITTI as in [`read_kitti`]
/// without a period).
pub fn read_trajectory(path: &Path) -> Result<Trajectory, PoseError> {
    let name = path.display().to_string();
    let text = read_text(path)?;
    match detect_format(&name, &text) {
        Some(PoseFormat::Tum) => parse_tum(&text, &name),
        Some(PoseFormat::Kitti) => read_kitti(path, None),
        Some(PoseFormat::Spires) => parse_spires(&text, &name),
        Some(PoseFormat::Euroc) => parse_euroc(&text, &name),
        None => Err(invalid(
            &name,
            "unknown pose format: expected TUM (8 numbers per line), KITTI (12), Oxford Spires CSV \
             (counter, sec, nsec, x, y, z, qx, qy, qz, qw) or EuRoC CSV (timestamp [ns], p xyz, q wxyz)"
                .into(),
        )),
    }
}

/// Writes KITTI poses and their `times.txt`, each through a temporary file and a rename.
pub fn write_kitti(poses: &Path, times: &Path, traj: &Trajectory) -> Result<(), PoseError> {
    write_atomic(poses, kitti_string(traj).as_bytes())?;
    write_atomic(times, kitti_times_string(traj).as_bytes())?;
    Ok(())
}

/// Writes an Oxford Spires CSV through a temporary file and a rename.
pub fn write_spires(path: &Path, traj: &Trajectory) -> Result<(), PoseError> {
    Ok(write_atomic(path, spires_string(traj).as_bytes())?)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Trajectory {
        let stamps = vec![1710338055.1234567, 1710338055.2234567, 1710338056.0];
        let poses = vec![
            Se3::IDENTITY,
            Se3::new(
                DQuat::from_euler(glam::EulerRot::ZYX, 0.3, -0.2, 1.1),
                DVec3::new(1.5, -2.25, 0.125),
            ),
            Se3::new(
                DQuat::from_euler(glam::EulerRot::ZYX, -2.9, 1.2, 0.01),
                DVec3::new(-1234.5678901234, 1e-9, 42.0),
            ),
        ];
        Trajectory::new(stamps, poses).unwrap()
    }

    fn assert_close(a: &Trajectory, b: &Trajectory, stamp_tol: f64, tol: f64) {
        assert_eq!(a.len(), b.len());
        for (x, y) in a.stamps().iter().zip(b.stamps()) {
            assert!((x - y).abs() <= stamp_tol, "stamp {x} vs {y}");
        }
        for (p, q) in a.poses().iter().zip(b.poses()) {
            assert!(p.distance_to(q) <= tol, "{p:?} vs {q:?}");
            assert!(p.angle_to(q) <= tol, "{p:?} vs {q:?}");
        }
    }

    fn message(r: Result<Trajectory, PoseError>) -> String {
        r.unwrap_err().to_string()
    }

    #[test]
    fn round_trips() {
        let t = sample();
        // TUM writes 9 decimals.
        assert_close(
            &t,
            &parse_tum(&tum_string(&t), "t.txt").unwrap(),
            1e-6,
            1e-8,
        );
        // KITTI and Spires write shortest round-trip numbers; Spires stamps are whole nanoseconds, and at
        // 1.7e9 s an f64 stamp resolves 2.4e-7 s.
        let kitti = parse_kitti(
            &kitti_string(&t),
            "00.txt",
            KittiTimes::Text {
                text: &kitti_times_string(&t),
                name: "times.txt",
            },
        )
        .unwrap();
        assert_close(&t, &kitti, 0.0, 1e-12);
        assert_close(
            &t,
            &parse_spires(&spires_string(&t), "s.csv").unwrap(),
            5e-7,
            1e-12,
        );
        assert!(spires_string(&t).contains("\n0, 1710338055, 123456"));
        // Negative stamps split into floor seconds and positive nanoseconds.
        let neg = Trajectory::new(vec![-1.25, 0.5], vec![Se3::IDENTITY; 2]).unwrap();
        assert!(spires_string(&neg).contains("0, -2, 750000000,"));
        assert_close(
            &neg,
            &parse_spires(&spires_string(&neg), "n").unwrap(),
            1e-12,
            0.0,
        );
    }

    #[test]
    fn reads_hand_written_tum() {
        let text =
            "\u{feff}# timestamp tx ty tz qx qy qz qw\n\n1.0 1 2 3 0 0 0 2\n2.5 0 0 0 0 0 1 0\n";
        let t = parse_tum(text, "gt.txt").unwrap();
        assert_eq!(t.stamps(), &[1.0, 2.5]);
        assert_eq!(t.poses()[0].trans, DVec3::new(1.0, 2.0, 3.0));
        assert_eq!(t.poses()[0].rot, DQuat::IDENTITY);
        let e = message(parse_tum(
            "1 0 0 0 0 0 0 1\n# c\n1 0 0 0 0 0 0 1\n",
            "gt.txt",
        ));
        assert!(
            e.starts_with("gt.txt, line 3:") && e.contains("repeats") && e.contains("line 1"),
            "{e}"
        );
        let e = message(parse_tum("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 0\n", "gt.txt"));
        assert!(
            e.contains("gt.txt") && e.contains("line 2") && e.contains("zero quaternion"),
            "{e}"
        );
        let e = message(parse_tum("1 0 0 0 0 0 0\n", "gt.txt"));
        assert!(e.contains("gt.txt") && e.contains("line 1"), "{e}");
    }

    const KITTI: &str = "\
1.000000e+00 9.043680e-12 2.326809e-11 5.551115e-17 9.043683e-12 1.000000e+00 2.392370e-10 3.330669e-16 2.326810e-11 2.392370e-10 9.999999e-01 -4.440892e-16
9.999978e-01 5.272628e-04 -2.066935e-03 -4.690294e-02 -5.296506e-04 9.999992e-01 -1.154865e-03 -2.839928e-02 2.066324e-03 1.155958e-03 9.999971e-01 8.586941e-01
";

    #[test]
    fn reads_hand_written_kitti() {
        let times = "0.000000e+00\n1.036594e-01\n";
        let t = parse_kitti(
            KITTI,
            "00.txt",
            KittiTimes::Text {
                text: times,
                name: "times.txt",
            },
        )
        .unwrap();
        assert_eq!(t.stamps(), &[0.0, 0.1036594]);
        let p = t.poses()[1];
        assert!(
            (p.trans - DVec3::new(-4.690294e-02, -2.839928e-02, 8.586941e-01)).length() < 1e-15
        );
        // Re-orthonormalised: an exact rotation within the file's precision of the printed block.
        let r = p.rotation_matrix();
        assert!(max_abs(r.transpose() * r - DMat3::IDENTITY) < 1e-14);
        assert!(
            (r.x_axis.x - 9.999978e-01).abs() < 1e-6 && (r.y_axis.x - 5.272628e-04).abs() < 1e-6
        );
        assert!((p.rot.length() - 1.0).abs() < 1e-15);

        let t = parse_kitti(KITTI, "00.txt", KittiTimes::Period(0.1)).unwrap();
        assert_eq!(t.stamps(), &[0.0, 0.1]);
    }

    #[test]
    fn kitti_rotations_are_projected_or_refused() {
        let row = |r: DMat3| {
            let v = [
                r.x_axis.x, r.y_axis.x, r.z_axis.x, 0.0, r.x_axis.y, r.y_axis.y, r.z_axis.y, 0.0,
                r.x_axis.z, r.y_axis.z, r.z_axis.z, 0.0,
            ];
            let line = v.map(|x| x.to_string()).join(" ");
            parse_kitti(&line, "p.txt", KittiTimes::Period(1.0))
        };
        let exact = DMat3::from_quat(DQuat::from_euler(glam::EulerRot::ZYX, 0.4, 0.3, -0.2));
        // A perturbation of 1e-5 is projected onto the nearest rotation (well within 1e-5 of it).
        let noisy =
            exact + DMat3::from_cols_array(&[1e-5, -2e-5, 0.0, 0.5e-5, 0.0, 1e-5, 0.0, 0.0, -1e-5]);
        let p = row(noisy).unwrap().poses()[0];
        let r = p.rotation_matrix();
        assert!(max_abs(r.transpose() * r - DMat3::IDENTITY) < 1e-14);
        assert!(max_abs(r - noisy) < 3e-5 && max_abs(r - exact) < 3e-5);
        let e = message(row(exact * 1.01));
        assert!(
            e.starts_with("p.txt, line 1:") && e.contains("not orthonormal"),
            "{e}"
        );
        let e = message(row(exact * DMat3::from_diagonal(DVec3::new(1.0, 1.0, -1.0))));
        assert!(e.contains("reflection"), "{e}");
    }

    #[test]
    fn malformed_kitti_is_refused() {
        let p = KittiTimes::Period(0.1);
        let e = message(parse_kitti("1 0 0 0 0 1 0 0 0 0 1\n", "00.txt", p));
        assert!(
            e.starts_with("00.txt, line 1:") && e.contains("11 numbers, expected 12"),
            "{e}"
        );
        let e = message(parse_kitti("1 0 0 0 0 1 0 0 0 0 1 0 5 6\n", "00.txt", p));
        assert!(e.contains("14 numbers"), "{e}");
        let e = message(parse_kitti("1 0 0 0\n\n0 1 0 0 0 0 NaN 0\n", "00.txt", p));
        assert!(e.starts_with("00.txt, line 1:"), "{e}");
        let e = message(parse_kitti("1 0 0 0 0 1 0 0 0 0 1 x\n", "00.txt", p));
        assert!(e.contains("value 12 'x' is not a number"), "{e}");
        let e = message(parse_kitti("", "00.txt", p));
        assert!(e.contains("no poses"), "{e}");
        let e = message(parse_kitti(KITTI, "00.txt", KittiTimes::Period(0.0)));
        assert!(e.contains("period"), "{e}");
        let e = message(parse_kitti(KITTI, "00.txt", KittiTimes::Period(f64::NAN)));
        assert!(e.contains("period"), "{e}");
        let times = |text| KittiTimes::Text {
            text,
            name: "times.txt",
        };
        let e = message(parse_kitti(KITTI, "00.txt", times("0\n")));
        assert!(
            e.starts_with("times.txt:") && e.contains("fewer stamps than the 2 poses of 00.txt"),
            "{e}"
        );
        let e = message(parse_kitti(KITTI, "00.txt", times("0\n1\n2\n")));
        assert!(e.contains("more stamps"), "{e}");
        let e = message(parse_kitti(KITTI, "00.txt", times("0.5\n0.5\n")));
        assert!(
            e.starts_with("times.txt, line 2:") && e.contains("repeats"),
            "{e}"
        );
        let e = message(parse_kitti(KITTI, "00.txt", times("0.5\n0.4\n")));
        assert!(e.contains("goes back"), "{e}");
        let e = message(parse_kitti(KITTI, "00.txt", times("0 1\n1\n")));
        assert!(
            e.starts_with("times.txt, line 1:") && e.contains("one number"),
            "{e}"
        );
        let e = message(parse_kitti(KITTI, "00.txt", times("0\ninf\n")));
        assert!(e.contains("not finite"), "{e}");
    }

    const SPIRES: &str = "\
# counter, sec, nsec, x, y, z, qx, qy, qz, qw
0, 1710338055, 599885000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0
1, 1710338055, 699885000, 0.1, -0.2, 0.3, 0.0, 0.0, 0.3826834, 0.9238795
2, 1710338056, 5, 1, 2, 3, 0, 0, 0, 2
";

    #[test]
    fn reads_hand_written_spires() {
        let t = parse_spires(SPIRES, "slam-poses.csv").unwrap();
        assert_eq!(t.len(), 3);
        assert!((t.stamps()[0] - 1710338055.599885).abs() < 1e-6);
        assert!((t.stamps()[2] - 1710338056.0).abs() < 1e-6);
        assert_eq!(t.poses()[1].trans, DVec3::new(0.1, -0.2, 0.3));
        // 45° about z, normalised; the last row's (0, 0, 0, 2) becomes the identity.
        assert!((t.poses()[1].rot.to_axis_angle().1 - std::f64::consts::FRAC_PI_4).abs() < 1e-6);
        assert!((t.poses()[1].rot.length() - 1.0).abs() < 1e-15);
        assert_eq!(t.poses()[2].rot, DQuat::IDENTITY);

        let err = |text: &str| message(parse_spires(text, "slam-poses.csv"));
        let e = err("0, 1, 0, 0, 0, 0, 0, 0, 0\n");
        assert!(
            e.starts_with("slam-poses.csv, line 1:") && e.contains("9 fields"),
            "{e}"
        );
        let e = err("# h\n0, 1, 1000000000, 0, 0, 0, 0, 0, 0, 1\n");
        assert!(
            e.starts_with("slam-poses.csv, line 2:") && e.contains("nsec"),
            "{e}"
        );
        let e = err("0, 1.5, 0, 0, 0, 0, 0, 0, 0, 1\n");
        assert!(e.contains("sec '1.5'"), "{e}");
        let e = err("0, 1, 0, 0, 0, 0, 0, 0, 0, 0\n");
        assert!(e.contains("zero quaternion"), "{e}");
        let e = err("0, 1, 0, 0, nan, 0, 0, 0, 0, 1\n");
        assert!(e.contains("y 'nan' is not finite"), "{e}");
        let e = err("0, 2, 0, 0, 0, 0, 0, 0, 0, 1\n1, 1, 999999999, 0, 0, 0, 0, 0, 0, 1\n");
        assert!(
            e.starts_with("slam-poses.csv, line 2:") && e.contains("goes back"),
            "{e}"
        );
        let e = err("# only a header\n");
        assert!(e.contains("no poses"), "{e}");
    }

    const EUROC: &str = "\
#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]
1403636580838555648,4.688319,-1.786938,0.783338,0.534108,-0.153029,-0.827383,-0.082152,-0.027876,0.033207,0.800006,-0.003172,0.021267,0.078502,-0.025266,0.136696,0.075593
1403636580843555328,4.688177,-1.786770,0.787350,0.534250,-0.152930,-0.827312,-0.082180,-0.029510,0.034077,0.802941,-0.003172,0.021267,0.078502,-0.025266,0.136696,0.075593
";

    #[test]
    fn reads_hand_written_euroc() {
        let t = parse_euroc(EUROC, "mav0/state_groundtruth_estimate0/data.csv").unwrap();
        assert_eq!(t.len(), 2);
        assert!((t.stamps()[0] - 1403636580.8385556).abs() < 1e-6);
        assert!((t.stamps()[1] - t.stamps()[0] - 0.00499968).abs() < 1e-6);
        let p = t.poses()[0];
        assert_eq!(p.trans, DVec3::new(4.688319, -1.786938, 0.783338));
        // w first in the file.
        let q = DQuat::from_xyzw(-0.153029, -0.827383, -0.082152, 0.534108).normalize();
        assert!(p.rot.angle_between(q) < 1e-12);
        // A Vicon-style file has only the 8 pose columns.
        let t = parse_euroc(
            "#timestamp [ns],x,y,z,qw,qx,qy,qz\n5,1,2,3,1,0,0,0\n",
            "data.csv",
        )
        .unwrap();
        assert!((t.stamps()[0] - 5e-9).abs() < 1e-20);

        let err = |text: &str| message(parse_euroc(text, "data.csv"));
        let e = err("#timestamp [ns],filename\n1403636579758555392,1403636579758555392.png\n");
        assert!(
            e.starts_with("data.csv, line 2:") && e.contains("2 fields"),
            "{e}"
        );
        let e = err("1.5,1,2,3,1,0,0,0\n");
        assert!(e.contains("timestamp '1.5'"), "{e}");
        let e = err("5,1,2,3,0,0,0,0\n");
        assert!(e.contains("zero quaternion"), "{e}");
        let e = err("5,1,2,3,1,0,0,0\n5,1,2,3,1,0,0,0\n");
        assert!(e.contains("line 2") && e.contains("repeats"), "{e}");
        let e = err("5,1,,3,1,0,0,0\n");
        assert!(e.contains("p_y '' is not a number"), "{e}");
    }

    #[test]
    fn detects_formats() {
        use PoseFormat::*;
        assert_eq!(
            detect_format("x/slam-poses.csv", "0, 1, 2, 0, 0, 0, 0, 0, 0, 1"),
            Some(Spires)
        );
        assert_eq!(detect_format("poses.csv", SPIRES), Some(Spires));
        assert_eq!(detect_format("gt.csv", EUROC), Some(Euroc));
        assert_eq!(detect_format("mav0\\vicon0\\data.csv", ""), Some(Euroc));
        assert_eq!(
            detect_format("poses.txt", &tum_string(&sample())),
            Some(Tum)
        );
        assert_eq!(detect_format("run.tum", "1 2 3"), Some(Tum));
        assert_eq!(detect_format("00.txt", KITTI), Some(Kitti));
        assert_eq!(detect_format("est.txt", "1 0 0 0 0 0 0 1\n"), Some(Tum));
        assert_eq!(
            detect_format("a.csv", "0,1,2,0,0,0,0,0,0,1\n"),
            Some(Spires)
        );
        assert_eq!(detect_format("a.csv", "5,1,2,3,1,0,0,0,9\n"), Some(Euroc));
        assert_eq!(detect_format("a.txt", "1 2 3\n"), None);
        assert_eq!(detect_format("a.txt", ""), None);
    }

    #[test]
    fn arbitrary_text_never_panics() {
        // Cheap deterministic fuzz: mutate the sample files character by character.
        let kitti_times = kitti_times_string(&sample());
        let tum = tum_string(&sample());
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        for base in [KITTI, SPIRES, EUROC, tum.as_str(), kitti_times.as_str()] {
            for _ in 0..300 {
                let mut b = base.as_bytes().to_vec();
                for _ in 0..4 {
                    state ^= state << 13;
                    state ^= state >> 7;
                    state ^= state << 17;
                    let i = (state % b.len() as u64) as usize;
                    let alphabet = b" ,-.0123456789e#\nNaix";
                    b[i] = alphabet[(state >> 32) as usize % alphabet.len()];
                }
                let text = String::from_utf8_lossy(&b);
                let _ = detect_format("f", &text);
                let _ = parse_tum(&text, "f");
                let _ = parse_spires(&text, "f");
                let _ = parse_euroc(&text, "f");
                let _ = parse_kitti(&text, "f", KittiTimes::Period(0.1));
                let times = KittiTimes::Text {
                    text: &text,
                    name: "t",
                };
                let _ = parse_kitti(KITTI, "f", times);
            }
        }
    }

    #[test]
    fn native_files() {
        let dir = tempfile::tempdir().unwrap();
        let t = sample();
        // KITTI odometry layout: poses/00.txt with sequences/00/times.txt.
        let poses = dir.path().join("dataset/poses/00.txt");
        let times = dir.path().join("dataset/sequences/00/times.txt");
        write_kitti(&poses, &times, &t).unwrap();
        assert_eq!(kitti_times_path(&poses), Some(times.clone()));
        assert_close(&t, &read_trajectory(&poses).unwrap(), 0.0, 1e-12);
        // Without times.txt: a period is needed.
        std::fs::remove_file(&times).unwrap();
        let e = message(read_trajectory(&poses));
        assert!(e.contains("00.txt") && e.contains("period"), "{e}");
        let by_period = read_kitti(&poses, Some(0.1)).unwrap();
        assert_eq!(by_period.stamps(), &[0.0, 0.1, 0.2]);
        // times.txt next to the poses wins.
        std::fs::write(poses.with_file_name("times.txt"), "1\n2\n3\n").unwrap();
        assert_eq!(
            read_kitti(&poses, Some(0.1)).unwrap().stamps(),
            &[1.0, 2.0, 3.0]
        );

        let spires = dir.path().join("slam-poses.csv");
        write_spires(&spires, &t).unwrap();
        assert_close(&t, &read_trajectory(&spires).unwrap(), 5e-7, 1e-12);
        let euroc = dir.path().join("data.csv");
        std::fs::write(&euroc, EUROC).unwrap();
        assert_eq!(read_trajectory(&euroc).unwrap().len(), 2);
        let unknown = dir.path().join("what.txt");
        std::fs::write(&unknown, "1 2 3\n").unwrap();
        let e = message(read_trajectory(&unknown));
        assert!(
            e.contains("what.txt") && e.contains("unknown pose format"),
            "{e}"
        );
        let e = message(read_trajectory(&dir.path().join("missing.txt")));
        assert!(e.contains("missing.txt"), "{e}");
    }
}
