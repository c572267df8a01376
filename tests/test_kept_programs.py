"""Whole compiled programs kept on disk (sljax.runtime.kept_programs): a second process loads the program
instead of tracing and compiling it, with the same numbers; anything that changes the program
changes its key; a damaged entry is compiled again with one line and never runs; the folder is
bounded with the compile cache's; and `python train.py` run twice continues identically."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sljax.errors import SljaxError
from sljax.runtime import compile_cache, kept_programs, program_keys

ROOT = Path(__file__).resolve().parents[1]


def _step(state, x):
  """A small program with a donated, nested state (the training step's shape of arguments)."""
  new = {"w": state["w"] - 0.1 * jnp.tanh(x @ state["w"]).T @ x, "n": state["n"] + 1}
  return new, {"loss": jnp.sum(new["w"] ** 2)}


def _jitted():
  return jax.jit(_step, donate_argnums=(0,))


def _args(seed=0, rows=4):
  rng = np.random.default_rng(seed)
  return ({"w": jnp.asarray(rng.normal(size=(3, 3)), jnp.float32), "n": jnp.zeros((), jnp.int32)},
          jnp.asarray(rng.normal(size=(rows, 3)), jnp.float32))


@pytest.fixture
def folder(tmp_path, monkeypatch):
  """Programs kept in a folder of this test's own, turned off again afterwards."""
  monkeypatch.setenv(kept_programs.ENV, "on")
  jax.clear_caches()  # each test's first compile is XLA's, not one kept from another test
  where = kept_programs.enable(tmp_path / "xla")
  yield where
  kept_programs.enable(None)


def _entries(where: Path, name: str = "") -> list[Path]:
  return sorted(where.glob(f"{kept_programs.PREFIX}{name}*-cache"))


def _reference(seed=0, rows=4, calls=3):
  """The plain jitted function's outputs over a few calls (the state carried)."""
  state, x = _args(seed, rows)
  outs = []
  for _ in range(calls):
    state, metrics = _jitted()(state, x)
    outs.append(jax.tree.map(np.asarray, (state, metrics)))
  return outs


def _run(program, seed=0, rows=4, calls=3):
  state, x = _args(seed, rows)
  outs = []
  for _ in range(calls):
    state, metrics = program(state, x)
    outs.append(jax.tree.map(np.asarray, (state, metrics)))
  return outs


def _equal(a, b):
  for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
    np.testing.assert_array_equal(x, y)


def test_a_new_program_object_loads_what_the_first_compiled(folder):
  first = kept_programs.Program(_jitted(), "step", ("demo", 1))
  _equal(_run(first), _reference())
  assert first.origin == "compiled" and len(_entries(folder, "step")) == 1
  # A fresh object stands for a fresh process: it must load, not lower or compile.
  second = kept_programs.Program(_jitted(), "step", ("demo", 1))
  second.jitted = None  # any use of the jitted function would fail
  _equal(_run(second), _reference())
  assert second.origin == "loaded" and len(_entries(folder)) == 1


def test_each_signature_gets_its_own_program(folder):
  program = kept_programs.Program(_jitted(), "step", "demo")
  _equal(_run(program, rows=4), _reference(rows=4))
  _equal(_run(program, rows=6), _reference(rows=6))  # another batch shape: another program
  _equal(_run(program, rows=4), _reference(rows=4))  # and back
  assert len(_entries(folder, "step")) == 2


def test_a_genuine_error_is_raised_not_swallowed(folder):
  program = kept_programs.Program(_jitted(), "step", "demo")
  _run(program, calls=1)
  state, _ = _args()
  with pytest.raises(TypeError):
    program(state, "not an array")


def test_the_key_changes_with_everything_that_changes_the_program(folder, monkeypatch):
  sig = program_keys.signature(_args())
  base = program_keys.entry_key("step", ("demo", 1), sig)
  assert program_keys.entry_key("step", ("demo", 1), sig) == base  # deterministic
  assert program_keys.entry_key("step", ("demo", 2), sig) != base  # the caller's description
  assert program_keys.entry_key("eval", ("demo", 1), sig) != base  # the program's name
  assert program_keys.entry_key("step", ("demo", 1), program_keys.signature(_args(rows=5))) != base
  f64 = (_args()[0], np.zeros((4, 3), np.float64))
  assert program_keys.signature(f64) != sig  # dtypes
  with monkeypatch.context() as m:
    m.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", "") + " --xla_cpu_enable_fast_math=true")
    assert program_keys.entry_key("step", ("demo", 1), sig) != base
  with jax.default_matmul_precision("bfloat16"):
    assert program_keys.entry_key("step", ("demo", 1), sig) != base  # a jax setting
  with monkeypatch.context() as m:
    m.setattr(program_keys, "source_digest", lambda: "edited")
    assert program_keys.entry_key("step", ("demo", 1), sig) != base  # sljax's own code
  with monkeypatch.context() as m:
    m.setattr(program_keys, "_versions", lambda: {"jax": "0.0"})
    assert program_keys.entry_key("step", ("demo", 1), sig) != base  # the libraries
  # Where caches go and what is logged do not change a program: the same key.
  with jax.log_compiles(True):
    assert program_keys.entry_key("step", ("demo", 1), sig) == base
  assert program_keys.entry_key("step", ("demo", 1), sig) == base


def test_source_digest_changes_with_any_file(tmp_path):
  assert len(program_keys.source_digest()) == 64
  # By default the whole package: an edit of a network changes every key, not only of runtime/.
  import sljax
  assert program_keys.SOURCE_ROOT == Path(sljax.__file__).resolve().parent
  for name in ("a.py", "sub/b.py", "notes.txt"):
    (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
    (tmp_path / name).write_text("x = 1\n")
  base = program_keys.source_digest.__wrapped__(tmp_path)
  (tmp_path / "sub/b.py").write_text("x = 2\n")
  assert program_keys.source_digest.__wrapped__(tmp_path) != base
  (tmp_path / "sub/b.py").write_text("x = 1\n")
  assert program_keys.source_digest.__wrapped__(tmp_path) == base
  (tmp_path / "notes.txt").write_text("not code")  # only Python files count
  assert program_keys.source_digest.__wrapped__(tmp_path) == base
  (tmp_path / "sub/b.py").rename(tmp_path / "b.py")  # a file moved is another program
  assert program_keys.source_digest.__wrapped__(tmp_path) != base


@pytest.mark.parametrize("damage", ["flip", "truncate", "other-key", "garbage"])
def test_a_damaged_entry_is_compiled_again_with_one_line(folder, damage):
  kept_programs.Program(_jitted(), "step", "demo")(*_args())
  (path,) = _entries(folder, "step")
  data = bytearray(path.read_bytes())
  if damage == "flip":
    data[-100] ^= 0xFF
  elif damage == "truncate":
    data = data[:len(data) // 2]
  elif damage == "other-key":
    header, _, body = bytes(data[len(kept_programs.MAGIC):]).partition(b"\n")
    meta = dict(json.loads(header), key="sljax-program-step-another")
    data = kept_programs.MAGIC + json.dumps(meta).encode() + b"\n" + body
  else:
    data = b"\0" * 64
  path.write_bytes(bytes(data))
  if damage == "flip":  # the checksum, not the luck of XLA's parser, refuses it
    with pytest.raises(ValueError, match="checksum"):
      kept_programs.unpack(path.name[:-len("-cache")], bytes(data))
  lines = []
  jax.clear_caches()  # as a new process: XLA compiles it again
  program = kept_programs.Program(_jitted(), "step", "demo", log=lines.append)
  _equal(_run(program), _reference())
  assert program.origin == "compiled"
  assert len(lines) == 1 and "unusable" in lines[0] and "compiling it again" in lines[0]
  assert str(path) in lines[0]
  # Written anew: the next process loads it.
  again = kept_programs.Program(_jitted(), "step", "demo", log=lines.append)
  _equal(_run(again), _reference())
  assert again.origin == "loaded" and len(lines) == 1


def test_off_means_the_plain_jitted_function(tmp_path, monkeypatch):
  monkeypatch.setenv(kept_programs.ENV, "off")
  assert kept_programs.enable(tmp_path) is None
  program = kept_programs.Program(_jitted(), "step", "demo")
  _equal(_run(program), _reference())
  assert program.origin is None and not list(tmp_path.iterdir())
  monkeypatch.setenv(kept_programs.ENV, "on")
  assert kept_programs.enable(None) is None  # the compile cache off turns it off too
  kept_programs.enable(None)


def test_the_compile_cache_turns_it_on_only_for_command_lines(monkeypatch):
  monkeypatch.setenv(kept_programs.ENV, "on")
  try:  # the suite's compile cache is on (conftest): its folder is the one returned
    folder = compile_cache.enable_compile_cache()
    assert kept_programs.folder() is None  # library code: not kept
    assert compile_cache.enable_compile_cache(programs=True) == folder
    assert kept_programs.folder() == folder
  finally:
    kept_programs.enable(None)


def test_entries_are_bounded_with_the_compile_cache(folder, monkeypatch):
  """Entries carry jax's access-time files, so the size limit of the folder evicts them, least
  recently used first."""
  kept_programs.Program(_jitted(), "step", "a")(*_args())
  (first,) = _entries(folder)
  assert first.with_name(first.name[:-len("-cache")] + "-atime").exists()
  limit = jax.config.jax_compilation_cache_max_size
  jax.config.update("jax_compilation_cache_max_size", int(first.stat().st_size * 1.5))
  try:
    jax.clear_caches()
    kept_programs.Program(_jitted(), "step", "b")(*_args())
  finally:
    jax.config.update("jax_compilation_cache_max_size", limit)
  assert not first.exists() and len(_entries(folder)) == 1


def test_a_folder_of_the_users_own_without_a_limit_keeps_programs(folder):
  """jax's default is no limit, and then its entries have no access-time files: sljax's must
  not ask for them (every keep failed with FileNotFoundError)."""
  limit = jax.config.jax_compilation_cache_max_size
  jax.config.update("jax_compilation_cache_max_size", -1)
  try:
    program = kept_programs.Program(_jitted(), "step", "demo")
    _run(program)
    assert program.origin == "compiled" and len(_entries(folder)) == 1
  finally:
    jax.config.update("jax_compilation_cache_max_size", limit)


def test_a_folder_that_refuses_costs_the_cache_not_the_run(folder, monkeypatch):
  """A read-only, full or busy folder: one line, and the run goes on compiling."""
  class Refusing:
    def __init__(self, *a, **k):
      pass

    def get(self, key):
      raise PermissionError(13, "Permission denied")

    put = get
  _run(kept_programs.Program(_jitted(), "step", "demo"), calls=1)  # remembered, kept
  monkeypatch.setattr(kept_programs, "_store", Refusing)
  jax.clear_caches()
  lines = []
  program = kept_programs.Program(_jitted(), "step", "demo", log=lines.append).prefetch()
  _equal(_run(program), _reference())
  assert program.origin == "compiled, not kept"
  assert any("not readable" in line for line in lines) and any(
      "not kept" in line for line in lines)


def test_an_entry_that_fails_in_its_first_run_is_deleted_with_one_line(folder, monkeypatch):
  _run(kept_programs.Program(_jitted(), "step", "demo"), calls=1)
  (path,) = _entries(folder, "step")

  def broken(*args):
    raise jax.errors.JaxRuntimeError("NOT_FOUND: Function transpose_copy_fusion.21 not found")
  monkeypatch.setattr(kept_programs, "unpack", lambda key, data, device=None: broken)
  program = kept_programs.Program(_jitted(), "step", "demo")
  with pytest.raises(SljaxError, match="failed when it ran .*NOT_FOUND.* it is deleted"):
    program(*_args())
  assert not path.exists()


def test_a_prefetch_under_other_settings_is_not_served(folder):
  """Keys are computed on the calling thread: a program prefetched under the process's
  settings is not used by a call under a thread-local other one."""
  _run(kept_programs.Program(_jitted(), "step", "demo"), calls=1)
  program = kept_programs.Program(_jitted(), "step", "demo").prefetch()
  jax.clear_caches()
  with jax.default_matmul_precision("bfloat16"):
    program(*_args())
  assert program.origin == "compiled" and len(_entries(folder, "step")) == 2


def _train(workdir: Path, env: dict, *more: str) -> subprocess.CompletedProcess:
  flags = ["--model", "unet-sl", "--unet-depth", "2", "--unet-width", "4", "--size", "32",
           "--synth-n", "12", "--synth-size", "32", "--batch-size", "2", "--steps", "3",
           "--val-every-steps", "3", "--max-val", "2", "--workdir", str(workdir), *more]
  return subprocess.run([sys.executable, str(ROOT / "train.py"), *flags], env=env, cwd=ROOT,
                        capture_output=True, text=True, timeout=600)


def _rows(workdir: Path) -> list[dict]:
  return [{k: v for k, v in json.loads(line).items()
           if k not in ("seconds", "samples_per_s", "time")}
          for line in (workdir / "metrics.jsonl").read_text().splitlines()]


def test_train_py_twice_loads_the_steps_and_trains_identically(tmp_path):
  env = dict(os.environ, SLJAX_PROGRAM_CACHE="on", SLJAX_COMPILE_CACHE=str(tmp_path / "xla"),
             SLJAX_CACHE_DIR=str(tmp_path / "cache"))
  first = _train(tmp_path / "a", env)
  assert first.returncode == 0, first.stderr[-2000:]
  names = {p.name.split("-")[2] for p in (tmp_path / "xla").rglob("sljax-program-*-cache")}
  assert {"init", "train", "eval"} <= names, names
  # The first run compiled its step ahead, beside the initialisation (Program.ahead), for the
  # shapes the real call had (one program kept, not a second for other shapes): the same rows
  # as a run that keeps no programs, compiling the step at its first call.
  assert len(list((tmp_path / "xla").rglob("sljax-program-train-step-*-cache"))) == 1
  plain = _train(tmp_path / "p", dict(env, SLJAX_PROGRAM_CACHE="off",
                                      SLJAX_COMPILE_CACHE=str(tmp_path / "plain")))
  assert plain.returncode == 0, plain.stderr[-2000:]
  assert _rows(tmp_path / "p") == _rows(tmp_path / "a")
  second = _train(tmp_path / "b", env)
  assert second.returncode == 0, second.stderr[-2000:]
  assert "first step (loaded the compiled step)" in second.stderr
  assert "first step (loaded" not in first.stderr
  assert _rows(tmp_path / "a") == _rows(tmp_path / "b") and len(_rows(tmp_path / "a")) == 3
  # Stopped after a step and resumed from its checkpoint on loaded programs: the same rows.
  for more in (["--stop-after", "1", "--save-every", "1"], ["--resume"]):
    part = _train(tmp_path / "d", env, *more)
    assert part.returncode == 0, part.stderr[-2000:]
    assert "first step (loaded the compiled step)" in part.stderr
  assert _rows(tmp_path / "d") == _rows(tmp_path / "a")
  # A damaged training step: one line, compiled again (jax's cache has it: compiled afresh
  # and kept, module docstring), the same numbers; the run after it loads it and runs.
  (step,) = (tmp_path / "xla").rglob("sljax-program-train-step-*-cache")
  step.write_bytes(step.read_bytes()[:1000])
  third = _train(tmp_path / "c", env)
  assert third.returncode == 0, third.stderr[-2000:]
  assert third.stderr.count("unusable") == 1 and "compiling it again" in third.stderr
  assert _rows(tmp_path / "c") == _rows(tmp_path / "a")
  fourth = _train(tmp_path / "e", env)
  assert fourth.returncode == 0, fourth.stderr[-2000:]
  assert "first step (loaded the compiled step)" in fourth.stderr
  assert _rows(tmp_path / "e") == _rows(tmp_path / "a")


def test_only_a_fresh_compile_is_kept(folder, monkeypatch):
  """XLA:CPU re-serialises an executable it did not compile in this call (jax's persistent
  cache, or an earlier compile in the process) without some kernels: such an entry loaded, then
  failed when run. A program a cache gave is compiled afresh under FRESH_OPTION and kept."""
  jitted = _jitted()
  lowered = jitted.lower(*_args())
  assert kept_programs.fresh_compile(lowered)[1]
  assert not kept_programs.fresh_compile(lowered)[1]  # jax's compile of this process
  assert kept_programs.fresh_compile(lowered, kept_programs.FRESH_OPTION)[1]
  jax.clear_caches()
  kept_programs.fresh_compile(jitted.lower(*_args()))  # as jax's cache would have it
  seen = []
  real = kept_programs.fresh_compile
  monkeypatch.setattr(kept_programs, "fresh_compile",
                      lambda lowered, options=None: seen.append(options) or real(lowered, options))
  program = kept_programs.Program(jitted, "step", "demo")
  _equal(_run(program), _reference())
  assert seen == [None, kept_programs.FRESH_OPTION]  # the cached one, then afresh
  assert program.origin == "compiled" and len(_entries(folder)) == 1
  again = kept_programs.Program(_jitted(), "step", "demo")
  _equal(_run(again), _reference())
  assert again.origin == "loaded"
  # If even that came from a cache, nothing is kept.
  for path in _entries(folder):
    path.unlink()
  monkeypatch.setattr(kept_programs, "fresh_compile", lambda lowered, options=None: (
      real(lowered, options)[0], False))
  third = kept_programs.Program(_jitted(), "step", "demo")
  _equal(_run(third), _reference())
  assert third.origin == "compiled, not kept" and not _entries(folder)


_ONE_COPY = """
import sys
from pathlib import Path
import jax, jax.numpy as jnp
where = Path(sys.argv[1])
jax.config.update("jax_compilation_cache_dir", str(where))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
from sljax.runtime import kept_programs
kept_programs.enable(where)
def kept(x):
  return jnp.tanh(x) @ x
def plain(x):
  return jnp.sin(x) @ x
x = jnp.ones((3, 3))
names = lambda: sorted(p.name.split("-")[0] for p in where.glob("*-cache"))
program = kept_programs.Program(jax.jit(kept), "kept", "demo")
program(x)
print(program.origin, names())
jax.jit(plain)(x)  # not kept: jax's cache as before
print(names())
"""


def test_a_kept_program_is_not_also_written_to_jaxs_cache(tmp_path):
  """One copy per program: jax's entry would never serve a kept program (one from jax's cache
  is compiled afresh) and would double its bytes in the bounded folder."""
  env = dict(os.environ, **{kept_programs.ENV: "on"})
  env.pop("JAX_COMPILATION_CACHE_DIR", None)
  out = subprocess.run([sys.executable, "-c", _ONE_COPY, str(tmp_path / "xla")], env=env,
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
  assert out.returncode == 0, out.stderr
  kept, plain = out.stdout.strip().splitlines()
  assert kept.startswith("compiled [") and "'sljax'" in kept  # sljax's entry
  assert "jit_kept" not in kept  # and not jax's
  assert "jit_plain" in plain  # a program that is not kept still goes to jax's cache


def test_threads_calling_a_new_program_at_once_compile_it_once(folder, monkeypatch):
  """The data loader's threads call the renderer's programs side by side: one of them
  compiles (or loads) each signature's program, the others wait for it."""
  import threading
  compiles = []
  real = kept_programs.compile_and_keep
  monkeypatch.setattr(kept_programs, "compile_and_keep", lambda *a: compiles.append(1) or real(*a))
  program = kept_programs.Program(jax.jit(lambda x: jnp.tanh(x) @ x.T), "side-by-side", "demo")
  x = jnp.asarray(np.random.default_rng(0).normal(size=(64, 64)), jnp.float32)
  start, results = threading.Barrier(4), []

  def call():
    start.wait()
    results.append(np.asarray(program(x)))

  threads = [threading.Thread(target=call) for _ in range(4)]
  for t in threads:
    t.start()
  for t in threads:
    t.join()
  assert len(compiles) == 1 and len(results) == 4
  for r in results:
    np.testing.assert_array_equal(r, np.asarray(jnp.tanh(x) @ x.T))


def test_prefetch_loads_the_remembered_signatures_before_the_first_call(folder):
  first = kept_programs.Program(_jitted(), "step", "demo")
  _run(first, rows=4)
  _run(first, rows=6)
  assert kept_programs.remembered("step", "demo") == [program_keys.signature(_args(rows=6)),
                                                    program_keys.signature(_args(rows=4))]
  second = kept_programs.Program(_jitted(), "step", "demo").prefetch()
  assert len(second._loading) == 2  # pylint: disable=protected-access
  second.jitted = None  # neither lowered nor compiled
  _equal(_run(second, rows=4), _reference(rows=4))
  assert second.origin == "loaded"
  # An index that names programs no longer kept, or is garbage, only misses the prefetch.
  for path in _entries(folder):
    path.unlink()
  jax.clear_caches()
  third = kept_programs.Program(_jitted(), "step", "demo").prefetch()
  _equal(_run(third, rows=4), _reference(rows=4))
  assert third.origin == "compiled"
  kept_programs.index_path(folder, "step", "demo").write_text("{garbage")
  assert kept_programs.remembered("step", "demo") == []
  _equal(_run(kept_programs.Program(_jitted(), "step", "demo").prefetch()), _reference())


def _shapes(args):
  return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, weak_type=x.weak_type),
                      args)


def test_a_program_compiled_ahead_from_shapes_serves_the_first_call(folder, monkeypatch):
  """`ahead` compiles (and keeps) the program for arguments known by their shapes on a
  background thread; the first real call takes it, with the plain function's numbers; a call
  of another signature compiles its own; a failure ahead is raised by the real call."""
  program = kept_programs.Program(_jitted(), "step", "ahead")
  program.ahead(*_shapes(_args()))
  assert program.prefetching
  compiled_now = []
  real = kept_programs.compile_and_keep
  monkeypatch.setattr(kept_programs, "compile_and_keep",
                      lambda *a, **k: compiled_now.append(a[3]) or real(*a, **k))
  _equal(_run(program), _reference())
  assert program.origin == "compiled" and not program.prefetching
  assert all(isinstance(x, jax.ShapeDtypeStruct) for x in jax.tree.leaves(compiled_now))
  assert len(_entries(folder, "step")) == 1  # kept: a later process loads it
  _equal(_run(program, rows=6), _reference(rows=6))  # another signature: its own program
  assert len(_entries(folder, "step")) == 2
  # A program whose trace fails ahead: the real call fails the same way, where it is made.
  def broken(state, x):
    raise ValueError("traced and failed")
  failing = kept_programs.Program(jax.jit(broken), "broken", "ahead")
  failing.ahead(*_shapes(_args()))
  with pytest.raises(ValueError, match="traced and failed"):
    failing(*_args())
  # Off the cache nothing starts (jit's own cache would not see it).
  kept_programs.enable(None)
  off = kept_programs.Program(_jitted(), "step", "off")
  assert not off.ahead(*_shapes(_args())).prefetching


def test_a_launch_loads_what_the_last_same_launch_ran(folder, monkeypatch):
  """At launch, before anything is imported or parsed, the programs the last launch with the
  same arguments ran start loading; a program takes that load only when its own key is the
  same; other arguments, another program or a damaged record load nothing early."""
  monkeypatch.setitem(kept_programs._state, "launch", None)  # pylint: disable=protected-access
  monkeypatch.setattr(kept_programs, "_early", {})
  early = lambda: kept_programs._early  # pylint: disable=protected-access
  kept_programs.load_early(["--a"], ("step",))
  assert not early()  # nothing remembered yet
  _run(kept_programs.Program(_jitted(), "step", "demo"))
  record = json.loads((folder / kept_programs.LAUNCHES).read_text())
  launch = kept_programs.launch_digest(["--a"])
  assert list(record) == [launch] and record[launch]["step"].startswith("sljax-program-step-")
  # The same launch again: loading before the program exists, which then takes that load.
  kept_programs.load_early(["--a"], ("step",))
  assert early()["step"][0] == record[launch]["step"]
  second = kept_programs.Program(_jitted(), "step", "demo").prefetch()
  assert not early()
  second.jitted = None  # neither lowered nor compiled
  _equal(_run(second), _reference())
  assert second.origin == "loaded"
  # Other arguments: nothing early. A program whose key differs leaves the early load alone.
  kept_programs.load_early(["--b"], ("step",))
  assert not early()
  kept_programs.load_early(["--a"], ("step",))
  other = kept_programs.Program(_jitted(), "step", "another description").prefetch()
  assert "step" in early()
  _equal(_run(other), _reference())
  assert other.origin == "compiled"
  early().clear()
  (folder / kept_programs.LAUNCHES).write_text("{garbage")
  kept_programs.load_early(["--a"], ("step",))
  assert not early()


def test_a_damaged_prefetched_entry_is_compiled_again_with_one_line(folder):
  _run(kept_programs.Program(_jitted(), "step", "demo"), calls=1)
  (path,) = _entries(folder, "step")
  path.write_bytes(path.read_bytes()[:-10])
  lines = []
  jax.clear_caches()
  program = kept_programs.Program(_jitted(), "step", "demo", log=lines.append).prefetch()
  _equal(_run(program), _reference())
  assert program.origin == "compiled" and len(lines) == 1 and "unusable" in lines[0]


def test_both_training_command_lines_start_the_early_load(monkeypatch):
  """`sljax train ARGS` and `python train.py ARGS` start the same early load, keyed by ARGS,
  before the training modules are imported."""
  from sljax import cli
  from sljax.runtime import compile_cache
  seen = []
  monkeypatch.setattr(compile_cache, "load_last_programs", seen.append)
  with pytest.raises(SystemExit):
    cli.main(["train", "--strategy", "epr", "--help"])
  assert seen == [["--strategy", "epr", "--help"]]
  text = (ROOT / "train.py").read_text()
  assert text.index("load_last_programs(sys.argv[1:])") < text.index("from sljax.train.cli")


def test_variable_shapes_are_the_initialisers_tree():
  """`variable_shapes` (what the step is compiled ahead for, and --init-from is checked
  against) is `init_variables`' tree, shapes and dtypes, without running it."""
  from sljax.nets.model_config import ModelConfig, init_variables, variable_shapes
  model = ModelConfig.of("unet-disp", depth=2, base_width=4).build()
  real = init_variables(model, 0, 32, 32, 3)
  shapes = variable_shapes(model, 32, 32, 3)
  assert jax.tree.structure(shapes) == jax.tree.structure(real)
  assert all(jax.tree.leaves(jax.tree.map(lambda a, b: (a.shape, a.dtype) == (b.shape, b.dtype),
                                          shapes, real)))
