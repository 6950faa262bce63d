#!/usr/bin/env bash
# Lidar odometry side by side (issue 34): `silvr odometry` against KISS-ICP 1.3.0 (Python, PyPI) on the same
# points, scored by the same code (`silvr eval-poses --align se3` against exact ground truth).
#
#   scripts/bench-odometry.sh
#
# Inputs: the real KITTI snippets in ../shared/data/real/kitti_odometry (sequences 00 and 03, 10 sweeps each,
# motion-compensated: both tools without deskew) when present, and the synthetic bags (`silvr synth
# --preset micro|ci --mcap`, per-point times: both tools deskew), plus any bag named in EXTRA_BAGS (a
# `silvr synth --mcap` bag whose dataset folder lies beside it with the same stem, e.g. the default world).
# `silvr odometry --export-sweeps` writes each sweep as read, and scripts/kiss_icp_peer.py runs KISS-ICP on
# exactly those points with its default configuration. Time per sweep: the odometry alone in both
# (KissICP.register_frame; ours without reading the bag), both on every core of this machine.
#
# Environment: OUT=FILE summary JSON (default target/bench-odometry/summary.json); WORK=DIR (default a new
# /tmp/bench-odometry.XXXXXX); SILVR=BIN (no build); KISS_VENV=DIR (default ~/.cache/silvr-kiss-venv).
# KISS-ICP is installed into its own virtual environment; it is never a product dependency.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
OUT="${OUT:-$ROOT/target/bench-odometry/summary.json}"
WORK="${WORK:-$(mktemp -d /tmp/bench-odometry.XXXXXX)}"
VENV="${KISS_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/silvr-kiss-venv}"
mkdir -p "$(dirname "$OUT")" "$WORK"
log() { echo "[bench-odometry] $*" >&2; }

if [ -z "${SILVR:-}" ]; then
  (cd "$ROOT" && cargo build --release -p silvr --bin silvr >&2)
  SILVR="$ROOT/target/release/silvr"
fi
if ! "$VENV/bin/python" -c 'import kiss_icp' >/dev/null 2>&1; then
  log "python3 -m venv $VENV + pip install kiss-icp==1.3.0"
  python3 -m venv "$VENV"
  "$VENV/bin/python" -m pip install --quiet 'kiss-icp==1.3.0'
fi

rows=()
run_pair() { # name input deskew(auto|off) gt_args...
  local name=$1 input=$2 deskew=$3; shift 3
  local d="$WORK/$name"; mkdir -p "$d"
  log "$name: silvr odometry"
  "$SILVR" odometry "$input" --out "$d/silvr.tum" --deskew "$deskew" --export-sweeps "$d/sweeps" \
    --report "$d/silvr.json" "$@" 2>"$d/silvr.log"
  local gt="$d/gt.tum"
  [ -f "$gt" ] || gt="$GT_FILE"
  log "$name: KISS-ICP"
  local kflag=(); [ "$deskew" = auto ] && kflag=(--deskew)
  "$VENV/bin/python" "$ROOT/scripts/kiss_icp_peer.py" "$d/sweeps" "$d/kiss.tum" "${kflag[@]}" >"$d/kiss.json"
  "$SILVR" eval-poses --est "$d/silvr.tum" --gt "$gt" --align se3 --out "$d/silvr_err.json" 2>/dev/null
  "$SILVR" eval-poses --est "$d/kiss.tum" --gt "$gt" --align se3 --out "$d/kiss_err.json" 2>/dev/null
  rows+=("$name")
}

KITTI="$ROOT/../shared/data/real/kitti_odometry/sequences"
for seq in 00 03; do
  if [ -d "$KITTI/$seq/velodyne" ]; then
    GT_FILE="" run_pair "kitti_$seq" "$KITTI/$seq" off --gt-out "$WORK/kitti_$seq/gt.tum"
  fi
done
bags=()
for preset in micro ci; do
  log "synth --preset $preset --mcap"
  "$SILVR" synth --preset "$preset" --out "$WORK/$preset" --mcap "$WORK/$preset.mcap" --overwrite >/dev/null 2>&1
  bags+=("$WORK/$preset.mcap")
done
for b in ${EXTRA_BAGS:-}; do bags+=("$b"); done
for bag in "${bags[@]}"; do
  name=$(basename "$bag" .mcap); ds="${bag%.mcap}"
  # The exact lidar trajectory on the bag's clock (synthetic bags: simulation time + EPOCH).
  awk 'NR==1{print;next}{printf "%.9f", $1+1700000000; for(i=2;i<=8;i++) printf " %s", $i; print ""}' \
    "$ds/poses/odometry_lidar_tum.txt" >"$WORK/${name}_gt.tum"
  GT_FILE="$WORK/${name}_gt.tum" run_pair "$name" "$bag" auto --gt "$WORK/${name}_gt.tum"
done

python3 - "$WORK" "$OUT" "${rows[@]}" <<'PY'
import json, sys, platform, os
work, out, names = sys.argv[1], sys.argv[2], sys.argv[3:]
summary = {"machine": platform.processor() or platform.machine(), "cores": os.cpu_count(), "inputs": {}}
print(f"{'input':<10} {'tool':<8} {'sweeps':>6} {'ATE m':>7} {'RPE m':>7} {'RPE deg':>8} {'rot deg':>8} {'ms/sweep':>9}")
for n in names:
    d = os.path.join(work, n)
    row = {}
    for tool, rep, err in [("silvr", "silvr.json", "silvr_err.json"), ("kiss-icp", "kiss.json", "kiss_err.json")]:
        r = json.load(open(os.path.join(d, rep)))
        e = json.load(open(os.path.join(d, err)))
        row[tool] = {"sweeps": r["sweeps"], "ms_per_sweep_median": r["ms_per_sweep_median"],
                     "ate_rmse_m": e["ate_rmse_m"], "rpe_trans_rmse_m": e["rpe_trans_rmse_m"],
                     "rpe_rot_rmse_deg": e["rpe_rot_rmse_deg"], "rot_rmse_deg": e["rot_rmse_deg"]}
        x = row[tool]
        print(f"{n:<10} {tool:<8} {x['sweeps']:>6} {x['ate_rmse_m']:>7.3f} {x['rpe_trans_rmse_m']:>7.3f} "
              f"{x['rpe_rot_rmse_deg']:>8.2f} {x['rot_rmse_deg']:>8.2f} {x['ms_per_sweep_median']:>9.1f}")
    row["ate_ratio_silvr_over_kiss"] = row["silvr"]["ate_rmse_m"] / max(row["kiss-icp"]["ate_rmse_m"], 1e-12)
    row["time_ratio_silvr_over_kiss"] = row["silvr"]["ms_per_sweep_median"] / row["kiss-icp"]["ms_per_sweep_median"]
    summary["inputs"][n] = row
tmp = out + ".tmp"
json.dump(summary, open(tmp, "w"), indent=2)
os.replace(tmp, out)
print(f"summary: {out}")
PY
