//! The `worker` binary: trunk builds it as a Web Worker (`data-type="worker"`), and `main` runs when the
//! loader shim instantiates the wasm module.

#[cfg(target_arch = "wasm32")]
fn main() {
    silvr_worker::start();
}

#[cfg(not(target_arch = "wasm32"))]
fn main() {
    eprintln!(
        "silvr-worker is SiLVR Studio's Web Worker and only runs in a browser: build the studio with \
         `trunk build --release` (see scripts/browser-tests.sh). Natively, use the `silvr` binary."
    );
    std::process::exit(2);
}
