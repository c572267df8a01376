# The plumbing the GPU session scripts share, sourced from the repository root after they set
# `session` (their name), `deadline_s` (the default of DEADLINE, seconds) and `dry`:
#   $OUT        where everything comes back (session.log first); the benchmarks' records go
#               to $OUT/records (SLJAX_BENCH_RESULTS)
#   $PY         the interpreter (PYTHON, default python3)
#   left        seconds to the deadline (DEADLINE seconds from the start; at least 1)
#   log, ran    a line into session.log with the time since the start; the exit code of the
#               command just run, a timeout named
#   $refarg     --reference DIR when a checkout of the reference PSMNet is at .ref/PSMNet (or
#               REFERENCE=DIR), else empty ($ref names the folder looked at)
#   header, footer   the machine, commit and versions at the start; GPU memory and "done" at the end
OUT=${OUT:-/tmp/$session}
mkdir -p "$OUT"
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 SLJAX_BENCH_RESULTS=$OUT/records
PY=${PYTHON:-python3}
start=$(date +%s); deadline=$((start + ${DEADLINE:-$deadline_s}))
left() { local l=$((deadline - $(date +%s))); [ $l -lt 1 ] && l=1; echo $l; }
log() {
  echo "== $(date -u +%H:%M:%S) (+$(($(date +%s) - start)) s) $*" | tee -a "$OUT/session.log"
}
ran() { local rc=$?; log "exit code $rc$([ $rc = 124 ] && echo ' (timed out)')"; }

ref=${REFERENCE:-.ref/PSMNet}
refarg=""; [ -f "$ref/models/stackhourglass.py" ] && refarg="--reference $ref"

header() {
  log "$session${*:+ $*}${dry:+ (dry run)};" \
    "reference: ${refarg:-none (no $ref/models/stackhourglass.py)}"
  { nvidia-smi -L 2>/dev/null || echo "no nvidia-smi"; git log --oneline -1;
    $PY -c "import jax, flax; print('jax', jax.__version__, jax.devices(), 'flax', flax.__version__)";
    $PY -c "import torch; print('torch', torch.__version__, torch.cuda.is_available())" 2>&1 |
      tail -1; } \
    2>&1 | tee -a "$OUT/session.log"
}
footer() {
  nvidia-smi --query-gpu=name,memory.used,memory.total --format=csv 2>/dev/null |
    tee -a "$OUT/session.log"
  log "done"
}
