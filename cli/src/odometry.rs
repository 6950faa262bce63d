//! `silvr odometry`: a trajectory from a recording's lidar alone (silvr_core::odometry), written as TUM
//! (`T_world_lidar`, the world the first sweep's lidar frame), with a JSON report: time per sweep and,
//! where the recording has ground truth (a KITTI sequence's poses, or `--gt`), ATE and RPE after an SE(3)
//! alignment (no scale: lidar odometry claims metres).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use serde_json::json;
use silvr_core::geometry::{Se3, Trajectory};
use silvr_core::ingest::{odometry_input, poses};
use silvr_core::odometry::{self, DeskewMode, OdometryConfig};

#[derive(clap::Args, Debug)]
pub struct OdometryCmd {
    /// A KITTI odometry sequence folder (velodyne/, times.txt; ground truth beside it is scored) or a
    /// ROS 2 bag (.mcap).
    input: PathBuf,
    /// The trajectory to write (TUM: t tx ty tz qx qy qz qw, T_world_lidar); its report (per sweep:
    /// time, ICP, how well the scene constrains the motion, warnings) goes beside it as OUT.json.
    #[arg(long)]
    out: PathBuf,
    /// The bag's lidar topic (default: its only PointCloud2 topic).
    #[arg(long)]
    lidar_topic: Option<String>,
    /// `auto` (per-point time, else azimuth order) or `off` (sweeps already motion-compensated). Default:
    /// off for KITTI (its sweeps are compensated), auto for bags.
    #[arg(long)]
    deskew: Option<String>,
    /// Points beyond this range (m) are ignored; also the local map's radius.
    #[arg(long, default_value_t = 100.0)]
    max_range: f64,
    /// Points nearer than this (m: the rig, the vehicle) are ignored.
    #[arg(long, default_value_t = 0.0)]
    min_range: f64,
    /// Voxel size (m) of the local map (default: max range / 100).
    #[arg(long)]
    voxel_size: Option<f64>,
    /// Exact trajectory to score against (TUM, T_world_lidar), matched by time within 5 ms.
    #[arg(long)]
    gt: Option<PathBuf>,
    /// Also write the recording's own ground truth (a KITTI sequence's, in the lidar frame of its first
    /// sweep, at the sweeps' times) as TUM: the reference a peer's trajectory is scored against.
    #[arg(long)]
    gt_out: Option<PathBuf>,
    /// Also write every sweep as read (before cropping) into this folder, for a peer to run on the same
    /// points: `NNNNNN.bin` (float32 x y z t, t in s from the sweep's stamp, NaN without point times)
    /// and `stamps.txt` (each sweep's stamp, s).
    #[arg(long)]
    export_sweeps: Option<PathBuf>,
    /// Write the JSON report here (printed to stdout otherwise).
    #[arg(long)]
    report: Option<PathBuf>,
}

pub fn run(c: OdometryCmd) -> Result<()> {
    let mut input = odometry_input::open(&c.input, c.lidar_topic.as_deref())?;
    let deskew = match c.deskew.as_deref() {
        None => input.default_deskew,
        Some("auto") => DeskewMode::Auto,
        Some("off") => DeskewMode::Off,
        Some(o) => bail!("--deskew {o}: expected auto or off"),
    };
    let config = OdometryConfig {
        max_range: c.max_range,
        min_range: c.min_range,
        voxel_size: c.voxel_size,
        deskew,
        ..OdometryConfig::default()
    };
    let start = Instant::now();
    let sweeps = std::mem::replace(&mut input.sweeps, Box::new(std::iter::empty()));
    if let Some(dir) = &c.export_sweeps {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let mut stamps_txt = String::new();
    let mut export_error = None;
    let mut index = 0usize;
    let sweeps = sweeps.inspect(|s| {
        let (Some(dir), Ok(s)) = (&c.export_sweeps, s) else {
            return;
        };
        let mut bytes = Vec::with_capacity(s.points.len() * 16);
        for (i, p) in s.points.iter().enumerate() {
            let t = s.times.as_ref().map_or(f64::NAN, |t| t[i] - s.stamp);
            for v in [p.x, p.y, p.z, t] {
                bytes.extend_from_slice(&(v as f32).to_le_bytes());
            }
        }
        stamps_txt.push_str(&format!("{:.9}\n", s.stamp));
        if let Err(e) = std::fs::write(dir.join(format!("{index:06}.bin")), bytes) {
            export_error.get_or_insert(e);
        }
        index += 1;
    });
    let run = odometry::run(
        &config,
        sweeps.map(|s| s.map_err(|e| odometry::OdometryError::Input(e.to_string()))),
        |i, r| {
            for w in &r.warnings {
                eprintln!("warning: sweep {i} (t = {:.6} s): {w}", r.stamp);
            }
            if i % 50 == 0 {
                eprintln!(
                    "sweep {i}: {} points registered, σ {:.3} m, {} map points",
                    r.source_points, r.sigma, r.map_points
                );
            }
        },
    )
    .with_context(|| format!("lidar odometry of {}", c.input.display()))?;
    let total = start.elapsed().as_secs_f64();
    if let Some(dir) = &c.export_sweeps {
        if let Some(e) = export_error {
            bail!("writing sweeps into {}: {e}", dir.display());
        }
        std::fs::write(dir.join("stamps.txt"), &stamps_txt)
            .with_context(|| format!("writing {}", dir.join("stamps.txt").display()))?;
    }
    if run.poses.len() < 2 {
        bail!(
            "{}: {} usable sweep(s); odometry needs at least 2",
            c.input.display(),
            run.poses.len()
        );
    }
    let traj = Trajectory::new(run.stamps.clone(), run.poses.clone())?;
    crate::write_atomic(&c.out, poses::tum_string(&traj).as_bytes())?;

    // Ground truth: the KITTI sequence's (by sweep), or --gt (by time).
    let gt: Option<(String, Vec<Se3>, Vec<Se3>)> = if let Some(path) = &c.gt {
        let t = poses::read_trajectory(path)?;
        let (est, exact) = silvr_core::eval::poses::match_by_time(&traj, &t, 5e-3);
        Some((path.display().to_string(), est, exact))
    } else {
        input
            .ground_truth
            .as_ref()
            .map(|(p, g)| (p.display().to_string(), run.poses.clone(), g.clone()))
    };
    if let Some(path) = &c.gt_out {
        match &input.ground_truth {
            Some((_, g)) => {
                let t = Trajectory::new(run.stamps.clone(), g.clone())?;
                crate::write_atomic(path, poses::tum_string(&t).as_bytes())?;
            }
            None => bail!(
                "--gt-out {}: {} has no ground truth of its own",
                path.display(),
                c.input.display()
            ),
        }
    }
    let errors = match &gt {
        Some((name, est, exact)) if est.len() >= 3 => {
            let e = silvr_core::eval::poses::pose_errors_se3(est, exact)?;
            eprintln!("against {name}: {}", crate::pose_line(&e));
            Some(json!({"ground_truth": name, "matched": est.len(), "errors": e}))
        }
        Some((name, est, _)) => {
            eprintln!(
                "against {name}: only {} poses matched; not scored",
                est.len()
            );
            None
        }
        None => None,
    };
    let per_sweep: Vec<f64> = run.sweeps.iter().map(|r| r.seconds).collect();
    let mut sorted = per_sweep.clone();
    sorted.sort_by(f64::total_cmp);
    let median_ms = 1e3 * sorted[sorted.len() / 2];
    let dropped = input.dropped.borrow().clone();
    let report = json!({
        "input": c.input,
        "kind": input.kind,
        "topic": input.topic,
        "out": c.out,
        "sweeps": run.poses.len(),
        "dropped": dropped,
        "config": config,
        "seconds": total,
        "seconds_note": "seconds: the whole run with reading the sweeps; ms_per_sweep: odometry alone (deskew, down-sampling, ICP, map update)",
        "ms_per_sweep_median": median_ms,
        "ms_per_sweep_mean": 1e3 * per_sweep.iter().sum::<f64>() / per_sweep.len() as f64,
        "threads": std::thread::available_parallelism().map_or(1, |n| n.get()),
        "pose_errors": errors,
        "warnings": run.sweeps.iter().map(|r| r.warnings.len()).sum::<usize>(),
        "degenerate_sweeps": run
            .sweeps
            .iter()
            .filter(|r| r.constraint.is_some_and(|c| c < odometry::MIN_CONSTRAINT))
            .count(),
        "sweep_reports": run.sweeps,
    });
    eprintln!(
        "{} sweeps in {total:.2} s ({median_ms:.1} ms a sweep, median) → {}",
        run.poses.len(),
        c.out.display()
    );
    let text = serde_json::to_string_pretty(&report)?;
    // The trajectory's sidecar: its report beside it (OUT.json), whatever else is asked for.
    crate::write_atomic(&c.out.with_extension("json"), text.as_bytes())?;
    match &c.report {
        Some(p) => crate::write_atomic(p, text.as_bytes())?,
        None => println!("{text}"),
    }
    Ok(())
}
