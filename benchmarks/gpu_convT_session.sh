#!/usr/bin/env bash
# usage: bash benchmarks/gpu_convT_session.sh [dry]
#
# The transposed-convolution study on a GPU in one call (about 8 minutes):
#
#   1. convT: PSMNet's transposed 3D convolutions (conv6, conv5) at the paper preset's shapes,
#      every form (lax, gpu, gpu-phase, gpu-autodiff, fast) and program (fwd, dx, dk, both),
#      the gradients alone and together profiled: which gradient lands in cuDNN's
#      fallback kernel, and which form avoids it (benchmarks/bench_convT.py).
#   2. step: the whole training step at the paper preset (256x256, maxdisp 96, batch 12) in
#      default float32, each side in its own process: the reference PSMNet (PyTorch,
#      cudnn.benchmark), sljax with "gpu" (compiled cold, then again from the compile cache:
#      the warm start), "lax" (today's) and "gpu-phase", each with its top kernels
#      (benchmarks/bench_gpu.py --part step).
#   3. if the deadline allows: the same at PSMNet's training crop (256x512, maxdisp 192,
#      batch 8), gpu against the reference.
#
# The reference side needs a local checkout of JiaRenChang/PSMNet (sljax neither ships nor
# fetches it) at .ref/PSMNet: mkdir -p .ref && cp -r PSMNET_CHECKOUT .ref/PSMNet.
# Logs and the records come back under $OUT (session.log first; records/*.jsonl go to
# benchmarks/results/). DEADLINE (seconds, default 450) bounds the whole; a part that would
# start too late is skipped and says so. A dry run on a CPU does the same at tiny sizes
# (REFERENCE=DIR names the checkout when .ref/PSMNet is absent):
#   OUT=/tmp/out REFERENCE=/tmp/psmnet-ref bash benchmarks/gpu_convT_session.sh dry
set -uo pipefail
cd "$(dirname "$0")/.."
dry=${1:-}
session=gpu_convT_session deadline_s=450
source benchmarks/gpu_common.sh

convT="--shapes paper --profile dx,dk,both"
step="--shapes paper --precisions fp32 --impls gpu,lax,gpu-phase --twin none --warm-start"
step="$step --profile-top 8"
crop="--shapes crop --precisions fp32 --impls gpu --twin none"
convT_limit=200; crop_need=150
if [ -n "$dry" ]; then
  convT="--shapes paper --profile dx,dk,both --tiny"
  step="--shapes 256x256x16x2 --precisions fp32 --impls gpu,lax --twin none --warm-start"
  step="$step --profile-top 4 --steps 1 --warmup 1"
  crop="--shapes 256x256x16x2 --precisions bf16 --impls gpu --twin none --steps 1 --warmup 1"
  convT_limit=600; crop_need=300
fi

header

log "1. bench_convT.py $convT (within $convT_limit s)"
timeout "$convT_limit" $PY benchmarks/bench_convT.py $convT > "$OUT/bench_convT.log" 2>&1
ran; grep -E "^\||top kernels|^ +[0-9.]+ ms" "$OUT/bench_convT.log" | tee -a "$OUT/session.log"

log "2. bench_gpu.py --part step $step (deadline $(left) s)"
timeout "$(left)" $PY benchmarks/bench_gpu.py --part step $step $refarg \
  --deadline "$(($(left) - 5))" > "$OUT/step.log" 2>&1
ran; grep -E "^\||^Training|ran on|recorded" "$OUT/step.log" | tee -a "$OUT/session.log"

if [ "$(left)" -ge "$crop_need" ]; then
  log "3. bench_gpu.py --part step $crop (deadline $(left) s)"
  timeout "$(left)" $PY benchmarks/bench_gpu.py --part step $crop $refarg \
    --deadline "$(($(left) - 5))" > "$OUT/step-crop.log" 2>&1
  ran; grep -E "^\||recorded" "$OUT/step-crop.log" | tee -a "$OUT/session.log"
else
  log "3. skipped: $(left) s left, the crop shape needs about $crop_need"
fi
footer
