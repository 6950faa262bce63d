//! The page in the browser: DOM updates, the worker bridge and the drop zone.

use std::cell::RefCell;
use std::rc::Rc;

use serde::Serialize;
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;
use web_sys::{
    DragEvent, Element, ErrorEvent, Event, File, FileList, HtmlButtonElement, HtmlElement,
    HtmlInputElement, MessageEvent, Worker,
};

use crate::dom::{by_id, clear, document, listen, text_el};
use crate::protocol::{capitalize, describe_size, explain_error, group_digits};
use silvr_core::gpu::AdapterReport;
use silvr_core::lidar::project::SelfCheck;
use silvr_worker::{BrowserAdapterInfo, FromPage, Stage, ToPage};

const TITLE: &str = "SiLVR Studio";
/// Points of the self-check the "Run again" button asks for (the worker's startup check uses 4 000).
const RERUN_POINTS: usize = 20_000;

struct Page {
    doc: web_sys::Document,
    worker: Option<Worker>,
    /// Workers started so far; events of an older one are ignored.
    generation: u32,
    /// The current worker has reported its adapter (a failure after that is a crash, not a load error).
    worker_ready: bool,
    /// Checks asked for with the button so far (their ids are 1, 2, …).
    requested: u32,
    /// Projection results shown so far (startup one included).
    runs: u32,
}

type Shared = Rc<RefCell<Page>>;

pub fn start() {
    install_panic_hook();
    let doc = document();
    let page: Shared = Rc::new(RefCell::new(Page {
        doc: doc.clone(),
        worker: None,
        generation: 0,
        worker_ready: false,
        requested: 0,
        runs: 0,
    }));
    set_state(&doc, "loading", "Starting the engine worker…");
    setup_drop_zone(&doc);
    match start_worker(&page) {
        Ok(worker) => {
            crate::viewer::start(&worker);
            page.borrow_mut().worker = Some(worker);
            crate::train::start();
        }
        Err(e) => fail(
            &doc,
            &format!("Could not start the engine worker: {}", js_error_text(&e)),
        ),
    }
    if let Some(button) = by_id(&doc, "rerun").and_then(|e| e.dyn_into::<HtmlButtonElement>().ok())
    {
        button.set_text_content(Some(&format!(
            "Run again ({} points)",
            group_digits(RERUN_POINTS as u64)
        )));
        let page = page.clone();
        listen(&button, "click", move |_: Event| request_check(&page));
    }
}

fn start_worker(page: &Shared) -> Result<Worker, JsValue> {
    // trunk's loader shim for the `worker` binary (fixed, unhashed name next to index.html).
    let worker = Worker::new("./worker_loader.js")?;
    let generation = {
        let mut p = page.borrow_mut();
        p.generation += 1;
        p.worker_ready = false;
        p.generation
    };
    {
        let page = page.clone();
        let on_message = Closure::<dyn FnMut(MessageEvent)>::new(move |ev: MessageEvent| {
            if page.borrow().generation != generation {
                return;
            }
            let data = ev.data();
            // A download carries its bytes as a Uint8Array, read as such (not through serde).
            let kind = js_sys::Reflect::get(&data, &"type".into())
                .ok()
                .and_then(|t| t.as_string());
            if kind.as_deref() == Some("train-view") {
                crate::viewer::worker_listening();
                return crate::train::on_view(&data);
            }
            if kind.as_deref() == Some("download") {
                let get =
                    |k: &str| js_sys::Reflect::get(&data, &k.into()).unwrap_or(JsValue::UNDEFINED);
                let name = get("name")
                    .as_string()
                    .unwrap_or_else(|| "filtered.ply".into());
                match get("bytes").dyn_into::<js_sys::Uint8Array>() {
                    Ok(bytes) => crate::viewer::on_download(&name, &bytes),
                    Err(_) => {
                        crate::viewer::on_view_error("the worker sent a download without bytes")
                    }
                }
                return;
            }
            match serde_wasm_bindgen::from_value::<ToPage>(ev.data()) {
                Ok(msg) => on_worker_message(&page, msg),
                Err(e) => web_sys::console::warn_2(
                    &format!("studio: unexpected worker message ({e})").into(),
                    &ev.data(),
                ),
            }
        });
        worker.set_onmessage(Some(on_message.as_ref().unchecked_ref()));
        on_message.forget();
    }
    {
        let doc = page.borrow().doc.clone();
        let page = page.clone();
        let on_error = Closure::<dyn FnMut(ErrorEvent)>::new(move |ev: ErrorEvent| {
            ev.prevent_default();
            if page.borrow().generation != generation {
                return;
            }
            // A worker that was running died (a panic traps the wasm instance): start another.
            if page.borrow().worker_ready {
                let why = if ev.message().is_empty() {
                    "it stopped".to_string()
                } else {
                    ev.message()
                };
                return restart_worker(&page, &why);
            }
            let what = if ev.message().is_empty() {
                "the worker script could not be loaded (is worker_loader.js next to index.html?)"
                    .to_string()
            } else {
                ev.message()
            };
            fail(&doc, &format!("The engine worker failed: {what}"));
        });
        worker.set_onerror(Some(on_error.as_ref().unchecked_ref()));
        on_error.forget();
    }
    Ok(worker)
}

/// Workers started after crashes, at most: a worker that keeps crashing is a bug to report, not to loop on.
const MAX_RESTARTS: u32 = 3;

/// The worker crashed: say so, start a new one, hand it the view, and let the training card offer the
/// run saved in the browser's storage.
fn restart_worker(page: &Shared, why: &str) {
    let (doc, generation) = {
        let p = page.borrow();
        (p.doc.clone(), p.generation)
    };
    if let Some(old) = page.borrow_mut().worker.take() {
        old.terminate();
    }
    if generation > MAX_RESTARTS {
        return fail(
            &doc,
            &format!(
                "The engine worker crashed again ({why}); reload the page, and please report it."
            ),
        );
    }
    show_error(
        &doc,
        &format!(
            "The engine worker crashed ({why}). A new worker was started; a training run saved in this \
             browser can be resumed from its last checkpoint."
        ),
    );
    if let Some(e) = by_id(&doc, "error") {
        e.set_attribute("data-restarts", &generation.to_string())
            .ok();
    }
    set_state(&doc, "loading", "Starting a new engine worker…");
    match start_worker(page) {
        Ok(worker) => {
            crate::viewer::restart(&worker);
            page.borrow_mut().worker = Some(worker);
            crate::train::on_worker_restart();
        }
        Err(e) => fail(
            &doc,
            &format!("Could not start a new engine worker: {}", js_error_text(&e)),
        ),
    }
}

fn on_worker_message(page: &Shared, msg: ToPage) {
    let doc = page.borrow().doc.clone();
    crate::viewer::worker_listening();
    match msg {
        ToPage::Adapter { adapter, browser } => {
            page.borrow_mut().worker_ready = true;
            show_adapter(&doc, &adapter, browser.as_ref());
            set_state(
                &doc,
                "loading",
                "Checking the projection kernel against the CPU…",
            );
        }
        ToPage::Projection {
            id,
            seed,
            n,
            elapsed_ms,
            passed,
            check,
        } => {
            let runs = {
                let mut p = page.borrow_mut();
                p.runs += 1;
                p.runs
            };
            show_projection(&doc, &check, passed, n, seed, elapsed_ms, runs);
            set_button_enabled(&doc, true);
            let status = if passed {
                "Ready".to_string()
            } else {
                "Ready — the projection kernel disagrees with its CPU reference".to_string()
            };
            if id.is_none() {
                // The startup check: everything the page waits for has arrived.
                set_state(&doc, "ready", &status);
            } else if body_state(&doc).as_deref() != Some("error") {
                set_status(&doc, &status);
            }
        }
        ToPage::Progress {
            source,
            stage,
            loaded,
            total,
            ..
        } => crate::viewer::on_progress(&source, &stage, loaded, total),
        ToPage::Layer { layer, .. } => crate::viewer::on_layer(layer),
        ToPage::LoadError {
            source, message, ..
        } => crate::viewer::on_load_error(&source, &message),
        ToPage::Filter { counts } => crate::viewer::on_filter(counts),
        ToPage::TrainLoaded {
            source,
            images,
            train,
            held_out,
            lidar,
            skipped,
            ..
        } => crate::train::on_loaded(&source, images, train, held_out, lidar, &skipped),
        ToPage::TrainState { state, step, steps } => crate::train::on_state(&state, step, steps),
        ToPage::TrainStep { report } => crate::train::on_step(report),
        ToPage::TrainProgress {
            stage,
            done,
            total,
            eta_s,
        } => crate::train::on_progress(&stage, done, total, eta_s),
        ToPage::TrainDone { summary } => crate::train::on_done(summary),
        ToPage::TrainError { source, message } => crate::train::on_error(&source, &message),
        ToPage::TrainSaved { step } => crate::train::on_saved(step),
        ToPage::TrainSavedRun { run } => crate::train::on_saved_run(run),
        ToPage::Frame {
            n,
            ms,
            points,
            seq,
            draw,
        } => crate::viewer::on_frame(n, ms, points, seq, draw),
        ToPage::Bench {
            frames,
            ms_per_frame,
            points,
            draw,
            wasm_bytes,
            ..
        } => {
            if let Some(c) = by_id(&doc, "view") {
                c.set_attribute("data-bench-draw", draw.name()).ok();
                c.set_attribute("data-bench-wasm-bytes", &wasm_bytes.to_string())
                    .ok();
                c.set_attribute("data-bench-ms", &ms_per_frame.to_string())
                    .ok();
                c.set_attribute("data-bench-points", &points.to_string())
                    .ok();
                c.set_attribute("data-bench-frames", &frames.to_string())
                    .ok();
            }
        }
        ToPage::Error {
            stage: Stage::View,
            message,
            ..
        } => crate::viewer::on_view_error(&capitalize(&message)),
        ToPage::Error {
            stage: Stage::Panic,
            message,
            ..
        } if page.borrow().worker_ready => restart_worker(page, &message),
        ToPage::Error {
            id,
            stage,
            message,
            detail,
        } => {
            let mut text = explain_error(stage, &message);
            let fatal = id.is_none() || matches!(stage, Stage::Webgpu | Stage::Panic);
            if stage == Stage::Webgpu {
                if let Some(el) = by_id(&doc, "adapter") {
                    clear(&el);
                    el.set_attribute("data-error", "webgpu").ok();
                    el.append_child(&text_el(&doc, "p", "headline bad", "WebGPU unavailable"))
                        .ok();
                    el.append_child(&text_el(&doc, "p", "", &message)).ok();
                    if let Some(detail) = &detail {
                        el.append_child(&details(&doc, detail)).ok();
                    }
                }
                if let Some(el) = by_id(&doc, "projection") {
                    clear(&el);
                    el.append_child(&text_el(&doc, "p", "muted", "Not run: it needs WebGPU."))
                        .ok();
                }
            } else if let Some(detail) = &detail {
                text = format!("{text} ({detail})");
            }
            if fatal {
                fail(&doc, &text);
            } else {
                set_button_enabled(&doc, true);
                show_error(&doc, &text);
            }
        }
    }
}

fn request_check(page: &Shared) {
    let (worker, id) = {
        let mut p = page.borrow_mut();
        p.requested += 1;
        (p.worker.clone(), p.requested)
    };
    let Some(worker) = worker else { return };
    let doc = page.borrow().doc.clone();
    let msg = FromPage::RunCheck {
        id: Some(id),
        n: Some(RERUN_POINTS),
        // A new problem each time, reproducible from the id.
        seed: Some(1000 + id as u64),
    };
    match msg.serialize(&serde_wasm_bindgen::Serializer::json_compatible()) {
        Ok(v) => {
            if let Err(e) = worker.post_message(&v) {
                show_error(
                    &doc,
                    &format!("Could not message the worker: {}", js_error_text(&e)),
                );
                return;
            }
            set_button_enabled(&doc, false);
            set_status(&doc, "Running the projection check…");
        }
        Err(e) => show_error(&doc, &format!("Could not encode the request: {e}")),
    }
}

fn show_adapter(doc: &web_sys::Document, a: &AdapterReport, browser: Option<&BrowserAdapterInfo>) {
    let Some(el) = by_id(doc, "adapter") else {
        return;
    };
    clear(&el);
    el.set_attribute("data-name", &a.name).ok();
    el.set_attribute("data-software", if a.software { "true" } else { "false" })
        .ok();
    let head = doc.create_element("p").unwrap();
    head.set_class_name("headline");
    head.append_child(&text_el(doc, "span", "name", &a.name))
        .ok();
    let (badge_class, badge) = if a.software {
        ("badge soft", "software")
    } else {
        ("badge hard", "hardware")
    };
    head.append_child(&text_el(doc, "span", badge_class, badge))
        .ok();
    el.append_child(&head).ok();
    let mut rows = vec![
        ("Backend", a.backend.clone()),
        ("Device type", a.device_type.clone()),
    ];
    if let Some(summary) = browser.and_then(BrowserAdapterInfo::summary) {
        rows.push(("Vendor", summary));
    }
    let driver = format!("{} {}", a.driver, a.driver_info).trim().to_string();
    if !driver.is_empty() {
        rows.push(("Driver", driver));
    }
    if a.max_compute_invocations_per_workgroup > 0 {
        rows.push((
            "Workgroup size",
            format!("≤ {} invocations", a.max_compute_invocations_per_workgroup),
        ));
    }
    if a.max_storage_buffer_binding_size > 0 {
        rows.push((
            "Storage binding",
            format!(
                "≤ {:.0} MiB",
                a.max_storage_buffer_binding_size as f64 / (1024.0 * 1024.0)
            ),
        ));
    }
    el.append_child(&table(doc, &rows)).ok();
    if a.software {
        el.append_child(&text_el(
            doc,
            "p",
            "muted small",
            "A CPU rasteriser: results are exact, but large scenes will be slow.",
        ))
        .ok();
    }
}

fn show_projection(
    doc: &web_sys::Document,
    c: &SelfCheck,
    passed: bool,
    n: usize,
    seed: u64,
    elapsed_ms: f64,
    runs: u32,
) {
    let Some(el) = by_id(doc, "projection") else {
        return;
    };
    clear(&el);
    for (k, v) in [
        ("data-passed", passed.to_string()),
        ("data-mismatches", c.winner_mismatches.to_string()),
        ("data-filled", c.filled_pixels.to_string()),
        ("data-points", c.points.to_string()),
        ("data-runs", runs.to_string()),
    ] {
        el.set_attribute(k, &v).ok();
    }
    let verdict = if passed {
        text_el(
            doc,
            "p",
            "headline good",
            "✓ GPU kernel agrees with the CPU reference",
        )
    } else {
        text_el(
            doc,
            "p",
            "headline bad",
            "✗ GPU kernel disagrees with the CPU reference",
        )
    };
    el.append_child(&verdict).ok();
    let rows = [
        (
            "Points",
            format!("{} (seed {seed})", group_digits(n as u64)),
        ),
        (
            "Pixels filled",
            format!(
                "{} of {}",
                group_digits(c.filled_pixels as u64),
                group_digits(c.pixels as u64)
            ),
        ),
        (
            "Winner mismatches",
            group_digits(c.winner_mismatches as u64),
        ),
        ("Max uv error", format!("{:.1e} px", c.max_uv_error_px)),
        (
            "Max range error",
            format!("{:.1e} (relative)", c.max_range_rel_error),
        ),
        ("Time", format!("{elapsed_ms:.0} ms (GPU + CPU reference)")),
    ];
    el.append_child(&table(doc, &rows)).ok();
}

fn setup_drop_zone(doc: &web_sys::Document) {
    // A file dropped next to the zone must not make the browser navigate away from the studio.
    if let Some(body) = doc.body() {
        listen(&body, "dragover", |ev: Event| ev.prevent_default());
        listen(&body, "drop", |ev: Event| ev.prevent_default());
    }
    let Some(zone) = by_id(doc, "drop") else {
        return;
    };
    for name in ["dragenter", "dragover"] {
        let zone2 = zone.clone();
        listen(&zone, name, move |ev: DragEvent| {
            ev.prevent_default();
            ev.stop_propagation();
            if let Some(dt) = ev.data_transfer() {
                dt.set_drop_effect("copy");
            }
            zone2.class_list().add_1("over").ok();
        });
    }
    {
        let zone2 = zone.clone();
        listen(&zone, "dragleave", move |_: DragEvent| {
            zone2.class_list().remove_1("over").ok();
        });
    }
    {
        let zone2 = zone.clone();
        let doc = doc.clone();
        listen(&zone, "drop", move |ev: DragEvent| {
            ev.prevent_default();
            ev.stop_propagation();
            zone2.class_list().remove_1("over").ok();
            match ev.data_transfer().and_then(|dt| dt.files()) {
                Some(files) if files.length() > 0 => {
                    show_files(&doc, &files);
                    open_files(&files);
                }
                _ => show_error(
                    &doc,
                    "That drop held no file: drop a file from your computer.",
                ),
            }
        });
    }
    if let Some(input) =
        by_id(doc, "file-input").and_then(|e| e.dyn_into::<HtmlInputElement>().ok())
    {
        let doc = doc.clone();
        let input2 = input.clone();
        listen(&input, "change", move |_: Event| {
            if let Some(files) = input2.files() {
                if files.length() > 0 {
                    show_files(&doc, &files);
                    open_files(&files);
                }
            }
        });
    }
}

fn open_files(files: &FileList) {
    let files: Vec<File> = (0..files.length()).filter_map(|i| files.get(i)).collect();
    // A submap archive goes to the training card; point clouds to the view.
    let (archives, rest): (Vec<File>, Vec<File>) = files
        .into_iter()
        .partition(|f| f.name().to_ascii_lowercase().ends_with(".tar"));
    if let Some(a) = archives.into_iter().next() {
        crate::train::choose(vec![(a.name(), a)]);
    }
    if !rest.is_empty() {
        crate::viewer::open_files(&rest);
    }
}

fn show_files(doc: &web_sys::Document, files: &FileList) {
    let Some(el) = by_id(doc, "dropped") else {
        return;
    };
    clear(&el);
    let files: Vec<File> = (0..files.length()).filter_map(|i| files.get(i)).collect();
    let Some(first) = files.first() else { return };
    el.set_attribute("data-name", &first.name()).ok();
    el.set_attribute("data-bytes", &(first.size() as u64).to_string())
        .ok();
    el.set_attribute("data-count", &files.len().to_string())
        .ok();
    el.class_list().remove_1("muted").ok();
    let list = doc.create_element("ul").unwrap();
    list.set_class_name("files");
    for f in &files {
        let li = doc.create_element("li").unwrap();
        li.append_child(&text_el(doc, "span", "name", &f.name()))
            .ok();
        li.append_child(&text_el(
            doc,
            "span",
            "size",
            &describe_size(f.size() as u64),
        ))
        .ok();
        list.append_child(&li).ok();
    }
    el.append_child(&list).ok();
}

// ----- page-only DOM pieces -----

/// A collapsed `<details>` block with technical text.
fn details(doc: &web_sys::Document, text: &str) -> Element {
    let d = doc.create_element("details").unwrap();
    d.append_child(&text_el(doc, "summary", "muted small", "Details"))
        .ok();
    d.append_child(&text_el(doc, "p", "muted small detail", text))
        .ok();
    d
}

fn table(doc: &web_sys::Document, rows: &[(&str, String)]) -> Element {
    let dl = doc.create_element("dl").unwrap();
    for (k, v) in rows {
        dl.append_child(&text_el(doc, "dt", "", k)).ok();
        dl.append_child(&text_el(doc, "dd", "", v)).ok();
    }
    dl
}

fn body_state(doc: &web_sys::Document) -> Option<String> {
    doc.body().and_then(|b| b.get_attribute("data-state"))
}

fn set_state(doc: &web_sys::Document, state: &str, status: &str) {
    if body_state(doc).as_deref() == Some("error") {
        return; // errors stick
    }
    if let Some(body) = doc.body() {
        body.set_attribute("data-state", state).ok();
    }
    doc.set_title(&match state {
        "ready" => format!("{TITLE} — ready"),
        "error" => format!("{TITLE} — error"),
        _ => TITLE.to_string(),
    });
    set_status(doc, status);
}

fn set_status(doc: &web_sys::Document, text: &str) {
    if let Some(el) = by_id(doc, "status") {
        el.set_text_content(Some(text));
    }
}

fn set_button_enabled(doc: &web_sys::Document, enabled: bool) {
    if let Some(b) = by_id(doc, "rerun").and_then(|e| e.dyn_into::<HtmlButtonElement>().ok()) {
        b.set_disabled(!enabled);
    }
}

fn show_error(doc: &web_sys::Document, text: &str) {
    web_sys::console::error_1(&format!("studio: {text}").into());
    if let Some(el) = by_id(doc, "error").and_then(|e| e.dyn_into::<HtmlElement>().ok()) {
        el.set_text_content(Some(text));
        el.set_hidden(false);
    }
}

/// Shows an error that stops the studio and sets the `error` state.
fn fail(doc: &web_sys::Document, text: &str) {
    show_error(doc, text);
    set_state(doc, "error", "Error");
    set_button_enabled(doc, false);
}

fn js_error_text(e: &JsValue) -> String {
    e.dyn_ref::<js_sys::Error>()
        .map(|e| String::from(e.message()))
        .or_else(|| e.as_string())
        .unwrap_or_else(|| format!("{e:?}"))
}

fn install_panic_hook() {
    std::panic::set_hook(Box::new(|info| {
        let text = format!("The studio page crashed; reload it. Details: {info}");
        if let Some(doc) = web_sys::window().and_then(|w| w.document()) {
            fail(&doc, &text);
        } else {
            web_sys::console::error_1(&text.into());
        }
    }));
}
