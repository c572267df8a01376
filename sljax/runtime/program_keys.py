"""What a kept program's key is made of (sljax.runtime.kept_programs): the caller's description,
the arguments' signature, and everything outside them that changes a compiled program."""

import functools
import hashlib
import json
import os
import sys
from pathlib import Path
from typing import Any

import jax
import jaxlib
import numpy as np

from sljax.runtime import machine

PREFIX = "sljax-program-"  # every kept program's file name starts so
SOURCE_ROOT = Path(__file__).resolve().parents[1]  # the sljax package: any edit changes keys
# jax settings that do not change a compiled program (where caches, logs and dumps go, checks
# of the host's use): left out of the key, so that setting them does not miss the cache.
_IGNORED_SETTINGS = ("jax_compilation_cache", "jax_persistent_cache", "jax_log_compiles",
                     "jax_logging_level", "jax_debug_log_modules", "jax_dump_ir",
                     "jax_explain_cache_misses", "jax_pprint", "jax_traceback_filtering",
                     "jax_tracer_error_num_traceback_frames", "jax_transfer_guard",
                     "jax_thread_guard", "jax_source_url_schema", "jax_captured_constants")


@functools.cache
def source_digest(root: Path | None = None) -> str:
  """SHA-256 over the Python files under root, sljax's by default (their paths and bytes):
  an edited sljax never loads a program compiled from the old code."""
  root = root or SOURCE_ROOT
  h = hashlib.sha256()
  for path in sorted(root.rglob("*.py")):
    h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
  return h.hexdigest()


def _versions() -> dict[str, str]:
  import flax
  import optax
  return {"jax": jax.__version__, "jaxlib": jaxlib.__version__, "flax": flax.__version__,
          "optax": optax.__version__, "numpy": np.__version__,
          "python": sys.version.split()[0]}


@functools.cache
def _cpu() -> str:
  flags = ",".join(sorted(machine.cpu_flags()))
  return f"{machine.cpu_key()} {hashlib.sha1(flags.encode()).hexdigest()[:8]}"


def environment() -> dict[str, Any]:
  """Everything outside the caller's description that changes a compiled program."""
  settings = {k: repr(getattr(jax.config, k, v)) for k, v in sorted(jax.config.values.items())
              if not k.startswith(_IGNORED_SETTINGS)}
  env = {k: v for k, v in sorted(os.environ.items())
         if k in ("XLA_FLAGS", "LIBTPU_INIT_ARGS") or k.startswith("SLJAX_CONV")}
  devices = [f"{d.platform}:{d.device_kind}:{d.id}" for d in jax.devices()]
  return {"versions": _versions(), "backend": jax.default_backend(), "devices": devices,
          "cpu": _cpu(), "settings": settings, "env": env, "sljax": source_digest()}


def signature(args: tuple) -> str:
  """The arguments' tree, shapes, dtypes and weak types (what a compiled program is for)."""
  leaves, tree = jax.tree.flatten(args)
  return repr(tree) + repr([(np.shape(x), str(getattr(x, "dtype", type(x).__name__)),
                             bool(getattr(x, "weak_type", False))) for x in leaves])


def digest(obj: Any) -> str:
  """A file-name-safe digest of a JSON-able object."""
  return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:40]


def entry_key(name: str, description: Any, sig: str) -> str:
  """The file-name-safe key of one program: a digest of what it is and where it runs."""
  found = digest({"name": name, "description": repr(description), "signature": sig,
                  **environment()})
  return f"{PREFIX}{name}-{found}"
