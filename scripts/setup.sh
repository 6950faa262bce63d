#!/usr/bin/env bash
# Installs what one purpose of SiLVR Studio needs, skipping whatever is already there:
#   scripts/setup.sh demo     the native binary and the demo: Mesa 25 lavapipe (the Vulkan driver when there
#                             is no GPU) and vulkan-tools
#   scripts/setup.sh studio   + the studio build: clang (mcap's lz4/zstd for wasm32), the wasm32 target,
#                             wasm-bindgen-cli pinned to the crate's version, trunk, web/'s npm packages
#                             (binaryen 132, playwright-core)
#   scripts/setup.sh [test]   + the browser tests: Chromium + ChromeDriver, Firefox ESR ≥ 141 (bookworm-security
#                             has 153; bookworm's 140 has no WebGPU), and numpy + scipy for the evaluator's
#                             cross-check in a virtual environment ($SILVR_VENV, default ~/.cache/silvr-venv;
#                             python3-venv from apt where `python3 -m venv` is missing) (the default: everything)
# Debian bookworm (root): Mesa 25 comes from bookworm-backports (4-7x faster than bookworm's Mesa 22).
set -euo pipefail
cd "$(dirname "$0")/.."

purpose="${1:-test}"
case "$purpose" in
  demo|studio|test) ;;
  *) echo "usage: scripts/setup.sh [demo|studio|test]" >&2; exit 2 ;;
esac

log() { printf '\033[1m[setup]\033[0m %s\n' "$*"; }
SUDO=""
[ "$(id -u)" = 0 ] || SUDO="sudo"

pkgs=(vulkan-tools)
[ "$purpose" = demo ] || pkgs+=(clang)
[ "$purpose" = test ] && pkgs+=(chromium chromium-driver firefox-esr)
need_apt=()
for p in "${pkgs[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || need_apt+=("$p")
done
# The tests' SciPy cross-check runs in a virtual environment (below): python3 with its venv module (Debian
# ships ensurepip, which `python3 -m venv` needs, in python3-venv).
if [ "$purpose" = test ]; then
  command -v python3 >/dev/null || need_apt+=(python3)
  python3 -c 'import venv, ensurepip' >/dev/null 2>&1 || need_apt+=(python3-venv)
fi
mesa_ok=0
if dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null | grep -qE '^(2[5-9]|[3-9][0-9])\.'; then mesa_ok=1; fi

if [ ${#need_apt[@]} -gt 0 ] || [ $mesa_ok = 0 ]; then
  if command -v apt-get >/dev/null; then
    if [ $mesa_ok = 0 ] && [ -f /etc/apt/sources.list.d/debian.sources ] && \
       grep -q 'bookworm' /etc/apt/sources.list.d/debian.sources && \
       [ ! -f /etc/apt/sources.list.d/bookworm-backports.sources ]; then
      log "adding bookworm-backports (for Mesa 25)"
      awk 'BEGIN{RS="";ORS="\n\n"} /Suites: bookworm bookworm-updates/' /etc/apt/sources.list.d/debian.sources \
        | sed 's/^Suites: .*/Suites: bookworm-backports/' | $SUDO tee /etc/apt/sources.list.d/bookworm-backports.sources >/dev/null
    fi
    log "apt-get install ${need_apt[*]} (and Mesa lavapipe)"
    $SUDO apt-get update -qq
    [ ${#need_apt[@]} -gt 0 ] && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need_apt[@]}" >/dev/null
    if [ $mesa_ok = 0 ]; then
      if [ -f /etc/apt/sources.list.d/bookworm-backports.sources ]; then
        $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq -t bookworm-backports \
          mesa-vulkan-drivers libegl-mesa0 libgl1-mesa-dri libglx-mesa0 libgbm1 >/dev/null
      else
        $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq mesa-vulkan-drivers >/dev/null
      fi
    fi
  else
    log "warning: no apt-get; install a Vulkan driver (Mesa lavapipe), chromium, chromedriver and clang yourself"
  fi
fi

if [ "$purpose" = demo ]; then
  log "ready (demo)"
  exit 0
fi

rustup target list --installed 2>/dev/null | grep -q wasm32-unknown-unknown || { log "rustup target add wasm32"; rustup target add wasm32-unknown-unknown; }

# The two Rust tools are built unoptimised, without debug info or LTO, into one shared target folder (their
# common crates compile once): on 2 cores 42 s + 115 s instead of 81 s + 189 s at opt-level 1. Their run
# time is not the build's: binding our 37 MB worker takes 1.2 s instead of 0.4 s, trunk only copies files.
tools_env=(CARGO_PROFILE_RELEASE_LTO=off CARGO_PROFILE_RELEASE_CODEGEN_UNITS=16 CARGO_PROFILE_RELEASE_OPT_LEVEL=0
  CARGO_PROFILE_RELEASE_DEBUG=false CARGO_TARGET_DIR="${TMPDIR:-/tmp}/silvr-tools-build")
if ! (command -v wasm-bindgen >/dev/null && wasm-bindgen --version | grep -q ' 0.2.130'); then
  log "cargo install wasm-bindgen-cli 0.2.130 (~1 min)"
  env "${tools_env[@]}" cargo install -q wasm-bindgen-cli --version 0.2.130 --force
fi
if ! (command -v trunk >/dev/null && trunk --version | grep -q ' 0.21.14'); then
  # Without its TLS / update-check features: we build offline with wasm-bindgen and wasm-opt already on PATH.
  log "cargo install trunk 0.21.14 (~2 min)"
  env "${tools_env[@]}" cargo install -q trunk --version 0.21.14 --locked --no-default-features --force
fi
rm -rf "${TMPDIR:-/tmp}/silvr-tools-build"

if [ ! -x web/node_modules/.bin/wasm-opt ] || [ web/package-lock.json -nt web/node_modules/.package-lock.json ]; then
  log "npm ci (web/: binaryen, playwright-core, puppeteer-core)"
  npm ci --prefix web --no-audit --no-fund --loglevel=error
fi
if [ "$purpose" = test ]; then
  # numpy + scipy for scripts/crosscheck_eval.py and rosbags + mcap for core/tests/rosbags.rs, in a virtual
  # environment of their own: Debian's Python
  # refuses `pip install` outside one (PEP 668). scripts/test.sh runs the cross-check with its python.
  venv="${SILVR_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/silvr-venv}"
  if ! "$venv/bin/python" -c 'import numpy, scipy, rosbags, mcap, pye57, laspy, lazrs' >/dev/null 2>&1; then
    if [ -e "$venv" ] && [ ! -f "$venv/pyvenv.cfg" ]; then
      echo "$venv exists and is not a virtual environment: move it away or set SILVR_VENV" >&2; exit 1
    fi
    clear=()
    # A venv whose Python is gone (e.g. upgraded) is made again in place (it is ours: it has pyvenv.cfg).
    if [ -f "$venv/pyvenv.cfg" ] && ! "$venv/bin/python" -c '' >/dev/null 2>&1; then clear=(--clear); fi
    log "python3 -m venv $venv + pip install -r scripts/requirements-crosscheck.txt"
    python3 -m venv "${clear[@]}" "$venv"
    "$venv/bin/python" -m pip install --quiet -r scripts/requirements-crosscheck.txt
  fi
  # WebGPU in Firefox needs ESR 141 or later (Debian's security updates carry 153).
  ffv=$(firefox-esr --version 2>/dev/null | grep -oE '[0-9]+' | head -1 || true)
  if [ -z "$ffv" ] || [ "$ffv" -lt 141 ]; then
    log "firefox-esr ${ffv:-missing} is older than 141, which has no WebGPU: upgrading from bookworm-security"
    $SUDO apt-get update -qq
    $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq firefox-esr >/dev/null
    ffv=$(firefox-esr --version 2>/dev/null | grep -oE '[0-9]+' | head -1 || true)
    [ -n "$ffv" ] && [ "$ffv" -ge 141 ] || { echo "firefox-esr ${ffv:-missing} < 141: WebGPU is not available in it (configure the bookworm-security source)" >&2; exit 1; }
  fi
fi
log "ready ($purpose)"
