//! One job API for a radiance-field run: training, held-out renders, the point export, the uncertainty
//! pass and the default filter, exactly as `silvr train` / `silvr uncertainty` and the studio's worker
//! run them. Front ends keep only their own concerns: the CLI parses arguments and prints, the worker
//! turns [`StepReport`]s and outputs into messages.
//!
//! Everything here is `async` and never blocks on the GPU (the worker's thread is the browser's event
//! loop); outputs go to a [`Sink`] by name (a folder natively, messages to the page in the studio) and
//! progress to an [`Observer`]. Times come from `web_time` so they work in the browser too.

use std::cell::RefCell;
use std::collections::BTreeMap;
use std::rc::Rc;

use serde::{Deserialize, Serialize};
use web_time::Instant;

use crate::field::model::ModelConfig;
use crate::gpu::GpuError;
use crate::pointcloud::{self, PointCloud};
use crate::train::checkpoint::{Checkpoint, CheckpointError};
use crate::train::data::{DataError, TrainData};
use crate::train::export::{ExportDepth, ViewScore};
use crate::train::{Backend, Engine, Mode, TrainConfig, Trainer};
use crate::uncertainty::{self, filter, Fisher, UncertaintyConfig};

/// Why a job stopped, naming the file, the stage or the step.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    #[error(transparent)]
    Data(#[from] DataError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error("{0}")]
    Invalid(String),
    #[error("writing {name}: {detail}")]
    Output { name: String, detail: String },
}

/// Where a job's outputs go, by `/`-separated name (`points.ply`, `renders/x_rgb.png`).
pub trait Sink {
    fn put(&mut self, name: &str, bytes: &[u8]) -> Result<(), JobError>;
}

/// A folder: each file written under a temporary name and renamed (never half-written).
#[cfg(not(target_arch = "wasm32"))]
pub struct DirSink(pub std::path::PathBuf);

#[cfg(not(target_arch = "wasm32"))]
impl Sink for DirSink {
    fn put(&mut self, name: &str, bytes: &[u8]) -> Result<(), JobError> {
        let p = self.0.join(name);
        crate::dataset::write_atomic(&p, bytes).map_err(|e| JobError::Output {
            name: p.display().to_string(),
            detail: e.to_string(),
        })
    }
}

/// Outputs kept in memory (the worker sends them to the page; tests read them).
#[derive(Default)]
pub struct MemSink(pub BTreeMap<String, Vec<u8>>);

impl Sink for MemSink {
    fn put(&mut self, name: &str, bytes: &[u8]) -> Result<(), JobError> {
        self.0.insert(name.to_string(), bytes.to_vec());
        Ok(())
    }
}

/// What a new run trains: the settings `silvr train` takes and the studio's form offers.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobSpec {
    pub mode: Mode,
    /// Model preset: `nerfacto`, `medium` or `small` ([`ModelConfig::preset`]).
    pub model: String,
    pub steps: u32,
    pub rays: usize,
    pub seed: u64,
    /// DS-NeRF σ schedule (metres, start → end); `None`: SiLVR's.
    #[serde(default)]
    pub depth_sigma: Option<(f32, f32)>,
}

/// A stage's progress, for bars and ETAs.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Progress {
    /// `render`, `export` or `uncertainty`.
    pub stage: &'static str,
    pub done: usize,
    pub total: usize,
    /// Seconds since the stage started.
    pub elapsed_s: f64,
}

impl Progress {
    /// Seconds left at the rate so far.
    pub fn eta_s(&self) -> f64 {
        if self.done == 0 {
            return f64::NAN;
        }
        self.elapsed_s / self.done as f64 * (self.total.saturating_sub(self.done)) as f64
    }
}

/// Receives progress; shared so the trainer's render callback can reach it too.
pub type Observer = Rc<RefCell<dyn FnMut(Progress)>>;

/// An observer that ignores everything.
pub fn quiet() -> Observer {
    Rc::new(RefCell::new(|_| {}))
}

/// One training step as the page's chart and the CLI's progress line show it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StepReport {
    /// Steps done after this one.
    pub step: u32,
    pub steps: u32,
    pub loss: f64,
    /// Training PSNR of this batch (dB).
    pub psnr: f64,
    pub depth: f64,
    pub interlevel: f64,
    /// Seconds of training so far in this session (pauses excluded).
    pub train_s: f64,
    /// Rays per second over this session's steps.
    pub rays_per_s: f64,
    /// Seconds left at that rate.
    pub eta_s: f64,
}

/// A held-out view rendered with the current field, beside its photo.
pub struct HeldOut {
    /// Index into `TrainData::images`.
    pub image: usize,
    /// File-name stem for outputs (`images_cam_front_00005`).
    pub stem: String,
    pub score: ViewScore,
    pub width: u32,
    pub height: u32,
    pub rgb_png: Vec<u8>,
    pub depth_png: Vec<u8>,
    /// Empty unless normals were asked for.
    pub normal_png: Vec<u8>,
    /// The photo (ground truth), same size.
    pub photo_png: Vec<u8>,
}

/// What happens after training.
#[derive(Clone, Debug)]
pub struct FinishOptions {
    /// The dataset as the user named it (recorded in `train.json`).
    pub dataset: String,
    /// Held-out views to render and score, spread along the held-out list (`None`: all).
    pub render_views: Option<usize>,
    /// Normals for the first held-out view and the exported points.
    pub view_normals: bool,
    /// Training rays of the point export (0: no export).
    pub export_rays: usize,
    pub export_depth: ExportDepth,
    pub uncertainty: Option<UncertaintyConfig>,
    /// The adapter's description for the report.
    pub adapter: String,
}

/// What the uncertainty pass produced.
#[derive(Clone, Debug, Serialize)]
pub struct UncertaintySummary {
    pub seconds: f64,
    /// The threshold on `log_std_combined` (Tukey's fence, or `max_sigma_m`), and the points it keeps.
    pub threshold: f32,
    pub kept: usize,
    pub total: usize,
    pub rays: u64,
    pub lidar_rays: u64,
    /// Whether `points.ply` was annotated (and `points_filtered.ply` written).
    pub annotated: bool,
    /// The calibration on held-out lidar returns (factors per read-out: colour, depth, combined; `returns`
    /// 0 when there were none and the read-out is the raw Laplace σ).
    pub calibration: uncertainty::Calibration,
    /// Held-out returns the dataset has (the calibration renders up to the config's number of them).
    pub held_out_returns: usize,
    /// σ against the held-out returns the factors were not fitted on (every other one): per read-out
    /// (colour, depth, combined), raw and calibrated; each residual against √(σ² + lidar noise²). The
    /// check that needs no ground truth.
    pub held_out_check: Option<HeldOutCheck>,
    /// The prior's σ (metres) and the log-std from which a point counts as unconstrained.
    pub prior_sigma_m: f64,
    pub unconstrained_log_std: f32,
    /// Points of the cloud that read the prior (unconstrained).
    pub unconstrained: usize,
    /// Σ of the Fisher diagonals over every cell, colour and depth (the pass's aggregate).
    pub fisher_totals: [f64; 2],
}

/// The read-outs on held-out lidar returns the calibration did not see.
#[derive(Clone, Debug, Serialize)]
pub struct HeldOutCheck {
    pub returns: usize,
    pub raw: Vec<Option<uncertainty::reliability::Reliability>>,
    pub calibrated: Vec<Option<uncertainty::reliability::Reliability>>,
    /// AUSE of the residuals ranked by each calibrated read-out (colour, depth, combined), and by chance.
    pub ause: [Option<f64>; 3],
    pub ause_random: f64,
}

/// The uncertainty pass in a few numbers ([`JobSummary::uncertainty_brief`]).
#[derive(Clone, Debug, Default, PartialEq, Serialize, serde::Deserialize)]
pub struct UncertaintyBrief {
    /// Calibration factor k per read-out (colour, depth, combined); 1 when uncalibrated.
    pub factors: [f64; 3],
    /// The factor a on the rays' spread per read-out; 0 when uncalibrated.
    #[serde(default)]
    pub spread_factors: [f64; 3],
    /// Median raw Laplace σ (k = 1, no spread) per read-out on the held-out lidar returns (metres, with the
    /// lidar's noise in quadrature as the check compares them), where checked.
    pub raw_median_sigma_m: [Option<f64>; 3],
    /// Median calibrated point σ (with the rays' spread, and the lidar's noise in quadrature) per read-out on
    /// the same returns: what the fit made of them, steadier than its two factors, which trade against each
    /// other.
    #[serde(default)]
    pub calibrated_median_sigma_m: [Option<f64>; 3],
    /// The prior's σ (metres): `(prior / σ)² − 1` is the Fisher's weight against the prior's.
    pub prior_sigma_m: f64,
    /// Σ of the Fisher diagonals over every cell, colour and depth.
    pub fisher_totals: [f64; 2],
}

impl UncertaintyBrief {
    pub fn of(u: &UncertaintySummary) -> Self {
        let (mut raw, mut calibrated) = ([None; 3], [None; 3]);
        if let Some(h) = &u.held_out_check {
            for (slot, r) in raw.iter_mut().zip(&h.raw) {
                *slot = r.as_ref().map(|r| r.median_sigma_m);
            }
            for (slot, r) in calibrated.iter_mut().zip(&h.calibrated) {
                *slot = r.as_ref().map(|r| r.median_sigma_m);
            }
        }
        Self {
            factors: u.calibration.factor,
            spread_factors: u.calibration.spread,
            raw_median_sigma_m: raw,
            calibrated_median_sigma_m: calibrated,
            prior_sigma_m: u.prior_sigma_m,
            fisher_totals: u.fisher_totals,
        }
    }
}

/// What a finished run measured (also written as `train.json`).
#[derive(Clone, Debug, Serialize)]
pub struct JobSummary {
    pub mode: &'static str,
    pub dataset: String,
    /// The images' integer downscale in training (1 = full size).
    pub downscale: u32,
    pub steps: u32,
    pub train_s: f64,
    /// `wgpu` or `cpu`.
    pub backend: &'static str,
    /// The engine of each stage that ran: training, renders, export, uncertainty.
    pub backends: BTreeMap<&'static str, &'static str>,
    pub adapter: String,
    pub train_psnr_last20: f64,
    pub heldout: Vec<ViewScore>,
    pub heldout_psnr_mean: f64,
    pub heldout_ssim_mean: f64,
    /// Output names in the sink.
    pub points: Option<String>,
    pub train_rays_per_s: f64,
    pub render_rays_per_s: Option<f64>,
    pub export_rays_per_s: Option<f64>,
    pub uncertainty_s: Option<f64>,
    /// The uncertainty pass in brief (the full summary is `uncertainty`, not serialised): what the
    /// browser's run is compared with, since a briefly trained field's calibrated σ all read the prior
    /// while these follow the Fisher the pass accumulated.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub uncertainty_brief: Option<UncertaintyBrief>,
    #[serde(skip)]
    pub uncertainty: Option<UncertaintySummary>,
    #[serde(skip)]
    pub exported: usize,
}

/// Mean of the values (NaN when there are none).
pub fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 {
        f64::NAN
    } else {
        s / n as f64
    }
}

/// A step's error; a batch that outgrew the device's limit says which setting to change.
fn too_large(e: GpuError, rays: usize) -> JobError {
    match e {
        e @ GpuError::BufferTooLarge { .. } => JobError::Invalid(format!(
            "{e}: use fewer rays per batch than {rays}, or a smaller model"
        )),
        e => JobError::Gpu(e),
    }
}

/// A training run in progress.
pub struct TrainJob {
    pub trainer: Trainer,
    /// Step at which this session started (after a resume, the checkpoint's).
    pub start_step: u32,
    /// Seconds spent inside steps this session.
    pub train_s: f64,
}

impl TrainJob {
    /// A new run on `data`.
    pub fn new(data: TrainData, spec: &JobSpec, backend: Backend) -> Result<TrainJob, JobError> {
        if spec.mode != Mode::Vision && !data.has_lidar() {
            return Err(JobError::Invalid(format!(
                "{}: mode {} needs lidar depth images (depth_file_path), and this dataset has none; train it vision-only",
                data.root.display(),
                spec.mode.name()
            )));
        }
        let model = ModelConfig::preset(&spec.model, data.train.len())?;
        let mut config = TrainConfig::for_run(spec.mode, spec.steps, spec.rays, spec.seed);
        if let Some((a, b)) = spec.depth_sigma {
            config.schedule_sigma(a, b);
        }
        let trainer = Trainer::new(data, model, config, backend)?;
        if let Engine::Wgpu(e) = &trainer.engine {
            e.check_batch(spec.rays)
                .map_err(|e| too_large(e, spec.rays))?;
        }
        Ok(Self::around(trainer))
    }

    /// Continues a checkpointed run on the same dataset, now to `steps` steps.
    pub fn resume(
        data: TrainData,
        ck: Checkpoint,
        backend: Backend,
        steps: u32,
    ) -> Result<TrainJob, JobError> {
        let mut t = Trainer::resume(data, ck, backend)?;
        t.config.steps = steps;
        Ok(Self::around(t))
    }

    fn around(trainer: Trainer) -> TrainJob {
        TrainJob {
            start_step: trainer.step,
            trainer,
            train_s: 0.0,
        }
    }

    pub fn done(&self) -> bool {
        self.trainer.step >= self.trainer.config.steps
    }

    /// One step, timed; errors name the step.
    pub async fn step(&mut self) -> Result<StepReport, JobError> {
        let t0 = Instant::now();
        let rays = self.trainer.config.rays_per_batch;
        let s = self
            .trainer
            .train_step()
            .await
            .map_err(|e| too_large(e, rays))?;
        self.train_s += t0.elapsed().as_secs_f64();
        let t = &self.trainer;
        let session = (t.step - self.start_step) as f64;
        let rate = session / self.train_s.max(1e-9);
        Ok(StepReport {
            step: t.step,
            steps: t.config.steps,
            loss: s.loss,
            psnr: s.psnr(),
            depth: s.depth,
            interlevel: s.interlevel,
            train_s: self.train_s,
            rays_per_s: rate * t.config.rays_per_batch as f64,
            eta_s: t.config.steps.saturating_sub(t.step) as f64 / rate.max(1e-12),
        })
    }

    /// The checkpoint's bytes (the native format: a browser checkpoint resumes natively and back).
    pub async fn checkpoint_bytes(&mut self) -> Result<Vec<u8>, JobError> {
        Ok(self.trainer.checkpoint().await?.to_bytes())
    }

    /// Renders held-out view `k` (of `data.val`) and scores it against its photo.
    pub async fn held_out(&mut self, k: usize, normals: bool) -> Result<HeldOut, JobError> {
        let t = &mut self.trainer;
        let i = *t.data.val.get(k).ok_or_else(|| {
            JobError::Invalid(format!(
                "held-out view {k} asked for; the dataset holds out {}",
                t.data.val.len()
            ))
        })?;
        let v = t.render_view(i, normals).await?;
        let score = t.score_view(i, &v)?;
        let (rgb_png, depth_png, normal_png) = t.view_pngs(i, &v);
        let im = &t.data.images[i];
        Ok(HeldOut {
            image: i,
            stem: stem(&im.name),
            score,
            width: v.width,
            height: v.height,
            rgb_png,
            depth_png,
            normal_png: if normals { normal_png } else { Vec::new() },
            photo_png: crate::dataset::png_rgb(im.width, im.height, &im.rgb),
        })
    }

    /// Everything after training: the checkpoint, held-out renders and scores, the point export, the
    /// uncertainty pass (annotating the points, the default filter), and `train.json`.
    pub async fn finish(
        &mut self,
        opts: &FinishOptions,
        sink: &mut dyn Sink,
        observer: Observer,
    ) -> Result<JobSummary, JobError> {
        let engine = self.trainer.engine.name();
        let mut backends = BTreeMap::from([("training", engine)]);
        sink.put("checkpoint.ckpt", &self.checkpoint_bytes().await?)?;
        let recent = &self.trainer.history[self.trainer.history.len().saturating_sub(20)..];
        let mse = recent.iter().map(|s| s.rgb_mse).sum::<f64>() / recent.len().max(1) as f64;
        // Held-out views.
        let stage = Rc::new(RefCell::new(("render", Instant::now())));
        {
            let (obs, stage) = (observer.clone(), stage.clone());
            self.trainer.render_progress = Some(Box::new(move |done, total| {
                let (name, t0) = *stage.borrow();
                (obs.borrow_mut())(Progress {
                    stage: name,
                    done,
                    total,
                    elapsed_s: t0.elapsed().as_secs_f64(),
                });
            }));
        }
        let t_render = Instant::now();
        let mut rendered = 0usize;
        let mut views = Vec::new();
        let held = self.trainer.data.val.len();
        let count = held.min(opts.render_views.unwrap_or(usize::MAX));
        for k in 0..count {
            *stage.borrow_mut() = ("render", Instant::now());
            let normals = opts.view_normals && k == 0;
            // Fewer views than are held out: spread along the list (it runs along the trajectory,
            // cameras interleaved), not the first few.
            let h = self.held_out(k * held / count, normals).await?;
            rendered += (h.width * h.height) as usize;
            sink.put(&format!("renders/{}_rgb.png", h.stem), &h.rgb_png)?;
            sink.put(&format!("renders/{}_depth.png", h.stem), &h.depth_png)?;
            if normals {
                sink.put(&format!("renders/{}_normal.png", h.stem), &h.normal_png)?;
            }
            views.push(h.score);
        }
        let render_s = t_render.elapsed().as_secs_f64();
        if !views.is_empty() {
            backends.insert("renders", engine);
        }
        // The point export.
        let t_export = Instant::now();
        *stage.borrow_mut() = ("export", Instant::now());
        let mut cloud = None;
        if opts.export_rays > 0 {
            let seed = self.trainer.config.seed ^ 0xE0;
            let c = self
                .trainer
                .export_points(opts.export_rays, seed, opts.view_normals, opts.export_depth)
                .await?;
            backends.insert("export", engine);
            cloud = Some(c);
        }
        let export_s = t_export.elapsed().as_secs_f64();
        self.trainer.render_progress = None;
        let exported = cloud.as_ref().map_or(0, PointCloud::len);
        let uncertainty = match &opts.uncertainty {
            Some(cfg) => {
                let u = uncertainty_pass(&mut self.trainer, cfg, cloud.as_mut(), sink, observer)
                    .await?;
                backends.insert("uncertainty", engine);
                Some(u)
            }
            None => None,
        };
        let points = match &cloud {
            Some(c) => {
                put_ply(sink, "points.ply", c)?;
                Some("points.ply".to_string())
            }
            None => None,
        };
        let session_steps = self.trainer.step.saturating_sub(self.start_step);
        let summary = JobSummary {
            mode: self.trainer.config.mode.name(),
            dataset: opts.dataset.clone(),
            downscale: self.trainer.data.downscale,
            steps: self.trainer.step,
            train_s: self.train_s,
            backend: engine,
            backends,
            adapter: opts.adapter.clone(),
            train_psnr_last20: -10.0 * mse.max(1e-12).log10(),
            heldout_psnr_mean: mean(views.iter().map(|v| v.psnr)),
            heldout_ssim_mean: mean(views.iter().map(|v| v.ssim)),
            heldout: views,
            points,
            train_rays_per_s: session_steps as f64 * self.trainer.config.rays_per_batch as f64
                / self.train_s.max(1e-9),
            render_rays_per_s: (rendered > 0).then(|| rendered as f64 / render_s),
            export_rays_per_s: (opts.export_rays > 0).then(|| opts.export_rays as f64 / export_s),
            uncertainty_s: uncertainty.as_ref().map(|u| u.seconds),
            uncertainty_brief: uncertainty.as_ref().map(UncertaintyBrief::of),
            uncertainty,
            exported,
        };
        let json = serde_json::to_vec_pretty(&summary).expect("plain data serialises");
        sink.put("train.json", &json)?;
        Ok(summary)
    }
}

fn put_ply(sink: &mut dyn Sink, name: &str, cloud: &PointCloud) -> Result<(), JobError> {
    let bytes = pointcloud::write_ply_bytes(cloud).map_err(|e| JobError::Output {
        name: name.into(),
        detail: e.to_string(),
    })?;
    sink.put(name, &bytes)
}

/// `images/cam_front/00005.png` → `images_cam_front_00005`: an output's name from its image's identity in
/// its dataset. A name reached through another folder (`../ds/images/cam/00005.png`, as refined poses name
/// the frames) keeps its part from `images/` on, and `.`/`..` are dropped, so that no output is a hidden
/// file (`.._ds_images_…`) or names where it was read from.
pub fn stem(name: &str) -> String {
    let parts: Vec<&str> = name
        .split(['/', '\\'])
        .filter(|p| !p.is_empty() && *p != "." && *p != "..")
        .collect();
    let from = parts.iter().rposition(|p| *p == "images").unwrap_or(0);
    parts[from..]
        .join("_")
        .trim_end_matches(".png")
        .trim_end_matches(".jpg")
        .to_string()
}

/// The uncertainty pass on a trained field: writes `uncertainty.bin`; with a cloud, annotates it with the
/// read-out (`log_std_colour`, `log_std_depth`, `log_std_combined`; the caller writes it) and writes
/// `points_filtered.ply` at the default threshold; renders the first held-out view's uncertainty image.
pub async fn uncertainty_pass(
    trainer: &mut Trainer,
    config: &UncertaintyConfig,
    cloud: Option<&mut PointCloud>,
    sink: &mut dyn Sink,
    observer: Observer,
) -> Result<UncertaintySummary, JobError> {
    let t0 = Instant::now();
    let mut fisher = uncertainty::compute_fisher(trainer, config, |done, total| {
        (observer.borrow_mut())(Progress {
            stage: "uncertainty",
            done,
            total,
            elapsed_s: t0.elapsed().as_secs_f64(),
        })
    })
    .await?;
    // Two factors per read-out (k on the Laplace σ, a on the rays' spread), fitted on lidar returns training
    // held out (never on ground truth).
    let held = if config.calibration_returns > 0 {
        uncertainty::calibrate::held_out_returns(trainer, config.calibration_returns, config.seed)
            .await?
    } else {
        Default::default()
    };
    // A cloud exported without its rays' spreads (by an older silvr) cannot carry it in its σ: the factors
    // are then fitted without it too, or they would lean on a term its points lack.
    let mut held = held;
    if cloud
        .as_ref()
        .is_some_and(|c| c.scalar(uncertainty::DEPTH_SPREAD_FIELD).is_none())
    {
        held.spread_m.clear();
    }
    // Fitted on every other return, checked on the rest.
    let (fit, check) = held.split();
    uncertainty::calibrate::calibrate(&mut fisher, &fit);
    let held_out_check = (!check.residual_m.is_empty()).then(|| {
        let table = |post| {
            uncertainty::Modality::ALL
                .iter()
                .map(|&m| uncertainty::calibrate::held_out_reliability(&fisher, m, post, &check))
                .collect()
        };
        HeldOutCheck {
            returns: check.residual_m.len(),
            raw: table(uncertainty::Posterior::Raw),
            calibrated: table(uncertainty::Posterior::Calibrated),
            ause: uncertainty::Modality::ALL.map(|m| {
                uncertainty::calibrate::held_out_ause(
                    &fisher,
                    m,
                    uncertainty::Posterior::Calibrated,
                    &check,
                )
            }),
            ause_random: uncertainty::sparsify::random_ause(&check.residual_m, 5, 17),
        }
    });
    let seconds = t0.elapsed().as_secs_f64();
    sink.put("uncertainty.bin", &fisher.to_bytes())?;
    let prior_sigma_m = fisher.prior_sigma_m();
    let unconstrained_log_std = uncertainty::unconstrained_log_std(prior_sigma_m);
    let mut s = UncertaintySummary {
        seconds,
        threshold: f32::INFINITY,
        kept: 0,
        total: 0,
        rays: fisher.rays,
        lidar_rays: fisher.lidar_rays,
        annotated: false,
        calibration: fisher.calibration.clone(),
        held_out_returns: held.available,
        held_out_check,
        prior_sigma_m,
        unconstrained_log_std,
        unconstrained: 0,
        fisher_totals: [&fisher.colour, &fisher.depth].map(|v| v.iter().map(|&x| x as f64).sum()),
    };
    if let Some(cloud) = cloud {
        uncertainty::annotate_cloud(&fisher, cloud);
        let comb = cloud.scalar("log_std_combined").unwrap_or(&[]).to_vec();
        s.unconstrained = comb.iter().filter(|&&v| v >= unconstrained_log_std).count();
        s.threshold = match config.max_sigma_m {
            Some(m) => m.log10() as f32,
            None => filter::default_threshold(&comb),
        };
        let kept = filter::filter_cloud(cloud, "log_std_combined", s.threshold);
        s.kept = kept.len();
        s.total = cloud.len();
        s.annotated = true;
        put_ply(sink, "points_filtered.ply", &kept)?;
    }
    if let Some(&i) = trainer.data.val.first() {
        let png = uncertainty_image(trainer, &fisher, i).await?;
        let name = format!(
            "renders/{}_uncertainty.png",
            stem(&trainer.data.images[i].name)
        );
        sink.put(&name, &png)?;
    }
    Ok(s)
}

/// Per-pixel combined uncertainty of a held-out view, read out at each pixel's expected-depth point,
/// as a greyscale PNG: black = the most certain pixel of the view, white = the prior.
pub async fn uncertainty_image(
    trainer: &mut Trainer,
    fisher: &Fisher,
    i: usize,
) -> Result<Vec<u8>, JobError> {
    let v = trainer.render_view(i, false).await?;
    let (rays, _) = trainer.view_rays(i);
    let scale = trainer.data.frame.scale as f32;
    let pts: Vec<[f32; 3]> = rays
        .iter()
        .zip(&v.depth_m)
        .map(|(r, &d)| {
            let t = d * scale;
            [0, 1, 2].map(|k| r.origin[k] + r.dir[k] * t)
        })
        .collect();
    // Each pixel's σ as a point there would carry it: with its ray's spread.
    let a = fisher.spread_factors(uncertainty::Posterior::Calibrated)
        [uncertainty::Modality::Combined.index()];
    let u: Vec<f32> = fisher
        .read_out_scene(
            uncertainty::Modality::Combined,
            uncertainty::Posterior::Calibrated,
            &pts,
        )
        .iter()
        .zip(&v.spread_m)
        .map(|(&l, &s)| uncertainty::with_spread(l, s, a))
        .collect();
    let lo = u
        .iter()
        .cloned()
        .filter(|x| x.is_finite())
        .fold(f32::INFINITY, f32::min);
    let hi = fisher.prior_sigma_m().log10() as f32;
    let px: Vec<u8> = (0..(v.width * v.height) as usize)
        .map(|k| {
            if !v.valid[k] {
                return 0;
            }
            let s = ((u[k] - lo) / (hi - lo).max(1e-6)).clamp(0.0, 1.0);
            (s * 255.0).round() as u8
        })
        .collect();
    Ok(crate::dataset::png_gray8(v.width, v.height, &px))
}

#[cfg(test)]
mod stem_tests {
    use super::stem;

    #[test]
    fn output_names_come_from_the_images_identity_never_hidden() {
        assert_eq!(stem("images/cam_front/00005.png"), "images_cam_front_00005");
        assert_eq!(
            stem("../ds/images/cam_left/00000.png"),
            "images_cam_left_00000"
        );
        assert_eq!(stem("./images/a/1.jpg"), "images_a_1");
        assert_eq!(stem("photos/IMG_1.jpg"), "photos_IMG_1");
        assert_eq!(stem("../../x/y.png"), "x_y");
        assert!(!stem("../.hidden/images/c/1.png").starts_with('.'));
    }
}
