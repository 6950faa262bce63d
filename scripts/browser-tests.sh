#!/usr/bin/env bash
# SiLVR Studio's browser tests, in headless Chromium with SwiftShader WebGPU (shared/reference/toolchain.md) and
# headless Firefox ESR on lavapipe (shared/reference/browser_testing.md):
#   1. npm ci --prefix web          (binaryen 132 for trunk's wasm-opt, playwright-core, puppeteer-core)
#   2. trunk build --release        (the studio: page + worker → dist/)
#   3. wasm-bindgen-test            (the engine's GPU code in a dedicated Worker: worker/tests/browser_gpu.rs)
#   4. node --test tests/browser/   (the studio page end to end: adapter, kernel check, drag and drop; the
#                                    view in Chromium and Firefox on the ci demo's clouds, see viewer.mjs)
# Needs trunk 0.21.14, wasm-bindgen-cli 0.2.130, chromium, chromedriver, firefox-esr ≥ 141 (scripts/setup.sh installs them;
# this script installs nothing but web/node_modules). Exits non-zero on the first failure.
set -euo pipefail
cd "$(dirname "$0")/.."

CHROMEDRIVER="${CHROMEDRIVER:-/usr/bin/chromedriver}"
export CHROMEDRIVER
# SwiftShader compiles kernels on the CPU: give the runner more than its 20 s / 5 s defaults on a busy machine.
export WASM_BINDGEN_TEST_TIMEOUT="${WASM_BINDGEN_TEST_TIMEOUT:-180}"
export WASM_BINDGEN_TEST_DRIVER_TIMEOUT="${WASM_BINDGEN_TEST_DRIVER_TIMEOUT:-30}"

step() { printf '\033[1m[browser-tests]\033[0m %s\n' "$*"; }
die() { printf '\033[1;31m[browser-tests] error:\033[0m %s\n' "$*" >&2; exit 1; }
elapsed() { echo "$(( $(date +%s) - $1 )) s"; }

# --- tools (installing them is scripts/setup.sh's job) ---
command -v trunk >/dev/null || die "trunk is not installed (scripts/setup.sh, or: cargo install trunk --version 0.21.14 --locked)"
command -v wasm-bindgen-test-runner >/dev/null || die "wasm-bindgen-test-runner is missing (cargo install wasm-bindgen-cli --version 0.2.130)"
wasm-bindgen --version | grep -q ' 0.2.130' || die "wasm-bindgen-cli must be 0.2.130 (the crate's pin), found: $(wasm-bindgen --version)"
[ -x "$CHROMEDRIVER" ] || die "no chromedriver at $CHROMEDRIVER (apt-get install chromium-driver, or set CHROMEDRIVER)"
[ -x /usr/bin/chromium ] || [ -n "${SILVR_CHROMIUM:-}" ] || die "no /usr/bin/chromium (apt-get install chromium, or set SILVR_CHROMIUM)"
[ -x /usr/bin/firefox-esr ] || [ -n "${SILVR_FIREFOX:-}" ] || die "no /usr/bin/firefox-esr (scripts/setup.sh, or set SILVR_FIREFOX)"
command -v node >/dev/null && command -v npm >/dev/null || die "node and npm are needed (Node 20+)"
rustup target list --installed 2>/dev/null | grep -q wasm32-unknown-unknown || die "the wasm32 target is missing: rustup target add wasm32-unknown-unknown"

# --- 1. web/node_modules ---
if [ ! -x web/node_modules/.bin/wasm-opt ] || [ ! -d web/node_modules/playwright-core ] || \
   [ ! -d web/node_modules/puppeteer-core ] || \
   [ web/package-lock.json -nt web/node_modules/.package-lock.json ]; then
  step "npm ci --prefix web"
  npm ci --prefix web --no-audit --no-fund --loglevel=error
else
  step "web/node_modules is up to date"
fi
export PATH="$PWD/web/node_modules/.bin:$PATH"
wasm-opt --version | grep -q 'version 132' || die "wasm-opt on PATH is not binaryen 132: $(command -v wasm-opt)"

# --- 2. the studio bundle ---
# Trunk.toml sets offline = true (cargo --offline): make sure every crate is in the local registry first.
step "cargo fetch"
cargo fetch --quiet
step "trunk build --release"
t=$(date +%s)
trunk build --release
[ -f dist/index.html ] && [ -f dist/worker_loader.js ] || die "trunk did not produce dist/index.html and dist/worker_loader.js"
step "trunk build took $(elapsed "$t")"

# --- 3. Rust GPU tests inside Chromium (dedicated Worker) ---
# --release: the dependencies trunk just built for wasm32 are reused (a dev build compiled them all again,
# ~75 s more on a fresh 2-core machine).
step "wasm-bindgen-test: cargo test --release -p silvr-worker --target wasm32-unknown-unknown"
t=$(date +%s)
CARGO_TARGET_WASM32_UNKNOWN_UNKNOWN_RUNNER=wasm-bindgen-test-runner \
  cargo test --release -p silvr-worker --target wasm32-unknown-unknown
step "wasm-bindgen-test took $(elapsed "$t")"

# --- 4. the studio page end to end ---
# The streaming test's map at scale (issue 36): a generated 20 M-point cloud as COPC, written by the
# workspace's silvr (scripts/test.sh built it), with what the export printed (the native filter's count).
# Kept between runs: it takes about a minute and 0.4 GB.
export SILVR_STUDIO_SCALE="${SILVR_STUDIO_SCALE:-$PWD/target/studio-scale}"
if [ ! -s "$SILVR_STUDIO_SCALE/cloud20m.txt" ]; then
  step "generating a 20 M-point COPC map in $SILVR_STUDIO_SCALE"
  t=$(date +%s)
  silvr="${CARGO_TARGET_DIR:-$PWD/target}/debug/silvr"
  [ -x "$silvr" ] || die "no $silvr: build the workspace first (cargo build --workspace)"
  python="${SILVR_PYTHON:-${SILVR_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/silvr-venv}/bin/python}"
  mkdir -p "$SILVR_STUDIO_SCALE"
  rm -f "$SILVR_STUDIO_SCALE"/cloud20m.*
  "$python" scripts/gen_cloud.py 20000000 "$SILVR_STUDIO_SCALE/cloud20m.ply"
  "$silvr" export copc "$SILVR_STUDIO_SCALE/cloud20m.ply" --out "$SILVR_STUDIO_SCALE/cloud20m.copc.laz" \
    > "$SILVR_STUDIO_SCALE/cloud20m.part"
  rm "$SILVR_STUDIO_SCALE/cloud20m.ply"
  mv "$SILVR_STUDIO_SCALE/cloud20m.part" "$SILVR_STUDIO_SCALE/cloud20m.txt"
  cat "$SILVR_STUDIO_SCALE/cloud20m.txt"
  step "the 20 M-point map took $(elapsed "$t")"
fi
step "node --test --test-concurrency=1 --test-reporter=tap tests/browser/"
t=$(date +%s)
# TAP, whatever the Node version or the terminal: its `# SKIP` lines are what scripts/test.sh lists (Node
# 23+ prints another format by default, even into a pipe).
node --test --test-concurrency=1 --test-reporter=tap tests/browser/
step "page tests took $(elapsed "$t")"
step "all browser tests passed"
