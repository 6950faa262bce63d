//! `silvr ingest`: a ROS 1 or ROS 2 bag (+ rig file) → the dataset layout; `--info` lists what a bag holds.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use silvr_core::gpu::Gpu;
use silvr_core::ingest::bag;
use silvr_core::ingest::config::RigConfig;
use silvr_core::ingest::rosbag::{self, IngestSummary};

#[derive(clap::Args)]
pub struct IngestCmd {
    /// The bag: an MCAP file, a ROS 1 `.bag` (format 2.0), a rosbag2 folder (metadata.yaml + .db3 or
    /// .mcap) or a `.db3` file; recognised from the content.
    pub bag: PathBuf,
    /// Rig file: the Oxford Spires sensor.yaml schema plus an optional `ingest:` block
    /// (topics, keyframe rules); see `silvr synth --mcap` for a complete example.
    #[arg(long, required_unless_present = "info")]
    pub config: Option<PathBuf>,
    /// Output dataset folder (must not exist unless --overwrite).
    #[arg(long, required_unless_present = "info")]
    pub out: Option<PathBuf>,
    #[arg(long)]
    pub overwrite: bool,
    /// Override ingest.keyframe_distance (m).
    #[arg(long)]
    pub keyframe_distance: Option<f64>,
    /// Override ingest.keyframe_angle_deg.
    #[arg(long)]
    pub keyframe_angle: Option<f64>,
    /// Override ingest.max_keyframes.
    #[arg(long)]
    pub max_keyframes: Option<usize>,
    /// Where the trajectory comes from: `lidar` runs lidar odometry over the lidar topic (for a bag with
    /// no SLAM trajectory; one without a trajectory gets it anyway, with a notice). Default: the rig
    /// file's trajectory_topic or trajectory_file.
    #[arg(long)]
    pub trajectory: Option<String>,
    /// Only list the bag's topics, types, counts and time span (no rig file needed).
    #[arg(long)]
    pub info: bool,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(c: IngestCmd, open_gpu: impl FnOnce() -> Result<Gpu>) -> Result<()> {
    if c.info {
        return info(&c.bag, c.json);
    }
    let cfg_path = c.config.clone().expect("clap requires --config");
    let out = c.out.clone().expect("clap requires --out");
    let mut cfg = RigConfig::read(&cfg_path)?;
    if let Some(d) = c.keyframe_distance {
        cfg.ingest.keyframe_distance = d;
    }
    if let Some(a) = c.keyframe_angle {
        cfg.ingest.keyframe_angle_deg = a;
    }
    if let Some(m) = c.max_keyframes {
        cfg.ingest.max_keyframes = Some(m);
    }
    match c.trajectory.as_deref() {
        None => {}
        Some("lidar") => cfg.ingest.trajectory_from_lidar = true,
        Some(o) => anyhow::bail!(
            "--trajectory {o}: expected lidar (a topic or file is set in the rig file's ingest block)"
        ),
    }
    let gpu = open_gpu()?;
    let cfg_dir = cfg_path.parent().unwrap_or(Path::new(".")).to_path_buf();
    let summary = ingest(&gpu, &c.bag, &cfg, &cfg_dir, &out, c.overwrite)?;
    if c.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        print_summary(&summary);
    }
    Ok(())
}

/// Runs the ingest with progress on stderr.
pub fn ingest(
    gpu: &Gpu,
    bag: &Path,
    cfg: &RigConfig,
    cfg_dir: &Path,
    out: &Path,
    overwrite: bool,
) -> Result<IngestSummary> {
    let start = Instant::now();
    let mut last = (String::new(), u64::MAX);
    let summary = pollster::block_on(rosbag::ingest_bag(
        bag,
        cfg,
        cfg_dir,
        out,
        overwrite,
        gpu,
        &mut |p| {
            if (p.stage, p.done) != (last.0.as_str(), last.1) {
                last = (p.stage.to_string(), p.done);
                let of = if p.total > 0 {
                    format!("/{}", p.total)
                } else {
                    " messages".into()
                };
                eprintln!(
                    "[ingest] {} {}{of} ({:.1} s)",
                    p.stage,
                    p.done,
                    start.elapsed().as_secs_f64()
                );
            }
        },
    ))
    .with_context(|| format!("ingesting {} into {}", bag.display(), out.display()))?;
    for n in &summary.notices {
        eprintln!("[ingest] notice: {n}");
    }
    eprintln!("[ingest] trajectory: {}", summary.trajectory);
    eprintln!(
        "[ingest] wrote {} ({} keyframes, {} images, {} lidar points) in {:.1} s",
        summary.path.display(),
        summary.keyframes,
        summary.images,
        summary.lidar_points,
        start.elapsed().as_secs_f64()
    );
    Ok(summary)
}

fn print_summary(s: &IngestSummary) {
    println!(
        "{}: {:.1} s of data ({:.3} .. {:.3})",
        s.bag,
        s.time_span.1 - s.time_span.0,
        s.time_span.0,
        s.time_span.1
    );
    println!(
        "{:<60} {:<36} {:>9} {:>9}",
        "topic", "type", "messages", "used"
    );
    for (topic, t) in &s.topics {
        println!(
            "{topic:<60} {:<36} {:>9} {:>9}",
            t.schema, t.messages, t.used
        );
    }
    println!(
        "lidar range image: {} beams x {} columns",
        s.lidar_beams, s.lidar_columns
    );
    if s.dropped.is_empty() {
        println!("nothing dropped");
    } else {
        println!("dropped:");
        for (why, n) in &s.dropped {
            println!("  {n:>7}  {why}");
        }
    }
    println!(
        "dataset: {} ({} keyframes, {} images)",
        s.path.display(),
        s.keyframes,
        s.images
    );
}

fn info(bag: &Path, json: bool) -> Result<()> {
    let s = bag::summarize(bag)?;
    if json {
        let topics: serde_json::Map<String, serde_json::Value> = s
            .topics
            .iter()
            .map(|(k, t)| {
                (
                    k.clone(),
                    serde_json::json!({
                        "type": t.schema_name,
                        "encoding": t.message_encoding,
                        "messages": t.messages,
                        "decoded": t.decoded,
                        "first_log_time_ns": t.first_log_time,
                        "last_log_time_ns": t.last_log_time,
                    }),
                )
            })
            .collect();
        let v = serde_json::json!({
            "bag": bag.display().to_string(),
            "format": s.format.map(|f| f.name()),
            "notes": s.notes,
            "messages": s.messages,
            "duration_s": s.duration(),
            "topics": topics,
            "skipped": s.skipped,
            "decode_errors": s.decode_errors,
            "first_errors": s.first_errors,
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    println!(
        "{} ({}): {} messages over {:.3} s",
        bag.display(),
        s.format.map_or("?", |f| f.name()),
        s.messages,
        s.duration()
    );
    for n in &s.notes {
        println!("note: {n}");
    }
    println!(
        "{:<60} {:<36} {:>9} {:>9}",
        "topic", "type", "messages", "decoded"
    );
    for (topic, t) in &s.topics {
        println!(
            "{topic:<60} {:<36} {:>9} {:>9}",
            t.schema_name, t.messages, t.decoded
        );
    }
    for (why, n) in &s.skipped {
        println!("not decoded: {n} ({why})");
    }
    if s.decode_errors > 0 {
        println!("decode errors: {}", s.decode_errors);
        for e in &s.first_errors {
            println!("  {e}");
        }
    }
    Ok(())
}

#[derive(clap::Args)]
pub struct BenchIngestCmd {
    /// A bag to read; default: the `ci` synthetic world recorded as a bag in a temporary folder.
    pub bag: Option<PathBuf>,
    /// Its rig file (default: BAG with the extension `rig.yaml`, as `silvr synth --mcap` writes it).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Timed repetitions of each measurement (the best is reported).
    #[arg(long, default_value_t = 3)]
    pub reps: usize,
}

/// Ingest throughput, JSON on stdout: MB/s and messages/s of reading + decoding every message (clouds to
/// points, images to RGB), and of the whole ingest (two passes, deskew, normals, GPU projection, PNGs).
pub fn bench(c: BenchIngestCmd, open_gpu: impl FnOnce() -> Result<Gpu>) -> Result<()> {
    use silvr_core::ingest::ros::RosMessage;
    let gpu = open_gpu()?;
    let tmp = std::env::temp_dir().join(format!("silvr-bench-ingest-{}", std::process::id()));
    std::fs::create_dir_all(&tmp)?;
    let _cleanup = RemoveOnDrop(tmp.clone());
    let (bag, cfg_path) = match c.bag {
        Some(b) => {
            let cfg = c.config.unwrap_or_else(|| b.with_extension("rig.yaml"));
            (b, cfg)
        }
        None => {
            let preset = silvr_core::synthetic::Preset::ci(1);
            let bag = tmp.join("scene.mcap");
            let mut rec = silvr_core::synthetic::bag::BagRecorder::create(&bag)?;
            eprintln!("[bench-ingest] recording the ci world as a bag ...");
            pollster::block_on(silvr_core::synthetic::generate::generate_recording(
                &preset,
                &gpu,
                &tmp.join("synth"),
                false,
                &mut |_| {},
                Some(&mut rec),
            ))?;
            let cfg = tmp.join("scene.rig.yaml");
            std::fs::write(
                &cfg,
                silvr_core::synthetic::bag::rig_config(&preset).to_yaml(),
            )?;
            (bag, cfg)
        }
    };
    let cfg = RigConfig::read(&cfg_path)?;
    let mb = bag::bag_bytes(&bag)? as f64 / 1e6;
    let reps = c.reps.max(1);

    // 1. Read + decode everything.
    let mut best_decode = f64::INFINITY;
    let (mut messages, mut points, mut pixels) = (0u64, 0u64, 0u64);
    for _ in 0..reps {
        let t = Instant::now();
        (messages, points, pixels) = (0, 0, 0);
        for msg in bag::BagReader::open(&bag)? {
            let msg = msg?;
            messages += 1;
            match msg.decode() {
                Ok(Ok(RosMessage::PointCloud2(pc))) => {
                    points += pc.to_scan()?.positions.len() as u64
                }
                Ok(Ok(RosMessage::Image(img))) => pixels += img.to_rgb()?.pixels.len() as u64,
                Ok(Ok(RosMessage::CompressedImage(img))) => {
                    pixels += img.to_rgb()?.pixels.len() as u64
                }
                _ => {}
            }
        }
        best_decode = best_decode.min(t.elapsed().as_secs_f64());
    }
    // 2. The whole ingest.
    let mut best_ingest = f64::INFINITY;
    let mut keyframes = 0;
    let cfg_dir = cfg_path.parent().unwrap_or(Path::new(".")).to_path_buf();
    for r in 0..reps {
        let out = tmp.join(format!("ingested-{r}"));
        let t = Instant::now();
        let s = pollster::block_on(rosbag::ingest_bag(
            &bag,
            &cfg,
            &cfg_dir,
            &out,
            false,
            &gpu,
            &mut |_| {},
        ))?;
        best_ingest = best_ingest.min(t.elapsed().as_secs_f64());
        keyframes = s.keyframes;
        let _ = std::fs::remove_dir_all(&out);
    }
    let v = serde_json::json!({
        "bag": bag.display().to_string(),
        "bag_mb": mb,
        "adapter": gpu.report(),
        "decode": {
            "seconds": best_decode,
            "mb_per_s": mb / best_decode,
            "messages_per_s": messages as f64 / best_decode,
            "points_per_s": points as f64 / best_decode,
            "megapixels_per_s": pixels as f64 / best_decode / 1e6,
        },
        "ingest": {
            "seconds": best_ingest,
            "mb_per_s": mb / best_ingest,
            "keyframes": keyframes,
            "keyframes_per_s": keyframes as f64 / best_ingest,
            "points_per_s": points as f64 / best_ingest,
        },
    });
    println!("{}", serde_json::to_string_pretty(&v)?);
    Ok(())
}

struct RemoveOnDrop(PathBuf);

impl Drop for RemoveOnDrop {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

#[derive(clap::Args)]
pub struct ImportCmd {
    /// Source layout: `dgp` (a DGP scene folder: scene_*.json, calibration/, point_cloud/, rgb/),
    /// `nerfstudio` (a transforms.json, e.g. from nerfstudio, instant-ngp or SiLVR's Spires tools) or
    /// `spires` (an Oxford Spires sequence: sensor.yaml, raw/camN/, processed/vilens-slam/), `colmap` (a
    /// text model folder; photos from --images) or `kitti` (a KITTI odometry sequence folder
    /// `sequences/NN`: image_2/, image_3/, velodyne/, calib.txt, times.txt; ground truth from
    /// `poses/NN.txt` two levels up or `poses.txt` inside, or --poses; or a KITTI raw drive folder
    /// `DATE/DATE_drive_NNNN_sync`: image_02/, image_03/, velodyne_points/, oxts/, with calib_*.txt in
    /// DATE/; poses from the OXTS).
    pub format: String,
    /// The source folder (dgp, spires, kitti) or transforms.json (nerfstudio).
    pub source: PathBuf,
    /// Rig file for spires (default: SOURCE/sensor.yaml).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// colmap: the folder the model's image names are relative to (default: SOURCE/../images).
    #[arg(long)]
    pub images: Option<PathBuf>,
    /// Output dataset folder (must not exist unless --overwrite).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long)]
    pub overwrite: bool,
    /// kitti: the trajectory to use instead of the ground truth beside the sequence or a drive's OXTS
    /// (KITTI format: T_world_cam0 of frame i on line i), or `lidar` for lidar odometry over the sweeps
    /// (what a sequence without either gets anyway, with a notice).
    #[arg(long)]
    pub poses: Option<PathBuf>,
    /// kitti: only frames FIRST..=LAST (KITTI frame numbers), e.g. `--frames 0:99`.
    #[arg(long, value_parser = parse_frame_range)]
    pub frames: Option<(usize, usize)>,
    /// kitti: every N-th of the selected frames.
    #[arg(long, default_value_t = 1)]
    pub every: usize,
    /// Integer image downscale (intrinsics follow; dgp, kitti).
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    /// Metres per depth PNG unit (nerfstudio; default: the file's depth_unit_scale_factor, else 0.001).
    #[arg(long)]
    pub depth_scale: Option<f64>,
    /// The depth PNGs hold range along each ray instead of z-depth (nerfstudio).
    #[arg(long)]
    pub depth_is_range: bool,
}

/// `FIRST:LAST` (inclusive) → the pair.
fn parse_frame_range(s: &str) -> Result<(usize, usize), String> {
    let (a, b) = s
        .split_once(':')
        .ok_or_else(|| format!("{s:?}: expected FIRST:LAST, e.g. 0:99"))?;
    let n = |t: &str| {
        t.trim()
            .parse::<usize>()
            .map_err(|_| format!("{t:?} is not a frame number"))
    };
    let (a, b) = (n(a)?, n(b)?);
    if a > b {
        return Err(format!("{s:?}: FIRST is after LAST"));
    }
    Ok((a, b))
}

#[derive(clap::Args)]
pub struct ExportCmd {
    /// Target layout: `colmap` (text model: cameras.txt, images.txt, empty points3D.txt), `spires`
    /// (sensor.yaml, raw/camN/ images, undistorted PCD clouds, slam-poses.csv) or `las` (a point cloud
    /// PLY as LAS 1.4 / LAZ by --out's extension, its scalars — uncertainty, submap, error — as
    /// extra-bytes dimensions) or `copc` (the same as COPC, the octree-ordered LAZ streaming viewers read by
    /// byte ranges, with a summary of the uncertainty filter over the whole cloud; streamed, bounded memory).
    pub format: String,
    /// Dataset folder (holding transforms.json); for `las`, the PLY; for `copc`, a PLY or LAS/LAZ.
    pub dataset: PathBuf,
    /// Output folder (for `las`: the .laz or .las file; for `copc`: the .copc.laz file).
    #[arg(long)]
    pub out: PathBuf,
}

/// `silvr export FORMAT DATASET --out DIR`.
pub fn export(c: ExportCmd) -> Result<()> {
    match c.format.as_str() {
        "colmap" => {
            let n = silvr_core::ingest::convert::export_colmap(&c.dataset, &c.out)
                .with_context(|| format!("exporting {} as COLMAP", c.dataset.display()))?;
            println!("wrote {} images to {}", n, c.out.display());
            Ok(())
        }
        "spires" => {
            let n = silvr_core::ingest::spires::export_spires(&c.dataset, &c.out).with_context(
                || format!("exporting {} in the Spires layout", c.dataset.display()),
            )?;
            println!("wrote {} images to {}", n, c.out.display());
            Ok(())
        }
        "las" | "laz" => {
            // DATASET is a point cloud here: a PLY the pipeline wrote (points.ply, merged.ply, ...).
            let cloud = silvr_core::pointcloud::read_ply(&c.dataset)?;
            let n = silvr_core::lasfile::write_las(&c.out, &cloud)?;
            let dims: Vec<&str> = cloud.scalars.iter().map(|(k, _)| k.as_str()).collect();
            println!(
                "wrote {n} points to {} (extra dimensions: {})",
                c.out.display(),
                if dims.is_empty() {
                    "none".into()
                } else {
                    dims.join(", ")
                }
            );
            Ok(())
        }
        "copc" => {
            // DATASET is a point cloud, streamed in chunks: a PLY, or a LAS/LAZ (COPC included).
            use silvr_core::copc::write::{write_copc, CopcInput, CopcOptions};
            let input = match silvr_core::eval::scan::detect(&c.dataset)? {
                silvr_core::eval::scan::ScanFormat::Las => CopcInput::Las(&c.dataset),
                silvr_core::eval::scan::ScanFormat::Ply => CopcInput::Ply(&c.dataset),
                other => anyhow::bail!(
                    "{}: a {other:?} file; `export copc` reads a PLY or a LAS/LAZ",
                    c.dataset.display()
                ),
            };
            let w = write_copc(input, &c.out, &CopcOptions::default())?;
            println!(
                "wrote {} points to {} ({:.1} MB; extra dimensions: {})",
                w.points,
                c.out.display(),
                w.bytes as f64 / 1e6,
                if w.fields.is_empty() {
                    "none".into()
                } else {
                    w.fields.join(", ")
                }
            );
            if let Some(f) = &w.summary.filter {
                println!(
                    "summary: the default filter (σ ≤ {1}, on {0}) keeps {2} of {3} points",
                    f.field,
                    f.threshold.map_or("∞".into(), |t| {
                        silvr_core::uncertainty::reliability::format_metres(10f64.powf(t as f64))
                    }),
                    f.kept,
                    w.points
                );
            }
            Ok(())
        }
        other => {
            anyhow::bail!("unknown export format {other:?} (supported: colmap, spires, las, copc)")
        }
    }
}

/// `silvr import FORMAT SOURCE --out DIR`: other dataset layouts → ours.
pub fn import(c: ImportCmd, open_gpu: impl FnOnce() -> Result<Gpu>) -> Result<()> {
    use silvr_core::ingest::dgp;
    match c.format.as_str() {
        "dgp" => {
            let gpu = open_gpu()?;
            let start = Instant::now();
            let s = pollster::block_on(dgp::import_dgp(
                &c.source,
                &c.out,
                c.overwrite,
                dgp::DgpOptions {
                    downscale: c.downscale,
                    ..Default::default()
                },
                &gpu,
                &mut |done, total| eprintln!("[import] sample {done}/{total}"),
            ))
            .with_context(|| {
                format!("importing {} into {}", c.source.display(), c.out.display())
            })?;
            eprintln!("[import] done in {:.1} s", start.elapsed().as_secs_f64());
            println!("{}", serde_json::to_string_pretty(&s)?);
            Ok(())
        }
        "nerfstudio" => {
            use silvr_core::ingest::convert;
            let depth = c.depth_scale.map(|scale| convert::DepthEncoding {
                scale,
                z_depth: !c.depth_is_range,
            });
            let s = convert::import_nerfstudio(&c.source, &c.out, c.overwrite, depth)
                .with_context(|| {
                    format!("importing {} into {}", c.source.display(), c.out.display())
                })?;
            println!("{}", serde_json::to_string_pretty(&s)?);
            Ok(())
        }
        "colmap" => {
            let images = c
                .images
                .clone()
                .unwrap_or_else(|| c.source.join("../images"));
            let s =
                silvr_core::ingest::convert::import_colmap(&c.source, &images, &c.out, c.overwrite)
                    .with_context(|| {
                        format!("importing {} into {}", c.source.display(), c.out.display())
                    })?;
            println!("{}", serde_json::to_string_pretty(&s)?);
            Ok(())
        }
        "spires" => {
            use silvr_core::ingest::spires;
            let gpu = open_gpu()?;
            let s = pollster::block_on(spires::import_spires(
                &c.source,
                c.config.as_deref(),
                &c.out,
                c.overwrite,
                &gpu,
                &mut |done, total| eprintln!("[import] keyframe {done}/{total}"),
            ))
            .with_context(|| {
                format!("importing {} into {}", c.source.display(), c.out.display())
            })?;
            println!("{}", serde_json::to_string_pretty(&s)?);
            Ok(())
        }
        "kitti" => {
            use silvr_core::ingest::kitti_import as kitti;
            anyhow::ensure!(c.every >= 1, "--every must be at least 1");
            anyhow::ensure!(c.downscale >= 1, "--downscale must be at least 1");
            let gpu = open_gpu()?;
            let start = Instant::now();
            let s = pollster::block_on(kitti::import_kitti(
                &c.source,
                &c.out,
                c.overwrite,
                kitti::KittiOptions {
                    downscale: c.downscale,
                    poses: c.poses.clone().filter(|p| p.as_os_str() != "lidar"),
                    lidar_odometry: c.poses.as_ref().is_some_and(|p| p.as_os_str() == "lidar"),
                    frames: c.frames,
                    every: c.every,
                    ..Default::default()
                },
                &gpu,
                &mut |done, total| eprintln!("[import] frame {done}/{total}"),
            ))
            .with_context(|| {
                format!("importing {} into {}", c.source.display(), c.out.display())
            })?;
            eprintln!(
                "[import] done in {:.1} s: KITTI {:?} layout, {} keyframes, {} images, poses from {}; no \
                 deskew (the sweeps carry no point times; see the manifest's notes)",
                start.elapsed().as_secs_f64(),
                s.layout,
                s.keyframes,
                s.images,
                s.poses
            );
            for why in &s.skipped {
                eprintln!("[import] skipped frame {why}");
            }
            for n in &s.notices {
                eprintln!("[import] notice: {n}");
            }
            println!("{}", serde_json::to_string_pretty(&s)?);
            Ok(())
        }
        other => {
            anyhow::bail!(
                "unknown import format {other:?} (supported: dgp, nerfstudio, spires, colmap, kitti)"
            )
        }
    }
}
