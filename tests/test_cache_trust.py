"""Caches never run a stranger's code (sljax.runtime.cache_trust): the compile cache and the kept
programs are loaded only from folders, parents and entries that no one but the user, root and
the user's groups can write; otherwise the run compiles, writes nothing there and says so once.

The suite runs as root in CI, and root owns every file it makes, so ownership is tested through
the pure rule (`untrusted_reason`) and through monkeypatched stat results; the mode bits are
also tested on real folders."""

import os
import stat
import subprocess
import sys
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sljax.runtime import cache_trust, compile_cache, kept_programs

ME, MINE, LAB, OTHER, STRANGER = 1000, 1000, 2000, 1001, 3000
GROUPS = {MINE, LAB}


@pytest.mark.parametrize("uid,gid,mode,trusted", [
    (ME, MINE, 0o700, True),          # the user's own private folder
    (ME, MINE, 0o755, True),
    (ME, LAB, 0o2770, True),          # docs/cluster.md's group folder, as its creator sees it
    (OTHER, LAB, 0o2770, True),       # ... and as another member sees it
    (OTHER, LAB, 0o664, True),        # a member's entry in it
    (0, 0, 0o755, True),              # root's (OpenSSH trusts root too)
    (0, LAB, 0o775, True),            # root's, writable by the lab
    (ME, MINE, 0o777, False),         # writable by others, even the user's own
    (ME, MINE, 0o757, False),
    (ME, MINE, 0o1777, False),        # sticky does not stop others writing new entries
    (0, 0, 0o777, False),
    (OTHER, STRANGER, 0o755, False),  # a stranger's folder: only they write it, and they are
    (OTHER, STRANGER, 0o700, False),  # no one the user trusts (they can always chmod it)
    (ME, STRANGER, 0o775, False),     # writable by a group the user is not in
    (0, STRANGER, 0o770, False),
])
def test_the_rule(uid, gid, mode, trusted):
  found = cache_trust.untrusted_reason(uid, gid, mode | stat.S_IFDIR, ME, GROUPS)
  assert (found is None) == trusted
  if not trusted:
    why, fix = found
    assert why and fix


def test_the_fix_named_fits_the_reason():
  assert cache_trust.untrusted_reason(ME, MINE, 0o757, ME, GROUPS)[1] == "chmod o-w {path}"
  assert cache_trust.untrusted_reason(ME, STRANGER, 0o775, ME, GROUPS)[1] == "chmod g-w {path}"
  assert "chgrp" in cache_trust.untrusted_reason(OTHER, STRANGER, 0o755, ME, GROUPS)[1]


def test_chain_runs_up_to_the_root_only(tmp_path):
  deep = tmp_path / "a" / "b" / "c"
  assert cache_trust.chain(deep, tmp_path / "a") == [deep, deep.parent, tmp_path / "a"]
  assert cache_trust.chain(deep, deep) == [deep]
  assert cache_trust.chain(deep, tmp_path / "elsewhere") == [deep]  # root not above it


def _tree(tmp_path: Path) -> tuple[Path, Path]:
  """A cache root with a folder of entries, all the user's own, 0o700 / 0o600."""
  root = tmp_path / "root"
  folder = root / "cpu-jax"
  folder.mkdir(parents=True)
  (folder / "entry-cache").write_bytes(b"x")
  for p, mode in ((root, 0o700), (folder, 0o700), (folder / "entry-cache", 0o600)):
    os.chmod(p, mode)
  return root, folder


def test_real_mode_bits(tmp_path):
  root, folder = _tree(tmp_path)
  assert cache_trust.untrusted_folder(folder, root) is None  # the user's own: trusted
  os.chmod(folder, 0o770)
  assert cache_trust.untrusted_folder(folder, root) is None  # group-writable, the user's group
  for mode in (0o777, 0o757):
    os.chmod(folder, mode)
    path, why, fix = cache_trust.untrusted_folder(folder, root)
    assert path == folder and why == "is writable by others" and fix == f"chmod o-w {folder}"
  os.chmod(folder, 0o700)
  os.chmod(folder / "entry-cache", 0o606)  # an entry others can write, in a good folder
  assert cache_trust.untrusted_folder(folder, root)[0] == folder / "entry-cache"
  os.chmod(folder / "entry-cache", 0o600)
  os.chmod(root, 0o757)  # a parent others can write: they could swap the folder
  assert cache_trust.untrusted_folder(folder, root)[0] == root
  assert cache_trust.untrusted_chain(folder, folder) is None  # above the root: not checked
  os.chmod(root, 0o700)
  assert cache_trust.untrusted_folder(root / "absent", root) is None  # nothing to load


def _as_owner(monkeypatch, owners: dict[Path, tuple[int, int]]):
  """os.stat as if `owners` (path -> (uid, gid)) held, for a user 1000 in groups 1000 and 2000."""
  real = os.stat

  def fake(path, *a, **k):
    st = real(path, *a, **k)
    if Path(path) not in owners:
      return os.stat_result((st.st_mode, st.st_ino, st.st_dev, st.st_nlink, ME, MINE,
                             st.st_size, st.st_atime, st.st_mtime, st.st_ctime))
    uid, gid = owners[Path(path)]
    return os.stat_result((st.st_mode, st.st_ino, st.st_dev, st.st_nlink, uid, gid,
                           st.st_size, st.st_atime, st.st_mtime, st.st_ctime))
  monkeypatch.setattr(cache_trust.os, "stat", fake)
  monkeypatch.setattr(cache_trust, "_me", lambda: (ME, set(GROUPS)))


def test_a_folder_of_another_owner(tmp_path, monkeypatch):
  root, folder = _tree(tmp_path)
  _as_owner(monkeypatch, {folder: (OTHER, STRANGER)})
  path, why, _ = cache_trust.untrusted_folder(folder, root)
  assert path == folder and f"user {OTHER}" in why
  _as_owner(monkeypatch, {folder: (OTHER, LAB)})  # a lab member's: trusted
  assert cache_trust.untrusted_folder(folder, root) is None
  _as_owner(monkeypatch, {folder / "entry-cache": (OTHER, STRANGER)})  # a stranger's entry
  assert cache_trust.untrusted_folder(folder, root)[0] == folder / "entry-cache"
  _as_owner(monkeypatch, {root: (OTHER, STRANGER)})  # a stranger's parent
  assert cache_trust.untrusted_folder(folder, root)[0] == root


@pytest.fixture
def fresh_warning(monkeypatch):
  """The once-per-process line, as if this process had not printed it yet."""
  monkeypatch.setattr(cache_trust, "_warned", type(cache_trust._warned)())


def _fake_jax_config(monkeypatch, cache_dir: str | None) -> list[tuple]:
  """compile_cache's view of jax's settings, with the cache folder `cache_dir`, recording the
  updates it makes (the session's own settings are left as they are); returns the record."""
  updates = []

  class Config:
    jax_compilation_cache_dir = cache_dir

    @staticmethod
    def update(*a):
      updates.append(a)
  monkeypatch.setattr(compile_cache, "jax", types.SimpleNamespace(
      config=Config, __version__=jax.__version__))
  return updates


def test_the_line_appears_once_per_process(tmp_path, fresh_warning, capsys):
  root, folder = _tree(tmp_path)
  os.chmod(folder, 0o777)
  assert not compile_cache.trusted(folder, root)
  assert not compile_cache.trusted(folder, root)
  err = capsys.readouterr().err.splitlines()
  assert err == [f"sljax: compile cache {folder} not trusted: {folder} is writable by others, "
                 "so whoever can write it could run code in your runs; compiling without the "
                 f"cache. To allow it: chmod o-w {folder}; or set SLJAX_COMPILE_CACHE to a "
                 "folder of your own, or to off"]


def test_an_untrusted_compile_cache_is_neither_used_nor_written(tmp_path, monkeypatch,
                                                                fresh_warning, capsys):
  root = tmp_path / "shared"
  root.mkdir()
  os.chmod(root, 0o777)
  monkeypatch.setenv("SLJAX_COMPILE_CACHE", str(root))
  monkeypatch.setenv(kept_programs.ENV, "on")
  updates = _fake_jax_config(monkeypatch, None)  # as in a fresh process
  try:
    assert compile_cache.enable_compile_cache(programs=True) is None
    assert kept_programs.folder() is None and updates == [] and not list(root.iterdir())
  finally:
    kept_programs.enable(None)
  assert "not trusted" in capsys.readouterr().err


def test_an_untrusted_folder_of_the_users_own_setting_is_turned_off(tmp_path, monkeypatch,
                                                                    fresh_warning):
  mine = tmp_path / "jax-cache"
  mine.mkdir()
  os.chmod(mine, 0o757)
  updates = _fake_jax_config(monkeypatch, str(mine))
  assert compile_cache.enable_compile_cache(programs=True) is None
  assert updates == [("jax_compilation_cache_dir", None)] and kept_programs.folder() is None


def test_a_trusted_compile_cache_is_used(tmp_path, monkeypatch, fresh_warning, capsys):
  root = tmp_path / "lab"
  root.mkdir()
  os.chmod(root, 0o2770)  # docs/cluster.md's group folder
  monkeypatch.setenv("SLJAX_COMPILE_CACHE", str(root))
  monkeypatch.setenv(kept_programs.ENV, "on")
  updates = _fake_jax_config(monkeypatch, None)
  try:
    folder = compile_cache.enable_compile_cache(programs=True)
    assert folder == compile_cache.compile_cache_dir() and kept_programs.folder() == folder
    assert ("jax_compilation_cache_dir", str(folder)) in updates
  finally:
    kept_programs.enable(None)
  assert capsys.readouterr().err == ""


def _step(x):
  return jnp.tanh(x @ x.T).sum()


def test_kept_programs_load_only_trusted_entries(tmp_path, monkeypatch, fresh_warning, capsys):
  """A 0o700 folder of the user's own loads as before; an entry made writable by others is
  never unpickled: the program compiles, keeps nothing, and one line says so."""
  monkeypatch.setenv(kept_programs.ENV, "on")
  jax.clear_caches()
  root = tmp_path / "xla"
  root.mkdir(mode=0o700)
  x = jnp.asarray(np.arange(6.0, dtype=np.float32).reshape(2, 3))
  try:
    assert kept_programs.enable(root) == root
    first = kept_programs.Program(jax.jit(_step), "step", "trust")
    want = first(x)
    assert first.origin == "compiled"
    (entry,) = root.glob(f"{kept_programs.PREFIX}*-cache")
    jax.clear_caches()
    again = kept_programs.Program(jax.jit(_step), "step", "trust")
    assert again(x) == want and again.origin == "loaded"

    os.chmod(entry, 0o666)
    unpickled = []
    monkeypatch.setattr(kept_programs.pickle, "loads", lambda *a: unpickled.append(a))
    jax.clear_caches()
    third = kept_programs.Program(jax.jit(_step), "step", "trust")
    assert third(x) == want and third.origin == "compiled, not kept" and unpickled == []
    assert kept_programs.folder() is None  # the rest of the process keeps nothing there
    before = sorted(p.name for p in root.iterdir())
    kept_programs.Program(jax.jit(lambda v: _step(v) + 1), "other", "trust")(x)
    assert sorted(p.name for p in root.iterdir()) == before
  finally:
    kept_programs.enable(None)
  err = capsys.readouterr().err.splitlines()
  assert len(err) == 1 and f"{entry} is writable by others" in err[0]


def test_an_untrusted_kept_programs_folder_is_off(tmp_path, monkeypatch, fresh_warning):
  monkeypatch.setenv(kept_programs.ENV, "on")
  root = tmp_path / "xla"
  folder = root / "cpu"
  folder.mkdir(parents=True)
  os.chmod(root, 0o777)
  try:
    assert kept_programs.enable(folder, root=root) is None and kept_programs.folder() is None
    os.chmod(root, 0o755)
    assert kept_programs.enable(folder, root=root) == folder
  finally:
    kept_programs.enable(None)


CHILD = """
import sys
from sljax.runtime.compile_cache import enable_compile_cache
print(enable_compile_cache(programs=True))
print(enable_compile_cache(programs=True))
"""


def test_one_line_per_process(tmp_path):
  """A command line's process: one line on stderr however often the folder is refused."""
  root = tmp_path / "shared"
  root.mkdir()
  os.chmod(root, 0o757)
  env = dict(os.environ, SLJAX_COMPILE_CACHE=str(root), SLJAX_PROGRAM_CACHE="on")
  env.pop("JAX_COMPILATION_CACHE_DIR", None)
  out = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True,
                       check=True)
  assert out.stdout.split() == ["None", "None"]
  lines = [line for line in out.stderr.splitlines() if "not trusted" in line]
  assert len(lines) == 1 and f"chmod o-w {root}" in lines[0]
  assert not list(root.iterdir())
