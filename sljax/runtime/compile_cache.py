"""sljax's folder in the user's cache directory, and JAX's persistent compilation cache in it.

Compiling PSMNet's training step takes about a minute on a 2-core CPU and its twin's two, and
the same programs compile again in every run: every seed of an experiment, every resume, every
`sljax predict`. With the compilation cache on, XLA's executables are kept on disk and a later
process loads a program instead of compiling it. A loaded program is the one a compile would
give (the key is the program's HLO, the compiler options and the jax/jaxlib versions), so the
numbers are the same; only the time differs.

The executables sit in a folder per CPU (its model and full ISA flag set: an executable uses
the instructions of the CPU that compiled it, and a home directory can be shared by different
machines) and per jax/jaxlib version, at most MAX_BYTES in all (least recently used go first)
where the `filelock` package is installed; without it the folder is not limited.
`SLJAX_COMPILE_CACHE=off` turns it off, `SLJAX_COMPILE_CACHE=DIR` moves it, and a
`JAX_COMPILATION_CACHE_DIR` the user set wins. sljax's command lines (`sljax ...`,
`python train.py`) turn it on; code importing sljax decides for itself (`enable_compile_cache`).

Executables are code that runs, so the folder is used only when no one but the user, root and
the user's groups can write it, its parents up to the cache's root or its entries
(sljax.runtime.cache_trust); otherwise the run compiles, neither loading nor writing there, and
says so in one line.
"""

import hashlib
import importlib.util
import os
import sys
from pathlib import Path

import jax
import jaxlib

from sljax.runtime import cache_trust, kept_programs, machine

ENV_DIR = "SLJAX_CACHE_DIR"
ENV_COMPILE = "SLJAX_COMPILE_CACHE"
OFF = ("0", "off", "false", "no")
MAX_BYTES = 2 * 2**30
CACHE_SUFFIX, ATIME_SUFFIX = "-cache", "-atime"  # jax's LRU cache's file names (lru_cache.py)


def user_cache_dir() -> Path:
  """$SLJAX_CACHE_DIR, else $XDG_CACHE_HOME/sljax, else ~/.cache/sljax (never a dataset)."""
  if os.environ.get(ENV_DIR):
    return Path(os.environ[ENV_DIR])
  return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "sljax"


def compile_cache_root() -> Path | None:
  """The folder the user named for compiled programs ($SLJAX_COMPILE_CACHE), else sljax's cache
  folder (user_cache_dir); None: turned off. Trust is checked from an entry up to here."""
  setting = os.environ.get(ENV_COMPILE, "").strip()
  if setting.lower() in OFF:
    return None
  return Path(setting) if setting else user_cache_dir()


def compile_cache_dir() -> Path | None:
  """The folder of this CPU's and jax version's executables (None: turned off)."""
  setting = os.environ.get(ENV_COMPILE, "").strip()
  if setting.lower() in OFF:
    return None
  root = Path(setting) if setting else user_cache_dir() / "xla"
  flags = ",".join(sorted(machine.cpu_flags()))
  isa = hashlib.sha1(flags.encode()).hexdigest()[:8]
  return root / f"{machine.cpu_key()}-{isa}-jax-{jax.__version__}-jaxlib-{jaxlib.__version__}"


def trusted(folder: Path, root: Path) -> bool:
  """Whether a compile-cache folder may be loaded from (sljax.runtime.cache_trust); if not, one
  line on stderr says which path and how to allow it (once per process)."""
  found = cache_trust.untrusted_folder(folder, root)
  if found is not None:
    cache_trust.warn_once(folder, found)
  return found is None


def enable_compile_cache(programs: bool = False) -> Path | None:
  """Turns JAX's persistent compilation cache on in compile_cache_dir(), and with `programs`
  sljax's cache of whole compiled programs in the same folder (sljax.runtime.kept_programs: command
  lines only); returns the folder in use (the user's JAX_COMPILATION_CACHE_DIR when set;
  None when turned off or not trusted)."""
  if jax.config.jax_compilation_cache_dir:
    folder = Path(jax.config.jax_compilation_cache_dir)
    if not trusted(folder, folder):
      # jax would load the user's own setting too: the check holds for it as for sljax's.
      jax.config.update("jax_compilation_cache_dir", None)
      kept_programs.enable(None)
      return None
    kept_programs.enable(folder if programs else None, root=folder, checked=True)
    return folder
  folder, root = compile_cache_dir(), compile_cache_root()
  if folder is not None and not trusted(folder, root):
    folder = None  # compiled here, never loaded nor written there
  kept_programs.enable(folder if programs else None, root=root, checked=True)
  if folder is None:
    return None
  jax.config.update("jax_compilation_cache_dir", str(folder))
  if importlib.util.find_spec("filelock") is not None:
    # jax's size limit locks the folder with filelock; without that package jax fails every
    # read of the cache, so the folder is left to grow instead.
    try:
      add_missing_atimes(folder)
    except Exception as e:  # noqa: BLE001  a read-only or busy folder: jax then only warns
      print(f"sljax: compile cache {folder}: could not add access times ({type(e).__name__}); "
            "writes to it may fail with warnings", file=sys.stderr)
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
  return folder


def add_missing_atimes(folder: Path) -> int:
  """Gives every entry of a compilation-cache folder the access-time file that jax's size limit
  needs; returns how many were added.

  Entries written without the limit (before `filelock` was installed, which torch, for one,
  brings) have none, and with the limit on jax reads every entry's access time before each
  write: one missing file failed every later write ("Error writing persistent compilation cache
  entry ... -atime: FileNotFoundError", seen in a user's cache). The entry's modification time
  stands in for its last use."""
  import filelock
  if not folder.is_dir():
    return 0
  added = 0
  with filelock.FileLock(folder / ".lockfile", timeout=10):  # jax's own lock of the folder
    for entry in folder.glob(f"*{CACHE_SUFFIX}"):
      atime = folder / (entry.name[:-len(CACHE_SUFFIX)] + ATIME_SUFFIX)
      if not atime.exists():
        atime.write_bytes(entry.stat().st_mtime_ns.to_bytes(8, "little"))
        added += 1
  return added


def load_last_programs(argv: list[str], names: tuple[str, ...] = ("train-step", "init")) -> None:
  """At a command line's launch, before its heavy imports: the compile cache on (as the command
  will turn it on) and the programs `names` its last launch with these arguments ran loading in
  the background (sljax.runtime.kept_programs.load_early). Not for distributed runs (nothing is
  kept across processes)."""
  if "--distributed" in argv:
    return
  enable_compile_cache(programs=True)
  kept_programs.load_early(argv, names)
