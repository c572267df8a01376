#!/usr/bin/env bash
# usage: bash benchmarks/gpu_issue42_session.sh [dry]
#
# Issue 42 on a GPU in one call (at most 9 minutes), parts in order of importance:
#
#   1. first: the main job's first step at the paper preset (`python train.py --strategy epr
#      --preset paper`, psmnet-mtl), from an empty SLJAX_CACHE_DIR (cold) and from the cache
#      that run filled (warm): train.py's own "first step (...) N s", split into tracing,
#      lowering, XLA's compile (cuDNN autotuning included) and cache load, and three later
#      steps (benchmarks/bench_compile.py --part run).
#   2. kernels: PSMNet's training step at the paper preset (256x256, maxdisp 96, batch 12):
#      which convolutions run in cuDNN's sm80 `indexed` kernels and which bring `nchwToNhwc`
#      layout conversions, each kernel with its XLA operation and layer (jax.profiler;
#      benchmarks/profile_step.py --kernels).
#   3. fullres: full-resolution inference, PSMNet in pad mode, batch 1, maxdisp 192, at
#      1920x1080 and 2048x1500: time per pair and peak GPU memory, against the reference's own
#      forward in its own process, both padded to a multiple of 16 (benchmarks/bench_fullres.py).
#
# The reference side needs a local checkout of JiaRenChang/PSMNet (sljax neither ships nor
# fetches it) at .ref/PSMNet (or REFERENCE=DIR); without it part 3 runs sljax alone.
# Logs come back under $OUT (session.log first); the records go to $OUT/records/*.jsonl (copy
# them into benchmarks/results/). DEADLINE (seconds, default 530) bounds the whole; a part
# that would start too late is skipped and says so. A dry run on a CPU does the same at tiny
# sizes: OUT=/tmp/out bash benchmarks/gpu_issue42_session.sh dry
set -uo pipefail
cd "$(dirname "$0")/.."
dry=${1:-}
session=gpu_issue42_session deadline_s=530
source benchmarks/gpu_common.sh

first_args="--strategy epr --preset paper"
first="--part run --later-steps 3"
kernels="--size 256 --maxdisp 96 --batch 12 --kernels indexed,nchwToNhwc"
fullres="--size 1080x1920,1500x2048 --maxdisp 192 --models psmnet --repeats 2"
first_limit=270; kernels_limit=150; kernels_need=90; fullres_need=60
if [ -n "$dry" ]; then
  first_args="--strategy epr --preset quick --size 32x32 --maxdisp 16 --batch-size 2"
  first="--part run --later-steps 1"
  kernels="--size 64 --maxdisp 16 --batch 1 --kernels indexed,nchwToNhwc"
  fullres="--size 60x76,44x60 --maxdisp 16 --models psmnet --repeats 1"
  first_limit=400; kernels_limit=300; kernels_need=10; fullres_need=10
fi

header

log "1. bench_compile.py $first --train-args '$first_args' (within $first_limit s)"
timeout "$first_limit" $PY benchmarks/bench_compile.py $first --train-args "$first_args" \
  > "$OUT/first_step.log" 2>&1
ran; grep -E "^\||^First|runs on|recorded" "$OUT/first_step.log" | tee -a "$OUT/session.log"

if [ "$(left)" -ge "$kernels_need" ]; then
  limit=$(( $(left) < kernels_limit ? $(left) : kernels_limit ))
  log "2. profile_step.py $kernels (within $limit s)"
  timeout "$limit" $PY benchmarks/profile_step.py $kernels > "$OUT/kernels.log" 2>&1
  ran; grep -E "^\||device kernels|recorded|no device" "$OUT/kernels.log" |
    tee -a "$OUT/session.log"
else
  log "2. skipped: $(left) s left, the kernel profile needs about $kernels_need"
fi

if [ "$(left)" -ge "$fullres_need" ]; then
  log "3. bench_fullres.py $fullres $refarg (deadline $(left) s)"
  timeout "$(left)" $PY benchmarks/bench_fullres.py $fullres $refarg > "$OUT/fullres.log" 2>&1
  ran; cat "$OUT/fullres.log" | tee -a "$OUT/session.log"
else
  log "3. skipped: $(left) s left, full-resolution inference needs about $fullres_need"
fi
footer
