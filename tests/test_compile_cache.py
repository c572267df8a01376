"""The user cache folder and JAX's persistent compilation cache (sljax.runtime.compile_cache)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jaxlib
import pytest

from sljax.runtime import compile_cache, machine

# A child process that compiles one program with the cache in a given folder and reports its
# output and how many compilations the cache served (jax's monitoring events).
CHILD = """
import json, sys
import jax, jax.numpy as jnp
from sljax.runtime.compile_cache import enable_compile_cache
hits = []
jax.monitoring.register_event_listener(
    lambda name, **kw: hits.append(name) if name.endswith("cache_hits") else None)
folder = enable_compile_cache()
f = jax.jit(lambda x: jnp.cumsum(jnp.sin(x) * 3.0) @ jnp.cos(x))
y = f(jnp.linspace(0.0, 1.0, 257))
print(json.dumps({"folder": str(folder), "y": float(y), "hits": len(hits)}))
"""


def _child(env: dict) -> dict:
  out = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True,
                       check=True)
  return json.loads(out.stdout.strip().splitlines()[-1])


def test_user_cache_dir_order(monkeypatch, tmp_path):
  monkeypatch.setenv("SLJAX_CACHE_DIR", str(tmp_path / "a"))
  assert compile_cache.user_cache_dir() == tmp_path / "a"
  monkeypatch.delenv("SLJAX_CACHE_DIR")
  monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
  assert compile_cache.user_cache_dir() == tmp_path / "xdg" / "sljax"


def test_compile_cache_folder_is_per_cpu_flags_and_versions(monkeypatch, tmp_path):
  monkeypatch.setenv("SLJAX_COMPILE_CACHE", str(tmp_path))
  monkeypatch.setattr(machine, "cpu_flags", lambda *a: {"sse2", "avx2"})
  a = compile_cache.compile_cache_dir()
  monkeypatch.setattr(machine, "cpu_flags", lambda *a: {"sse2", "avx2", "avx512f"})
  b = compile_cache.compile_cache_dir()
  assert a.parent == b.parent == tmp_path and a != b  # another ISA: another folder
  assert a.name.startswith(machine.cpu_key()) and a.name.endswith(
      f"jax-{jax.__version__}-jaxlib-{jaxlib.__version__}")
  for off in ("off", "0", "no"):
    monkeypatch.setenv("SLJAX_COMPILE_CACHE", off)
    assert compile_cache.compile_cache_dir() is None


def test_second_process_loads_the_program_and_gets_the_same_numbers(tmp_path):
  env = dict(os.environ, SLJAX_COMPILE_CACHE=str(tmp_path / "xla"),
             JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
  env.pop("JAX_COMPILATION_CACHE_DIR", None)
  first = _child(env)
  folder = Path(first["folder"])
  assert folder.parent == tmp_path / "xla" and any(folder.iterdir())
  second = _child(env)
  assert first["hits"] == 0 and second["hits"] >= 1
  assert second["y"] == first["y"]
  off = _child(dict(env, SLJAX_COMPILE_CACHE="off"))
  assert off["folder"] == "None" and off["hits"] == 0 and off["y"] == first["y"]


def test_entries_written_without_the_size_limit_do_not_break_later_writes(tmp_path):
  """A cache folder filled while `filelock` was missing (no size limit, so no access-time
  files), then used with the limit on: jax's own LRU cache fails every write until the
  missing access times are added."""
  from jax._src.lru_cache import LRUCache  # the class jax's persistent cache uses
  unlimited = LRUCache(str(tmp_path), max_size=-1)
  unlimited.put("old", b"x" * 100)
  limited = LRUCache(str(tmp_path), max_size=2**20)
  if not (tmp_path / "old-cache").exists():
    # A jax whose cache names entries otherwise (jax 0.11.2 on an H100 failed this test when it
    # expected jax 0.10's names and error; its traceback did not come back): the repair must
    # find nothing to add and leave the cache working.
    assert compile_cache.add_missing_atimes(tmp_path) == 0
    limited.put("new", b"y" * 100)
    assert limited.get("new") == b"y" * 100 and limited.get("old") == b"x" * 100
    return
  try:
    limited.put("new", b"y" * 100)  # jax 0.10 fails every write until the access times exist
  except FileNotFoundError as err:
    assert "old-atime" in str(err)
  mtime = (tmp_path / "old-cache").stat().st_mtime_ns
  assert compile_cache.add_missing_atimes(tmp_path) == 1
  assert int.from_bytes((tmp_path / "old-atime").read_bytes(), "little") == mtime
  assert compile_cache.add_missing_atimes(tmp_path) == 0  # idempotent
  limited.put("new", b"y" * 100)
  assert limited.get("new") == b"y" * 100 and limited.get("old") == b"x" * 100
  assert compile_cache.add_missing_atimes(tmp_path / "absent") == 0
