//! The worker's browser side: message plumbing, startup, panic and log forwarding.

use std::cell::RefCell;
use std::rc::Rc;

use silvr_core::gpu::{Gpu, GpuOptions};
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;
use wasm_bindgen_futures::spawn_local;
use web_sys::MessageEvent;

use crate::copc;
use crate::js::{
    fetch_bytes, get, post, post_bytes, read_stream, scope, sleep_ms, url_file_name, RangeSource,
};
use crate::studio::{parse_cameras, parse_layer, Layers, MAX_FILE_BYTES, MAX_LAYERS};
use crate::view::{is_fetchable, Camera, ViewState};
use crate::{
    name_adapter, run_check, BrowserAdapterInfo, FromPage, Stage, ToPage, STARTUP_POINTS,
    STARTUP_SEED,
};
use futures_util::StreamExt;
use silvr_core::gpu::wgpu;
use silvr_core::viewer::{Frame, PointRenderer, ViewTargets};

/// The device, once startup has settled. Messages that arrive before are queued as they came.
enum GpuState {
    Starting(Vec<JsValue>),
    Ready(Rc<RefCell<Studio>>),
    Failed(String),
}

/// The view's state in the worker: the device, the layers, the canvas it draws into.
struct Studio {
    gpu: Gpu,
    layers: Layers,
    view: ViewState,
    target: Option<Target>,
    /// The canvas's size in pixels.
    size: (u32, u32),
    /// The canvas's surface while no device can draw into it (a recovery that failed): a canvas gives
    /// its context only once, so it is kept for the next attempt.
    spare: Option<wgpu::Surface<'static>>,
    recovering: bool,
    /// The page's number of the view in force.
    seq: u32,
    frames: u32,
    /// A frame is on the GPU: at most one is, so a slow adapter never queues frames of views already
    /// gone (an orbit drawn at the adapter's pace, showing the latest view each time).
    drawing: bool,
    /// The view changed while a frame was on the GPU: draw again when it is done.
    redraw: bool,
    last_counts: Option<crate::studio::FilterCounts>,
    /// The COPC layers' streams, by layer index.
    streams: std::collections::HashMap<u32, Stream>,
    /// Bumped when the camera, the canvas, the budget or the hidden layers change: a refinement started
    /// for an older view stops, and the view at rest starts its own.
    view_gen: u64,
}

/// A COPC layer's stream: its octree state, where its bytes come from, and the box it was first shown in
/// (kept, so the fitted camera does not move as nodes arrive).
struct Stream {
    copc: copc::CopcStream,
    src: Rc<RangeSource>,
    name: String,
    source: String,
    bounds: Option<[[f64; 3]; 4]>,
    /// The nodes the layer shows, and the budget they were chosen within.
    shown: (Vec<silvr_core::copc::read::VoxelKey>, u64),
}

/// The canvas surface and what drawing into it needs.
struct Target {
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    renderer: PointRenderer,
    /// The quad draw's depth and the compute rasteriser's per-pixel words, the canvas's size.
    targets: ViewTargets,
}

type Shared = Rc<RefCell<GpuState>>;

/// Entry point of the worker binary: hooks up messages and starts WebGPU. Returns at once; the work runs
/// on the worker's event loop.
pub fn start() {
    install_panic_hook();
    let _ = log::set_logger(&CONSOLE_LOGGER).map(|()| log::set_max_level(log::LevelFilter::Info));

    let state: Shared = Rc::new(RefCell::new(GpuState::Starting(Vec::new())));
    let on_message = {
        let state = state.clone();
        Closure::<dyn FnMut(MessageEvent)>::new(move |ev: MessageEvent| receive(&state, ev.data()))
    };
    scope().set_onmessage(Some(on_message.as_ref().unchecked_ref()));
    // The handler lives as long as the worker.
    on_message.forget();
    spawn_local(startup(state));
}

async fn startup(state: Shared) {
    let gpu = match Gpu::new(GpuOptions::default()).await {
        Ok(gpu) => gpu,
        Err(e) => {
            let message = match browser_adapter_info().await {
                Err(missing) => missing,
                Ok(None) => "navigator.gpu offers no adapter: WebGPU is switched off or the GPU is blocklisted \
                             (Chromium without a GPU needs --enable-unsafe-webgpu)"
                    .to_string(),
                Ok(Some(_)) => "the browser's WebGPU adapter cannot run SiLVR's kernels".to_string(),
            };
            let detail = e.to_string();
            post(&ToPage::Error {
                id: None,
                stage: Stage::Webgpu,
                message: message.clone(),
                detail: Some(detail.clone()),
            });
            let why = format!("WebGPU is not available: {message} ({detail})");
            let old = std::mem::replace(&mut *state.borrow_mut(), GpuState::Failed(why.clone()));
            if let GpuState::Starting(queued) = old {
                for data in queued {
                    post(&ToPage::Error {
                        id: message_id(&data),
                        stage: Stage::Webgpu,
                        message: why.clone(),
                        detail: None,
                    });
                }
            }
            return;
        }
    };
    let mut adapter = gpu.report().clone();
    let browser = browser_adapter_info().await.ok().flatten();
    if let Some(info) = &browser {
        name_adapter(&mut adapter, info);
    }
    log::info!("silvr worker: {adapter}");
    post(&ToPage::Adapter { adapter, browser });
    post(&run_check(&gpu, None, STARTUP_POINTS, STARTUP_SEED).await);
    let studio = Rc::new(RefCell::new(Studio {
        gpu,
        layers: Layers::default(),
        view: ViewState::default(),
        target: None,
        size: (1, 1),
        spare: None,
        recovering: false,
        seq: 0,
        frames: 0,
        drawing: false,
        redraw: false,
        last_counts: None,
        streams: Default::default(),
        view_gen: 0,
    }));
    let old = std::mem::replace(&mut *state.borrow_mut(), GpuState::Ready(studio.clone()));
    if let GpuState::Starting(queued) = old {
        for data in queued {
            dispatch(&studio, data);
        }
    }
}

fn receive(state: &Shared, data: JsValue) {
    let mut st = state.borrow_mut();
    match &mut *st {
        GpuState::Starting(queue) => queue.push(data),
        GpuState::Failed(why) => post(&ToPage::Error {
            id: message_id(&data),
            stage: Stage::Webgpu,
            message: why.clone(),
            detail: None,
        }),
        GpuState::Ready(studio) => {
            let studio = studio.clone();
            drop(st);
            dispatch(&studio, data);
        }
    }
}

fn message_id(data: &JsValue) -> Option<u32> {
    js_sys::Reflect::get(data, &"id".into())
        .ok()
        .and_then(|v| v.as_f64())
        .map(|v| v as u32)
}

/// What training borrows from the studio: its device, and the view for the trained points.
fn train_host(studio: &Rc<RefCell<Studio>>) -> crate::train::Host {
    let (s1, s2) = (studio.clone(), studio.clone());
    crate::train::Host {
        gpu: Rc::new(move || s1.borrow().gpu.clone()),
        open_points: Rc::new(move |bytes, name, source| {
            add_layer(&s2, crate::train::TRAINED_LAYER, bytes, name, source)
        }),
    }
}

/// Handles one message once the device is ready. Messages that carry JS objects (a canvas, a file)
/// are read field by field; the rest through serde.
fn dispatch(studio: &Rc<RefCell<Studio>>, data: JsValue) {
    match get(&data, "type").as_string().as_deref() {
        Some("canvas") => {
            let Ok(canvas) = get(&data, "canvas").dyn_into::<web_sys::OffscreenCanvas>() else {
                post(&view_error(
                    None,
                    "the canvas message carries no OffscreenCanvas",
                ));
                return;
            };
            let size = |k| get(&data, k).as_f64().unwrap_or(1.0).clamp(1.0, 16384.0) as u32;
            let (w, h) = (size("width"), size("height"));
            spawn_local(attach(studio.clone(), canvas, w, h));
            return;
        }
        Some("train-files") => {
            let id = message_id(&data).unwrap_or(0);
            let settings = match serde_wasm_bindgen::from_value(get(&data, "settings")) {
                Ok(s) => s,
                Err(e) => {
                    return post(&ToPage::TrainError {
                        source: "the training settings".into(),
                        message: e.to_string(),
                    })
                }
            };
            let files = js_sys::Array::from(&get(&data, "files"));
            let paths = js_sys::Array::from(&get(&data, "paths"));
            let files: Vec<(String, web_sys::File)> = files
                .iter()
                .enumerate()
                .filter_map(|(i, f)| {
                    let f = f.dyn_into::<web_sys::File>().ok()?;
                    let p = paths.get(i as u32).as_string().unwrap_or_else(|| f.name());
                    Some((p, f))
                })
                .collect();
            let checkpoint = get(&data, "checkpoint").dyn_into::<web_sys::File>().ok();
            spawn_local(crate::train::train_files(
                train_host(studio),
                id,
                files,
                checkpoint,
                settings,
            ));
            return;
        }
        Some("open-file") => {
            let id = message_id(&data).unwrap_or(0);
            match get(&data, "file").dyn_into::<web_sys::File>() {
                Ok(file) => spawn_local(open_file(studio.clone(), id, file)),
                Err(_) => post(&ToPage::LoadError {
                    id,
                    source: "a dropped file".into(),
                    message: "the message carries no File".into(),
                }),
            }
            return;
        }
        _ => {}
    }
    let msg: FromPage = match serde_wasm_bindgen::from_value(data.clone()) {
        Ok(m) => m,
        Err(e) => {
            let shown = js_sys::JSON::stringify(&data)
                .ok()
                .and_then(|s| s.as_string())
                .unwrap_or_else(|| format!("{data:?}"));
            post(&ToPage::Error {
                id: js_sys::Reflect::get(&data, &"id".into())
                    .ok()
                    .and_then(|v| v.as_f64())
                    .map(|v| v as u32),
                stage: Stage::Message,
                message: format!("the worker does not understand the message {shown}"),
                detail: Some(e.to_string()),
            });
            return;
        }
    };
    match msg {
        FromPage::RunCheck { id, n, seed } => {
            let gpu = studio.borrow().gpu.clone();
            spawn_local(async move {
                post(
                    &run_check(
                        &gpu,
                        id,
                        n.unwrap_or(STARTUP_POINTS),
                        seed.unwrap_or(STARTUP_SEED),
                    )
                    .await,
                )
            });
        }
        FromPage::Resize { width, height } => {
            resize(studio, width, height);
            draw(studio);
            view_changed(studio);
        }
        FromPage::View { view, seq } => {
            let moved = {
                let mut s = studio.borrow_mut();
                let moved = s.view.camera != view.camera
                    || s.view.budget != view.budget
                    || s.view.hidden != view.hidden;
                s.view = view;
                s.seq = seq;
                moved
            };
            draw(studio);
            report_counts(studio);
            if moved {
                view_changed(studio);
            }
        }
        FromPage::OpenUrl { id, url, token } => {
            spawn_local(open_url(studio.clone(), id, url, token))
        }
        FromPage::Download { id, layer, view } => {
            let out = studio.borrow().layers.filtered_ply(&view, layer);
            match out {
                Ok((name, bytes)) => post_bytes(id, &name, &bytes),
                Err(e) => post(&view_error(Some(id), &e)),
            }
        }
        FromPage::Bench { id, frames } => spawn_local(bench(studio.clone(), id, frames)),
        FromPage::TrainUrl {
            id,
            url,
            settings,
            token,
        } => spawn_local(crate::train::train_url(
            train_host(studio),
            id,
            url,
            settings,
            token,
        )),
        FromPage::TrainControl { action } => crate::train::control(action),
        FromPage::TrainDownload { id, name } => crate::train::download(id, &name),
        FromPage::TrainQuerySaved => spawn_local(crate::train::query_saved()),
        FromPage::DebugPanic => panic!("a test asked the worker to panic (debug-panic)"),
        FromPage::TrainResumeSaved { id } => {
            spawn_local(crate::train::resume_saved(train_host(studio), id))
        }
        FromPage::DebugLoseDevice => {
            let gpu = studio.borrow().gpu.clone();
            gpu.device.destroy();
            let studio = studio.clone();
            // The browser reports the loss asynchronously; draw once it has.
            spawn_local(async move {
                for _ in 0..20 {
                    sleep_ms(100).await;
                    if studio.borrow().gpu.check_lost().is_err() {
                        return draw(&studio);
                    }
                }
                // Firefox 153 does not resolve `device.lost` after `destroy()`: recover all the same.
                log::warn!("the destroyed device was not reported lost within 2 s");
                recover(&studio, "destroyed (the browser did not report it)".into());
            });
        }
    }
}

/// After a device loss: a new device, the layers uploaded again from the worker's copies, a new surface
/// on the same canvas. The page is told, and keeps its view.
fn recover(studio: &Rc<RefCell<Studio>>, why: String) {
    let surface = {
        let mut s = studio.borrow_mut();
        if s.recovering {
            return;
        }
        s.recovering = true;
        for l in &mut s.layers.layers {
            l.gpu = None;
        }
        let spare = s.spare.take();
        s.target.take().map(|t| t.surface).or(spare)
    };
    let studio = studio.clone();
    spawn_local(async move {
        match Gpu::new(GpuOptions::default()).await {
            Ok(gpu) => {
                {
                    let mut s = studio.borrow_mut();
                    s.gpu = gpu;
                    s.recovering = false;
                }
                post(&view_error(
                    None,
                    &format!(
                        "the GPU device was lost ({why}); the view was re-created on a new device"
                    ),
                ));
                if let Some(surface) = surface {
                    configure_view(&studio, surface).await;
                }
            }
            Err(e) => {
                {
                    let mut s = studio.borrow_mut();
                    s.recovering = false;
                    s.spare = surface;
                }
                post(&view_error(
                    None,
                    &format!("the GPU device was lost ({why}) and no new one could be opened: {e}"),
                ));
            }
        }
    });
}

fn view_error(id: Option<u32>, message: &str) -> ToPage {
    ToPage::Error {
        id,
        stage: Stage::View,
        message: message.to_string(),
        detail: None,
    }
}

/// Makes the canvas the view's target: a surface from the engine's own instance, on its device.
async fn attach(studio: Rc<RefCell<Studio>>, canvas: web_sys::OffscreenCanvas, w: u32, h: u32) {
    let gpu = studio.borrow().gpu.clone();
    studio.borrow_mut().size = (w, h);
    let surface = match gpu
        .instance
        .create_surface(wgpu::SurfaceTarget::OffscreenCanvas(canvas))
    {
        Ok(s) => s,
        Err(e) => {
            post(&view_error(
                None,
                &format!("the canvas cannot show WebGPU: {e}"),
            ));
            return;
        }
    };
    configure_view(&studio, surface).await;
}

/// Configures `surface` (the canvas's) for the studio's device and builds what drawing into it needs.
/// After a device loss it runs again with the same surface: a canvas gives its context only once (Firefox
/// refuses a second `getContext`), and the context accepts the new device.
async fn configure_view(studio: &Rc<RefCell<Studio>>, surface: wgpu::Surface<'static>) {
    let (gpu, (w, h)) = {
        let s = studio.borrow();
        (s.gpu.clone(), s.size)
    };
    let caps = surface.get_capabilities(&gpu.adapter);
    // Colours are written as encoded (sRGB values in a non-sRGB format), as the canvas shows them.
    let format = caps
        .formats
        .iter()
        .copied()
        .find(|f| !f.is_srgb())
        .or_else(|| caps.formats.first().copied());
    let Some(format) = format else {
        post(&view_error(None, "the canvas offers no texture format"));
        return;
    };
    let renderer = match PointRenderer::new(&gpu, format).await {
        Ok(r) => r,
        Err(e) => {
            post(&view_error(
                None,
                &format!("the point view cannot be built: {e}"),
            ));
            return;
        }
    };
    let Some(mut config) = surface.get_default_config(&gpu.adapter, w, h) else {
        post(&view_error(
            None,
            "the canvas cannot be configured for this device",
        ));
        return;
    };
    config.format = format;
    config.usage = wgpu::TextureUsages::RENDER_ATTACHMENT;
    config.view_formats = vec![];
    if caps.alpha_modes.contains(&wgpu::CompositeAlphaMode::Opaque) {
        config.alpha_mode = wgpu::CompositeAlphaMode::Opaque;
    }
    surface.configure(&gpu.device, &config);
    let targets = renderer.targets(&gpu, w, h);
    {
        let mut s = studio.borrow_mut();
        s.target = Some(Target {
            surface,
            config,
            renderer,
            targets,
        });
        // A frame in flight on a lost device never reports: the new target starts with none.
        s.drawing = false;
        s.redraw = false;
    }
    // Layers opened before the canvas came (or lost with the last device) get their buffers now.
    upload_pending(studio);
    draw(studio);
}

fn resize(studio: &Rc<RefCell<Studio>>, width: u32, height: u32) {
    let mut s = studio.borrow_mut();
    let gpu = s.gpu.clone();
    let max = gpu.device.limits().max_texture_dimension_2d;
    let (w, h) = (width.clamp(1, max), height.clamp(1, max));
    s.size = (w, h);
    if let Some(t) = s.target.as_mut() {
        if (t.config.width, t.config.height) != (w, h) {
            t.config.width = w;
            t.config.height = h;
            t.surface.configure(&gpu.device, &t.config);
            t.targets = t.renderer.targets(&gpu, w, h);
        }
    }
}

/// Uploads the layers that have no GPU buffers yet (needs the renderer), reporting failures.
fn upload_pending(studio: &Rc<RefCell<Studio>>) {
    let mut s = studio.borrow_mut();
    let Studio {
        gpu,
        layers,
        target,
        ..
    } = &mut *s;
    let Some(t) = target.as_ref() else { return };
    for l in layers.layers.iter_mut().filter(|l| l.gpu.is_none()) {
        match t.renderer.upload(gpu, &l.cloud) {
            Ok(g) => {
                l.info.gpu_bytes = g.bytes();
                l.gpu = Some(g);
            }
            Err(e) => post(&view_error(
                None,
                &format!("{}: cannot be put on the GPU: {e}", l.info.name),
            )),
        }
    }
}

/// Draws the view into the canvas and reports the frame when the GPU has finished it; while a frame is
/// still on the GPU, the view is drawn once that one is done instead (the latest view, however many
/// changes came meanwhile).
fn draw(studio: &Rc<RefCell<Studio>>) {
    let lost = studio.borrow().gpu.check_lost().err();
    if let Some(e) = lost {
        let why = match e {
            silvr_core::gpu::GpuError::DeviceLost { reason, .. } => reason,
            other => other.to_string(),
        };
        return recover(studio, why);
    }
    let mut s = studio.borrow_mut();
    if s.drawing {
        s.redraw = true;
        return;
    }
    let Some(t) = s.target.as_ref() else { return };
    let texture = match t.surface.get_current_texture() {
        wgpu::CurrentSurfaceTexture::Success(f) | wgpu::CurrentSurfaceTexture::Suboptimal(f) => f,
        other => {
            log::warn!("no canvas texture this frame: {other:?}");
            return;
        }
    };
    let (w, h) = (t.config.width, t.config.height);
    let Some((lo, hi)) = s.layers.bounds(&s.view) else {
        // Nothing open: clear to the background.
        let frame = frame_for(&s.view, Camera::fit([0.0; 3], [1.0; 3]), 1.0, (w, h));
        let view = texture.texture.create_view(&Default::default());
        t.renderer
            .render(&s.gpu, &view, &t.targets, &frame, &[], s.view.draw);
        s.gpu.queue.present(texture);
        return;
    };
    let radius = 0.5
        * (glam::DVec3::from_array(hi) - glam::DVec3::from_array(lo))
            .length()
            .max(1e-3);
    let Some(camera) = camera_now(&s) else { return };
    let frame = frame_for(&s.view, camera, radius, (w, h));
    let draws = s.layers.draws(&s.view);
    let points: u64 = draws.iter().map(|d| d.layer.points() as u64).sum();
    let view = texture.texture.create_view(&Default::default());
    let start = js_sys::Date::now();
    let used = t
        .renderer
        .render(&s.gpu, &view, &t.targets, &frame, &draws, s.view.draw);
    drop(draws);
    s.gpu.queue.present(texture);
    s.frames += 1;
    s.drawing = true;
    let (n, seq) = (s.frames, s.seq);
    // wgpu wants a `Send` callback: it only signals, and the task below (holding the studio) goes on.
    let (done, finished) = futures_channel::oneshot::channel::<()>();
    s.gpu.queue.on_submitted_work_done(move || {
        let _ = done.send(());
    });
    let again = studio.clone();
    spawn_local(async move {
        let _ = finished.await;
        post(&ToPage::Frame {
            n,
            ms: js_sys::Date::now() - start,
            points,
            seq,
            draw: used,
        });
        let redraw = {
            let mut s = again.borrow_mut();
            s.drawing = false;
            std::mem::take(&mut s.redraw)
        };
        if redraw {
            draw(&again);
        }
    });
}

/// The camera the view draws with: the page's, else one that fits the visible layers.
fn camera_now(s: &Studio) -> Option<Camera> {
    s.view.camera.or_else(|| {
        let (lo, hi) = s.layers.bounds(&s.view)?;
        let (a, b) = s.layers.fit_bounds(&s.view).unwrap_or((lo, hi));
        Some(Camera::fit(a, b))
    })
}

fn frame_for(view: &ViewState, camera: Camera, radius: f64, (w, h): (u32, u32)) -> Frame {
    let reference = glam::DVec3::from_array(camera.target);
    Frame {
        reference,
        view_proj: camera.view_proj((w, h), radius, reference),
        width: w,
        height: h,
        point_size: view.point_size,
        round: view.point_size >= 3.0,
        background: if view.dark {
            [0.06, 0.07, 0.09]
        } else {
            [0.97, 0.97, 0.96]
        },
    }
}

/// Sends the filter's counts when they changed.
fn report_counts(studio: &Rc<RefCell<Studio>>) {
    let mut s = studio.borrow_mut();
    let counts = s.layers.counts(&s.view);
    if s.last_counts.as_ref() != Some(&counts) {
        s.last_counts = Some(counts.clone());
        post(&ToPage::Filter { counts });
    }
}

async fn open_url(studio: Rc<RefCell<Studio>>, id: u32, url: String, token: Option<String>) {
    let fail = |message: String| {
        post(&ToPage::LoadError {
            id,
            source: url.clone(),
            message,
        })
    };
    if !is_fetchable(&url) {
        return fail("only http: and https: URLs are opened".into());
    }
    let name = url_file_name(&url, "points.ply");
    if is_copc(&name) {
        let src = RangeSource::Url {
            url: url.clone(),
            token,
        };
        return open_copc(&studio, id, src, &name, &url).await;
    }
    match fetch_bytes(&url, id, token.as_deref()).await {
        Ok(bytes) => add_layer(&studio, id, &bytes, &name, &url),
        Err(e) => fail(e),
    }
}

async fn open_file(studio: Rc<RefCell<Studio>>, id: u32, file: web_sys::File) {
    let name = file.name();
    let source = format!("file:{name}");
    if is_copc(&name) {
        // Read by slices: a dropped map larger than the studio's file limit opens too.
        return open_copc(&studio, id, RangeSource::File(file), &name, &source).await;
    }
    let size = file.size();
    if size > MAX_FILE_BYTES as f64 {
        return post(&ToPage::LoadError {
            id,
            source,
            message: format!(
                "it is {:.0} MiB, more than the {} MiB the studio opens",
                size / 1048576.0,
                MAX_FILE_BYTES >> 20
            ),
        });
    }
    match read_stream(file.stream(), Some(size), id, &source).await {
        Ok(bytes) => add_layer(&studio, id, &bytes, &name, &source),
        Err(message) => post(&ToPage::LoadError {
            id,
            source,
            message,
        }),
    }
}

fn is_copc(name: &str) -> bool {
    name.to_ascii_lowercase().ends_with(".copc.laz")
}

/// Opens a COPC map by byte ranges: its head and hierarchy, then a coarse top of the octree for the first
/// frame (within [`copc::FIRST_FRAME_POINTS`]), each node decoded here as it arrives; the view at rest then
/// refines it to the budget ([`refine`]). Its counts over the whole map come from the file's summary.
async fn open_copc(
    studio: &Rc<RefCell<Studio>>,
    id: u32,
    src: RangeSource,
    name: &str,
    source: &str,
) {
    let fail = |message: String| {
        post(&ToPage::LoadError {
            id,
            source: source.to_string(),
            message,
        })
    };
    if studio.borrow().layers.layers.len() >= MAX_LAYERS {
        return fail(format!(
            "the studio holds at most {MAX_LAYERS} layers; close one first"
        ));
    }
    let mut stream = match open_stream(&src, name).await {
        Ok(s) => s,
        Err(message) => return fail(message),
    };
    let budget = current_budget(&studio.borrow());
    let first = copc::choose(
        &stream.head,
        &stream.entries,
        copc::FIRST_FRAME_POINTS.min(budget),
    );
    let want: u64 = first.iter().map(|e| e.point_count.max(0) as u64).sum();
    let mut loaded = 0u64;
    let src = Rc::new(src);
    let mut arrivals = fetch_nodes(src.clone(), first.clone());
    while let Some((e, bytes)) = arrivals.next().await {
        match decode(&stream.head, &e, bytes, stream.origin, name) {
            Ok(p) => {
                loaded += p.positions.len() as u64;
                stream.insert(e.key, p);
            }
            // Without the root there is nothing to show; a deeper node is left out, with a message.
            Err(message) if e.key.level == 0 => return fail(message),
            Err(message) => {
                stream.fail(e.key);
                post(&view_error(
                    None,
                    &format!("{name}: {message}; the view keeps what it has"),
                ));
            }
        }
        post(&ToPage::Progress {
            id,
            source: source.to_string(),
            stage: "decode".into(),
            loaded: loaded as f64,
            total: Some(want as f64),
        });
    }
    studio.borrow_mut().streams.insert(
        id,
        Stream {
            copc: stream,
            src,
            name: name.to_string(),
            source: source.to_string(),
            bounds: None,
            shown: (Vec::new(), 0),
        },
    );
    if let Err(message) = show_stream(studio, id, &first, 0) {
        studio.borrow_mut().streams.remove(&id);
        return fail(message);
    }
    let gen = studio.borrow().view_gen;
    spawn_local(refine(studio.clone(), id, gen));
}

/// A COPC map's head and hierarchy (every page), read by ranges.
async fn open_stream(src: &RangeSource, name: &str) -> Result<copc::CopcStream, String> {
    use silvr_core::copc::read::{head_len, parse_head, HierarchyWalk, LAS_HEADER_BYTES};
    let (first, mut file_len) = src.range(0, LAS_HEADER_BYTES as u64).await?;
    let n = head_len(&first, name).map_err(|e| e.to_string())?;
    let (head_bytes, len) = src.range(0, n).await?;
    file_len = file_len.or(len);
    let head = parse_head(&head_bytes, name).map_err(|e| e.to_string())?;
    let mut walk = HierarchyWalk::new(&head, file_len, name);
    while let Some(r) = walk.next_page().map_err(|e| e.to_string())? {
        let (bytes, _) = src.range(r.offset, r.size).await?;
        walk.add_page(r, &bytes).map_err(|e| e.to_string())?;
    }
    let entries = walk.finish();
    Ok(copc::CopcStream::new(head, entries))
}

/// Range requests a COPC layer keeps in flight: a remote server's latency overlaps the decoding of the
/// nodes that have come (on loopback the decoding dominates either way).
const FETCHES_IN_FLIGHT: usize = 4;

/// The octree nodes' bytes, fetched [`FETCHES_IN_FLIGHT`] at a time and yielded in `entries`' order.
/// Dropping the stream drops the requests still in flight.
fn fetch_nodes(
    src: Rc<RangeSource>,
    entries: Vec<silvr_core::copc::read::Entry>,
) -> impl futures_util::Stream<Item = (silvr_core::copc::read::Entry, Result<Vec<u8>, String>)> {
    futures_util::stream::iter(entries)
        .map(move |e| {
            let src = src.clone();
            async move {
                let got = src.range(e.offset, e.byte_size.max(0) as u64).await;
                (e, got.map(|(bytes, _)| bytes))
            }
        })
        .buffered(FETCHES_IN_FLIGHT)
}

/// One node's points from its fetched bytes; the error names the node.
fn decode(
    head: &silvr_core::copc::read::CopcHead,
    e: &silvr_core::copc::read::Entry,
    bytes: Result<Vec<u8>, String>,
    origin: glam::DVec3,
    name: &str,
) -> Result<silvr_core::copc::read::NodePoints, String> {
    let k = e.key;
    let node = format!("octree node {}-{}-{}-{}", k.level, k.x, k.y, k.z);
    let bytes = bytes.map_err(|m| format!("{node} could not be read: {m}"))?;
    silvr_core::copc::read::decode_node(head, e, &bytes, origin, name)
        .map_err(|m| format!("{node}: {m}"))
}

/// The point budget in force: the view's, else the adapter's default.
fn current_budget(s: &Studio) -> u64 {
    copc::budget(s.view.budget, s.gpu.report().software)
}

/// Makes layer `id` the decoded nodes of `chosen` (those of them decoded), `pending` nodes still to come,
/// and drops decoded nodes past the cache bound, least recently shown first.
fn show_stream(
    studio: &Rc<RefCell<Studio>>,
    id: u32,
    chosen: &[silvr_core::copc::read::Entry],
    pending: u32,
) -> Result<(), String> {
    let layer = {
        let mut s = studio.borrow_mut();
        let budget = current_budget(&s);
        let Some(st) = s.streams.get_mut(&id) else {
            return Ok(());
        };
        let (cloud, keys) = st.copc.show(chosen);
        st.copc.evict(budget.saturating_mul(copc::CACHE_PER_BUDGET));
        let view = silvr_core::viewer::ViewCloud::from_cloud(
            &cloud,
            silvr_core::viewer::ViewCloud::MAX_POINTS,
        );
        drop(cloud);
        if view.is_empty() {
            return Err(format!("{}: no point has finite coordinates", st.name));
        }
        let mut layer = crate::studio::Layer::new(view, st.name.clone(), &st.source, id);
        let i = &mut layer.info;
        let [min, max, fit_min, fit_max] = *st
            .bounds
            .get_or_insert([i.min, i.max, i.fit_min, i.fit_max]);
        (i.min, i.max, i.fit_min, i.fit_max) = (min, max, fit_min, fit_max);
        i.total = st.copc.head.points;
        let filter = st
            .copc
            .head
            .summary
            .as_ref()
            .and_then(|s| s.filter.as_ref());
        i.lod = Some(copc::LodInfo {
            nodes: keys.len() as u32,
            nodes_total: st.copc.entries.len() as u32,
            budget,
            pending,
            failed: st.copc.failed() as u32,
            summary_kept: filter.map(|f| f.kept),
            summary_threshold: filter.and_then(|f| f.threshold),
        });
        st.shown = (keys, budget);
        layer
    };
    insert_layer(studio, id, layer);
    Ok(())
}

/// How long the camera must rest before the level of detail follows it (ms): an orbit sends a view a
/// frame, and each would otherwise start fetching.
const REST_MS: i32 = 250;
/// While nodes arrive, the layer is redrawn with what has come at most this often (ms).
const REFINE_SHOW_MS: f64 = 700.0;

/// The view changed: once it has rested, the COPC layers refine for it.
fn view_changed(studio: &Rc<RefCell<Studio>>) {
    let gen = {
        let mut s = studio.borrow_mut();
        s.view_gen += 1;
        if s.streams.is_empty() {
            return;
        }
        s.view_gen
    };
    let studio = studio.clone();
    spawn_local(async move {
        sleep_ms(REST_MS).await;
        let ids: Vec<u32> = studio.borrow().streams.keys().copied().collect();
        for id in ids {
            if studio.borrow().view_gen != gen {
                return;
            }
            refine(studio.clone(), id, gen).await;
        }
    });
}

/// Loads the nodes the view `gen` wants of layer `id` (largest on screen first, within the budget),
/// showing what has come every [`REFINE_SHOW_MS`]; stops when the view changes (what was fetched stays
/// decoded for the next). A node that cannot be read is reported and left out; the view keeps the rest.
async fn refine(studio: Rc<RefCell<Studio>>, id: u32, gen: u64) {
    let current = |s: &Studio| s.view_gen == gen && s.streams.contains_key(&id);
    let (plan, head, src, name, same) = {
        let s = studio.borrow();
        if !current(&s) || s.view.hidden.contains(&id) {
            return;
        }
        let Some(camera) = camera_now(&s) else { return };
        let st = &s.streams[&id];
        let plan = st
            .copc
            .plan(&copc::lod_view(&camera, s.size), current_budget(&s));
        let budget = current_budget(&s);
        let same = st.shown.1 == budget
            && st.shown.0.len() == plan.chosen.len()
            && st
                .shown
                .0
                .iter()
                .zip(&plan.chosen)
                .all(|(k, e)| *k == e.key);
        (
            plan,
            st.copc.head.clone(),
            st.src.clone(),
            st.name.clone(),
            same,
        )
    };
    log::debug!(
        "COPC layer {id}, view {gen}: {} nodes wanted, {} to load",
        plan.chosen.len(),
        plan.missing.len()
    );
    if plan.missing.is_empty() {
        // Everything wanted is decoded: show it unless it is what is shown.
        if !same {
            let _ = show_stream(&studio, id, &plan.chosen, 0);
        }
        return;
    }
    let origin = head.center();
    let mut last = js_sys::Date::now();
    let total = plan.missing.len();
    let mut arrivals = fetch_nodes(src, plan.missing.clone());
    let mut i = 0;
    while let Some((e, bytes)) = arrivals.next().await {
        if !current(&studio.borrow()) {
            return;
        }
        let got = decode(&head, &e, bytes, origin, &name);
        {
            let mut s = studio.borrow_mut();
            let Some(st) = s.streams.get_mut(&id) else {
                return;
            };
            match got {
                Ok(p) => st.copc.insert(e.key, p),
                Err(message) => {
                    st.copc.fail(e.key);
                    drop(s);
                    post(&view_error(
                        None,
                        &format!("{name}: {message}; the view keeps what it has"),
                    ));
                }
            }
        }
        i += 1;
        let left = total - i;
        if left > 0 && js_sys::Date::now() - last > REFINE_SHOW_MS && current(&studio.borrow()) {
            let _ = show_stream(&studio, id, &plan.chosen, left as u32);
            last = js_sys::Date::now();
        }
    }
    if current(&studio.borrow()) {
        let _ = show_stream(&studio, id, &plan.chosen, 0);
    }
}

fn add_layer(studio: &Rc<RefCell<Studio>>, id: u32, bytes: &[u8], name: &str, source: &str) {
    {
        let s = studio.borrow();
        if s.layers.layers.len() >= MAX_LAYERS {
            return post(&ToPage::LoadError {
                id,
                source: source.to_string(),
                message: format!("the studio holds at most {MAX_LAYERS} layers; close one first"),
            });
        }
    }
    post(&ToPage::Progress {
        id,
        source: source.to_string(),
        stage: "parse".into(),
        loaded: bytes.len() as f64,
        total: Some(bytes.len() as f64),
    });
    // The request id is the layer's number: the page numbers a link's sources by their order, so a
    // link's `hide=` means the same layers whichever file arrives first.
    let index = id;
    let parsed = if name.to_ascii_lowercase().ends_with(".json") {
        parse_cameras(bytes, name, source, index)
    } else {
        parse_layer(bytes, name, source, index)
    };
    match parsed {
        Ok(layer) => insert_layer(studio, id, layer),
        Err(message) => post(&ToPage::LoadError {
            id,
            source: source.to_string(),
            message,
        }),
    }
}

/// Adds (or replaces) layer `id`, uploads it, tells the page and draws.
fn insert_layer(studio: &Rc<RefCell<Studio>>, id: u32, layer: crate::studio::Layer) {
    let index = id;
    {
        let mut s = studio.borrow_mut();
        s.layers.layers.retain(|l| l.info.index != index);
        s.layers.layers.push(layer);
        s.layers.layers.sort_by_key(|l| l.info.index);
    }
    upload_pending(studio);
    let info = studio
        .borrow()
        .layers
        .layers
        .iter()
        .find(|l| l.info.index == index)
        .map(|l| l.info.clone());
    if let Some(layer) = info {
        post(&ToPage::Layer { id, layer });
    }
    draw(studio);
    report_counts(studio);
}

/// Draws `frames` frames, each after the previous one finished on the GPU, and reports ms per frame.
async fn bench(studio: Rc<RefCell<Studio>>, id: u32, frames: u32) {
    let frames = frames.clamp(1, 1000);
    // Start with no frame on the GPU, so that every one below is drawn.
    while studio.borrow().drawing {
        let gpu = studio.borrow().gpu.clone();
        let (tx, rx) = futures_channel::oneshot::channel();
        gpu.queue.on_submitted_work_done(move || {
            let _ = tx.send(());
        });
        let _ = rx.await;
    }
    let start = js_sys::Date::now();
    for _ in 0..frames {
        draw(&studio);
        let gpu = studio.borrow().gpu.clone();
        let (tx, rx) = futures_channel::oneshot::channel();
        gpu.queue.on_submitted_work_done(move || {
            let _ = tx.send(());
        });
        let _ = rx.await;
    }
    let s = studio.borrow();
    let points = s.layers.layers.iter().map(|l| l.info.points).sum();
    let draw = match &s.target {
        Some(t) => t.targets.draw_for(s.view.draw),
        None => s.view.draw,
    };
    // The wasm heap's size: what the worker holds (it only grows, so this is the high-water mark); GPU
    // buffers live in the browser's GPU process and are counted per layer.
    let wasm_bytes = wasm_bindgen::memory()
        .dyn_into::<js_sys::WebAssembly::Memory>()
        .ok()
        .and_then(|m| m.buffer().dyn_into::<js_sys::ArrayBuffer>().ok())
        .map_or(0, |b| b.byte_length() as u64);
    post(&ToPage::Bench {
        id,
        frames,
        draw,
        wasm_bytes,
        ms_per_frame: (js_sys::Date::now() - start) / frames as f64,
        points,
    });
}

/// Asks `navigator.gpu` directly for the adapter's `GPUAdapterInfo` (wgpu does not pass vendor and
/// architecture on). `Err` says why there is no `navigator.gpu`; `Ok(None)`: it offers no adapter.
async fn browser_adapter_info() -> Result<Option<BrowserAdapterInfo>, String> {
    let get = |obj: &JsValue, key: &str| {
        js_sys::Reflect::get(obj, &JsValue::from_str(key)).unwrap_or(JsValue::UNDEFINED)
    };
    let gpu = get(&get(&js_sys::global(), "navigator"), "gpu");
    if gpu.is_undefined() || gpu.is_null() {
        return Err(
            "navigator.gpu is missing: this browser has WebGPU switched off or does not support it"
                .into(),
        );
    }
    let request = get(&gpu, "requestAdapter")
        .dyn_into::<js_sys::Function>()
        .map_err(|_| "navigator.gpu.requestAdapter is not a function".to_string())?;
    let options = js_sys::Object::new();
    js_sys::Reflect::set(
        &options,
        &"powerPreference".into(),
        &"high-performance".into(),
    )
    .ok();
    let promise = request
        .call1(&gpu, &options)
        .map_err(|e| format!("requestAdapter threw {e:?}"))?
        .dyn_into::<js_sys::Promise>()
        .map_err(|_| "requestAdapter did not return a promise".to_string())?;
    let adapter = wasm_bindgen_futures::JsFuture::from(promise)
        .await
        .map_err(|e| format!("requestAdapter failed: {e:?}"))?;
    if adapter.is_null() || adapter.is_undefined() {
        return Ok(None);
    }
    let info = get(&adapter, "info");
    let text = |key: &str| get(&info, key).as_string().unwrap_or_default();
    Ok(Some(BrowserAdapterInfo {
        vendor: text("vendor"),
        architecture: text("architecture"),
        device: text("device"),
        description: text("description"),
    }))
}

/// Panics abort a wasm instance; tell the page (and the console) why before that happens.
fn install_panic_hook() {
    std::panic::set_hook(Box::new(|info| {
        let message = format!("the worker crashed: {info}");
        web_sys::console::error_1(&message.clone().into());
        post(&ToPage::Error {
            id: None,
            stage: Stage::Panic,
            message,
            detail: None,
        });
    }));
}

/// Forwards the engine's `log` records (e.g. uncaptured wgpu errors) to the browser console.
struct ConsoleLogger;

static CONSOLE_LOGGER: ConsoleLogger = ConsoleLogger;

impl log::Log for ConsoleLogger {
    fn enabled(&self, metadata: &log::Metadata) -> bool {
        metadata.level() <= log::max_level()
    }

    fn log(&self, record: &log::Record) {
        if !self.enabled(record.metadata()) {
            return;
        }
        let line: JsValue = format!(
            "[{}] {}: {}",
            record.level(),
            record.target(),
            record.args()
        )
        .into();
        match record.level() {
            log::Level::Error => web_sys::console::error_1(&line),
            log::Level::Warn => web_sys::console::warn_1(&line),
            _ => web_sys::console::log_1(&line),
        }
    }

    fn flush(&self) {}
}
