"""Transparent huge pages for XLA:CPU's buffers: a command line re-executes itself once with
glibc's `glibc.malloc.hugetlb=1`.

XLA:CPU allocates an execution's temporaries afresh each time (PSMNet's training step at
256x256: one 2.5 GB buffer, and Eigen's 38-76 MB blocks for its convolutions, about 100 a step),
and glibc serves every allocation over 32 MB with a fresh mmap. So each step faulted its whole
working set in again in 4 KiB pages: 630,000 page faults and about 1 s of kernel time per
3.3 s step on a 2-core Zen 5. With the tunable, malloc asks the kernel for transparent huge
pages (2 MiB; madvise) where the system offers them on request, as most distributions do
(`/sys/kernel/mm/transparent_hugepage/enabled` reads `[madvise]`): 2,000-5,000 faults a
step, and the step 0.86-0.88x (docs/benchmarks/huge-pages.md). glibc reads its tunables
only when a process starts, so a command line that wants them starts again, once, before it
imports jax (the same process id, arguments and interpreter flags).

Not done where it cannot help or was asked not to be: off Linux or glibc older than 2.35
(which ignores the tunable), where huge pages are always or never used, where GLIBC_TUNABLES
already names the tunable (your choice wins, and the second start sees it), and with
SLJAX_HUGEPAGES=0.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping

TUNABLE = "glibc.malloc.hugetlb"
OPT_OUT = "SLJAX_HUGEPAGES"
THP_ENABLED = "/sys/kernel/mm/transparent_hugepage/enabled"
MIN_GLIBC = (2, 35)  # the first glibc with glibc.malloc.hugetlb


def thp_mode(path: str = THP_ENABLED) -> str:
  """The kernel's transparent huge page mode ('always', 'madvise', 'never'; '' if unknown)."""
  try:
    with open(path, encoding="ascii") as f:
      text = f.read()
  except OSError:
    return ""
  start, end = text.find("["), text.find("]")
  return text[start + 1:end] if 0 <= start < end else ""


def glibc_version() -> tuple[int, ...] | None:
  """The running glibc's version, None off glibc."""
  try:
    name, _, version = os.confstr("CS_GNU_LIBC_VERSION").partition(" ")
  except (AttributeError, ValueError, OSError):
    return None
  if name != "glibc":
    return None
  try:
    return tuple(int(p) for p in version.split(".")[:2])
  except ValueError:
    return None


def restart_environment(environ: Mapping[str, str], mode: str,
                        glibc: tuple[int, ...] | None) -> dict[str, str] | None:
  """The environment to start again with (GLIBC_TUNABLES with the tunable added), or None
  where a restart would not help or was declined."""
  if environ.get(OPT_OUT, "1") == "0" or mode != "madvise":
    return None
  if glibc is None or glibc < MIN_GLIBC:
    return None
  tunables = environ.get("GLIBC_TUNABLES", "")
  if TUNABLE in tunables:
    return None
  env = dict(environ)
  env["GLIBC_TUNABLES"] = ":".join(t for t in (tunables, f"{TUNABLE}=1") if t)
  return env


def active(environ: Mapping[str, str] = os.environ) -> bool:
  """Whether this process was started with malloc's huge pages (the tunable set to 1)."""
  return f"{TUNABLE}=1" in environ.get("GLIBC_TUNABLES", "").split(":")


def reexec() -> None:
  """Starts this command line again with huge pages where that helps (see the module's
  docstring); returns where it does not. Call it first thing, before jax is imported."""
  if not sys.platform.startswith("linux") or not sys.executable or not sys.orig_argv:
    return
  env = restart_environment(os.environ, thp_mode(), glibc_version())
  if env is None:
    return
  sys.stdout.flush()
  sys.stderr.flush()
  try:
    os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], env)
  except OSError:
    pass  # run on without them
