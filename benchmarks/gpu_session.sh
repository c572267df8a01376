#!/usr/bin/env bash
# The plan for a session lent a GPU (the device tool: 30 min of device time, 10 min a call),
# written and dry-run on a CPU beforehand so the GPU's minutes go to measuring. Three calls:
#
#   check: which tests pass on the GPU, at XLA's default float32 (TF32 allowed) and at
#          'highest' (the reference test).
#   speed: bench_gpu: PSMNet's GPU forward against the CPU's, PSMNet's and unet-sl's speed beside
#          PyTorch on the same GPU (the reference PSMNet when .ref/PSMNet is carried), peak memory.
#   train: the real training step and loop (bench_train, paper preset, the twin, fp32 and
#          bf16: is the data pipeline hidden behind a GPU step?) and the main job,
#          `python train.py --strategy epr --preset paper`, for two and a half minutes.
#
# From the device tool (the machine's image has jax with CUDA, flax, optax, orbax, OpenCV and
# a CUDA torch; nothing is installed, sljax runs from the checkout):
#   here, once:  echo /.ref/ >> .git/info/exclude && mkdir -p .ref && cp -r PSMNET_CHECKOUT .ref/PSMNet
#   run(command="bash benchmarks/gpu_session.sh check", timeout_s=600)
#   run(command="bash benchmarks/gpu_session.sh speed", carry=[".ref"], timeout_s=600)
#   run(command="bash benchmarks/gpu_session.sh train", timeout_s=600)
# Logs and the benchmarks' records come back under $OUT (session.log first); copy the records'
# lines into benchmarks/results/ and the figures into the README. On a CPU (a dry run) each
# part does the same at a tiny size: `OUT=/tmp/out bash benchmarks/gpu_session.sh check dry`.
set -uo pipefail
cd "$(dirname "$0")/.."
part=${1:?check, speed or train}
dry=${2:-}
OUT=${OUT:-/tmp/gpu_session}
mkdir -p "$OUT"
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 SLJAX_BENCH_RESULTS=$OUT/records
PY=${PYTHON:-python3}
log() { echo "== $(date -u +%H:%M:%S) $*" | tee -a "$OUT/session.log"; }
ran() { local rc=$?; log "exit code $rc$([ $rc = 124 ] && echo ' (timed out)')"; }

log "part $part ${dry:+(dry run)}"
{ nvidia-smi -L 2>/dev/null || echo "no nvidia-smi"; $PY -c "import jax, flax, optax; print(jax.__version__, jax.devices(), flax.__version__, optax.__version__)"; } \
  2>&1 | tee -a "$OUT/session.log"

if [ "$part" = check ]; then
  tests="tests/test_reference_psmnet.py tests/test_psmnet.py tests/test_psmnet_mtl.py
         tests/test_unet.py tests/test_correlation.py tests/test_losses.py tests/test_weighting.py
         tests/test_step.py tests/test_inference.py tests/test_loop.py"
  [ -n "$dry" ] && tests="tests/test_correlation.py tests/test_losses.py"
  log "tests at XLA's default precision"
  timeout 360 $PY -m pytest -q -p no:cacheprovider -o addopts="-ra" $tests > "$OUT/tests-default.log" 2>&1
  ran; tail -15 "$OUT/tests-default.log" | tee -a "$OUT/session.log"
  log "the reference test at 'highest' precision (TF32 off)"
  JAX_DEFAULT_MATMUL_PRECISION=highest timeout 150 $PY -m pytest -q -p no:cacheprovider \
    -o addopts="-ra" tests/test_reference_psmnet.py > "$OUT/tests-highest.log" 2>&1
  ran; tail -5 "$OUT/tests-highest.log" | tee -a "$OUT/session.log"
elif [ "$part" = speed ]; then
  ref=""; [ -d .ref/PSMNet ] && ref="--reference .ref/PSMNet"
  args="--batch 4 --models psmnet,unet-sl"; [ -n "$dry" ] && args="--size 64 --maxdisp 32 --batch 1 --repeats 1 --models psmnet"
  log "bench_gpu $args $ref"
  timeout 540 $PY benchmarks/bench_gpu.py $args $ref > "$OUT/bench_gpu.log" 2>&1
  ran; cat "$OUT/bench_gpu.log" >> "$OUT/session.log"
elif [ "$part" = train ]; then
  args="--preset paper --steps 20 --epochs 2"
  [ -n "$dry" ] && args="--preset quick --steps 2 --epochs 2"
  for net in psmnet-mtl; do  # PSMNet's own step: bench_gpu's fwd+bwd
    for precision in fp32 bf16; do
      log "bench_train $args --net $net --precision $precision"
      timeout 180 $PY benchmarks/bench_train.py $args --net $net --precision $precision \
        > "$OUT/bench_train-$net-$precision.log" 2>&1
      ran; tail -8 "$OUT/bench_train-$net-$precision.log" | tee -a "$OUT/session.log"
    done
  done
  run="--preset paper --epochs 1"; [ -n "$dry" ] && run="--preset quick --epochs 1"
  log "python train.py --strategy epr $run (stopped after 150 s: time per step from its log)"
  timeout 150 $PY train.py --strategy epr $run --workdir /tmp/gpu-epr > "$OUT/train-epr.log" 2>&1
  ran; tr '\r' '\n' < "$OUT/train-epr.log" | tail -5 | tee -a "$OUT/session.log"
else
  echo "usage: gpu_session.sh check|speed|train [dry]" >&2; exit 2
fi
log "done"
