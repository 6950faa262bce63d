#!/usr/bin/env bash
# SiLVR Studio's main job (README): the demo on the built-in synthetic world. Extra arguments go to
# `silvr demo` (e.g. --preset default --seed 3 --out my-demo).
set -euo pipefail
cd "$(dirname "$0")/.."
# The demo needs only the Vulkan driver (lavapipe where there is no GPU), not the studio's tools.
[ "${SILVR_SKIP_SETUP:-0}" = 1 ] || scripts/setup.sh demo
export WGPU_BACKEND="${WGPU_BACKEND:-vulkan}"
if [ $# -eq 0 ]; then set -- --out silvr-demo; fi
exec cargo run --release -q -p silvr -- demo "$@"
