#!/usr/bin/env bash
# Fuzzes the parsers of untrusted input with cargo-fuzz (libFuzzer) for a bounded time each:
#   scripts/fuzz.sh [SECONDS_EACH=600] [TARGET ...]
#   targets: cdr pcd ply transforms_json rig_yaml colmap poses kitti_bin checkpoint view_link submap_tar http_head
# Runs on stable Rust with `--sanitizer none` (the parsers are safe Rust: the fuzzer hunts panics, hangs,
# overflow checks — debug assertions are on — and runaway allocation, capped by -rss_limit_mb). Installs
# cargo-fuzz when missing. Seeds: fuzz/seeds/<target> (committed); the growing corpus and any crash
# reproducers go to fuzz/corpus/ and fuzz/artifacts/ (git-ignored). Exits non-zero on the first crash.
set -euo pipefail
cd "$(dirname "$0")/.."
secs="${1:-600}"
[ $# -gt 0 ] && shift
targets=("$@")
[ ${#targets[@]} -gt 0 ] || targets=(cdr pcd ply transforms_json rig_yaml colmap poses kitti_bin checkpoint view_link submap_tar http_head)
command -v cargo-fuzz >/dev/null || { echo "[fuzz] cargo install cargo-fuzz"; cargo install -q cargo-fuzz --locked; }
# cargo-fuzz builds with its own flags: keep its artefacts apart from the workspace's target dir.
export CARGO_TARGET_DIR="${SILVR_FUZZ_TARGET_DIR:-$PWD/fuzz/target}"
unset RUSTC_WORKSPACE_WRAPPER CLIPPY_ARGS
for t in "${targets[@]}"; do
  mkdir -p "fuzz/corpus/$t"
  # A build failure is not a finding: report it as such, before any fuzzing starts.
  cargo fuzz build --fuzz-dir fuzz -s none --debug-assertions "$t" >"fuzz/corpus/$t.build.log" 2>&1 \
    || { echo "[fuzz] $t: the target does not build (fuzz/corpus/$t.build.log)"; exit 2; }
  echo "[fuzz] $t for ${secs} s"
  start=$(date +%s)
  log="fuzz/corpus/$t.log"
  status=0
  cargo fuzz run --fuzz-dir fuzz -s none --debug-assertions "$t" "fuzz/corpus/$t" "fuzz/seeds/$t" -- \
    -max_total_time="$secs" -rss_limit_mb=2048 -timeout=10 -print_final_stats=1 >"$log" 2>&1 || status=$?
  grep -E "^#[0-9]+ *DONE|stat::number_of_executed_units|stat::peak_rss_mb|ERROR|panicked|SUMMARY|Test unit written" "$log" || true
  [ "$status" = 0 ] || { echo "[fuzz] $t FAILED (exit $status) after $(( $(date +%s) - start )) s; log $log, reproducer in fuzz/artifacts/$t"; exit 1; }
  echo "[fuzz] $t: no crash in $(( $(date +%s) - start )) s"
done
