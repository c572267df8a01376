"""Compiled programs kept on disk, so that a second run neither traces, lowers nor compiles.

JAX's persistent compilation cache (sljax.runtime.compile_cache) saves XLA's compile, but each process still
traces the Python program to a jaxpr and lowers it to StableHLO before it can look the
executable up: for the twin's training step on a 2-core CPU that was 4-9 s of a warm first
step. Here the compiled executable itself is serialised (`jax.experimental.serialize_executable`)
and loaded by a key computed without tracing: the caller's description of the program (for a
training step: the resolved model config, loss, optimiser settings, compiler options and mesh),
the arguments' tree and shapes and dtypes, the jax, jaxlib, flax and optax versions, the
backend and its devices, the CPU kind and instruction set, XLA_FLAGS and the jax settings that
change programs, and a digest of sljax's own source files. Anything that could change the
program changes the key; what cannot be keyed (a function patched at run time) is why the
cache is off unless a command line turns it on (`enable`), as `python train.py` and `sljax`
do: code importing sljax and the test suite trace as before.

An entry holds a header (its key and the payload's SHA-256), the pickled argument and output
trees and XLA's serialised executable. A damaged or unloadable entry (a partial write, another
XLA) is deleted and compiled again, with one line on stderr; one that loads but fails in its
first run is deleted and the run stops with one line (the next run compiles it). Only an
executable XLA compiled in the call is kept: XLA:CPU (jaxlib 0.10.2) re-serialises one it
loaded from jax's cache without some of its kernels, and such an entry loaded, then failed
("NOT_FOUND: Function transpose_copy_fusion.21 not found"). So when jax's cache answers (after
an edit of sljax that left the program as it was, say) the program is compiled afresh once,
under a compiler option that jax's key sees and XLA ignores, and kept. Entries sit in the
compile cache's folder under jax's own file names, bounded with it by jax's size limit (least
recently used first), and whatever turns the compile cache off (`SLJAX_COMPILE_CACHE=off`)
turns this off too. A folder it cannot read or write costs the cache, never the run. An entry
is unpickled and loaded only when it, its folder and their parents up to the cache's root pass
sljax.runtime.cache_trust's check (checked again at each load: the pickled trees run code);
otherwise one line, and the process keeps no programs from then on.
Multi-process runs (`--distributed`) are not cached: an executable there spans the processes'
devices.
"""

import concurrent.futures
import functools
import hashlib
import json
import os
import pickle
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax

from sljax.errors import SljaxError
from sljax.runtime import cache_trust
from sljax.runtime.program_keys import (PREFIX, digest, entry_key, environment, signature,
                                        source_digest)

ENV = "SLJAX_PROGRAM_CACHE"  # 0/off/false/no: never keep or load compiled programs
MAGIC = b"sljax-executable 1\n"
INDEXED = 4  # argument signatures remembered per program (batch shapes of one run)
# A compile option jax's cache key includes and XLA ignores without a dump folder: a program
# compiled under it misses jax's cache, so XLA compiles it afresh (`compile_and_keep`).
FRESH_OPTION = {"xla_dump_large_constants": True}

LAUNCHES = f"{PREFIX}launches.json"  # {launch digest: {program name: entry key}}, in the folder
KEPT_LAUNCHES = 16  # launches remembered (the newest first)

_state = {"folder": None, "root": None, "launch": None}
# program name -> (entry key, future of (program or None, 'loaded')): loads started at launch
_early: dict[str, tuple[str, concurrent.futures.Future]] = {}


def enable(folder: Path | None, root: Path | None = None, checked: bool = False) -> Path | None:
  """Keeps compiled programs in `folder` (the compile cache's; None turns it off) unless
  $SLJAX_PROGRAM_CACHE is off or the folder is not trusted (sljax.runtime.cache_trust, its
  parents checked up to `root`, by default the folder itself; `checked`: the caller has just
  made that check, which scans every entry); returns the folder in use."""
  off = os.environ.get(ENV, "").strip().lower() in ("0", "off", "false", "no")
  _state["folder"] = None if off or folder is None else Path(folder)
  _state["root"] = None if _state["folder"] is None else Path(root or folder)
  if _state["folder"] is not None and not checked and _untrusted(
      cache_trust.untrusted_folder(_state["folder"], _state["root"])):
    return None
  return _state["folder"]


def _untrusted(found: tuple[Path, str, str] | None) -> bool:
  """Whether a trust check found something; if so the process keeps no programs from now on
  (neither loading nor writing there), and one line says so (once per process)."""
  if found is None:
    return False
  where, _state["folder"] = _state["folder"], None
  if where is not None:
    cache_trust.warn_once(where, found)
  return True


def folder() -> Path | None:
  """The folder programs are kept in (None: off)."""
  return _state["folder"]


def _store(path: Path):
  """jax's cache over the compile cache's folder, with jax's own size limit of it (sljax's
  folder: sljax.runtime.compile_cache.MAX_BYTES; a folder of the user's: theirs, unbounded by default)."""
  from jax._src import lru_cache
  return lru_cache.LRUCache(str(path), max_size=jax.config.jax_compilation_cache_max_size)


def pack(key: str, compiled) -> bytes:
  """An entry: header, trees, executable."""
  from jax.experimental import serialize_executable
  payload, in_tree, out_tree = serialize_executable.serialize(compiled)
  trees = pickle.dumps((in_tree, out_tree))
  body = len(trees).to_bytes(8, "little") + trees + payload
  header = json.dumps({"key": key, "sha256": hashlib.sha256(body).hexdigest()}).encode()
  return MAGIC + header + b"\n" + body


def unpack(key: str, data: bytes, device: jax.Device | None = None):
  """The compiled program of an entry, loaded for `device` (None: the default backend's
  devices); ValueError when it is not an intact entry for `key`."""
  from jax.experimental import serialize_executable
  if not data.startswith(MAGIC):
    raise ValueError("not an sljax executable")
  header, sep, body = data[len(MAGIC):].partition(b"\n")
  if not sep:
    raise ValueError("no header")
  meta = json.loads(header)
  if meta.get("key") != key:
    raise ValueError("written for another program")
  if hashlib.sha256(body).hexdigest() != meta.get("sha256"):
    raise ValueError("damaged (checksum differs)")
  n = int.from_bytes(body[:8], "little")
  in_tree, out_tree = pickle.loads(body[8:8 + n])
  if device is None:
    return serialize_executable.deserialize_and_load(body[8 + n:], in_tree, out_tree)
  return serialize_executable.deserialize_and_load(body[8 + n:], in_tree, out_tree,
                                                 device.client, [device])


def index_path(where: Path, name: str, description: Any) -> Path:
  """The file listing the argument signatures a program was last used with (newest first):
  what a later process loads before its first call."""
  found = digest({"name": name, "description": repr(description), **environment()})
  return where / f"{PREFIX}{name}-signatures-{found}.json"


def _remember(where: Path, name: str, description: Any, sig: str) -> None:
  """Puts `sig` first in the program's index (at most INDEXED kept); a failure is only a
  missed prefetch."""
  path = index_path(where, name, description)
  try:
    old = json.loads(path.read_text(encoding="utf-8")) if path.exists() else []
    sigs = [sig] + [s for s in old if isinstance(s, str) and s != sig][:INDEXED - 1]
    if sigs != old:
      tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
      tmp.write_text(json.dumps(sigs), encoding="utf-8")
      os.replace(tmp, path)
  except (OSError, ValueError):
    pass


def remembered(name: str, description: Any) -> list[str]:
  """The signatures in the program's index ([] when there is none or it is unreadable)."""
  where = folder()
  if where is None:
    return []
  try:
    sigs = json.loads(index_path(where, name, description).read_text(encoding="utf-8"))
  except (OSError, ValueError):
    return []
  return [s for s in sigs if isinstance(s, str)] if isinstance(sigs, list) else []


def load(name: str, key: str, log: Callable[[str], None], device: jax.Device | None = None):
  """The kept program under `key`, or None: none kept, a folder that cannot be read (one
  line), or an entry that is not intact (deleted, one line)."""
  where = folder()
  if where is None or _untrusted(cache_trust.untrusted_chain(where / f"{key}-cache",
                                                             _state["root"] or where)):
    return None  # the entry is checked before its bytes are unpickled and loaded
  try:
    data = _store(where).get(key)
  except Exception as e:  # noqa: BLE001  a read-only, full or busy folder: compile instead
    log(f"sljax: compiled programs in {where} not readable ({type(e).__name__}: {e})")
    return None
  if data is None:
    return None
  try:
    return unpack(key, data, device)
  except Exception as e:  # noqa: BLE001  any failure to load means: compile it again
    log(f"sljax: compiled {name} program {where / key}-cache unusable "
        f"({type(e).__name__}: {e}); compiling it again")
    forget(where, key)
    return None


def forget(where: Path, key: str) -> None:
  """Deletes an entry (a folder that refuses only leaves it for the next run to find)."""
  for suffix in ("-cache", "-atime"):
    try:
      (where / f"{key}{suffix}").unlink(missing_ok=True)
    except OSError:
      pass


_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"  # XLA asked (or jax's cache read)
_HIT_EVENT = "/jax/compilation_cache/cache_hits"  # ... and jax's cache answered
_events = threading.local()


def _on_event(event: str, *args, **kwargs) -> None:
  if event in (_COMPILE_EVENT, _HIT_EVENT):
    seen = getattr(_events, "seen", None)
    if seen is not None:
      seen.add(event)


@functools.cache
def _listening() -> bool:
  jax.monitoring.register_event_listener(_on_event)
  jax.monitoring.register_event_duration_secs_listener(_on_event)
  return True


def fresh_compile(lowered, options: dict[str, Any] | None = None) -> tuple[Any, bool]:
  """(the lowered program compiled, whether XLA compiled it in this call: not when jax took
  it from its persistent cache or from a compile earlier in this process)."""
  _listening()
  _events.seen = set()
  try:
    compiled = lowered.compile(compiler_options=options)
    return compiled, _events.seen == {_COMPILE_EVENT}
  finally:
    _events.seen = None


def _jax_cache_unwritten():
  """In this thread, jax's persistent cache writes nothing: a kept program's entry there would
  never serve it (one from that cache is compiled afresh, above) and would double its bytes
  in the bounded folder; writing it cost 0.8 s of the main job's cold first step on Zen 5."""
  from jax._src import config as jax_config
  return jax_config.persistent_cache_min_compile_time_secs(float("inf"))


def compile_and_keep(jitted, name: str, key: str | None, args: tuple,
                     log: Callable[[str], None]) -> tuple[Any, str]:
  """(the program compiled for `args`, 'compiled' or 'compiled, not kept'), kept under `key`
  (None: not kept) when XLA compiled it afresh, compiling it afresh when jax's cache gave it."""
  lowered = jitted.lower(*args)
  if key is None:
    return fresh_compile(lowered)[0], "compiled, not kept"
  with _jax_cache_unwritten():
    compiled, fresh = fresh_compile(lowered)
    if not fresh:  # a cached executable re-serialises without some kernels (module docstring)
      compiled, fresh = fresh_compile(lowered, FRESH_OPTION)
  if not fresh:
    return compiled, "compiled, not kept"
  try:
    _store(folder()).put(key, pack(key, compiled))
  except Exception as e:  # noqa: BLE001  a full disk or an unserialisable program: run anyway
    log(f"sljax: compiled {name} program not kept ({type(e).__name__}: {e})")
    forget(folder(), key)  # a partial write
    return compiled, "compiled, not kept"
  return compiled, "compiled"


# ----------------------------------------------------------------------------- at launch


def launch_digest(argv: list[str]) -> str:
  """What a command line's programs depend on before anything is parsed: its arguments, the
  environment variables sljax, jax and XLA read, and sljax's source."""
  env = {k: v for k, v in sorted(os.environ.items())
         if k.startswith(("SLJAX_", "JAX_", "XLA_", "LIBTPU_"))}
  return digest({"argv": list(argv), "env": env, "sljax": source_digest()})


def load_early(argv: list[str], names: tuple[str, ...]) -> None:
  """Starts loading, on background threads, the programs `names` that the last launch with the
  same arguments ran (its key, remembered in the folder's LAUNCHES), before the caller has
  imported, parsed or set up anything: a warm run's first step waited for its 3.3 s load. A
  program takes such a load only when its own key, computed as ever, is the same
  (`Program.prefetch`); otherwise it is dropped."""
  where = folder()
  if where is None:
    return
  _state["launch"] = launch_digest(argv)
  keys = _read_launches(where).get(_state["launch"])
  for name in names:
    key = keys.get(name) if isinstance(keys, dict) else None
    if isinstance(key, str) and key.startswith(f"{PREFIX}{name}-") and name not in _early:
      _early[name] = (key, _POOL.submit(lambda n=name, k=key: (load(n, k, _stderr), "loaded")))


def _take_early(name: str, key: str) -> concurrent.futures.Future | None:
  """The load started at launch for this program if it is of `key`, else None."""
  entry = _early.get(name)
  if entry is None or entry[0] != key:
    return None
  del _early[name]
  return entry[1]


def _read_launches(where: Path) -> dict:
  try:
    data = json.loads((where / LAUNCHES).read_text(encoding="utf-8"))
  except (OSError, ValueError):
    return {}
  return data if isinstance(data, dict) else {}


def _remember_launch(where: Path, name: str, key: str) -> None:
  """Notes that this launch ran `name` as `key`, the launch first (a failure only misses the
  next early load)."""
  launch = _state["launch"]
  if launch is None:
    return
  data = _read_launches(where)
  entry = data.get(launch)
  entry = dict(entry) if isinstance(entry, dict) else {}
  if next(iter(data), None) == launch and entry.get(name) == key:
    return
  entry[name] = key
  others = [(k, v) for k, v in data.items() if k != launch][:KEPT_LAUNCHES - 1]
  try:
    tmp = where / f"{LAUNCHES}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(dict([(launch, entry), *others])), encoding="utf-8")
    os.replace(tmp, where / LAUNCHES)
  except OSError:
    pass


def _stderr(line: str) -> None:
  print(line, file=sys.stderr, flush=True)


class Program:
  """A jitted function served from the disk cache: called like it, it loads (or compiles and
  keeps) one executable per argument signature. Off the cache it is the jitted function.

  `prefetch` starts loading, on background threads, the programs kept for the signatures this
  program was last used with: XLA's load releases the GIL, so on a 2-core CPU it runs beside
  the run's initialisation, and the first call waits only for what is left. `ahead` does the
  same for arguments known only by their shapes: it loads, else compiles and keeps, the
  program for them on a background thread, so that XLA compiles while the caller initialises
  (a fresh run's first step). Keys are always
  computed on the calling thread (jax's settings can be thread-local). `device` names the one
  device a program runs on when that is not the default backend's (the caller places its
  arguments there): it is part of the key, and kept programs load for it."""

  def __init__(self, jitted, name: str, description: Any,
               log: Callable[[str], None] = _stderr, device: jax.Device | None = None):
    self.jitted, self.name, self.log, self.device = jitted, name, log, device
    self.description = (description if device is None
                        else (description, f"{device.platform}:{device.id}"))
    self._by_signature: dict[str, Any] = {}
    # signature -> (key, future of (program or None, how it came)): prefetched or compiled ahead
    self._loading: dict[str, tuple[str, concurrent.futures.Future]] = {}
    self._unproven: set[int] = set()  # loaded programs not yet run once
    self._last = None
    # Loader threads call a program side by side (the renderer's stages): one of them finds,
    # loads or compiles each signature's program, and runs a loaded one first, the others wait.
    self._lock = threading.Lock()
    self.origin: str | None = None  # how the last new program came: loaded or compiled

  def prefetch(self) -> "Program":
    """Starts loading the kept programs of the remembered signatures; returns self."""
    if folder() is None or jax.process_count() > 1:
      return self
    with self._lock:
      for sig in remembered(self.name, self.description):
        if sig not in self._by_signature and sig not in self._loading:
          key = entry_key(self.name, self.description, sig)
          early = _take_early(self.name, key) if self.device is None else None
          self._loading[sig] = (key, early or _POOL.submit(self._loaded, key))
    return self

  def ahead(self, *args) -> "Program":
    """Starts getting the program for arguments given by their shapes and dtypes
    (`jax.ShapeDtypeStruct`s, with the weak types the real ones will have) on a background
    thread: loaded where kept, else traced, compiled and kept. The call with the real arguments
    then waits for it; one whose signature differs gets its own program as before. Off the
    cache (or across processes) nothing starts: jit's own cache would not see the result."""
    if folder() is None or jax.process_count() > 1:
      return self
    sig = signature(args)
    with self._lock:
      if sig not in self._by_signature and sig not in self._loading:
        key = entry_key(self.name, self.description, sig)
        self._loading[sig] = (key, _POOL.submit(self._got, key, args))
    return self

  @property
  def prefetching(self) -> bool:
    """Whether a program for some signature is being loaded or compiled in the background."""
    with self._lock:
      return bool(self._loading)

  def _loaded(self, key: str):
    """(the kept program under `key` or None, 'loaded')."""
    return load(self.name, key, self.log, self.device), "loaded"

  def _got(self, key: str, args: tuple):
    """(the program, how it came): loaded, else compiled and kept; (None, None) where that
    fails, so that the real call compiles and reports the failure itself."""
    compiled, origin = self._loaded(key)
    if compiled is not None:
      return compiled, origin
    try:
      return compile_and_keep(self.jitted, self.name, key if folder() else None, args, self.log)
    except Exception:  # noqa: BLE001  the real call raises it where the caller sees it
      return None, None

  def _program(self, sig: str, args: tuple):
    """The program for this signature: prefetched, loaded, or compiled and kept."""
    where = folder()
    key = None if where is None or jax.process_count() > 1 else entry_key(
        self.name, self.description, sig)
    compiled = origin = None
    if sig in self._loading:
      prefetched, future = self._loading.pop(sig)
      if prefetched == key:
        compiled, origin = future.result()
    if compiled is None and key is not None:
      compiled, origin = self._loaded(key)
    if folder() is None:  # a trust check in a load turned the cache off: keep nothing there
      where = key = None
    if compiled is not None:
      self.origin = origin
      if origin == "loaded":
        self._unproven.add(id(compiled))
    else:
      compiled, self.origin = compile_and_keep(self.jitted, self.name, key, args, self.log)
    if key is not None and self.origin != "compiled, not kept":
      _remember(where, self.name, self.description, sig)
      _remember_launch(where, self.name, key)
    return compiled, key

  def _first_run(self, compiled, key: str, args: tuple):
    """A loaded program's first run, waited for: one that fails is deleted, with one line."""
    try:
      return jax.block_until_ready(compiled(*args))
    except jax.errors.JaxRuntimeError as e:
      forget(folder(), key)
      raise SljaxError(f"the kept compiled {self.name} program {folder() / key}-cache failed "
                       f"when it ran ({str(e).splitlines()[0][:200]}); it is deleted: run the "
                       "command again") from None
    finally:
      self._unproven.discard(id(compiled))

  def __call__(self, *args):
    if folder() is None:
      return self.jitted(*args)
    if self._last is not None and id(self._last) not in self._unproven:
      try:
        return self._last(*args)
      except (TypeError, ValueError):
        # Argument types differ from the last program's (its check runs before anything
        # executes, so a donated argument is intact); the signature decides below.
        pass
    sig = signature(args)
    with self._lock:
      entry = self._by_signature.get(sig)
      if entry is None:
        entry = self._by_signature[sig] = self._program(sig, args)
      elif entry[0] is self._last and id(self._last) not in self._unproven:
        return self._last(*args)  # the same signature failed: a genuine error, raised here
      compiled, key = entry
      self._last = compiled
      if id(compiled) in self._unproven:
        return self._first_run(compiled, key, args)
    return compiled(*args)


# Loads run on these threads (a few: programs of one run load side by side).
_POOL = concurrent.futures.ThreadPoolExecutor(max_workers=2, thread_name_prefix="sljax-load")
