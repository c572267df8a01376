#!/usr/bin/env bash
# The plan for a session lent a GPU (the device tool: 30 min of device time, 10 min a call),
# written and dry-run on a CPU beforehand so the GPU's minutes go to measuring. Three calls:
#
#   check: which tests pass on the GPU at 'highest' (the suite's setting, tests/conftest.py),
#          and the bitwise tests (exact resume, two programs) with XLA's deterministic GPU
#          operations. First run (2026-11-25, H100): docs/testing.md "On a GPU".
#   speed: bench_gpu: PSMNet's GPU forward against the CPU's, PSMNet's and unet-sl's speed beside
#          PyTorch on the same GPU (the reference PSMNet when .ref/PSMNet is carried), peak memory.
#   train: the real training step and loop (bench_train, paper preset, the twin, fp32 and
#          bf16: is the data pipeline hidden behind a GPU step?). The main job at the paper
#          preset was timed on 2026-11-25 (README, Benchmarks).
#   next:  the second session's single call (15 min of device time): check's files at
#          `highest` without the bitwise tests, the bitwise tests under deterministic GPU
#          operations (with and without autotuning), then the twin's step in fp32 and bf16.
#   resume: the exact-resume tests with the killed child on the GPU, as is and under
#          deterministic operations; then the same step benchmark. (2026-11-26, H200: exact
#          resume held bitwise under deterministic operations; neither step compiled in 4.5 min
#          when the two precisions compiled in two threads: next time one at a time.)
#   suite: the third session's single call (15 min of device time): the whole suite on the
#          GPU as `pytest` runs it there (deterministic operations, `highest`), one line a test
#          so that a cut-short run still tells; beside it the twin's bf16 step compiled alone
#          (the GPU's timing then shared with the suite: its compile time is the finding);
#          then, alone on the GPU, unet-sl's and PSMNet's step with and without
#          deterministic operations (their speed cost), while the deadline allows.
#
# From the device tool (the machine's image has jax with CUDA, flax, optax, orbax, OpenCV and
# a CUDA torch; nothing is installed, sljax runs from the checkout):
#   here, once:  echo /.ref/ >> .git/info/exclude && mkdir -p .ref && cp -r PSMNET_CHECKOUT .ref/PSMNet
#   run(command="bash benchmarks/gpu_session.sh check", timeout_s=600)
#   run(command="bash benchmarks/gpu_session.sh speed", carry=[".ref"], timeout_s=600)
#   run(command="bash benchmarks/gpu_session.sh train", timeout_s=600)
#   run(command="bash benchmarks/gpu_session.sh next", timeout_s=480)
#   run(command="bash benchmarks/gpu_session.sh resume", timeout_s=410)
#   run(command="bash benchmarks/gpu_session.sh suite", timeout_s=560)
# Logs and the benchmarks' records come back under $OUT (session.log first); copy the records'
# lines into benchmarks/results/ and the figures into the README. On a CPU (a dry run) each
# part does the same at a tiny size: `OUT=/tmp/out bash benchmarks/gpu_session.sh check dry`.
set -uo pipefail
cd "$(dirname "$0")/.."
part=${1:?check, speed, train, next, resume or suite}
dry=${2:-}
OUT=${OUT:-/tmp/gpu_session}
mkdir -p "$OUT"
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 SLJAX_BENCH_RESULTS=$OUT/records
PY=${PYTHON:-python3}
log() { echo "== $(date -u +%H:%M:%S) $*" | tee -a "$OUT/session.log"; }
ran() { local rc=$?; log "exit code $rc$([ $rc = 124 ] && echo ' (timed out)')"; }

det="--xla_gpu_deterministic_ops=true"
pids=""
# XLA_FLAGS with more flags; never a lone space, which XLA reads as a file of flags and dies.
with_flags() { echo "${XLA_FLAGS:+$XLA_FLAGS }$1" | sed 's/^ *//; s/ *$//'; }
# pytest NAME "XLA flags" ARGS...: in the background, into $OUT/tests-NAME.log, within $limit s.
pytest_bg() {
  local name=$1 flags=$2; shift 2
  XLA_FLAGS="$(with_flags "$flags")" timeout "$limit" $PY -m pytest -q -p no:cacheprovider \
    -o addopts="-ra" --tb=line "$@" > "$OUT/tests-$name.log" 2>&1 &
  pids="$pids $!:$name"
}
# Waits for each pytest_bg run and logs its exit code and summary.
wait_tests() {
  local job rc
  for job in $pids; do
    wait "${job%%:*}"; rc=$?
    log "${job#*:}: exit code $rc$([ $rc = 124 ] && echo ' (timed out)')"
    grep -E "^(FAILED|ERROR)|passed|failed" "$OUT/tests-${job#*:}.log" | tail -25 | tee -a "$OUT/session.log"
  done
  pids=""
}
# The twin's compiled step in float32 and bf16 side by side, alone on the GPU, within $blimit s.
bench_precisions() {
  log "bench_train $args --net psmnet-mtl --step-only --precision fp32,bf16 (alone on the GPU)"
  timeout "$blimit" $PY benchmarks/bench_train.py $args --net psmnet-mtl --step-only \
    --precision fp32,bf16 > "$OUT/bench_train-psmnet-mtl-precisions.log" 2>&1
  ran; grep -v cuda_timer "$OUT/bench_train-psmnet-mtl-precisions.log" | tail -9 | tee -a "$OUT/session.log"
}

log "part $part ${dry:+(dry run)}"
{ nvidia-smi -L 2>/dev/null || echo "no nvidia-smi"; $PY -c "import jax, flax, optax; print(jax.__version__, jax.devices(), flax.__version__, optax.__version__)"; } \
  2>&1 | tee -a "$OUT/session.log"

if [ "$part" = check ]; then
  # In parallel: run one by one these files took over 6 minutes on an H100 (compiling).
  xd=""; $PY -c "import xdist" 2>/dev/null && xd="-n 6"
  export XLA_PYTHON_CLIENT_PREALLOCATE=false  # six processes share the GPU's memory
  tests="tests/test_reference_psmnet.py tests/test_psmnet.py tests/test_psmnet_mtl.py
         tests/test_unet.py tests/test_correlation.py tests/test_losses.py tests/test_weighting.py
         tests/test_step.py tests/test_inference.py tests/test_loop.py tests/test_export.py"
  bitwise="tests/test_loop.py::test_exact_resume_after_kill_mid_epoch_and_during_a_save
           tests/test_inference.py::test_twin_in_two_programs_equals_one"
  [ -n "$dry" ] && tests="tests/test_correlation.py tests/test_losses.py" && bitwise="tests/test_losses.py"
  log "tests at 'highest' precision (tests/conftest.py), $xd"
  timeout 300 $PY -m pytest $xd -q -p no:cacheprovider -o addopts="-ra" --tb=line $tests \
    > "$OUT/tests-highest.log" 2>&1
  ran; grep -E "^(FAILED|ERROR)|passed|failed" "$OUT/tests-highest.log" | tail -25 | tee -a "$OUT/session.log"
  log "the bitwise tests (exact resume, two programs) with XLA's deterministic GPU operations"
  XLA_FLAGS="$(with_flags "$det")" timeout 240 $PY -m pytest $xd -q \
    -p no:cacheprovider -o addopts="-ra" --tb=line $bitwise > "$OUT/tests-deterministic.log" 2>&1
  ran; grep -E "^(FAILED|ERROR)|passed|failed" "$OUT/tests-deterministic.log" | tail -10 | tee -a "$OUT/session.log"
elif [ "$part" = speed ]; then
  ref=""; [ -d .ref/PSMNet ] && ref="--reference .ref/PSMNet"
  args="--batch 4 --models psmnet,unet-sl"; [ -n "$dry" ] && args="--size 64 --maxdisp 32 --batch 1 --repeats 1 --models psmnet"
  log "bench_gpu $args $ref"
  timeout 540 $PY benchmarks/bench_gpu.py $args $ref > "$OUT/bench_gpu.log" 2>&1
  ran; cat "$OUT/bench_gpu.log" >> "$OUT/session.log"
elif [ "$part" = train ]; then
  args="--preset paper --steps 20 --epochs 2"
  [ -n "$dry" ] && args="--preset quick --steps 2 --epochs 2"
  for precision in fp32 bf16; do  # the twin's step compiled for about 2 min on an H100
    log "bench_train $args --net psmnet-mtl --precision $precision"
    timeout 280 $PY benchmarks/bench_train.py $args --net psmnet-mtl --precision $precision \
      > "$OUT/bench_train-psmnet-mtl-$precision.log" 2>&1
    ran; grep -v cuda_timer "$OUT/bench_train-psmnet-mtl-$precision.log" | tail -8 | tee -a "$OUT/session.log"
  done
elif [ "$part" = next ]; then
  # The second session's one call (15 min of device time in all): the nine files at `highest`
  # without the four bitwise tests, beside those four under XLA's deterministic GPU operations,
  # alone and with autotuning off (each compilation picks convolution kernels by timing them);
  # then the twin's step in float32 and bf16 side by side, alone on the GPU so that the timing
  # is clean (compiled together, then timed in alternation).
  export XLA_PYTHON_CLIENT_PREALLOCATE=false
  xd=""; $PY -c "import xdist" 2>/dev/null && xd="-n 8"; xb=""; [ -n "$xd" ] && xb="-n 4"
  tests="tests/test_psmnet.py tests/test_psmnet_mtl.py tests/test_unet.py tests/test_correlation.py
         tests/test_losses.py tests/test_weighting.py tests/test_step.py tests/test_inference.py
         tests/test_loop.py"
  bitwise="tests/test_loop.py::test_exact_resume_after_kill_mid_epoch_and_during_a_save
           tests/test_inference.py::test_twin_in_two_programs_equals_one"
  args="--preset paper --steps 20"; limit=200; blimit=240
  if [ -n "$dry" ]; then
    tests="tests/test_correlation.py tests/test_losses.py"; bitwise="tests/test_losses.py"
    args="--preset quick --steps 2"; limit=120; blimit=120
  fi
  deselect=""; for t in $bitwise; do deselect="$deselect --deselect $t"; done
  log "tests at 'highest' (tests/conftest.py) without the bitwise ones, $xd; beside them the bitwise tests"
  pytest_bg highest "" $xd $tests $deselect
  pytest_bg deterministic "$det" $xb $bitwise
  pytest_bg deterministic-noautotune "$det --xla_gpu_autotune_level=0" $xb $bitwise
  wait_tests
  bench_precisions
elif [ "$part" = resume ]; then
  # Exact resume with the killed child on the parent's device (it ran on the CPU before
  # 2026-11-26), at XLA's GPU settings as they are and with deterministic operations; then the
  # twin's step in both precisions, alone on the GPU.
  export XLA_PYTHON_CLIENT_PREALLOCATE=false
  xb=""; $PY -c "import xdist" 2>/dev/null && xb="-n 4"
  bitwise="tests/test_loop.py::test_exact_resume_after_kill_mid_epoch_and_during_a_save
           tests/test_loop.py::test_ctrl_c_stops_after_the_step_and_resumes_exactly"
  args="--preset paper --steps 20"; limit=120; blimit=270
  [ -n "$dry" ] && args="--preset quick --steps 2" && limit=200 && blimit=150
  log "exact resume, the child on the parent's device: as is, and with deterministic GPU operations"
  pytest_bg resume "" $xb $bitwise
  pytest_bg resume-deterministic "$det" $xb $bitwise
  wait_tests
  bench_precisions
elif [ "$part" = suite ]; then
  export XLA_PYTHON_CLIENT_PREALLOCATE=false
  start=$(date +%s); deadline=$((start + ${DEADLINE:-470}))
  left() { echo $((deadline - $(date +%s))); }
  # The console script `sljax`, which some tests run, from the checkout without a network.
  $PY -m pip install -q --no-deps --no-build-isolation --no-index -e . > /tmp/install.log 2>&1
  log "pip install -e . exit code $?"
  xd="-n 8"; files=""; limit=330; blimit=400; args="--preset paper --steps 10"
  if [ -n "$dry" ]; then
    xd="-n 2"; files="tests/test_correlation.py tests/test_losses.py"; limit=150; blimit=150
    args="--preset quick --steps 2"
  fi
  log "the whole suite (tests/conftest.py: 'highest', deterministic GPU operations), $xd, -v"
  timeout "$limit" $PY -m pytest $xd --dist loadfile -v -p no:cacheprovider \
    -o addopts="-ra --durations=25" --tb=line $files > "$OUT/tests-suite.log" 2>&1 &
  suite=$!
  log "beside it: bench_train $args --net psmnet-mtl --step-only --precision bf16 (alone: one precision)"
  timeout "$blimit" $PY benchmarks/bench_train.py $args --net psmnet-mtl --step-only \
    --precision bf16 > "$OUT/bench_train-bf16.log" 2>&1 &
  bf16=$!
  wait $suite; rc=$?; log "suite: exit code $rc$([ $rc = 124 ] && echo ' (timed out)')"
  grep -E "^(FAILED|ERROR)|passed|failed" "$OUT/tests-suite.log" | tail -40 | tee -a "$OUT/session.log"
  grep -c " PASSED" "$OUT/tests-suite.log" | sed 's/^/PASSED lines: /' | tee -a "$OUT/session.log"
  wait $bf16; rc=$?; log "bf16 step: exit code $rc$([ $rc = 124 ] && echo ' (timed out)')"
  grep -v cuda_timer "$OUT/bench_train-bf16.log" | tail -6 | tee -a "$OUT/session.log"
  # The speed cost of deterministic operations, one process each, alone on the GPU.
  # PSMNet's pair starts only with time for both compilations (about 2 min each on an H100).
  for net in unet-sl psmnet; do
    need=40; [ $net = psmnet ] && [ -z "$dry" ] && need=300
    [ "$(left)" -lt $need ] && { log "no time left for $net ($(left) s)"; continue; }
    for flags in "" "$det"; do
      log "bench_train $args --net $net --step-only --precision fp32, XLA_FLAGS='$flags'"
      XLA_FLAGS="$(with_flags "$flags")" timeout "$(left)" $PY benchmarks/bench_train.py $args \
        --net $net --step-only --precision fp32 > /tmp/bench.log 2>&1
      ran; cat /tmp/bench.log >> "$OUT/bench_train-det.log"
      grep -E "compiled|^\| \(a\)" /tmp/bench.log | tee -a "$OUT/session.log"
    done
  done
  nvidia-smi --query-gpu=name,memory.used,memory.total --format=csv 2>&1 | tee -a "$OUT/session.log"
else
  echo "usage: gpu_session.sh check|speed|train|next|resume|suite [dry]" >&2; exit 2
fi
log "done"
