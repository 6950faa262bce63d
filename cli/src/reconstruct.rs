//! `silvr reconstruct`: the whole map from one dataset, the paper's end-to-end system — the poses stage
//! (`silvr poses`: the dataset's poses taken as the SLAM prior and refined; `--poses skip` trains on them
//! as they are), submaps (`silvr submaps`, co-visibility by the refined model's shared tracks), then per
//! submap train → uncertainty → filtered export (`silvr train`'s job), then the merge
//! (`silvr_core::submap::merge`: each submap filtered by its own uncertainty, the submap whose training
//! cameras are nearest keeps each overlapping voxel) and, where the dataset has ground truth, the
//! evaluation of the merged map filtered and unfiltered.
//!
//! The per-submap work is a task (`silvr reconstruct-task OUT/reconstruct.json --index I`, the index from
//! `SLURM_ARRAY_TASK_ID` when not given): `reconstruct.json` records what every task is computed from (the
//! dataset, the submaps, the training settings, the program's version), and each finished submap records
//! the settings it was trained with and a fingerprint of its inputs (`train/NAME/task.json`, written
//! last: [`TaskRecord`]). A submap is done when that record matches; a rerun redoes only the rest, so a
//! kill loses at most the tasks that were running, and a changed input file redoes the tasks that read it
//! (and, when it is the dataset's, the poses and the cut before them).
//! A failed task writes `train/NAME.error.txt` and the others go on.
//!
//! Schedulers: `local` runs the tasks here (`--jobs N` at once as child processes, one at a time in
//! process by default); `slurm` writes `slurm/job.sh`, submits one array of the missing tasks
//! (`sbatch --array`), follows it (`squeue`, `scontrol`), and reports failed tasks with their logs. Any
//! other scheduler can run the same manifest: one `reconstruct-task` per index, then `reconstruct` again
//! to merge.
//!
//! After the merge: the evaluation (merged map filtered and unfiltered, its boundary zone on its own, and
//! with `--single` one field over all images, trained as one more task, as the baseline) and blended
//! renders of a camera path at the submap boundaries (`crate::renders`, `OUT/renders`).

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};
use silvr_core::eval::{self, GeometryOptions};
use silvr_core::pointcloud::{read_ply, write_ply};

use crate::train::{self, TrainArgs};

#[derive(clap::Args)]
pub struct ReconstructCmd {
    /// Dataset folder (its transforms.json).
    pub dataset: PathBuf,
    /// Output folder (submaps/, train/submap_NN/, merged.ply + merged.laz, report.json); rerun on it to
    /// finish a job.
    #[arg(long)]
    pub out: PathBuf,
    /// The poses stage first: `refine` (`silvr poses`: the dataset's poses are the SLAM prior, refined by
    /// structure from motion; submaps are then cut by its shared tracks) or `skip` (train on the dataset's
    /// poses as they are).
    #[arg(long, default_value = "refine")]
    pub poses: String,
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
    /// Where submap tasks run: `local` or `slurm` (one `sbatch --array` of the missing submaps).
    #[arg(long, default_value = "local")]
    pub scheduler: String,
    /// Local scheduler: submap tasks at once (child processes; 1 = one after another in this process).
    #[arg(long, default_value_t = 1)]
    pub jobs: usize,
    /// Slurm: the partition (`#SBATCH --partition`).
    #[arg(long)]
    pub partition: Option<String>,
    /// Slurm: the time limit per task (`#SBATCH --time`, e.g. 02:00:00).
    #[arg(long)]
    pub time: Option<String>,
    /// Slurm: GPUs per task (`#SBATCH --gpus-per-task`).
    #[arg(long)]
    pub gpus: Option<u32>,
    /// Slurm: extra `#SBATCH` lines, as written after `#SBATCH ` (repeatable: `--sbatch "--qos=long"`).
    #[arg(long = "sbatch", allow_hyphen_values = true)]
    pub sbatch: Vec<String>,
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
    /// Also train one field over all images (a task like the submaps'): the baseline the merged map is
    /// compared with in the report.
    #[arg(long)]
    pub single: bool,
    /// Blended renders: at most this many boundary views of the camera path (0: none).
    #[arg(long, default_value_t = 12)]
    pub renders: usize,
    /// Blended renders: a second submap joins when its cameras are this close (m; SiLVR's 2 m).
    #[arg(long, default_value_t = silvr_core::submap::blend::BLEND_RADIUS_M)]
    pub blend_radius: f64,
    /// The boundary zone the report scores on its own: merged-map points whose two nearest submaps'
    /// cameras are within this many metres of the same distance.
    #[arg(long, default_value_t = 2.0)]
    pub boundary: f64,
}

/// `silvr reconstruct-task`: one submap of a reconstruction, from its manifest.
#[derive(clap::Args)]
pub struct TaskCmd {
    /// The reconstruction's `reconstruct.json` (written by `silvr reconstruct`).
    pub manifest: PathBuf,
    /// Which submap (0-based); default: `SLURM_ARRAY_TASK_ID` (Kubernetes Indexed Jobs:
    /// `JOB_COMPLETION_INDEX`).
    #[arg(long)]
    pub index: Option<usize>,
}

/// How each submap is trained: what a finished submap's `task.json` must match to count as done.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TaskSettings {
    pub mode: String,
    pub model: String,
    pub steps: u32,
    pub rays: usize,
    pub backend: String,
    pub seed: u64,
    pub export_rays: usize,
    pub uncertainty_batches: usize,
    pub uncertainty_rays: usize,
    /// The program that trained it (a new version retrains).
    pub version: String,
}

/// How the submaps were cut: a rerun with other options is refused rather than mixing two cuts.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CutSettings {
    /// `refine` or `skip` (the poses stage).
    pub poses: String,
    pub method: String,
    pub count: Option<usize>,
    pub max_images: Option<usize>,
    pub overlap: f64,
}

/// `OUT/reconstruct.json`: everything a task needs, with absolute paths (tasks run from anywhere).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Manifest {
    pub dataset: PathBuf,
    pub out: PathBuf,
    pub cut: CutSettings,
    /// The submaps: tasks `0..names.len()`.
    pub names: Vec<String>,
    pub settings: TaskSettings,
    /// The dataset the submaps were cut from (the refined poses, or the dataset itself).
    #[serde(default)]
    pub trained_from: PathBuf,
    /// Whether task `names.len()` trains one field over all of `trained_from` (`train/single`).
    #[serde(default)]
    pub single: bool,
    /// The dataset's input fingerprint ([`inputs_fingerprint`]): when it changes, the poses and the cut
    /// are done again.
    #[serde(default)]
    pub dataset_inputs: String,
    /// Per task, the fingerprint of what it trains on: a task is redone when its inputs changed.
    #[serde(default)]
    pub inputs: Vec<String>,
}

/// The single-field baseline's task name.
pub const SINGLE: &str = "single";

/// What a finished task's `task.json` records: the settings it was trained with and the fingerprint of
/// what it read; it is done while both match the manifest's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TaskRecord {
    #[serde(flatten)]
    pub settings: TaskSettings,
    pub inputs: String,
}

/// A fingerprint of what training on a dataset reads: its transforms.json, and the name, size and
/// modification time of every file a frame names (what make and cargo compare: hashing the images would
/// read every one of them on each rerun). FNV-1a, 64 bits, stable across builds.
pub fn inputs_fingerprint(dataset: &Path) -> Result<String> {
    struct Fnv(u64);
    impl Fnv {
        fn write(&mut self, b: &[u8]) {
            for &x in b {
                self.0 = (self.0 ^ x as u64).wrapping_mul(0x100_0000_01b3);
            }
        }
    }
    let json = crate::transforms_file(dataset);
    let root = json.parent().unwrap_or(Path::new(".")).to_path_buf();
    let bytes = std::fs::read(&json).with_context(|| format!("reading {}", json.display()))?;
    let mut h = Fnv(0xcbf2_9ce4_8422_2325);
    h.write(&bytes);
    let text = std::str::from_utf8(&bytes)
        .with_context(|| format!("{} is not UTF-8 text", json.display()))?;
    let (frames, _, _) = silvr_core::dataset::parse_frames(text, &json)?;
    for f in &frames {
        let files = [
            Some(&f.file_path),
            f.depth_file_path.as_ref(),
            f.normal_file_path.as_ref(),
            f.sky_mask_path.as_ref(),
        ];
        for p in files.into_iter().flatten() {
            h.write(p.as_bytes());
            match std::fs::metadata(root.join(p)) {
                Ok(m) => {
                    h.write(&m.len().to_le_bytes());
                    let t = m
                        .modified()
                        .ok()
                        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                        .map_or(0, |d| d.as_nanos());
                    h.write(&t.to_le_bytes());
                }
                Err(_) => h.write(b"missing"),
            }
        }
    }
    Ok(format!("{:016x}", h.0))
}

impl Manifest {
    fn read(path: &Path) -> Result<Manifest> {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        serde_json::from_slice(&bytes).with_context(|| {
            format!(
                "{}: not a reconstruct.json written by this version of silvr",
                path.display()
            )
        })
    }

    fn dir(&self, name: &str) -> PathBuf {
        self.out.join("train").join(name)
    }

    /// Tasks: the submaps, then the single field when asked for.
    fn tasks(&self) -> usize {
        self.names.len() + self.single as usize
    }

    fn name(&self, k: usize) -> &str {
        self.names.get(k).map_or(SINGLE, String::as_str)
    }

    /// What task `k` trains on.
    fn task_dataset(&self, k: usize) -> PathBuf {
        match self.names.get(k) {
            Some(n) => self.out.join("submaps").join(n),
            None => self.trained_from.clone(),
        }
    }

    /// Whether task `k` finished with the current settings.
    fn done(&self, k: usize) -> bool {
        let dir = self.dir(self.name(k));
        dir.join("train.json").is_file()
            && std::fs::read(dir.join("task.json"))
                .ok()
                .and_then(|b| serde_json::from_slice::<TaskRecord>(&b).ok())
                .is_some_and(|r| {
                    r.settings == self.settings && Some(&r.inputs) == self.inputs.get(k)
                })
    }

    /// Prints the submaps not in `todo` as done earlier.
    fn say_done(&self, todo: &[usize]) {
        for k in (0..self.tasks()).filter(|k| !todo.contains(k)) {
            eprintln!(
                "[reconstruct] {} ({}/{}): done earlier",
                self.name(k),
                k + 1,
                self.tasks()
            );
        }
    }

    fn error_file(&self, name: &str) -> PathBuf {
        self.out.join("train").join(format!("{name}.error.txt"))
    }
}

/// `silvr reconstruct-task`: trains submap `index` of the manifest (skips it when already done).
pub fn task(c: &TaskCmd) -> Result<()> {
    let m = Manifest::read(&c.manifest)?;
    let index = match c.index {
        Some(i) => i,
        None => ["SLURM_ARRAY_TASK_ID", "JOB_COMPLETION_INDEX"]
            .iter()
            .find_map(|v| std::env::var(v).ok())
            .context("no --index, and neither SLURM_ARRAY_TASK_ID nor JOB_COMPLETION_INDEX is set")?
            .trim()
            .parse()
            .context("the task index in the environment is not a number")?,
    };
    if index >= m.tasks() {
        anyhow::bail!(
            "--index {index}: {} lists {} tasks (0..{})",
            c.manifest.display(),
            m.tasks(),
            m.tasks()
        );
    }
    run_task(&m, index, true)
}

/// One submap: train → uncertainty → filtered export into `train/NAME`, then its `task.json`. A failure
/// is written to `train/NAME.error.txt` (and returned).
fn run_task(m: &Manifest, k: usize, say: bool) -> Result<()> {
    let name = m.name(k);
    let dir = m.dir(name);
    if m.done(k) {
        if say {
            eprintln!(
                "[reconstruct] {name} ({}/{}): done earlier",
                k + 1,
                m.tasks()
            );
        }
        return Ok(());
    }
    if say {
        eprintln!("[reconstruct] {name} ({}/{}): training", k + 1, m.tasks());
    }
    // A killed or outdated run leaves a folder: start that submap again.
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(m.out.join("train"))?;
    let s = &m.settings;
    let trained = (|| -> Result<()> {
        let mode: silvr_core::train::Mode = s
            .mode
            .parse()
            .map_err(|e: String| anyhow::anyhow!("--mode: {e}"))?;
        train::run(&TrainArgs {
            dataset: m.task_dataset(k),
            // The submaps (and the poses stage's output) name the world's images from beside them.
            data_root: Some(crate::data_root(&m.dataset, &m.out)?),
            mode,
            steps: s.steps,
            rays: s.rays,
            model: s.model.clone(),
            out: dir.clone(),
            resume: None,
            checkpoint_every: 0,
            backend: s.backend.clone(),
            downscale: 1,
            seed: s.seed,
            export_rays: s.export_rays,
            render_views: None,
            export_depth: Default::default(),
            quiet: true,
            view_normals: false,
            depth_sigma: None,
            uncertainty: (mode != silvr_core::train::Mode::Vision).then(|| {
                silvr_core::uncertainty::UncertaintyConfig {
                    batches: s.uncertainty_batches,
                    rays_per_batch: s.uncertainty_rays,
                    ..Default::default()
                }
            }),
        })?;
        let record = TaskRecord {
            settings: s.clone(),
            inputs: m.inputs.get(k).cloned().unwrap_or_default(),
        };
        crate::write_atomic(
            &dir.join("task.json"),
            serde_json::to_string_pretty(&record)?.as_bytes(),
        )
    })()
    .with_context(|| format!("submap {name}"));
    let err_file = m.error_file(name);
    match trained {
        Ok(()) => {
            let _ = std::fs::remove_file(&err_file);
            Ok(())
        }
        Err(e) => {
            let text = format!("{e:#}\n");
            let _ = std::fs::write(&err_file, &text);
            Err(e.context(format!("written to {}", err_file.display())))
        }
    }
}

/// Why a task did not finish: its error, and where its log is.
struct Failure {
    name: String,
    error: String,
    log: Option<PathBuf>,
}

pub fn run(c: &ReconstructCmd) -> Result<()> {
    if !["local", "slurm"].contains(&c.scheduler.as_str()) {
        anyhow::bail!("--scheduler {}: expected local or slurm", c.scheduler);
    }
    let _: silvr_core::train::Mode = c
        .mode
        .parse()
        .map_err(|e: String| anyhow::anyhow!("--mode: {e}"))?;
    let total = Instant::now();
    std::fs::create_dir_all(&c.out).with_context(|| format!("creating {}", c.out.display()))?;
    let abs =
        |p: &Path| std::path::absolute(p).with_context(|| format!("resolving {}", p.display()));
    let out = abs(&c.out)?;
    if !["refine", "skip"].contains(&c.poses.as_str()) {
        anyhow::bail!("--poses {}: expected refine or skip", c.poses);
    }
    let cut = CutSettings {
        poses: c.poses.clone(),
        method: c.submaps.clone(),
        count: c.count,
        max_images: c.max_images,
        overlap: c.overlap,
    };
    let manifest_path = out.join("reconstruct.json");
    let dataset_inputs = inputs_fingerprint(&c.dataset)?;
    if manifest_path.is_file() {
        let before = Manifest::read(&manifest_path)?;
        if before.cut != cut {
            anyhow::bail!(
                "{} was cut into submaps with other options ({:?}); this run asks for {:?}: use a new --out",
                out.display(),
                before.cut,
                cut
            );
        }
        // The dataset changed since (a file a frame names, or transforms.json): poses and cut again;
        // the tasks whose inputs changed with them are redone, the others kept.
        if !before.dataset_inputs.is_empty() && before.dataset_inputs != dataset_inputs {
            eprintln!(
                "[reconstruct] {} changed since the last run: refining the poses and cutting again",
                c.dataset.display()
            );
            for stage in ["poses", "submaps"] {
                let dir = out.join(stage);
                if dir.exists() {
                    std::fs::remove_dir_all(&dir)
                        .with_context(|| format!("removing {}", dir.display()))?;
                }
            }
        }
    }
    // The poses stage: the dataset's poses refined (written as a dataset under OUT/poses, renamed into
    // place when complete, so its report marks it done), and the Sim(3) from the refined poses back to
    // the dataset's, which maps the merged map into the frame its ground truth is in.
    let (cut_from, poses_block, alignment) = if c.poses == "refine" {
        let dir = out.join("poses");
        let report: serde_json::Value = if dir.join("report.json").is_file() {
            eprintln!("[reconstruct] poses: reusing {}", dir.display());
            serde_json::from_slice(&std::fs::read(dir.join("report.json"))?)
                .with_context(|| format!("reading {}/report.json", dir.display()))?
        } else {
            eprintln!("[reconstruct] poses: refining the dataset's poses (silvr poses)");
            crate::poses::run(&crate::poses::PosesArgs {
                dataset: c.dataset.clone(),
                out: dir.clone(),
                gt: Some(c.dataset.clone()),
                refine_extrinsics: false,
                no_loops: false,
                max_features: 4096,
                peak_threshold: None,
                downscale: None,
                quiet: true,
            })?
        };
        let p = &report["poses"];
        eprintln!(
            "[reconstruct] poses: {}/{} images registered, reprojection RMSE {:.3} px on the prior → {:.3} px",
            p["registered"],
            p["images"],
            p["rmse_prior_px"].as_f64().unwrap_or(f64::NAN),
            p["rmse_px"].as_f64().unwrap_or(f64::NAN)
        );
        let align: silvr_core::eval::poses::PoseErrors =
            serde_json::from_value(report["errors"]["refined"].clone()).with_context(|| {
                format!(
                    "{}/report.json has no refined-vs-dataset errors",
                    dir.display()
                )
            })?;
        let block = serde_json::json!({
            "dir": dir,
            "registered": p["registered"],
            "images": p["images"],
            "rmse_px": p["rmse_px"],
            "rmse_prior_px": p["rmse_prior_px"],
            "moved_from_dataset": report["errors"]["refined"],
        });
        (dir, block, Some(align.alignment))
    } else {
        (
            c.dataset.clone(),
            serde_json::json!({ "skipped": true }),
            None,
        )
    };
    let subs = out.join("submaps");
    let plan: serde_json::Value = if subs.join("manifest.json").is_file() {
        eprintln!("[reconstruct] submaps: reusing {}", subs.display());
        serde_json::from_slice(&std::fs::read(subs.join("manifest.json"))?)
            .with_context(|| format!("reading {}/manifest.json", subs.display()))?
    } else {
        let p = crate::submaps::run(
            &cut_from,
            &subs,
            &c.submaps,
            c.max_images,
            c.count,
            c.overlap,
            Some(&crate::data_root(&c.dataset, &out)?),
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
    let mut m = Manifest {
        dataset: abs(&c.dataset)?,
        out: out.clone(),
        cut,
        names: names.clone(),
        settings: TaskSettings {
            mode: c.mode.clone(),
            model: c.model.clone(),
            steps: c.steps,
            rays: c.rays,
            backend: c.backend.clone(),
            seed: c.seed,
            export_rays: c.export_rays,
            uncertainty_batches: c.uncertainty_batches,
            uncertainty_rays: c.uncertainty_rays,
            version: env!("CARGO_PKG_VERSION").to_string(),
        },
        trained_from: abs(&cut_from)?,
        single: c.single,
        dataset_inputs,
        inputs: Vec::new(),
    };
    m.inputs = (0..m.tasks())
        .map(|k| inputs_fingerprint(&m.task_dataset(k)))
        .collect::<Result<_>>()?;
    crate::write_atomic(&manifest_path, serde_json::to_string_pretty(&m)?.as_bytes())?;

    let started: Vec<bool> = (0..m.tasks()).map(|k| !m.done(k)).collect();
    let failures = match c.scheduler.as_str() {
        "slurm" => slurm(c, &m, &manifest_path)?,
        _ => local(c, &m, &manifest_path)?,
    };

    // Merge what finished.
    let mut per_submap = Vec::new();
    let mut filtered = Vec::new();
    let mut unfiltered = Vec::new();
    // Each merged submap's training cameras (the merge rule keeps a shared voxel's nearest submap).
    let mut merge_cameras = Vec::new();
    for (k, name) in names.iter().enumerate() {
        if !m.done(k) {
            continue;
        }
        let dir = m.dir(name);
        let summary: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.join("train.json"))?)
                .with_context(|| format!("reading {}/train.json", dir.display()))?;
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
            "backend": summary["backend"],
            "backends": summary["stages"],
            "trained_this_run": started[k],
        }));
        filtered.push((k as u32, kept));
        unfiltered.push((k as u32, all));
        merge_cameras.push(crate::renders::training_cameras(&subs.join(name))?);
    }
    let failed: Vec<serde_json::Value> = failures
        .iter()
        .map(|f| serde_json::json!({ "name": f.name, "error": f.error, "log": f.log }))
        .collect();
    if filtered.is_empty() {
        anyhow::bail!(
            "every submap failed ({}); see the error files under {}",
            names.join(", "),
            out.join("train").display()
        );
    }
    let merge_voxel = silvr_core::submap::MERGE_VOXEL_M;
    let merged = silvr_core::submap::merge(&filtered, &merge_cameras, merge_voxel);
    let merged_all = silvr_core::submap::merge(&unfiltered, &merge_cameras, merge_voxel);
    let merged_path = out.join("merged.ply");
    let merged_all_path = out.join("merged_unfiltered.ply");
    // `write_ply` writes atomically: a kill never leaves half a merged map.
    for (path, cloud) in [(&merged_path, &merged), (&merged_all_path, &merged_all)] {
        write_ply(path, cloud).with_context(|| format!("writing {}", path.display()))?;
    }
    // The filtered map also as LAZ 1.4 for survey and GIS tools (uncertainty and submap as extra bytes).
    let merged_laz = out.join("merged.laz");
    silvr_core::lasfile::write_las(&merged_laz, &merged)?;
    // Every merged point with its uncertainty as COPC (merged_unfiltered.ply's points), for the studio and
    // streaming viewers to open by link and filter themselves (its header's summary states the default
    // filter over the whole map); `silvr serve`'s link opens it in place of that PLY.
    let merged_copc = out.join("merged_unfiltered.copc.laz");
    if !merged_all.is_empty() {
        use silvr_core::copc::write::{write_copc, CopcInput, CopcOptions};
        let w = write_copc(
            CopcInput::Cloud(&merged_all),
            &merged_copc,
            &CopcOptions::default(),
        )?;
        eprintln!(
            "[reconstruct] {} points as COPC → {} ({:.1} MB)",
            w.points,
            merged_copc.display(),
            w.bytes as f64 / 1e6
        );
    }
    eprintln!(
        "[reconstruct] merged {} submaps: {} points ({} before the uncertainty filter) → {}",
        filtered.len(),
        merged.len(),
        merged_all.len(),
        merged_path.display()
    );
    // Evaluation against ground truth when the dataset has it.
    let gt = crate::transforms_file(&c.dataset)
        .parent()
        .unwrap_or(Path::new("."))
        .to_path_buf();
    let single_dir = m.dir(SINGLE);
    let single_done = m.single && m.done(m.names.len());
    // The baseline field's own summary (held-out PSNR over all of the dataset's held-out views).
    let single = if single_done {
        let t: serde_json::Value =
            serde_json::from_slice(&std::fs::read(single_dir.join("train.json"))?)
                .with_context(|| format!("reading {}/train.json", single_dir.display()))?;
        serde_json::json!({
            "heldout_psnr_mean": t["heldout_psnr_mean"],
            "train_s": t["train_s"],
            "backend": t["backend"],
            "trained_this_run": started[m.names.len()],
        })
    } else {
        serde_json::Value::Null
    };
    let evaluation = if gt.join("gt/cloud.ply").is_file() {
        let opts = GeometryOptions {
            reconstruction_to_gt: alignment.map(|a| a.to_mat4()),
            ..GeometryOptions::default()
        };
        // The merged maps as in memory; the single field's clouds from its folder.
        let mut clouds: Vec<(&str, std::borrow::Cow<silvr_core::pointcloud::PointCloud>)> =
            Vec::new();
        if single_done {
            for (key, file) in [
                ("single_unfiltered", "points.ply"),
                ("single_filtered", "points_filtered.ply"),
            ] {
                let path = single_dir.join(file);
                if path.is_file() {
                    let cloud =
                        read_ply(&path).with_context(|| format!("reading {}", path.display()))?;
                    clouds.push((key, std::borrow::Cow::Owned(cloud)));
                }
            }
        }
        clouds.push(("unfiltered", std::borrow::Cow::Borrowed(&merged_all)));
        clouds.push(("filtered", std::borrow::Cow::Borrowed(&merged)));
        let mut rows = Vec::new();
        let mut table = serde_json::Map::new();
        let truth = eval::GroundTruth::load(&gt)?;
        for (key, cloud) in &clouds {
            let ev = truth.evaluate(cloud, &opts)?.report;
            rows.push((key.to_string(), ev.clone()));
            table.insert(key.to_string(), serde_json::to_value(&ev)?);
        }
        // σ against the error over the merged map: each point's calibrated read-out (its submap's) and
        // the raw Laplace one, from that submap's uncertainty.bin.
        let fishers: Vec<Option<silvr_core::uncertainty::Fisher>> = names
            .iter()
            .map(|n| {
                let p = m.dir(n).join("uncertainty.bin");
                let bytes = std::fs::read(&p).ok()?;
                silvr_core::uncertainty::Fisher::from_bytes(&bytes, &p.display().to_string()).ok()
            })
            .collect();
        if let Some(first) = fishers.iter().flatten().next() {
            let at = silvr_core::uncertainty::unconstrained_log_std(first.prior_sigma_m());
            let mut with_raw = merged_all.clone();
            crate::uncertainty::add_raw_fields(&mut with_raw, |s| fishers.get(s)?.as_ref());
            let ev = truth.evaluate(&with_raw, &opts)?;
            let rel =
                crate::uncertainty::reliability_block(&out, &ev.reconstruction, &ev.rec_to_gt, at)?;
            table.insert("reliability".into(), rel);
        }
        // The boundary zone of each merged map scored on its own: points near the bisector of two
        // submaps' cameras, where a cut shows as a seam.
        let cameras: Vec<Vec<glam::DVec3>> = names
            .iter()
            .map(|n| crate::renders::training_cameras(&subs.join(n)))
            .collect::<Result<_>>()?;
        for (key, cloud) in [
            ("boundary_unfiltered", &merged_all),
            ("boundary_filtered", &merged),
        ] {
            let mask = silvr_core::submap::near_boundary(&cloud.positions, &cameras, c.boundary);
            let idx: Vec<usize> = (0..mask.len()).filter(|&i| mask[i]).collect();
            if idx.is_empty() {
                continue;
            }
            let ev = truth.evaluate(&cloud.select(&idx), &opts)?.report;
            rows.push((key.to_string(), ev.clone()));
            table.insert(key.to_string(), serde_json::to_value(&ev)?);
        }
        // Each submap's own clouds scored on what its training cameras saw (synthetic worlds only: that
        // takes each image's exact depth), so a cut is judged by how well each side reconstructs its part.
        let mut seen_rows = Vec::new();
        let mut seen_note = None;
        for (k, name) in names.iter().enumerate() {
            if !m.done(k) {
                continue;
            }
            // An optional score: a problem with the exact depth is said and recorded, not fatal.
            let seen = match seen_by(&subs.join(name), alignment.as_ref()) {
                Ok(Some(seen)) => seen,
                Ok(None) => break,
                Err(e) => {
                    let note = format!("each submap on what it saw: skipped, {e:#}");
                    eprintln!("[reconstruct] {note}");
                    seen_note = Some(note);
                    seen_rows.clear();
                    break;
                }
            };
            let gt_idx = seen.select(&truth.cloud.positions);
            let mut entry = serde_json::json!({ "name": name, "gt_points_seen": gt_idx.len() });
            for (key, file) in [
                ("unfiltered", "points.ply"),
                ("filtered", "points_filtered.ply"),
            ] {
                let path = m.dir(name).join(file);
                if !path.is_file() || gt_idx.is_empty() {
                    continue;
                }
                let cloud =
                    read_ply(&path).with_context(|| format!("reading {}", path.display()))?;
                let ev = truth.evaluate_within(&cloud, &gt_idx, &opts)?.report;
                entry[key] = serde_json::to_value(&ev)?;
                rows.push((format!("{name} {key}, its view"), ev));
            }
            seen_rows.push(entry);
        }
        if let Some(note) = seen_note {
            table.insert(
                "per_submap_seen".into(),
                serde_json::json!({ "note": note }),
            );
        }
        if !seen_rows.is_empty() {
            let mean = |key: &str, field: &dyn Fn(&serde_json::Value) -> Option<f64>| {
                let v: Vec<f64> = seen_rows.iter().filter_map(|e| field(&e[key])).collect();
                (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
            };
            let acc = |r: &serde_json::Value| r["accuracy_m"].as_f64();
            let f10 = |r: &serde_json::Value| r["fscore_10cm"].as_f64();
            let r10 = |r: &serde_json::Value| r["recall_10cm"].as_f64();
            table.insert(
                "per_submap_seen".into(),
                serde_json::json!({
                    "what": format!("each submap's clouds against the GT its own training cameras saw (exact depth, {} m voxels)", silvr_core::submap::MERGE_VOXEL_M),
                    "submaps": seen_rows,
                    "mean_accuracy_m": { "unfiltered": mean("unfiltered", &acc), "filtered": mean("filtered", &acc) },
                    "mean_fscore_10cm": { "unfiltered": mean("unfiltered", &f10), "filtered": mean("filtered", &f10) },
                    "mean_recall_10cm": { "unfiltered": mean("unfiltered", &r10), "filtered": mean("filtered", &r10) },
                }),
            );
        }
        // The trade-off the studio's filter slider makes, over the whole merged map: its unfiltered points
        // ranked by their log-std (one threshold across submaps), the most uncertain dropped first.
        let curve = filter_curve(&truth, &opts, &merged_all)?;
        if !curve.is_empty() {
            table.insert("filter_curve".into(), serde_json::to_value(&curve)?);
        }
        table.insert(
            "plots".into(),
            serde_json::to_value(report_plots(&out, &rows, &curve)?)?,
        );
        crate::print_table(
            &rows
                .iter()
                .map(|(k, r)| (k.as_str(), r))
                .collect::<Vec<_>>(),
        );
        let get = |k: &str| rows.iter().find(|(n, _)| n == k).map(|(_, r)| r);
        if let (Some(u), Some(f)) = (get("unfiltered"), get("filtered")) {
            let claims = serde_json::json!({
                "filter_accuracy_gain": 1.0 - f.accuracy_m / u.accuracy_m,
                "filter_completeness_loss_at_10cm": 1.0 - recall_10cm(f) / recall_10cm(u),
                "claim": "the paper: filtering improves merged accuracy by ≥ 30 % at ≤ 10 % completeness loss (completeness: GT points within 10 cm)",
                "merged_vs_single_accuracy_m": get("single_unfiltered").map(|s| [s.accuracy_m, u.accuracy_m]),
                "boundary_accuracy_m": get("boundary_filtered").map(|b| b.accuracy_m),
                "boundary_radius_m": c.boundary,
            });
            eprintln!(
                "[reconstruct] uncertainty filter: accuracy {:+.1} %, completeness (GT within 10 cm) {:+.1} %",
                100.0 * (f.accuracy_m / u.accuracy_m - 1.0),
                100.0 * (recall_10cm(f) / recall_10cm(u) - 1.0)
            );
            table.insert("claims".into(), claims);
        }
        serde_json::Value::Object(table)
    } else {
        serde_json::Value::Null
    };
    // Blended renders along the camera path (skipped while a task is missing: the map is incomplete).
    let renders = if c.renders > 0 && failures.is_empty() {
        let key = crate::renders::RenderKey {
            views: c.renders,
            radius_m: c.blend_radius,
            submaps: names.clone(),
            settings: serde_json::to_value(&m.settings)?,
        };
        let retrained = started.iter().any(|&s| s);
        let report = match crate::renders::reuse(&out, &key).filter(|_| !retrained) {
            Some(r) => {
                eprintln!(
                    "[reconstruct] renders: reusing {}",
                    out.join("renders").display()
                );
                r
            }
            None => {
                eprintln!(
                    "[reconstruct] renders: blending submaps along the camera path (up to {} boundary views)",
                    c.renders
                );
                crate::renders::run(&crate::renders::RenderJob {
                    out: &out,
                    dataset: &c.dataset,
                    trained_from: &cut_from,
                    submaps: names.iter().map(|n| (n.clone(), m.dir(n))).collect(),
                    alignment,
                    backend: &c.backend,
                    key,
                })?
            }
        };
        eprintln!(
            "[reconstruct] renders: {} boundary views of {} ({}): PSNR nearest only {:.2} dB, SiLVR blend {:.2} dB, Block-NeRF blend {:.2} dB",
            report.views.len(),
            report.path_views,
            report.path,
            report.mean_psnr_nearest,
            report.mean_psnr_blended_silvr,
            report.mean_psnr_blended_idw
        );
        serde_json::to_value(&report)?
    } else {
        serde_json::Value::Null
    };
    let report = serde_json::json!({
        "dataset": m.dataset,
        "scheduler": c.scheduler,
        "manifest": manifest_path,
        "poses": poses_block,
        "submaps": plan,
        "per_submap": per_submap,
        "single": single,
        "merge": { "rule": "per 0.2 m voxel shared by submaps, the one whose training cameras are nearest (median over its points there) keeps its points; lower median log_std_combined breaks ties", "voxel_m": merge_voxel },
        "failed": failed,
        "merged_points": merged.len(),
        "merged_unfiltered_points": merged_all.len(),
        "evaluation": evaluation,
        "renders": renders,
        "seconds": total.elapsed().as_secs_f64(),
    });
    let path = out.join("report.json");
    crate::write_atomic(&path, serde_json::to_string_pretty(&report)?.as_bytes())?;
    eprintln!(
        "[reconstruct] report: {} ({:.1} s); open in the studio: {}",
        path.display(),
        total.elapsed().as_secs_f64(),
        crate::serve::open_command(&out)
    );
    if !failures.is_empty() {
        let names: Vec<&str> = failures.iter().map(|f| f.name.as_str()).collect();
        anyhow::bail!(
            "{} of {} {} failed ({}): the map above is merged without them; fix the cause and rerun on {} to train only those",
            failures.len(),
            m.tasks(),
            if m.single { "tasks" } else { "submaps" },
            names.join(", "),
            out.display()
        );
    }
    Ok(())
}

/// The local scheduler: in process one after another, or `--jobs N` child processes at once.
fn local(c: &ReconstructCmd, m: &Manifest, manifest_path: &Path) -> Result<Vec<Failure>> {
    let mut failures = Vec::new();
    let t = Instant::now();
    if c.jobs <= 1 {
        let todo: Vec<usize> = (0..m.tasks()).filter(|&k| !m.done(k)).collect();
        for k in 0..m.tasks() {
            if todo.contains(&k) {
                progress(&todo, todo.iter().filter(|&&j| j < k).count(), t);
            }
            if let Err(e) = run_task(m, k, true) {
                eprintln!(
                    "[reconstruct] {} failed: {e:#}; the others go on",
                    m.name(k)
                );
                failures.push(Failure {
                    name: m.name(k).to_string(),
                    error: format!("{e:#}"),
                    log: Some(m.error_file(m.name(k))),
                });
            }
        }
        return Ok(failures);
    }
    let exe = std::env::current_exe().context("finding the silvr binary")?;
    let logs = m.out.join("logs");
    std::fs::create_dir_all(&logs)?;
    let todo: Vec<usize> = (0..m.tasks()).filter(|&k| !m.done(k)).collect();
    m.say_done(&todo);
    let mut queue = todo.clone().into_iter();
    let mut finished = 0;
    let mut running: Vec<(usize, std::process::Child, PathBuf)> = Vec::new();
    loop {
        while running.len() < c.jobs {
            let Some(k) = queue.next() else { break };
            let log = logs.join(format!("{}.log", m.name(k)));
            let file = std::fs::File::create(&log)
                .with_context(|| format!("creating {}", log.display()))?;
            let child = std::process::Command::new(&exe)
                .arg("reconstruct-task")
                .arg(manifest_path)
                .arg("--index")
                .arg(k.to_string())
                .stdout(file.try_clone()?)
                .stderr(file)
                .spawn()
                .with_context(|| format!("starting {}", exe.display()))?;
            eprintln!(
                "[reconstruct] {} ({}/{}): training (log {})",
                m.name(k),
                k + 1,
                m.tasks(),
                log.display()
            );
            running.push((k, child, log));
        }
        if running.is_empty() {
            break;
        }
        std::thread::sleep(Duration::from_millis(200));
        let mut i = 0;
        while i < running.len() {
            if let Some(status) = running[i].1.try_wait()? {
                let (k, _, log) = running.swap_remove(i);
                finished += 1;
                if !status.success() || !m.done(k) {
                    let error = std::fs::read_to_string(m.error_file(m.name(k)))
                        .unwrap_or_else(|_| format!("exited with {status}"));
                    eprintln!(
                        "[reconstruct] {} failed ({}): see {}",
                        m.name(k),
                        error.trim(),
                        log.display()
                    );
                    failures.push(Failure {
                        name: m.name(k).to_string(),
                        error: error.trim().to_string(),
                        log: Some(log),
                    });
                } else {
                    eprintln!("[reconstruct] {}: done", m.name(k));
                }
                progress(&todo, finished, t);
            } else {
                i += 1;
            }
        }
    }
    Ok(failures)
}

/// Completeness as the claims state it: the fraction of GT points within 10 cm of the map.
fn recall_10cm(r: &silvr_core::eval::GeometryReport) -> f64 {
    r.thresholds
        .iter()
        .find(|t| (t.threshold_m - 0.10).abs() < 1e-9)
        .map_or(f64::NAN, |t| t.recall)
}

/// One point of the merged map's filter curve.
#[derive(serde::Serialize)]
struct CurvePoint {
    kept_fraction: f64,
    accuracy_m: f64,
    recall_10cm: f64,
}

/// Accuracy and completeness (GT within 10 cm) of the unfiltered merged map keeping its least uncertain
/// 100 %, 90 % … 50 % of points by `log_std_combined`. Empty when the cloud has no log-std.
fn filter_curve(
    truth: &eval::GroundTruth,
    opts: &GeometryOptions,
    merged_all: &silvr_core::pointcloud::PointCloud,
) -> Result<Vec<CurvePoint>> {
    let Some(log_std) = merged_all.scalar("log_std_combined") else {
        return Ok(Vec::new());
    };
    // Non-finite log-std ranks as the most uncertain, so 100 % is the unfiltered map itself.
    let rank = |i: usize| {
        let v = log_std[i];
        if v.is_finite() {
            v
        } else {
            f32::INFINITY
        }
    };
    let mut order: Vec<usize> = (0..log_std.len()).collect();
    order.sort_by(|&a, &b| rank(a).total_cmp(&rank(b)));
    let mut curve = Vec::new();
    for kept in [1.0, 0.9, 0.8, 0.7, 0.6, 0.5] {
        let n = ((order.len() as f64 * kept).round() as usize).max(1);
        let r = truth
            .evaluate(&merged_all.select(&order[..n]), opts)?
            .report;
        curve.push(CurvePoint {
            kept_fraction: kept,
            accuracy_m: r.accuracy_m,
            recall_10cm: recall_10cm(&r),
        });
    }
    Ok(curve)
}

/// The report's charts, beside report.json: the F-score of each map by distance threshold, and the filter
/// curve relative to the unfiltered map. Returns the files written.
fn report_plots(
    out: &Path,
    rows: &[(String, silvr_core::eval::GeometryReport)],
    curve: &[CurvePoint],
) -> Result<Vec<String>> {
    use silvr_core::eval::plot;
    let mut written = Vec::new();
    let maps: Vec<(&str, Vec<f64>, Vec<f64>)> = [
        ("single_unfiltered", "one field"),
        ("unfiltered", "merged"),
        ("filtered", "merged, filtered"),
        ("boundary_filtered", "boundary zone, filtered"),
    ]
    .iter()
    .filter_map(|(key, label)| {
        let r = &rows.iter().find(|(k, _)| k == key)?.1;
        let x = r.thresholds.iter().map(|t| t.threshold_m * 100.0).collect();
        let y = r.thresholds.iter().map(|t| t.fscore).collect();
        Some((*label, x, y))
    })
    .collect();
    if !maps.is_empty() {
        let series: Vec<plot::Series> = maps
            .iter()
            .enumerate()
            .map(|(k, (name, x, y))| plot::Series {
                name,
                x,
                y,
                colour: plot::PALETTE[k % plot::PALETTE.len()],
            })
            .collect();
        let img = plot::line_chart("F-score by threshold", "threshold (cm)", "F-score", &series);
        crate::write_atomic(&out.join("fscore.png"), &plot::png_bytes(&img))?;
        written.push("fscore.png".to_string());
    }
    if let Some(all) = curve.first() {
        let x: Vec<f64> = curve.iter().map(|c| c.kept_fraction).collect();
        let acc: Vec<f64> = curve
            .iter()
            .map(|c| c.accuracy_m / all.accuracy_m)
            .collect();
        let rec: Vec<f64> = curve
            .iter()
            .map(|c| c.recall_10cm / all.recall_10cm)
            .collect();
        let series = [
            plot::Series {
                name: "accuracy (mean error)",
                x: &x,
                y: &acc,
                colour: plot::PALETTE[0],
            },
            plot::Series {
                name: "GT within 10 cm",
                x: &x,
                y: &rec,
                colour: plot::PALETTE[1],
            },
        ];
        let img = plot::line_chart(
            "merged map filtered by its uncertainty",
            "fraction of points kept (least uncertain)",
            "relative to unfiltered",
            &series,
        );
        crate::write_atomic(&out.join("filter_curve.png"), &plot::png_bytes(&img))?;
        written.push("filter_curve.png".to_string());
    }
    Ok(written)
}

/// What a submap's training cameras saw, from each image's exact depth (`gt/depth`, synthetic worlds),
/// in the GT frame: each camera through `to_gt` (the Sim(3) the evaluation maps the clouds with), its
/// metric range added there. `None` when an image has no exact depth.
fn seen_by(
    submap_dataset: &Path,
    to_gt: Option<&silvr_core::geometry::Sim3>,
) -> Result<Option<silvr_core::eval::SeenVoxels>> {
    let json = crate::transforms_file(submap_dataset);
    let (frames, _, val) = silvr_core::dataset::read_frames(&json)?;
    let base = json.parent().unwrap_or(Path::new("."));
    let mut seen = silvr_core::eval::SeenVoxels::new(silvr_core::submap::MERGE_VOXEL_M);
    for f in frames.iter().filter(|f| !val.contains(&f.file_path)) {
        let Some(depth) = crate::synthetic_gt_file(&base.join(&f.file_path), "depth") else {
            return Ok(None);
        };
        let (model, pose) = f.camera(&json)?;
        let (w, h, px) = silvr_core::dataset::read_png16(&depth)?;
        if (w, h) != (model.width, model.height) {
            anyhow::bail!(
                "{}: {w}x{h}, but {} is {}x{} in {}",
                depth.display(),
                f.file_path,
                model.width,
                model.height,
                json.display()
            );
        }
        let range: Vec<f32> = px
            .iter()
            .map(|&v| silvr_core::lidar::images::decode_depth(v).unwrap_or(f32::NAN))
            .collect();
        let pose = to_gt.map_or(pose, |a| a.transform_pose(&pose));
        seen.add_view(&model, &pose, &range, 1);
    }
    Ok(Some(seen))
}

/// `finished` of the tasks `todo` of this run are over after `t`: how many, and the time left at that
/// pace.
fn progress(todo: &[usize], finished: usize, t: Instant) {
    if finished == 0 || finished >= todo.len() {
        return;
    }
    let s = t.elapsed().as_secs_f64();
    eprintln!(
        "[reconstruct] {finished}/{} tasks of this run over ({s:.0} s), ETA {:.0} s",
        todo.len(),
        s / finished as f64 * (todo.len() - finished) as f64
    );
}

/// Runs a command, its stdout as text, or an error naming it and its stderr.
fn command(program: &str, args: &[&str]) -> Result<String> {
    let out = std::process::Command::new(program)
        .args(args)
        .output()
        .with_context(|| format!("running {program} (is Slurm installed and on PATH?)"))?;
    if !out.status.success() {
        anyhow::bail!(
            "{program} {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// The Slurm scheduler: one array job of the submaps not done (a job of an earlier run still in the
/// queue is followed instead of submitting again), followed to the end; tasks that did not finish are
/// reported with their state and log.
fn slurm(c: &ReconstructCmd, m: &Manifest, manifest_path: &Path) -> Result<Vec<Failure>> {
    let dir = m.out.join("slurm");
    let logs = m.out.join("logs");
    std::fs::create_dir_all(&dir)?;
    std::fs::create_dir_all(&logs)?;
    let submitted = dir.join("submitted.json");
    let todo: Vec<usize> = (0..m.tasks()).filter(|&k| !m.done(k)).collect();
    m.say_done(&todo);
    if todo.is_empty() {
        return Ok(Vec::new());
    }
    // An earlier run's job still queued or running: follow it.
    let earlier: Option<(String, Vec<usize>)> = std::fs::read(&submitted)
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .and_then(|v| {
            let id = v["job"].as_str()?.to_string();
            let idx = v["indices"]
                .as_array()?
                .iter()
                .filter_map(|x| x.as_u64().map(|x| x as usize))
                .collect();
            Some((id, idx))
        })
        .filter(|(id, _)| {
            command("squeue", &["-h", "-j", id, "-o", "%i"])
                .map(|s| !s.trim().is_empty())
                .unwrap_or(false)
        });
    let (job, indices) = match earlier {
        Some((id, idx)) => {
            eprintln!(
                "[reconstruct] slurm job {id} from an earlier run is still queued: following it"
            );
            (id, idx)
        }
        None => {
            let exe = std::env::current_exe().context("finding the silvr binary")?;
            let list: Vec<String> = todo.iter().map(|k| k.to_string()).collect();
            let mut script = String::from("#!/bin/bash\n");
            script += "#SBATCH --job-name=silvr-reconstruct\n";
            script += &format!("#SBATCH --output={}/slurm-%A_%a.out\n", logs.display());
            if let Some(p) = &c.partition {
                script += &format!("#SBATCH --partition={p}\n");
            }
            if let Some(t) = &c.time {
                script += &format!("#SBATCH --time={t}\n");
            }
            if let Some(g) = c.gpus {
                script += &format!("#SBATCH --gpus-per-task={g}\n");
            }
            for l in &c.sbatch {
                script += &format!("#SBATCH {l}\n");
            }
            script += "# One task per submap; the index is SLURM_ARRAY_TASK_ID.\n";
            script += &format!(
                "exec '{}' reconstruct-task '{}'\n",
                exe.display(),
                manifest_path.display()
            );
            let path = dir.join("job.sh");
            crate::write_atomic(&path, script.as_bytes())?;
            let array = format!("--array={}", list.join(","));
            let out = command(
                "sbatch",
                &["--parsable", &array, path.to_str().context("job path")?],
            )?;
            let id = out.trim().split(';').next().unwrap_or("").to_string();
            if id.is_empty() {
                anyhow::bail!("sbatch printed no job id for {}", path.display());
            }
            crate::write_atomic(
                &submitted,
                serde_json::to_string_pretty(&serde_json::json!({ "job": id, "indices": todo }))?
                    .as_bytes(),
            )?;
            eprintln!(
                "[reconstruct] submitted slurm job {id}: {} of {} submaps ({}), script {}",
                todo.len(),
                m.tasks(),
                list.join(","),
                path.display()
            );
            (id, todo.clone())
        }
    };
    // Follow the job until it leaves the queue.
    let t = Instant::now();
    let mut last = String::new();
    loop {
        let q = command("squeue", &["-h", "-j", &job, "-o", "%T"]).unwrap_or_default();
        if q.trim().is_empty() {
            break;
        }
        let (mut running, mut pending) = (0, 0);
        for s in q.lines() {
            match s.trim() {
                "RUNNING" | "COMPLETING" => running += 1,
                _ => pending += 1,
            }
        }
        let done = indices.iter().filter(|&&k| m.done(k)).count();
        let line = format!(
            "{running} running, {pending} pending, {done}/{} done",
            indices.len()
        );
        if line != last {
            let eta = if done > 0 {
                format!(
                    ", ETA {:.0} s",
                    t.elapsed().as_secs_f64() / done as f64 * (indices.len() - done) as f64
                )
            } else {
                String::new()
            };
            eprintln!(
                "[reconstruct] slurm job {job}: {line} ({:.0} s{eta})",
                t.elapsed().as_secs_f64()
            );
            last = line;
        }
        std::thread::sleep(Duration::from_secs(1));
    }
    let mut failures = Vec::new();
    for &k in &indices {
        if m.done(k) {
            continue;
        }
        let task = format!("{job}_{k}");
        let state = command("scontrol", &["-o", "show", "job", &task])
            .ok()
            .and_then(|s| {
                let f = |key: &str| {
                    s.split_whitespace()
                        .find_map(|w| w.strip_prefix(key))
                        .map(String::from)
                };
                Some(format!(
                    "{} (exit {})",
                    f("JobState=")?,
                    f("ExitCode=").unwrap_or_default()
                ))
            })
            .unwrap_or_else(|| "not finished".into());
        let log = logs.join(format!("slurm-{job}_{k}.out"));
        let error = std::fs::read_to_string(m.error_file(m.name(k)))
            .map(|e| format!("{state}: {}", e.trim()))
            .unwrap_or(state);
        eprintln!(
            "[reconstruct] {} failed as slurm task {task}: {error}; log {}",
            m.name(k),
            log.display()
        );
        failures.push(Failure {
            name: m.name(k).to_string(),
            error,
            log: Some(log),
        });
    }
    Ok(failures)
}
