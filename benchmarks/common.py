"""What every benchmark shares: where it ran, best-of timing, fresh child processes, and the
per-CPU (or per-accelerator) record of every result (`benchmarks/results/<cpu>.jsonl`,
`<backend>-<device kind>.jsonl` off the CPU; one JSON line a run)."""

from __future__ import annotations

import datetime
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

# Benchmarks measure the checkout they sit in, not whichever sljax is installed.
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
  sys.path.insert(0, ROOT)

from sljax.runtime.machine import cpu_description, cpu_info, cpu_key  # noqa: E402  (after the path)


def peak_gflops(cpu: dict | None = None) -> tuple[float, str]:
  """The CPU's nominal fp32 peak in GFLOP/s and how it was computed: cores x FLOP per cycle x
  clock. FLOP per cycle assumes two FMA pipes of the widest vector (AVX-512: 2 x 16 x 2 = 64,
  AVX2: 2 x 8 x 2 = 32, as on Zen 3, Zen 5 and Xeons since Skylake-SP); the clock is the
  nominal one /proc/cpuinfo reports (turbo can exceed it, so shares near 100% are possible)."""
  cpu = cpu or cpu_info()
  mhz = 0.0
  try:
    with open("/proc/cpuinfo", encoding="utf-8") as f:
      mhz = next(float(l.split(":")[1]) for l in f if l.startswith("cpu MHz"))
  except (OSError, StopIteration, ValueError):
    pass
  per_cycle = 64 if "AVX-512" in cpu["isa"] else 32 if "AVX2" in cpu["isa"] else 16
  peak = cpu["cores"] * per_cycle * mhz / 1e3
  return peak, f"{cpu['cores']} cores x {per_cycle} FLOP/cycle x {mhz / 1e3:.2f} GHz"


def machine(torch_module=None) -> str:
  """One line naming the CPU, the accelerator and the versions; print it above every table."""
  import jax
  import jaxlib
  dev = jax.devices()[0]
  line = (f"{cpu_description()}; {jax.device_count()} x {dev.device_kind} "
          f"({jax.default_backend()}); jax {jax.__version__}, jaxlib {jaxlib.__version__}")
  if torch_module is not None:
    line += f", torch {torch_module.__version__} ({torch_module.get_num_threads()} threads)"
  from sljax.runtime import hugepages
  return line + f"; malloc huge pages {'on' if hugepages.active() else 'off'}"


def best_time(fn: Callable[[], object], repeats: int) -> float:
  """Minimum wall time of fn() over `repeats` runs after one warm-up."""
  fn()
  best = float("inf")
  for _ in range(repeats):
    t0 = time.perf_counter()
    fn()
    best = min(best, time.perf_counter() - t0)
  return best


def run_child(script: str, args: list[str], env: dict | None = None, timeout: float | None = None,
              check: bool = True) -> tuple[dict | None, float]:
  """Runs `script` with args in a fresh process; its last stdout line (JSON) and peak RSS (MiB).

  env replaces the environment; past `timeout` seconds the child is killed. A failed child
  ends the benchmark, or with check=False gives None (its stderr is left on the console)."""
  proc = subprocess.Popen([sys.executable, os.path.abspath(script)] + args,
                          stdout=subprocess.PIPE, text=True, env=env)
  timer = threading.Timer(timeout, proc.kill) if timeout else None
  if timer:
    timer.start()
  out = proc.stdout.read()
  _, status, usage = os.wait4(proc.pid, 0)
  if timer:
    timer.cancel()
  code = os.waitstatus_to_exitcode(status)
  rss = usage.ru_maxrss / 1024  # Linux: KiB
  if code != 0:
    if check:
      raise SystemExit(f"benchmark child {' '.join(args)} failed with exit code {code}")
    return None, rss
  return json.loads(out.strip().splitlines()[-1]), rss


RESULTS = Path(os.environ.get("SLJAX_BENCH_RESULTS", os.path.join(ROOT, "benchmarks", "results")))


def git_commit() -> str:
  """The checkout's commit, with '+dirty' when tracked files differ from it ('unknown' outside
  git)."""
  try:
    head = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"], text=True,
                          capture_output=True, check=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", ROOT, "status", "--porcelain", "--untracked-files=no"],
                           text=True, capture_output=True, check=True).stdout.strip()
  except (OSError, subprocess.CalledProcessError):
    return "unknown"
  return head + ("+dirty" if dirty else "")


def records_key(cpu: dict, backend: str, device_kind: str) -> str:
  """The records file's name: the CPU kind on the CPU, else the accelerator's kind (a GPU's
  numbers do not belong to the host CPU it happened to sit beside)."""
  if backend == "cpu":
    return cpu_key(cpu)
  slug = "".join(c if c.isalnum() else "-" for c in f"{backend} {device_kind}".lower())
  return "-".join(filter(None, slug.split("-")))


def device_of_process(torch_module=None) -> dict:
  """Where this process runs: jax's backend, its first device's kind and the machine line
  (initialises jax's backend: on a GPU, its memory)."""
  import jax
  return {"backend": jax.default_backend(), "device_kind": jax.devices()[0].device_kind,
          "machine": machine(torch_module),
          "glibc_tunables": os.environ.get("GLIBC_TUNABLES", "").strip()}


def record(benchmark: str, rows: list[dict], torch_module=None, quiet: bool = False,
           where: dict | None = None, **extra) -> Path:
  """Appends one run's rows, with the machine, versions, commit, command line and the load
  average (the machines are shared: a high load marks a contended run) to the CPU's records file;
  returns its path. SLJAX_BENCH_RESULTS moves the folder. `where` (device_of_process() of the
  process that measured) spares a parent process that launches the measuring ones its own
  accelerator: on a GPU, jax's backend would hold memory the children need."""
  import jax
  import jaxlib
  cpu = cpu_info()
  where = where or device_of_process(torch_module)
  versions = {"jax": jax.__version__, "jaxlib": jaxlib.__version__}
  if torch_module is not None:
    versions.update(torch=torch_module.__version__, torch_threads=torch_module.get_num_threads())
  entry = {"time": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
           "benchmark": benchmark, "argv": sys.argv[1:], "cpu": cpu,
           "machine": where["machine"], "backend": where["backend"],
           "versions": versions, "commit": git_commit(),
           "loadavg_1min": round(os.getloadavg()[0], 2), "rows": rows, **extra}
  flags = os.environ.get("XLA_FLAGS", "").strip()
  if flags:  # a figure under other compiler flags is another figure
    entry["xla_flags"] = flags
  tunables = where.get("glibc_tunables", "")  # the measuring process's (device_of_process)
  if tunables:  # malloc's huge pages (sljax/runtime/hugepages.py) change the CPU figures
    entry["glibc_tunables"] = tunables
  RESULTS.mkdir(parents=True, exist_ok=True)
  path = RESULTS / f"{records_key(cpu, where['backend'], where['device_kind'])}.jsonl"
  with open(path, "a", encoding="utf-8") as f:
    f.write(json.dumps(entry) + "\n")
  if not quiet:
    print(f"\nrecorded in {os.path.relpath(path)}")
  return path
