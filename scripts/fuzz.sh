#!/usr/bin/env bash
# Fuzzes the parsers of untrusted input with cargo-fuzz (libFuzzer) for a bounded time each:
#   scripts/fuzz.sh [SECONDS_EACH=600] [TARGET ...]
#   scripts/fuzz.sh --smoke [TARGET ...]    CI: every target built once, then each run for
#                                           SILVR_FUZZ_SMOKE_SECS (default 4) seconds
#   targets: cdr pcd ply transforms_json rig_yaml colmap poses kitti_bin checkpoint view_link submap_tar
#            npz mcap http_head kitti_text ros1_bag ros1_definition rosbag2_metadata rosbag2_db3 scan_file
#            copc_file
# Runs on stable Rust with `--sanitizer none` (the parsers are safe Rust: the fuzzer hunts panics, hangs,
# overflow checks — debug assertions are on — and runaway allocation, capped by -rss_limit_mb). Installs
# cargo-fuzz when missing. Seeds: fuzz/seeds/<target> (committed); the growing corpus and any crash
# reproducers go to fuzz/corpus/ and fuzz/artifacts/ (git-ignored). Exits non-zero on the first crash (1)
# or when a target does not build (2).
set -euo pipefail
cd "$(dirname "$0")/.."
all=(cdr pcd ply transforms_json rig_yaml colmap poses kitti_bin checkpoint view_link submap_tar npz mcap http_head kitti_text ros1_bag ros1_definition rosbag2_metadata rosbag2_db3 scan_file copc_file)
smoke=0
if [ "${1:-}" = --smoke ]; then
  smoke=1
  shift
  secs="${SILVR_FUZZ_SMOKE_SECS:-4}"
else
  secs="${1:-600}"
  [ $# -gt 0 ] && shift
fi
targets=("$@")
[ ${#targets[@]} -gt 0 ] || targets=("${all[@]}")
command -v cargo-fuzz >/dev/null || { echo "[fuzz] cargo install cargo-fuzz"; cargo install -q cargo-fuzz --locked; }
# cargo-fuzz builds with its own flags: keep its artefacts apart from the workspace's target dir.
export CARGO_TARGET_DIR="${SILVR_FUZZ_TARGET_DIR:-$PWD/fuzz/target}"
unset RUSTC_WORKSPACE_WRAPPER CLIPPY_ARGS
mkdir -p fuzz/corpus
flags=(--fuzz-dir fuzz -s none --debug-assertions)
# The smoke builds unoptimised (`--dev`): its seconds of fuzzing need no speed, and CI's cold build of every
# target (wgpu, naga, image and our crates under coverage instrumentation) drops from about 20 minutes to
# what BENCHMARKS.md records.
[ "$smoke" = 0 ] || flags+=(--dev)
# One input may take this long before it counts as a hang: unoptimised, the mcap target's largest legal
# record length (zeroed by the mcap crate before reading) takes ~12 s, where the release build takes < 1 s.
unit_timeout=10
[ "$smoke" = 0 ] || unit_timeout=60
build() { # TARGET... (none: all of them, in one cargo build)
  local log="fuzz/corpus/${1:-all}.build.log" start
  start=$(date +%s)
  # A build failure is not a finding: report it as such, before any fuzzing starts.
  cargo fuzz build "${flags[@]}" "$@" >"$log" 2>&1 \
    || { tail -n 30 "$log"; echo "[fuzz] ${*:-the fuzz crate} does not build ($log)"; exit 2; }
  echo "[fuzz] built ${*:-every target} in $(( $(date +%s) - start )) s"
}
[ "$smoke" = 0 ] || build
for t in "${targets[@]}"; do
  mkdir -p "fuzz/corpus/$t"
  [ "$smoke" = 1 ] || build "$t"
  echo "[fuzz] $t for ${secs} s"
  start=$(date +%s)
  log="fuzz/corpus/$t.log"
  status=0
  cargo fuzz run "${flags[@]}" "$t" "fuzz/corpus/$t" "fuzz/seeds/$t" -- \
    -max_total_time="$secs" -rss_limit_mb=2048 -timeout="$unit_timeout" -print_final_stats=1 >"$log" 2>&1 || status=$?
  grep -E "^#[0-9]+ *DONE|stat::number_of_executed_units|stat::peak_rss_mb|ERROR|panicked|SUMMARY|Test unit written" "$log" || true
  [ "$status" = 0 ] || { tail -n 40 "$log"; echo "[fuzz] $t FAILED (exit $status) after $(( $(date +%s) - start )) s; log $log, reproducer in fuzz/artifacts/$t"; exit 1; }
  echo "[fuzz] $t: no crash in $(( $(date +%s) - start )) s"
done
