//! `silvr reconstruct`: the whole map from one dataset, the paper's end-to-end system — submaps
//! (`silvr submaps`), then per submap train → uncertainty → filtered export (`silvr train`'s job), then
//! the merge (`silvr_core::submap::merge`: each submap filtered by its own uncertainty, the more certain
//! submap keeps each overlapping voxel) and, where the dataset has ground truth, the evaluation of the
//! merged map filtered and unfiltered.
//!
//! Scheduler: `local`, one submap after another. A submap whose `train.json` exists is done and skipped,
//! so a rerun after a kill redoes only the submaps that had not finished. A submap that fails is written
//! to `train/NAME.error.txt` and left out of the merge; the others go on, and the run exits non-zero
//! naming it. Slurm arrays, the
//! `reconstruct-task` command and the blended renders are the rest of the issue.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use silvr_core::eval::{self, GeometryOptions};
use silvr_core::pointcloud::{read_ply, write_ply};

use crate::train::{self, TrainArgs};

#[derive(clap::Args)]
pub struct ReconstructCmd {
    /// Dataset folder (its transforms.json).
    pub dataset: PathBuf,
    /// Output folder (submaps/, train/submap_NN/, merged.ply, report.json); rerun on it to finish a job.
    #[arg(long)]
    pub out: PathBuf,
    /// How submaps are cut: distance or covis.
    #[arg(long, default_value = "covis")]
    pub submaps: String,
    /// Cut into this many submaps.
    #[arg(long, conflicts_with = "max_images")]
    pub count: Option<usize>,
    /// Cut until each submap holds at most this many images (default 300).
    #[arg(long)]
    pub max_images: Option<usize>,
    /// Keyframes within this many metres of a neighbouring submap's are trained by both.
    #[arg(long, default_value_t = 2.0)]
    pub overlap: f64,
    /// Where submap tasks run: local (Slurm: not yet).
    #[arg(long, default_value = "local")]
    pub scheduler: String,
    #[arg(long, default_value = "silvr")]
    pub mode: String,
    #[arg(long, default_value = "small")]
    pub model: String,
    #[arg(long, default_value_t = 2000)]
    pub steps: u32,
    #[arg(long, default_value_t = 1024)]
    pub rays: usize,
    #[arg(long, default_value = "auto")]
    pub backend: String,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Training rays exported as points per submap.
    #[arg(long, default_value_t = 100_000)]
    pub export_rays: usize,
    /// Batches of the uncertainty pass per submap.
    #[arg(long, default_value_t = 100)]
    pub uncertainty_batches: usize,
    #[arg(long, default_value_t = 1024)]
    pub uncertainty_rays: usize,
}

pub fn run(c: &ReconstructCmd) -> Result<()> {
    if c.scheduler != "local" {
        anyhow::bail!(
            "--scheduler {}: only local runs in this build (Slurm arrays are being built: issue 19)",
            c.scheduler
        );
    }
    let mode: silvr_core::train::Mode = c
        .mode
        .parse()
        .map_err(|e: String| anyhow::anyhow!("--mode: {e}"))?;
    let total = Instant::now();
    std::fs::create_dir_all(&c.out).with_context(|| format!("creating {}", c.out.display()))?;
    let subs = c.out.join("submaps");
    let plan: serde_json::Value = if subs.join("manifest.json").is_file() {
        eprintln!("[reconstruct] submaps: reusing {}", subs.display());
        serde_json::from_slice(&std::fs::read(subs.join("manifest.json"))?)
            .with_context(|| format!("reading {}/manifest.json", subs.display()))?
    } else {
        let p = crate::submaps::run(
            &c.dataset,
            &subs,
            &c.submaps,
            c.max_images,
            c.count,
            c.overlap,
        )?;
        serde_json::to_value(&p)?
    };
    let names: Vec<String> = plan["submaps"]
        .as_array()
        .map(|a| {
            a.iter()
                .filter_map(|s| s["name"].as_str().map(String::from))
                .collect()
        })
        .unwrap_or_default();
    if names.is_empty() {
        anyhow::bail!("{}/manifest.json lists no submaps", subs.display());
    }
    let mut per_submap = Vec::new();
    let mut failed = Vec::new();
    let mut filtered = Vec::new();
    let mut unfiltered = Vec::new();
    for (k, name) in names.iter().enumerate() {
        let dir = c.out.join("train").join(name);
        let done = dir.join("train.json");
        let t = Instant::now();
        if done.is_file() {
            eprintln!(
                "[reconstruct] {name} ({}/{}): done earlier",
                k + 1,
                names.len()
            );
        } else {
            eprintln!("[reconstruct] {name} ({}/{}): training", k + 1, names.len());
            // A killed run leaves a partial folder: start that submap again.
            let _ = std::fs::remove_dir_all(&dir);
            let trained = train::run(&TrainArgs {
                dataset: subs.join(name),
                mode,
                steps: c.steps,
                rays: c.rays,
                model: c.model.clone(),
                out: dir.clone(),
                resume: None,
                checkpoint_every: 0,
                backend: c.backend.clone(),
                downscale: 1,
                seed: c.seed,
                export_rays: c.export_rays,
                render_views: None,
                export_depth: Default::default(),
                quiet: true,
                view_normals: false,
                depth_sigma: None,
                uncertainty: (mode != silvr_core::train::Mode::Vision).then(|| {
                    silvr_core::uncertainty::UncertaintyConfig {
                        batches: c.uncertainty_batches,
                        rays_per_batch: c.uncertainty_rays,
                        ..Default::default()
                    }
                }),
            })
            .with_context(|| format!("submap {name}"));
            // A failed submap is reported with its error file and does not stop the others.
            if let Err(e) = trained {
                let log = c.out.join("train").join(format!("{name}.error.txt"));
                let text = format!("{e:#}\n");
                let _ = std::fs::create_dir_all(c.out.join("train"));
                let _ = std::fs::write(&log, &text);
                eprintln!(
                    "[reconstruct] {name} failed: {e:#} (written to {}); the others go on",
                    log.display()
                );
                failed.push(serde_json::json!({
                    "name": name,
                    "error": text.trim_end(),
                    "log": log,
                }));
                continue;
            }
            let _ = std::fs::remove_file(c.out.join("train").join(format!("{name}.error.txt")));
        }
        let summary: serde_json::Value = serde_json::from_slice(&std::fs::read(&done)?)?;
        let read = |f: &str| {
            let p = dir.join(f);
            read_ply(&p).with_context(|| format!("reading {}", p.display()))
        };
        let all = read("points.ply")?;
        let kept = if dir.join("points_filtered.ply").is_file() {
            read("points_filtered.ply")?
        } else {
            all.clone()
        };
        per_submap.push(serde_json::json!({
            "name": name,
            "points": all.len(),
            "kept": kept.len(),
            "heldout_psnr_mean": summary["heldout_psnr_mean"],
            "train_s": summary["train_s"],
            "seconds_this_run": t.elapsed().as_secs_f64(),
        }));
        filtered.push((k as u32, kept));
        unfiltered.push((k as u32, all));
    }
    if filtered.is_empty() {
        anyhow::bail!(
            "every submap failed ({}); see the error files under {}",
            names.join(", "),
            c.out.join("train").display()
        );
    }
    let merge_voxel = silvr_core::submap::MERGE_VOXEL_M;
    let merged = silvr_core::submap::merge(&filtered, merge_voxel);
    let merged_all = silvr_core::submap::merge(&unfiltered, merge_voxel);
    let merged_path = c.out.join("merged.ply");
    let merged_all_path = c.out.join("merged_unfiltered.ply");
    write_ply(&merged_path, &merged)?;
    write_ply(&merged_all_path, &merged_all)?;
    eprintln!(
        "[reconstruct] merged {} submaps: {} points ({} before the uncertainty filter) → {}",
        names.len(),
        merged.len(),
        merged_all.len(),
        merged_path.display()
    );
    // Evaluation against ground truth when the dataset has it.
    let gt = crate::transforms_file(&c.dataset)
        .parent()
        .unwrap_or(Path::new("."))
        .to_path_buf();
    let evaluation = if gt.join("gt/cloud.ply").is_file() {
        let mut table = serde_json::Map::new();
        let mut rows = Vec::new();
        for (key, path) in [("unfiltered", &merged_all_path), ("filtered", &merged_path)] {
            let ev = eval::evaluate_files(path, &gt, &GeometryOptions::default())?;
            rows.push((key, ev.clone()));
            table.insert(key.into(), serde_json::to_value(&ev)?);
        }
        crate::print_table(&rows.iter().map(|(k, r)| (*k, r)).collect::<Vec<_>>());
        serde_json::Value::Object(table)
    } else {
        serde_json::Value::Null
    };
    let report = serde_json::json!({
        "dataset": c.dataset,
        "scheduler": c.scheduler,
        "submaps": plan,
        "per_submap": per_submap,
        "merge": { "rule": "per 0.2 m voxel, the submap with the lowest median log_std_combined there keeps its points", "voxel_m": merge_voxel },
        "failed": failed,
        "merged_points": merged.len(),
        "merged_unfiltered_points": merged_all.len(),
        "evaluation": evaluation,
        "seconds": total.elapsed().as_secs_f64(),
    });
    let path = c.out.join("report.json");
    crate::write_atomic(&path, serde_json::to_string_pretty(&report)?.as_bytes())?;
    eprintln!(
        "[reconstruct] report: {} ({:.1} s); open in the studio: {}",
        path.display(),
        total.elapsed().as_secs_f64(),
        crate::serve::open_command(&c.out)
    );
    if !failed.is_empty() {
        let names: Vec<&str> = failed.iter().filter_map(|f| f["name"].as_str()).collect();
        anyhow::bail!(
            "{} of {} submaps failed ({}): the map above is merged without them; fix the cause and rerun on {} to train only those",
            failed.len(),
            per_submap.len() + failed.len(),
            names.join(", "),
            c.out.display()
        );
    }
    Ok(())
}
