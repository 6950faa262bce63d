#!/usr/bin/env bash
# GPU benchmark + quality run for a lent NVIDIA machine (the `device` tool): the stripped release binary
# travels in .devbin/, the Vulkan loader in .gl/ (see BENCHMARKS.md). Writes JSON + a log under $OUT.
# Every stage is time-boxed so the whole script ends inside one device call.
set -u
OUT=${OUT:-/tmp/silvr-device}
mkdir -p "$OUT"
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
B=./.devbin/silvr
export WGPU_BACKEND=vulkan
log() { echo "[$(date +%T)] $*" | tee -a "$OUT/log.txt"; }
if ! $B gpu-info >>"$OUT/log.txt" 2>&1; then
  export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
  $B gpu-info >>"$OUT/log.txt" 2>&1 || { log "no Vulkan adapter"; exit 1; }
fi
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv >>"$OUT/log.txt" 2>&1
log "synth ci"
timeout 120 $B synth --preset ci --out /tmp/ci >>"$OUT/log.txt" 2>&1
log "bench: WGSL nerfacto 4096 rays"
timeout 70 $B bench-train /tmp/ci --backend wgpu --model nerfacto --rays 4096 --steps 4000 --target-psnr 25 --max-seconds 50 >"$OUT/bench_wgpu_nerfacto.json" 2>>"$OUT/log.txt"
log "bench: WGSL small 1024 rays (the ci demo's model) vs the CPU reference on 16 cores"
timeout 60 $B bench-train /tmp/ci --backend wgpu --model small --rays 1024 --steps 300 --target-psnr 25 --max-seconds 40 >"$OUT/bench_wgpu_small.json" 2>>"$OUT/log.txt"
timeout 60 $B bench-train /tmp/ci --backend cpu --model small --rays 1024 --steps 300 --target-psnr 25 --max-seconds 40 >"$OUT/bench_cpu_small.json" 2>>"$OUT/log.txt"
for mode in silvr vision; do
  log "train $mode: WGSL nerfacto, ${STEPS:-2000} steps x 4096 rays"
  timeout 130 $B train /tmp/ci --mode $mode --backend wgpu --model nerfacto --steps "${STEPS:-2000}" --rays 4096 \
    --checkpoint-every 0 --out /tmp/tr_$mode >>"$OUT/log.txt" 2>&1
  cp /tmp/tr_$mode/train.json "$OUT/train_$mode.json" 2>/dev/null
  timeout 60 $B eval --reconstruction /tmp/tr_$mode/points.ply --gt /tmp/ci --out "$OUT/eval_$mode.json" >>"$OUT/log.txt" 2>&1
done
log "demo ci on WGSL: refined poses, the metric uncertainty and its reliability (the CI test's run)"
timeout 240 $B demo --preset ci --backend wgpu --out /tmp/demo >>"$OUT/log.txt" 2>&1
cp /tmp/demo/report.json "$OUT/demo_report.json" 2>/dev/null
cp /tmp/demo/silvr/reliability.json "$OUT/demo_reliability.json" 2>/dev/null
log "done"
