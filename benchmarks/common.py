"""What every benchmark shares: where it ran, best-of timing, fresh child processes."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable

# Benchmarks measure the checkout they sit in, not whichever sljax is installed.
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
  sys.path.insert(0, ROOT)

# /proc/cpuinfo flag -> the name people know; AMX and AVX512_BF16 decide bf16 speed.
ISA_FLAGS = (("avx2", "AVX2"), ("avx512f", "AVX-512"), ("avx512_bf16", "AVX512_BF16"),
             ("avx512_vnni", "AVX512_VNNI"), ("amx_tile", "AMX"))


def cpu_description() -> str:
  """CPU model (family/model numbers too: virtual machines often say only 'AMD EPYC'), ISA
  flags and core count, e.g. 'AMD EPYC, family 26 model 2 (AVX2, AVX-512; 2 cores)'."""
  info: dict[str, str] = {}
  try:
    with open("/proc/cpuinfo", encoding="utf-8") as f:
      for line in f:
        key, _, value = line.partition(":")
        info.setdefault(key.strip(), value.strip())  # the first processor's entries
  except OSError:
    pass
  model = info.get("model name") or platform.processor() or "unknown CPU"
  if "cpu family" in info:
    model += f", family {info['cpu family']} model {info.get('model', '?')}"
  flags = set(info.get("flags", "").split())
  isa = [name for flag, name in ISA_FLAGS if flag in flags]
  return f"{model} ({', '.join(isa) or 'ISA unknown'}; {os.cpu_count()} cores)"


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
