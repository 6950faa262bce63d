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
# The ci demo test leaves its reconstructions here for the studio's browser tests. The script clears only
# the folder it owns (target/studio-fixtures); a folder the user names instead is never deleted: it must be
# empty or absent, so that no stale fixture from an earlier run is tested.
own_fixtures="$PWD/target/studio-fixtures"
export SILVR_STUDIO_FIXTURES="${SILVR_STUDIO_FIXTURES:-$own_fixtures}"
if [ "$(realpath -m "$SILVR_STUDIO_FIXTURES")" = "$(realpath -m "$own_fixtures")" ]; then
	rm -rf "$own_fixtures"
elif [ -n "$(ls -A "$SILVR_STUDIO_FIXTURES" 2>/dev/null)" ]; then
	echo "SILVR_STUDIO_FIXTURES=$SILVR_STUDIO_FIXTURES is not empty: empty it yourself or unset it (the script clears only $own_fixtures)" >&2
	exit 1
fi

# Every test's output goes to target/test-logs too; tests that skip print `SKIP: <test>: <why>` (the Rust
# tests through one helper, core/tests/common/skip.rs; node's test runner `# SKIP`), and the summary of them
# is printed at the end, pass or fail.
logs="$PWD/target/test-logs"
mkdir -p "$logs"
rm -f "$logs"/*.log
skip_summary() {
	local skips
	skips=$(cat "$logs"/*.log 2>/dev/null | grep -oE 'SKIP: .*|# SKIP.*' | sort -u || true)
	if [ -n "$skips" ]; then
		echo "== skipped tests ($(wc -l <<<"$skips")):"
		echo "$skips"
	else
		echo "== no test skipped"
	fi
}
cleanup=(skip_summary)
on_exit() {
	local i
	for ((i = ${#cleanup[@]} - 1; i >= 0; i--)); do ${cleanup[i]} || true; done
}
trap on_exit EXIT

# A private one-node Slurm for the reconstruct test (`silvr reconstruct --scheduler slurm`): started here as
# root wherever its daemons are installed or installable (Debian's slurmctld/slurmd/munged, no systemd
# needed), with its own config, munge, ports and state under target/slurm (a cluster's Slurm on this machine
# is never used or changed), reached through SLURM_CONF, and stopped by PID on exit. Elsewhere the test
# skips, and says so in the summary.
slurm_state="$PWD/target/slurm"
stop_slurm() { STATE="$slurm_state" scripts/slurm.sh down; }
if [ "$(id -u)" = 0 ] && [ "${SILVR_NO_SLURM:-0}" != 1 ] &&
	{ command -v apt-get >/dev/null || command -v slurmctld >/dev/null; }; then
	echo "== one-node Slurm (scripts/slurm.sh up)"
	cleanup+=(stop_slurm)
	if ! STATE="$slurm_state" scripts/slurm.sh up >"$logs/slurm-up.txt" 2>&1; then
		cat "$logs/slurm-up.txt"
		exit 1
	fi
	SLURM_CONF=$(STATE="$slurm_state" scripts/slurm.sh conf)
	export SLURM_CONF SILVR_REQUIRE_SLURM=1
fi

# The Python peers (SciPy for the evaluator, rosbags for ROS 1 / .db3 bags) live in the virtual environment
# scripts/setup.sh made (Debian's own Python refuses `pip install`, PEP 668); the Rust tests that call them
# find it through SILVR_PYTHON and must not skip.
venv="${SILVR_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/silvr-venv}"
[ -x "$venv/bin/python" ] || { echo "no Python environment at $venv: run scripts/setup.sh" >&2; exit 1; }
export SILVR_PYTHON="$venv/bin/python" SILVR_REQUIRE_PEERS=1

echo "== native tests (cargo test --workspace)"
# One build of every target first; the end-to-end tests then run its target/debug/silvr
# (SILVR_TESTS_PREBUILT) instead of `cargo build -p silvr`, which resolves features for one package and
# compiled naga, wgpu, image and our crates a second time.
cargo build --workspace --all-targets
SILVR_TESTS_PREBUILT=1 cargo test --workspace --no-fail-fast 2>&1 | tee "$logs/cargo-test.log"

echo "== evaluator cross-check against SciPy cKDTree (and scikit-image SSIM)"
"$venv/bin/python" scripts/crosscheck_eval.py

# The browser tests compile silvr-core for wasm32 (through silvr-web and silvr-worker): that is also the
# check that the engine has no native-only dependency in its wasm32 build.
echo "== browser tests"
scripts/browser-tests.sh 2>&1 | tee "$logs/browser-tests.log"
echo "== all tests passed"
