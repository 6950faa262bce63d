#!/usr/bin/env bash
# SiLVR Studio's main job (README): the demo on the built-in synthetic world. Extra arguments go to
# `silvr demo` (e.g. --preset default --seed 3 --out my-demo).
set -euo pipefail
cd "$(dirname "$0")/.."
[ "${SILVR_SKIP_SETUP:-0}" = 1 ] || scripts/setup.sh
export WGPU_BACKEND="${WGPU_BACKEND:-vulkan}"
if [ $# -eq 0 ]; then set -- --out silvr-demo; fi
exec cargo run --release -q -p silvr -- demo "$@"
