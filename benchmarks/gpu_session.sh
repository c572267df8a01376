#!/usr/bin/env bash
# usage: bash benchmarks/gpu_session.sh suite|speed|step [dry]
#
# What a machine with a GPU shows, one part a call of the device tool, results under $OUT
# (session.log first; the benchmarks' records in $OUT/records, to append to benchmarks/results/):
#   suite  the whole test suite on the GPU as tests/conftest.py sets it there (`highest`
#          precision, XLA's deterministic GPU operations), 8 workers, one line a test.
#   speed  bench_gpu.py: PSMNet's and unet-sl's forward and forward + backward beside PyTorch
#          on the same GPU (the reference PSMNet when .ref/PSMNet is carried), GPU against CPU
#          agreement, peak memory.
#   step   bench_train.py --step-only: PSMNet's and the twin's compiled training step at the
#          paper preset in float32 and bf16, one process each, alone on the GPU.
# `dry` runs the same at a tiny size, on any machine (check a part on a CPU before a GPU call):
#   OUT=/tmp/gpu bash benchmarks/gpu_session.sh step dry
# `speed` compares with the reference PyTorch PSMNet when a checkout of it is in .ref/PSMNet
# (mkdir -p .ref && cp -r PSMNET_CHECKOUT .ref/PSMNet, or REFERENCE=DIR); without one it times
# sljax alone. The plumbing the session scripts share is benchmarks/gpu_common.sh.
set -uo pipefail
cd "$(dirname "$0")/.."
part=${1:-}
dry=${2:-}
case "$part" in suite|speed|step) ;; *)
  echo "usage: bash benchmarks/gpu_session.sh suite|speed|step [dry]" >&2; exit 2 ;;
esac
session=gpu_session deadline_s=540
source benchmarks/gpu_common.sh
header "part $part"

if [ "$part" = suite ]; then
  export XLA_PYTHON_CLIENT_PREALLOCATE=false  # the workers share the GPU's memory
  # The console script `sljax`, which some tests run, from the checkout without a network.
  $PY -m pip install -q --no-deps --no-build-isolation --no-index -e . > "$OUT/install.log" 2>&1
  xd="-n 8"; files=""; limit=${LIMIT:-540}
  [ -n "$dry" ] && xd="-n 2" && files="tests/test_correlation.py tests/test_losses.py" && limit=150
  log "pytest $xd --dist loadfile -v $files"
  timeout "$limit" $PY -m pytest $xd --dist loadfile -v -p no:cacheprovider \
    -o addopts="-ra --durations=25" --tb=line $files > "$OUT/tests-suite.log" 2>&1
  ran; grep -E "^(FAILED|ERROR)|passed|failed" "$OUT/tests-suite.log" | tail -40 | tee -a "$OUT/session.log"
elif [ "$part" = speed ]; then
  args="--batch 4 --models psmnet,unet-sl"
  [ -n "$dry" ] && args="--size 64 --maxdisp 32 --batch 1 --repeats 1 --models psmnet"
  log "bench_gpu $args $refarg"
  timeout 540 $PY benchmarks/bench_gpu.py $args $refarg > "$OUT/bench_gpu.log" 2>&1
  ran; cat "$OUT/bench_gpu.log" >> "$OUT/session.log"
else
  args="--preset paper --steps 20"; limit=270
  [ -n "$dry" ] && args="--preset quick --steps 2" && limit=200
  for net in psmnet psmnet-mtl; do
    for precision in fp32 bf16; do
      log "bench_train $args --net $net --step-only --precision $precision"
      timeout "$limit" $PY benchmarks/bench_train.py $args --net $net --step-only \
        --precision $precision > "$OUT/bench_train-$net-$precision.log" 2>&1
      ran; grep -v cuda_timer "$OUT/bench_train-$net-$precision.log" | tail -6 | tee -a "$OUT/session.log"
    done
  done
fi
footer
