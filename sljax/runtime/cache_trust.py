"""Whether a cache folder on disk may be loaded from: compiled programs are code that runs.

jax's persistent compilation cache (sljax.runtime.compile_cache) holds XLA executables, native
code that a later run loads and runs, and sljax's kept programs (sljax.runtime.kept_programs)
add pickled trees, which run code when they are unpickled. So whoever can write a cache folder
can run code in every run that loads from it. A folder on a shared file system
(`SLJAX_COMPILE_CACHE=/shared/sljax-xla`, docs/cluster.md) is loaded only when everyone who can
write it is someone the user trusts already.

The rule (OpenSSH's check of ~/.ssh, with the user's groups trusted as well). A path is trusted
when
- no one can write it through the "others" bits (no `o+w`), and
- its owner is the user or root, or its group is one of the user's groups: a file or folder
  of another owner is trusted because it carries a group the user belongs to, since only a
  member of a group can give a file that group (`chgrp`, or creating it in a setgid folder of
  that group, which needs the right to write there); and
- when it is group-writable, its group is one of the user's groups (that group's members are
  the lab the user shares the folder with).
The owner counts among the writers even without a write bit: an owner can always `chmod`.
A folder is checked with each of its parents up to the cache's root (OpenSSH's secure_path:
whoever can rename a parent can put another folder in its place), and every entry in it, each
entry again before it is read. Above the root the user chose the place (a sticky /tmp, say).
Paths that do not exist yet are skipped: there is nothing to load from them, and the run that
creates them creates them as the user. One caveat the rule cannot see: where every user of a
machine shares one group (`users`), that group is everyone, so it must not be a cache's group.
"""

import os
import stat
import sys
import threading
from collections.abc import Iterable
from pathlib import Path

_warned = threading.Event()  # the line is printed once per process (loader threads share it)
_warn_lock = threading.Lock()


def untrusted_reason(uid: int, gid: int, mode: int, me: int,
                     groups: Iterable[int]) -> tuple[str, str] | None:
  """(why a path with this owner, group and mode is not trusted, how to allow it), or None
  when it is trusted by the user `me` in `groups` (the rule of the module docstring)."""
  groups = set(groups)
  if mode & stat.S_IWOTH:
    return "is writable by others", "chmod o-w {path}"
  if uid not in (me, 0) and gid not in groups:
    return (f"belongs to user {uid} and to group {gid}, not one of yours",
            "have its owner `chgrp` it to a group you share (docs/cluster.md)")
  if mode & stat.S_IWGRP and gid not in groups:
    return f"is writable by group {gid}, which you are not in", "chmod g-w {path}"
  return None


def _me() -> tuple[int, set[int]]:
  """This process's effective user and its groups (supplementary and effective)."""
  return os.geteuid(), set(os.getgroups()) | {os.getegid()}


def untrusted_path(path: Path) -> tuple[Path, str, str] | None:
  """(path, why, how to allow) when this one path is not trusted; None when it is or is absent."""
  try:
    st = os.stat(path)
  except FileNotFoundError:
    return None
  except OSError as e:  # a path that cannot even be looked at cannot be vouched for
    return path, f"cannot be checked ({type(e).__name__})", "make it readable"
  me, groups = _me()
  found = untrusted_reason(st.st_uid, st.st_gid, st.st_mode, me, groups)
  return None if found is None else (path, found[0], found[1].format(path=path))


def chain(path: Path, root: Path) -> list[Path]:
  """`path` and its parents up to `root` (inclusive; only `path` when root is not above it)."""
  path, root = Path(os.path.abspath(path)), Path(os.path.abspath(root))
  if path != root and root not in path.parents:
    return [path]
  out = [path]
  while out[-1] != root:
    out.append(out[-1].parent)
  return out


def untrusted_chain(path: Path, root: Path) -> tuple[Path, str, str] | None:
  """The first path from `path` up to `root` that is not trusted, or None."""
  for p in chain(path, root):
    found = untrusted_path(p)
    if found is not None:
      return found
  return None


def untrusted_folder(folder: Path, root: Path) -> tuple[Path, str, str] | None:
  """The first of a cache folder, its parents up to `root` and its entries that is not
  trusted, or None: all of it may be loaded."""
  found = untrusted_chain(folder, root)
  if found is not None:
    return found
  try:
    entries = sorted(os.scandir(folder), key=lambda e: e.name)
  except FileNotFoundError:
    return None
  except OSError as e:
    return folder, f"cannot be listed ({type(e).__name__})", "make it readable"
  for entry in entries:
    found = untrusted_path(Path(entry.path))
    if found is not None:
      return found
  return None


def message(folder: Path, found: tuple[Path, str, str]) -> str:
  """The one line that says which cache folder is not trusted and how to allow it."""
  path, why, fix = found
  return (f"sljax: compile cache {folder} not trusted: {path} {why}, so whoever can write it "
          f"could run code in your runs; compiling without the cache. To allow it: {fix}; or "
          "set SLJAX_COMPILE_CACHE to a folder of your own, or to off")


def warn_once(folder: Path, found: tuple[Path, str, str]) -> None:
  """Prints `message` on stderr, the first time in this process only."""
  with _warn_lock:
    if _warned.is_set():
      return
    _warned.set()
  print(message(folder, found), file=sys.stderr, flush=True)
