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
    /// `odometry`.
    pub layout: String,
    /// The sequence folder's name (`00`).
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

/// Frame numbers of the `NNNNNN.png` files in `dir`, sorted.
fn png_frames(dir: &Path) -> Result<Vec<usize>, KittiImportError> {
    let mut frames: Vec<usize> = std::fs::read_dir(dir)
        .map_err(|e| invalid(dir, e.to_string()))?
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().to_str()?.to_string();
            let stem = name.strip_suffix(".png")?;
            (!stem.is_empty() && stem.bytes().all(|b| b.is_ascii_digit()))
                .then(|| stem.parse().ok())
                .flatten()
        })
        .collect();
    frames.sort_unstable();
    Ok(frames)
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

/// Imports the KITTI odometry sequence folder `seq` (`…/sequences/NN`) into a dataset at `out`.
pub async fn import_kitti(
    seq: &Path,
    out: &Path,
    overwrite: bool,
    options: KittiOptions,
    gpu: &Gpu,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<KittiSummary, KittiImportError> {
    let calib_path = seq.join("calib.txt");
    if !calib_path.is_file() {
        let sequences = seq.join("sequences");
        if sequences.is_dir() {
            let mut names: Vec<String> = std::fs::read_dir(&sequences)
                .map_err(|e| invalid(&sequences, e.to_string()))?
                .flatten()
                .filter(|e| e.path().join("calib.txt").is_file())
                .filter_map(|e| e.file_name().to_str().map(str::to_string))
                .collect();
            names.sort();
            return Err(invalid(
                seq,
                format!(
                    "a KITTI odometry root: give one sequence folder, e.g. {} (sequences with calib.txt: {})",
                    sequences.join(names.first().map_or("00", String::as_str)).display(),
                    if names.is_empty() { "none".to_string() } else { names.join(", ") }
                ),
            ));
        }
        return Err(invalid(
            seq,
            "not a KITTI odometry sequence: no calib.txt (expected calib.txt, times.txt, image_2/, \
             image_3/, velodyne/)",
        ));
    }
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

    // The trajectory: given, the ground truth beside the sequence, or lidar odometry (asked for, or with
    // a notice when there is neither).
    let mut notices = Vec::new();
    let tried = pose_candidates(seq);
    let file = match &options.poses {
        Some(p) => Some(p.clone()),
        None if options.lidar_odometry => None,
        None => tried.iter().find(|p| p.is_file()).cloned(),
    };
    let (poses_name, gt): (String, Vec<Se3>) = match file {
        Some(poses_path) => {
            let name = poses_path.display().to_string();
            // Frame i's pose is line i: the stamps come from times.txt by index, so a period of 1 is a
            // placeholder.
            let gt = poses::parse_kitti(
                &read_text(&poses_path, MAX_TEXT_BYTES)?,
                &name,
                KittiTimes::Period(1.0),
            )?;
            (name, gt.poses().to_vec())
        }
        None => {
            if !options.lidar_odometry {
                notices.push(format!(
                    "no trajectory: KITTI publishes ground truth for sequences 00-10 only and none was found \
                     ({}); using lidar odometry over velodyne/ (--poses lidar says so explicitly; --poses FILE \
                     gives one, KITTI format: T_world_cam0 of frame i on line i)",
                    tried
                        .iter()
                        .map(|p| p.display().to_string())
                        .collect::<Vec<_>>()
                        .join(", ")
                ));
            }
            (
                "lidar odometry (velodyne/)".to_string(),
                lidar_trajectory(seq, &t_cam0_lidar, options.frames)?,
            )
        }
    };
    let poses_path = PathBuf::from(&poses_name);
    let gt = gt.as_slice();

    // Frames: every image_2 frame with its image_3 frame and sweep, within the selection.
    let dirs = [seq.join("image_2"), seq.join("image_3")];
    let velo = seq.join("velodyne");
    let mut skipped = Vec::new();
    let mut frames = Vec::new();
    let every = options.every.max(1);
    let selected = png_frames(&dirs[0])?
        .into_iter()
        .filter(|f| options.frames.is_none_or(|(a, b)| (a..=b).contains(f)));
    for (i, f) in selected.enumerate() {
        if i % every != 0 {
            continue;
        }
        let name = format!("{f:06}");
        if !dirs[1].join(format!("{name}.png")).is_file() {
            skipped.push(format!("{name}: no image_3/{name}.png"));
        } else if !velo.join(format!("{name}.bin")).is_file() {
            skipped.push(format!("{name}: no velodyne/{name}.bin"));
        } else {
            frames.push(f);
        }
    }
    let Some(&last) = frames.last() else {
        return Err(invalid(
            seq,
            format!(
                "no frame with image_2/NNNNNN.png, image_3/NNNNNN.png and velodyne/NNNNNN.bin{}{}",
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
                "{} stamps, but frame {last:06} needs line {}",
                times.len(),
                last + 1
            ),
        ));
    }
    if last >= gt.len() {
        return Err(invalid(
            &poses_path,
            format!(
                "{} poses, but frame {last:06} needs line {}",
                gt.len(),
                last + 1
            ),
        ));
    }

    // The rig: base = cam0, the lidar by Tr, both colour cameras at their first image's size.
    let scale = options.downscale.max(1);
    let first = format!("{:06}.png", frames[0]);
    let mut cameras = Vec::new();
    let mut full_sizes = Vec::new();
    for ((dir, p), name) in dirs.iter().zip(&projections).zip(["image_2", "image_3"]) {
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
        let name = format!("{f:06}");
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
        layout: "odometry".into(),
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
        "calib": calib_path.display().to_string(),
        "times": times_path.display().to_string(),
        "downscale": scale,
        "summary": &summary,
        "world": "KITTI's (cam0 of frame 0: x right, y down, z forward) turned z-up: our (x, y, z) = KITTI's (z, -x, -y); metres",
        "notes": {
            "deskew": "none: KITTI odometry sweeps are motion-compensated already and carry no per-point time; lidar/deskewed = lidar/raw, and each sweep pairs with its frame's images through the fixed rig (the cameras are triggered as the lidar faces forward)",
            "rings": "none in the .bin sweeps: rings and columns from an angular grid (cells about as many as points), as for DGP sweeps",
            "sky": "lidar no-returns above the horizon with nothing above them seed a flood fill over blue-leaning, smooth pixels, stopped by projected returns; the HDL-64E sees only up to about +2 degrees, so higher up the image alone decides (pixels more than 2 degrees above the top beam that look like sky); a white, overexposed sky is not sky-coloured by this rule and stays unmasked (sky_pixels counts what was masked)",
            "cameras": "image_2 and image_3 from P2 and P3: rectified pinhole, intrinsics from P's left 3x3, each camera at -K^-1 P[:,3] in cam0's frame with cam0's rotation; lidar to cam0 from Tr",
            "hold_out": "every keyframe k with k mod 10 = 5 (both cameras)",
        },
        "files": w.files(),
    });
    w.write_json("manifest.json", &manifest)?;
    let path = w.commit()?;
    Ok(KittiSummary { path, ..summary })
}

/// `T_world_cam0` per KITTI frame number (identity where a frame has no sweep) from lidar odometry over the
/// sequence's sweeps within `frames`: `Tr · T_lidar0_lidar · Tr⁻¹`, the world cam0 at the first sweep, as
/// KITTI's ground truth is. The sweeps are motion-compensated: no deskew.
fn lidar_trajectory(
    seq: &Path,
    t_cam0_lidar: &Se3,
    frames: Option<(usize, usize)>,
) -> Result<Vec<Se3>, KittiImportError> {
    let mut lidar = KittiLidar::open(seq)?;
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
    let velo = seq.join("velodyne");
    let run = crate::odometry::run(
        &config,
        (0..lidar.frames.len()).map(|k| {
            lidar
                .sweep(k)
                .map_err(|e| crate::odometry::OdometryError::Input(e.to_string()))
        }),
        |_, _| {},
    )
    .map_err(|e| invalid(&velo, format!("lidar odometry: {e}")))?;
    let last = lidar.frames.last().copied().unwrap_or(0);
    let mut out = vec![Se3::IDENTITY; last + 1];
    let tr_inv = t_cam0_lidar.inverse();
    for (&f, p) in lidar.frames.iter().zip(&run.poses) {
        out[f] = *t_cam0_lidar * *p * tr_inv;
    }
    Ok(out)
}

/// The lidar of a KITTI odometry sequence, for lidar odometry (`silvr odometry SEQ`): the sweeps in frame
/// order with their times, and the ground truth in the lidar's frame where the sequence has one.
pub struct KittiLidar {
    velo: PathBuf,
    /// KITTI frame numbers with a sweep, ascending.
    pub frames: Vec<usize>,
    /// Time of each of `frames` (s, times.txt).
    pub times: Vec<f64>,
    /// `T_lidar0_lidar` of each of `frames` (`Tr⁻¹ · T_world_cam0 · Tr`, relative to the first), and the
    /// file it came from, when ground truth was found beside the sequence.
    pub ground_truth: Option<(PathBuf, Vec<Se3>)>,
}

impl KittiLidar {
    /// Reads the sequence folder's `times.txt`, `calib.txt` (for the ground truth) and lists `velodyne/`.
    pub fn open(seq: &Path) -> Result<Self, KittiImportError> {
        let velo = seq.join("velodyne");
        let mut frames: Vec<usize> = std::fs::read_dir(&velo)
            .map_err(|e| {
                invalid(
                    &velo,
                    format!("{e} (a KITTI odometry sequence has velodyne/NNNNNN.bin)"),
                )
            })?
            .flatten()
            .filter_map(|e| {
                let name = e.file_name();
                let s = name.to_str()?;
                let stem = s.strip_suffix(".bin")?;
                (stem.len() == 6).then(|| stem.parse().ok()).flatten()
            })
            .collect();
        frames.sort_unstable();
        if frames.is_empty() {
            return Err(invalid(&velo, "no NNNNNN.bin sweep"));
        }
        let times_path = seq.join("times.txt");
        let all_times = kitti::parse_times(
            &read_text(&times_path, MAX_TEXT_BYTES)?,
            &times_path.display().to_string(),
        )?;
        let last = *frames.last().unwrap_or(&0);
        if last >= all_times.len() {
            return Err(invalid(
                &times_path,
                format!(
                    "{} stamps, but frame {last:06} needs line {}",
                    all_times.len(),
                    last + 1
                ),
            ));
        }
        let times = frames.iter().map(|&f| all_times[f]).collect();
        let calib_path = seq.join("calib.txt");
        let ground_truth = match pose_candidates(seq).into_iter().find(|p| p.is_file()) {
            Some(path) if calib_path.is_file() => {
                let calib = kitti::parse_calib(
                    &read_text(&calib_path, MAX_CALIB_BYTES)?,
                    &calib_path.display().to_string(),
                )?;
                let tr = calib.rigid("Tr")?;
                let gt = poses::parse_kitti(
                    &read_text(&path, MAX_TEXT_BYTES)?,
                    &path.display().to_string(),
                    KittiTimes::Period(1.0),
                )?;
                let gt = gt.poses();
                if last >= gt.len() {
                    return Err(invalid(
                        &path,
                        format!(
                            "{} poses, but frame {last:06} needs line {}",
                            gt.len(),
                            last + 1
                        ),
                    ));
                }
                let w_l = |f: usize| gt[f] * tr;
                let first = w_l(frames[0]).inverse();
                Some((path, frames.iter().map(|&f| first * w_l(f)).collect()))
            }
            _ => None,
        };
        Ok(Self {
            velo,
            frames,
            times,
            ground_truth,
        })
    }

    /// Sweep `k` (of `frames`): motion-compensated already, so no point times.
    pub fn sweep(&self, k: usize) -> Result<crate::odometry::Sweep, KittiImportError> {
        let path = self.velo.join(format!("{:06}.bin", self.frames[k]));
        let bytes = read_bounded(&path, MAX_SWEEP_BYTES)?;
        let scan = kitti::read_bin_bytes(&bytes, &path.display().to_string(), kitti::KITTI_STRIDE)?;
        Ok(crate::odometry::Sweep {
            stamp: self.times[k],
            points: scan.cloud.positions,
            times: None,
        })
    }
}
