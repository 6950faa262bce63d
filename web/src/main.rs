//! The studio page: starts the engine's Web Worker, shows what it reports, and takes dropped files.
//!
//! The static layout lives in `index.html` (ids `#status`, `#adapter`, `#projection`, `#rerun`, `#drop`,
//! `#dropped`, `#error`); this binary fills it in. For tests, `<body data-state>` goes `loading` → `ready`
//! (the worker reported its adapter and the startup kernel check) or `error` (no WebGPU, the worker died),
//! and `document.title` becomes `SiLVR Studio — ready` / `SiLVR Studio — error`.

mod protocol;

#[cfg(target_arch = "wasm32")]
mod dom;
#[cfg(target_arch = "wasm32")]
mod page;
#[cfg(target_arch = "wasm32")]
mod train;
#[cfg(target_arch = "wasm32")]
mod viewer;

#[cfg(target_arch = "wasm32")]
fn main() {
    page::start();
}

#[cfg(not(target_arch = "wasm32"))]
fn main() {
    eprintln!(
        "silvr-web is SiLVR Studio's page and only runs in a browser: build it with `trunk build --release` \
         and serve dist/ (see scripts/browser-tests.sh)."
    );
    std::process::exit(2);
}
