//! SiLVR Studio's Web Worker: the engine on WebGPU, off the page's main thread.
//!
//! The page starts it with `new Worker("./worker_loader.js")` (trunk's loader shim for the `worker` binary).
//! It talks to the page with plain JS objects tagged by `type` (see [`ToPage`] and [`FromPage`]):
//!
//! | direction | message |
//! |---|---|
//! | worker → page | `{type: "adapter", adapter: AdapterReport}` once WebGPU gave a device |
//! | worker → page | `{type: "projection", id, seed, n, elapsed_ms, passed, check: SelfCheck}` after each kernel self-check (`id` is `null` for the one at startup) |
//! | worker → page | `{type: "error", id, stage, message, detail}`: `stage` is `"webgpu"` (no usable adapter), `"projection"`, `"message"` (a message the worker does not understand) or `"panic"` |
//! | page → worker | `{type: "run-check", id?, n?, seed?}`: run the projection self-check again |
//! | page → worker | `{type: "canvas", canvas: OffscreenCanvas, width, height}` (transferred): the view draws there |
//! | page → worker | `{type: "resize", width, height}`, `{type: "view", view: ViewState}`: draw again |
//! | page → worker | `{type: "open-url", id, url, token?}`, `{type: "open-file", id, file: File}`: open a PLY as a layer (`token`: the page's `?token=`, sent to the page's own origin only) |
//! | page → worker | `{type: "download", id, layer, view}`: the layer's kept points as PLY; `{type: "bench", id, frames}` |
//! | worker → page | `{type: "progress", id, source, stage, loaded, total}` while a file streams in |
//! | worker → page | `{type: "layer", id, layer: LayerInfo}`, `{type: "load-error", id, source, message}` |
//! | worker → page | `{type: "filter", counts: FilterCounts}` after a view or layer change; `{type: "frame", n, ms}` after each draw |
//! | worker → page | `{type: "download", id, name, bytes: Uint8Array}`, `{type: "bench", id, frames, ms_per_frame, points}` |
//!
//! Natively the crate builds (the message types and [`run_check`] are plain Rust) but the `worker` binary
//! does nothing: the browser is its only home.

use serde::{Deserialize, Serialize};
use silvr_core::camera::{CameraModel, Distortion};
use silvr_core::gpu::{AdapterReport, Gpu};
use silvr_core::lidar::project::{self, SelfCheck};

pub mod copc;
#[cfg(target_arch = "wasm32")]
mod js;
pub mod studio;
#[cfg(target_arch = "wasm32")]
mod train;
pub mod view;
#[cfg(target_arch = "wasm32")]
mod web;
#[cfg(target_arch = "wasm32")]
pub use web::start;

/// Seed of the self-check the worker runs at startup.
pub const STARTUP_SEED: u64 = 7;
/// Points of the startup self-check: small, because SwiftShader is slow.
pub const STARTUP_POINTS: usize = 4000;
/// Largest self-check the page may ask for.
pub const MAX_CHECK_POINTS: usize = 2_000_000;

/// The camera the self-check projects into: the Spires front fisheye at a quarter of its resolution
/// (the same one as `silvr gpu-info`).
pub fn check_camera() -> CameraModel {
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

/// Where an error happened, for the page to word it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Stage {
    /// No WebGPU adapter, or it is too limited, or no device could be opened.
    Webgpu,
    /// The projection self-check could not run.
    Projection,
    /// The page sent something the worker does not understand.
    Message,
    /// The view (canvas, rendering, downloads).
    View,
    /// The worker panicked; it is dead afterwards.
    Panic,
}

/// The browser's own description of the adapter (`GPUAdapterInfo`). wgpu takes the adapter name from
/// `description`, which browsers usually leave empty for privacy; vendor and architecture are still set.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct BrowserAdapterInfo {
    pub vendor: String,
    pub architecture: String,
    pub device: String,
    pub description: String,
}

impl BrowserAdapterInfo {
    /// `google / swiftshader`: vendor, architecture and device as the browser gave them, or `None`.
    pub fn summary(&self) -> Option<String> {
        let parts: Vec<&str> = [&self.vendor, &self.architecture, &self.device]
            .into_iter()
            .map(|s| s.trim())
            .filter(|s| !s.is_empty())
            .collect();
        (!parts.is_empty()).then(|| parts.join(" / "))
    }

    /// A readable name: the description, else vendor, architecture and device (e.g. `google swiftshader`).
    pub fn display_name(&self) -> Option<String> {
        if !self.description.trim().is_empty() {
            return Some(self.description.trim().to_string());
        }
        let parts: Vec<&str> = [&self.vendor, &self.architecture, &self.device]
            .into_iter()
            .map(|s| s.trim())
            .filter(|s| !s.is_empty())
            .collect();
        (!parts.is_empty()).then(|| parts.join(" "))
    }
}

/// Gives an adapter that wgpu could not name (`"unnamed adapter"`) the browser's name for it.
pub fn name_adapter(report: &mut AdapterReport, info: &BrowserAdapterInfo) {
    let unnamed = report.name.trim().is_empty() || report.name == "unnamed adapter";
    if let (true, Some(name)) = (unnamed, info.display_name()) {
        report.name = name;
    }
}

/// Messages from the worker to the page (the page reads them with the same type).
#[derive(Debug, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "kebab-case")]
pub enum ToPage {
    Adapter {
        adapter: AdapterReport,
        /// `GPUAdapterInfo` as the browser reports it, where it could be read.
        #[serde(default)]
        browser: Option<BrowserAdapterInfo>,
    },
    Projection {
        id: Option<u32>,
        seed: u64,
        n: usize,
        elapsed_ms: f64,
        passed: bool,
        check: SelfCheck,
    },
    /// A file streaming in (`stage`: `download`, `parse`, `upload`); `total` when known.
    Progress {
        id: u32,
        source: String,
        stage: String,
        loaded: f64,
        total: Option<f64>,
    },
    /// A file opened as a layer.
    Layer { id: u32, layer: studio::LayerInfo },
    /// A file that could not be opened: the source and the problem.
    LoadError {
        id: u32,
        source: String,
        message: String,
    },
    /// The filter's outcome for the view in force.
    Filter { counts: studio::FilterCounts },
    /// A frame was drawn (`ms`: submit to done on the GPU queue) for the view numbered `seq` with `draw`
    /// (the view's choice, or quads where the canvas is too large for the compute rasteriser); the filter
    /// counts of that view were sent before it.
    Frame {
        n: u32,
        ms: f64,
        points: u64,
        seq: u32,
        draw: silvr_core::viewer::Raster,
    },
    /// `frames` frames drawn back to back with `draw`; `wasm_bytes`: the worker's wasm heap then.
    Bench {
        id: u32,
        frames: u32,
        draw: silvr_core::viewer::Raster,
        wasm_bytes: u64,
        ms_per_frame: f64,
        points: u64,
    },
    /// A training dataset was read and loaded.
    TrainLoaded {
        id: u32,
        source: String,
        images: usize,
        train: usize,
        held_out: usize,
        lidar: bool,
        /// Frames listed but skipped, with why.
        skipped: Vec<String>,
    },
    /// The run's state: `loading`, `running`, `paused`, `stopping`, `finishing`, `done`, `failed`.
    TrainState {
        state: String,
        step: u32,
        steps: u32,
    },
    /// One training step (sent after every step).
    TrainStep { report: silvr_core::job::StepReport },
    /// A stage after training (`render`, `export`, `uncertainty`), for the bar and its ETA.
    TrainProgress {
        stage: String,
        done: usize,
        total: usize,
        eta_s: f64,
    },
    /// The run finished: its scores and outputs (the points were opened as a layer; `outputs` can be
    /// asked for with `train-download`).
    TrainDone { summary: TrainResult },
    /// The run could not start or stopped: the source or stage, and the problem.
    TrainError { source: String, message: String },
    /// A checkpoint of the run was saved in the origin-private file system (every N steps, on pause).
    TrainSaved { step: u32 },
    /// Answer to `train-query-saved`: the run saved in this origin (to resume after a reload), if any.
    TrainSavedRun { run: Option<SavedRun> },
    Error {
        id: Option<u32>,
        stage: Stage,
        /// One sentence for people.
        message: String,
        /// The underlying error, for the curious and for bug reports.
        #[serde(default)]
        detail: Option<String>,
    },
}

/// Messages from the page to the worker.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "kebab-case")]
pub enum FromPage {
    /// Runs the projection self-check (defaults: [`STARTUP_POINTS`] points, seed [`STARTUP_SEED`]).
    RunCheck {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        id: Option<u32>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        n: Option<usize>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        seed: Option<u64>,
    },
    /// The canvas (its `OffscreenCanvas` travels beside the message) changed size.
    Resize { width: u32, height: u32 },
    /// Draw this view; `seq` comes back with the frame that drew it.
    View {
        view: view::ViewState,
        #[serde(default)]
        seq: u32,
    },
    /// Fetch a PLY over http(s) and open it as a layer.
    OpenUrl {
        id: u32,
        url: String,
        /// The page's access token (`?token=`, see [`view::TOKEN_HEADER`]): sent with the fetch when
        /// `url` is on the page's own origin, never to another.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        token: Option<String>,
    },
    /// The kept points of layer `layer` under `view` as PLY bytes.
    Download {
        id: u32,
        layer: u32,
        view: view::ViewState,
    },
    /// Draw `frames` frames back to back and report the time per frame.
    Bench { id: u32, frames: u32 },
    /// Destroys the device, as a driver reset or a GPU process crash would (tests of the recovery).
    DebugLoseDevice,
    /// Panics in the worker, as a bug would (tests of the page's crash recovery).
    DebugPanic,
    /// Fetch a dataset archive (`silvr pack`) over http(s) and train it. (Dropped files travel as
    /// `{type: "train-files", id, files: [File], paths: [string], settings}`, read field by field.)
    TrainUrl {
        id: u32,
        url: String,
        settings: TrainSettings,
        /// As in [`FromPage::OpenUrl`].
        #[serde(default, skip_serializing_if = "Option::is_none")]
        token: Option<String>,
    },
    /// `pause`, `resume` or `stop` (stop still renders, exports and runs the uncertainty pass).
    TrainControl { action: TrainAction },
    /// One of the finished run's outputs (`points.ply`, `checkpoint.ckpt`, …) as a download; while a
    /// run is paused, its checkpoint.
    TrainDownload { id: u32, name: String },
    /// Is there a run saved in this origin's private file system?
    TrainQuerySaved,
    /// Resume the saved run (its dataset and checkpoint come from the origin-private file system).
    TrainResumeSaved { id: u32 },
}

/// A run saved in the origin-private file system: what the page offers to resume.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SavedRun {
    /// The dataset as the user gave it (archive, folder or URL).
    pub source: String,
    pub settings: TrainSettings,
    /// Step of the saved checkpoint.
    pub step: u32,
}

/// What the page's training form sets.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainSettings {
    pub job: silvr_core::job::JobSpec,
    /// A checkpoint is saved in the origin-private file system every this many steps (0: on pause only).
    #[serde(default = "default_checkpoint_every")]
    pub checkpoint_every: u32,
    /// Integer image downscale (1 = full size), as `silvr train --downscale`.
    #[serde(default = "one")]
    pub downscale: u32,
    /// A held-out view is rendered beside its photo every this many steps (0: only at the end).
    #[serde(default = "default_view_every")]
    pub view_every: u32,
    /// Held-out views rendered and scored after training (at most).
    #[serde(default = "default_render_views")]
    pub render_views: usize,
    /// Training rays of the point export.
    #[serde(default = "default_export_rays")]
    pub export_rays: usize,
    /// Batches of the uncertainty pass (0: no pass), of `uncertainty_rays` rays each.
    #[serde(default = "default_uncertainty_batches")]
    pub uncertainty_batches: usize,
    #[serde(default = "default_uncertainty_rays")]
    pub uncertainty_rays: usize,
}

fn default_checkpoint_every() -> u32 {
    100
}
fn one() -> u32 {
    1
}
fn default_view_every() -> u32 {
    100
}
fn default_render_views() -> usize {
    8
}
fn default_export_rays() -> usize {
    16_384
}
fn default_uncertainty_batches() -> usize {
    8
}
fn default_uncertainty_rays() -> usize {
    1024
}

impl TrainSettings {
    /// Refuses settings no adapter could run (absurd sizes) before anything is loaded.
    pub fn validate(&self) -> Result<(), String> {
        let j = &self.job;
        if j.steps == 0 || j.steps > 1_000_000 {
            return Err(format!("steps must be 1 to 1 000 000, not {}", j.steps));
        }
        if j.rays == 0 || j.rays > 1 << 20 {
            return Err(format!(
                "rays per batch must be 1 to 1 048 576, not {}",
                j.rays
            ));
        }
        if !(1..=16).contains(&self.downscale) {
            return Err(format!("downscale must be 1 to 16, not {}", self.downscale));
        }
        if self.export_rays > 1 << 22 {
            return Err(format!(
                "export rays at most 4 194 304, not {}",
                self.export_rays
            ));
        }
        if self.uncertainty_batches > 10_000 || self.uncertainty_rays > 1 << 16 {
            return Err("the uncertainty pass takes at most 10 000 batches of 65 536 rays".into());
        }
        silvr_core::field::model::ModelConfig::preset(&j.model, 1).map_err(|e| e.to_string())?;
        Ok(())
    }
}

/// What the training card's buttons ask.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TrainAction {
    Pause,
    Resume,
    Stop,
}

/// A finished run as the page shows it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TrainResult {
    /// The mode it trained (a camera-only capture trains `vision` whatever was asked).
    pub mode: String,
    pub steps: u32,
    pub train_s: f64,
    pub rays_per_s: f64,
    pub backend: String,
    pub heldout_psnr: f64,
    pub heldout_ssim: f64,
    pub held_out_views: usize,
    pub points: usize,
    /// Points the default uncertainty filter keeps, and its threshold (log10 m); `None` without the pass.
    pub kept: Option<usize>,
    pub threshold: Option<f32>,
    /// `log_std_combined` quantiles (5, 25, 50, 75, 95 %) of the exported points.
    pub log_std_quantiles: Vec<f32>,
    /// The uncertainty pass's calibration factors and raw σ on held-out returns (as `train.json` has them).
    pub uncertainty: Option<silvr_core::job::UncertaintyBrief>,
    /// Output names the worker holds.
    pub outputs: Vec<String>,
}

impl FromPage {
    /// The request id the answer carries, where the message has one.
    pub fn id(&self) -> Option<u32> {
        match self {
            FromPage::RunCheck { id, .. } => *id,
            FromPage::OpenUrl { id, .. }
            | FromPage::Download { id, .. }
            | FromPage::Bench { id, .. }
            | FromPage::TrainUrl { id, .. }
            | FromPage::TrainDownload { id, .. }
            | FromPage::TrainResumeSaved { id } => Some(*id),
            FromPage::Resize { .. }
            | FromPage::View { .. }
            | FromPage::DebugLoseDevice
            | FromPage::DebugPanic
            | FromPage::TrainControl { .. }
            | FromPage::TrainQuerySaved => None,
        }
    }
}

/// Runs the projection kernel against its CPU reference on `n` generated points and words the outcome
/// as a message for the page.
pub async fn run_check(gpu: &Gpu, id: Option<u32>, n: usize, seed: u64) -> ToPage {
    if n > MAX_CHECK_POINTS {
        return ToPage::Error {
            id,
            stage: Stage::Projection,
            message: format!(
                "a self-check takes at most {MAX_CHECK_POINTS} points, {n} were asked for"
            ),
            detail: None,
        };
    }
    let start = now_ms();
    match project::self_check(gpu, &check_camera(), seed, n).await {
        Ok(check) => ToPage::Projection {
            id,
            seed,
            n,
            elapsed_ms: now_ms() - start,
            passed: check.passed(),
            check,
        },
        Err(e) => ToPage::Error {
            id,
            stage: Stage::Projection,
            message: "the projection kernel could not run".into(),
            detail: Some(e.to_string()),
        },
    }
}

/// Answers one message from the page.
pub async fn handle(gpu: &Gpu, msg: FromPage) -> ToPage {
    match msg {
        FromPage::RunCheck { id, n, seed } => {
            run_check(
                gpu,
                id,
                n.unwrap_or(STARTUP_POINTS),
                seed.unwrap_or(STARTUP_SEED),
            )
            .await
        }
        // The view's messages need the worker's layers and canvas (`web.rs`), not just a device.
        other => ToPage::Error {
            id: other.id(),
            stage: Stage::Message,
            message: "this message needs the studio's view, which only the worker in a browser has"
                .into(),
            detail: None,
        },
    }
}

#[cfg(target_arch = "wasm32")]
fn now_ms() -> f64 {
    js_sys::Date::now()
}

#[cfg(not(target_arch = "wasm32"))]
fn now_ms() -> f64 {
    use std::time::{SystemTime, UNIX_EPOCH};
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs_f64() * 1e3)
        .unwrap_or(0.0)
}

#[cfg(all(test, not(target_arch = "wasm32")))]
mod tests {
    use super::*;

    #[test]
    fn check_camera_is_valid() {
        check_camera().validate().unwrap();
    }

    #[test]
    fn page_messages_parse_with_defaults() {
        let m: FromPage = serde_json::from_str(r#"{"type":"run-check"}"#).unwrap();
        assert_eq!(
            m,
            FromPage::RunCheck {
                id: None,
                n: None,
                seed: None
            }
        );
        let m: FromPage =
            serde_json::from_str(r#"{"type":"run-check","id":2,"n":500,"seed":9}"#).unwrap();
        assert_eq!(
            m,
            FromPage::RunCheck {
                id: Some(2),
                n: Some(500),
                seed: Some(9)
            }
        );
        assert!(serde_json::from_str::<FromPage>(r#"{"type":"bogus"}"#).is_err());
    }

    #[test]
    fn the_token_travels_only_when_the_page_has_one() {
        let m: FromPage =
            serde_json::from_str(r#"{"type":"open-url","id":1,"url":"http://h/data/a.ply"}"#)
                .unwrap();
        assert_eq!(
            m,
            FromPage::OpenUrl {
                id: 1,
                url: "http://h/data/a.ply".into(),
                token: None
            }
        );
        assert!(serde_json::to_value(&m).unwrap().get("token").is_none());
        let m = FromPage::OpenUrl {
            id: 1,
            url: "http://h/data/a.ply".into(),
            token: Some("k".into()),
        };
        let v = serde_json::to_value(&m).unwrap();
        assert_eq!(v["token"], "k");
        assert_eq!(serde_json::from_value::<FromPage>(v).unwrap(), m);
    }

    #[test]
    fn unnamed_adapters_get_the_browser_name() {
        let info = BrowserAdapterInfo {
            vendor: "google".into(),
            architecture: "swiftshader".into(),
            ..Default::default()
        };
        assert_eq!(info.display_name().as_deref(), Some("google swiftshader"));
        assert_eq!(BrowserAdapterInfo::default().display_name(), None);
        let described = BrowserAdapterInfo {
            description: "NVIDIA GeForce RTX 4090".into(),
            ..info.clone()
        };
        assert_eq!(
            described.display_name().as_deref(),
            Some("NVIDIA GeForce RTX 4090")
        );
    }

    #[test]
    fn worker_messages_are_tagged_by_type() {
        let msg = ToPage::Error {
            id: Some(3),
            stage: Stage::Projection,
            message: "x".into(),
            detail: None,
        };
        let v = serde_json::to_value(&msg).unwrap();
        assert_eq!(v["type"], "error");
        assert_eq!(v["stage"], "projection");
        assert_eq!(v["id"], 3);
    }
}
