//! The training card: choose a submap (a `silvr pack` archive or a dataset folder, or `?train=URL`), set
//! the run, and watch it train in the worker: step, losses, PSNR, rays/s and ETA, a live loss/PSNR chart,
//! a held-out view beside its photo every few hundred steps; pause, resume, stop; the result's points
//! open in the view, its outputs download.
//!
//! Query keys preset the form: `steps`, `rays`, `model`, `mode`, `downscale`, `export`, `views`, `uncertainty`,
//! `view-every`, `checkpoint-every`.
//!
//! For tests, `#train-status` carries `data-state` (`idle`, `ready`, `loading`, `running`, `paused`,
//! `stopping`, `finishing`, `done`, `failed`), `data-step`, `data-steps`, `data-loss`, `data-first-step` / `data-first-loss` (this session's first
//! step: after a resume, the checkpoint's step + 1), `data-saved-step`,
//! `data-loss-start` / `data-loss-recent` (means of the first and latest ten steps), `data-psnr`,
//! `data-rays-per-s`; `#train-result` the result as `data-result` (JSON); `#train-render`
//! the step of the view it shows (`data-step`); `#train-error` the last error.

use std::cell::RefCell;

use serde::Serialize;
use silvr_core::job::{JobSpec, StepReport};
use silvr_core::train::Mode;
use silvr_worker::{FromPage, TrainAction, TrainResult, TrainSettings};
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;
use web_sys::{
    CanvasRenderingContext2d, Event, File, HtmlButtonElement, HtmlCanvasElement, HtmlElement,
    HtmlImageElement, HtmlInputElement, HtmlSelectElement,
};

use crate::dom::{by_id, clear, document, listen, text_el};
use crate::protocol::{describe_size, group_digits};

#[derive(Default)]
struct Card {
    /// Files chosen (path within the choice, file).
    chosen: Vec<(String, File)>,
    history: Vec<StepReport>,
    last_draw: f64,
    state: String,
    next_id: u32,
    outputs: Vec<String>,
    /// A checkpoint to continue (`silvr train`'s or one downloaded from the studio).
    checkpoint: Option<File>,
    /// `?train=URL`, started once the worker says no saved run waits.
    pending_url: Option<String>,
}

thread_local! {
    static CARD: RefCell<Card> = RefCell::new(Card::default());
}

fn el<T: JsCast>(id: &str) -> Option<T> {
    by_id(&document(), id).and_then(|e| e.dyn_into::<T>().ok())
}

/// Wires the card up; starts a run at once when the page was opened with `?train=URL`.
pub fn start() {
    let doc = document();
    for id in ["train-file", "train-folder"] {
        if let Some(input) = el::<HtmlInputElement>(id) {
            let i2 = input.clone();
            listen(&input, "change", move |_: Event| {
                let Some(list) = i2.files() else { return };
                let files: Vec<(String, File)> = (0..list.length())
                    .filter_map(|k| list.get(k))
                    .map(|f| {
                        let rel = js_sys::Reflect::get(&f, &"webkitRelativePath".into())
                            .ok()
                            .and_then(|v| v.as_string())
                            .filter(|s| !s.is_empty())
                            .unwrap_or_else(|| f.name());
                        (rel, f)
                    })
                    .collect();
                choose(files);
            });
        }
    }
    if let Some(b) = el::<HtmlButtonElement>("train-start") {
        listen(&b, "click", |_: Event| start_run(None));
    }
    if let Some(b) = el::<HtmlButtonElement>("train-pause") {
        let b2 = b.clone();
        listen(&b, "click", move |_: Event| {
            let paused = CARD.with(|c| c.borrow().state == "paused");
            let action = if paused {
                TrainAction::Resume
            } else {
                TrainAction::Pause
            };
            b2.set_disabled(true);
            post(&FromPage::TrainControl { action });
        });
    }
    if let Some(b) = el::<HtmlButtonElement>("train-stop") {
        listen(&b, "click", |_: Event| {
            post(&FromPage::TrainControl {
                action: TrainAction::Stop,
            })
        });
    }
    if let Some(input) = el::<HtmlInputElement>("train-checkpoint") {
        let i2 = input.clone();
        listen(&input, "change", move |_: Event| {
            let f = i2.files().and_then(|l| l.get(0));
            CARD.with(|c| c.borrow_mut().checkpoint = f);
        });
    }
    if let Some(b) = el::<HtmlButtonElement>("train-resume") {
        listen(&b, "click", |_: Event| resume_saved());
    }
    if let Some(b) = el::<HtmlButtonElement>("train-save") {
        listen(&b, "click", |_: Event| {
            let id = next_id();
            post(&FromPage::TrainDownload {
                id,
                name: "checkpoint.ckpt".into(),
            });
        });
    }
    wire_drop();
    // Tests of the crash recovery: `silvr-debug-panic` on the document makes the worker panic.
    listen(&doc, "silvr-debug-panic", |_: Event| {
        post(&FromPage::DebugPanic)
    });
    let url = query_train_url();
    CARD.with(|c| c.borrow_mut().pending_url = url);
    // A run saved before a reload is offered first; `?train=` starts once the worker says there is none.
    post(&FromPage::TrainQuerySaved);
}

/// A new worker replaced a crashed one: the run in it is gone; offer the saved one.
pub fn on_worker_restart() {
    CARD.with(|c| c.borrow_mut().history.clear());
    status(
        "failed",
        "The worker running the training stopped; a new one was started.",
    );
    post(&FromPage::TrainQuerySaved);
}

fn next_id() -> u32 {
    CARD.with(|c| {
        let mut c = c.borrow_mut();
        c.next_id += 1;
        c.next_id
    })
}

/// The worker's answer to `train-query-saved`.
pub fn on_saved_run(run: Option<silvr_worker::SavedRun>) {
    let pending = CARD.with(|c| c.borrow_mut().pending_url.take());
    match run {
        Some(r) => {
            if let Some(b) = el::<HtmlButtonElement>("train-resume") {
                b.set_text_content(Some(&format!(
                    "Resume {} at step {} of {}",
                    r.source, r.step, r.settings.job.steps
                )));
                b.set_hidden(false);
                b.set_disabled(false);
                b.set_attribute("data-step", &r.step.to_string()).ok();
            }
            status(
                "saved",
                &format!(
                    "A run of {} was saved at step {}: resume it, or choose a submap to start over.",
                    r.source, r.step
                ),
            );
        }
        None => {
            if let Some(url) = pending {
                start_run(Some(url));
            }
        }
    }
}

fn resume_saved() {
    CARD.with(|c| c.borrow_mut().history.clear());
    if let Some(b) = el::<HtmlButtonElement>("train-resume") {
        b.set_disabled(true);
        b.set_hidden(true);
    }
    draw_chart(true);
    status("loading", "Reading the saved run…");
    post(&FromPage::TrainResumeSaved { id: next_id() });
}

/// A checkpoint was saved in the browser's storage.
pub fn on_saved(step: u32) {
    if let Some(s) = el::<HtmlElement>("train-status") {
        s.set_attribute("data-saved-step", &step.to_string()).ok();
    }
    if let Some(n) = el::<HtmlElement>("train-saved") {
        n.set_text_content(Some(&format!(
            "Checkpoint saved in this browser at step {step}: a reload offers to resume from it."
        )));
    }
}

/// Drops on the training card: an archive, dataset files, or a whole folder (walked through the
/// browser's file-system entries, so its files keep their paths).
fn wire_drop() {
    let Some(card) = el::<HtmlElement>("train-card") else {
        return;
    };
    for name in ["dragenter", "dragover"] {
        let c2 = card.clone();
        listen(&card, name, move |ev: web_sys::DragEvent| {
            ev.prevent_default();
            ev.stop_propagation();
            c2.class_list().add_1("over").ok();
        });
    }
    {
        let c2 = card.clone();
        listen(&card, "dragleave", move |_: web_sys::DragEvent| {
            c2.class_list().remove_1("over").ok();
        });
    }
    let c2 = card.clone();
    listen(&card, "drop", move |ev: web_sys::DragEvent| {
        ev.prevent_default();
        ev.stop_propagation();
        c2.class_list().remove_1("over").ok();
        let Some(dt) = ev.data_transfer() else { return };
        // Entries must be taken while the event is dispatched; walking them can wait.
        let items = js_sys::Reflect::get(&dt, &"items".into()).unwrap_or(JsValue::UNDEFINED);
        let n = js_sys::Reflect::get(&items, &"length".into())
            .ok()
            .and_then(|v| v.as_f64())
            .unwrap_or(0.0) as u32;
        let mut entries = Vec::new();
        for i in 0..n {
            let item = js_sys::Reflect::get(&items, &i.into()).unwrap_or(JsValue::UNDEFINED);
            if let Ok(e) = call(&item, "webkitGetAsEntry", &[]) {
                if !e.is_null() && !e.is_undefined() {
                    entries.push(e);
                }
            }
        }
        if entries.is_empty() {
            let files: Vec<(String, File)> = dt
                .files()
                .map(|l| (0..l.length()).filter_map(|k| l.get(k)).collect::<Vec<_>>())
                .unwrap_or_default()
                .into_iter()
                .map(|f| (f.name(), f))
                .collect();
            if files.is_empty() {
                return error("That drop held no file or folder.");
            }
            return choose(files);
        }
        status("loading", "Reading the dropped folder…");
        wasm_bindgen_futures::spawn_local(async move {
            let mut files = Vec::new();
            for e in entries {
                if let Err(e) = walk(e, &mut files).await {
                    status("failed", "The dropped folder could not be read.");
                    return error(&format!("Reading the drop: {e}"));
                }
            }
            choose(files);
        });
    });
}

fn call(obj: &JsValue, method: &str, args: &[JsValue]) -> Result<JsValue, JsValue> {
    let f: js_sys::Function = js_sys::Reflect::get(obj, &method.into())?.dyn_into()?;
    match args {
        [] => f.call0(obj),
        [a] => f.call1(obj, a),
        [a, b] => f.call2(obj, a, b),
        _ => Err("too many arguments".into()),
    }
}

/// A callback-style entry method (`file`, `readEntries`) as a future.
async fn callback(obj: &JsValue, method: &str) -> Result<JsValue, String> {
    let promise = js_sys::Promise::new(&mut |resolve, reject| {
        if let Err(e) = call(obj, method, &[resolve.into(), reject.clone().into()]) {
            let _ = reject.call1(&JsValue::NULL, &e);
        }
    });
    wasm_bindgen_futures::JsFuture::from(promise)
        .await
        .map_err(|e| format!("{e:?}"))
}

/// Collects the files under a dropped entry with their paths (`capture/images/0001.jpg`); at most
/// 100 000 files.
async fn walk(root: JsValue, out: &mut Vec<(String, File)>) -> Result<(), String> {
    let mut stack = vec![root];
    while let Some(e) = stack.pop() {
        let get = |k: &str| js_sys::Reflect::get(&e, &k.into()).unwrap_or(JsValue::UNDEFINED);
        if get("isFile").as_bool() == Some(true) {
            let path = get("fullPath").as_string().unwrap_or_default();
            let f: File = callback(&e, "file")
                .await?
                .dyn_into()
                .map_err(|_| "not a file")?;
            out.push((path.trim_start_matches('/').to_string(), f));
            if out.len() > 100_000 {
                return Err("more than 100 000 files: drop the dataset folder itself".into());
            }
        } else if get("isDirectory").as_bool() == Some(true) {
            let reader = call(&e, "createReader", &[]).map_err(|e| format!("{e:?}"))?;
            // `readEntries` gives a folder's entries in batches until an empty one.
            loop {
                let batch = js_sys::Array::from(&callback(&reader, "readEntries").await?);
                if batch.length() == 0 {
                    break;
                }
                stack.extend(batch.iter());
            }
        }
    }
    Ok(())
}

/// `?train=URL` (plus `steps=`, `rays=`, `model=`, `mode=`, `uncertainty=` to preset the form).
fn query_train_url() -> Option<String> {
    let search = web_sys::window()?.location().search().ok()?;
    let mut url = None;
    for part in search.trim_start_matches('?').split('&') {
        let Some((k, v)) = part.split_once('=') else {
            continue;
        };
        let Some(v) = silvr_worker::view::decode(&v.replace('+', " ")) else {
            continue;
        };
        let field = match k {
            "train" => {
                url = Some(v);
                continue;
            }
            "steps" => "train-steps",
            "rays" => "train-rays",
            "uncertainty" => "train-unc",
            "view-every" => "train-view-every",
            "downscale" => "train-downscale",
            "checkpoint-every" => "train-ckpt-every",
            "export" => "train-export",
            "views" => "train-views",
            "model" => "train-model",
            "mode" => "train-mode",
            _ => continue,
        };
        if let Some(i) = el::<HtmlInputElement>(field) {
            i.set_value(&v);
        } else if let Some(s) = el::<HtmlSelectElement>(field) {
            s.set_value(&v);
        }
    }
    url
}

/// A dataset chosen or dropped (also a `.tar` dropped on the page's main drop zone).
pub fn choose(files: Vec<(String, File)>) {
    let bytes: f64 = files.iter().map(|(_, f)| f.size()).sum();
    let what = match files.as_slice() {
        [] => return,
        [(p, _)] => p.clone(),
        [(p, _), ..] => format!(
            "{} ({} files)",
            p.split('/').next().unwrap_or("folder"),
            files.len()
        ),
    };
    CARD.with(|c| c.borrow_mut().chosen = files);
    status(
        "ready",
        &format!(
            "Chosen: {what}, {}. Set the run and press Train.",
            describe_size(bytes as u64)
        ),
    );
    enable("train-start", true);
}

fn value(id: &str) -> String {
    el::<HtmlInputElement>(id)
        .map(|i| i.value())
        .or_else(|| el::<HtmlSelectElement>(id).map(|s| s.value()))
        .unwrap_or_default()
}

fn settings() -> Result<TrainSettings, String> {
    let num = |id: &str, what: &str| -> Result<u64, String> {
        value(id)
            .trim()
            .parse::<u64>()
            .map_err(|_| format!("{what} must be a whole number"))
    };
    let mode: Mode = value("train-mode").parse()?;
    let s = TrainSettings {
        job: JobSpec {
            mode,
            model: value("train-model"),
            steps: num("train-steps", "Steps")?.min(u32::MAX as u64) as u32,
            rays: num("train-rays", "Rays per batch")? as usize,
            seed: 1,
            depth_sigma: None,
        },
        checkpoint_every: num("train-ckpt-every", "Checkpoint every")?.min(u32::MAX as u64) as u32,
        downscale: num("train-downscale", "Downscale")?.min(u32::MAX as u64) as u32,
        view_every: num("train-view-every", "Held-out view every")?.min(u32::MAX as u64) as u32,
        export_rays: num("train-export", "Export rays")? as usize,
        render_views: num("train-views", "Held-out views")? as usize,
        uncertainty_batches: num("train-unc", "Uncertainty batches")? as usize,
        uncertainty_rays: 1024,
    };
    s.validate()?;
    Ok(s)
}

fn start_run(url: Option<String>) {
    let s = match settings() {
        Ok(s) => s,
        Err(e) => return error(&e),
    };
    let id = CARD.with(|c| {
        let mut c = c.borrow_mut();
        c.history.clear();
        c.outputs.clear();
        c.next_id += 1;
        c.next_id
    });
    if let Some(r) = el::<HtmlElement>("train-result") {
        clear(&r);
        r.remove_attribute("data-result").ok();
    }
    if let Some(e) = el::<HtmlElement>("train-error") {
        e.set_hidden(true);
    }
    draw_chart(true);
    enable("train-start", false);
    match url {
        Some(url) => {
            // A relative link (`?train=data/submap.tar`) is relative to the studio's page.
            let base = web_sys::window().and_then(|w| w.location().href().ok());
            let url = base
                .and_then(|b| web_sys::Url::new_with_base(&url, &b).ok())
                .map(|u| u.href())
                .unwrap_or(url);
            status("loading", &format!("Fetching {url}…"));
            post(&FromPage::TrainUrl {
                id,
                url,
                settings: s,
                token: crate::dom::page_token(),
            });
        }
        None => {
            let chosen = CARD.with(|c| c.borrow().chosen.clone());
            if chosen.is_empty() {
                enable("train-start", true);
                return error(
                    "Choose a dataset first: an archive from `silvr pack`, or a dataset folder.",
                );
            }
            status("loading", "Reading the dataset…");
            let msg = js_sys::Object::new();
            let set = |k: &str, v: &JsValue| {
                js_sys::Reflect::set(&msg, &JsValue::from_str(k), v).ok();
            };
            set("type", &"train-files".into());
            set("id", &JsValue::from(id));
            let files = js_sys::Array::new();
            let paths = js_sys::Array::new();
            for (p, f) in &chosen {
                files.push(f);
                paths.push(&JsValue::from_str(p));
            }
            set("files", &files);
            set("paths", &paths);
            if let Some(ck) = CARD.with(|c| c.borrow().checkpoint.clone()) {
                set("checkpoint", &ck);
            }
            match s.serialize(&serde_wasm_bindgen::Serializer::json_compatible()) {
                Ok(v) => set("settings", &v),
                Err(e) => return error(&format!("Could not encode the settings: {e}")),
            }
            crate::viewer::send_raw(msg.into());
        }
    }
}

fn post(msg: &FromPage) {
    match msg.serialize(&serde_wasm_bindgen::Serializer::json_compatible()) {
        Ok(v) => crate::viewer::send_raw(v),
        Err(e) => error(&format!("Could not encode a message: {e}")),
    }
}

fn enable(id: &str, on: bool) {
    if let Some(b) = el::<HtmlButtonElement>(id) {
        b.set_disabled(!on);
    }
}

fn status(state: &str, text: &str) {
    CARD.with(|c| c.borrow_mut().state = state.to_string());
    if let Some(s) = el::<HtmlElement>("train-status") {
        s.set_attribute("data-state", state).ok();
        s.set_text_content(Some(text));
    }
    let running = matches!(state, "running" | "paused");
    enable("train-pause", running);
    enable("train-stop", running);
    enable("train-save", state == "paused");
    if let Some(b) = el::<HtmlButtonElement>("train-pause") {
        b.set_text_content(Some(if state == "paused" { "Resume" } else { "Pause" }));
    }
    if matches!(state, "done" | "failed") {
        let chosen = CARD.with(|c| !c.borrow().chosen.is_empty());
        enable("train-start", chosen);
        if let Some(p) = el::<HtmlElement>("train-progress") {
            p.set_hidden(true);
        }
    }
}

fn error(text: &str) {
    if let Some(e) = el::<HtmlElement>("train-error") {
        e.set_text_content(Some(text));
        e.set_hidden(false);
    }
}

/// A training message from the worker.
pub fn on_loaded(
    source: &str,
    images: usize,
    train: usize,
    held_out: usize,
    lidar: bool,
    skipped: &[String],
) {
    let mut text = format!(
        "Loaded {source}: {images} images ({train} train, {held_out} held out), {}.",
        if lidar {
            "with lidar"
        } else {
            "camera only: training vision-only"
        }
    );
    if !skipped.is_empty() {
        text.push_str(&format!(
            " Skipped {}: {}",
            skipped.len(),
            skipped.join("; ")
        ));
    }
    status("running", &text);
}

pub fn on_state(state: &str, step: u32, steps: u32) {
    let text = match state {
        "loading" => "Reading the dataset…".to_string(),
        "running" => format!("Training: step {step} of {steps}…"),
        "paused" => format!("Paused at step {step} of {steps}."),
        "stopping" => format!("Stopping after step {step}…"),
        "finishing" => format!(
            "Trained {step} steps: rendering the held-out views, exporting points, computing uncertainty…"
        ),
        "done" => return status("done", &done_text()),
        "failed" => "The run stopped; see the message below.".to_string(),
        // After a device loss: the run goes on from its checkpoint, the chart with it.
        "resumed" => {
            CARD.with(|c| c.borrow_mut().history.clear());
            return status("running", &format!("Training resumed at step {step} of {steps}…"));
        }
        other => other.to_string(),
    };
    status(state, &text);
}

fn done_text() -> String {
    el::<HtmlElement>("train-result")
        .and_then(|r| r.get_attribute("data-summary"))
        .unwrap_or_else(|| "Done.".into())
}

pub fn on_step(r: StepReport) {
    // Means of the first and the latest ten steps: one step's loss is noisy (its batch).
    let (first, start, recent) = CARD.with(|c| {
        let mut c = c.borrow_mut();
        c.history.push(r);
        let h = &c.history;
        let mean = |s: &[StepReport]| s.iter().map(|r| r.loss).sum::<f64>() / s.len().max(1) as f64;
        (
            h[0],
            mean(&h[..h.len().min(10)]),
            mean(&h[h.len().saturating_sub(10)..]),
        )
    });
    if let Some(s) = el::<HtmlElement>("train-status") {
        let set = |k: &str, v: String| {
            s.set_attribute(k, &v).ok();
        };
        set("data-step", r.step.to_string());
        set("data-steps", r.steps.to_string());
        set("data-loss", r.loss.to_string());
        set("data-first-loss", first.loss.to_string());
        set("data-first-step", first.step.to_string());
        set("data-loss-start", start.to_string());
        set("data-loss-recent", recent.to_string());
        set("data-psnr", r.psnr.to_string());
        set("data-rays-per-s", r.rays_per_s.to_string());
        let state = CARD.with(|c| c.borrow().state.clone());
        if state == "running" {
            s.set_text_content(Some(&format!(
                "Step {} of {} · loss {:.4} · PSNR {:.2} dB · {} rays/s · ETA {}",
                r.step,
                r.steps,
                r.loss,
                r.psnr,
                group_digits(r.rays_per_s.round() as u64),
                eta(r.eta_s)
            )));
        }
    }
    draw_chart(false);
}

fn eta(s: f64) -> String {
    if !s.is_finite() {
        return "—".into();
    }
    let s = s.round() as u64;
    if s >= 3600 {
        format!("{} h {:02} min", s / 3600, s / 60 % 60)
    } else if s >= 60 {
        format!("{} min {:02} s", s / 60, s % 60)
    } else {
        format!("{s} s")
    }
}

pub fn on_progress(stage: &str, done: usize, total: usize, eta_s: f64) {
    if let Some(p) = el::<HtmlElement>("train-progress") {
        p.set_hidden(false);
        if let Some(bar) = p.query_selector("progress").ok().flatten() {
            bar.set_attribute("value", &(done as f64 / total.max(1) as f64).to_string())
                .ok();
        }
        if let Some(span) = p.query_selector("span").ok().flatten() {
            span.set_text_content(Some(&format!(
                "{stage}: {} of {} · ETA {}",
                group_digits(done as u64),
                group_digits(total as u64),
                eta(eta_s)
            )));
        }
    }
}

pub fn on_error(source: &str, message: &str) {
    error(&format!("{source}: {message}"));
    let state = CARD.with(|c| c.borrow().state.clone());
    if matches!(state.as_str(), "loading" | "ready") {
        status(
            "failed",
            "The dataset could not be trained; see the message below.",
        );
    }
}

pub fn on_done(r: TrainResult) {
    let doc = document();
    let Some(el_r) = el::<HtmlElement>("train-result") else {
        return;
    };
    clear(&el_r);
    let summary = format!(
        "Trained {} steps in {:.0} s ({} rays/s on {}): held-out PSNR {:.2} dB, SSIM {:.3} over {} views; {} points{}.",
        r.steps,
        r.train_s,
        group_digits(r.rays_per_s.round() as u64),
        r.backend,
        r.heldout_psnr,
        r.heldout_ssim,
        r.held_out_views,
        group_digits(r.points as u64),
        match (r.kept, r.threshold) {
            (Some(k), Some(t)) => format!(
                ", the uncertainty filter keeps {} (log10 σ ≤ {t:.2}); the points are open in the view",
                group_digits(k as u64)
            ),
            _ => "; the points are open in the view".into(),
        }
    );
    el_r.set_attribute("data-summary", &summary).ok();
    if let Ok(json) = serde_json_text(&r) {
        el_r.set_attribute("data-result", &json).ok();
    }
    el_r.append_child(&text_el(&doc, "p", "", &summary)).ok();
    let list = doc.create_element("p").unwrap();
    list.set_class_name("downloads");
    for name in r.outputs.iter().filter(|n| !n.starts_with("renders/")) {
        let b: HtmlButtonElement = doc.create_element("button").unwrap().unchecked_into();
        b.set_type("button");
        b.set_text_content(Some(&format!("Download {name}")));
        b.set_attribute("data-output", name).ok();
        let name = name.clone();
        listen(&b, "click", move |_: Event| {
            let id = CARD.with(|c| {
                let mut c = c.borrow_mut();
                c.next_id += 1;
                c.next_id
            });
            post(&FromPage::TrainDownload {
                id,
                name: name.clone(),
            });
        });
        list.append_child(&b).ok();
    }
    el_r.append_child(&list).ok();
    CARD.with(|c| c.borrow_mut().outputs = r.outputs.clone());
}

fn serde_json_text(r: &TrainResult) -> Result<String, JsValue> {
    let v = r
        .serialize(&serde_wasm_bindgen::Serializer::json_compatible())
        .map_err(|e| JsValue::from_str(&e.to_string()))?;
    js_sys::JSON::stringify(&v).map(String::from)
}

/// A held-out view (PNG bytes) beside its photo, and the uncertainty image at the end.
pub fn on_view(data: &JsValue) {
    let get = |k: &str| js_sys::Reflect::get(data, &k.into()).unwrap_or(JsValue::UNDEFINED);
    let step = get("step").as_f64().unwrap_or(0.0) as u32;
    let psnr = get("psnr").as_f64().unwrap_or(f64::NAN);
    let name = get("name").as_string().unwrap_or_default();
    for (key, id) in [
        ("render", "train-render"),
        ("photo", "train-photo"),
        ("uncertainty", "train-uncertainty"),
    ] {
        let Ok(bytes) = get(key).dyn_into::<js_sys::Uint8Array>() else {
            continue;
        };
        let Some(img) = el::<HtmlImageElement>(id) else {
            continue;
        };
        let parts = js_sys::Array::of1(&bytes);
        let opts = web_sys::BlobPropertyBag::new();
        opts.set_type("image/png");
        let Ok(blob) = web_sys::Blob::new_with_u8_array_sequence_and_options(&parts, &opts) else {
            continue;
        };
        let Ok(url) = web_sys::Url::create_object_url_with_blob(&blob) else {
            continue;
        };
        let old = img.src();
        if old.starts_with("blob:") {
            let _ = web_sys::Url::revoke_object_url(&old);
        }
        img.set_src(&url);
        img.set_hidden(false);
        img.set_attribute("data-step", &step.to_string()).ok();
        if let Some(fig) = img.parent_element() {
            fig.remove_attribute("hidden").ok();
        }
    }
    if let Some(c) = el::<HtmlElement>("train-view-caption") {
        c.set_text_content(Some(&format!(
            "{name} at step {step}: PSNR {psnr:.2} dB against its photo"
        )));
    }
}

/// The loss (log scale, left) and training PSNR (right) so far; redrawn at most 4 times a second.
fn draw_chart(force: bool) {
    let now = js_sys::Date::now();
    let due = CARD.with(|c| {
        let mut c = c.borrow_mut();
        let due = force || now - c.last_draw > 250.0;
        if due {
            c.last_draw = now;
        }
        due
    });
    if !due {
        return;
    }
    let Some(canvas) = el::<HtmlCanvasElement>("train-chart") else {
        return;
    };
    let Some(ctx) = canvas
        .get_context("2d")
        .ok()
        .flatten()
        .and_then(|c| c.dyn_into::<CanvasRenderingContext2d>().ok())
    else {
        return;
    };
    let (w, h) = (canvas.width() as f64, canvas.height() as f64);
    ctx.clear_rect(0.0, 0.0, w, h);
    CARD.with(|c| {
        let c = c.borrow();
        let hist = &c.history;
        let Some(last) = hist.last() else { return };
        let steps = last.steps.max(1) as f64;
        let (pad_l, pad_r, pad_t, pad_b) = (44.0, 44.0, 10.0, 20.0);
        let pw = w - pad_l - pad_r;
        let ph = h - pad_t - pad_b;
        let x = |step: u32| pad_l + pw * step as f64 / steps;
        // Smoothed series: a running mean over 10 steps, so the chart shows the trend.
        let smooth = |f: &dyn Fn(&StepReport) -> f64| -> Vec<(u32, f64)> {
            let mut out = Vec::with_capacity(hist.len());
            let mut acc = std::collections::VecDeque::new();
            let mut sum = 0.0;
            for r in hist {
                let v = f(r);
                if !v.is_finite() {
                    continue;
                }
                acc.push_back(v);
                sum += v;
                if acc.len() > 10 {
                    sum -= acc.pop_front().unwrap_or(0.0);
                }
                out.push((r.step, sum / acc.len() as f64));
            }
            out
        };
        let loss = smooth(&|r| r.loss.max(1e-6).log10());
        let psnr = smooth(&|r| r.psnr);
        let range = |v: &[(u32, f64)]| {
            let lo = v.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
            let hi = v.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max);
            if hi - lo < 1e-9 {
                (lo - 0.5, hi + 0.5)
            } else {
                (lo, hi)
            }
        };
        ctx.set_line_width(1.0);
        ctx.set_stroke_style_str("#8884");
        ctx.stroke_rect(pad_l, pad_t, pw, ph);
        ctx.set_font("11px sans-serif");
        for (series, colour, left) in [(&loss, "#e4572e", true), (&psnr, "#2e86de", false)] {
            if series.is_empty() {
                continue;
            }
            let (lo, hi) = range(series);
            let y = |v: f64| pad_t + ph * (1.0 - (v - lo) / (hi - lo));
            ctx.set_stroke_style_str(colour);
            ctx.set_line_width(1.5);
            ctx.begin_path();
            for (k, (s, v)) in series.iter().enumerate() {
                if k == 0 {
                    ctx.move_to(x(*s), y(*v));
                } else {
                    ctx.line_to(x(*s), y(*v));
                }
            }
            ctx.stroke();
            ctx.set_fill_style_str(colour);
            let label = |v: f64| {
                if left {
                    format!("{:.3}", 10f64.powf(v))
                } else {
                    format!("{v:.1} dB")
                }
            };
            let lx = if left { 2.0 } else { w - pad_r + 4.0 };
            ctx.fill_text(&label(hi), lx, pad_t + 10.0).ok();
            ctx.fill_text(&label(lo), lx, pad_t + ph).ok();
        }
        ctx.set_fill_style_str("#888");
        ctx.fill_text(
            &format!(
                "step {} of {} · loss (red, log) · PSNR (blue)",
                last.step, last.steps
            ),
            pad_l,
            h - 4.0,
        )
        .ok();
    });
}
