#!/usr/bin/env bash
# usage: bash benchmarks/gpu_issue49_session.sh [dry]
#
# Issue 49's item 5 on a GPU in one call (at most 9 minutes): where the targets stand, parts in
# order of importance (each later part runs only if the deadline leaves it time):
#
#   1. first: the main job's first step at the paper preset (`python train.py --strategy epr
#      --preset paper`, psmnet-mtl), from an empty SLJAX_CACHE_DIR (cold) and from the cache
#      that run filled (warm): train.py's own "first step (...) N s" and three later steps
#      (benchmarks/bench_compile.py --part run). Targets: <= 30 s cold, <= 5 s warm.
#   2. step: PSMNet's training step at the paper shape (256x256, maxdisp 96, batch 12), TF32
#      (fp32, each side's default) and bf16, each side in its own process against the
#      reference's (benchmarks/bench_gpu.py --part step), with sljax's top 8 device kernels.
#      Targets: <= 0.45x the reference in TF32, <= 0.3x in bf16.
#   3. fullres: full-resolution inference, PSMNet in pad mode, batch 1, maxdisp 192, at
#      1920x1080, against the reference's forward in its own process (bench_fullres.py).
#   4. kernels: which convolutions run in cutlass `analytic` kernels (24% of the TF32 step on an
#      H200, 2026-11-28, layer unknown) and cuDNN's `indexed` ones, and which bring
#      `nchwToNhwc` conversions, each with its layer (profile_step.py --kernels).
#   5. nhwc: part 2's TF32 step, sljax alone, with XLA_FLAGS=--xla_gpu_force_conv_nhwc=true: XLA
#      lays float32 convolutions out NCHW (dim_labels bf012 on the H200), so cuDNN converts
#      each 3D convolution's operands (`nchwToNhwc`) and its forwards run outside the `indexed`
#      kernels; in bf16 they run NHWC. Compare with part 2's sljax TF32 row of the same call.
#   6. autotune: part 1 again (cold and warm) with XLA:GPU's convolution autotuning off
#      (XLA_FLAGS=--xla_gpu_autotune_level=0): how much of the cold compile it is, and what the
#      later steps pay for cuDNN's heuristic choice instead.
#
# PARTS (default: first,step,fullres,kernels,nhwc,autotune) chooses the parts, in that order; each
# runs only if the deadline leaves it about the time it needs.
#
# The reference side needs a local checkout of JiaRenChang/PSMNet (sljax neither ships nor
# fetches it) at .ref/PSMNet (or REFERENCE=DIR). Logs come back under $OUT (session.log
# first); records go to $OUT/records/*.jsonl (copy them into benchmarks/results/). DEADLINE
# (seconds, default 530) bounds the whole. A dry run on a CPU does the same at tiny sizes:
# OUT=/tmp/out bash benchmarks/gpu_issue49_session.sh dry
# Where the GPU machine takes a working tree of at most 64 MiB, leave out docs/results (91 MiB
# of committed experiment records; the benchmarks need none of it).
set -uo pipefail
cd "$(dirname "$0")/.."
dry=${1:-}
session=gpu_issue49_session deadline_s=530
source benchmarks/gpu_common.sh
parts=",${PARTS:-first,step,fullres,kernels,nhwc,autotune},"

first_args="--strategy epr --preset paper"
first="--part run --later-steps 3"
step="--shapes paper --precisions fp32,bf16 --impls gpu --twin none --steps 10 --warmup 3"
step="$step --profile-top 8"
fullres="--size 1080x1920 --maxdisp 192 --models psmnet --repeats 2"
kernels="--size 256 --maxdisp 96 --batch 12 --kernels analytic,indexed,nchwToNhwc"
nhwc="--shapes paper --precisions fp32 --impls gpu --twin none --steps 10 --warmup 3 --profile-top 8"
first_limit=230; step_need=150; fullres_need=60; kernels_need=80; nhwc_need=110; autotune_need=120
if [ -n "$dry" ]; then
  first_args="--strategy epr --preset quick --size 32x32 --maxdisp 16 --batch-size 2"
  first="--part run --later-steps 1"
  step="--shapes 256x256x16x2 --precisions fp32,bf16 --impls gpu --twin none --steps 2"
  step="$step --warmup 1 --profile-top 3"
  fullres="--size 256x256 --maxdisp 16 --models psmnet --repeats 1"
  kernels="--size 64 --maxdisp 16 --batch 1 --kernels analytic,indexed,nchwToNhwc"
  nhwc="--shapes 256x256x16x2 --precisions fp32 --impls gpu --twin none --steps 2 --warmup 1"
  first_limit=400; step_need=10; fullres_need=10; kernels_need=10; nhwc_need=10; autotune_need=10
fi
# part NAME NEED: whether to run part NAME now (chosen in PARTS, NEED seconds left), else why not
part() {
  case "$parts" in *",$1,"*) ;; *) return 1 ;; esac
  [ "$(left)" -ge "$2" ] && return 0
  log "$1: skipped, $(left) s left, it needs about $2"; return 1
}
first_rows() { grep -E "^\||^First|^programs before|runs on|recorded" "$1" | tee -a "$OUT/session.log"; }

header

if part first 1; then
  log "1. bench_compile.py $first --train-args '$first_args' (within $first_limit s)"
  timeout "$first_limit" $PY benchmarks/bench_compile.py $first --train-args "$first_args" \
    > "$OUT/first_step.log" 2>&1
  ran; first_rows "$OUT/first_step.log"
fi

if part step "$step_need"; then
  log "2. bench_gpu.py --part step $step (deadline $(( $(left) - 40 )) s)"
  timeout "$(left)" $PY benchmarks/bench_gpu.py --part step $step \
    --deadline $(( $(left) - 40 )) $refarg > "$OUT/step.log" 2>&1
  ran; grep -E "^\||runs? on|recorded" "$OUT/step.log" | tee -a "$OUT/session.log"
fi

if part fullres "$fullres_need"; then
  log "3. bench_fullres.py $fullres $refarg (deadline $(left) s)"
  timeout "$(left)" $PY benchmarks/bench_fullres.py $fullres $refarg > "$OUT/fullres.log" 2>&1
  ran; cat "$OUT/fullres.log" | tee -a "$OUT/session.log"
fi

if part kernels "$kernels_need"; then
  log "4. profile_step.py $kernels (deadline $(left) s)"
  timeout "$(left)" $PY benchmarks/profile_step.py $kernels > "$OUT/kernels.log" 2>&1
  ran; grep -E "^\||device kernels|recorded|no device" "$OUT/kernels.log" |
    tee -a "$OUT/session.log"
fi

if part nhwc "$nhwc_need"; then
  log "5. XLA_FLAGS=--xla_gpu_force_conv_nhwc=true bench_gpu.py --part step $nhwc (deadline $(left) s)"
  XLA_FLAGS="${XLA_FLAGS:-} --xla_gpu_force_conv_nhwc=true" timeout "$(left)" \
    $PY benchmarks/bench_gpu.py --part step $nhwc --deadline $(( $(left) - 20 )) \
    > "$OUT/nhwc.log" 2>&1
  ran; grep -E "^\||runs? on|recorded" "$OUT/nhwc.log" | tee -a "$OUT/session.log"
fi

if part autotune "$autotune_need"; then
  log "6. XLA_FLAGS=--xla_gpu_autotune_level=0 bench_compile.py $first (deadline $(left) s)"
  XLA_FLAGS="${XLA_FLAGS:-} --xla_gpu_autotune_level=0" timeout "$(left)" \
    $PY benchmarks/bench_compile.py $first --train-args "$first_args" > "$OUT/autotune.log" 2>&1
  ran; first_rows "$OUT/autotune.log"
fi
footer
