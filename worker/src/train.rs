//! Training in the worker: a dataset from dropped files, a `silvr pack` archive or a URL, loaded by the
//! core's loader through [`silvr_core::source::Files`], then the core's job API ([`silvr_core::job`]) —
//! the same steps, renders, export and uncertainty pass as `silvr train`. Steps are chained on the
//! worker's event loop: every GPU readback is awaited and each step ends by yielding to the loop, so the
//! page's pause / resume / stop messages are handled between steps and nothing blocks.

use std::cell::RefCell;
use std::collections::BTreeMap;
use std::rc::Rc;

use silvr_core::job::{FinishOptions, MemSink, Observer, Progress, TrainJob};
use silvr_core::pointcloud::read_ply_bytes;
use silvr_core::source::{Files, MAX_BYTES};
use silvr_core::train::data::{LoadOptions, TrainData};
use silvr_core::train::{Backend, Mode};
use silvr_core::uncertainty::UncertaintyConfig;
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;

use crate::js::{
    fetch_bytes, get, js_text, post, post_bytes, read_stream, scope, sleep_ms, url_file_name,
};
use crate::view::is_fetchable;
use crate::{SavedRun, ToPage, TrainAction, TrainResult, TrainSettings};
use silvr_core::train::checkpoint::Checkpoint;
use std::path::Path;

/// Names in the origin-private file system (folder `silvr-train`): the run's dataset as an archive,
/// its latest checkpoint (the native format) and what the page needs to offer resuming it.
const DATASET: &str = "dataset.tar";
const CHECKPOINT: &str = "checkpoint.ckpt";
const RUN: &str = "run.json";

/// What training needs from the rest of the worker (passed in, so training does not import the view):
/// the device, and a way to open the trained points in the view.
#[derive(Clone)]
pub(crate) struct Host {
    pub gpu: Rc<dyn Fn() -> silvr_core::gpu::Gpu>,
    pub open_points: OpenPoints,
}

/// (PLY bytes, name, source) → a layer of the view.
pub(crate) type OpenPoints = Rc<dyn Fn(&[u8], &str, &str)>;

/// The layer number the trained points take in the view (the page numbers its own sources from 0).
pub const TRAINED_LAYER: u32 = 1000;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Control {
    Running,
    Paused,
    Stopping,
}

/// The run in this worker (one at a time) and the last run's outputs.
#[derive(Default)]
struct Slot {
    control: Option<Control>,
    step: (u32, u32),
    outputs: BTreeMap<String, Vec<u8>>,
}

thread_local! {
    static SLOT: RefCell<Slot> = RefCell::new(Slot::default());
}

fn state(state: &str) {
    let (step, steps) = SLOT.with(|s| s.borrow().step);
    post(&ToPage::TrainState {
        state: state.into(),
        step,
        steps,
    });
}

fn fail(source: &str, message: impl Into<String>) {
    post(&ToPage::TrainError {
        source: source.into(),
        message: message.into(),
    });
}

/// Pause, resume or stop the run in progress.
pub(crate) fn control(action: TrainAction) {
    let now = SLOT.with(|s| {
        let mut s = s.borrow_mut();
        let c = s.control.as_mut()?;
        *c = match (action, *c) {
            (_, Control::Stopping) => Control::Stopping,
            (TrainAction::Pause, _) => Control::Paused,
            (TrainAction::Resume, _) => Control::Running,
            (TrainAction::Stop, _) => Control::Stopping,
        };
        Some(*c)
    });
    // `paused` and `running` are announced by the training loop once they hold (a step in flight
    // finishes first), so the page never sees a step after `paused`.
    match now {
        None => fail("training", "no training run is in progress"),
        Some(Control::Stopping) => state("stopping"),
        Some(_) => {}
    }
}

/// One of the last run's outputs, as a download.
pub(crate) fn download(id: u32, name: &str) {
    let bytes = SLOT.with(|s| s.borrow().outputs.get(name).cloned());
    match bytes {
        Some(b) => post_bytes(id, name.rsplit('/').next().unwrap_or(name), &b),
        None => fail(
            name,
            "no such output: the run has not finished, or it did not write this file",
        ),
    }
}

/// Dropped or chosen files (`paths`: each file's path within what was dropped) → a training run.
pub(crate) async fn train_files(
    host: Host,
    id: u32,
    files: Vec<(String, web_sys::File)>,
    checkpoint: Option<web_sys::File>,
    settings: TrainSettings,
) {
    let name = match files.as_slice() {
        [(p, _)] => p.clone(),
        [(p, _), ..] => p.split('/').next().unwrap_or("dropped files").to_string(),
        [] => return fail("dropped files", "no file was given"),
    };
    let total: f64 = files.iter().map(|(_, f)| f.size()).sum();
    if total > MAX_BYTES as f64 {
        return fail(
            &name,
            format!(
                "{:.0} MiB is more than the {} GiB the studio trains from",
                total / 1048576.0,
                MAX_BYTES >> 30
            ),
        );
    }
    state("loading");
    let mut out = Files::new(name.clone());
    for (path, file) in &files {
        let bytes = match read_stream(file.stream(), Some(file.size()), id, path).await {
            Ok(b) => b,
            Err(e) => return fail(path, e),
        };
        let is_tar = files.len() == 1 && path.to_ascii_lowercase().ends_with(".tar");
        if is_tar {
            match Files::from_tar(path, bytes) {
                Ok(f) => out = f,
                Err(e) => return fail(path, e.to_string()),
            }
        } else if let Err(e) = out.insert(path, bytes) {
            return fail(path, e.to_string());
        }
    }
    let resume = match checkpoint {
        Some(f) => match read_stream(f.stream(), Some(f.size()), id, &f.name()).await {
            Ok(b) => Some(b),
            Err(e) => return fail(&f.name(), e),
        },
        None => None,
    };
    run(host, id, out, settings, resume).await
}

/// A dataset archive fetched over http(s) → a training run (`token`: the page's access token, see
/// [`fetch_bytes`]).
pub(crate) async fn train_url(
    host: Host,
    id: u32,
    url: String,
    settings: TrainSettings,
    token: Option<String>,
) {
    if !is_fetchable(&url) {
        return fail(&url, "only http: and https: URLs are opened");
    }
    state("loading");
    let bytes = match fetch_bytes(&url, id, token.as_deref()).await {
        Ok(b) => b,
        Err(e) => return fail(&url, e),
    };
    let name = url_file_name(&url, "submap.tar");
    match Files::from_tar(&name, bytes) {
        Ok(files) => run(host, id, files, settings, None).await,
        Err(e) => fail(&url, e.to_string()),
    }
}

async fn run(host: Host, id: u32, files: Files, settings: TrainSettings, resume: Option<Vec<u8>>) {
    if let Err(e) = settings.validate() {
        return fail("the training settings", e);
    }
    let busy = SLOT.with(|s| {
        let mut s = s.borrow_mut();
        if s.control.is_some() {
            return true;
        }
        s.control = Some(Control::Running);
        s.step = (0, settings.job.steps);
        s.outputs.clear();
        false
    });
    if busy {
        return fail(
            &files.name,
            "a training run is already in progress: stop it first",
        );
    }
    let result = run_inner(&host, id, files, &settings, resume).await;
    SLOT.with(|s| s.borrow_mut().control = None);
    match result {
        Ok(()) => state("done"),
        Err((source, message)) => {
            fail(&source, message);
            state("failed");
        }
    }
}

type Failure = (String, String);

async fn run_inner(
    host: &Host,
    id: u32,
    files: Files,
    settings: &TrainSettings,
    resume: Option<Vec<u8>>,
) -> Result<(), Failure> {
    let name = files.name.clone();
    let resume_bytes = resume;
    let files = files
        .rooted_at_transforms()
        .map_err(|e| (name.clone(), e.to_string()))?;
    let checkpoint = match &resume_bytes {
        Some(bytes) => Some(
            Checkpoint::from_bytes(bytes, Path::new("the checkpoint"))
                .map_err(|e| ("the checkpoint".to_string(), e.to_string()))?,
        ),
        None => None,
    };
    let opts = LoadOptions {
        downscale: settings.downscale,
        skip_lidar: settings.job.mode == Mode::Vision,
    };
    let data = TrainData::load_from(&files, "transforms.json", &opts)
        .map_err(|e| (name.clone(), e.to_string()))?;
    // The dataset is kept in the origin-private file system beside the checkpoints, so a reload can
    // resume without the user dropping the files again.
    // An archive is written back as it was read (no second copy of it in memory).
    let saved = opfs::write(DATASET, &files.as_tar()).await;
    if let Err(e) = &saved {
        log::warn!("the dataset could not be kept for resuming after a reload: {e}");
    }
    drop(files);
    post(&ToPage::TrainLoaded {
        id,
        source: name.clone(),
        images: data.images.len(),
        train: data.train.len(),
        held_out: data.val.len(),
        lidar: data.has_lidar(),
        skipped: data.skipped.clone(),
    });
    let has_val = !data.val.is_empty();
    // A camera-only capture (a nerfstudio folder) trains vision-only whatever the form said.
    let mut spec = settings.job.clone();
    if spec.mode != Mode::Vision && !data.has_lidar() {
        spec.mode = Mode::Vision;
        log::info!("no lidar depth in {name}: training vision-only");
    }
    let gpu = (host.gpu)();
    let adapter = gpu.report().to_string();
    if let Some(bytes) = resume_bytes {
        // The run's own checkpoint until it saves a newer one (what a device loss resumes from).
        SLOT.with(|s| {
            s.borrow_mut()
                .outputs
                .insert("checkpoint.ckpt".into(), bytes)
        });
    }
    let mut job = match checkpoint {
        Some(ck) => {
            if ck.header.step >= settings.job.steps {
                return Err((
                    "the checkpoint".into(),
                    format!(
                        "it is at step {}; ask for more steps than that to continue it",
                        ck.header.step
                    ),
                ));
            }
            TrainJob::resume(data, ck, Backend::Wgpu(gpu), settings.job.steps)
        }
        None => TrainJob::new(data, &spec, Backend::Wgpu(gpu)),
    }
    .map_err(|e| ("training".to_string(), e.to_string()))?;
    SLOT.with(|s| s.borrow_mut().step = (job.trainer.step, settings.job.steps));
    state("running");
    let save = |job: &mut TrainJob| {
        let meta = SavedRun {
            source: name.clone(),
            settings: settings.clone(),
            step: job.trainer.step,
        };
        (meta, saved.is_ok())
    };
    let mut paused = false;
    let mut recoveries = 0;
    while !job.done() {
        match SLOT.with(|s| s.borrow().control) {
            Some(Control::Stopping) | None => break,
            Some(Control::Paused) => {
                if !paused {
                    paused = true;
                    let (meta, keep) = save(&mut job);
                    checkpoint_to_opfs(&mut job, meta, keep).await?;
                    state("paused");
                }
                sleep_ms(100).await;
                continue;
            }
            Some(Control::Running) => {
                if paused {
                    paused = false;
                    state("running");
                }
            }
        }
        let r = match job.step().await {
            Ok(r) => r,
            // A lost device (a driver reset, a GPU process crash, the tab's device destroyed): a new
            // device, and the run goes on from its last checkpoint.
            Err(e) if recoveries < MAX_RECOVERIES && device_problem(&e) => {
                recoveries += 1;
                job = recover(job, settings, &e.to_string()).await?;
                continue;
            }
            Err(e) => return Err(("training".to_string(), e.to_string())),
        };
        SLOT.with(|s| s.borrow_mut().step = (r.step, r.steps));
        post(&ToPage::TrainStep { report: r });
        if settings.checkpoint_every > 0 && r.step % settings.checkpoint_every == 0 && !job.done() {
            let (meta, keep) = save(&mut job);
            checkpoint_to_opfs(&mut job, meta, keep).await?;
        }
        if has_val && settings.view_every > 0 && r.step % settings.view_every == 0 && !job.done() {
            post_view(&mut job).await?;
        }
        // Let the page's messages (pause, stop, view changes) in between steps.
        sleep_ms(0).await;
    }
    state("finishing");
    let observer: Observer = Rc::new(RefCell::new(|p: Progress| {
        post(&ToPage::TrainProgress {
            stage: p.stage.into(),
            done: p.done,
            total: p.total,
            eta_s: p.eta_s(),
        })
    }));
    let uncertainty = (settings.uncertainty_batches > 0).then(|| UncertaintyConfig {
        batches: settings.uncertainty_batches,
        rays_per_batch: settings.uncertainty_rays,
        ..Default::default()
    });
    let opts = FinishOptions {
        dataset: name.clone(),
        render_views: Some(settings.render_views),
        view_normals: false,
        export_rays: settings.export_rays,
        export_depth: Default::default(),
        uncertainty,
        adapter,
    };
    let mut sink = MemSink::default();
    let summary = job
        .finish(&opts, &mut sink, observer)
        .await
        .map_err(|e| ("after training".to_string(), e.to_string()))?;
    // The held-out view at the end (the render `finish` made), with its uncertainty image when the pass ran.
    if let (Some(&i), Some(score)) = (job.trainer.data.val.first(), summary.heldout.first()) {
        let im = &job.trainer.data.images[i];
        let stem = silvr_core::job::stem(&im.name);
        if let Some(rgb) = sink.0.get(&format!("renders/{stem}_rgb.png")) {
            let photo = silvr_core::dataset::png_rgb(im.width, im.height, &im.rgb);
            let unc = sink.0.get(&format!("renders/{stem}_uncertainty.png"));
            send_view(job.trainer.step, score, rgb, &photo, unc.map(Vec::as_slice));
        }
    }
    let mut result = TrainResult {
        mode: summary.mode.to_string(),
        steps: summary.steps,
        train_s: summary.train_s,
        rays_per_s: summary.train_rays_per_s,
        backend: summary.backend.to_string(),
        heldout_psnr: summary.heldout_psnr_mean,
        heldout_ssim: summary.heldout_ssim_mean,
        held_out_views: summary.heldout.len(),
        points: summary.exported,
        kept: summary.uncertainty.as_ref().map(|u| u.kept),
        threshold: summary.uncertainty.as_ref().map(|u| u.threshold),
        log_std_quantiles: Vec::new(),
        uncertainty: summary.uncertainty_brief.clone(),
        outputs: sink.0.keys().cloned().collect(),
    };
    if let Some(bytes) = sink.0.get("points.ply") {
        if let Ok(cloud) = read_ply_bytes(bytes, "points.ply") {
            if let Some(v) = cloud.scalar("log_std_combined") {
                result.log_std_quantiles = quantiles(v, &[0.05, 0.25, 0.5, 0.75, 0.95]);
            }
        }
        let source = format!("trained: {name}");
        (host.open_points)(bytes, "points.ply", &source);
    }
    SLOT.with(|s| s.borrow_mut().outputs = std::mem::take(&mut sink.0));
    // A finished run is not offered for resuming; its outputs stay downloadable.
    opfs::clear().await;
    post(&ToPage::TrainDone { summary: result });
    Ok(())
}

/// Nearest-rank quantiles of the finite values.
fn quantiles(v: &[f32], qs: &[f64]) -> Vec<f32> {
    let mut v: Vec<f32> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return Vec::new();
    }
    v.sort_by(f32::total_cmp);
    qs.iter()
        .map(|q| v[((v.len() - 1) as f64 * q).round() as usize])
        .collect()
}

/// Renders the first held-out view and sends it beside its photo.
async fn post_view(job: &mut TrainJob) -> Result<(), Failure> {
    let h = job
        .held_out(0, false)
        .await
        .map_err(|e| ("held-out render".to_string(), e.to_string()))?;
    send_view(job.trainer.step, &h.score, &h.rgb_png, &h.photo_png, None);
    Ok(())
}

/// A held-out view to the page (PNG bytes as `Uint8Array`s, not serde arrays of numbers).
fn send_view(
    step: u32,
    score: &silvr_core::train::export::ViewScore,
    render: &[u8],
    photo: &[u8],
    uncertainty: Option<&[u8]>,
) {
    let msg = js_sys::Object::new();
    let set = |k: &str, v: &JsValue| {
        js_sys::Reflect::set(&msg, &JsValue::from_str(k), v).ok();
    };
    let bytes = |b: &[u8]| {
        let a = js_sys::Uint8Array::new_with_length(b.len() as u32);
        a.copy_from(b);
        a
    };
    set("type", &"train-view".into());
    set("step", &JsValue::from(step));
    set("name", &score.name.clone().into());
    set("psnr", &JsValue::from(score.psnr));
    set("render", &bytes(render));
    set("photo", &bytes(photo));
    if let Some(u) = uncertainty {
        set("uncertainty", &bytes(u));
    }
    if let Err(e) = scope().post_message(&msg) {
        web_sys::console::error_2(&"silvr worker: postMessage failed".into(), &e);
    }
}

/// Saves the run's checkpoint (and what resuming needs) in the origin-private file system, keeps it as
/// the `checkpoint.ckpt` download, and tells the page. A failed save is reported, and training goes on.
async fn checkpoint_to_opfs(job: &mut TrainJob, meta: SavedRun, keep: bool) -> Result<(), Failure> {
    let bytes = job
        .checkpoint_bytes()
        .await
        .map_err(|e| ("checkpoint".to_string(), e.to_string()))?;
    let step = meta.step;
    if keep {
        let meta_json = serde_json_bytes(&meta);
        let r = match opfs::write(CHECKPOINT, &bytes).await {
            Ok(()) => opfs::write(RUN, &meta_json).await,
            Err(e) => Err(e),
        };
        match r {
            Ok(()) => post(&ToPage::TrainSaved { step }),
            Err(e) => fail(
                "checkpoint",
                format!("could not be saved in the browser's storage ({e}); training goes on"),
            ),
        }
    }
    SLOT.with(|s| {
        s.borrow_mut()
            .outputs
            .insert("checkpoint.ckpt".into(), bytes)
    });
    Ok(())
}

fn serde_json_bytes(meta: &SavedRun) -> Vec<u8> {
    let v = serde_wasm_bindgen::to_value(meta).unwrap_or(JsValue::NULL);
    js_sys::JSON::stringify(&v)
        .ok()
        .and_then(|s| s.as_string())
        .unwrap_or_default()
        .into_bytes()
}

/// Tells the page whether a run is saved in this origin.
pub(crate) async fn query_saved() {
    post(&ToPage::TrainSavedRun {
        run: saved_run().await,
    });
}

async fn saved_run() -> Option<SavedRun> {
    let bytes = opfs::read(RUN).await.ok().flatten()?;
    let text = String::from_utf8(bytes).ok()?;
    let v = js_sys::JSON::parse(&text).ok()?;
    let run: SavedRun = serde_wasm_bindgen::from_value(v).ok()?;
    // Only a run whose checkpoint and dataset are both there.
    let has = |n: &'static str| async move { opfs::read(n).await.ok().flatten().is_some() };
    (has(CHECKPOINT).await && has(DATASET).await).then_some(run)
}

/// Resumes the run saved in this origin (after a reload, or a new worker).
pub(crate) async fn resume_saved(host: Host, id: u32) {
    let Some(meta) = saved_run().await else {
        return fail("the saved run", "no run is saved in this browser's storage");
    };
    state("loading");
    let (dataset, ck) = match (opfs::read(DATASET).await, opfs::read(CHECKPOINT).await) {
        (Ok(Some(d)), Ok(Some(c))) => (d, c),
        (Err(e), _) | (_, Err(e)) => return fail("the saved run", e),
        _ => return fail("the saved run", "its dataset or checkpoint is gone"),
    };
    match Files::from_tar(&meta.source, dataset) {
        Ok(files) => run(host, id, files, meta.settings, Some(ck)).await,
        Err(e) => fail("the saved run", e.to_string()),
    }
}

/// The origin-private file system, through its JS API (called by name: web-sys gates these types
/// behind unstable flags). Writes go through `createWritable`, which commits on `close`: a reload or a
/// crash mid-write leaves the previous file.
mod opfs {
    use super::*;

    async fn call(obj: &JsValue, method: &str, args: &[JsValue]) -> Result<JsValue, String> {
        let f: js_sys::Function = get(obj, method)
            .dyn_into()
            .map_err(|_| format!("{method} is not available"))?;
        let r = match args {
            [] => f.call0(obj),
            [a] => f.call1(obj, a),
            [a, b] => f.call2(obj, a, b),
            _ => unreachable!("at most two arguments"),
        }
        .map_err(|e| js_text(&e))?;
        if r.has_type::<js_sys::Promise>() {
            wasm_bindgen_futures::JsFuture::from(js_sys::Promise::from(r))
                .await
                .map_err(|e| js_text(&e))
        } else {
            Ok(r)
        }
    }

    async fn dir() -> Result<JsValue, String> {
        let storage = get(&get(&js_sys::global(), "navigator"), "storage");
        if storage.is_undefined() {
            return Err("this browser gives workers no storage (navigator.storage)".into());
        }
        let root = call(&storage, "getDirectory", &[]).await?;
        let opts = js_sys::Object::new();
        js_sys::Reflect::set(&opts, &"create".into(), &true.into()).ok();
        call(
            &root,
            "getDirectoryHandle",
            &["silvr-train".into(), opts.into()],
        )
        .await
    }

    pub async fn write(name: &str, bytes: &[u8]) -> Result<(), String> {
        let d = dir().await?;
        let opts = js_sys::Object::new();
        js_sys::Reflect::set(&opts, &"create".into(), &true.into()).ok();
        let h = call(&d, "getFileHandle", &[name.into(), opts.into()]).await?;
        let w = call(&h, "createWritable", &[]).await?;
        let a = js_sys::Uint8Array::new_with_length(bytes.len() as u32);
        a.copy_from(bytes);
        if let Err(e) = call(&w, "write", &[a.into()]).await {
            let _ = call(&w, "abort", &[]).await;
            return Err(e);
        }
        call(&w, "close", &[]).await.map(|_| ())
    }

    /// `Ok(None)` when the file does not exist.
    pub async fn read(name: &str) -> Result<Option<Vec<u8>>, String> {
        let d = dir().await?;
        let Ok(h) = call(&d, "getFileHandle", &[name.into()]).await else {
            return Ok(None);
        };
        let file = call(&h, "getFile", &[]).await?;
        let buf = call(&file, "arrayBuffer", &[]).await?;
        Ok(Some(js_sys::Uint8Array::new(&buf).to_vec()))
    }

    pub async fn clear() {
        if let Ok(d) = dir().await {
            for n in [RUN, CHECKPOINT, DATASET] {
                let _ = call(&d, "removeEntry", &[n.into()]).await;
            }
        }
    }
}

/// Device losses a run survives before it gives up.
const MAX_RECOVERIES: u32 = 3;

/// Errors a new device may cure (not bad input or a diverged loss).
fn device_problem(e: &silvr_core::job::JobError) -> bool {
    use silvr_core::gpu::GpuError;
    matches!(
        e,
        silvr_core::job::JobError::Gpu(
            GpuError::DeviceLost { .. } | GpuError::Readback(_) | GpuError::Kernel { .. }
        )
    )
}

/// A new device and the run continued from its last checkpoint (from the start when it has none).
async fn recover(job: TrainJob, settings: &TrainSettings, why: &str) -> Result<TrainJob, Failure> {
    let lost_at = job.trainer.step;
    // The mode the run really trains (camera-only data trains vision-only).
    let spec = silvr_core::job::JobSpec {
        mode: job.trainer.config.mode,
        ..settings.job.clone()
    };
    let data = job.trainer.data;
    let gpu = silvr_core::gpu::Gpu::new(silvr_core::gpu::GpuOptions::default())
        .await
        .map_err(|e| {
            (
                "training".to_string(),
                format!("the GPU device was lost at step {lost_at} ({why}) and no new one could be opened: {e}"),
            )
        })?;
    let ck = SLOT.with(|s| s.borrow().outputs.get("checkpoint.ckpt").cloned());
    let from = match &ck {
        Some(b) => Checkpoint::from_bytes(b, Path::new("the last checkpoint"))
            .ok()
            .map(|c| (c.header.step, c)),
        None => None,
    };
    let (job, resumed) = match from {
        Some((step, c)) => (
            TrainJob::resume(data, c, Backend::Wgpu(gpu), settings.job.steps),
            format!("from the checkpoint at step {step}"),
        ),
        None => (
            TrainJob::new(data, &spec, Backend::Wgpu(gpu)),
            "from the start (no checkpoint was saved yet)".to_string(),
        ),
    };
    let job = job.map_err(|e| ("training".to_string(), e.to_string()))?;
    fail(
        "training",
        format!("the GPU device was lost at step {lost_at} ({why}); training goes on on a new device {resumed}"),
    );
    SLOT.with(|s| s.borrow_mut().step = (job.trainer.step, settings.job.steps));
    state("resumed");
    Ok(job)
}
