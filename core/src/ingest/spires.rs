//! The Oxford Spires folder layout (what SiLVR was built on) ↔ the project's dataset.
//!
//! ```text
//! sensor.yaml                                        the rig (config/sensor.yaml schema, `ingest::config`)
//! raw/cam{0,1,2}/<sec>.<nsec>.{jpg,png}              images; the folder is the `camN` of the camera's topic
//! processed/vilens-slam/slam-poses.csv               `# counter, sec, nsec, x, y, z, qx, qy, qz, qw`, T_world_base
//! processed/vilens-slam/undist-clouds/cloud_<sec>_<nsec>.pcd   motion-undistorted sweeps in the lidar frame at
//!                                                    their stamp (VIEWPOINT = T_world_lidar)
//! ```
//!
//! Import: image sets (one per camera within `camera_sync`) with a SLAM pose close by and an undistorted cloud
//! within half a sweep become keyframes by the rig file's distance/angle rule; each cloud is carried from its
//! stamp to the image time through the trajectory and goes through the same lidar code as everything else.
//! Export writes our dataset in this layout (images as PNG, clouds as binary PCD), which is also how the
//! import is tested end to end.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::DVec3;
use serde::Serialize;

use super::config::{se3_from_t_xyz_q_xyzw, CameraEntry, ConfigError, RigConfig};
use super::pcd::{self, PcdError};
use super::poses::{self, PoseError};
use crate::dataset::{self, png_rgb, DatasetError, DatasetWriter, Transforms};
use crate::geometry::{Se3, Trajectory};
use crate::gpu::{Gpu, GpuError};
use crate::lidar::{normals, products};
use crate::pointcloud::{read_ply, write_ply_bytes, PointCloud};
use crate::rig::{Rig, RigCamera};

const POSES: &str = "processed/vilens-slam/slam-poses.csv";
const CLOUDS: &str = "processed/vilens-slam/undist-clouds";

/// Why a Spires folder could not be read or written; every message names the file.
#[derive(Debug, thiserror::Error)]
pub enum SpiresError {
    #[error("{file}: {reason}")]
    Invalid { file: String, reason: String },
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Poses(#[from] PoseError),
    #[error(transparent)]
    Pcd(#[from] PcdError),
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error("GPU: {0}")]
    Gpu(#[from] GpuError),
}

fn invalid(file: &Path, reason: impl Into<String>) -> SpiresError {
    SpiresError::Invalid {
        file: file.display().to_string(),
        reason: reason.into(),
    }
}

/// What an import wrote.
#[derive(Clone, Debug, Serialize)]
pub struct SpiresSummary {
    pub path: PathBuf,
    pub keyframes: usize,
    pub images: usize,
    pub lidar_points: usize,
    pub dropped: BTreeMap<String, usize>,
}

/// `<sec>.<nsec>` (images) or `cloud_<sec>_<nsec>` (clouds) → seconds; nsec is an integer count.
fn stamp_of(stem: &str) -> Option<f64> {
    let stem = stem.strip_prefix("cloud_").unwrap_or(stem);
    let (s, ns) = stem.split_once(['.', '_'])?;
    let (s, ns) = (s.parse::<i64>().ok()?, ns.parse::<u64>().ok()?);
    (ns < 1_000_000_000).then_some(s as f64 + ns as f64 * 1e-9)
}

fn stamp_name(t: f64, sep: char) -> String {
    let ns = (t * 1e9).round() as i64;
    format!(
        "{}{sep}{:09}",
        ns.div_euclid(1_000_000_000),
        ns.rem_euclid(1_000_000_000)
    )
}

/// A file and its stamp (s).
type Stamped = (f64, PathBuf);

/// Files of `dir` with one of `exts`, with their stamps, sorted by time.
fn stamped_files(dir: &Path, exts: &[&str]) -> Result<Vec<(f64, PathBuf)>, SpiresError> {
    let mut v = Vec::new();
    for e in std::fs::read_dir(dir)
        .map_err(|e| invalid(dir, e.to_string()))?
        .flatten()
    {
        let p = e.path();
        let ext = p
            .extension()
            .and_then(|x| x.to_str())
            .unwrap_or("")
            .to_ascii_lowercase();
        if !exts.contains(&ext.as_str()) {
            continue;
        }
        let stem = p.file_stem().and_then(|s| s.to_str()).unwrap_or("");
        let t =
            stamp_of(stem).ok_or_else(|| invalid(&p, "file name is not a <sec>.<nsec> stamp"))?;
        v.push((t, p));
    }
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    Ok(v)
}

/// The `camN` folder of a camera: from its topic (`/alphasense_driver_ros/cam0/...`), else its label.
fn camera_folder(c: &CameraEntry) -> String {
    c.topic
        .split('/')
        .find(|s| s.len() > 3 && s.starts_with("cam") && s[3..].bytes().all(|b| b.is_ascii_digit()))
        .unwrap_or(&c.label)
        .to_string()
}

fn nearest(list: &[(f64, PathBuf)], t: f64) -> Option<&(f64, PathBuf)> {
    let j = list.partition_point(|(s, _)| *s < t);
    [j.wrapping_sub(1), j]
        .into_iter()
        .filter_map(|j| list.get(j))
        .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()))
}

/// Imports the Spires folder `root` (rig file: `root/sensor.yaml` unless `config` is given).
pub async fn import_spires(
    root: &Path,
    config: Option<&Path>,
    out: &Path,
    overwrite: bool,
    gpu: &Gpu,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<SpiresSummary, SpiresError> {
    let cfg_path = config.map_or_else(|| root.join("sensor.yaml"), Path::to_path_buf);
    let cfg = RigConfig::read(&cfg_path)?;
    let ing = &cfg.ingest;
    let t_base_lidar = match &cfg.sensor.t_base_lidar {
        Some(v) => se3_from_t_xyz_q_xyzw(v)
            .map_err(|e| invalid(&cfg_path, format!("T_base_lidar: {e}")))?,
        None => return Err(invalid(&cfg_path, "no T_base_lidar_t_xyz_q_xyzw")),
    };
    let mut cams = Vec::new();
    for c in &cfg.sensor.cameras {
        let model = cfg
            .camera_model(c)
            .map_err(|e| invalid(&cfg_path, format!("{}: {e}", c.label)))?;
        let t = c.t_cam_lidar.as_deref().ok_or_else(|| {
            invalid(
                &cfg_path,
                format!("{}: no T_cam_lidar_t_xyz_q_xyzw", c.label),
            )
        })?;
        let t_cam_lidar = se3_from_t_xyz_q_xyzw(t)
            .map_err(|e| invalid(&cfg_path, format!("{}: {e}", c.label)))?;
        cams.push(RigCamera {
            name: c.label.clone(),
            model,
            t_lidar_cam: t_cam_lidar.inverse(),
        });
    }
    let rig = Rig {
        base_frame: ing.base_frame.clone(),
        lidar_frame: "lidar".into(),
        t_base_lidar,
        cameras: cams,
    };
    rig.validate()
        .map_err(|e| invalid(&cfg_path, e.to_string()))?;

    let base = poses::read_trajectory(&root.join(POSES))?;
    let lidar_traj = Trajectory::new(
        base.stamps().to_vec(),
        base.poses().iter().map(|p| *p * t_base_lidar).collect(),
    )
    .map_err(|e| invalid(&root.join(POSES), e.to_string()))?;
    let clouds = stamped_files(&root.join(CLOUDS), &["pcd"])?;
    let images: Vec<Vec<(f64, PathBuf)>> = cfg
        .sensor
        .cameras
        .iter()
        .map(|c| {
            stamped_files(
                &root.join("raw").join(camera_folder(c)),
                &["jpg", "jpeg", "png"],
            )
        })
        .collect::<Result<_, _>>()?;
    if clouds.is_empty() {
        return Err(invalid(
            &root.join(CLOUDS),
            "no cloud_<sec>_<nsec>.pcd files",
        ));
    }
    if images[0].is_empty() {
        return Err(invalid(
            root,
            format!("no images in raw/{}", camera_folder(&cfg.sensor.cameras[0])),
        ));
    }
    let max_pose_gap = cfg.sensor.max_time_diff_camera_and_pose.unwrap_or(0.05);
    let max_cloud_gap = 0.05;

    // Keyframes.
    let mut dropped: BTreeMap<String, usize> = BTreeMap::new();
    let mut chosen: Vec<(f64, Vec<Stamped>, Stamped, Se3)> = Vec::new();
    let mut last: Option<Se3> = None;
    for lead in &images[0] {
        let t = lead.0;
        let mut set = vec![lead.clone()];
        for list in &images[1..] {
            match nearest(list, t) {
                Some(r) if (r.0 - t).abs() <= ing.camera_sync => set.push(r.clone()),
                _ => break,
            }
        }
        if set.len() < images.len() {
            *dropped
                .entry("image set: a camera has no image within camera_sync".into())
                .or_default() += 1;
            continue;
        }
        let gap = nearest(
            &base
                .stamps()
                .iter()
                .map(|&s| (s, PathBuf::new()))
                .collect::<Vec<_>>(),
            t,
        )
        .map_or(f64::INFINITY, |(s, _)| (s - t).abs());
        let Some(pose) = lidar_traj.at(t).filter(|_| gap <= max_pose_gap) else {
            *dropped
                .entry("image set: no SLAM pose within max_time_diff_camera_and_pose".into())
                .or_default() += 1;
            continue;
        };
        let Some(cloud) = nearest(&clouds, t)
            .filter(|c| (c.0 - t).abs() <= max_cloud_gap && lidar_traj.at(c.0).is_some())
        else {
            *dropped
                .entry("image set: no undistorted cloud within 50 ms".into())
                .or_default() += 1;
            continue;
        };
        if let Some(prev) = last {
            if prev.distance_to(&pose) < ing.keyframe_distance
                && prev.angle_to(&pose).to_degrees() < ing.keyframe_angle_deg
            {
                *dropped
                    .entry("image set: not a keyframe (moved too little)".into())
                    .or_default() += 1;
                continue;
            }
        }
        last = Some(pose);
        chosen.push((t, set, cloud.clone(), pose));
        if ing.max_keyframes.is_some_and(|m| chosen.len() >= m) {
            break;
        }
    }
    if chosen.is_empty() {
        return Err(invalid(root, format!("no keyframe (dropped: {dropped:?})")));
    }

    let w = DatasetWriter::create(out, overwrite)?;
    let mut frames = Vec::new();
    let (mut times, mut lidar_poses, mut base_poses) = (Vec::new(), Vec::new(), Vec::new());
    let mut cam_poses: Vec<Vec<Se3>> = vec![Vec::new(); rig.cameras.len()];
    let mut lidar_points = 0;
    let total = chosen.len();
    for (k, (t, set, (t_cloud, cloud_path), t_world_lidar)) in chosen.into_iter().enumerate() {
        progress(k, total);
        let name = format!("{k:05}");
        let pcd = pcd::read_pcd(&cloud_path)?;
        let raw = pcd.cloud;
        // Carry the cloud from its stamp to the image time.
        let at_cloud = lidar_traj.at(t_cloud).expect("checked when choosing");
        let move_to_image = t_world_lidar.inverse() * at_cloud;
        let positions: Vec<DVec3> = raw
            .positions
            .iter()
            .map(|&p| move_to_image.transform_point(p))
            .collect();
        lidar_points += positions.len();
        let (ring, column, beams, columns) = match raw.scalar("ring") {
            Some(r) => {
                let ring: Vec<u16> = r
                    .iter()
                    .map(|&v| {
                        if (0.0..65535.0).contains(&v) {
                            v as u16
                        } else {
                            u16::MAX
                        }
                    })
                    .collect();
                let beams = ring
                    .iter()
                    .filter(|&&v| v != u16::MAX)
                    .max()
                    .map_or(1, |&m| m as usize + 1);
                let columns = normals::columns_from_azimuths(&raw.positions, &ring).unwrap_or(1024);
                let column = raw
                    .positions
                    .iter()
                    .map(|&p| normals::column_of(p, columns))
                    .collect();
                (ring, column, beams, columns)
            }
            None => normals::angular_grid(&raw.positions),
        };
        let mut cloud = PointCloud::from_positions(raw.positions.clone());
        cloud.scalars = raw.scalars.clone();
        cloud.set_scalar("ring", ring.iter().map(|&r| r as f32).collect());
        cloud.set_scalar("column", column.iter().map(|&c| c as f32).collect());
        let ply =
            |pc: &PointCloud| write_ply_bytes(pc).map_err(|e| invalid(&cloud_path, e.to_string()));
        w.write(&format!("lidar/raw/{name}.ply"), &ply(&cloud)?)?;
        cloud.positions = positions.clone();
        w.write(&format!("lidar/deskewed/{name}.ply"), &ply(&cloud)?)?;

        let mut rgbs = Vec::new();
        for ((c, (_, path)), _) in rig.cameras.iter().zip(&set).zip(0..) {
            let img = image::open(path)
                .map_err(|e| invalid(path, e.to_string()))?
                .to_rgb8();
            if (img.width(), img.height()) != (c.model.width, c.model.height) {
                return Err(invalid(
                    path,
                    format!(
                        "image is {}x{}, sensor.yaml says {}x{}",
                        img.width(),
                        img.height(),
                        c.model.width,
                        c.model.height
                    ),
                ));
            }
            rgbs.push(img.pixels().map(|p| p.0).collect::<Vec<[u8; 3]>>());
        }
        let sweep = products::SweepInput {
            positions: &positions,
            ring: &ring,
            column: &column,
            beams,
            columns,
            min_range: ing.min_range,
            t_world_lidar,
        };
        let inputs: Vec<(&RigCamera, &[[u8; 3]])> = rig
            .cameras
            .iter()
            .zip(&rgbs)
            .map(|(c, p)| (c, p.as_slice()))
            .collect();
        let made = products::keyframe_products(gpu, &sweep, &inputs).await?;
        for (ci, ((cam, p), (rgb, (t_cam, _)))) in rig
            .cameras
            .iter()
            .zip(made)
            .zip(rgbs.iter().zip(&set))
            .enumerate()
        {
            let t_world_cam = lidar_traj.at(*t_cam).unwrap_or(t_world_lidar) * cam.t_lidar_cam;
            cam_poses[ci].push(t_world_cam);
            frames.push(products::write_camera(
                &w,
                cam,
                k,
                *t_cam,
                &t_world_cam,
                rgb,
                &p,
            )?);
        }
        times.push(t);
        lidar_poses.push(t_world_lidar);
        base_poses.push(t_world_lidar * t_base_lidar.inverse());
    }
    progress(total, total);
    w.write_poses(
        &times,
        &base_poses,
        &lidar_poses,
        &rig,
        &cam_poses,
        &lidar_traj,
    )?;
    let n_images = frames.len();
    let transforms = products::transforms(frames, products::every_tenth_keyframe);
    w.write_json("transforms.json", &transforms)?;
    let summary = SpiresSummary {
        path: out.to_path_buf(),
        keyframes: total,
        images: n_images,
        lidar_points,
        dropped,
    };
    let manifest = serde_json::json!({
        "layout_version": dataset::LAYOUT_VERSION,
        "generator": "silvr-import-spires 1",
        "source": root.display().to_string(),
        "config": &cfg,
        "summary": &summary,
    });
    w.write_json("manifest.json", &manifest)?;
    let path = w.commit()?;
    Ok(SpiresSummary { path, ..summary })
}

/// Writes `dataset` in the Spires layout at `out` (which must not exist): `sensor.yaml` from
/// `calib/rig.json`, images as PNG named by their time, each keyframe's deskewed sweep as the undistorted
/// cloud at the image time, and `slam-poses.csv` from the odometry (or keyframe) poses of the base.
pub fn export_spires(dataset: &Path, out: &Path) -> Result<usize, SpiresError> {
    let rig_path = dataset.join("calib/rig.json");
    let rig: Rig = serde_json::from_str(
        &std::fs::read_to_string(&rig_path).map_err(|e| invalid(&rig_path, e.to_string()))?,
    )
    .map_err(|e| invalid(&rig_path, e.to_string()))?;
    let t = Transforms::read(&dataset.join("transforms.json"))?;
    let lidar = dataset::read_tum(&dataset.join("poses/lidar_tum.txt"))?;
    let odo_path = dataset.join("poses/odometry_lidar_tum.txt");
    let odo = if odo_path.exists() {
        dataset::read_tum(&odo_path)?
    } else {
        lidar.clone()
    };
    let w = DatasetWriter::create(out, false)?;
    let mut cfg = RigConfig::from_rig(&rig, |i| {
        format!("/alphasense_driver_ros/cam{i}/debayered/image/compressed")
    });
    // Spires' own file has no ingest block.
    cfg.ingest = Default::default();
    w.write("sensor.yaml", cfg.to_yaml().as_bytes())?;
    let lidar_base = rig.t_base_lidar.inverse();
    let base = Trajectory::new(
        odo.stamps().to_vec(),
        odo.poses().iter().map(|p| *p * lidar_base).collect(),
    )
    .map_err(|e| invalid(&odo_path, e.to_string()))?;
    w.write(POSES, poses::spires_string(&base).as_bytes())?;
    let mut n = 0;
    for f in &t.frames {
        let (Some(cam), Some(time)) = (f.camera.as_deref(), f.time) else {
            return Err(invalid(
                &dataset.join("transforms.json"),
                format!("{}: needs camera and time", f.file_path),
            ));
        };
        let i = rig
            .cameras
            .iter()
            .position(|c| c.name == cam)
            .ok_or_else(|| invalid(&rig_path, format!("no camera {cam}")))?;
        let src = dataset.join(&f.file_path);
        let (iw, ih, px) = dataset::read_rgb(&src)?;
        w.write(
            &format!("raw/cam{i}/{}.png", stamp_name(time, '.')),
            &png_rgb(iw, ih, &px),
        )?;
        n += 1;
    }
    for (k, (&time, pose)) in lidar.stamps().iter().zip(lidar.poses()).enumerate() {
        let ply = dataset.join(format!("lidar/deskewed/{k:05}.ply"));
        let mut pc = read_ply(&ply).map_err(|e| invalid(&ply, e.to_string()))?;
        let keep: Vec<usize> = (0..pc.len())
            .filter(|&i| pc.positions[i].is_finite())
            .collect();
        pc = pc.select(&keep);
        pc.scalars.retain(|(n, _)| n == "intensity" || n == "ring");
        pc.normals = None;
        pc.colors = None;
        w.write(
            &format!("{CLOUDS}/cloud_{}.pcd", stamp_name(time, '_')),
            &pcd::write_pcd_bytes(&pc, pose),
        )?;
    }
    w.commit()?;
    Ok(n)
}
