//! `silvr`: the native companion binary. Same engine as the browser studio, run headless.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use silvr_core::camera::{CameraModel, Distortion};
use silvr_core::eval::{self, GeometryOptions, GeometryReport};
use silvr_core::gpu::{Gpu, GpuOptions};
use silvr_core::lidar::{map, project};
use silvr_core::synthetic::{generate, Preset};
use silvr_core::train::export::ExportDepth;

mod backend;
mod ingest;
mod odometry;
mod poses;
mod reconstruct;
mod renders;
mod serve;
mod submaps;
mod train;
mod uncertainty;

#[derive(Parser)]
#[command(
    name = "silvr",
    version,
    about = "SiLVR Studio: lidar-visual radiance fields with uncertainty, headless"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Print the GPU adapter SiLVR would use, and check the projection kernel against its CPU reference.
    GpuInfo {
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
        /// Refuse software adapters (lavapipe, SwiftShader).
        #[arg(long)]
        require_hardware: bool,
        /// Skip the kernel self-check.
        #[arg(long)]
        no_check: bool,
    },
    /// Generate the built-in synthetic world as a dataset (images, lidar, ground truth).
    Synth {
        /// `ci` (small, seconds), `micro` (the parity tests' 180x135 street), `default` (720x540, 64
        /// beams, 120 keyframes round a block) or `campus` (720x540, 1,027 keyframes over 21,900 m² with
        /// three loops; cut it with --keyframes).
        #[arg(long, default_value = "ci")]
        preset: String,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Output folder (must not exist unless --overwrite).
        #[arg(long)]
        out: PathBuf,
        #[arg(long)]
        overwrite: bool,
        /// Generate only the first N keyframes of the preset's walk (the same poses and world; for
        /// growth curves and quick looks).
        #[arg(long)]
        keyframes: Option<usize>,
        /// Also record the world as a ROS 2 bag (Oxford Spires topics, Hesai clouds) at this path, with
        /// the rig file `silvr ingest` reads it with beside it (NAME.rig.yaml).
        #[arg(long)]
        mcap: Option<PathBuf>,
    },
    /// A ROS 2 bag (MCAP) + rig file → a dataset: deskewed lidar, per-camera depth, normals and sky masks,
    /// poses, transforms.json. `--info` lists a bag's topics.
    Ingest(ingest::IngestCmd),
    /// Another dataset layout → a dataset: `dgp` (a DGP scene: lidar .npz sweeps, pinhole cameras),
    /// `nerfstudio` (a transforms.json with optional depth / normal / sky images), `spires`, `colmap` or
    /// `kitti` (a KITTI odometry sequence or raw drive: stereo colour, velodyne, calibration, ground-truth
    /// poses or OXTS).
    Import(ingest::ImportCmd),
    /// A dataset → another layout (`colmap`: a text model of the cameras and posed images).
    Export(ingest::ExportCmd),
    /// Ingest throughput: MB/s of MCAP reading + decoding, and of the whole bag → dataset (JSON).
    BenchIngest(ingest::BenchIngestCmd),
    /// Score a reconstruction against ground truth: accuracy, completeness, precision/recall/F.
    Eval {
        /// Reconstruction point cloud (PLY).
        #[arg(long)]
        reconstruction: PathBuf,
        /// Dataset (or folder) holding gt/cloud.ply and optionally gt/observed.bin, or a scanner's
        /// point-cloud file: E57 (every scan, each placed by its pose), LAS/LAZ, PLY or PCD.
        #[arg(long)]
        gt: PathBuf,
        /// A point-cloud --gt's pose in the map's frame (T_map_scan): a row-major 4x4 (16 numbers) or a
        /// TUM pose `x y z qx qy qz qw`.
        #[arg(long, allow_hyphen_values = true)]
        gt_transform: Option<String>,
        /// Write the JSON report here (printed to stdout otherwise).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Write the evaluated reconstruction coloured by its distance to the GT.
        #[arg(long)]
        error_ply: Option<PathBuf>,
        /// Keep points in space the GT never observed.
        #[arg(long)]
        keep_unknown: bool,
        /// The poses the reconstruction was made on (transforms.json or its folder), when they are not
        /// the ground truth's frame (refined or lidar-odometry poses): the reconstruction is scored after
        /// the Sim(3) that aligns them to the exact poses in GT's transforms.json.
        #[arg(long)]
        poses: Option<PathBuf>,
    },
    /// Split a dataset into submaps by recursive normalised cuts of its keyframe graph (distance: camera
    /// positions' nearest neighbours, as SiLVR's public code; covis: the structure two keyframes both
    /// see, from the lidar depth until `silvr poses` gives tracks). Each submap is a folder with a transforms.json pointing back at the dataset's images (no
    /// copies) that `silvr train` accepts, plus manifest.json and a top-down plot.
    Submaps {
        /// Dataset folder (or its transforms.json).
        dataset: PathBuf,
        /// Output folder (submap_00/, submap_01/ ..., manifest.json, submaps.png).
        #[arg(long)]
        out: PathBuf,
        /// distance or covis.
        #[arg(long, default_value = "distance")]
        method: String,
        /// Cut until each submap holds at most this many images (default 300 when --count is absent).
        #[arg(long, conflicts_with = "count")]
        max_images: Option<usize>,
        /// Cut into this many submaps instead.
        #[arg(long)]
        count: Option<usize>,
        /// Keyframes within this many metres of a neighbouring submap's are trained by both.
        #[arg(long, default_value_t = 2.0)]
        overlap: f64,
        /// Let the dataset's files lie anywhere under this folder (default: inside the dataset's own
        /// folder only). silvr's submap and poses outputs read their world's images from beside them:
        /// give a folder holding both.
        #[arg(long)]
        data_root: Option<PathBuf>,
    },
    /// Refine a SLAM prior's camera poses by structure from motion bootstrapped from it: SIFT features,
    /// matching gated by the prior's epipolar geometry, tracks, triangulation, bundle adjustment with the
    /// odometry as prior terms and the rig as a constraint, Sim(3) back to the prior's metric frame. Writes
    /// a folder that `silvr train` accepts (its transforms.json points back at the dataset's images), a
    /// COLMAP text model (colmap/) and report.json (registered images, reprojection RMSE, time per stage)
    Poses {
        /// Dataset folder (its transforms.json) or the transforms file holding the prior
        /// (a synthetic world's transforms_prior.json).
        dataset: PathBuf,
        /// Output folder (must not exist).
        #[arg(long)]
        out: PathBuf,
        /// Exact poses to score the prior and the refined poses against (ATE, rotation, RPE).
        #[arg(long)]
        gt: Option<PathBuf>,
        /// Refine each camera's place on the rig too (default: the calibration is a constraint).
        #[arg(long)]
        refine_extrinsics: bool,
        /// No loop closure: every candidate pair from the prior is matched under its gate at once (the
        /// stage before loop closure; on a walk under 30 m there is nothing to close anyway).
        #[arg(long)]
        no_loops: bool,
        /// Strongest SIFT features kept per image.
        #[arg(long, default_value_t = 4096)]
        max_features: usize,
        /// SIFT's difference-of-Gaussians peak threshold (images in [0, 1]); default 0.0025, lower
        /// than COLMAP's 0.0067 (tuned for photographs) so small or low-contrast images keep enough.
        #[arg(long)]
        peak_threshold: Option<f32>,
        /// Find features on images downscaled by this integer factor (block means). Default: the
        /// smallest factor that brings the largest image within about a megapixel, the size the
        /// stage's thresholds are tuned at (2 for 1080p). Poses and the COLMAP model stay at full
        /// resolution.
        #[arg(long)]
        downscale: Option<u32>,
        /// No progress lines.
        #[arg(long)]
        quiet: bool,
    },
    /// Perturb the poses of a transforms.json (noise per image, optional drift along the listed order),
    /// to test pose refinement on a capture whose poses are good: writes OUT/transforms.json pointing
    /// back at the dataset's files.
    PerturbPoses {
        /// Dataset folder (its transforms.json) or a transforms.json.
        dataset: PathBuf,
        /// Output folder (must not exist).
        #[arg(long)]
        out: PathBuf,
        /// Translation noise per image (scene units, 1 σ per axis).
        #[arg(long, default_value_t = 0.02)]
        noise: f64,
        /// Rotation noise per image (degrees, 1 σ per axis).
        #[arg(long, default_value_t = 0.2)]
        noise_deg: f64,
        /// Drift along the frames' order: scale error and random walk, as a fraction of each step.
        #[arg(long, default_value_t = 0.0)]
        drift: f64,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// Candidate image pairs to match, from the poses of a transforms.json (a SLAM prior: centres near,
    /// optical axes within an angle, view frusta overlapping): one `image1 image2` line per pair, the
    /// match list `colmap matches_importer --match_type pairs` reads.
    Pairs {
        /// Dataset folder (its transforms.json) or a transforms.json (transforms_prior.json, say).
        dataset: PathBuf,
        /// The pair list to write.
        #[arg(long)]
        out: PathBuf,
        /// Largest distance between camera centres (m).
        #[arg(long, default_value_t = 20.0)]
        max_distance: f64,
        /// Largest angle between optical axes (degrees).
        #[arg(long, default_value_t = 100.0)]
        max_angle: f64,
        /// Smallest frustum overlap (fraction of samples seen by the other image, both ways).
        #[arg(long, default_value_t = 0.1)]
        min_overlap: f64,
    },
    /// Pose accuracy of a trajectory against the exact one: ATE (camera centres) and rotation error after a
    /// robust Sim(3) alignment, and RPE of consecutive frames; both given as transforms.json files (a
    /// synthetic dataset's transforms_prior.json against its transforms.json, say), frames matched by image.
    EvalPoses {
        /// The estimated poses: transforms.json, a dataset folder holding it, or a COLMAP text model
        /// folder (cameras.txt, images.txt), its images matched to the exact frames by NAME.
        #[arg(long)]
        est: PathBuf,
        /// The exact poses (transforms.json, or a dataset folder holding it).
        #[arg(long)]
        gt: PathBuf,
        /// Write the JSON report here (printed to stdout otherwise).
        #[arg(long)]
        out: Option<PathBuf>,
        /// The alignment before scoring: `sim3` (rotation, translation and scale: visual SfM, whose
        /// scale is arbitrary) or `se3` (no scale: lidar odometry, which claims metres). Default: sim3
        /// for transforms.json and COLMAP, se3 for two trajectory files.
        #[arg(long)]
        align: Option<String>,
    },
    /// Measure the kernels: points/s of lidar projection (WGSL vs CPU reference) and of deskewing.
    Bench {
        /// Points per projection call.
        #[arg(long, default_value_t = 200_000)]
        points: usize,
        /// Timed repetitions (after one warm-up).
        #[arg(long, default_value_t = 5)]
        reps: usize,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// Train a radiance field on a dataset (nerfstudio transforms.json, with lidar images when present).
    Train {
        /// Dataset folder (holding transforms.json) or the JSON file.
        dataset: PathBuf,
        /// silvr (colour + lidar depth + normals + sky), vision (colour only), depth-only (no normals).
        #[arg(long, default_value = "silvr")]
        mode: silvr_core::train::Mode,
        #[arg(long, default_value_t = 2000)]
        steps: u32,
        /// Rays per batch.
        #[arg(long, default_value_t = 4096)]
        rays: usize,
        /// Model sizes: nerfacto, medium (2^18 table, fewer samples) or small.
        #[arg(long, default_value = "nerfacto")]
        model: String,
        /// Output folder: checkpoint, train.json, renders/, points.ply.
        #[arg(long, default_value = "silvr-train")]
        out: PathBuf,
        /// Continue from a checkpoint written by an earlier run on the same dataset.
        #[arg(long)]
        resume: Option<PathBuf>,
        /// Write a checkpoint every this many steps (0: only at the end).
        #[arg(long, default_value_t = 500)]
        checkpoint_every: u32,
        /// auto, wgpu or cpu.
        #[arg(long, default_value = "auto")]
        backend: String,
        /// Integer image downscale.
        #[arg(long, default_value_t = 1)]
        downscale: u32,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Training rays rendered for the exported point cloud (0: none).
        #[arg(long, default_value_t = 200_000)]
        export_rays: usize,
        /// Held-out views rendered and scored after training (default: all; 0 for none).
        #[arg(long)]
        render_views: Option<usize>,
        /// Depth that places an exported point on its ray: expected (SiLVR's exporter) or median
        /// (nerfacto's depth, which never floats between two surfaces at an object's silhouette).
        #[arg(long, default_value = "expected")]
        export_depth: ExportDepth,
        /// DS-NeRF σ schedule, standard deviation in metres: start, end (decay ×0.99985 per step).
        #[arg(long, num_args = 2, value_names = ["START", "END"])]
        depth_sigma: Option<Vec<f32>>,
        /// Run the uncertainty pass after training with this many batches (0: none; `silvr uncertainty`
        /// runs it later): annotates points.ply, writes points_filtered.ply and uncertainty.bin.
        #[arg(long, default_value_t = 0)]
        uncertainty_batches: usize,
        /// Rays per batch of that pass.
        #[arg(long, default_value_t = 4096)]
        uncertainty_rays: usize,
        /// Let the dataset's files lie anywhere under this folder (default: inside the dataset's own
        /// folder only). silvr's submap and poses outputs read their world's images from beside them:
        /// give a folder holding both.
        #[arg(long)]
        data_root: Option<PathBuf>,
    },
    /// Training throughput and time to quality: field samples/s (forward + backward), rays/s per step,
    /// seconds to a target training PSNR. JSON on stdout.
    BenchTrain {
        /// Dataset folder (e.g. from `silvr synth`).
        dataset: PathBuf,
        #[arg(long, default_value = "silvr")]
        mode: silvr_core::train::Mode,
        /// auto, wgpu or cpu.
        #[arg(long, default_value = "auto")]
        backend: String,
        #[arg(long, default_value = "nerfacto")]
        model: String,
        #[arg(long, default_value_t = 4096)]
        rays: usize,
        /// Most steps to run while waiting for the target PSNR.
        #[arg(long, default_value_t = 2000)]
        steps: u32,
        /// Training-batch PSNR (mean of the last 20 steps) that counts as reached.
        #[arg(long, default_value_t = 25.0)]
        target_psnr: f64,
        /// Stop after this many seconds even if the target is not reached.
        #[arg(long, default_value_t = 300.0)]
        max_seconds: f64,
        /// Time every GPU pass of the WGSL step (timestamp queries, or timed submits where the adapter
        /// has none) and print time and bound bytes per pass per step; implies --backend wgpu.
        #[arg(long)]
        profile: bool,
        /// Steps timed by --profile (after the warm-up).
        #[arg(long, default_value_t = 10)]
        profile_steps: u32,
        /// Also time inference (a held-out view, no normals) of this trained field (a `silvr train`
        /// checkpoint on the same dataset) beside the short run's.
        #[arg(long)]
        render_checkpoint: Option<PathBuf>,
    },
    /// Proposal networks vs an Instant-NGP occupancy grid for placing the final samples: the same training
    /// on the CPU reference with each; wall time, PSNR curve, held-out PSNR, geometry when GT is present.
    BenchSampler(train::SamplerBenchArgs),
    /// Epistemic uncertainty of a trained field (perturbation field + Laplace, colour and lidar depth):
    /// writes uncertainty.bin, the read-out as fields of points.ply, points_filtered.ply and an
    /// uncertainty image; with --gt also sparsification curves, AUSE and plots.
    Uncertainty(UncertaintyCmd),
    /// The main job: generate the synthetic world, build the reconstructions, evaluate, write report.json.
    Demo {
        /// `ci` or `default`; `ci` when the only GPU adapter is a software one.
        #[arg(long)]
        preset: Option<String>,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        #[arg(long, default_value = "silvr-demo")]
        out: PathBuf,
        /// Training steps of each radiance field (default: 300 for `ci`, 5000 for `default`).
        #[arg(long)]
        steps: Option<u32>,
        /// Model size, nerfacto, medium or small (default: small for `ci`, nerfacto for `default`).
        #[arg(long)]
        model: Option<String>,
        /// Rays per training batch (default: 1024 for `ci`, 4096 for `default`).
        #[arg(long)]
        rays: Option<usize>,
        /// Train, render and score the held-out views at 1/N of the image resolution.
        #[arg(long, default_value_t = 1)]
        downscale: u32,
        /// Keep OUT/dataset when an earlier run generated it from the same preset and seed (the
        /// `default` world takes minutes to generate) instead of generating it again.
        #[arg(long)]
        reuse_dataset: bool,
        /// Batches of training rays of the uncertainty pass (default: 8 × 1024 rays for `ci`, 1000 × 4096
        /// for `default`).
        #[arg(long)]
        uncertainty_batches: Option<usize>,
        /// Engine of every stage (training, renders, export, uncertainty): `wgpu` the WGSL engine on any
        /// adapter (lavapipe included), `cpu` the rayon reference, `auto` WGSL on a hardware GPU and the CPU
        /// where the only adapter is a software one.
        #[arg(long, default_value = "auto")]
        backend: String,
        /// Poses the fields train on: `refined` (the poses stage's output, like a user's data: the
        /// default), `prior` (the SLAM-like prior as it is) or `exact` (the generator's). Geometry is
        /// scored after the Sim(3) that aligns the trained-on poses with the exact ones.
        #[arg(long, default_value = "refined")]
        poses: String,
    },
    /// Serve the built studio and a folder of reconstructions over HTTP, and print the link that opens
    /// the folder's PLY files in the studio.
    Serve(serve::ServeCmd),
    /// The whole map: submaps (covis or distance), then per submap train → uncertainty → filtered export,
    /// the merge (the more certain submap keeps each overlap voxel) and, with ground truth, its evaluation
    /// filtered and unfiltered. Rerun on the same --out to finish a killed job (finished submaps are kept).
    Reconstruct(reconstruct::ReconstructCmd),
    /// A trajectory from the lidar alone (KISS-ICP-class odometry) for a recording without a SLAM
    /// trajectory: a KITTI sequence folder or a ROS 2 bag → TUM, scored where ground truth exists.
    Odometry(odometry::OdometryCmd),
    /// One submap of a reconstruction (train → uncertainty → filtered export) from its
    /// OUT/reconstruct.json: what each Slurm array task runs (the index from SLURM_ARRAY_TASK_ID), and what
    /// any other scheduler can run per index before `silvr reconstruct` merges.
    ReconstructTask(reconstruct::TaskCmd),
    /// Pack what training reads from a dataset (transforms.json, images, lidar depth, normals, sky masks,
    /// calib, manifest) into one tar archive a user can drop into the studio, or inspect with `tar tf`.
    Pack {
        /// Dataset folder (or its transforms.json).
        dataset: PathBuf,
        /// The archive to write (`.tar`).
        #[arg(long)]
        out: PathBuf,
        /// Store every image downscaled by this integer factor, the intrinsics rewritten to match (the
        /// archive trains as the folder does with `--downscale` at this factor; a smaller download).
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=16))]
        downscale: u32,
    },
}

#[derive(clap::Args)]
struct UncertaintyCmd {
    /// Folder of a `silvr train` run (checkpoint.ckpt, train.json, points.ply).
    model: PathBuf,
    /// Dataset the model was trained on (default: the one train.json names).
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// Let the dataset's files lie anywhere under this folder (default: inside its own folder only):
    /// for a model of a submap or poses output, a folder holding it and its world.
    #[arg(long)]
    data_root: Option<PathBuf>,
    /// Ground truth (a dataset with gt/cloud.ply) for sparsification curves, AUSE and the filtered
    /// cloud's scores.
    #[arg(long)]
    gt: Option<PathBuf>,
    /// auto, wgpu or cpu.
    #[arg(long, default_value = "auto")]
    backend: String,
    /// Perturbation-grid cells per axis (0: from the ray budget, 256 for the defaults).
    #[arg(long, default_value_t = 0)]
    cells: u32,
    /// Batches of training rays.
    #[arg(long, default_value_t = 1000)]
    batches: usize,
    #[arg(long, default_value_t = 4096)]
    rays: usize,
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Time every GPU pass of the WGSL uncertainty pass and print time and bound bytes per pass.
    #[arg(long)]
    profile: bool,
    /// `points_filtered.ply` keeps the points whose σ (metres) is at most this, instead of the default
    /// rule (Tukey's fence on log σ).
    #[arg(long, value_name = "METRES")]
    max_sigma: Option<f64>,
}

fn uncertainty_cmd(c: UncertaintyCmd) -> Result<()> {
    let config = silvr_core::uncertainty::UncertaintyConfig {
        cells: c.cells,
        batches: c.batches,
        rays_per_batch: c.rays,
        seed: c.seed,
        max_sigma_m: c.max_sigma,
        ..Default::default()
    };
    config.validate()?;
    // The GT folder is only the reference: the field's own dataset places the per-label read-out.
    let trained_on = match &c.dataset {
        Some(d) => d.clone(),
        None => uncertainty::dataset_of(&c.model)?,
    };
    let summary = uncertainty::run(&uncertainty::UncertaintyArgs {
        model_dir: c.model.clone(),
        dataset: c.dataset,
        data_root: c.data_root.clone(),
        backend: c.backend,
        config,
        quiet: false,
        profile: c.profile,
    })?;
    if let Some(gt) = c.gt {
        let v = uncertainty::evaluate(
            &c.model,
            &gt,
            &trained_on,
            c.data_root.as_deref(),
            &GeometryOptions::default(),
            &summary,
        )?;
        println!("{}", serde_json::to_string_pretty(&v)?);
    }
    Ok(())
}

fn main() {
    restore_sigpipe();
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or("warn")).init();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::GpuInfo {
            json,
            require_hardware,
            no_check,
        } => gpu_info(json, require_hardware, !no_check),
        Command::Synth {
            preset,
            seed,
            out,
            overwrite,
            keyframes,
            mcap,
        } => match mcap {
            None => synth(&preset, seed, &out, overwrite, keyframes).map(|_| ()),
            Some(bag) => synth_bag(&preset, seed, &out, overwrite, &bag),
        },
        Command::Ingest(c) => ingest::run(c, open_gpu),
        Command::BenchIngest(c) => ingest::bench(c, open_gpu),
        Command::Import(c) => ingest::import(c, open_gpu),
        Command::Odometry(c) => odometry::run(c),
        Command::Export(c) => ingest::export(c),
        Command::Poses {
            dataset,
            out,
            gt,
            refine_extrinsics,
            no_loops,
            max_features,
            peak_threshold,
            downscale,
            quiet,
        } => poses::run(&poses::PosesArgs {
            dataset,
            out,
            gt,
            refine_extrinsics,
            no_loops,
            max_features,
            peak_threshold,
            downscale,
            quiet,
        })
        .map(|_| ()),
        Command::PerturbPoses {
            dataset,
            out,
            noise,
            noise_deg,
            drift,
            seed,
        } => poses::perturb(&dataset, &out, noise, noise_deg, drift, seed),
        Command::EvalPoses {
            est,
            gt,
            out,
            align,
        } => eval_poses(&est, &gt, out.as_deref(), align.as_deref()),
        Command::Pairs {
            dataset,
            out,
            max_distance,
            max_angle,
            min_overlap,
        } => pairs(
            &dataset,
            &out,
            silvr_core::sfm::pairs::PairOptions {
                max_distance_m: max_distance,
                max_angle_deg: max_angle,
                min_overlap,
                ..Default::default()
            },
        ),
        Command::Submaps {
            dataset,
            out,
            method,
            max_images,
            count,
            overlap,
            data_root,
        } => submaps::run(
            &dataset,
            &out,
            &method,
            max_images,
            count,
            overlap,
            data_root.as_deref(),
        )
        .map(|_| ()),
        Command::Eval {
            reconstruction,
            gt,
            gt_transform,
            out,
            error_ply,
            keep_unknown,
            poses,
        } => eval_cmd(
            &reconstruction,
            &gt,
            gt_transform.as_deref(),
            out.as_deref(),
            error_ply.as_deref(),
            keep_unknown,
            poses.as_deref(),
        ),
        Command::Train {
            dataset,
            mode,
            steps,
            rays,
            model,
            out,
            resume,
            checkpoint_every,
            backend,
            downscale,
            seed,
            export_rays,
            render_views,
            export_depth,
            depth_sigma,
            uncertainty_batches,
            uncertainty_rays,
            data_root,
        } => train::run(&train::TrainArgs {
            depth_sigma: depth_sigma.map(|v| (v[0], v[1])),
            dataset,
            data_root,
            mode,
            steps,
            rays,
            model,
            out,
            resume,
            checkpoint_every,
            backend,
            downscale,
            seed,
            export_rays,
            render_views,
            export_depth,
            quiet: false,
            view_normals: true,
            uncertainty: (uncertainty_batches > 0).then(|| {
                silvr_core::uncertainty::UncertaintyConfig {
                    batches: uncertainty_batches,
                    rays_per_batch: uncertainty_rays,
                    ..Default::default()
                }
            }),
        })
        .map(|_| ()),
        Command::Uncertainty(c) => uncertainty_cmd(c),
        Command::Demo {
            preset,
            seed,
            out,
            steps,
            model,
            rays,
            downscale,
            reuse_dataset,
            uncertainty_batches,
            backend,
            poses,
        } => demo(
            preset.as_deref(),
            seed,
            &out,
            &DemoTraining {
                steps,
                model,
                rays,
                downscale,
                uncertainty_batches,
                backend,
                poses,
            },
            reuse_dataset,
        ),
        Command::BenchTrain {
            dataset,
            mode,
            backend,
            model,
            rays,
            steps,
            target_psnr,
            max_seconds,
            profile,
            profile_steps,
            render_checkpoint,
        } => train::bench(&train::BenchArgs {
            dataset,
            mode,
            backend,
            model,
            rays,
            steps,
            target_psnr,
            max_seconds,
            profile: profile.then_some(profile_steps),
            render_checkpoint,
        }),
        Command::BenchSampler(a) => train::bench_sampler(&a),
        Command::Bench { points, reps, json } => bench(points, reps, json),
        Command::Serve(c) => serve::run(c),
        Command::Reconstruct(c) => reconstruct::run(&c),
        Command::ReconstructTask(c) => reconstruct::task(&c),
        Command::Pack {
            dataset,
            out,
            downscale,
        } => pack(&dataset, &out, downscale),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

/// A synthetic world's ground truth of one image: `<world>/images/<rest>` → `<world>/gt/<kind>/<rest>`,
/// wherever the transforms file naming the image lives (a poses or submap output names it
/// `../<world>/images/...`). `None` when the path has no `images` folder or the file is not there.
pub(crate) fn synthetic_gt_file(image: &Path, kind: &str) -> Option<PathBuf> {
    let parts: Vec<_> = image.components().collect();
    let k = parts.iter().rposition(|c| c.as_os_str() == "images")?;
    let world: PathBuf = parts[..k].iter().collect();
    let rest: PathBuf = parts[k + 1..].iter().collect();
    let file = world.join("gt").join(kind).join(rest);
    file.is_file().then_some(file)
}

/// The folder a dataset's files may be read from when it is silvr's own output beside its world: the
/// nearest folder holding both `dataset` (its transforms file's folder) and `out`. Submaps and the poses
/// stage name the world's images `../../dataset/images/…`, which a folder confined to itself refuses
/// (`silvr_core::source::Dir`).
pub(crate) fn data_root(dataset: &Path, out: &Path) -> Result<PathBuf> {
    let json = transforms_file(dataset);
    let folder = json
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let real = |p: &Path| {
        p.canonicalize()
            .with_context(|| format!("resolving {}", p.display()))
    };
    let (a, b) = (real(folder)?, real(out)?);
    Ok(a.ancestors()
        .find(|anc| b.starts_with(anc))
        .unwrap_or(Path::new("/"))
        .to_path_buf())
}

/// The transforms.json a command named (a dataset folder means the one inside it). Plain files only:
/// these commands write paths relative to it or read poses, so the archives `source::open` also takes
/// are not for them.
pub(crate) fn transforms_file(p: &Path) -> PathBuf {
    if p.is_dir() {
        p.join("transforms.json")
    } else {
        p.to_path_buf()
    }
}

/// `silvr pairs`: candidate pairs from a transforms.json's poses, as a COLMAP match list.
fn pairs(dataset: &Path, out: &Path, opts: silvr_core::sfm::pairs::PairOptions) -> Result<()> {
    for (what, v) in [
        ("--max-distance", opts.max_distance_m),
        ("--max-angle", opts.max_angle_deg),
        ("--min-overlap", opts.min_overlap),
    ] {
        if !(v.is_finite() && v >= 0.0) {
            anyhow::bail!("{what} {v}: expected a finite number ≥ 0");
        }
    }
    let json = transforms_file(dataset);
    let (frames, _, _) = silvr_core::dataset::read_frames(&json)?;
    let cams = frames
        .iter()
        .map(|f| f.camera(&json))
        .collect::<Result<Vec<_>, _>>()?;
    let t = Instant::now();
    let found = silvr_core::sfm::pairs::candidate_pairs(&cams, &opts);
    let mut text = String::new();
    for p in &found {
        text.push_str(&format!(
            "{} {}\n",
            frames[p.i].file_path, frames[p.j].file_path
        ));
    }
    write_atomic(out, text.as_bytes())?;
    let n = frames.len();
    eprintln!(
        "{} candidate pairs of {} possible ({:.1} %) among {n} images in {:.2} s; wrote {}",
        found.len(),
        n * n.saturating_sub(1) / 2,
        100.0 * found.len() as f64 / (n * n.saturating_sub(1) / 2).max(1) as f64,
        t.elapsed().as_secs_f64(),
        out.display()
    );
    Ok(())
}

/// `silvr eval-poses`: ATE / rotation / RPE of a transforms.json, or of a COLMAP model folder, against
/// an exact transforms.json.
fn eval_poses(est: &Path, gt: &Path, out: Option<&Path>, align: Option<&str>) -> Result<()> {
    use silvr_core::eval::poses;
    let trajectory_file = |p: &Path| p.is_file() && p.extension().is_none_or(|e| e != "json");
    if trajectory_file(est) && trajectory_file(gt) {
        // Two trajectories (TUM, KITTI, EuRoC, Spires): matched by time.
        let read = silvr_core::ingest::poses::read_trajectory;
        let (e, g) = poses::match_by_time(&read(est)?, &read(gt)?, 5e-3);
        let errors = match align.unwrap_or("se3") {
            "se3" => poses::pose_errors_se3(&e, &g)?,
            "sim3" => poses::pose_errors(&e, &g)?,
            o => anyhow::bail!("--align {o}: expected se3 or sim3"),
        };
        eprintln!("{}", pose_line(&errors));
        let json = serde_json::to_string_pretty(&errors)?;
        match out {
            Some(p) => write_atomic(p, json.as_bytes())?,
            None => println!("{json}"),
        }
        return Ok(());
    }
    if align.is_some_and(|a| a != "sim3") {
        anyhow::bail!("--align se3 applies to two trajectory files (TUM, KITTI); camera sets are aligned by Sim(3)");
    }
    let colmap = est.is_dir()
        && !est.join("transforms.json").exists()
        && (est.join("images.txt").exists() || est.join("images.bin").exists());
    let e = if colmap {
        poses::compare_colmap(est, &transforms_file(gt))?
    } else {
        poses::compare_transforms(&transforms_file(est), &transforms_file(gt))?
    };
    eprintln!("{}", pose_line(&e));
    let json = serde_json::to_string_pretty(&e)?;
    match out {
        Some(p) => write_atomic(p, json.as_bytes())?,
        None => println!("{json}"),
    }
    Ok(())
}

/// One line of pose errors for the terminal.
fn pose_line(e: &silvr_core::eval::poses::PoseErrors) -> String {
    format!(
        "{}/{} frames registered ({} in the alignment, scale {:.4}): ATE {:.3} m RMSE, {:.3} m median, {:.3} m max; rotation {:.2}° RMSE; RPE {:.3} m, {:.2}° per step",
        e.registered,
        e.frames,
        e.inliers,
        e.scale,
        e.ate_rmse_m,
        e.ate_median_m,
        e.ate_max_m,
        e.rot_rmse_deg,
        e.rpe_trans_rmse_m,
        e.rpe_rot_rmse_deg
    )
}

/// `silvr pack`: one archive of a dataset's training inputs (written under a temporary name, then renamed).
fn pack(dataset: &Path, out: &Path, downscale: u32) -> Result<()> {
    use silvr_core::source;
    let (src, json) = source::open(dataset)?;
    let (files, skipped) = silvr_core::train::data::pack(src.as_ref(), &json, downscale)?;
    for s in &skipped {
        eprintln!("warning: left out {s}");
    }
    let tar = files.to_tar();
    silvr_core::dataset::write_atomic(out, &tar)
        .with_context(|| format!("writing {}", out.display()))?;
    eprintln!(
        "packed {} files ({:.1} MB{}) from {} into {}",
        files.len(),
        tar.len() as f64 / 1e6,
        if downscale > 1 {
            format!(", images downscaled by {downscale}")
        } else {
            String::new()
        },
        dataset.display(),
        out.display()
    );
    Ok(())
}

/// The camera the self-check projects into: the Spires front fisheye at a quarter of its resolution.
fn check_camera() -> CameraModel {
    CameraModel {
        width: 360,
        height: 270,
        fx: 174.54,
        fy: 174.63,
        cx: 177.82,
        cy: 139.77,
        distortion: Distortion::Fisheye {
            k1: -0.041142,
            k2: -0.002422,
            k3: 0.003400,
            k4: -0.001852,
        },
    }
}

fn gpu_info(json: bool, require_hardware: bool, check: bool) -> Result<()> {
    let gpu = pollster::block_on(Gpu::new(GpuOptions {
        require_hardware,
        ..Default::default()
    }))
    .context("no usable GPU")?;
    let check = if check {
        Some(
            pollster::block_on(project::self_check(&gpu, &check_camera(), 7, 20_000))
                .context("projection kernel self-check")?,
        )
    } else {
        None
    };
    if json {
        let v = serde_json::json!({ "adapter": gpu.report(), "projection_check": check });
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("adapter: {}", gpu.report());
        if let Some(c) = &check {
            println!(
                "projection kernel vs CPU reference: {} ({} points, {} of {} pixels filled, {} winner mismatches, max uv error {:.2e} px)",
                if c.passed() { "agree" } else { "DISAGREE" },
                c.points,
                c.filled_pixels,
                c.pixels,
                c.winner_mismatches,
                c.max_uv_error_px
            );
        }
    }
    if let Some(c) = check {
        anyhow::ensure!(
            c.passed(),
            "the GPU projection kernel disagrees with its CPU reference: {c:?}"
        );
    }
    Ok(())
}

fn open_gpu() -> Result<Gpu> {
    let gpu = pollster::block_on(Gpu::new(GpuOptions::default())).context("no usable GPU")?;
    eprintln!("[gpu] {}", gpu.report());
    Ok(gpu)
}

fn preset_by_name(name: &str, seed: u64) -> Result<Preset> {
    Preset::by_name(name, seed)
        .with_context(|| format!("unknown preset {name:?} (use {})", Preset::NAMES))
}

fn synth_with(
    gpu: &Gpu,
    preset: &Preset,
    out: &Path,
    overwrite: bool,
) -> Result<generate::SynthSummary> {
    let start = Instant::now();
    let mut last = usize::MAX;
    let summary = pollster::block_on(generate::generate(preset, gpu, out, overwrite, &mut |p| {
        if p.done != last {
            last = p.done;
            let t = start.elapsed().as_secs_f64();
            // The keyframes take nearly all the time; the ETA is theirs.
            let eta = if p.stage == "keyframes" && p.done > 0 {
                format!(
                    ", ETA {:.0} s",
                    t / p.done as f64 * (p.total - p.done) as f64
                )
            } else {
                String::new()
            };
            eprintln!("[synth] {} {}/{} ({t:.1} s{eta})", p.stage, p.done, p.total);
        }
    }))
    .with_context(|| {
        format!(
            "generating the {} world into {}",
            preset.name,
            out.display()
        )
    })?;
    eprintln!(
        "[synth] wrote {} ({} keyframes, {} images, {} lidar points, {} GT points, {} files) in {:.1} s",
        summary.path.display(),
        summary.keyframes,
        summary.images,
        summary.lidar_points,
        summary.gt_points,
        summary.files,
        start.elapsed().as_secs_f64()
    );
    Ok(summary)
}

/// The rig file written beside a bag: `scene.mcap` → `scene.rig.yaml`.
fn rig_file_for(bag: &Path) -> PathBuf {
    bag.with_extension("rig.yaml")
}

fn synth_bag(preset: &str, seed: u64, out: &Path, overwrite: bool, bag: &Path) -> Result<()> {
    use silvr_core::synthetic::bag;
    let preset = preset_by_name(preset, seed)?;
    if bag.exists() && !overwrite {
        anyhow::bail!("{}: already exists (use --overwrite)", bag.display());
    }
    let gpu = open_gpu()?;
    let mut recorder = bag::BagRecorder::create(bag)?;
    let start = Instant::now();
    let summary = pollster::block_on(generate::generate_recording(
        &preset,
        &gpu,
        out,
        overwrite,
        &mut |p| {
            if p.done % 5 == 0 || p.done == p.total {
                eprintln!("[synth] {} {}/{}", p.stage, p.done, p.total);
            }
        },
        Some(&mut recorder),
    ))
    .with_context(|| {
        format!(
            "generating the {} world into {}",
            preset.name,
            out.display()
        )
    })?;
    let rig = rig_file_for(bag);
    silvr_core::dataset::write_atomic(&rig, bag::rig_config(&preset).to_yaml().as_bytes())?;
    eprintln!(
        "[synth] wrote {} ({} keyframes), the bag {} ({} bytes) and its rig file {} in {:.1} s",
        summary.path.display(),
        summary.keyframes,
        bag.display(),
        std::fs::metadata(bag).map(|m| m.len()).unwrap_or(0),
        rig.display(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

fn synth(
    preset: &str,
    seed: u64,
    out: &Path,
    overwrite: bool,
    keyframes: Option<usize>,
) -> Result<generate::SynthSummary> {
    let mut preset = preset_by_name(preset, seed)?;
    if let Some(n) = keyframes {
        preset = preset
            .prefix(n)
            .map_err(|e| anyhow::anyhow!("--keyframes {n}: {e}"))?;
    }
    let gpu = open_gpu()?;
    synth_with(&gpu, &preset, out, overwrite)
}

fn eval_cmd(
    rec: &Path,
    gt: &Path,
    gt_transform: Option<&str>,
    out: Option<&Path>,
    error_ply: Option<&Path>,
    keep_unknown: bool,
    poses: Option<&Path>,
) -> Result<()> {
    let alignment = match poses {
        Some(p) => {
            let e = silvr_core::eval::poses::compare_transforms(
                &transforms_file(p),
                &transforms_file(gt),
            )?;
            eprintln!("poses: {}", pose_line(&e));
            Some(e.alignment.to_mat4())
        }
        None => None,
    };
    let options = GeometryOptions {
        filter_unknown: !keep_unknown,
        reconstruction_to_gt: alignment,
        ..GeometryOptions::default()
    };
    let ev = if gt.is_file() {
        // A scanner's point cloud as the reference.
        let transform = gt_transform
            .map(silvr_core::eval::scan::parse_transform)
            .transpose()
            .map_err(|e| anyhow::anyhow!("--gt-transform: {e}"))?;
        let (truth, notes) = eval::GroundTruth::from_scan(gt, transform, &options)?;
        let mut ev = truth.evaluate(&silvr_core::pointcloud::read_ply(rec)?, &options)?;
        ev.report.notes.extend(notes);
        ev
    } else {
        anyhow::ensure!(
            gt_transform.is_none(),
            "--gt-transform applies to a point-cloud --gt file, not a dataset folder"
        );
        eval::evaluate_files_full(rec, gt, &options)?
    };
    if let Some(p) = error_ply {
        write_error_cloud(&ev, p)?;
    }
    let json = ev.report.to_json_pretty();
    match out {
        Some(p) => {
            write_atomic(p, json.as_bytes())?;
            eprintln!("{}", ev.report.summary());
        }
        None => println!("{json}"),
    }
    Ok(())
}

fn write_error_cloud(ev: &eval::GeometryEvaluation, path: &Path) -> Result<()> {
    let cloud = eval::error_colored_cloud(&ev.reconstruction, &ev.rec_to_gt, 0.2);
    silvr_core::pointcloud::write_ply(path, &cloud)
        .with_context(|| format!("writing {}", path.display()))
}

pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    silvr_core::dataset::write_atomic(path, bytes).map_err(Into::into)
}

/// Rust ignores SIGPIPE, so `println!` into a closed pipe (`silvr ingest --info | head`) panics; a
/// command-line tool should end quietly like any Unix filter instead.
fn restore_sigpipe() {
    #[cfg(unix)]
    // SAFETY: called first thing in main, before any thread exists; SIG_DFL is a valid disposition.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// `silvr demo`'s training overrides (each `None` takes the preset's value from [`demo_training`]).
struct DemoTraining {
    steps: Option<u32>,
    model: Option<String>,
    rays: Option<usize>,
    downscale: u32,
    uncertainty_batches: Option<usize>,
    backend: String,
    /// `refined`, `prior` or `exact`.
    poses: String,
}

/// Whether `dataset` was generated from exactly `preset` (its manifest records the preset).
fn generated_from(dataset: &Path, preset: &Preset) -> bool {
    let Ok(bytes) = std::fs::read(dataset.join("manifest.json")) else {
        return false;
    };
    let Ok(manifest) = serde_json::from_slice::<serde_json::Value>(&bytes) else {
        return false;
    };
    // Through text, as the manifest was written: serde_json's default float parser is not exact to the
    // last bit, so a parsed manifest never equals `to_value(preset)` on the default rig's extrinsics.
    serde_json::to_string(preset)
        .ok()
        .and_then(|s| serde_json::from_str::<serde_json::Value>(&s).ok())
        .is_some_and(|p| manifest["preset"] == p)
}

fn demo(
    preset: Option<&str>,
    seed: u64,
    out: &Path,
    overrides: &DemoTraining,
    reuse_dataset: bool,
) -> Result<()> {
    if !["refined", "prior", "exact"].contains(&overrides.poses.as_str()) {
        anyhow::bail!(
            "--poses {}: expected refined, prior or exact",
            overrides.poses
        );
    }
    let total = Instant::now();
    let gpu = open_gpu()?;
    let name = preset.unwrap_or(if gpu.report().software {
        "ci"
    } else {
        "default"
    });
    let preset = preset_by_name(name, seed)?;
    eprintln!(
        "[demo] preset {name}, seed {seed}, output {}",
        out.display()
    );
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let dataset = out.join("dataset");
    let t = Instant::now();
    if reuse_dataset && generated_from(&dataset, &preset) {
        eprintln!(
            "[demo] reusing {} (same preset and seed)",
            dataset.display()
        );
    } else {
        synth_with(&gpu, &preset, &dataset, true)?;
    }
    let synth_s = t.elapsed().as_secs_f64();

    // The poses stage: the SLAM-like prior refined by structure from motion, both scored against the
    // exact poses (training still uses the exact ones; see the report's `trained_on`).
    let t = Instant::now();
    let prior_file = dataset.join("transforms_prior.json");
    let mut poses_block = if prior_file.is_file() {
        let dir = out.join("poses");
        if dir.exists() {
            std::fs::remove_dir_all(&dir).with_context(|| format!("clearing {}", dir.display()))?;
        }
        let r = poses::run(&poses::PosesArgs {
            dataset: prior_file,
            out: dir,
            gt: Some(dataset.join("transforms.json")),
            refine_extrinsics: false,
            no_loops: false,
            max_features: 4096,
            peak_threshold: None,
            downscale: None,
            quiet: true,
        })?;
        let e = &r["errors"];
        let p = &r["poses"];
        for key in ["prior", "refined"] {
            if let Ok(pe) =
                serde_json::from_value::<silvr_core::eval::poses::PoseErrors>(e[key].clone())
            {
                eprintln!("[demo] {key} poses: {}", pose_line(&pe));
            }
        }
        eprintln!(
            "[demo] poses stage ({:.1} s): {}/{} images registered, {} points, reprojection RMSE {:.3} px",
            t.elapsed().as_secs_f64(),
            p["registered"],
            p["images"],
            p["points"],
            p["rmse_px"].as_f64().unwrap_or(f64::NAN)
        );
        serde_json::json!({
            "prior": e["prior"],
            "refined": e["refined"],
            "registered": p["registered"],
            "images": p["images"],
            "points": p["points"],
            "rmse_px": p["rmse_px"],
            "rmse_prior_px": p["rmse_prior_px"],
            "seconds": t.elapsed().as_secs_f64(),
            "trained_on": overrides.poses,
        })
    } else {
        // A dataset generated before the prior existed (reused with --reuse-dataset).
        if overrides.poses != "exact" {
            anyhow::bail!(
                "{} has no transforms_prior.json (generated before the SLAM-like prior existed): \
                 generate the world again (drop --reuse-dataset) or pass --poses exact",
                dataset.display()
            );
        }
        serde_json::json!({ "trained_on": "exact" })
    };
    let poses_s = t.elapsed().as_secs_f64();
    // What the fields train on, and the Sim(3) that maps their frame onto the exact one for scoring
    // (the poses stage aligns its output to the prior's frame, then rescales it to the lidar's metric
    // scale: what remains is the prior's frame and a small scale residual).
    let (train_on, alignment) = match overrides.poses.as_str() {
        "exact" => (dataset.clone(), None),
        which => {
            let file = if which == "refined" {
                out.join("poses").join("transforms.json")
            } else {
                dataset.join("transforms_prior.json")
            };
            let a: silvr_core::eval::poses::PoseErrors =
                serde_json::from_value(poses_block[which].clone())
                    .with_context(|| format!("the poses stage scored no {which} poses"))?;
            (file, Some(a.alignment))
        }
    };
    // The poses stage's output names the world's images from beside it.
    let root = data_root(&dataset, out)?;
    if let Some(a) = &alignment {
        eprintln!(
            "[demo] training on the {} poses ({}); geometry scored after their Sim(3) to the exact ones (scale {:.4})",
            overrides.poses,
            train_on.display(),
            a.scale
        );
        poses_block["alignment"] = serde_json::to_value(a)?;
    }
    let geo = GeometryOptions {
        reconstruction_to_gt: alignment.map(|a| a.to_mat4()),
        ..GeometryOptions::default()
    };

    // Lidar-only baseline: the deskewed sweeps in the world frame.
    let t = Instant::now();
    let cloud = map::lidar_map(&dataset)?;
    let lidar_ply = out.join("lidar_only.ply");
    silvr_core::pointcloud::write_ply(&lidar_ply, &cloud)
        .with_context(|| format!("writing {}", lidar_ply.display()))?;
    let ev = eval::evaluate_files_full(&lidar_ply, &dataset, &GeometryOptions::default())?;
    write_error_cloud(&ev, &out.join("lidar_only_error.ply"))?;
    let lidar_s = t.elapsed().as_secs_f64();

    // The two radiance fields: vision-only (nerfacto) and lidar-visual (SiLVR), same model and steps.
    let (steps, model, rays) = demo_training(name);
    let steps = overrides.steps.unwrap_or(steps);
    let model = overrides.model.as_deref().unwrap_or(model);
    let rays = overrides.rays.unwrap_or(rays);
    let mut methods = serde_json::json!({ "lidar_only": report_json(&ev.report) });
    let mut rows = vec![("lidar_only".to_string(), ev.report.clone())];
    let mut uncertainty_block = None;
    let mut timing = serde_json::json!({
        "synth_s": synth_s,
        "poses_s": poses_s,
        "lidar_only_s": lidar_s,
    });
    for (key, mode) in [
        ("vision_only", silvr_core::train::Mode::Vision),
        ("silvr", silvr_core::train::Mode::Silvr),
    ] {
        let t = Instant::now();
        let dir = out.join(key);
        let summary = train::run(&train::TrainArgs {
            dataset: train_on.clone(),
            data_root: Some(root.clone()),
            mode,
            steps,
            rays,
            model: model.into(),
            out: dir.clone(),
            resume: None,
            checkpoint_every: 0,
            backend: overrides.backend.clone(),
            downscale: overrides.downscale,
            seed,
            export_rays: demo_export_rays(name),
            render_views: demo_render_views(name),
            export_depth: ExportDepth::default(),
            quiet: true,
            // The demo reports PSNR/SSIM; normal renders are `silvr train`'s.
            view_normals: false,
            depth_sigma: None,
            uncertainty: (mode == silvr_core::train::Mode::Silvr).then(|| {
                let mut u = demo_uncertainty(name);
                u.batches = overrides.uncertainty_batches.unwrap_or(u.batches);
                u
            }),
        })?;
        let points = summary
            .points
            .clone()
            .context("training exported no points")?;
        let ev = eval::evaluate_files_full(&points, &dataset, &geo)?;
        write_error_cloud(&ev, &dir.join("error.ply"))?;
        let mut v = report_json(&ev.report);
        let psnr = train::mean(summary.views.iter().map(|v| v.psnr));
        let ssim = train::mean(summary.views.iter().map(|v| v.ssim));
        if let Some(obj) = v.as_object_mut() {
            obj.insert("psnr".into(), psnr.into());
            obj.insert("ssim".into(), ssim.into());
            obj.insert("heldout_views".into(), summary.views.len().into());
        }
        methods[key] = v;
        if let Some(u) = &summary.uncertainty {
            let block = uncertainty::evaluate(&dir, &dataset, &train_on, Some(&root), &geo, u)?;
            eprintln!(
                "[demo] uncertainty ({:.1} s): AUSE colour {:.3}, depth {:.3}, combined {:.3} (random {:.3})",
                u.seconds,
                block["ause_colour"].as_f64().unwrap_or(f64::NAN),
                block["ause_depth"].as_f64().unwrap_or(f64::NAN),
                block["ause_combined"].as_f64().unwrap_or(f64::NAN),
                block["ause_random"].as_f64().unwrap_or(f64::NAN)
            );
            uncertainty_block = Some(block);
            timing["uncertainty_s"] = u.seconds.into();
        }
        timing[key] = serde_json::json!({
            "train_s": summary.train_s,
            "total_s": t.elapsed().as_secs_f64(),
            "steps": summary.steps,
            "rays_per_batch": rays,
            "model": model,
            "downscale": overrides.downscale,
            "backend": summary.backend,
            "backends": summary.stages,
            "adapter": summary.adapter,
        });
        eprintln!(
            "[demo] {key}: {} steps in {:.1} s, held-out PSNR {psnr:.2} dB, SSIM {ssim:.3}",
            summary.steps, summary.train_s
        );
        rows.push((key.to_string(), ev.report));
    }
    // The WGSL training step against the CPU reference on this dataset, from the trained SiLVR field
    // (not its initialisation): losses and gradients of one batch on both engines.
    let check = train::crosscheck(
        &train_on,
        Some(&root),
        &out.join("silvr").join("checkpoint.ckpt"),
        1024,
    )?;
    eprintln!("[demo] WGSL step vs CPU reference: {check}");
    let max_diff = check["grad_rel_l2"].as_f64().unwrap_or(f64::INFINITY);
    let loss_diff = check["loss_rel_diff"].as_f64().unwrap_or(f64::INFINITY);
    // Every tensor's gradient within 1 % of the CPU's in the L2 norm and the loss within 0.1 %: the
    // CAS-atomic sums add in another order than the CPU's, and a proposal interval overlap can flip on a
    // rounding error (see `crosscheck`); nothing else differs.
    if max_diff > 1e-2 || loss_diff > 1e-3 {
        anyhow::bail!(
            "the WGSL training step disagrees with the CPU reference on {}: {check}",
            dataset.display()
        );
    }
    timing["wgsl_crosscheck"] = check;
    timing["total_s"] = total.elapsed().as_secs_f64().into();
    timing["adapter"] = serde_json::to_value(gpu.report())?;
    let report = serde_json::json!({
        "preset": name,
        "seed": seed,
        "dataset": dataset,
        "methods": methods,
        "uncertainty": uncertainty_block,
        "poses": poses_block,
        "timing": timing,
    });
    let path = out.join("report.json");
    write_atomic(&path, serde_json::to_string_pretty(&report)?.as_bytes())?;
    let table: Vec<(&str, &GeometryReport)> = rows.iter().map(|(k, r)| (k.as_str(), r)).collect();
    print_table(&table);
    eprintln!(
        "[demo] report: {} ({:.1} s)",
        path.display(),
        total.elapsed().as_secs_f64()
    );
    eprintln!(
        "[demo] open the result in the studio: {}",
        serve::open_command(out)
    );
    Ok(())
}

/// The uncertainty pass per preset: `ci` stays under a tenth of its CPU training time (8 × 1024 rays of
/// each kind, a 128³ grid: ~6 s against ~75 s of training on 2 cores).
fn demo_uncertainty(preset: &str) -> silvr_core::uncertainty::UncertaintyConfig {
    match preset {
        "ci" => silvr_core::uncertainty::UncertaintyConfig {
            batches: 8,
            rays_per_batch: 1024,
            ..Default::default()
        },
        _ => silvr_core::uncertainty::UncertaintyConfig::default(),
    }
}

/// Training length and model size per preset: `ci` fits the 5-minute budget of a 2-core machine.
fn demo_training(preset: &str) -> (u32, &'static str, usize) {
    match preset {
        "ci" => (300, "small", 1024),
        _ => (5000, "nerfacto", 4096),
    }
}

/// Held-out views rendered and scored: half of the `ci` street's six (one per camera, spread along the
/// path; rendering all took as long as a third of the training on 2 cores), all of the others.
fn demo_render_views(preset: &str) -> Option<usize> {
    match preset {
        "ci" => Some(3),
        _ => None,
    }
}

/// Training rays exported as points: nerfstudio's default million on the full loop, fewer on the short
/// `ci` street (completeness there is dominated by what no camera saw).
fn demo_export_rays(preset: &str) -> usize {
    match preset {
        "ci" => 60_000,
        _ => 1_000_000,
    }
}

/// The report keys of one method (full report underneath, for the curious).
fn report_json(r: &GeometryReport) -> serde_json::Value {
    let mut v = serde_json::to_value(r).unwrap_or_default();
    if let Some(obj) = v.as_object_mut() {
        obj.remove("options");
    }
    v
}

pub(crate) fn print_table(rows: &[(&str, &GeometryReport)]) {
    let width = rows
        .iter()
        .map(|(n, _)| n.chars().count())
        .fold(20, usize::max);
    println!(
        "{:<width$} {:>10} {:>10} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8}",
        "method", "acc [m]", "comp [m]", "P@5cm", "R@5cm", "F@5cm", "P@10cm", "R@10cm", "F@10cm"
    );
    for (name, r) in rows {
        let g = |k: &str| r.per_threshold.get(k).copied().unwrap_or(f64::NAN);
        println!(
            "{:<width$} {:>10.4} {:>10.4} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8.3}",
            name,
            r.accuracy_m,
            r.completeness_m,
            g("precision_5cm"),
            g("recall_5cm"),
            g("fscore_5cm"),
            g("precision_10cm"),
            g("recall_10cm"),
            g("fscore_10cm")
        );
    }
}

fn median_rate(mut secs: Vec<f64>, n: usize) -> f64 {
    secs.sort_by(f64::total_cmp);
    n as f64 / secs[secs.len() / 2]
}

fn bench(points: usize, reps: usize, json: bool) -> Result<()> {
    use silvr_core::geometry::{Se3, Trajectory};
    let gpu = open_gpu()?;
    let cam = check_camera();
    let pts = project::sample_points(&cam, 3, points);
    let input = project::ProjectionInput {
        camera: &cam,
        t_cam_points: Se3::IDENTITY,
        points: &pts,
        near: 0.1,
    };
    let reps = reps.max(1);
    let time = |f: &mut dyn FnMut() -> Result<()>| -> Result<Vec<f64>> {
        f()?;
        let mut v = Vec::new();
        for _ in 0..reps {
            let t = Instant::now();
            f()?;
            v.push(t.elapsed().as_secs_f64());
        }
        Ok(v)
    };
    let gpu_t = time(&mut || {
        pollster::block_on(project::project_gpu(&gpu, &input))?;
        Ok(())
    })?;
    let cpu_t = time(&mut || {
        project::project_cpu(&input)?;
        Ok(())
    })?;
    // Deskew: a 10 Hz sweep's worth of per-column times against a 100 Hz trajectory.
    let stamps: Vec<f64> = (0..=20).map(|i| i as f64 * 0.01).collect();
    let poses = stamps
        .iter()
        .map(|&t| {
            Se3::new(
                glam::DQuat::from_rotation_z(t),
                glam::DVec3::new(1.4 * t, 0.0, 0.0),
            )
        })
        .collect();
    let traj = Trajectory::new(stamps, poses)?;
    let times: Vec<f64> = (0..points)
        .map(|i| 0.05 + 0.1 * (i / 64) as f64 / (points / 64).max(1) as f64)
        .collect();
    let times: Vec<f64> = times.into_iter().map(|t| t.min(0.15)).collect();
    let desk_t = time(&mut || {
        silvr_core::lidar::deskew::deskew(&pts, &times, &traj, 0.1)?;
        Ok(())
    })?;
    let v = serde_json::json!({
        "adapter": gpu.report(),
        "points": points,
        "projection_gpu_points_per_s": median_rate(gpu_t, points),
        "projection_cpu_points_per_s": median_rate(cpu_t, points),
        "deskew_cpu_points_per_s": median_rate(desk_t, points),
        "note": "projection_gpu includes upload, three dispatches and readback; CPU is single-threaded f64",
    });
    if json {
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("adapter: {}", gpu.report());
        for k in [
            "projection_gpu_points_per_s",
            "projection_cpu_points_per_s",
            "deskew_cpu_points_per_s",
        ] {
            println!("{k:<32} {:>14.0}", v[k].as_f64().unwrap_or(f64::NAN));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `--reuse-dataset` keeps a dataset only when its manifest records exactly the preset asked for.
    #[test]
    fn a_dataset_is_reused_only_for_its_own_preset_and_seed() {
        let dir = std::env::temp_dir().join(format!("silvr-reuse-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        assert!(!generated_from(&dir, &Preset::ci(1)), "no manifest");
        let manifest = serde_json::json!({ "preset": Preset::ci(1), "files": {} });
        std::fs::write(dir.join("manifest.json"), manifest.to_string()).unwrap();
        assert!(generated_from(&dir, &Preset::ci(1)));
        assert!(!generated_from(&dir, &Preset::ci(2)), "other seed");
        assert!(
            !generated_from(&dir, &Preset::default_preset(1)),
            "other preset"
        );
        // The default rig's extrinsics do not survive serde_json's float parser bit for bit; written as
        // the generator writes it, its manifest must still match.
        let manifest = serde_json::json!({ "preset": Preset::default_preset(1) });
        std::fs::write(
            dir.join("manifest.json"),
            serde_json::to_string_pretty(&manifest).unwrap(),
        )
        .unwrap();
        assert!(generated_from(&dir, &Preset::default_preset(1)));
        std::fs::write(dir.join("manifest.json"), b"{ not json").unwrap();
        assert!(!generated_from(&dir, &Preset::ci(1)), "corrupt manifest");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
