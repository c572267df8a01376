"""What every benchmark shares: where it ran, best-of timing, fresh child processes, and the
per-CPU record of every result (`benchmarks/results/<cpu>.jsonl`, one JSON line a run)."""

from __future__ import annotations

import datetime
import json
import os
import platform
import re
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

# Benchmarks measure the checkout they sit in, not whichever sljax is installed.
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
  sys.path.insert(0, ROOT)

# /proc/cpuinfo flag -> the name people know; AMX and AVX512_BF16 decide bf16 speed.
ISA_FLAGS = (("avx2", "AVX2"), ("avx512f", "AVX-512"), ("avx512_bf16", "AVX512_BF16"),
             ("avx512_vnni", "AVX512_VNNI"), ("amx_tile", "AMX"))


def cpu_info() -> dict:
  """The CPU as fields: model name, family and model numbers, ISA flags people know, cores."""
  info: dict[str, str] = {}
  try:
    with open("/proc/cpuinfo", encoding="utf-8") as f:
      for line in f:
        key, _, value = line.partition(":")
        info.setdefault(key.strip(), value.strip())  # the first processor's entries
  except OSError:
    pass
  flags = set(info.get("flags", "").split())
  return {"model": info.get("model name") or platform.processor() or "unknown CPU",
          "family": info.get("cpu family"), "model_number": info.get("model"),
          "isa": [name for flag, name in ISA_FLAGS if flag in flags], "cores": os.cpu_count()}


def cpu_description(cpu: dict | None = None) -> str:
  """CPU model (family/model numbers too: virtual machines often say only 'AMD EPYC'), ISA
  flags and core count, e.g. 'AMD EPYC, family 26 model 2 (AVX2, AVX-512; 2 cores)'."""
  cpu = cpu or cpu_info()
  model = cpu["model"]
  if cpu.get("family") is not None:
    model += f", family {cpu['family']} model {cpu.get('model_number') or '?'}"
  return f"{model} ({', '.join(cpu['isa']) or 'ISA unknown'}; {cpu['cores']} cores)"


def cpu_key(cpu: dict | None = None) -> str:
  """File-name key of a CPU kind: model name, family and model numbers, AVX-512 or not
  ('amd-epyc-f25-m1-avx2'); one records file per key under benchmarks/results/."""
  cpu = cpu or cpu_info()
  parts = [cpu["model"]]
  if cpu.get("family") is not None:
    parts.append(f"f{cpu['family']}-m{cpu.get('model_number') or 'x'}")
  parts.append("avx512" if "AVX-512" in cpu["isa"] else "avx2" if "AVX2" in cpu["isa"] else "")
  slug = re.sub(r"[^a-z0-9]+", "-", "-".join(parts).lower()).strip("-")
  return slug or "unknown-cpu"


def machine(torch_module=None) -> str:
  """One line naming the CPU, the accelerator and the versions; print it above every table."""
  import jax
  import jaxlib
  dev = jax.devices()[0]
  line = (f"{cpu_description()}; {jax.device_count()} x {dev.device_kind} "
          f"({jax.default_backend()}); jax {jax.__version__}, jaxlib {jaxlib.__version__}")
  if torch_module is not None:
    line += f", torch {torch_module.__version__} ({torch_module.get_num_threads()} threads)"
  return line


def best_time(fn: Callable[[], object], repeats: int) -> float:
  """Minimum wall time of fn() over `repeats` runs after one warm-up."""
  fn()
  best = float("inf")
  for _ in range(repeats):
    t0 = time.perf_counter()
    fn()
    best = min(best, time.perf_counter() - t0)
  return best


def run_child(script: str, args: list[str]) -> tuple[dict, float]:
  """Runs `script` with args in a fresh process; its last stdout line (JSON) and peak RSS (MiB)."""
  proc = subprocess.Popen([sys.executable, os.path.abspath(script)] + args,
                          stdout=subprocess.PIPE, text=True)
  out = proc.stdout.read()
  _, status, usage = os.wait4(proc.pid, 0)
  code = os.waitstatus_to_exitcode(status)
  if code != 0:
    raise SystemExit(f"benchmark child {' '.join(args)} failed with exit code {code}")
  return json.loads(out.strip().splitlines()[-1]), usage.ru_maxrss / 1024  # Linux: KiB


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


def record(benchmark: str, rows: list[dict], torch_module=None, **extra) -> Path:
  """Appends one run's rows, with the machine, versions, commit, command line and the load
  average (the machines are shared: a high load marks a contended run) to the CPU's records file;
  returns its path. SLJAX_BENCH_RESULTS moves the folder."""
  import jax
  import jaxlib
  cpu = cpu_info()
  versions = {"jax": jax.__version__, "jaxlib": jaxlib.__version__}
  if torch_module is not None:
    versions.update(torch=torch_module.__version__, torch_threads=torch_module.get_num_threads())
  entry = {"time": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
           "benchmark": benchmark, "argv": sys.argv[1:], "cpu": cpu,
           "machine": machine(torch_module), "backend": jax.default_backend(),
           "versions": versions, "commit": git_commit(),
           "loadavg_1min": round(os.getloadavg()[0], 2), "rows": rows, **extra}
  RESULTS.mkdir(parents=True, exist_ok=True)
  path = RESULTS / f"{cpu_key(cpu)}.jsonl"
  with open(path, "a", encoding="utf-8") as f:
    f.write(json.dumps(entry) + "\n")
  print(f"\nrecorded in {os.path.relpath(path)}")
  return path
