//! The worker's browser plumbing, shared by the view (`web.rs`) and training (`train.rs`): posting to
//! the page, reading JS objects, timers, streamed reads.

use serde::Serialize;
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;
use web_sys::DedicatedWorkerGlobalScope;

use crate::studio::MAX_FILE_BYTES;
use crate::view::TOKEN_HEADER;
use crate::ToPage;

pub(crate) fn get(obj: &JsValue, key: &str) -> JsValue {
    js_sys::Reflect::get(obj, &JsValue::from_str(key)).unwrap_or(JsValue::UNDEFINED)
}

pub(crate) async fn sleep_ms(ms: i32) {
    let promise = js_sys::Promise::new(&mut |resolve, _| {
        let _ = scope().set_timeout_with_callback_and_timeout_and_arguments_0(&resolve, ms);
    });
    let _ = wasm_bindgen_futures::JsFuture::from(promise).await;
}

/// Reads a stream to its end into memory, reporting progress, refusing more than [`MAX_FILE_BYTES`].
pub(crate) async fn read_stream(
    stream: web_sys::ReadableStream,
    total: Option<f64>,
    id: u32,
    source: &str,
) -> Result<Vec<u8>, String> {
    let reader: web_sys::ReadableStreamDefaultReader = stream.get_reader().unchecked_into();
    // Reserve what the server announced, but at most 64 MiB up front: several sources that each claim
    // 1.5 GiB must not exhaust the wasm heap before a byte arrives.
    let cap = total.unwrap_or(0.0).clamp(0.0, (64u64 << 20) as f64) as usize;
    let mut out = Vec::with_capacity(cap);
    let mut reported = 0usize;
    loop {
        let r = wasm_bindgen_futures::JsFuture::from(reader.read())
            .await
            .map_err(|e| format!("the transfer broke off: {}", js_text(&e)))?;
        if get(&r, "done").as_bool().unwrap_or(true) {
            break;
        }
        let chunk: js_sys::Uint8Array = get(&r, "value")
            .dyn_into()
            .map_err(|_| "the stream gave something other than bytes".to_string())?;
        let n = chunk.length() as usize;
        if (out.len() + n) as u64 > MAX_FILE_BYTES {
            let _ = reader.cancel();
            return Err(format!(
                "it is larger than the {} MiB the studio opens",
                MAX_FILE_BYTES >> 20
            ));
        }
        let at = out.len();
        out.try_reserve(n)
            .map_err(|_| "the worker ran out of memory while reading it".to_string())?;
        out.resize(at + n, 0);
        chunk.copy_to(&mut out[at..]);
        if out.len() - reported >= 4 << 20 {
            reported = out.len();
            post(&ToPage::Progress {
                id,
                source: source.to_string(),
                stage: "download".into(),
                loaded: out.len() as f64,
                total,
            });
        }
    }
    Ok(out)
}

pub(crate) fn js_text(e: &JsValue) -> String {
    e.as_string()
        .or_else(|| {
            e.dyn_ref::<js_sys::Error>()
                .map(|e| String::from(e.message()))
        })
        .unwrap_or_else(|| format!("{e:?}"))
}

/// Posts a download's bytes, transferring the buffer instead of copying it.
pub(crate) fn post_bytes(id: u32, name: &str, bytes: &[u8]) {
    let array = js_sys::Uint8Array::new_with_length(bytes.len() as u32);
    array.copy_from(bytes);
    let msg = js_sys::Object::new();
    let set = |k: &str, v: &JsValue| {
        js_sys::Reflect::set(&msg, &JsValue::from_str(k), v).ok();
    };
    set("type", &"download".into());
    set("id", &JsValue::from(id));
    set("name", &name.into());
    set("bytes", &array);
    let transfer = js_sys::Array::of1(&array.buffer());
    if let Err(e) = scope().post_message_with_transfer(&msg, &transfer) {
        web_sys::console::error_2(&"silvr worker: postMessage failed".into(), &e);
    }
}

pub(crate) fn scope() -> DedicatedWorkerGlobalScope {
    js_sys::global().unchecked_into()
}

/// Posts a message to the page as a plain JS object (structs and maps become objects, u64 numbers).
pub(crate) fn post(msg: &ToPage) {
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

/// The last path segment of a URL (`…/data/points.ply?x` → `points.ply`), or `default`.
pub(crate) fn url_file_name(url: &str, default: &str) -> String {
    url.split(['?', '#'])
        .next()
        .and_then(|p| p.rsplit('/').next())
        .filter(|n| !n.is_empty())
        .unwrap_or(default)
        .to_string()
}

/// Whether `url` is on this worker's origin (the page's: the worker is loaded from it), by the browser's
/// own URL parser, the one fetch uses.
fn same_origin(url: &str) -> bool {
    let scope: web_sys::WorkerGlobalScope = js_sys::global().unchecked_into();
    web_sys::Url::new(url).is_ok_and(|u| u.origin() == scope.location().origin())
}

/// Fetches an http(s) URL into memory (progress reported under `id`, at most [`MAX_FILE_BYTES`]); the
/// error is a sentence for the user. `token`, the page's access token, goes along as [`TOKEN_HEADER`]
/// only when `url` is on the page's own origin (a `silvr serve` on the network); then a redirect is an
/// error, so the header cannot follow one elsewhere.
pub(crate) async fn fetch_bytes(
    url: &str,
    id: u32,
    token: Option<&str>,
) -> Result<Vec<u8>, String> {
    let scope: web_sys::WorkerGlobalScope = js_sys::global().unchecked_into();
    let request = match token.filter(|_| same_origin(url)) {
        Some(token) => {
            let headers = web_sys::Headers::new().map_err(|e| js_text(&e))?;
            headers
                .set(TOKEN_HEADER, token)
                .map_err(|e| format!("the access token cannot be sent: {}", js_text(&e)))?;
            let init = web_sys::RequestInit::new();
            init.set_headers(&headers);
            init.set_redirect(web_sys::RequestRedirect::Error);
            scope.fetch_with_str_and_init(url, &init)
        }
        None => scope.fetch_with_str(url),
    };
    let response = match wasm_bindgen_futures::JsFuture::from(request).await {
        Ok(r) => r.unchecked_into::<web_sys::Response>(),
        Err(e) => {
            return Err(format!(
                "could not be fetched: the server is unreachable or refused the studio's origin (CORS) ({})",
                js_text(&e)
            ))
        }
    };
    if !response.ok() {
        // `silvr serve` off loopback without (the right) key: say what the key is.
        let hint = if response.status() == 401 && same_origin(url) {
            if token.is_some() {
                ": the link's access token (?token=) is not this server's (was it restarted?)"
            } else {
                ": this server wants its access token; open the full link silvr serve printed (with ?token=)"
            }
        } else {
            ""
        };
        return Err(format!(
            "the server answered HTTP {} {}{hint}",
            response.status(),
            response.status_text()
        ));
    }
    let total = content_length(&response).map(|t| t as f64);
    if total.is_some_and(|t| t > MAX_FILE_BYTES as f64) {
        return Err(format!(
            "it is {:.0} MiB, more than the {} MiB the studio opens",
            total.unwrap_or(0.0) / 1048576.0,
            MAX_FILE_BYTES >> 20
        ));
    }
    let Some(body) = response.body() else {
        return Err("the response has no body".into());
    };
    read_stream(body, total, id, url).await
}

/// Where a COPC map's bytes come from: a URL read by HTTP range requests, or a dropped file read by
/// slices (`Blob.slice`), so neither is read whole.
pub(crate) enum RangeSource {
    Url { url: String, token: Option<String> },
    File(web_sys::File),
}

impl RangeSource {
    /// Bytes `offset`..`offset + size`, and the file's length when the answer states it.
    pub(crate) async fn range(
        &self,
        offset: u64,
        size: u64,
    ) -> Result<(Vec<u8>, Option<u64>), String> {
        if size == 0 {
            return Ok((Vec::new(), None));
        }
        match self {
            RangeSource::File(file) => {
                let len = file.size() as u64;
                if offset.saturating_add(size) > len {
                    return Err(format!(
                        "bytes {offset}..+{size} lie past the file's end ({len} bytes)"
                    ));
                }
                let blob = file
                    .slice_with_f64_and_f64(offset as f64, (offset + size) as f64)
                    .map_err(|e| js_text(&e))?;
                let buf = wasm_bindgen_futures::JsFuture::from(blob.array_buffer())
                    .await
                    .map_err(|e| format!("the file could not be read: {}", js_text(&e)))?;
                Ok((js_sys::Uint8Array::new(&buf).to_vec(), Some(len)))
            }
            RangeSource::Url { url, token } => {
                fetch_range(url, token.as_deref(), offset, size).await
            }
        }
    }
}

/// The response's declared `Content-Length`, when it states a number.
fn content_length(response: &web_sys::Response) -> Option<u64> {
    response
        .headers()
        .get("content-length")
        .ok()
        .flatten()
        .and_then(|v| v.trim().parse::<u64>().ok())
}

/// One HTTP range request; the server must answer 206 with exactly those bytes (a server that ignores
/// ranges would send the whole map: refused, with the reason).
async fn fetch_range(
    url: &str,
    token: Option<&str>,
    offset: u64,
    size: u64,
) -> Result<(Vec<u8>, Option<u64>), String> {
    let scope: web_sys::WorkerGlobalScope = js_sys::global().unchecked_into();
    let headers = web_sys::Headers::new().map_err(|e| js_text(&e))?;
    headers
        .set("Range", &format!("bytes={offset}-{}", offset + size - 1))
        .map_err(|e| js_text(&e))?;
    let init = web_sys::RequestInit::new();
    if let Some(token) = token.filter(|_| same_origin(url)) {
        headers
            .set(TOKEN_HEADER, token)
            .map_err(|e| format!("the access token cannot be sent: {}", js_text(&e)))?;
        init.set_redirect(web_sys::RequestRedirect::Error);
    }
    init.set_headers(&headers);
    let response = wasm_bindgen_futures::JsFuture::from(scope.fetch_with_str_and_init(url, &init))
        .await
        .map_err(|e| {
            format!(
                "could not be fetched: the server is unreachable or refused the studio's origin (CORS) ({})",
                js_text(&e)
            )
        })?
        .unchecked_into::<web_sys::Response>();
    match response.status() {
        206 => {}
        200 => return Err(
            "the server does not answer byte-range requests (HTTP 200 for bytes of a COPC map); \
                 serve it with `silvr serve` or any server that does"
                .into(),
        ),
        s => {
            return Err(format!(
                "the server answered HTTP {s} {} for bytes {offset}..+{size}",
                response.status_text()
            ))
        }
    }
    // A body larger than asked is not read (a hostile server).
    let declared = content_length(&response);
    if declared.is_some_and(|d| d > size) {
        return Err(format!(
            "asked for {size} bytes, the server announces {}",
            declared.unwrap_or(0)
        ));
    }
    // `Content-Range: bytes a-b/LEN` (LEN may be `*`).
    let len = response
        .headers()
        .get("content-range")
        .ok()
        .flatten()
        .and_then(|v| {
            v.rsplit('/')
                .next()
                .and_then(|n| n.trim().parse::<u64>().ok())
        });
    let buf =
        wasm_bindgen_futures::JsFuture::from(response.array_buffer().map_err(|e| js_text(&e))?)
            .await
            .map_err(|e| format!("the transfer broke off: {}", js_text(&e)))?;
    let bytes = js_sys::Uint8Array::new(&buf).to_vec();
    // A last range may end at the file's end; any other length is a server's error.
    let expected = len.map_or(size, |l| size.min(l.saturating_sub(offset)));
    if bytes.len() as u64 != expected {
        return Err(format!(
            "asked for bytes {offset}..+{size}, the server sent {}",
            bytes.len()
        ));
    }
    Ok((bytes, len))
}
