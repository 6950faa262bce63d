//! A KITTI odometry sequence → the project's dataset (`silvr import kitti`).
//!
//! Layout (<https://www.cvlibs.net/datasets/kitti/eval_odometry.php>): `sequences/NN/` holds `image_2/` and
//! `image_3/` (the rectified colour stereo pair, `NNNNNN.png`), `velodyne/` (`NNNNNN.bin` sweeps),
//! `calib.txt` (`P0`…`P3`: rectified 3 × 4 projections from cam0's frame; `Tr`: velodyne → cam0) and
//! `times.txt` (seconds, line i = frame i). Ground truth is `T_world_cam0` per frame (12 numbers a line),
//! as `poses/NN.txt` two levels up (the odometry release) or `poses.txt` inside the sequence (SemanticKITTI).
//!
//! Both colour cameras form the rig: intrinsics from `P2`/`P3`, and each camera's place from the fourth
//! column of its `P` (`P = K · [I | t]`: the camera is at `−t` in cam0's frame, cam0's rotation); the lidar
//! from `Tr`. Each frame with both images and a sweep is a keyframe; its cameras are posed as
//! `T_world_cam0 · T_cam0_cam`. Without a trajectory file or ground truth the poses come from lidar
//! odometry over the sweeps (`crate::odometry`), and the summary says so. KITTI's world is cam0 at frame 0 (y down, z forward); ours is the same origin turned
//! z-up (`x, y, z = z, −x, −y` of KITTI's), since the sky masks and top-down plots take +z as up.
//!
//! The odometry sweeps are motion-compensated already and carry no per-point time, so nothing is deskewed
//! (`lidar/deskewed` = `lidar/raw`); the camera is triggered as the spinning lidar faces forward, so each
//! sweep pairs with its frame's images through the fixed rig. They carry no ring either: the range image
//! for normals and sky masks is an angular grid, as for DGP sweeps. The HDL-64E sees from about −25° to
//! +2°: above that the sky mask rests on the image alone (see the manifest's notes).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{DMat3, DQuat, DVec3};
use serde::Serialize;

use super::kitti::{self, BinCloudError, KittiTextError};
use super::poses::{self, KittiTimes, PoseError};
use crate::camera::{CameraModel, Distortion};
use crate::dataset::{self, DatasetError, DatasetWriter};
use crate::geometry::{Se3, Trajectory};
use crate::gpu::{Gpu, GpuError};
use crate::lidar::{images, normals, products};
use crate::pointcloud::write_ply_bytes;
use crate::rig::{Rig, RigCamera};

/// Largest calibration file read (KITTI's are ~1 KiB).
const MAX_CALIB_BYTES: u64 = 1 << 20;
/// Largest `times.txt` / pose file read (the longest sequence, 4 661 frames, is ~0.6 MB of poses).
const MAX_TEXT_BYTES: u64 = 256 << 20;
/// Largest velodyne sweep read (an HDL-64E sweep is ~2 MB).
const MAX_SWEEP_BYTES: u64 = 256 << 20;

/// Why a KITTI folder could not be imported; every message names the file or folder.
#[derive(Debug, thiserror::Error)]
pub enum KittiImportError {
    #[error("{file}: {reason}")]
    Invalid { file: String, reason: String },
    #[error(transparent)]
    Text(#[from] KittiTextError),
    #[error(transparent)]
    Poses(#[from] PoseError),
    #[error(transparent)]
    Sweep(#[from] BinCloudError),
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error("GPU: {0}")]
    Gpu(#[from] GpuError),
}

fn invalid(file: &Path, reason: impl Into<String>) -> KittiImportError {
    KittiImportError::Invalid {
        file: file.display().to_string(),
        reason: reason.into(),
    }
}

/// Import options.
#[derive(Clone, Debug)]
pub struct KittiOptions {
    /// Integer image downscale (1 = full resolution); intrinsics follow exactly (`CameraModel::downscaled`).
    pub downscale: u32,
    /// Lidar returns nearer than this (m) are ignored.
    pub min_range: f64,
    /// A trajectory file to use instead of the ground truth found beside the sequence: KITTI format,
    /// `T_world_cam0` of frame i on line i (what KITTI-format SLAM and odometry tools write).
    pub poses: Option<PathBuf>,
    /// The trajectory from lidar odometry over `velodyne/` (`--poses lidar`) instead of a file; also what a
    /// sequence without ground truth or `poses` gets, with a notice.
    pub lidar_odometry: bool,
    /// Only KITTI frames `first..=last`.
    pub frames: Option<(usize, usize)>,
    /// Every n-th of the selected frames (1 = all).
    pub every: usize,
}

impl Default for KittiOptions {
    fn default() -> Self {
        Self {
            downscale: 1,
            min_range: 0.5,
            poses: None,
            lidar_odometry: false,
            frames: None,
            every: 1,
        }
    }
}

/// What an import wrote.
#[derive(Clone, Debug, Serialize)]
pub struct KittiSummary {
    pub path: PathBuf,
    pub layout: KittiLayout,
    /// The sequence or drive folder's name (`00`, `2011_09_26_drive_0001_sync`).
    pub sequence: String,
    pub keyframes: usize,
    pub images: usize,
    /// KITTI frame number of each keyframe (keyframe k = `frames[k]`).
    pub frames: Vec<usize>,
    /// The trajectory used (`T_world_cam0` per frame).
    pub poses: String,
    pub lidar_points: usize,
    /// Per camera: lidar pixels in its depth images, summed over keyframes.
    pub depth_pixels: BTreeMap<String, usize>,
    /// Per camera: sky-mask pixels, summed over keyframes.
    pub sky_pixels: BTreeMap<String, usize>,
    /// Frames left out, with why (an image or the sweep missing).
    pub skipped: Vec<String>,
    /// Choices made for the user (lidar odometry standing in for missing ground truth).
    pub notices: Vec<String>,
}

fn read_bounded(path: &Path, max: u64) -> Result<Vec<u8>, KittiImportError> {
    let len = std::fs::metadata(path)
        .map_err(|e| invalid(path, e.to_string()))?
        .len();
    if len > max {
        return Err(invalid(
            path,
            format!("{len} bytes; more than the {max} a KITTI file of this kind can need"),
        ));
    }
    std::fs::read(path).map_err(|e| invalid(path, e.to_string()))
}

fn read_text(path: &Path, max: u64) -> Result<String, KittiImportError> {
    String::from_utf8(read_bounded(path, max)?).map_err(|_| invalid(path, "not UTF-8 text"))
}

/// KITTI's world (cam0 of frame 0: x right, y down, z forward) → ours (z up): `(z, −x, −y)`.
fn z_up() -> Se3 {
    let m = DMat3::from_cols(
        DVec3::new(0.0, -1.0, 0.0),
        DVec3::new(0.0, 0.0, -1.0),
        DVec3::new(1.0, 0.0, 0.0),
    );
    Se3::new(DQuat::from_mat3(&m), DVec3::ZERO)
}

/// Where the ground truth of sequence folder `seq` may be, in the order tried.
pub fn pose_candidates(seq: &Path) -> Vec<PathBuf> {
    let mut out = vec![seq.join("poses.txt")];
    if let Some(name) = seq.file_name() {
        let file = Path::new(name).with_extension("txt");
        if let Some(up) = seq.parent() {
            if let Some(root) = up.parent() {
                out.push(root.join("poses").join(&file));
            }
            out.push(up.join("poses").join(&file));
        }
    }
    out
}

/// A colour camera from its projection: pinhole intrinsics at the image's size, placed in cam0's frame.
fn camera_from(
    name: &str,
    p: &kitti::Projection,
    (width, height): (u32, u32),
    downscale: u32,
    t_cam0_lidar: &Se3,
    calib: &Path,
) -> Result<RigCamera, KittiImportError> {
    let full = CameraModel {
        width,
        height,
        fx: p.fx,
        fy: p.fy,
        cx: p.cx,
        cy: p.cy,
        distortion: Distortion::None,
    };
    full.validate()
        .map_err(|e| invalid(calib, format!("{name}: {e}")))?;
    // P = K [I | t]: p_cam = p_cam0 + t, so the camera sits at −t in cam0's frame.
    let t_cam0_cam = Se3::new(DQuat::IDENTITY, -p.t);
    Ok(RigCamera {
        name: name.to_string(),
        model: full.downscaled(downscale),
        t_lidar_cam: t_cam0_lidar.inverse() * t_cam0_cam,
    })
}

/// An image as the camera `m` takes it: full size checked, then (downscale f) cropped to a multiple of f
/// and averaged over f × f blocks, which is what `CameraModel::downscaled` describes exactly.
fn load_image(path: &Path, full: (u32, u32), f: u32) -> Result<Vec<[u8; 3]>, KittiImportError> {
    let img = image::open(path)
        .map_err(|e| invalid(path, e.to_string()))?
        .to_rgb8();
    if img.dimensions() != full {
        return Err(invalid(
            path,
            format!(
                "{}×{} pixels, but the sequence's first image is {}×{}",
                img.width(),
                img.height(),
                full.0,
                full.1
            ),
        ));
    }
    // Training's own f × f block mean, so the stored image is what `--downscale f` would read.
    let pixels = img.pixels().map(|p| p.0).collect();
    Ok(crate::dataset::resize_rgb(pixels, full.0, full.1, f))
}

/// Which KITTI release a folder follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum KittiLayout {
    /// The odometry benchmark: `sequences/NN/{image_2,image_3,velodyne,calib.txt,times.txt}`.
    Odometry,
    /// The raw release: `DATE/DATE_drive_NNNN_sync/{image_02,image_03,velodyne_points,oxts}/data/…` with
    /// `calib_cam_to_cam.txt`, `calib_velo_to_cam.txt` (and `calib_imu_to_velo.txt`) in `DATE/`.
    Raw,
}

/// A KITTI folder resolved to what the import reads, whichever release it follows: both colour cameras'
/// images, the sweeps, the calibration, the frame times, and the trajectory recorded with the data (the
/// odometry ground truth, or the raw release's OXTS) where there is one.
struct Source {
    layout: KittiLayout,
    /// The sequence or drive folder.
    root: PathBuf,
    /// `image_2`/`image_3` (odometry) or `image_02/data`/`image_03/data` (raw).
    images: [PathBuf; 2],
    /// `velodyne` or `velodyne_points/data`.
    velo: PathBuf,
    /// Digits of a frame's file name: 6 (odometry) or 10 (raw).
    digits: usize,
    /// The file the projections were read from, and every calibration file read.
    calib_path: PathBuf,
    calib_files: Vec<PathBuf>,
    projections: [kitti::Projection; 2],
    /// The lidar in rectified cam0's frame.
    t_cam0_lidar: Se3,
    /// Frame i's time (s), and the file they came from.
    times: Vec<f64>,
    times_path: PathBuf,
    /// Where ground truth was looked for (odometry), for the notice when none is found.
    tried: Vec<PathBuf>,
    /// The trajectory found with the data: its name and `T_world_cam0` per frame number (`None` where the
    /// frame has no record), the world being rectified cam0 at the first recorded frame, as KITTI's ground
    /// truth is.
    recorded: Option<(String, Vec<Option<Se3>>)>,
}

impl Source {
    fn frame_name(&self, f: usize) -> String {
        format!("{f:0width$}", width = self.digits)
    }

    fn dir_label(&self, i: usize) -> String {
        let dir = if i < 2 { &self.images[i] } else { &self.velo };
        dir.strip_prefix(&self.root)
            .unwrap_or(dir)
            .display()
            .to_string()
    }

    /// Resolves `path`: an odometry sequence (it holds `calib.txt`) or a raw drive (it holds `image_02/`
    /// or `velodyne_points/`); anything else is refused with what was expected (and, for a release's root,
    /// which folders inside it would do).
    fn open(path: &Path) -> Result<Self, KittiImportError> {
        if path.join("calib.txt").is_file() {
            return Self::odometry(path);
        }
        if path.join("image_02").is_dir() || path.join("velodyne_points").is_dir() {
            return Self::raw(path);
        }
        let sequences = path.join("sequences");
        if sequences.is_dir() {
            let names = subfolders(&sequences, |p| p.join("calib.txt").is_file())?;
            return Err(invalid(
                path,
                format!(
                    "a KITTI odometry root: give one sequence folder, e.g. {} (sequences with calib.txt: {})",
                    sequences.join(names.first().map_or("00", String::as_str)).display(),
                    if names.is_empty() { "none".to_string() } else { names.join(", ") }
                ),
            ));
        }
        let drives = subfolders(path, |p| p.join("image_02").is_dir())?;
        if !drives.is_empty() {
            return Err(invalid(
                path,
                format!(
                    "a KITTI raw date folder: give one drive, e.g. {} (drives: {})",
                    path.join(&drives[0]).display(),
                    drives.join(", ")
                ),
            ));
        }
        Err(invalid(
            path,
            "not a KITTI folder: expected an odometry sequence (calib.txt, times.txt, image_2/, image_3/, \
             velodyne/) or a raw drive (DATE_drive_NNNN_sync with image_02/, image_03/, velodyne_points/, \
             oxts/, and calib_cam_to_cam.txt, calib_velo_to_cam.txt beside it)",
        ))
    }

    fn odometry(seq: &Path) -> Result<Self, KittiImportError> {
        let calib_path = seq.join("calib.txt");
        let calib = kitti::parse_calib(
            &read_text(&calib_path, MAX_CALIB_BYTES)?,
            &calib_path.display().to_string(),
        )?;
        let projections = [calib.projection("P2")?, calib.projection("P3")?];
        let t_cam0_lidar = calib.rigid("Tr")?;
        let times_path = seq.join("times.txt");
        let times = kitti::parse_times(
            &read_text(&times_path, MAX_TEXT_BYTES)?,
            &times_path.display().to_string(),
        )?;
        let tried = pose_candidates(seq);
        let recorded = match tried.iter().find(|p| p.is_file()) {
            Some(p) => Some((p.display().to_string(), read_kitti_poses(p)?)),
            None => None,
        };
        Ok(Self {
            layout: KittiLayout::Odometry,
            root: seq.to_path_buf(),
            images: [seq.join("image_2"), seq.join("image_3")],
            velo: seq.join("velodyne"),
            digits: 6,
            calib_files: vec![calib_path.clone()],
            calib_path,
            projections,
            t_cam0_lidar,
            times,
            times_path,
            tried,
            recorded,
        })
    }

    fn raw(drive: &Path) -> Result<Self, KittiImportError> {
        // The calibration sits in the date folder above the drive (as released), or in the drive itself.
        let find = |name: &str| {
            let up = drive.parent().map(|d| d.join(name));
            let here = drive.join(name);
            if here.is_file() {
                Ok(here)
            } else if let Some(up) = up.filter(|p| p.is_file()) {
                Ok(up)
            } else {
                Err(invalid(
                    drive,
                    format!(
                        "a KITTI raw drive needs {name} in its date folder (or beside its image_02/): \
                         not found"
                    ),
                ))
            }
        };
        let read = |p: &Path| -> Result<kitti::Calib, KittiImportError> {
            Ok(kitti::parse_calib(
                &read_text(p, MAX_CALIB_BYTES)?,
                &p.display().to_string(),
            )?)
        };
        let cam_path = find("calib_cam_to_cam.txt")?;
        let velo_path = find("calib_velo_to_cam.txt")?;
        let cam = read(&cam_path)?;
        let projections = [cam.projection("P_rect_02")?, cam.projection("P_rect_03")?];
        // The projections act on rectified cam0 coordinates: velodyne → cam0 → rectified cam0.
        let r = cam.exactly("R_rect_00", 9, "a 3 × 3 rotation")?;
        let r_rect = DMat3::from_cols(
            DVec3::new(r[0], r[3], r[6]),
            DVec3::new(r[1], r[4], r[7]),
            DVec3::new(r[2], r[5], r[8]),
        );
        let r_rect = poses::nearest_rotation(r_rect)
            .map_err(|e| invalid(&cam_path, format!("R_rect_00: {e}")))?;
        let t_cam0_lidar = Se3::new(r_rect, DVec3::ZERO) * read(&velo_path)?.rigid_rt("R", "T")?;
        let mut calib_files = vec![cam_path.clone(), velo_path];
        let times_path = drive.join("image_02").join("timestamps.txt");
        let times = kitti::parse_datetimes(
            &read_text(&times_path, MAX_TEXT_BYTES)?,
            &times_path.display().to_string(),
        )?;
        // The OXTS (GPS/IMU) poses: the devkit's local Mercator frame, the IMU placed by
        // calib_imu_to_velo.txt, then re-based on the first frame's rectified cam0.
        let oxts_dir = drive.join("oxts").join("data");
        let recorded = if oxts_dir.is_dir() {
            let imu_path = find("calib_imu_to_velo.txt")?;
            let t_lidar_imu = read(&imu_path)?.rigid_rt("R", "T")?;
            calib_files.push(imu_path);
            let t_imu_cam0 = (t_cam0_lidar * t_lidar_imu).inverse();
            let frames = numbered_files(&oxts_dir, ".txt", 10)?;
            let mut records = Vec::new();
            for &f in &frames {
                let p = oxts_dir.join(format!("{f:010}.txt"));
                records.push(kitti::parse_oxts(
                    &read_text(&p, MAX_CALIB_BYTES)?,
                    &p.display().to_string(),
                )?);
            }
            let world_imu = kitti::oxts_poses(&records);
            let mut out = vec![None; frames.last().map_or(0, |&l| l + 1)];
            if let Some(first) = world_imu.first() {
                let base = (*first * t_imu_cam0).inverse();
                for (&f, p) in frames.iter().zip(&world_imu) {
                    out[f] = Some(base * *p * t_imu_cam0);
                }
            }
            Some((format!("{} (OXTS)", oxts_dir.display()), out))
        } else {
            None
        };
        Ok(Self {
            layout: KittiLayout::Raw,
            root: drive.to_path_buf(),
            images: [
                drive.join("image_02").join("data"),
                drive.join("image_03").join("data"),
            ],
            velo: drive.join("velodyne_points").join("data"),
            digits: 10,
            calib_path: cam_path,
            calib_files,
            projections,
            t_cam0_lidar,
            times,
            times_path,
            tried: vec![oxts_dir],
            recorded,
        })
    }
}

/// Names of the folders in `dir` that pass `keep`, sorted.
fn subfolders(dir: &Path, keep: impl Fn(&Path) -> bool) -> Result<Vec<String>, KittiImportError> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .map_err(|e| invalid(dir, e.to_string()))?
        .flatten()
        .filter(|e| keep(&e.path()))
        .filter_map(|e| e.file_name().to_str().map(str::to_string))
        .collect();
    names.sort();
    Ok(names)
}

/// Frame numbers of the files `<digits digits><ext>` in `dir`, sorted.
fn numbered_files(dir: &Path, ext: &str, digits: usize) -> Result<Vec<usize>, KittiImportError> {
    let mut frames: Vec<usize> = std::fs::read_dir(dir)
        .map_err(|e| invalid(dir, e.to_string()))?
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().to_str()?.to_string();
            let stem = name.strip_suffix(ext)?;
            (stem.len() == digits && stem.bytes().all(|b| b.is_ascii_digit()))
                .then(|| stem.parse().ok())
                .flatten()
        })
        .collect();
    frames.sort_unstable();
    Ok(frames)
}

/// A KITTI-format trajectory file: `T_world_cam0` of frame i on line i.
fn read_kitti_poses(path: &Path) -> Result<Vec<Option<Se3>>, KittiImportError> {
    // Frame i's pose is line i: the stamps come from the times by index, so a period of 1 is a placeholder.
    let gt = poses::parse_kitti(
        &read_text(path, MAX_TEXT_BYTES)?,
        &path.display().to_string(),
        KittiTimes::Period(1.0),
    )?;
    Ok(gt.poses().iter().copied().map(Some).collect())
}

/// Imports the KITTI odometry sequence folder or raw drive folder `seq` into a dataset at `out`.
pub async fn import_kitti(
    seq: &Path,
    out: &Path,
    overwrite: bool,
    options: KittiOptions,
    gpu: &Gpu,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<KittiSummary, KittiImportError> {
    let src = Source::open(seq)?;
    let (calib_path, times_path) = (src.calib_path.clone(), src.times_path.clone());
    let (t_cam0_lidar, times) = (src.t_cam0_lidar, &src.times);

    // The trajectory: given, the one recorded with the data (ground truth, OXTS), or lidar odometry (asked
    // for, or with a notice when there is none).
    let mut notices = Vec::new();
    let recorded = match &options.poses {
        Some(p) => Some((p.display().to_string(), read_kitti_poses(p)?)),
        None if options.lidar_odometry => None,
        None => src.recorded.clone(),
    };
    let (poses_name, gt): (String, Vec<Option<Se3>>) = match recorded {
        Some(r) => r,
        None => {
            if !options.lidar_odometry {
                let what = match src.layout {
                    KittiLayout::Odometry => {
                        "KITTI publishes ground truth for sequences 00-10 only and none was found"
                    }
                    KittiLayout::Raw => "the drive has no OXTS records",
                };
                notices.push(format!(
                    "no trajectory: {what} ({}); using lidar odometry over {} (--poses lidar says so \
                     explicitly; --poses FILE gives one, KITTI format: T_world_cam0 of frame i on line i)",
                    src.tried
                        .iter()
                        .map(|p| p.display().to_string())
                        .collect::<Vec<_>>()
                        .join(", "),
                    src.dir_label(2),
                ));
            }
            (
                format!("lidar odometry ({}/)", src.dir_label(2)),
                lidar_trajectory(&src, options.frames)?
                    .into_iter()
                    .map(Some)
                    .collect(),
            )
        }
    };
    let poses_path = PathBuf::from(&poses_name);

    // Frames: every left-camera frame with its right-camera frame and sweep, within the selection.
    let dirs = src.images.clone();
    let velo = src.velo.clone();
    let labels = [src.dir_label(0), src.dir_label(1), src.dir_label(2)];
    let mut skipped = Vec::new();
    let mut frames = Vec::new();
    let every = options.every.max(1);
    let selected = numbered_files(&dirs[0], ".png", src.digits)?
        .into_iter()
        .filter(|f| options.frames.is_none_or(|(a, b)| (a..=b).contains(f)));
    for (i, f) in selected.enumerate() {
        if i % every != 0 {
            continue;
        }
        let name = src.frame_name(f);
        if !dirs[1].join(format!("{name}.png")).is_file() {
            skipped.push(format!("{name}: no {}/{name}.png", labels[1]));
        } else if !velo.join(format!("{name}.bin")).is_file() {
            skipped.push(format!("{name}: no {}/{name}.bin", labels[2]));
        } else if f < gt.len() && gt[f].is_none() {
            skipped.push(format!("{name}: no pose in {poses_name}"));
        } else {
            frames.push(f);
        }
    }
    let Some(&last) = frames.last() else {
        return Err(invalid(
            seq,
            format!(
                "no frame with {0}/{3}.png, {1}/{3}.png and {2}/{3}.bin{4}{5}",
                labels[0],
                labels[1],
                labels[2],
                "N".repeat(src.digits),
                if options.frames.is_some() {
                    " in the selected range"
                } else {
                    ""
                },
                if skipped.is_empty() {
                    String::new()
                } else {
                    format!(" ({})", skipped.join("; "))
                }
            ),
        ));
    };
    if last >= times.len() {
        return Err(invalid(
            &times_path,
            format!(
                "{} stamps, but frame {} needs line {}",
                times.len(),
                src.frame_name(last),
                last + 1
            ),
        ));
    }
    if last >= gt.len() {
        return Err(invalid(
            &poses_path,
            format!(
                "{} poses, but frame {} needs line {}",
                gt.len(),
                src.frame_name(last),
                last + 1
            ),
        ));
    }
    let gt: Vec<Se3> = gt.into_iter().map(Option::unwrap_or_default).collect();
    let gt = gt.as_slice();
    let projections = src.projections;

    // The rig: base = cam0, the lidar by Tr, both colour cameras at their first image's size.
    let scale = options.downscale.max(1);
    let first = format!("{}.png", src.frame_name(frames[0]));
    let mut cameras = Vec::new();
    let mut full_sizes = Vec::new();
    let names = match src.layout {
        KittiLayout::Odometry => ["image_2", "image_3"],
        KittiLayout::Raw => ["image_02", "image_03"],
    };
    for ((dir, p), name) in dirs.iter().zip(&projections).zip(names) {
        let path = dir.join(&first);
        let size = image::image_dimensions(&path).map_err(|e| invalid(&path, e.to_string()))?;
        if size.0 < scale || size.1 < scale {
            return Err(invalid(
                &path,
                format!("smaller than the downscale {scale}"),
            ));
        }
        full_sizes.push(size);
        cameras.push(camera_from(
            name,
            p,
            size,
            scale,
            &t_cam0_lidar,
            &calib_path,
        )?);
    }
    let rig = Rig {
        base_frame: "cam0".into(),
        lidar_frame: "velodyne".into(),
        t_base_lidar: t_cam0_lidar,
        cameras,
    };
    rig.validate()
        .map_err(|e| invalid(&calib_path, e.to_string()))?;

    let w = DatasetWriter::create(out, overwrite)?;
    let world = z_up();
    let mut nsframes = Vec::new();
    let (mut stamps, mut base_poses, mut lidar_poses) = (Vec::new(), Vec::new(), Vec::new());
    let mut cam_poses: Vec<Vec<Se3>> = vec![Vec::new(); rig.cameras.len()];
    let mut depth_pixels: BTreeMap<String, usize> = BTreeMap::new();
    let mut sky_pixels: BTreeMap<String, usize> = BTreeMap::new();
    let mut lidar_points = 0;
    let total = frames.len();
    for (k, &f) in frames.iter().enumerate() {
        progress(k, total);
        let name = src.frame_name(f);
        let scan_path = velo.join(format!("{name}.bin"));
        let bytes = read_bounded(&scan_path, MAX_SWEEP_BYTES)?;
        let scan = kitti::read_bin_bytes(
            &bytes,
            &scan_path.display().to_string(),
            kitti::KITTI_STRIDE,
        )?;
        let positions = scan.cloud.positions.clone();
        lidar_points += positions.len();
        let (ring, column, rings, columns) = normals::angular_grid(&positions);
        let mut cloud = scan.cloud;
        cloud.set_scalar("ring", ring.iter().map(|&r| r as f32).collect());
        cloud.set_scalar("column", column.iter().map(|&c| c as f32).collect());
        let ply = write_ply_bytes(&cloud).map_err(|e| invalid(&scan_path, e.to_string()))?;
        let key = format!("{k:05}");
        w.write(&format!("lidar/raw/{key}.ply"), &ply)?;
        w.write(&format!("lidar/deskewed/{key}.ply"), &ply)?;

        let t_world_cam0 = world * gt[f];
        let t_world_lidar = t_world_cam0 * t_cam0_lidar;
        let time = times[f];
        stamps.push(time);
        base_poses.push(t_world_cam0);
        lidar_poses.push(t_world_lidar);

        let mut rgbs = Vec::new();
        for (dir, size) in dirs.iter().zip(&full_sizes) {
            rgbs.push(load_image(&dir.join(format!("{name}.png")), *size, scale)?);
        }
        let sweep = products::SweepInput {
            positions: &positions,
            ring: &ring,
            column: &column,
            beams: rings,
            columns,
            min_range: options.min_range,
            t_world_lidar,
        };
        let inputs: Vec<(&RigCamera, &[[u8; 3]])> = rig
            .cameras
            .iter()
            .zip(&rgbs)
            .map(|(c, p)| (c, p.as_slice()))
            .collect();
        let made = products::keyframe_products(gpu, &sweep, &inputs).await?;
        for (i, ((cam, p), rgb)) in rig.cameras.iter().zip(made).zip(&rgbs).enumerate() {
            *depth_pixels.entry(cam.name.clone()).or_insert(0) += p
                .depth
                .iter()
                .filter(|&&d| d > 0 && d != images::SKY_DEPTH)
                .count();
            *sky_pixels.entry(cam.name.clone()).or_insert(0) +=
                p.sky.iter().filter(|&&s| s != 0).count();
            let t_world_cam = t_world_lidar * cam.t_lidar_cam;
            cam_poses[i].push(t_world_cam);
            nsframes.push(products::write_camera(
                &w,
                cam,
                k,
                time,
                &t_world_cam,
                rgb,
                &p,
            )?);
        }
    }
    progress(total, total);
    let n_images = nsframes.len();
    let odometry = Trajectory::new(stamps.clone(), lidar_poses.clone())
        .map_err(|e| invalid(&times_path, e.to_string()))?;
    w.write_poses(
        &stamps,
        &base_poses,
        &lidar_poses,
        &rig,
        &cam_poses,
        &odometry,
    )?;
    w.write_json(
        "calib/lidar.json",
        &serde_json::json!({
            "model": "Velodyne HDL-64E",
            "frame": "velodyne",
            "beams": 64,
            "min_range": options.min_range,
            // The HDL-64E's stated range accuracy (< 2 cm, 1σ): the depth loss's and uncertainty's σ_d.
            "range_noise": 0.02,
        }),
    )?;
    let transforms = products::transforms(nsframes, products::every_tenth_keyframe);
    w.write_json("transforms.json", &transforms)?;
    let summary = KittiSummary {
        path: out.to_path_buf(),
        layout: src.layout,
        sequence: seq
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default(),
        keyframes: total,
        images: n_images,
        frames: frames.clone(),
        poses: poses_name,
        lidar_points,
        depth_pixels,
        sky_pixels,
        skipped,
        notices,
    };
    let manifest = serde_json::json!({
        "layout_version": dataset::LAYOUT_VERSION,
        "generator": "silvr-import-kitti 1",
        "source": seq.display().to_string(),
        "calib": src.calib_files.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
        "times": times_path.display().to_string(),
        "downscale": scale,
        "summary": &summary,
        "world": "KITTI's (cam0 of frame 0: x right, y down, z forward) turned z-up: our (x, y, z) = KITTI's (z, -x, -y); metres",
        "notes": {
            "deskew": match src.layout {
                KittiLayout::Odometry => "none: KITTI odometry sweeps are motion-compensated already and carry no per-point time; lidar/deskewed = lidar/raw, and each sweep pairs with its frame's images through the fixed rig (the cameras are triggered as the lidar faces forward)",
                KittiLayout::Raw => "none: the raw release's synced sweeps carry no per-point time (only each sweep's start and end); taken as one instant at the frame's image stamp, as the odometry benchmark (made from these drives) takes them; lidar/deskewed = lidar/raw (the cameras are triggered as the lidar faces forward, where the sweep and image agree best)",
            },
            "rings": "none in the .bin sweeps: rings and columns from an angular grid (cells about as many as points), as for DGP sweeps",
            "sky": "lidar no-returns above the horizon with nothing above them seed a flood fill over blue-leaning, smooth pixels, stopped by projected returns; the HDL-64E sees only up to about +2 degrees, so higher up the image alone decides (pixels more than 2 degrees above the top beam that look like sky); a white, overexposed sky is not sky-coloured by this rule and stays unmasked (sky_pixels counts what was masked)",
            "cameras": match src.layout {
                KittiLayout::Odometry => "image_2 and image_3 from P2 and P3: rectified pinhole, intrinsics from P's left 3x3, each camera at -K^-1 P[:,3] in cam0's frame with cam0's rotation; lidar to cam0 from Tr",
                KittiLayout::Raw => "image_02 and image_03 (the synced, rectified images) from P_rect_02 and P_rect_03: intrinsics from P's left 3x3, each camera at -K^-1 P[:,3] in rectified cam0's frame; lidar to rectified cam0 = R_rect_00 . [R|T] of calib_velo_to_cam.txt",
            },
            "poses": match src.layout {
                KittiLayout::Odometry => "the sequence's ground truth (T_world_cam0 per frame), a --poses file, or lidar odometry",
                KittiLayout::Raw => "OXTS as the KITTI devkit converts it (Mercator scaled by the first record's latitude; Rz(yaw) Ry(pitch) Rx(roll)), the IMU placed by calib_imu_to_velo.txt, re-based on the first frame's rectified cam0; or a --poses file, or lidar odometry",
            },
            "hold_out": "every keyframe k with k mod 10 = 5 (both cameras)",
        },
        "files": w.files(),
    });
    w.write_json("manifest.json", &manifest)?;
    let path = w.commit()?;
    Ok(KittiSummary { path, ..summary })
}

/// `T_world_cam0` per KITTI frame number (identity where a frame has no sweep) from lidar odometry over the
/// sweeps within `frames`: `Tr · T_lidar0_lidar · Tr⁻¹`, the world cam0 at the first sweep, as KITTI's
/// ground truth is. No deskew: the sweeps carry no point times.
fn lidar_trajectory(
    src: &Source,
    frames: Option<(usize, usize)>,
) -> Result<Vec<Se3>, KittiImportError> {
    let mut lidar = KittiLidar::from_source(src)?;
    if let Some((a, b)) = frames {
        let keep: Vec<usize> = (0..lidar.frames.len())
            .filter(|&k| (a..=b).contains(&lidar.frames[k]))
            .collect();
        lidar.times = keep.iter().map(|&k| lidar.times[k]).collect();
        lidar.frames = keep.iter().map(|&k| lidar.frames[k]).collect();
    }
    let config = crate::odometry::OdometryConfig {
        deskew: crate::odometry::DeskewMode::Off,
        ..Default::default()
    };
    let run = crate::odometry::run(
        &config,
        (0..lidar.frames.len()).map(|k| {
            lidar
                .sweep(k)
                .map_err(|e| crate::odometry::OdometryError::Input(e.to_string()))
        }),
        |_, _| {},
    )
    .map_err(|e| invalid(&src.velo, format!("lidar odometry: {e}")))?;
    let last = lidar.frames.last().copied().unwrap_or(0);
    let mut out = vec![Se3::IDENTITY; last + 1];
    let t_cam0_lidar = src.t_cam0_lidar;
    let tr_inv = t_cam0_lidar.inverse();
    for (&f, p) in lidar.frames.iter().zip(&run.poses) {
        out[f] = t_cam0_lidar * *p * tr_inv;
    }
    Ok(out)
}

/// The lidar of a KITTI odometry sequence or raw drive, for lidar odometry (`silvr odometry SEQ`): the
/// sweeps in frame order with their times, and the recorded trajectory (ground truth or OXTS) in the
/// lidar's frame where there is one.
pub struct KittiLidar {
    velo: PathBuf,
    digits: usize,
    /// KITTI frame numbers with a sweep, ascending.
    pub frames: Vec<usize>,
    /// Time of each of `frames` (s, times.txt or image_02/timestamps.txt).
    pub times: Vec<f64>,
    /// `T_lidar0_lidar` of each of `frames` (`Tr⁻¹ · T_world_cam0 · Tr`, relative to the first), and the
    /// file it came from, when the sequence or drive records a trajectory for every one of them.
    pub ground_truth: Option<(PathBuf, Vec<Se3>)>,
}

impl KittiLidar {
    /// Reads a sequence's `times.txt` and `calib.txt` (a drive's timestamps, calibration and OXTS) and lists
    /// its sweeps.
    pub fn open(seq: &Path) -> Result<Self, KittiImportError> {
        Self::from_source(&Source::open(seq)?)
    }

    fn from_source(src: &Source) -> Result<Self, KittiImportError> {
        let velo = src.velo.clone();
        let frames = numbered_files(&velo, ".bin", src.digits).map_err(|e| {
            invalid(
                &velo,
                format!("{e} (a KITTI sequence has velodyne/NNNNNN.bin, a raw drive velodyne_points/data/)"),
            )
        })?;
        let Some(&last) = frames.last() else {
            return Err(invalid(
                &velo,
                format!("no {}.bin sweep", "N".repeat(src.digits)),
            ));
        };
        if last >= src.times.len() {
            return Err(invalid(
                &src.times_path,
                format!(
                    "{} stamps, but frame {} needs line {}",
                    src.times.len(),
                    src.frame_name(last),
                    last + 1
                ),
            ));
        }
        let times = frames.iter().map(|&f| src.times[f]).collect();
        let ground_truth = match &src.recorded {
            Some((name, gt)) => {
                let tr = src.t_cam0_lidar;
                let w_l: Option<Vec<Se3>> = frames
                    .iter()
                    .map(|&f| gt.get(f).copied().flatten().map(|p| p * tr))
                    .collect();
                if w_l.is_none() && src.layout == KittiLayout::Odometry {
                    return Err(invalid(
                        Path::new(name),
                        format!(
                            "{} poses, but frame {} needs line {}",
                            gt.len(),
                            src.frame_name(last),
                            last + 1
                        ),
                    ));
                }
                w_l.map(|w_l| {
                    let first = w_l[0].inverse();
                    (
                        PathBuf::from(name),
                        w_l.iter().map(|p| first * *p).collect(),
                    )
                })
            }
            None => None,
        };
        Ok(Self {
            velo,
            digits: src.digits,
            frames,
            times,
            ground_truth,
        })
    }

    /// Sweep `k` (of `frames`): no point times.
    pub fn sweep(&self, k: usize) -> Result<crate::odometry::Sweep, KittiImportError> {
        let path = self
            .velo
            .join(format!("{:0w$}.bin", self.frames[k], w = self.digits));
        let bytes = read_bounded(&path, MAX_SWEEP_BYTES)?;
        let scan = kitti::read_bin_bytes(&bytes, &path.display().to_string(), kitti::KITTI_STRIDE)?;
        Ok(crate::odometry::Sweep {
            stamp: self.times[k],
            points: scan.cloud.positions,
            times: None,
        })
    }
}
