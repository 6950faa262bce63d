//! COLMAP's text model (`cameras.txt`, `images.txt`, `points3D.txt`), read and written.
//!
//! COLMAP (<https://colmap.github.io/format.html>) is what most users already ran on their images, and its
//! text model is what nerfstudio, Gaussian-splatting trainers and hloc exchange. Reading it lets a user
//! bring their own calibration and poses; writing it hands our poses to those tools.
//!
//! Conventions at the boundary (everything else in the crate is OpenCV):
//! - COLMAP puts the centre of the top-left pixel at (0.5, 0.5), we put it at (0, 0), so the principal
//!   point and the 2D keypoints are shifted by 0.5 on the way in and out.
//! - An image's pose is world → camera (`x_cam = R(q)·x_world + t`, Hamilton quaternion written
//!   `QW QX QY QZ`), kept as [`ColmapImage::t_cam_world`].
//! - Only the camera models that map exactly onto [`CameraModel`] are accepted; `FULL_OPENCV` only when its
//!   rational terms k4..k6 are zero, because our rad-tan has k3 but no rational denominator, and silently
//!   dropping them would bend every ray near the border.
//!
//! Parsing works on `&str` so the browser can use it; [`read_model`] and [`write_model`] are thin native
//! wrappers. Every reader treats its input as untrusted: errors name the file and line, never panic, and
//! allocate only in proportion to the text.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use glam::{DQuat, DVec2, DVec3};
use thiserror::Error;

use crate::camera::{CameraModel, Distortion};
use crate::dataset::{write_atomic, DatasetError};
use crate::geometry::Se3;
use crate::pointcloud::PointCloud;

/// COLMAP model read/write errors; every variant names the file.
#[derive(Debug, Error)]
pub enum ColmapError {
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
    Unsupported { file: String, reason: String },
    #[error("{file}: cannot write: {reason}")]
    Unwritable { file: String, reason: String },
    #[error(transparent)]
    Write(#[from] DatasetError),
}

/// One registered image of a COLMAP model.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapImage {
    pub id: u32,
    pub camera_id: u32,
    /// Path relative to COLMAP's image folder.
    pub name: String,
    /// World → camera, OpenCV camera axes (COLMAP's own).
    pub t_cam_world: Se3,
    /// Keypoints of the image's second line, in our pixel convention (COLMAP's minus 0.5).
    pub points2d: Vec<ColmapPoint2D>,
}

impl ColmapImage {
    /// Camera → world, the form the rest of the crate stores.
    pub fn t_world_cam(&self) -> Se3 {
        self.t_cam_world.inverse()
    }
}

/// A keypoint of a [`ColmapImage`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ColmapPoint2D {
    /// Pixel position, OpenCV convention (top-left pixel centre at (0, 0)).
    pub xy: DVec2,
    /// The triangulated point it observes (`-1` in the file when none).
    pub point3d_id: Option<u64>,
}

/// One observation in a [`ColmapPoint`]'s track.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ColmapTrackEntry {
    pub image_id: u32,
    /// Index into that image's [`ColmapImage::points2d`].
    pub point2d_idx: u32,
}

/// One triangulated point of `points3D.txt`.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapPoint {
    pub id: u64,
    pub position: DVec3,
    pub color: [u8; 3],
    /// Mean reprojection error in pixels (COLMAP writes -1 when unknown).
    pub error: f64,
    /// Kept so a written model is still a valid COLMAP model (its tools need the tracks).
    pub track: Vec<ColmapTrackEntry>,
}

/// A COLMAP sparse model: intrinsics by camera id, registered images, triangulated points.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ColmapModel {
    pub cameras: BTreeMap<u32, CameraModel>,
    pub images: Vec<ColmapImage>,
    pub points: Vec<ColmapPoint>,
}

impl ColmapModel {
    /// The triangulated points as a cloud with their colours and an `error` scalar (pixels).
    pub fn point_cloud(&self) -> PointCloud {
        let mut cloud =
            PointCloud::from_positions(self.points.iter().map(|p| p.position).collect());
        cloud.colors = Some(self.points.iter().map(|p| p.color).collect());
        cloud.set_scalar(
            "error",
            self.points.iter().map(|p| p.error as f32).collect(),
        );
        cloud
    }
}

/// The model names [`parse_cameras`] accepts, for error messages.
const SUPPORTED_MODELS: &str =
    "SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV, OPENCV_FISHEYE";

fn line_err(file: &str, line: usize) -> impl FnOnce(String) -> ColmapError + '_ {
    move |reason| ColmapError::Line {
        file: file.to_string(),
        line,
        reason,
    }
}

/// Lines with their 1-based numbers, a leading byte-order mark removed.
fn numbered_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.strip_prefix('\u{feff}')
        .unwrap_or(text)
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
}

fn is_skipped(line: &str) -> bool {
    line.is_empty() || line.starts_with('#')
}

fn finite(tok: &str, what: &str) -> Result<f64, String> {
    match tok.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        Ok(_) => Err(format!("{what} '{tok}' is not finite")),
        Err(_) => Err(format!("{what} '{tok}' is not a number")),
    }
}

fn integer<T: std::str::FromStr>(tok: &str, what: &str, range: &str) -> Result<T, String> {
    tok.parse::<T>()
        .map_err(|_| format!("{what} '{tok}' is not an integer in {range}"))
}

/// The next whitespace-separated token of `rest` (empty at the end), advancing `rest` past it.
fn next_token<'a>(rest: &mut &'a str) -> &'a str {
    let s = rest.trim_start();
    let end = s.find(char::is_whitespace).unwrap_or(s.len());
    let (tok, after) = s.split_at(end);
    *rest = after;
    tok
}

/// Exactly `N` parameters, or an error naming the model and the count it takes.
fn params<const N: usize>(model: &str, p: &[f64]) -> Result<[f64; N], String> {
    <[f64; N]>::try_from(p).map_err(|_| {
        format!(
            "{model} takes {N} parameters, found {} (see https://colmap.github.io/cameras.html)",
            p.len()
        )
    })
}

/// Our camera from a COLMAP model name, size and parameter list (COLMAP pixel convention).
fn camera_from_colmap(
    model: &str,
    width: u32,
    height: u32,
    p: &[f64],
) -> Result<CameraModel, String> {
    let radtan = |k1, k2, p1, p2, k3| Distortion::RadTan { k1, k2, p1, p2, k3 };
    let (fx, fy, cx, cy, distortion) = match model {
        "SIMPLE_PINHOLE" => {
            let [f, cx, cy] = params(model, p)?;
            (f, f, cx, cy, Distortion::None)
        }
        "PINHOLE" => {
            let [fx, fy, cx, cy] = params(model, p)?;
            (fx, fy, cx, cy, Distortion::None)
        }
        "SIMPLE_RADIAL" => {
            let [f, cx, cy, k] = params(model, p)?;
            (f, f, cx, cy, radtan(k, 0.0, 0.0, 0.0, 0.0))
        }
        "RADIAL" => {
            let [f, cx, cy, k1, k2] = params(model, p)?;
            (f, f, cx, cy, radtan(k1, k2, 0.0, 0.0, 0.0))
        }
        "OPENCV" => {
            let [fx, fy, cx, cy, k1, k2, p1, p2] = params(model, p)?;
            (fx, fy, cx, cy, radtan(k1, k2, p1, p2, 0.0))
        }
        "FULL_OPENCV" => {
            let [fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6] = params(model, p)?;
            if k4 != 0.0 || k5 != 0.0 || k6 != 0.0 {
                return Err(format!(
                    "FULL_OPENCV with rational terms k4={k4}, k5={k5}, k6={k6} is not supported: our \
                     rad-tan model has k1..k3 and p1, p2 but no rational denominator (recalibrate \
                     with OPENCV, or FULL_OPENCV with k4..k6 fixed to 0)"
                ));
            }
            (fx, fy, cx, cy, radtan(k1, k2, p1, p2, k3))
        }
        "OPENCV_FISHEYE" => {
            let [fx, fy, cx, cy, k1, k2, k3, k4] = params(model, p)?;
            (fx, fy, cx, cy, Distortion::Fisheye { k1, k2, k3, k4 })
        }
        other => {
            return Err(format!(
                "unsupported camera model '{other}' (supported: {SUPPORTED_MODELS})"
            ))
        }
    };
    let cam = CameraModel {
        width,
        height,
        fx,
        fy,
        cx: cx - 0.5,
        cy: cy - 0.5,
        distortion,
    };
    cam.validate().map_err(|e| e.to_string())?;
    Ok(cam)
}

fn camera_line(line: &str) -> Result<(u32, CameraModel), String> {
    let mut rest = line;
    let id = integer(next_token(&mut rest), "CAMERA_ID", "0..2^32")?;
    let model = next_token(&mut rest);
    if model.is_empty() {
        return Err("expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]".into());
    }
    let width = integer(next_token(&mut rest), "WIDTH", "0..2^32")?;
    let height = integer(next_token(&mut rest), "HEIGHT", "0..2^32")?;
    // At most 12 parameters are legal; collect one more so a long line is reported with its count.
    let mut p = Vec::with_capacity(12);
    for (i, tok) in rest.split_whitespace().enumerate() {
        if i > 12 {
            return Err(format!("{model}: more than 12 parameters"));
        }
        p.push(finite(tok, &format!("parameter {}", i + 1))?);
    }
    Ok((id, camera_from_colmap(model, width, height, &p)?))
}

/// Parses `cameras.txt` (`CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]` per line); `name` is used in errors.
pub fn parse_cameras(text: &str, name: &str) -> Result<BTreeMap<u32, CameraModel>, ColmapError> {
    let mut cameras = BTreeMap::new();
    for (n, line) in numbered_lines(text) {
        if is_skipped(line) {
            continue;
        }
        let (id, cam) = camera_line(line).map_err(line_err(name, n))?;
        if cameras.insert(id, cam).is_some() {
            return Err(line_err(name, n)(format!("duplicate CAMERA_ID {id}")));
        }
    }
    Ok(cameras)
}

/// The first line of an image: id, pose, camera id and name (the rest of the line, so names with spaces
/// survive; COLMAP itself stops at the first space).
fn image_line(line: &str) -> Result<(u32, Se3, u32, String), String> {
    let mut rest = line;
    let id = integer(next_token(&mut rest), "IMAGE_ID", "0..2^32")?;
    let mut v = [0.0; 7];
    for (slot, what) in v.iter_mut().zip(["QW", "QX", "QY", "QZ", "TX", "TY", "TZ"]) {
        let tok = next_token(&mut rest);
        if tok.is_empty() {
            return Err(format!(
                "image {id}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, missing {what}"
            ));
        }
        *slot = finite(tok, what)?;
    }
    let [qw, qx, qy, qz, tx, ty, tz] = v;
    let q = DQuat::from_xyzw(qx, qy, qz, qw);
    if q.length() < 1e-6 {
        return Err(format!("image {id}: zero quaternion"));
    }
    let camera_id = integer(next_token(&mut rest), "CAMERA_ID", "0..2^32")?;
    let name = rest.trim();
    if name.is_empty() {
        return Err(format!("image {id}: missing NAME"));
    }
    Ok((
        id,
        Se3::new(q, DVec3::new(tx, ty, tz)),
        camera_id,
        name.to_string(),
    ))
}

/// The second line of an image: `X Y POINT3D_ID` triples (COLMAP pixel convention), possibly none.
fn points2d_line(line: &str) -> Result<Vec<ColmapPoint2D>, String> {
    let toks: Vec<&str> = line.split_whitespace().collect();
    if !toks.len().is_multiple_of(3) {
        return Err(format!(
            "{} values, expected X Y POINT3D_ID triples (every image takes two lines; the second may \
             be empty but must be there)",
            toks.len()
        ));
    }
    let mut out = Vec::with_capacity(toks.len() / 3);
    for (k, t) in toks.chunks_exact(3).enumerate() {
        let [x, y, id] = [t[0], t[1], t[2]];
        let xy = DVec2::new(
            finite(x, &format!("point {k} X"))?,
            finite(y, &format!("point {k} Y"))?,
        );
        let point3d_id = match id.parse::<i64>() {
            Ok(-1) => None,
            Ok(v) if v >= 0 => Some(v as u64),
            _ => match id.parse::<u64>() {
                Ok(v) => Some(v),
                Err(_) => {
                    return Err(format!(
                        "point {k} POINT3D_ID '{id}' is neither -1 nor a non-negative integer"
                    ))
                }
            },
        };
        out.push(ColmapPoint2D {
            xy: xy - DVec2::splat(0.5),
            point3d_id,
        });
    }
    Ok(out)
}

/// Parses `images.txt`: per image one line `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` and one line of
/// `X Y POINT3D_ID` triples. The second line always follows the first (blank when the image has no
/// keypoints; missing at the end of the file is read as blank). `name` is used in errors.
pub fn parse_images(text: &str, name: &str) -> Result<Vec<ColmapImage>, ColmapError> {
    Ok(parse_images_numbered(text, name)?
        .into_iter()
        .map(|(_, img)| img)
        .collect())
}

/// [`parse_images`], each image with the number of its first line (for later cross-file errors).
fn parse_images_numbered(text: &str, name: &str) -> Result<Vec<(usize, ColmapImage)>, ColmapError> {
    let mut images = Vec::new();
    let mut ids = BTreeSet::new();
    let mut lines = numbered_lines(text);
    while let Some((n, line)) = lines.next() {
        if is_skipped(line) {
            continue;
        }
        let (id, t_cam_world, camera_id, image_name) =
            image_line(line).map_err(line_err(name, n))?;
        if !ids.insert(id) {
            return Err(line_err(name, n)(format!("duplicate IMAGE_ID {id}")));
        }
        let points2d = match lines.next() {
            Some((m, second)) => points2d_line(second)
                .map_err(|r| line_err(name, m)(format!("keypoints of image {id}: {r}")))?,
            None => Vec::new(),
        };
        images.push((
            n,
            ColmapImage {
                id,
                camera_id,
                name: image_name,
                t_cam_world,
                points2d,
            },
        ));
    }
    Ok(images)
}

fn point_line(line: &str) -> Result<ColmapPoint, String> {
    let toks: Vec<&str> = line.split_whitespace().collect();
    let Some((head, track)) = toks.split_first_chunk::<8>() else {
        return Err(format!(
            "{} values, expected POINT3D_ID X Y Z R G B ERROR TRACK[]",
            toks.len()
        ));
    };
    let [id, x, y, z, r, g, b, error] = *head;
    let id = integer(id, "POINT3D_ID", "0..2^64")?;
    let position = DVec3::new(finite(x, "X")?, finite(y, "Y")?, finite(z, "Z")?);
    let color = [
        integer(r, "R", "0..=255")?,
        integer(g, "G", "0..=255")?,
        integer(b, "B", "0..=255")?,
    ];
    let error = finite(error, "ERROR")?;
    if !track.len().is_multiple_of(2) {
        return Err(format!(
            "point {id}: track has {} values, expected IMAGE_ID POINT2D_IDX pairs",
            track.len()
        ));
    }
    let mut entries = Vec::with_capacity(track.len() / 2);
    for pair in track.chunks_exact(2) {
        entries.push(ColmapTrackEntry {
            image_id: integer(pair[0], "track IMAGE_ID", "0..2^32")?,
            point2d_idx: integer(pair[1], "track POINT2D_IDX", "0..2^32")?,
        });
    }
    Ok(ColmapPoint {
        id,
        position,
        color,
        error,
        track: entries,
    })
}

/// Parses `points3D.txt` (`POINT3D_ID X Y Z R G B ERROR TRACK[]` per line); `name` is used in errors.
pub fn parse_points3d(text: &str, name: &str) -> Result<Vec<ColmapPoint>, ColmapError> {
    let mut points = Vec::new();
    let mut ids = BTreeSet::new();
    for (n, line) in numbered_lines(text) {
        if is_skipped(line) {
            continue;
        }
        let p = point_line(line).map_err(line_err(name, n))?;
        if !ids.insert(p.id) {
            return Err(line_err(name, n)(format!("duplicate POINT3D_ID {}", p.id)));
        }
        points.push(p);
    }
    Ok(points)
}

/// `dir/file`, or `file` alone when `dir` is empty (names for error messages).
fn joined(dir: &str, file: &str) -> String {
    if dir.is_empty() {
        file.to_string()
    } else {
        format!("{}/{file}", dir.trim_end_matches(['/', '\\']))
    }
}

/// Parses the three texts of a model and checks that every image's camera exists. `dir` only names the
/// files in errors. Point references (keypoint → point, track → image) are not checked: models pruned by
/// other tools often leave dangling ones, and nothing here follows them.
pub fn parse_model(
    dir: &str,
    cameras: &str,
    images: &str,
    points3d: &str,
) -> Result<ColmapModel, ColmapError> {
    let cameras = parse_cameras(cameras, &joined(dir, "cameras.txt"))?;
    let images_name = joined(dir, "images.txt");
    let numbered = parse_images_numbered(images, &images_name)?;
    if let Some((line, img)) = numbered
        .iter()
        .find(|(_, i)| !cameras.contains_key(&i.camera_id))
    {
        return Err(line_err(&images_name, *line)(format!(
            "image {} ('{}') uses CAMERA_ID {}, which cameras.txt does not define",
            img.id, img.name, img.camera_id
        )));
    }
    let parsed_images = numbered.into_iter().map(|(_, img)| img).collect();
    Ok(ColmapModel {
        cameras,
        images: parsed_images,
        points: parse_points3d(points3d, &joined(dir, "points3D.txt"))?,
    })
}

fn read_text(path: &Path) -> Result<String, ColmapError> {
    std::fs::read_to_string(path).map_err(|source| ColmapError::Io {
        file: path.display().to_string(),
        source,
    })
}

/// Reads `cameras.txt`, `images.txt` and `points3D.txt` from a folder (COLMAP's `sparse/0`). A missing
/// `points3D.txt` reads as no points (hand-made "known poses" models often leave it out); a binary-only
/// model is refused with the command that converts it.
pub fn read_model(dir: &Path) -> Result<ColmapModel, ColmapError> {
    let cams = dir.join("cameras.txt");
    if !cams.exists() && dir.join("cameras.bin").exists() {
        return Err(ColmapError::Unsupported {
            file: dir.join("cameras.bin").display().to_string(),
            reason: "binary COLMAP models are not read; convert with `colmap model_converter \
                     --input_path <dir> --output_path <dir> --output_type TXT`"
                .into(),
        });
    }
    let cameras = read_text(&cams)?;
    let images = read_text(&dir.join("images.txt"))?;
    let points = dir.join("points3D.txt");
    let points = if points.exists() {
        read_text(&points)?
    } else {
        String::new()
    };
    parse_model(&dir.display().to_string(), &cameras, &images, &points)
}

fn unwritable(file: &str, reason: String) -> ColmapError {
    ColmapError::Unwritable {
        file: file.into(),
        reason,
    }
}

/// `cameras.txt` text. Pinhole → `PINHOLE`, rad-tan → `OPENCV` (or `FULL_OPENCV` with zero rational terms
/// when k3 ≠ 0), fisheye → `OPENCV_FISHEYE`; numbers in shortest round-trip form.
pub fn write_cameras(cameras: &BTreeMap<u32, CameraModel>) -> Result<String, ColmapError> {
    let mut s = format!(
        "# Camera list with one line of data per camera:\n\
         #   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n\
         # Number of cameras: {}\n",
        cameras.len()
    );
    for (id, cam) in cameras {
        cam.validate()
            .map_err(|e| unwritable("cameras.txt", format!("camera {id}: {e}")))?;
        s.push_str(&format!(
            "{id} {} {} {}",
            cam.colmap_name(),
            cam.width,
            cam.height
        ));
        for p in cam.colmap_params() {
            s.push_str(&format!(" {p}"));
        }
        s.push('\n');
    }
    Ok(s)
}

/// `images.txt` text, in the order given. Names must be non-empty and free of whitespace (COLMAP reads a
/// name up to the first space), ids unique, poses and keypoints finite.
pub fn write_images(images: &[ColmapImage]) -> Result<String, ColmapError> {
    let file = "images.txt";
    let observations: usize = images.iter().map(|i| i.points2d.len()).sum();
    let mean = if images.is_empty() {
        0.0
    } else {
        observations as f64 / images.len() as f64
    };
    let mut s = format!(
        "# Image list with two lines of data per image:\n\
         #   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n\
         #   POINTS2D[] as (X, Y, POINT3D_ID)\n\
         # Number of images: {}, mean observations per image: {mean}\n",
        images.len()
    );
    let mut ids = BTreeSet::new();
    for img in images {
        let id = img.id;
        if !ids.insert(id) {
            return Err(unwritable(file, format!("duplicate IMAGE_ID {id}")));
        }
        if img.name.is_empty() || img.name.contains(char::is_whitespace) {
            return Err(unwritable(
                file,
                format!(
                    "image {id}: name {:?} is empty or contains whitespace",
                    img.name
                ),
            ));
        }
        if !img.t_cam_world.is_finite() {
            return Err(unwritable(file, format!("image {id}: non-finite pose")));
        }
        let (q, t) = (img.t_cam_world.rot, img.t_cam_world.trans);
        s.push_str(&format!(
            "{id} {} {} {} {} {} {} {} {} {}\n",
            q.w, q.x, q.y, q.z, t.x, t.y, t.z, img.camera_id, img.name
        ));
        let mut first = true;
        for (k, p) in img.points2d.iter().enumerate() {
            if !p.xy.is_finite() {
                return Err(unwritable(
                    file,
                    format!("image {id}: keypoint {k} is not finite"),
                ));
            }
            let xy = p.xy + DVec2::splat(0.5);
            if !first {
                s.push(' ');
            }
            first = false;
            match p.point3d_id {
                Some(pid) => s.push_str(&format!("{} {} {pid}", xy.x, xy.y)),
                None => s.push_str(&format!("{} {} -1", xy.x, xy.y)),
            }
        }
        s.push('\n');
    }
    Ok(s)
}

/// `points3D.txt` text, in the order given; ids unique, positions and errors finite.
pub fn write_points3d(points: &[ColmapPoint]) -> Result<String, ColmapError> {
    let file = "points3D.txt";
    let track_total: usize = points.iter().map(|p| p.track.len()).sum();
    let mean = if points.is_empty() {
        0.0
    } else {
        track_total as f64 / points.len() as f64
    };
    let mut s = format!(
        "# 3D point list with one line of data per point:\n\
         #   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n\
         # Number of points: {}, mean track length: {mean}\n",
        points.len()
    );
    let mut ids = BTreeSet::new();
    for p in points {
        if !ids.insert(p.id) {
            return Err(unwritable(file, format!("duplicate POINT3D_ID {}", p.id)));
        }
        if !p.position.is_finite() || !p.error.is_finite() {
            return Err(unwritable(
                file,
                format!("point {}: non-finite position or error", p.id),
            ));
        }
        let ([r, g, b], x) = (p.color, p.position);
        s.push_str(&format!(
            "{} {} {} {} {r} {g} {b} {}",
            p.id, x.x, x.y, x.z, p.error
        ));
        for t in &p.track {
            s.push_str(&format!(" {} {}", t.image_id, t.point2d_idx));
        }
        s.push('\n');
    }
    Ok(s)
}

/// Writes the three text files into `dir` (created if needed), each through a temporary file and a rename.
/// Everything is formatted and checked (including that every image's camera exists) before the first
/// file is written, so an unwritable model leaves the folder untouched.
pub fn write_model(dir: &Path, model: &ColmapModel) -> Result<(), ColmapError> {
    if let Some(img) = model
        .images
        .iter()
        .find(|i| !model.cameras.contains_key(&i.camera_id))
    {
        return Err(unwritable(
            "images.txt",
            format!(
                "image {} uses CAMERA_ID {}, which the model does not define",
                img.id, img.camera_id
            ),
        ));
    }
    let files = [
        ("cameras.txt", write_cameras(&model.cameras)?),
        ("images.txt", write_images(&model.images)?),
        ("points3D.txt", write_points3d(&model.points)?),
    ];
    for (file, text) in files {
        write_atomic(&dir.join(file), text.as_bytes())?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    const CAMERAS: &str = "\
# Camera list with one line of data per camera:
#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]
# Number of cameras: 2
1 PINHOLE 640 480 500 501 320.5 240.5

2 OPENCV 1440 1080 700.25 699.75 720 540 -0.1 0.02 0.001 -0.0005
";

    const IMAGES: &str = "\
# Image list with two lines of data per image:
#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME
#   POINTS2D[] as (X, Y, POINT3D_ID)
# Number of images: 3, mean observations per image: 2
1 1 0 0 0 0 0 0 1 left/0001.png
100.5 200.5 10 300 50 -1
2 0.7071067811865476 0 0.7071067811865476 0 1.5 -2 0.25 2 right/0001.png

3 0.5 0.5 0.5 0.5 -1 2 3 1 left/0002.png
10.5 20.5 11";

    const POINTS: &str = "\
# 3D point list with one line of data per point:
#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)
10 1.5 -2.25 3 255 128 0 0.75 1 0 3 0
11 -0.5 0.5 8 10 20 30 -1
12 4 5 6 0 0 0 1.25 3 0
";

    fn example() -> ColmapModel {
        parse_model("sparse/0", CAMERAS, IMAGES, POINTS).unwrap()
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() <= 1e-12 * a.abs().max(b.abs()).max(1.0)
    }

    fn assert_models_close(a: &ColmapModel, b: &ColmapModel) {
        assert_eq!(a.cameras.len(), b.cameras.len());
        for ((ia, ca), (ib, cb)) in a.cameras.iter().zip(&b.cameras) {
            assert_eq!(ia, ib);
            assert_eq!(
                (ca.width, ca.height, ca.colmap_name()),
                (cb.width, cb.height, cb.colmap_name())
            );
            for (x, y) in ca.colmap_params().iter().zip(cb.colmap_params()) {
                assert!(close(*x, y), "camera {ia}: {x} vs {y}");
            }
        }
        assert_eq!(a.images.len(), b.images.len());
        for (ia, ib) in a.images.iter().zip(&b.images) {
            assert_eq!(
                (ia.id, ia.camera_id, &ia.name),
                (ib.id, ib.camera_id, &ib.name)
            );
            assert!(ia.t_cam_world.distance_to(&ib.t_cam_world) < 1e-12);
            assert!(ia.t_cam_world.angle_to(&ib.t_cam_world) < 1e-12);
            assert_eq!(ia.points2d.len(), ib.points2d.len());
            for (pa, pb) in ia.points2d.iter().zip(&ib.points2d) {
                assert_eq!(pa.point3d_id, pb.point3d_id);
                assert!(close(pa.xy.x, pb.xy.x) && close(pa.xy.y, pb.xy.y));
            }
        }
        assert_eq!(a.points.len(), b.points.len());
        for (pa, pb) in a.points.iter().zip(&b.points) {
            assert_eq!((pa.id, pa.color, &pa.track), (pb.id, pb.color, &pb.track));
            assert!((pa.position - pb.position).length() < 1e-12);
            assert!(close(pa.error, pb.error));
        }
    }

    #[test]
    fn reads_the_hand_written_model() {
        let m = example();
        // Windows line endings read the same.
        let crlf = |t: &str| t.replace('\n', "\r\n");
        assert_eq!(
            parse_model("", &crlf(CAMERAS), &crlf(IMAGES), &crlf(POINTS)).unwrap(),
            m
        );
        assert_eq!(m.cameras.len(), 2);
        let c1 = m.cameras[&1];
        assert_eq!(
            (c1.width, c1.height, c1.fx, c1.fy),
            (640, 480, 500.0, 501.0)
        );
        // COLMAP's (0.5, 0.5) pixel centre → ours (0, 0).
        assert_eq!((c1.cx, c1.cy), (320.0, 240.0));
        assert_eq!(c1.distortion, Distortion::None);
        let c2 = m.cameras[&2];
        assert_eq!((c2.cx, c2.cy), (719.5, 539.5));
        assert_eq!(
            c2.distortion,
            Distortion::RadTan {
                k1: -0.1,
                k2: 0.02,
                p1: 0.001,
                p2: -0.0005,
                k3: 0.0
            }
        );

        assert_eq!(m.images.len(), 3);
        let [a, b, c] = [&m.images[0], &m.images[1], &m.images[2]];
        assert_eq!(
            (a.id, a.camera_id, a.name.as_str()),
            (1, 1, "left/0001.png")
        );
        assert_eq!(
            a.points2d,
            vec![
                ColmapPoint2D {
                    xy: DVec2::new(100.0, 200.0),
                    point3d_id: Some(10)
                },
                ColmapPoint2D {
                    xy: DVec2::new(299.5, 49.5),
                    point3d_id: None
                },
            ]
        );
        // Image 2 has an empty keypoint line; image 3's keypoint line ends the file without a newline.
        assert!(b.points2d.is_empty());
        assert_eq!(c.points2d.len(), 1);
        // x_cam = R·x_world + t: a point at the world origin sits at t in the camera.
        assert!(
            (b.t_cam_world.transform_point(DVec3::ZERO) - DVec3::new(1.5, -2.0, 0.25)).length()
                < 1e-15
        );
        // Image 2 is rotated 90° about y, so world +z is camera +x.
        let z_in_cam = b.t_cam_world.transform_vector(DVec3::Z);
        assert!((z_in_cam - DVec3::X).length() < 1e-12, "{z_in_cam}");
        // The camera centre in the world is -Rᵀt.
        let centre = b.t_world_cam().trans;
        let expect = -(b.t_cam_world.rot.conjugate() * DVec3::new(1.5, -2.0, 0.25));
        assert!((centre - expect).length() < 1e-12);

        assert_eq!(m.points.len(), 3);
        let p = &m.points[0];
        assert_eq!(
            (p.id, p.position, p.color, p.error),
            (10, DVec3::new(1.5, -2.25, 3.0), [255, 128, 0], 0.75)
        );
        assert_eq!(
            p.track,
            vec![
                ColmapTrackEntry {
                    image_id: 1,
                    point2d_idx: 0
                },
                ColmapTrackEntry {
                    image_id: 3,
                    point2d_idx: 0
                }
            ]
        );
        assert!(m.points[1].track.is_empty());
        let cloud = m.point_cloud();
        assert_eq!(cloud.len(), 3);
        assert_eq!(cloud.colors.as_ref().unwrap()[0], [255, 128, 0]);
        assert_eq!(cloud.scalar("error").unwrap(), &[0.75, -1.0, 1.25]);
    }

    #[test]
    fn every_supported_model_maps_and_round_trips() {
        let cases = [
            ("SIMPLE_PINHOLE", "400 319.5 239.5", "PINHOLE"),
            ("SIMPLE_RADIAL", "400 319.5 239.5 -0.05", "OPENCV"),
            ("RADIAL", "400 319.5 239.5 -0.05 0.01", "OPENCV"),
            (
                "FULL_OPENCV",
                "400 410 319.5 239.5 -0.05 0.01 0.001 0.002 0.003 0 0 0",
                "FULL_OPENCV",
            ),
            (
                "OPENCV_FISHEYE",
                "300 301 320 240 0.1 -0.01 0.002 -0.0003",
                "OPENCV_FISHEYE",
            ),
        ];
        for (model, params, written_as) in cases {
            let text = format!("7 {model} 640 480 {params}\n");
            let cams = parse_cameras(&text, "cameras.txt").unwrap();
            let cam = cams[&7];
            assert_eq!(cam.colmap_name(), written_as, "{model}");
            let back = parse_cameras(&write_cameras(&cams).unwrap(), "again").unwrap();
            assert_eq!(back.len(), 1);
            for (x, y) in back[&7].colmap_params().iter().zip(cam.colmap_params()) {
                assert!(close(*x, y), "{model}: {x} vs {y}");
            }
        }
        let simple = parse_cameras("1 SIMPLE_RADIAL 10 10 5 4.5 4.5 0.25", "c").unwrap()[&1];
        assert_eq!(
            (simple.fx, simple.fy, simple.cx, simple.cy),
            (5.0, 5.0, 4.0, 4.0)
        );
        assert_eq!(
            simple.distortion,
            Distortion::RadTan {
                k1: 0.25,
                k2: 0.0,
                p1: 0.0,
                p2: 0.0,
                k3: 0.0
            }
        );
    }

    #[test]
    fn model_round_trips_through_text_and_files() {
        let m = example();
        let again = parse_model(
            "",
            &write_cameras(&m.cameras).unwrap(),
            &write_images(&m.images).unwrap(),
            &write_points3d(&m.points).unwrap(),
        )
        .unwrap();
        assert_models_close(&m, &again);

        // Awkward numbers: shortest round-trip formatting keeps them to the last bit (up to the ±0.5 shift).
        let mut m2 = m.clone();
        m2.images[0].t_cam_world = Se3::new(
            DQuat::from_euler(glam::EulerRot::ZYX, 0.1234567890123, -1.3, 2.9),
            DVec3::new(1e-17, -123456.789012345, 3.0e8),
        );
        m2.points[0].position = DVec3::new(0.1 + 0.2, -1e-300, 1e300);
        let again = parse_model(
            "",
            &write_cameras(&m2.cameras).unwrap(),
            &write_images(&m2.images).unwrap(),
            &write_points3d(&m2.points).unwrap(),
        )
        .unwrap();
        assert_models_close(&m2, &again);
        assert_eq!(again.points[0].position, m2.points[0].position);

        let dir = tempfile::tempdir().unwrap();
        let sparse = dir.path().join("sparse/0");
        write_model(&sparse, &m).unwrap();
        let read = read_model(&sparse).unwrap();
        assert_models_close(&m, &read);
        // No temporary files are left behind.
        let mut names: Vec<String> = std::fs::read_dir(&sparse)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert_eq!(names, ["cameras.txt", "images.txt", "points3D.txt"]);
        // points3D.txt may be left out of a hand-made model.
        std::fs::remove_file(sparse.join("points3D.txt")).unwrap();
        assert!(read_model(&sparse).unwrap().points.is_empty());
    }

    #[test]
    fn binary_models_and_missing_files_are_named() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("cameras.bin"), [0u8; 8]).unwrap();
        let e = read_model(dir.path()).unwrap_err().to_string();
        assert!(
            e.contains("cameras.bin") && e.contains("model_converter"),
            "{e}"
        );
        let empty = tempfile::tempdir().unwrap();
        let e = read_model(empty.path()).unwrap_err().to_string();
        assert!(e.contains("cameras.txt"), "{e}");
    }

    fn camera_err(text: &str) -> String {
        parse_cameras(text, "cams.txt").unwrap_err().to_string()
    }

    #[test]
    fn malformed_cameras_are_refused_with_file_and_line() {
        let e = camera_err("# header\n1 FOV 640 480 500 500 320 240 0.9\n");
        assert!(
            e.starts_with("cams.txt, line 2:") && e.contains("unsupported camera model 'FOV'"),
            "{e}"
        );
        let e = camera_err("1 PINHOLE 640 480 500 500 320\n");
        assert!(e.contains("PINHOLE takes 4 parameters, found 3"), "{e}");
        let e = camera_err("1 OPENCV 640 480 1 2 3 4 5 6 7 8 9 10 11 12 13 14\n");
        assert!(e.contains("more than 12"), "{e}");
        let e = camera_err("1 PINHOLE 640 480 500 abc 320 240\n");
        assert!(e.contains("parameter 2 'abc' is not a number"), "{e}");
        let e = camera_err("1 PINHOLE 640 480 500 NaN 320 240\n");
        assert!(e.contains("'NaN' is not finite"), "{e}");
        let e = camera_err("1 PINHOLE 640 480 500 inf 320 240\n");
        assert!(e.contains("not finite"), "{e}");
        let e = camera_err("1 PINHOLE 640 480 500 500 320 240\n1 PINHOLE 64 48 50 50 32 24\n");
        assert!(
            e.starts_with("cams.txt, line 2:") && e.contains("duplicate CAMERA_ID 1"),
            "{e}"
        );
        let e = camera_err("1 PINHOLE 0 480 500 500 320 240\n");
        assert!(e.contains("non-zero"), "{e}");
        let e = camera_err("1 PINHOLE 640 480 -500 500 320 240\n");
        assert!(e.contains("focal"), "{e}");
        let e = camera_err("-1 PINHOLE 640 480 500 500 320 240\n");
        assert!(e.contains("CAMERA_ID '-1'"), "{e}");
        let e = camera_err("1 PINHOLE -640 480 500 500 320 240\n");
        assert!(e.contains("WIDTH '-640'"), "{e}");
        let e = camera_err("1\n");
        assert!(e.contains("expected CAMERA_ID MODEL"), "{e}");
        let e = camera_err("1 FULL_OPENCV 640 480 500 500 320 240 0.1 0.01 0 0 0.001 0.2 0 0\n");
        assert!(e.contains("rational terms") && e.contains("k4=0.2"), "{e}");
        assert!(parse_cameras("", "c").unwrap().is_empty());
    }

    fn images_err(text: &str) -> String {
        parse_images(text, "imgs.txt").unwrap_err().to_string()
    }

    #[test]
    fn malformed_images_are_refused_with_file_and_line() {
        // A second line missing at the end of the file is an image without keypoints.
        let ok = parse_images("1 1 0 0 0 0 0 0 1 a.png", "imgs.txt").unwrap();
        assert_eq!(ok.len(), 1);
        assert!(ok[0].points2d.is_empty());
        // Names may contain spaces.
        let ok = parse_images("1 1 0 0 0 0 0 0 1 my image.png\n\n", "i").unwrap();
        assert_eq!(ok[0].name, "my image.png");

        let e = images_err("1 1 0 0 0 0 0 0 1 a.png\n1 2 3 4\n");
        assert!(
            e.starts_with("imgs.txt, line 2:") && e.contains("keypoints of image 1"),
            "{e}"
        );
        // One line per image (second lines left out): the next image is read as keypoints and refused.
        let e = images_err("1 1 0 0 0 0 0 0 1 a.png\n2 1 0 0 0 0 0 0 1 b.png\n");
        assert!(e.contains("line 2") && e.contains("two lines"), "{e}");
        let e = images_err("1 1 0 0 0 0 0 0 1 a.png\n1 2 x\n");
        assert!(e.contains("POINT3D_ID 'x'"), "{e}");
        let e = images_err("1 1 0 0 0 0 0 0 1 a.png\nNaN 2 -1\n");
        assert!(e.contains("not finite"), "{e}");
        let e = images_err("1 1 0 0 0 0 0 0 1 a.png\n1 2 -2\n");
        assert!(e.contains("neither -1"), "{e}");
        let e = images_err("1 1 0 0 0 0 nan 0 1 a.png\n\n");
        assert!(
            e.starts_with("imgs.txt, line 1:") && e.contains("TY 'nan' is not finite"),
            "{e}"
        );
        let e = images_err("1 0 0 0 0 0 0 0 1 a.png\n\n");
        assert!(e.contains("zero quaternion"), "{e}");
        let e = images_err("1 1 0 0 0 0 0 0 1\n\n");
        assert!(e.contains("missing NAME"), "{e}");
        let e = images_err("1 1 0 0\n\n");
        assert!(e.contains("missing QZ"), "{e}");
        let e = images_err("1 1 0 0 0 0 0 0 1 a.png\n\n# c\n\n1 1 0 0 0 0 0 0 1 b.png\n\n");
        assert!(
            e.starts_with("imgs.txt, line 5:") && e.contains("duplicate IMAGE_ID 1"),
            "{e}"
        );
        let e = images_err("1 1 0 0 0 0 0 0 one a.png\n\n");
        assert!(e.contains("CAMERA_ID 'one'"), "{e}");
    }

    #[test]
    fn malformed_points_and_models_are_refused() {
        let err = |t: &str| parse_points3d(t, "pts.txt").unwrap_err().to_string();
        let e = err("1 0 0 0 255 0 0\n");
        assert!(
            e.starts_with("pts.txt, line 1:") && e.contains("7 values"),
            "{e}"
        );
        let e = err("1 0 0 0 256 0 0 1\n");
        assert!(e.contains("R '256'"), "{e}");
        let e = err("1 0 0 0 255 0 0 1 5\n");
        assert!(e.contains("pairs"), "{e}");
        let e = err("1 0 0 0 255 0 0 1 5 -1\n");
        assert!(e.contains("POINT2D_IDX '-1'"), "{e}");
        let e = err("1 0 inf 0 255 0 0 1\n");
        assert!(e.contains("not finite"), "{e}");
        let e = err("1 0 0 0 1 2 3 1\n\n1 0 0 0 1 2 3 1\n");
        assert!(
            e.starts_with("pts.txt, line 3:") && e.contains("duplicate POINT3D_ID 1"),
            "{e}"
        );

        // An image referencing a camera that cameras.txt lacks.
        let images = "# c\n1 1 0 0 0 0 0 0 1 a.png\n\n2 1 0 0 0 0 0 0 9 b.png\n\n";
        let e = parse_model("m", CAMERAS, images, "")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("m/images.txt, line 4:") && e.contains("CAMERA_ID 9"),
            "{e}"
        );
        let e = parse_model("m", "1 PINHOLE 1 1 1\n", "", "")
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("m/cameras.txt, line 1:"), "{e}");
    }

    #[test]
    fn writers_refuse_what_the_readers_would() {
        let m = example();
        let mut bad = m.clone();
        bad.images[1].name = "has space.png".into();
        assert!(write_images(&bad.images).is_err());
        bad.images[1].name = String::new();
        assert!(write_images(&bad.images).is_err());
        let mut bad = m.clone();
        bad.images[2].id = 1;
        assert!(write_images(&bad.images).is_err());
        let mut bad = m.clone();
        bad.images[0].points2d[0].xy.x = f64::NAN;
        assert!(write_images(&bad.images).is_err());
        let mut bad = m.clone();
        bad.points[1].id = 10;
        assert!(write_points3d(&bad.points).is_err());
        let mut bad = m.clone();
        bad.points[0].error = f64::INFINITY;
        assert!(write_points3d(&bad.points).is_err());
        let mut bad = m.clone();
        bad.cameras.get_mut(&1).unwrap().fx = 0.0;
        assert!(write_cameras(&bad.cameras).is_err());
        let mut bad = m.clone();
        bad.images[0].camera_id = 5;
        let dir = tempfile::tempdir().unwrap();
        let e = write_model(dir.path(), &bad).unwrap_err().to_string();
        assert!(e.contains("CAMERA_ID 5"), "{e}");
        assert!(std::fs::read_dir(dir.path()).unwrap().next().is_none());
    }

    #[test]
    fn arbitrary_bytes_never_panic() {
        // Cheap deterministic fuzz: mutate the example texts byte by byte.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        for base in [CAMERAS, IMAGES, POINTS] {
            for _ in 0..300 {
                let mut b = base.as_bytes().to_vec();
                for _ in 0..4 {
                    state ^= state << 13;
                    state ^= state >> 7;
                    state ^= state << 17;
                    let i = (state % b.len() as u64) as usize;
                    let alphabet = b" -.0123456789e#\nNaxPINHOLE";
                    b[i] = alphabet[(state >> 32) as usize % alphabet.len()];
                }
                let text = String::from_utf8_lossy(&b);
                let _ = parse_model("fuzz", &text, &text, &text);
                let _ = parse_images(&text, "f");
                let _ = parse_points3d(&text, "f");
            }
        }
    }
}
