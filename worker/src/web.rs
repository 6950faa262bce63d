//! The worker's browser side: message plumbing, startup, panic and log forwarding.

use std::cell::RefCell;
use std::rc::Rc;

use serde::Serialize;
use silvr_core::gpu::{Gpu, GpuOptions};
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;
use wasm_bindgen_futures::spawn_local;
use web_sys::{DedicatedWorkerGlobalScope, MessageEvent};

use crate::{
    handle, name_adapter, run_check, BrowserAdapterInfo, FromPage, Stage, ToPage, STARTUP_POINTS,
    STARTUP_SEED,
};

/// The device, once startup has settled. Messages that arrive before are queued.
enum GpuState {
    Starting(Vec<FromPage>),
    Ready(Gpu),
    Failed(String),
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
                for msg in queued {
                    post(&refuse(&msg, &why));
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
    let old = std::mem::replace(&mut *state.borrow_mut(), GpuState::Ready(gpu.clone()));
    if let GpuState::Starting(queued) = old {
        for msg in queued {
            let gpu = gpu.clone();
            spawn_local(async move { post(&handle(&gpu, msg).await) });
        }
    }
}

fn receive(state: &Shared, data: JsValue) {
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
    let mut st = state.borrow_mut();
    match &mut *st {
        GpuState::Starting(queue) => queue.push(msg),
        GpuState::Failed(why) => post(&refuse(&msg, why)),
        GpuState::Ready(gpu) => {
            let gpu = gpu.clone();
            spawn_local(async move { post(&handle(&gpu, msg).await) });
        }
    }
}

fn refuse(msg: &FromPage, why: &str) -> ToPage {
    let FromPage::RunCheck { id, .. } = msg;
    ToPage::Error {
        id: *id,
        stage: Stage::Webgpu,
        message: why.to_string(),
        detail: None,
    }
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

fn scope() -> DedicatedWorkerGlobalScope {
    js_sys::global().unchecked_into()
}

/// Posts a message to the page as a plain JS object (structs and maps become objects, u64 numbers).
fn post(msg: &ToPage) {
    let serializer = serde_wasm_bindgen::Serializer::json_compatible();
    let value = match msg.serialize(&serializer) {
        Ok(v) => v,
        Err(e) => {
            web_sys::console::error_1(
                &format!("silvr worker: cannot serialize {msg:?}: {e}").into(),
            );
            return;
        }
    };
    if let Err(e) = scope().post_message(&value) {
        web_sys::console::error_2(&"silvr worker: postMessage failed".into(), &e);
    }
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
