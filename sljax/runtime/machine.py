"""What CPU this is: model, family and model numbers, the ISA flags that decide kernel speed;
and how busy other processes keep it.

One description serves the tuner's cache key (`sljax.runtime.choices`) and the benchmarks' records.
"""

import os
import platform
import re
import time

# /proc/cpuinfo flag -> the name people know; AMX and AVX512_BF16 decide bf16 speed.
ISA_FLAGS = (("avx2", "AVX2"), ("avx512f", "AVX-512"), ("avx512_bf16", "AVX512_BF16"),
             ("avx512_vnni", "AVX512_VNNI"), ("amx_tile", "AMX"))


def _first_processor(cpuinfo: str = "/proc/cpuinfo") -> dict[str, str]:
  """The first processor's /proc/cpuinfo entries ({} where there is no such file)."""
  info: dict[str, str] = {}
  try:
    with open(cpuinfo, encoding="utf-8") as f:
      for line in f:
        key, _, value = line.partition(":")
        info.setdefault(key.strip(), value.strip())
  except OSError:
    pass
  return info


def cpu_flags(cpuinfo: str = "/proc/cpuinfo") -> set[str]:
  """Every ISA flag the kernel reports (what compiled code may use)."""
  return set(_first_processor(cpuinfo).get("flags", "").split())


def cpu_info(cpuinfo: str = "/proc/cpuinfo") -> dict:
  """The CPU as fields: model name, family and model numbers, ISA flags people know, cores."""
  info = _first_processor(cpuinfo)
  flags = set(info.get("flags", "").split())
  return {"model": info.get("model name") or platform.processor() or "unknown CPU",
          "family": info.get("cpu family"), "model_number": info.get("model"),
          "isa": [name for flag, name in ISA_FLAGS if flag in flags], "cores": os.cpu_count()}


def cpu_description(cpu: dict | None = None) -> str:
  """'AMD EPYC, family 26 model 2 (AVX2, AVX-512; 2 cores)': family and model numbers too,
  since virtual machines often say only 'AMD EPYC'."""
  cpu = cpu or cpu_info()
  model = cpu["model"]
  if cpu.get("family") is not None:
    model += f", family {cpu['family']} model {cpu.get('model_number') or '?'}"
  return f"{model} ({', '.join(cpu['isa']) or 'ISA unknown'}; {cpu['cores']} cores)"


def cpu_key(cpu: dict | None = None) -> str:
  """A file-name-safe key of the CPU kind: 'amd-epyc-f25-m1-avx2'."""
  cpu = cpu or cpu_info()
  parts = [cpu["model"]]
  if cpu.get("family") is not None:
    parts.append(f"f{cpu['family']}-m{cpu.get('model_number') or 'x'}")
  parts.append("avx512" if "AVX-512" in cpu["isa"] else "avx2" if "AVX2" in cpu["isa"] else "")
  return re.sub(r"[^a-z0-9]+", "-", "-".join(parts).lower()).strip("-") or "unknown-cpu"


# ----------------------------------------------------------------------------- other processes


MIN_SECONDS = 0.25  # a shorter interval holds a few clock ticks: its share means nothing


def _usable_cpus() -> set[int] | None:
  """The cores this process may run on (None where the OS does not say)."""
  try:
    return set(os.sched_getaffinity(0))
  except (AttributeError, OSError):
    return None


def cpu_snapshot(stat: str = "/proc/stat", cpus: set[int] | None = None
                 ) -> tuple[float, float, float] | None:
  """(CPU seconds so far of the cores this process may use, of them busy, of them this
  process's), or None where /proc/stat cannot be read. A virtual machine's steal (the host
  running others) counts busy. `cpus`: those cores (default: this process's affinity)."""
  cpus = _usable_cpus() if cpus is None else cpus
  total = busy = 0
  found = False
  try:
    with open(stat, encoding="ascii") as f:
      for line in f:
        fields = line.split()
        name = fields[0] if fields else ""
        if not (name.startswith("cpu") and name[3:].isdigit()):
          continue
        if cpus is not None and int(name[3:]) not in cpus:
          continue  # a core this process never runs on: its load does not slow us
        # user nice system idle iowait irq softirq steal (guest time is inside user already)
        ticks = [int(x) for x in fields[1:9]]
        if len(ticks) < 8:
          return None
        total += sum(ticks)
        busy += sum(ticks) - ticks[3] - ticks[4]
        found = True
  except (OSError, ValueError):
    return None
  if not found:
    return None
  hz = os.sysconf("SC_CLK_TCK")
  own = os.times()  # every thread of this process
  return total / hz, busy / hz, own.user + own.system


def others_share(before: tuple[float, float, float] | None,
                 after: tuple[float, float, float] | None) -> float | None:
  """The share of the cores' time between two `cpu_snapshot`s that other processes used: about
  0 on an idle machine, 0.5 with one of two cores busy elsewhere; None when either is None or
  the interval is too short to tell (under `MIN_SECONDS`)."""
  if before is None or after is None:
    return None
  cores = max(1, len(_usable_cpus() or ()) or os.cpu_count() or 1)
  if after[0] - before[0] < MIN_SECONDS * cores:
    return None
  others = (after[1] - before[1]) - (after[2] - before[2])
  return min(1.0, max(0.0, others / (after[0] - before[0])))


def others_now(seconds: float = 0.5) -> float | None:
  """`others_share` over the next `seconds` (this process sleeping meanwhile)."""
  before = cpu_snapshot()
  time.sleep(seconds)
  return others_share(before, cpu_snapshot())
