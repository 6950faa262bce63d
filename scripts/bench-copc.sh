#!/usr/bin/env bash
# Time and peak memory of `silvr export copc` on generated clouds of growing size (issue 36), with
# `silvr export las` (whole cloud in memory, no octree) beside it where it fits in memory.
#
#   scripts/bench-copc.sh [WORK_DIR] [SIZES...]       e.g. scripts/bench-copc.sh /tmp/copc-bench 1000000 20000000
#
# Needs a release build (cargo build --release --workspace) and numpy (scripts/setup.sh's venv or the system's).
# Each cloud is removed after its runs, so the disk holds one input, one temporary LAS and one output at a time
# (about 47 + 56 + 25 bytes a point).
#
# Memory: "peak RSS" counts the pages of copc-writer's memory-mapped spill file, which the kernel drops under
# pressure; "anon" is the peak of the process's own (anonymous) memory, sampled every 0.1 s from /proc. With
# SILVR_BENCH_MEM_LIMIT=4G and a writable cgroup v1 memory controller, each export runs capped there (page
# cache included), so a run that finishes shows the bound holds.
set -euo pipefail
cd "$(dirname "$0")/.."
work=${1:-/tmp/copc-bench}
shift || true
sizes=("$@")
[ ${#sizes[@]} -gt 0 ] || sizes=(1000000 5000000 20000000)
py=${SILVR_PYTHON:-python3}
bin=target/release/silvr
[ -x "$bin" ] || { echo "build first: cargo build --release --workspace" >&2; exit 1; }
mkdir -p "$work"
echo "# $(date -u +%F) $(nproc) cores, $(awk '/MemTotal/ {printf "%.0f GiB", $2/1048576}' /proc/meminfo); $(git rev-parse --short HEAD)"
limit=${SILVR_BENCH_MEM_LIMIT:-}
cg=/sys/fs/cgroup/memory/silvr-bench-$$
if [ -n "$limit" ]; then
  mkdir "$cg" && echo "$limit" >"$cg/memory.limit_in_bytes" || { echo "no cgroup v1 memory controller to cap at $limit" >&2; exit 1; }
  trap 'rmdir "$cg" 2>/dev/null || true' EXIT
  echo "# each export capped at $limit (cgroup v1 memory.limit_in_bytes, page cache included)"
fi
printf "%-12s %-6s %10s %12s %12s %12s\n" points command seconds "peak RSS MB" "anon MB" "output MB"
for n in "${sizes[@]}"; do
  ply="$work/cloud$n.ply"
  "$py" scripts/gen_cloud.py "$n" "$ply" 2>/dev/null
  for cmd in copc las; do
    # The in-memory LAS export holds every point twice over; past 20 M it says nothing new.
    if [ "$cmd" = las ] && [ "$n" -gt 20000000 ]; then continue; fi
    out="$work/out$n.$cmd.laz"
    (
      [ -z "$limit" ] || echo $BASHPID >"$cg/cgroup.procs"
      exec /usr/bin/time -f "%e %M" -o "$work/time" "$bin" export "$cmd" "$ply" --out "$out" >/dev/null
    ) &
    runner=$!
    anon=0
    while kill -0 "$runner" 2>/dev/null; do
      pid=$(pgrep -n -f "$bin export $cmd" || true)
      if [ -n "$pid" ]; then
        a=$(awk '/RssAnon/ {print $2}' "/proc/$pid/status" 2>/dev/null || echo 0)
        [ "${a:-0}" -gt "$anon" ] && anon=$a
      fi
      sleep 0.1
    done
    wait "$runner"
    read -r secs kb <"$work/time"
    printf "%-12s %-6s %10s %12s %12s %12.1f\n" "$n" "$cmd" "$secs" "$((kb / 1024))" "$((anon / 1024))" "$(($(stat -c %s "$out") / 1000))e-3"
    rm -f "$out"
  done
  rm -f "$ply"
done
