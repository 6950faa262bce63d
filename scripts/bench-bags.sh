#!/usr/bin/env bash
# Ingest throughput of one recording in three containers, side by side in one run: the synthetic world as
# our MCAP (zstd chunks), and as a ROS 1 bag (lz4 chunks) and a rosbag2 sqlite3 .db3 (uncompressed) written
# from it by the Python `rosbags` package (scripts/rosbags_peer.py). Each goes through `silvr bench-ingest`
# (read + decode every message, then the whole ingest), whose JSON lines are printed and kept in $OUT.
#   scripts/bench-bags.sh [PRESET=ci]      env: VENV (a Python with rosbags + mcap; default: the test venv),
#                                               WORK (scratch, default a temp dir), OUT (default bench-bags.jsonl)
set -euo pipefail
cd "$(dirname "$0")/.."
preset="${1:-ci}"
venv="${VENV:-${SILVR_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/silvr-venv}}"
"$venv/bin/python" -c 'import rosbags, mcap' 2>/dev/null || {
  echo "[bench-bags] $venv lacks rosbags/mcap: run scripts/setup.sh (or set VENV)" >&2; exit 1; }
work="${WORK:-$(mktemp -d)}"
out="${OUT:-bench-bags.jsonl}"
cargo build --release -q -p silvr
silvr=target/release/silvr
rm -rf "$work/synth" "$work/scene.bag" "$work/scene_db3"
"$silvr" synth --preset "$preset" --out "$work/synth" --mcap "$work/scene.mcap" --overwrite
"$venv/bin/python" scripts/rosbags_peer.py convert "$work/scene.mcap" --ros1 "$work/scene.bag" --db3 "$work/scene_db3"
: >"$out"
for bag in "$work/scene.mcap" "$work/scene.bag" "$work/scene_db3"; do
  echo "[bench-bags] $bag"
  "$silvr" bench-ingest "$bag" --config "$work/scene.rig.yaml" --reps 3 | tee /dev/stderr |
    python3 -c 'import json,sys; print(json.dumps(json.load(sys.stdin)))' >>"$out"
done
echo "[bench-bags] results in $out (machine: $(nproc) cores, $(date -I))"
