//! Writes a synthetic world as a dataset (layout in `DATASET.md`): sensor data as a real rig would give it,
//! the lidar products the training reads (deskewed sweeps, per-camera depth, normals, sky masks — made by
//! the same `lidar` code that processes real data, projection on the GPU), and exact ground truth.

use std::collections::{BTreeMap, HashSet};
use std::hash::BuildHasherDefault;
use std::path::{Path, PathBuf};

use glam::{DVec2, DVec3};
use rayon::prelude::*;
use serde::Serialize;

use super::raycast::{Scene, Shape, GROUND};
use super::sensors::{render_rays, simulate_sweep, CameraRays, LidarNoise, RenderOptions, Sweep};
use super::world::{Label, World};
use super::{prior, Preset};
use crate::dataset::{self, png_gray16, png_gray8, png_rgb, DatasetError, DatasetWriter, NsFrame};
use crate::eval::occupancy::OccupancyGrid;
use crate::geometry::{Se3, Trajectory};
use crate::gpu::{Gpu, GpuError};
use crate::lidar::{deskew, images, products};
use crate::pointcloud::{write_ply_bytes, PointCloud, VoxelHasher};
use crate::rig::RigCamera;

/// Generator version, recorded in the manifest; bump when output bytes change for the same seed.
/// 3: a building's downward faces (the campus's passages and arcades overhead) are coloured as its roof, not
/// as a facade, which changes the town's `gt/mesh.ply` (faces no sensor sees) and nothing else.
pub const GENERATOR_VERSION: &str = "silvr-synth 3";

/// Why generation failed.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error("GPU: {0}")]
    Gpu(#[from] GpuError),
    #[error("{0}")]
    Other(String),
}

/// Progress of a long job: a stage name and a count.
#[derive(Clone, Debug)]
pub struct Progress<'a> {
    pub stage: &'a str,
    pub done: usize,
    pub total: usize,
}

/// What was written.
#[derive(Clone, Debug, Serialize)]
pub struct SynthSummary {
    pub path: PathBuf,
    pub keyframes: usize,
    pub images: usize,
    pub lidar_points: usize,
    pub gt_points: usize,
    pub files: usize,
}

/// Per-keyframe record in the manifest.
#[derive(Clone, Debug, Serialize)]
struct KeyframeRecord {
    index: usize,
    sweep_start: f64,
    image_time: f64,
    raw_points: usize,
    deskewed_dropped: usize,
}

#[derive(Serialize)]
struct Manifest<'a> {
    layout_version: u32,
    generator: &'a str,
    preset: &'a Preset,
    keyframes: Vec<KeyframeRecord>,
    cameras: Vec<&'a str>,
    labels: BTreeMap<u8, &'static str>,
    encodings: BTreeMap<&'static str, &'static str>,
    files: BTreeMap<String, u64>,
}

fn frame_name(k: usize) -> String {
    format!("{k:05}")
}

/// The lidar's trajectory as an odometry system would report it: T_world_lidar at 100 Hz. Deskewing reads
/// this (interpolated), never the analytic motion, exactly as it would with real data.
pub fn odometry(preset: &Preset) -> Trajectory {
    let t_end = preset.sweep_start(preset.keyframes) + preset.lidar.sweep_duration() + 0.1;
    let n = (t_end * 100.0).ceil() as usize + 1;
    let stamps: Vec<f64> = (0..n).map(|i| -0.05 + i as f64 * 0.01).collect();
    let poses = stamps.iter().map(|&t| preset.t_world_lidar(t)).collect();
    Trajectory::new(stamps, poses).expect("sorted finite stamps")
}

fn sweep_cloud(sweep: &Sweep, positions: &[DVec3]) -> PointCloud {
    let mut pc = PointCloud::from_positions(positions.to_vec());
    pc.set_scalar(
        "intensity",
        sweep.points.iter().map(|p| p.intensity).collect(),
    );
    pc.set_scalar("ring", sweep.points.iter().map(|p| p.ring as f32).collect());
    pc.set_scalar(
        "column",
        sweep.points.iter().map(|p| p.column as f32).collect(),
    );
    pc.set_scalar(
        "time_offset",
        sweep
            .points
            .iter()
            .map(|p| (p.time - sweep.t0) as f32)
            .collect(),
    );
    pc
}

fn ply(pc: &PointCloud, rel: &str) -> Result<Vec<u8>, SynthError> {
    write_ply_bytes(pc).map_err(|e| SynthError::Other(format!("{rel}: {e}")))
}

/// Receives the sensor data as the rig recorded it, in time order: the odometry first, then per keyframe
/// its camera images and the raw sweep. `silvr synth --mcap` writes a ROS 2 bag with it
/// (`synthetic::bag`), which `silvr ingest` turns back into this dataset.
pub trait SensorRecorder {
    /// Before the first keyframe: `T_world_lidar` as the odometry system reports it.
    fn begin(&mut self, preset: &Preset, odometry: &Trajectory) -> Result<(), String>;
    /// Camera `camera`'s image of keyframe `k`, taken at `time`.
    fn image(&mut self, k: usize, camera: usize, time: f64, rgb: &[[u8; 3]]) -> Result<(), String>;
    /// Keyframe `k`'s raw sweep (sensor frame at each point's firing time).
    fn sweep(&mut self, k: usize, sweep: &Sweep) -> Result<(), String>;
    /// After the last keyframe.
    fn finish(&mut self) -> Result<(), String>;
}

/// Generates `preset` into `out` (which must not exist unless `overwrite`).
pub async fn generate(
    preset: &Preset,
    gpu: &Gpu,
    out: &Path,
    overwrite: bool,
    progress: &mut dyn FnMut(Progress),
) -> Result<SynthSummary, SynthError> {
    generate_recording(preset, gpu, out, overwrite, progress, None).await
}

/// [`generate`], also handing the sensor data to `recorder` (see [`SensorRecorder`]). The recorder finishes
/// before the dataset is committed, so a failed recording leaves no dataset behind.
pub async fn generate_recording(
    preset: &Preset,
    gpu: &Gpu,
    out: &Path,
    overwrite: bool,
    progress: &mut dyn FnMut(Progress),
    mut recorder: Option<&mut dyn SensorRecorder>,
) -> Result<SynthSummary, SynthError> {
    let world = World::generate(preset.world.clone(), preset.seed);
    let o = DatasetWriter::create(out, overwrite)?;
    let odo = odometry(preset);
    if let Some(rec) = recorder.as_deref_mut() {
        rec.begin(preset, &odo).map_err(SynthError::Other)?;
    }
    let cams: Vec<&str> = preset.rig.cameras.iter().map(|c| c.name.as_str()).collect();
    let seen_voxel = preset.observed_voxel;
    let mut seen: HashSet<[i64; 3], BuildHasherDefault<VoxelHasher>> = HashSet::default();
    let vkey = |p: DVec3| -> [i64; 3] { (p / seen_voxel).floor().as_i64vec3().to_array() };
    let mut observed =
        OccupancyGrid::new(preset.observed_voxel).map_err(|e| SynthError::Other(e.to_string()))?;
    let mut frames = Vec::new();
    let mut records = Vec::new();
    let mut lidar_points = 0;
    let mut base_poses = Vec::new();
    let mut lidar_poses = Vec::new();
    let mut cam_poses: Vec<Vec<Se3>> = vec![Vec::new(); cams.len()];
    let mut image_times = Vec::new();
    let total = preset.keyframes;
    let rays: Vec<CameraRays> = preset
        .rig
        .cameras
        .iter()
        .map(|c| CameraRays::new(&c.model, preset.supersample))
        .collect();

    for k in 0..preset.keyframes {
        progress(Progress {
            stage: "keyframes",
            done: k,
            total,
        });
        let name = frame_name(k);
        let t0 = preset.sweep_start(k);
        let t_img = preset.image_time(k);
        image_times.push(t_img);
        base_poses.push(preset.t_world_base(t_img));
        let t_world_lidar = preset.t_world_lidar(t_img);
        lidar_poses.push(t_world_lidar);
        let pose_at = |t: f64| preset.t_world_lidar(t);
        let seed_k = preset.seed.wrapping_mul(1_000_003).wrapping_add(k as u64);

        // Lidar: the raw, motion-distorted sweep, then deskewed to the image time with the odometry.
        let sweep = simulate_sweep(
            &world,
            &preset.lidar,
            &pose_at,
            t0,
            None,
            LidarNoise {
                range: true,
                dropout: true,
            },
            seed_k,
        );
        lidar_points += sweep.points.len();
        let raw: Vec<DVec3> = sweep.points.iter().map(|p| p.position).collect();
        let times: Vec<f64> = sweep.points.iter().map(|p| p.time).collect();
        let rel = format!("lidar/raw/{name}.ply");
        o.write(&rel.clone(), &ply(&sweep_cloud(&sweep, &raw), &rel)?)?;
        let desk = deskew::deskew(&raw, &times, &odo, t_img)
            .map_err(|e| SynthError::Other(format!("keyframe {k}: {e}")))?;
        let rel = format!("lidar/deskewed/{name}.ply");
        o.write(
            &rel.clone(),
            &ply(&sweep_cloud(&sweep, &desk.positions), &rel)?,
        )?;
        records.push(KeyframeRecord {
            index: k,
            sweep_start: t0,
            image_time: t_img,
            raw_points: sweep.points.len(),
            deskewed_dropped: desk.dropped,
        });
        // Ground truth of what the lidar observed: exact returns, and free space along their rays.
        let exact = simulate_sweep(
            &world,
            &preset.lidar,
            &pose_at,
            t0,
            None,
            LidarNoise {
                range: false,
                dropout: false,
            },
            seed_k,
        );
        // Free space along the rays: one discretised scan per sweep from the sensor's mid-sweep position
        // (OctoMap-style, each free voxel updated once). The true origins differ by at most half a sweep of
        // motion (~7 cm), below the grid's 10 cm; the occupied endpoints are exact.
        let ends: Vec<DVec3> = exact
            .points
            .iter()
            .map(|p| preset.t_world_lidar(p.time).transform_point(p.position))
            .collect();
        for w in &ends {
            seen.insert(vkey(*w));
        }
        observed.insert_scan(t_world_lidar.trans, &ends);

        let mut rgbs = Vec::with_capacity(cams.len());
        for (ci, cam) in preset.rig.cameras.iter().enumerate() {
            let t_world_cam = t_world_lidar * cam.t_lidar_cam;
            cam_poses[ci].push(t_world_cam);
            let model = &cam.model;
            let (w, h) = (model.width, model.height);
            let frame = render_rays(
                &world,
                &rays[ci],
                &t_world_cam,
                RenderOptions {
                    supersample: preset.supersample,
                    noise_std: preset.pixel_noise,
                    seed: seed_k ^ ((ci as u64 + 1) << 40),
                },
            );
            let cn = cam.name.as_str();
            // The image itself is written with the lidar products below (`products::write_camera`).
            let gt_depth: Vec<u16> = frame
                .range
                .iter()
                .map(|&r| images::encode_depth(r))
                .collect();
            o.write(
                &format!("gt/depth/{cn}/{name}.png"),
                &png_gray16(w, h, &gt_depth),
            )?;
            let gt_n: Vec<[u8; 3]> = frame
                .normal
                .iter()
                .map(|n| images::encode_normal(glam::Vec3::from_array(*n).as_dvec3()))
                .collect();
            o.write(
                &format!("gt/normals/{cn}/{name}.png"),
                &png_rgb(w, h, &gt_n),
            )?;
            let gt_sky: Vec<u8> = frame
                .label
                .iter()
                .map(|&l| if l == Label::Sky as u8 { 255 } else { 0 })
                .collect();
            o.write(
                &format!("gt/sky/{cn}/{name}.png"),
                &png_gray8(w, h, &gt_sky),
            )?;
            o.write(
                &format!("gt/semantic/{cn}/{name}.png"),
                &png_gray8(w, h, &frame.label),
            )?;
            // What the camera observed: every pixel's surface; free space along every 4th pixel's ray (in x and y).
            // Rows in parallel; each row's keys deduplicated before they meet the shared set.
            let rows: Vec<(Vec<[i64; 3]>, Vec<DVec3>)> = (0..h)
                .into_par_iter()
                .map(|y| {
                    let (mut keys, mut ends) = (Vec::new(), Vec::new());
                    for x in 0..w {
                        let r = frame.range[(y * w + x) as usize] as f64;
                        if r <= 0.0 {
                            continue;
                        }
                        let Some(dir) = rays[ci].centre(x, y) else {
                            continue;
                        };
                        let p = t_world_cam.transform_point(dir * r);
                        keys.push(vkey(p));
                        if x % 4 == 0 && y % 4 == 0 {
                            ends.push(p);
                        }
                    }
                    keys.sort_unstable();
                    keys.dedup();
                    (keys, ends)
                })
                .collect();
            let mut cam_ends = Vec::new();
            for (keys, ends) in rows {
                seen.extend(keys);
                cam_ends.extend(ends);
            }

            observed.insert_scan(t_world_cam.trans, &cam_ends);

            rgbs.push(frame.rgb);
        }

        // Lidar supervision of every camera, exactly as for real data (`silvr ingest` runs the same code).
        let ring: Vec<u16> = sweep.points.iter().map(|p| p.ring).collect();
        let column: Vec<u16> = sweep.points.iter().map(|p| p.column).collect();
        let sweep_input = products::SweepInput {
            positions: &desk.positions,
            ring: &ring,
            column: &column,
            beams: preset.lidar.beams as usize,
            columns: preset.lidar.columns as usize,
            min_range: preset.lidar.min_range,
            t_world_lidar,
        };
        let cams_rgb: Vec<(&RigCamera, &[[u8; 3]])> = preset
            .rig
            .cameras
            .iter()
            .zip(&rgbs)
            .map(|(c, rgb)| (c, rgb.as_slice()))
            .collect();
        let made = products::keyframe_products(gpu, &sweep_input, &cams_rgb).await?;
        for (ci, (cam, p)) in preset.rig.cameras.iter().zip(made).enumerate() {
            let t_world_cam = cam_poses[ci][k];
            frames.push(products::write_camera(
                &o,
                cam,
                k,
                t_img,
                &t_world_cam,
                &rgbs[ci],
                &p,
            )?);
        }
        if let Some(rec) = recorder.as_deref_mut() {
            for (ci, rgb) in rgbs.iter().enumerate() {
                rec.image(k, ci, t_img, rgb).map_err(SynthError::Other)?;
            }
            rec.sweep(k, &sweep).map_err(SynthError::Other)?;
        }
    }

    progress(Progress {
        stage: "ground truth",
        done: 0,
        total: 3,
    });
    let gt = sample_gt_cloud(&world, preset.gt_spacing, |p| {
        let k = vkey(p);
        [
            [0, 0, 0],
            [1, 0, 0],
            [-1, 0, 0],
            [0, 1, 0],
            [0, -1, 0],
            [0, 0, 1],
            [0, 0, -1],
        ]
        .iter()
        .any(|d| seen.contains(&[k[0] + d[0], k[1] + d[1], k[2] + d[2]]))
    });
    let gt_points = gt.len();
    observed.mark_occupied(&gt.positions);
    o.write("gt/cloud.ply", &ply(&gt, "gt/cloud.ply")?)?;
    o.write("gt/mesh.ply", &mesh_ply(&world))?;
    // Streamed to its file: the grid (1.2 GB on the default world) is not copied into memory again,
    // and what it no longer needs goes first.
    drop((seen, gt));
    observed
        .save(&o.path("gt/observed.bin"))
        .map_err(|e| SynthError::Other(format!("gt/observed.bin: {e}")))?;
    o.written("gt/observed.bin")?;
    progress(Progress {
        stage: "ground truth",
        done: 3,
        total: 3,
    });

    // Poses, calibration, transforms.json, manifest.
    o.write_poses(
        &image_times,
        &base_poses,
        &lidar_poses,
        &preset.rig,
        &cam_poses,
        &odo,
    )?;
    o.write_json("calib/lidar.json", &preset.lidar)?;
    let n_frames = frames.len();
    // Hold out every 10th keyframe (all its cameras) for novel-view evaluation.
    let transforms = products::transforms(frames, products::every_tenth_keyframe);
    o.write_json("transforms.json", &transforms)?;
    // The SLAM-like prior: the same frames at the prior's poses (the rig moves with its drifted base;
    // extrinsics exact), its TUM files, and which keyframes carry a gross error.
    let (prior, gross) = prior_of_walk(preset, &base_poses);
    let mut prior_tf = transforms.clone();
    for f in &mut prior_tf.frames {
        let k = f.keyframe.unwrap_or(0);
        let (model, cam) = f
            .camera(Path::new("transforms.json"))
            .map_err(|e| SynthError::Other(e.to_string()))?;
        let moved = NsFrame::new(
            f.file_path.clone(),
            &model,
            &(prior[k] * base_poses[k].inverse() * cam),
        );
        f.transform_matrix = moved.transform_matrix;
    }
    o.write_json("transforms_prior.json", &prior_tf)?;
    o.write(
        "poses/prior_base_tum.txt",
        dataset::tum_string(&image_times, &prior).as_bytes(),
    )?;
    for (i, cam) in preset.rig.cameras.iter().enumerate() {
        let poses: Vec<Se3> = (0..prior.len())
            .map(|k| prior[k] * base_poses[k].inverse() * cam_poses[i][k])
            .collect();
        o.write(
            &format!("poses/prior_{}_tum.txt", cam.name),
            dataset::tum_string(&image_times, &poses).as_bytes(),
        )?;
    }
    o.write_json(
        "poses/prior.json",
        &serde_json::json!({
            "params": preset.prior,
            "gross_keyframes": gross,
        }),
    )?;
    let labels = Label::ALL.iter().map(|l| (*l as u8, l.name())).collect();
    let encodings = BTreeMap::from([
        ("images", "8-bit RGB PNG, display gamma 2.2"),
        ("lidar_depth", "16-bit PNG, Euclidean range from the camera centre x 256 (m), 0 = no return, 65535 = sky"),
        ("lidar_normals", "8-bit RGB PNG, (n + 1) / 2 x 255, unit normal in the OpenCV camera frame facing the camera, 128 = none"),
        ("sky_mask", "8-bit PNG, 255 = sky (from lidar no-returns and the image)"),
        ("gt/depth", "16-bit PNG, exact Euclidean range x 256 (m), 0 = sky"),
        ("gt/normals", "as lidar_normals, exact"),
        ("gt/sky", "8-bit PNG, 255 = sky, exact"),
        ("gt/semantic", "8-bit PNG, label ids (see labels)"),
        ("lidar/raw", "PLY, points in the sensor frame at their firing time; time_offset (s) from the sweep start"),
        ("lidar/deskewed", "PLY, points in the sensor frame at the keyframe's image time"),
        ("poses", "TUM: t tx ty tz qx qy qz qw, T_world_<frame>; base, lidar and cameras at image times, odometry at 100 Hz"),
        ("transforms.json", "nerfstudio: c2w in OpenGL axes, cx/cy with pixel centres at +0.5"),
        ("gt/cloud.ply", "surface samples of everything any sensor saw, double x/y/z"),
        ("gt/observed.bin", "occupancy grid (log-odds), see eval::occupancy"),
    ]);
    let files = o.files();
    let manifest = Manifest {
        layout_version: dataset::LAYOUT_VERSION,
        generator: GENERATOR_VERSION,
        preset,
        keyframes: records,
        cameras: cams.clone(),
        labels,
        encodings,
        files,
    };
    o.write_json("manifest.json", &manifest)?;
    let n_files = o.files().len();
    if let Some(rec) = recorder {
        rec.finish().map_err(SynthError::Other)?;
    }
    let path = o.commit()?;
    Ok(SynthSummary {
        path,
        keyframes: preset.keyframes,
        images: n_frames,
        lidar_points,
        gt_points,
        files: n_files,
    })
}

/// Samples every surface on a grid of `spacing`, keeping samples that `keep` accepts (observed space) and
/// that are not buried inside another solid. Deterministic order: primitives in order, then grid order.
/// The SLAM-like prior of the generated keyframes (`base`): drawn over the preset's whole walk when it is
/// a prefix ([`Preset::prefix`]), so the first N keyframes carry the same prior whatever N is.
fn prior_of_walk(preset: &Preset, base: &[Se3]) -> (Vec<Se3>, Vec<usize>) {
    let n = base.len();
    let walk = preset.walk_keyframes.unwrap_or(n).max(n);
    let mut all = base.to_vec();
    all.extend((n..walk).map(|k| preset.t_world_base(preset.image_time(k))));
    let (mut prior, gross) = prior::prior_trajectory(&all, &preset.prior, preset.seed);
    prior.truncate(n);
    (prior, gross.into_iter().filter(|&k| k < n).collect())
}

pub fn sample_gt_cloud(
    world: &World,
    spacing: f64,
    keep: impl Fn(DVec3) -> bool + Sync,
) -> PointCloud {
    use rayon::prelude::*;
    let scene: &Scene = &world.scene;
    let per_prim: Vec<Vec<DVec3>> = (0..scene.primitives.len())
        .into_par_iter()
        .map(|i| {
            let mut pts = Vec::new();
            surface_samples(&scene.primitives[i].shape, spacing, &mut pts);
            pts.retain(|&p| keep(p) && !scene.inside_solid(p, Some(i as u32), 1e-6));
            pts
        })
        .collect();
    let mut cloud: Vec<DVec3> = per_prim.into_iter().flatten().collect();
    // The ground: only where it was observed; sample the observed area's bounding box row by row.
    let (mut lo, mut hi) = (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY));
    for p in &cloud {
        lo = lo.min(p.truncate());
        hi = hi.max(p.truncate());
    }
    if lo.x.is_finite() {
        let nx = ((hi.x - lo.x) / spacing).ceil() as i64;
        let ny = ((hi.y - lo.y) / spacing).ceil() as i64;
        let x0 = (lo.x / spacing).floor();
        let y0 = (lo.y / spacing).floor();
        let rows: Vec<Vec<DVec3>> = (0..=ny)
            .into_par_iter()
            .map(|j| {
                let mut row = Vec::new();
                for i in 0..=nx {
                    let p = DVec3::new(
                        (x0 + i as f64 + 0.5) * spacing,
                        (y0 + j as f64 + 0.5) * spacing,
                        0.0,
                    );
                    if keep(p) && !scene.inside_solid(p, None, 1e-6) {
                        row.push(p);
                    }
                }
                row
            })
            .collect();
        cloud.extend(rows.into_iter().flatten());
    }
    let _ = GROUND;
    PointCloud::from_positions(cloud)
}

fn grid(n: f64) -> usize {
    (n.ceil() as usize).max(1)
}

/// Regular samples over a primitive's surface, about `s` apart.
fn surface_samples(shape: &Shape, s: f64, out: &mut Vec<DVec3>) {
    match *shape {
        Shape::Cuboid { min, max } => {
            let e = max - min;
            for axis in 0..3 {
                let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
                let (na, nb) = (grid(e[a] / s), grid(e[b] / s));
                for side in [min[axis], max[axis]] {
                    for i in 0..na {
                        for j in 0..nb {
                            let mut p = DVec3::ZERO;
                            p[axis] = side;
                            p[a] = min[a] + (i as f64 + 0.5) * e[a] / na as f64;
                            p[b] = min[b] + (j as f64 + 0.5) * e[b] / nb as f64;
                            out.push(p);
                        }
                    }
                }
            }
        }
        Shape::Cylinder {
            base,
            radius,
            height,
        } => {
            let na = grid(std::f64::consts::TAU * radius / s);
            let nz = grid(height / s);
            for i in 0..na {
                let a = std::f64::consts::TAU * (i as f64 + 0.5) / na as f64;
                for j in 0..nz {
                    out.push(
                        base + DVec3::new(
                            radius * a.cos(),
                            radius * a.sin(),
                            (j as f64 + 0.5) * height / nz as f64,
                        ),
                    );
                }
            }
            let nr = grid(2.0 * radius / s);
            for i in 0..nr {
                for j in 0..nr {
                    let x = -radius + (i as f64 + 0.5) * 2.0 * radius / nr as f64;
                    let y = -radius + (j as f64 + 0.5) * 2.0 * radius / nr as f64;
                    if x * x + y * y <= radius * radius {
                        out.push(base + DVec3::new(x, y, height));
                        out.push(base + DVec3::new(x, y, 0.0));
                    }
                }
            }
        }
        Shape::Sphere { center, radius } => {
            let nlat = grid(std::f64::consts::PI * radius / s);
            for i in 0..nlat {
                let th = std::f64::consts::PI * (i as f64 + 0.5) / nlat as f64;
                let nlon = grid(std::f64::consts::TAU * radius * th.sin() / s);
                for j in 0..nlon {
                    let ph = std::f64::consts::TAU * (j as f64 + 0.5) / nlon as f64;
                    out.push(
                        center
                            + radius
                                * DVec3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()),
                    );
                }
            }
        }
        Shape::Triangle { a, b, c } => {
            let n = grid((b - a).length().max((c - a).length()).max((c - b).length()) / s);
            for i in 0..n {
                for j in 0..(n - i) {
                    let u = (i as f64 + 1.0 / 3.0) / n as f64;
                    let v = (j as f64 + 1.0 / 3.0) / n as f64;
                    out.push(a + (b - a) * u + (c - a) * v);
                }
            }
        }
    }
}

/// The world as a triangle mesh (binary PLY): each face carries its semantic label and albedo.
pub fn mesh_ply(world: &World) -> Vec<u8> {
    let mut verts: Vec<DVec3> = Vec::new();
    let mut faces: Vec<([u32; 3], u8, [u8; 3])> = Vec::new();
    let scene = &world.scene;
    let mut add_tri =
        |verts: &mut Vec<DVec3>, a: DVec3, b: DVec3, c: DVec3, prim: u32, material: u16| {
            let base = verts.len() as u32;
            verts.extend([a, b, c]);
            let centre = (a + b + c) / 3.0;
            let n = (b - a).cross(c - a).normalize_or_zero();
            let hit = super::raycast::Hit {
                t: 0.0,
                point: centre,
                normal: n,
                primitive: prim,
                material,
            };
            let alb = world.albedo(&hit);
            faces.push((
                [base, base + 1, base + 2],
                world.label(&hit) as u8,
                alb.to_array()
                    .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8),
            ));
        };
    // Ground: one big quad around everything.
    let ext = world.ground_half_extent();
    let g = |x: f64, y: f64| DVec3::new(x, y, 0.0);
    add_tri(
        &mut verts,
        g(-ext, -ext),
        g(ext, -ext),
        g(ext, ext),
        GROUND,
        scene.ground_material,
    );
    add_tri(
        &mut verts,
        g(-ext, -ext),
        g(ext, ext),
        g(-ext, ext),
        GROUND,
        scene.ground_material,
    );
    for (i, prim) in scene.primitives.iter().enumerate() {
        let (pi, m) = (i as u32, prim.material);
        match prim.shape {
            Shape::Cuboid { min, max } => {
                let c = |x: usize, y: usize, z: usize| {
                    DVec3::new([min.x, max.x][x], [min.y, max.y][y], [min.z, max.z][z])
                };
                // Each face as two triangles wound outwards.
                let quads = [
                    [c(0, 0, 0), c(0, 1, 0), c(1, 1, 0), c(1, 0, 0)],
                    [c(0, 0, 1), c(1, 0, 1), c(1, 1, 1), c(0, 1, 1)],
                    [c(0, 0, 0), c(1, 0, 0), c(1, 0, 1), c(0, 0, 1)],
                    [c(0, 1, 0), c(0, 1, 1), c(1, 1, 1), c(1, 1, 0)],
                    [c(0, 0, 0), c(0, 0, 1), c(0, 1, 1), c(0, 1, 0)],
                    [c(1, 0, 0), c(1, 1, 0), c(1, 1, 1), c(1, 0, 1)],
                ];
                for q in quads {
                    add_tri(&mut verts, q[0], q[1], q[2], pi, m);
                    add_tri(&mut verts, q[0], q[2], q[3], pi, m);
                }
            }
            Shape::Cylinder {
                base,
                radius,
                height,
            } => {
                let n = 16;
                let p = |k: usize, z: f64| {
                    let a = std::f64::consts::TAU * k as f64 / n as f64;
                    base + DVec3::new(radius * a.cos(), radius * a.sin(), z)
                };
                let top = base + DVec3::new(0.0, 0.0, height);
                for k in 0..n {
                    add_tri(
                        &mut verts,
                        p(k, 0.0),
                        p(k + 1, 0.0),
                        p(k + 1, height),
                        pi,
                        m,
                    );
                    add_tri(&mut verts, p(k, 0.0), p(k + 1, height), p(k, height), pi, m);
                    add_tri(&mut verts, top, p(k, height), p(k + 1, height), pi, m);
                    add_tri(&mut verts, base, p(k + 1, 0.0), p(k, 0.0), pi, m);
                }
            }
            Shape::Sphere { center, radius } => {
                let (nl, nm) = (10, 16);
                let p = |i: usize, j: usize| {
                    let th = std::f64::consts::PI * i as f64 / nl as f64;
                    let ph = std::f64::consts::TAU * j as f64 / nm as f64;
                    center + radius * DVec3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos())
                };
                for i in 0..nl {
                    for j in 0..nm {
                        if i > 0 {
                            add_tri(&mut verts, p(i, j), p(i + 1, j), p(i, j + 1), pi, m);
                        }
                        if i + 1 < nl {
                            add_tri(&mut verts, p(i, j + 1), p(i + 1, j), p(i + 1, j + 1), pi, m);
                        }
                    }
                }
            }
            Shape::Triangle { a, b, c } => add_tri(&mut verts, a, b, c, pi, m),
        }
    }
    let mut out = format!(
        "ply\nformat binary_little_endian 1.0\ncomment SiLVR synthetic world, {GENERATOR_VERSION}, seed {}\nelement vertex {}\nproperty double x\nproperty double y\nproperty double z\nelement face {}\nproperty list uchar int vertex_indices\nproperty uchar label\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
        world.seed,
        verts.len(),
        faces.len()
    )
    .into_bytes();
    for v in &verts {
        for c in v.to_array() {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    for (idx, label, rgb) in &faces {
        out.push(3);
        for i in idx {
            out.extend_from_slice(&(*i as i32).to_le_bytes());
        }
        out.push(*label);
        out.extend_from_slice(rgb);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A prefix of a walk (`silvr synth --keyframes N`) carries the walk's own prior on its keyframes:
    /// drift and noise drawn over the whole walk, so growth curves compare the same trajectory.
    #[test]
    fn a_prefix_carries_the_whole_walks_prior() {
        let full = Preset::default_preset(3);
        let base: Vec<Se3> = (0..full.keyframes)
            .map(|k| full.t_world_base(full.image_time(k)))
            .collect();
        let (whole, gross) = prior_of_walk(&full, &base);
        assert_eq!(whole.len(), full.keyframes);
        assert!(!gross.is_empty(), "the default walk has gross errors");
        let part = full.clone().prefix(50).unwrap();
        let (prefix, prefix_gross) = prior_of_walk(&part, &base[..50]);
        assert_eq!(prefix, whole[..50]);
        assert_eq!(
            prefix_gross,
            gross
                .iter()
                .copied()
                .filter(|&k| k < 50)
                .collect::<Vec<_>>()
        );
        assert!(full.clone().prefix(2).is_err());
        assert!(full.clone().prefix(full.keyframes + 1).is_err());
    }
}
