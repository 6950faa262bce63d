//! The view card: the canvas the worker draws into, the controls, the layers list, the share link.
//!
//! The page owns the view state ([`ViewState`], defined once in the worker crate with its link codec)
//! and the camera controls; on every change it sends the state to the worker (at most once per animation
//! frame) and rewrites the URL hash (keeping the query), so the address bar is always the share link —
//! but for `silvr serve`'s `?token=`, which the "Share link" button leaves out. The worker parses the
//! files, keeps the layers on its device and answers with layer descriptions, filter counts and frames.
//!
//! Test hooks: `#view[data-view-matrix]` (the camera's view-projection, comma-separated), `#view
//! [data-frames|data-draw]`, `#kept[data-kept|data-total|data-threshold]`, `#layers li[data-index]`,
//! `#view-messages li` (one per problem, naming the source).

use std::cell::RefCell;
use std::rc::Rc;

use glam::DVec3;
use serde::Serialize;
use silvr_core::viewer::Raster;
use silvr_worker::studio::{
    scalar_range, union_box, FilterCounts, LayerInfo, LAYER_COLOURS, MAX_LAYERS,
};
use silvr_worker::view::{is_fetchable, Camera, Colour, Nav, ViewState, BUDGET_RANGE, MAX_SOURCES};
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;
use web_sys::{
    Event, File, HtmlButtonElement, HtmlCanvasElement, HtmlInputElement, HtmlSelectElement,
    KeyboardEvent, PointerEvent, WheelEvent, Worker,
};

use crate::dom::{by_id, document, listen, page_token, text_el};
use crate::protocol::group_digits;

/// Steps of the threshold slider between the filter field's smallest and largest value.
const SLIDER_STEPS: f64 = 1000.0;

struct Viewer {
    worker: Worker,
    state: ViewState,
    layers: Vec<LayerInfo>,
    counts: Option<FilterCounts>,
    /// Layers opened from dropped files (they cannot be linked).
    local: Vec<u32>,
    /// Next layer number for a dropped file.
    next_local: u32,
    frame_pending: bool,
    hash_pending: bool,
    drag: Option<(f64, f64, bool)>,
    /// The camera was fitted by the studio, not set by a link or the user.
    auto_camera: bool,
    /// The canvas size the worker was last told (device pixels).
    size: (u32, u32),
    /// Views sent so far (`#view[data-seq]`); frames report the one they drew (`data-drawn-seq`).
    seq: u32,
    /// Messages held until the worker listens: a worker's wasm sets its message handler only after it
    /// has loaded, and messages that arrive before that are lost.
    outbox: Option<Vec<(JsValue, Option<js_sys::Array>)>>,
}

type Shared = Rc<RefCell<Viewer>>;

thread_local! {
    static VIEWER: RefCell<Option<Shared>> = const { RefCell::new(None) };
}

fn viewer() -> Option<Shared> {
    VIEWER.with(|v| v.borrow().clone())
}

/// Hands the canvas to the worker, reads the link, wires the controls.
pub fn start(worker: &Worker) {
    let doc = document();
    let (mut state, notes) = link_state();
    // `?url=` (repeatable) opens sources too, for links written by other tools.
    for url in query_urls() {
        if state.sources.len() < MAX_SOURCES && !state.sources.contains(&url) {
            if is_fetchable(&url) {
                state.sources.push(url);
            } else {
                message(
                    "bad",
                    &format!("{}: not an http(s) URL; not opened", short(&url)),
                );
            }
        }
    }
    for n in &notes {
        message("warn", &format!("Link: {n}"));
    }
    let v = Rc::new(RefCell::new(Viewer {
        worker: worker.clone(),
        next_local: state.sources.len() as u32,
        state,
        layers: Vec::new(),
        counts: None,
        local: Vec::new(),
        frame_pending: false,
        hash_pending: false,
        drag: None,
        auto_camera: false,
        size: (0, 0),
        seq: 0,
        outbox: Some(Vec::new()),
    }));
    VIEWER.with(|cell| *cell.borrow_mut() = Some(v.clone()));
    if let Some(canvas) = by_id(&doc, "view").and_then(|e| e.dyn_into::<HtmlCanvasElement>().ok()) {
        hand_canvas(&v, &canvas);
    }
    wire_controls(&v);
    show_controls(&v);
    let sources = v.borrow().state.sources.clone();
    for (i, url) in sources.iter().enumerate() {
        post(
            &v,
            &silvr_worker::FromPage::OpenUrl {
                id: i as u32,
                url: url.clone(),
                token: page_token(),
            },
        );
    }
    schedule(&v);
}

/// Transfers the canvas to the worker (its control can be handed over once) and wires the camera to it.
fn hand_canvas(v: &Shared, canvas: &HtmlCanvasElement) {
    let (w, h) = canvas_size(canvas);
    v.borrow_mut().size = (w, h);
    match canvas.transfer_control_to_offscreen() {
        Ok(off) => {
            let msg = js_sys::Object::new();
            set(&msg, "type", &"canvas".into());
            set(&msg, "canvas", &off);
            set(&msg, "width", &JsValue::from(w));
            set(&msg, "height", &JsValue::from(h));
            send(v, msg.into(), Some(js_sys::Array::of1(&off)));
        }
        Err(e) => message(
            "bad",
            &format!("This browser cannot hand the canvas to the worker (OffscreenCanvas): {e:?}"),
        ),
    }
    wire_camera(v, canvas);
}

/// After the worker died and a new one started: a fresh canvas (the old canvas's control went to the dead
/// worker and cannot be taken back) handed to the new worker, the linked sources opened again. Layers from
/// dropped files died with the worker: the user is told to drop them again.
pub fn restart(worker: &Worker) {
    let Some(v) = viewer() else { return };
    let dropped = {
        let mut b = v.borrow_mut();
        b.worker = worker.clone();
        let dropped = b.local.len();
        b.layers.clear();
        b.local.clear();
        b.counts = None;
        b.frame_pending = false;
        b.outbox = Some(Vec::new());
        dropped
    };
    let doc = document();
    if let Some(old) = by_id(&doc, "view") {
        let fresh = old
            .clone_node()
            .ok()
            .and_then(|n| n.dyn_into::<HtmlCanvasElement>().ok());
        if let Some(canvas) = fresh {
            old.replace_with_with_node_1(&canvas).ok();
            hand_canvas(&v, &canvas);
        }
    }
    if dropped > 0 {
        message(
            "warn",
            &format!(
                "{dropped} dropped file(s) were open in the worker that stopped: drop them again"
            ),
        );
    }
    show_layers(&v);
    let sources = v.borrow().state.sources.clone();
    for (i, url) in sources.iter().enumerate() {
        post(
            &v,
            &silvr_worker::FromPage::OpenUrl {
                id: i as u32,
                url: url.clone(),
                token: page_token(),
            },
        );
    }
    schedule(&v);
}

/// The view state in the address bar's hash (and the problems found in it).
fn link_state() -> (ViewState, Vec<String>) {
    let hash = web_sys::window()
        .and_then(|w| w.location().hash().ok())
        .unwrap_or_default();
    ViewState::from_hash(&hash)
}

fn query_urls() -> Vec<String> {
    let search = web_sys::window()
        .and_then(|w| w.location().search().ok())
        .unwrap_or_default();
    let mut out = Vec::new();
    for part in search.trim_start_matches('?').split('&') {
        if let Some(v) = part.strip_prefix("url=") {
            if let Some(u) = silvr_worker::view::decode(&v.replace('+', " ")) {
                out.push(u);
            }
        }
    }
    out.truncate(MAX_SOURCES);
    out
}

fn canvas_size(canvas: &HtmlCanvasElement) -> (u32, u32) {
    let dpr = web_sys::window()
        .map(|w| w.device_pixel_ratio())
        .unwrap_or(1.0)
        .clamp(0.5, 4.0);
    let w = (canvas.client_width().max(1) as f64 * dpr).round() as u32;
    let h = (canvas.client_height().max(1) as f64 * dpr).round() as u32;
    (w.clamp(1, 8192), h.clamp(1, 8192))
}

fn set(obj: &js_sys::Object, k: &str, v: &JsValue) {
    js_sys::Reflect::set(obj, &JsValue::from_str(k), v).ok();
}

fn post(v: &Shared, msg: &silvr_worker::FromPage) {
    match msg.serialize(&serde_wasm_bindgen::Serializer::json_compatible()) {
        Ok(value) => send(v, value, None),
        Err(e) => message("bad", &format!("Could not encode a message: {e}")),
    }
}

/// Posts to the worker, or holds the message until it listens.
fn send(v: &Shared, msg: JsValue, transfer: Option<js_sys::Array>) {
    let mut b = v.borrow_mut();
    if let Some(outbox) = b.outbox.as_mut() {
        outbox.push((msg, transfer));
        return;
    }
    let r = match &transfer {
        Some(t) => b.worker.post_message_with_transfer(&msg, t),
        None => b.worker.post_message(&msg),
    };
    drop(b);
    if let Err(e) = r {
        message("bad", &format!("Could not message the worker: {e:?}"));
    }
}

/// Posts a message built by another card (training) to the worker, held until it listens.
pub fn send_raw(msg: JsValue) {
    if let Some(v) = viewer() {
        send(&v, msg, None);
    }
}

/// The worker has spoken, so it listens: send what was held.
pub fn worker_listening() {
    let Some(v) = viewer() else { return };
    let held = v.borrow_mut().outbox.take();
    for (msg, transfer) in held.unwrap_or_default() {
        send(&v, msg, transfer);
    }
}

/// Opens dropped or chosen `.ply` and `.copc.laz` files as layers; other files are named and left alone.
pub fn open_files(files: &[File]) {
    let Some(v) = viewer() else { return };
    for f in files {
        let name = f.name();
        let lower = name.to_ascii_lowercase();
        if !(lower.ends_with(".ply") || lower.ends_with(".json") || lower.ends_with(".copc.laz")) {
            message(
                "warn",
                &format!(
                    "{}: not a .ply, .copc.laz or transforms.json; the view opens PLY and COPC maps and a dataset's cameras",
                    short(&name)
                ),
            );
            continue;
        }
        let id = {
            let mut b = v.borrow_mut();
            if b.layers.len() + 1 > MAX_LAYERS || b.next_local as usize >= MAX_SOURCES {
                drop(b);
                message(
                    "bad",
                    &format!(
                        "{}: the studio holds at most {MAX_LAYERS} layers",
                        short(&name)
                    ),
                );
                continue;
            }
            let id = b.next_local;
            b.next_local += 1;
            b.local.push(id);
            id
        };
        set_progress(Some(&format!("Reading {name}…")), None);
        let msg = js_sys::Object::new();
        set(&msg, "type", &"open-file".into());
        set(&msg, "id", &JsValue::from(id));
        set(&msg, "file", f);
        send(&v, msg.into(), None);
    }
}

// ----- messages from the worker -----

pub fn on_progress(source: &str, stage: &str, loaded: f64, total: Option<f64>) {
    let what = match stage {
        "parse" => "Parsing",
        "upload" => "Uploading",
        _ => "Loading",
    };
    let text = match total {
        Some(t) if t > 0.0 => format!("{what} {} — {:.0} %", short(source), 100.0 * loaded / t),
        _ => format!("{what} {} — {:.1} MiB", short(source), loaded / 1048576.0),
    };
    set_progress(Some(&text), total.map(|t| loaded / t.max(1.0)));
}

pub fn on_layer(layer: LayerInfo) {
    let Some(v) = viewer() else { return };
    set_progress(None, None);
    {
        let mut b = v.borrow_mut();
        b.layers.retain(|l| l.index != layer.index);
        b.layers.push(layer.clone());
        b.layers.sort_by_key(|l| l.index);
        // Until the user moves it (or a link set it), the camera frames everything open, whichever
        // file arrived first.
        if b.state.camera.is_none() || b.auto_camera {
            b.state.camera = fit(&b);
            b.auto_camera = true;
        }
    }
    if layer.stride > 1 {
        message(
            "warn",
            &format!(
                "{}: {} points, shown decimated to every {}th ({} points)",
                layer.name,
                group_digits(layer.total),
                layer.stride,
                group_digits(layer.points)
            ),
        );
    }
    show_layers(&v);
    show_controls(&v);
    schedule(&v);
}

pub fn on_load_error(source: &str, message_text: &str) {
    set_progress(None, None);
    message("bad", &format!("{}: {message_text}", short(source)));
}

pub fn on_filter(counts: FilterCounts) {
    let Some(v) = viewer() else { return };
    v.borrow_mut().counts = Some(counts);
    show_counts(&v);
}

pub fn on_frame(n: u32, ms: f64, points: u64, seq: u32, draw: Raster) {
    let doc = document();
    if let Some(c) = by_id(&doc, "view") {
        c.set_attribute("data-draw", draw.name()).ok();
        c.set_attribute("data-frames", &n.to_string()).ok();
        c.set_attribute("data-drawn-seq", &seq.to_string()).ok();
        c.set_attribute("data-drawn-points", &points.to_string())
            .ok();
    }
    if let Some(el) = by_id(&doc, "frame") {
        el.set_text_content(Some(&format!(
            "{} points drawn, last frame {ms:.1} ms on the GPU ({})",
            group_digits(points),
            match draw {
                Raster::Compute => "compute rasteriser",
                Raster::Quads => "instanced quads",
            }
        )));
    }
}

pub fn on_download(name: &str, bytes: &js_sys::Uint8Array) {
    let parts = js_sys::Array::of1(bytes);
    let opts = web_sys::BlobPropertyBag::new();
    opts.set_type("application/octet-stream");
    let Ok(blob) = web_sys::Blob::new_with_u8_array_sequence_and_options(&parts, &opts) else {
        return message("bad", "The download could not be prepared");
    };
    let Ok(url) = web_sys::Url::create_object_url_with_blob(&blob) else {
        return message("bad", "The download could not be prepared");
    };
    let doc = document();
    if let Ok(a) = doc.create_element("a") {
        let a: web_sys::HtmlAnchorElement = a.unchecked_into();
        a.set_href(&url);
        a.set_download(name);
        a.click();
    }
    let _ = web_sys::Url::revoke_object_url(&url);
    message(
        "ok",
        &format!(
            "Downloaded {name} ({} bytes)",
            group_digits(bytes.length() as u64)
        ),
    );
}

pub fn on_view_error(text: &str) {
    message("bad", text);
}

// ----- state → worker, hash, DOM -----

/// Sends the state at the next animation frame (once however many changes come before it) and rewrites
/// the hash shortly after the last change.
fn schedule(v: &Shared) {
    if v.borrow().frame_pending {
        return;
    }
    v.borrow_mut().frame_pending = true;
    set_view_attr("data-pending", "1");
    let v2 = v.clone();
    let cb = Closure::once_into_js(move || {
        {
            let mut b = v2.borrow_mut();
            b.frame_pending = false;
            // The state in force is exactly what its link restores (angles wrapped, ranges clamped).
            b.state.camera = b.state.camera.and_then(|c| c.clamped());
        }
        let (view, seq) = {
            let mut b = v2.borrow_mut();
            b.seq += 1;
            (b.state.clone(), b.seq)
        };
        post(&v2, &silvr_worker::FromPage::View { view, seq });
        set_view_attr("data-seq", &seq.to_string());
        set_view_attr("data-pending", "0");
        show_matrix(&v2);
        schedule_hash(&v2);
    });
    if let Some(w) = web_sys::window() {
        let _ = w.request_animation_frame(cb.unchecked_ref());
    }
}

fn set_view_attr(name: &str, value: &str) {
    if let Some(c) = by_id(&document(), "view") {
        c.set_attribute(name, value).ok();
    }
}

fn schedule_hash(v: &Shared) {
    if v.borrow().hash_pending {
        return;
    }
    v.borrow_mut().hash_pending = true;
    let v2 = v.clone();
    let cb = Closure::once_into_js(move || {
        v2.borrow_mut().hash_pending = false;
        let hash = v2.borrow().state.to_hash();
        if let Some(w) = web_sys::window() {
            if let Ok(h) = w.history() {
                // The query stays: `?token=` (a reload must still reach the data), `?url=`, `?train=`.
                let loc = w.location();
                let url = format!(
                    "{}{}{}",
                    loc.pathname().unwrap_or_else(|_| "/".into()),
                    loc.search().unwrap_or_default(),
                    hash
                );
                let _ = h.replace_state_with_url(&JsValue::NULL, "", Some(&url));
            }
        }
    });
    if let Some(w) = web_sys::window() {
        let _ = w.set_timeout_with_callback_and_timeout_and_arguments_0(cb.unchecked_ref(), 150);
    }
}

fn bounds(b: &Viewer) -> Option<([f64; 3], [f64; 3])> {
    union_box(b.layers.iter(), &b.state, |l| (l.min, l.max))
}

fn fit_bounds(b: &Viewer) -> Option<([f64; 3], [f64; 3])> {
    union_box(b.layers.iter(), &b.state, |l| (l.fit_min, l.fit_max))
}

fn fit(b: &Viewer) -> Option<Camera> {
    fit_bounds(b).map(|(lo, hi)| Camera::fit(lo, hi))
}

/// The camera's view-projection on the canvas, as the worker computes it (for tests and the curious).
fn show_matrix(v: &Shared) {
    let b = v.borrow();
    let doc = document();
    let Some(canvas) = by_id(&doc, "view").and_then(|e| e.dyn_into::<HtmlCanvasElement>().ok())
    else {
        return;
    };
    let (Some(cam), Some((lo, hi))) = (b.state.camera, bounds(&b)) else {
        return;
    };
    let radius = 0.5
        * (DVec3::from_array(hi) - DVec3::from_array(lo))
            .length()
            .max(1e-3);
    let m = cam.view_proj(canvas_size(&canvas), radius, DVec3::from_array(cam.target));
    let s: Vec<String> = m.to_cols_array().iter().map(|x| format!("{x}")).collect();
    canvas.set_attribute("data-view-matrix", &s.join(",")).ok();
}

fn message(kind: &str, text: &str) {
    let doc = document();
    if let Some(list) = by_id(&doc, "view-messages") {
        let li = text_el(&doc, "li", kind, text);
        list.append_child(&li).ok();
        // Keep the last 8.
        while list.child_element_count() > 8 {
            if let Some(first) = list.first_element_child() {
                first.remove();
            }
        }
    }
}

fn set_progress(text: Option<&str>, fraction: Option<f64>) {
    let doc = document();
    let Some(el) = by_id(&doc, "progress") else {
        return;
    };
    match text {
        None => {
            el.set_attribute("hidden", "").ok();
        }
        Some(t) => {
            el.remove_attribute("hidden").ok();
            if let Some(span) = el.query_selector("span").ok().flatten() {
                span.set_text_content(Some(t));
            }
            if let Some(p) = el.query_selector("progress").ok().flatten() {
                match fraction {
                    Some(f) => p.set_attribute("value", &format!("{:.4}", f.clamp(0.0, 1.0))),
                    None => p.remove_attribute("value"),
                }
                .ok();
            }
        }
    }
}

fn short(s: &str) -> String {
    let s: String = s.chars().filter(|c| !c.is_control()).collect();
    if s.chars().count() > 120 {
        format!("{}…", s.chars().take(119).collect::<String>())
    } else {
        s
    }
}

/// A std in metres for people: `10^v` m as mm, cm or m.
pub fn metres(v: f64) -> String {
    if !v.is_finite() {
        return "—".into();
    }
    let m = v.abs();
    let sign = if v < 0.0 { "-" } else { "" };
    if m < 0.01 {
        format!("{sign}{:.1} mm", m * 1e3)
    } else if m < 1.0 {
        format!("{sign}{:.1} cm", m * 1e2)
    } else {
        format!("{sign}{m:.2} m")
    }
}

fn is_log_std(field: &str) -> bool {
    field.starts_with("log_std")
}

/// A value of `field` for people: log-std fields as 10^v metres, the rest as metres.
fn value_text(field: &str, v: f64) -> String {
    if is_log_std(field) {
        metres(10f64.powf(v))
    } else {
        metres(v)
    }
}

/// The filter field's finite range over the visible layers: the slider's ends.
fn field_range(b: &Viewer, field: &str) -> Option<(f32, f32)> {
    scalar_range(b.layers.iter(), &b.state, field, |s| (s.min, s.max))
}

fn select(id: &str) -> Option<HtmlSelectElement> {
    by_id(&document(), id).and_then(|e| e.dyn_into().ok())
}

fn input(id: &str) -> Option<HtmlInputElement> {
    by_id(&document(), id).and_then(|e| e.dyn_into().ok())
}

fn button(id: &str) -> Option<HtmlButtonElement> {
    by_id(&document(), id).and_then(|e| e.dyn_into().ok())
}

/// Puts the state into the controls (after a link was read, or a layer changed the ranges).
fn show_controls(v: &Shared) {
    let b = v.borrow();
    let s = &b.state;
    if let Some(sel) = select("colour") {
        sel.set_value(match &s.colour {
            Colour::Rgb => "rgb",
            Colour::Layer => "layer",
            Colour::Field(f) => f,
        });
    }
    if let Some(sel) = select("filter-field") {
        sel.set_value(&s.filter);
    }
    if let Some(i) = input("size") {
        i.set_value(&s.point_size.to_string());
    }
    if let Some(sel) = select("background") {
        sel.set_value(if s.dark { "dark" } else { "light" });
    }
    if let Some(sel) = select("nav") {
        sel.set_value(match s.nav {
            Nav::Orbit => "orbit",
            Nav::Fly => "fly",
        });
    }
    if let Some(sel) = select("draw") {
        sel.set_value(s.draw.name());
    }
    if let Some(sel) = select("budget") {
        let value = s.budget.map(|n| n.to_string()).unwrap_or_default();
        sel.set_value(&value);
        // A link's budget that is not one of the choices becomes one.
        if sel.value() != value {
            if let Ok(o) = web_sys::HtmlOptionElement::new_with_text_and_value(
                &format!("{} (link)", group_digits(s.budget.unwrap_or(0))),
                &value,
            ) {
                sel.add_with_html_option_element(&o).ok();
                sel.set_value(&value);
            }
        }
    }
    drop(b);
    show_counts(v);
    show_legend(v);
}

/// The threshold slider, its label and the kept count.
fn show_counts(v: &Shared) {
    let b = v.borrow();
    let doc = document();
    let range = field_range(&b, &b.state.filter);
    let threshold = b
        .state
        .threshold
        .or(b.counts.as_ref().and_then(|c| c.threshold));
    if let Some(slider) = input("threshold") {
        slider.set_disabled(range.is_none());
        if let (Some((lo, hi)), Some(t)) = (range, threshold) {
            let pos = if hi > lo {
                ((t - lo) as f64 / (hi - lo) as f64 * SLIDER_STEPS).clamp(0.0, SLIDER_STEPS)
            } else {
                SLIDER_STEPS
            };
            slider.set_value(&format!("{}", pos.round()));
        }
    }
    if let Some(bt) = button("threshold-default") {
        bt.set_disabled(b.state.threshold.is_none());
    }
    if let Some(el) = by_id(&doc, "threshold-label") {
        el.set_text_content(Some(&match threshold {
            Some(t) => format!(
                "{}{}",
                value_text(&b.state.filter, t as f64),
                if b.state.threshold.is_none() {
                    " (default: Tukey's fence)"
                } else {
                    ""
                }
            ),
            None => "—".into(),
        }));
    }
    if let Some(el) = by_id(&doc, "kept") {
        match &b.counts {
            Some(c) if c.total > 0 && c.field == b.state.filter => {
                el.set_text_content(Some(&format!(
                    "kept {} of {} points ({:.1} %)",
                    group_digits(c.kept),
                    group_digits(c.total),
                    100.0 * c.kept as f64 / c.total as f64
                )));
                el.set_attribute("data-kept", &c.kept.to_string()).ok();
                el.set_attribute("data-total", &c.total.to_string()).ok();
                if let Some(t) = c.threshold {
                    el.set_attribute("data-threshold", &t.to_string()).ok();
                }
            }
            _ => {
                el.set_text_content(Some(if b.layers.is_empty() {
                    "No reconstruction open."
                } else {
                    "No layer has this uncertainty."
                }));
                el.remove_attribute("data-kept").ok();
                el.remove_attribute("data-total").ok();
            }
        }
    }
    if let Some(bt) = button("download") {
        let has = b.layers.iter().any(|l| {
            !b.state.hidden.contains(&l.index) && l.scalars.iter().any(|s| s.name == b.state.filter)
        });
        bt.set_disabled(!has);
    }
}

/// The colour map's legend, in metres.
fn show_legend(v: &Shared) {
    let b = v.borrow();
    let doc = document();
    let Some(el) = by_id(&doc, "legend") else {
        return;
    };
    let Colour::Field(field) = &b.state.colour else {
        el.set_attribute("hidden", "").ok();
        return;
    };
    // The worker's colour range (1st-99th percentiles over the visible layers, unconstrained points
    // apart), by the same function.
    let (lo, hi) = scalar_range(b.layers.iter(), &b.state, field, |s| (s.p01, s.p99))
        .unwrap_or((f32::INFINITY, f32::NEG_INFINITY));
    while let Some(c) = el.first_child() {
        el.remove_child(&c).ok();
    }
    el.remove_attribute("hidden").ok();
    if lo > hi {
        el.append_child(&text_el(&doc, "span", "", &format!("No layer has {field}")))
            .ok();
        return;
    }
    let stops: Vec<String> = (0..=10)
        .map(|i| {
            let [r, g, bl] = silvr_core::viewer::turbo(i as f32 / 10.0);
            format!(
                "rgb({},{},{}) {}%",
                (r * 255.0) as u8,
                (g * 255.0) as u8,
                (bl * 255.0) as u8,
                i * 10
            )
        })
        .collect();
    let title = if is_log_std(field) {
        format!("{field}: σ in metres (the field's posterior and the ray's spread, calibrated on held-out lidar)")
    } else {
        format!("{field}: distance to ground truth")
    };
    el.append_child(&text_el(&doc, "div", "", &title)).ok();
    let bar = text_el(&doc, "div", "bar", "");
    bar.set_attribute(
        "style",
        &format!(
            "background: linear-gradient(to right, {})",
            stops.join(", ")
        ),
    )
    .ok();
    el.append_child(&bar).ok();
    let ends = text_el(&doc, "div", "ends", "");
    ends.append_child(&text_el(&doc, "span", "", &value_text(field, lo as f64)))
        .ok();
    ends.append_child(&text_el(&doc, "span", "", &value_text(field, hi as f64)))
        .ok();
    el.append_child(&ends).ok();
    el.set_attribute("data-lo", &lo.to_string()).ok();
    el.set_attribute("data-hi", &hi.to_string()).ok();
    // Points that read the prior are not a large σ but no measurement at all: said apart, in their own
    // colour (`viewer::UNCONSTRAINED_COLOUR`).
    let (count, at) = b
        .layers
        .iter()
        .filter(|l| !b.state.hidden.contains(&l.index))
        .filter_map(|l| l.scalars.iter().find(|s| &s.name == field))
        .fold((0u64, None), |(n, at), s| {
            (n + s.unconstrained, at.or(s.unconstrained_at))
        });
    if let Some(at) = at {
        let [r, g, bl] = silvr_core::viewer::UNCONSTRAINED_COLOUR.map(|c| (c * 255.0) as u8);
        let row = text_el(&doc, "div", "unconstrained", "");
        let swatch = text_el(&doc, "span", "swatch", "");
        swatch
            .set_attribute("style", &format!("background: rgb({r},{g},{bl})"))
            .ok();
        row.append_child(&swatch).ok();
        row.append_child(&text_el(
            &doc,
            "span",
            "",
            &format!(
                " unconstrained (σ ≥ {}, no observation beyond the prior): {count} points",
                value_text(field, at as f64)
            ),
        ))
        .ok();
        el.append_child(&row).ok();
        el.set_attribute("data-unconstrained", &count.to_string())
            .ok();
    }
}

fn show_layers(v: &Shared) {
    let b = v.borrow();
    let doc = document();
    let Some(list) = by_id(&doc, "layers") else {
        return;
    };
    while let Some(c) = list.first_child() {
        list.remove_child(&c).ok();
    }
    for l in &b.layers {
        let li = text_el(&doc, "li", "", "");
        li.set_attribute("data-index", &l.index.to_string()).ok();
        li.set_attribute("data-points", &l.points.to_string()).ok();
        li.set_attribute("data-total", &l.total.to_string()).ok();
        if let Some(lod) = &l.lod {
            li.set_attribute("data-budget", &lod.budget.to_string())
                .ok();
            li.set_attribute("data-nodes", &lod.nodes.to_string()).ok();
            li.set_attribute("data-pending", &lod.pending.to_string())
                .ok();
            if let Some(k) = lod.summary_kept {
                li.set_attribute("data-summary-kept", &k.to_string()).ok();
            }
        }
        let label = text_el(&doc, "label", "", "");
        let Ok(cb) = doc.create_element("input") else {
            continue;
        };
        cb.set_attribute("type", "checkbox").ok();
        cb.set_attribute("data-index", &l.index.to_string()).ok();
        let cb: HtmlInputElement = cb.unchecked_into();
        cb.set_checked(!b.state.hidden.contains(&l.index));
        {
            let v = v.clone();
            let index = l.index;
            let cb2 = cb.clone();
            listen(&cb, "change", move |_: Event| {
                {
                    let mut b = v.borrow_mut();
                    b.state.hidden.retain(|&i| i != index);
                    if !cb2.checked() {
                        b.state.hidden.push(index);
                        b.state.hidden.sort_unstable();
                    }
                }
                show_controls(&v);
                schedule(&v);
            });
        }
        label.append_child(&cb).ok();
        let [r, g, bl] = LAYER_COLOURS[l.index as usize % LAYER_COLOURS.len()];
        let sw = text_el(&doc, "span", "swatch", "");
        sw.set_attribute(
            "style",
            &format!(
                "background: rgb({},{},{})",
                (r * 255.0) as u8,
                (g * 255.0) as u8,
                (bl * 255.0) as u8
            ),
        )
        .ok();
        label.append_child(&sw).ok();
        let decimated = if let Some(lod) = &l.lod {
            // A COPC map: what the level of detail loaded, and the whole map's filter count from the
            // file's summary (the kept count below is of the loaded points).
            let whole = match lod.summary_kept {
                Some(k) => format!(
                    "; the default filter keeps {} of all {} (the file's summary)",
                    group_digits(k),
                    group_digits(l.total)
                ),
                None => String::new(),
            };
            let mut state = String::new();
            if lod.pending > 0 {
                state += &format!(", refining: {} more to load", lod.pending);
            }
            if lod.failed > 0 {
                state += &format!(", {} unreadable", lod.failed);
            }
            format!(
                " of {} loaded (level of detail: {} of {} octree nodes{state}, budget {}){whole}",
                group_digits(l.total),
                lod.nodes,
                lod.nodes_total,
                group_digits(lod.budget)
            )
        } else if l.stride > 1 {
            format!(", 1 in {} of {}", l.stride, group_digits(l.total))
        } else {
            String::new()
        };
        let fields: Vec<&str> = l.scalars.iter().map(|s| s.name.as_str()).collect();
        label
            .append_child(&text_el(
                &doc,
                "span",
                "",
                &format!(
                    "{} — {} points{decimated}{}",
                    l.name,
                    group_digits(l.points),
                    if fields.is_empty() {
                        String::new()
                    } else {
                        format!(" ({})", fields.join(", "))
                    }
                ),
            ))
            .ok();
        li.append_child(&label).ok();
        list.append_child(&li).ok();
    }
}

// ----- controls -----

fn wire_controls(v: &Shared) {
    let on_change = |id: &str, f: fn(&mut ViewState, &str)| {
        if let Some(el) = by_id(&document(), id) {
            let v = v.clone();
            let el2 = el.clone();
            let handler = move |_: Event| {
                let value = js_sys::Reflect::get(&el2, &"value".into())
                    .ok()
                    .and_then(|x| x.as_string())
                    .unwrap_or_default();
                f(&mut v.borrow_mut().state, &value);
                show_controls(&v);
                schedule(&v);
            };
            listen(&el, "input", handler);
        }
    };
    on_change("colour", |s, x| {
        s.colour = match x {
            "rgb" => Colour::Rgb,
            "layer" => Colour::Layer,
            f => Colour::Field(f.to_string()),
        }
    });
    on_change("filter-field", |s, x| {
        s.filter = x.to_string();
        s.threshold = None;
    });
    on_change("size", |s, x| {
        if let Ok(p) = x.parse::<f32>() {
            s.point_size = p.clamp(1.0, 32.0);
        }
    });
    on_change("background", |s, x| s.dark = x != "light");
    on_change("budget", |s, x| {
        s.budget = x
            .parse::<u64>()
            .ok()
            .map(|n| n.clamp(BUDGET_RANGE.0, BUDGET_RANGE.1))
    });
    on_change("draw", |s, x| s.draw = Raster::parse(x).unwrap_or_default());
    on_change("nav", |s, x| {
        s.nav = if x == "fly" { Nav::Fly } else { Nav::Orbit }
    });
    if let Some(slider) = input("threshold") {
        let v = v.clone();
        let s2 = slider.clone();
        listen(&slider, "input", move |_: Event| {
            let pos = s2.value_as_number();
            {
                let mut b = v.borrow_mut();
                let field = b.state.filter.clone();
                if let Some((lo, hi)) = field_range(&b, &field) {
                    // The top of the slider is exactly the largest value (keep everything finite).
                    let t = if pos >= SLIDER_STEPS {
                        hi
                    } else {
                        (lo as f64 + (hi as f64 - lo as f64) * (pos / SLIDER_STEPS)) as f32
                    };
                    b.state.threshold = Some(t);
                }
            }
            show_counts(&v);
            schedule(&v);
        });
    }
    if let Some(bt) = button("threshold-default") {
        let v = v.clone();
        listen(&bt, "click", move |_: Event| {
            v.borrow_mut().state.threshold = None;
            show_counts(&v);
            schedule(&v);
        });
    }
    if let Some(bt) = button("fit") {
        let v = v.clone();
        listen(&bt, "click", move |_: Event| {
            let cam = fit(&v.borrow());
            if cam.is_some() {
                v.borrow_mut().state.camera = cam;
            }
            schedule(&v);
        });
    }
    if let Some(bt) = button("share") {
        let v = v.clone();
        listen(&bt, "click", move |_: Event| share(&v));
    }
    if let Some(bt) = button("download") {
        let v = v.clone();
        listen(&bt, "click", move |_: Event| {
            let b = v.borrow();
            let targets: Vec<u32> = b
                .layers
                .iter()
                .filter(|l| {
                    !b.state.hidden.contains(&l.index)
                        && l.scalars.iter().any(|s| s.name == b.state.filter)
                })
                .map(|l| l.index)
                .collect();
            let view = b.state.clone();
            drop(b);
            for layer in targets {
                post(
                    &v,
                    &silvr_worker::FromPage::Download {
                        id: layer,
                        layer,
                        view: view.clone(),
                    },
                );
            }
        });
    }
    // The canvas follows its laid-out size (a scrollbar, a reflow of the card, the window, the zoom).
    let resized = {
        let v = v.clone();
        move || {
            let Some(c) =
                by_id(&document(), "view").and_then(|e| e.dyn_into::<HtmlCanvasElement>().ok())
            else {
                return;
            };
            let (width, height) = canvas_size(&c);
            if v.borrow().size == (width, height) {
                return;
            }
            v.borrow_mut().size = (width, height);
            post(&v, &silvr_worker::FromPage::Resize { width, height });
            schedule(&v);
        }
    };
    if let Some(c) = by_id(&document(), "view") {
        let resized = resized.clone();
        let cb = Closure::<dyn FnMut(JsValue)>::new(move |_: JsValue| resized());
        if let Ok(ro) = web_sys::ResizeObserver::new(cb.as_ref().unchecked_ref()) {
            ro.observe(&c);
            // Page-lifetime observer.
            std::mem::forget(ro);
        }
        cb.forget();
    }
    if let Some(w) = web_sys::window() {
        listen(&w, "resize", move |_: Event| resized());
    }
}

/// Shows the link of the current view; dropped files cannot be linked, and it says how instead.
fn share(v: &Shared) {
    let b = v.borrow();
    let doc = document();
    let Some(out) = by_id(&doc, "share-out") else {
        return;
    };
    out.remove_attribute("hidden").ok();
    while let Some(c) = out.first_child() {
        out.remove_child(&c).ok();
    }
    let local: Vec<&str> = b
        .layers
        .iter()
        .filter(|l| b.local.contains(&l.index))
        .map(|l| l.name.as_str())
        .collect();
    if !local.is_empty() {
        out.set_attribute("data-shareable", "false").ok();
        out.append_child(&text_el(
            &doc,
            "span",
            "warn",
            &format!(
                "Dropped files cannot be linked ({}): a link can only name files a server gives out. \
                 Serve the folder with `silvr serve DIR` and open the link it prints.",
                local.join(", ")
            ),
        ))
        .ok();
        return;
    }
    // The page's address without its access token: a shared link must not hand out the key (whoever
    // receives it and may read the data has a token of their own).
    let base = web_sys::window()
        .map(|w| {
            let loc = w.location();
            format!(
                "{}{}{}",
                loc.origin().unwrap_or_default(),
                loc.pathname().unwrap_or_default(),
                silvr_worker::view::query_without_token(&loc.search().unwrap_or_default())
            )
        })
        .unwrap_or_default();
    let link = format!("{base}{}", b.state.to_hash());
    out.set_attribute("data-shareable", "true").ok();
    out.set_attribute("data-link", &link).ok();
    let a = text_el(&doc, "a", "", &link);
    a.set_attribute("href", &link).ok();
    out.append_child(&a).ok();
    if let Some(w) = web_sys::window() {
        let _ = w.navigator().clipboard().write_text(&link);
    }
}

/// Orbit / fly controls on the canvas.
fn wire_camera(v: &Shared, canvas: &HtmlCanvasElement) {
    {
        let v = v.clone();
        let c = canvas.clone();
        listen(canvas, "pointerdown", move |ev: PointerEvent| {
            let _ = c.set_pointer_capture(ev.pointer_id());
            let _ = c.focus();
            let pan = ev.shift_key() || ev.button() == 2 || ev.button() == 1;
            let mut b = v.borrow_mut();
            b.drag = Some((ev.client_x() as f64, ev.client_y() as f64, pan));
            b.auto_camera = false;
        });
    }
    {
        let v = v.clone();
        listen(canvas, "pointermove", move |ev: PointerEvent| {
            let Some((x0, y0, pan)) = v.borrow().drag else {
                return;
            };
            let (x, y) = (ev.client_x() as f64, ev.client_y() as f64);
            let (dx, dy) = (x - x0, y - y0);
            {
                let mut b = v.borrow_mut();
                b.drag = Some((x, y, pan));
                let nav = b.state.nav;
                let Some(c) = b.state.camera.as_mut() else {
                    return;
                };
                if pan {
                    let back = c.back();
                    let right = DVec3::Z.cross(back).normalize_or_zero();
                    let up = back.cross(right);
                    let k = c.distance * 0.0015;
                    let t = DVec3::from_array(c.target) + (-right * dx + up * dy) * k;
                    c.target = t.to_array();
                } else {
                    let eye = c.eye();
                    c.yaw -= dx * 0.3;
                    c.pitch = (c.pitch + dy * 0.3).clamp(-89.0, 89.0);
                    if nav == Nav::Fly {
                        // Turn where the eye stands: move the target instead.
                        c.target = (eye - c.back() * c.distance).to_array();
                    }
                }
            }
            schedule(&v);
        });
    }
    for name in ["pointerup", "pointercancel"] {
        let v = v.clone();
        listen(canvas, name, move |_: PointerEvent| {
            v.borrow_mut().drag = None
        });
    }
    listen(canvas, "contextmenu", |ev: Event| ev.prevent_default());
    // Benchmarks (and the curious): `#view.dispatchEvent(new CustomEvent('silvr-bench', {detail: N}))`
    // draws N frames back to back; the time per frame lands in `#view[data-bench-ms]`.
    {
        let v = v.clone();
        listen(canvas, "silvr-bench", move |ev: web_sys::CustomEvent| {
            let frames = ev.detail().as_f64().unwrap_or(20.0).clamp(1.0, 1000.0) as u32;
            post(&v, &silvr_worker::FromPage::Bench { id: 0, frames });
        });
    }
    // Tests of the recovery: `silvr-lose-device` destroys the worker's device.
    {
        let v = v.clone();
        listen(canvas, "silvr-lose-device", move |_: Event| {
            post(&v, &silvr_worker::FromPage::DebugLoseDevice);
        });
    }
    {
        let v = v.clone();
        listen(canvas, "wheel", move |ev: WheelEvent| {
            ev.prevent_default();
            v.borrow_mut().auto_camera = false;
            if let Some(c) = v.borrow_mut().state.camera.as_mut() {
                c.distance = (c.distance * (ev.delta_y() * 0.001).exp()).clamp(1e-3, 1e7);
            }
            schedule(&v);
        });
    }
    {
        let v = v.clone();
        listen(canvas, "keydown", move |ev: KeyboardEvent| {
            let key = ev.key().to_ascii_lowercase();
            let step = |c: &Camera| c.distance.max(0.05) * 0.05;
            {
                let mut b = v.borrow_mut();
                let Some(c) = b.state.camera.as_mut() else {
                    return;
                };
                let back = c.back();
                let right = DVec3::Z.cross(back).normalize_or_zero();
                let d = match key.as_str() {
                    "w" | "arrowup" => -back,
                    "s" | "arrowdown" => back,
                    "a" | "arrowleft" => -right,
                    "d" | "arrowright" => right,
                    "e" => DVec3::Z,
                    "q" => -DVec3::Z,
                    _ => return,
                };
                ev.prevent_default();
                c.target = (DVec3::from_array(c.target) + d * step(c)).to_array();
                b.auto_camera = false;
            }
            schedule(&v);
        });
    }
}
