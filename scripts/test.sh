#!/usr/bin/env bash
# SiLVR Studio's test command (README): native tests with the WGSL kernels on wgpu (lavapipe where there is
# no GPU), the wasm32 build of the engine, and the browser tests (studio page + wasm-bindgen-test in Chromium).
# Installs missing tools first (scripts/setup.sh skips what is present).
set -euo pipefail
cd "$(dirname "$0")/.."
[ "${SILVR_SKIP_SETUP:-0}" = 1 ] || scripts/setup.sh

# Kernels must really run: a missing adapter fails the GPU tests instead of skipping them.
export SILVR_REQUIRE_GPU=1
# Prefer Vulkan (lavapipe or a real GPU); wgpu's GL path compiles shaders for minutes on llvmpipe.
export WGPU_BACKEND="${WGPU_BACKEND:-vulkan}"
# The ci demo test leaves its reconstructions here for the studio's browser tests.
export SILVR_STUDIO_FIXTURES="${SILVR_STUDIO_FIXTURES:-$PWD/target/studio-fixtures}"
rm -rf "$SILVR_STUDIO_FIXTURES"

# A one-node Slurm for the reconstruct test (`silvr reconstruct --scheduler slurm`): started here as root
# (Debian's slurmctld/slurmd/munge, no systemd needed) and stopped by PID on exit; elsewhere the test skips.
if [ "$(id -u)" = 0 ] && [ "${SILVR_NO_SLURM:-0}" != 1 ] && command -v apt-get >/dev/null; then
	echo "== one-node Slurm (scripts/slurm.sh up)"
	mkdir -p target
	if ! STATE="$PWD/target/slurm" scripts/slurm.sh up >target/slurm-up.log 2>&1; then
		cat target/slurm-up.log
		exit 1
	fi
	trap 'STATE="$PWD/target/slurm" scripts/slurm.sh down' EXIT
	export SILVR_REQUIRE_SLURM=1
fi

echo "== native tests (cargo test --workspace)"
# One build of every target first; the end-to-end tests then run its target/debug/silvr
# (SILVR_TESTS_PREBUILT) instead of `cargo build -p silvr`, which resolves features for one package and
# compiled naga, wgpu, image and our crates a second time.
cargo build --workspace --all-targets
SILVR_TESTS_PREBUILT=1 cargo test --workspace

echo "== evaluator cross-check against SciPy cKDTree (and scikit-image SSIM)"
python3 scripts/crosscheck_eval.py

# The browser tests compile silvr-core for wasm32 (through silvr-web and silvr-worker): that is also the
# check that the engine has no native-only dependency in its wasm32 build.
echo "== browser tests"
scripts/browser-tests.sh
echo "== all tests passed"
