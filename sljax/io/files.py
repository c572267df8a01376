"""Output files written whole: to temporary files beside them, renamed into place when complete.

A full disk or an error then leaves the earlier file (with --overwrite) or nothing, never a
truncated file; files written together are renamed only once all are complete (one after the
other, so only a kill between two renames can mix old and new). A kill while writing leaves a
hidden temporary file (.NAME.tmpPID.EXT) beside the output.

Folders of outputs are written the same way by `staged`: into a hidden folder, moved into place
only once the whole command has succeeded, so that a failure or Ctrl-C part way leaves the
output folder as it was (absent stays absent).
"""

import contextlib
import json
import os
import re
import shutil
import socket
import sys
import time
import zipfile
import zlib
from pathlib import Path
from typing import Any, Iterator

import cv2
import numpy as np

from sljax.errors import SljaxError

try:
  import fcntl
except ImportError:  # Windows: folders are not locked (see `exclusive`)
  fcntl = None


_TEMPORARY = re.compile(r"^\..+\.tmp\d+(\.[^.]*)?$")


def is_temporary(path: str | os.PathLike) -> bool:
  """Whether path is a temporary of temp_path (a leftover of a killed write)."""
  return bool(_TEMPORARY.match(Path(path).name))


def temp_path(path: str | os.PathLike) -> Path:
  """A hidden temporary name in path's folder with path's suffix (savefig picks the format by
  it); the same folder, so that the rename is atomic."""
  path = Path(path)
  return path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")


@contextlib.contextmanager
def replacing(*paths: str | os.PathLike) -> Iterator[tuple[Path, ...]]:
  """Yields a temporary path per path; renames each into place once the block has finished
  without error, else removes them (the files at paths stay as they were)."""
  tmps = tuple(temp_path(p) for p in paths)
  try:
    yield tmps
    for tmp, path in zip(tmps, paths):
      os.replace(tmp, path)
  except OSError as e:  # name the user's file, not the temporary one
    real = {str(t): os.fspath(p) for t, p in zip(tmps, paths)}
    e.filename = real.get(str(e.filename), e.filename)
    raise
  finally:
    for tmp in tmps:
      tmp.unlink(missing_ok=True)


STAGE_NAME = ".sljax-staged"


def stage_path(target: str | os.PathLike) -> Path:
  """Where `staged` writes target's contents: a hidden folder inside target when it is a folder
  already (nothing is written beside it, so `--out .` works), else beside it; on target's file
  system either way, so that moving it in is renaming. Both names match `is_temporary`."""
  target = Path(target)
  if target.is_dir():
    return target / f"{STAGE_NAME}.tmp{os.getpid()}"
  return temp_path(target.absolute())  # absolute: "out/" and "." have a name to hide


@contextlib.contextmanager
def staged(target: str | os.PathLike, whole: frozenset[str] = frozenset()) -> Iterator[Path]:
  """Yields an empty hidden folder to write target's contents into; once the block has finished
  without error, moves them into target (all or nothing), else removes them (any exception,
  KeyboardInterrupt included): target stays exactly as it was, absent or with its old files.

  An absent target is the staged folder renamed (none is made when nothing was written); into
  an existing one (the callers' --overwrite, or a folder that holds other things) each staged
  file replaces its namesake and each staged folder is merged into its namesake, except folders
  named in `whole`, which replace theirs (numbered sequences such as sl0/: a shorter new one
  must not keep stale old planes). Only a kill during those renames can mix old and new. Parent
  folders created for the stage are removed again on failure."""
  target = Path(target)
  if target.exists() and not target.is_dir():
    raise SljaxError(f"{target}: exists and is not a folder")
  stage = stage_path(target)
  created = [d for d in stage.parents if not d.exists()]  # deepest first
  shutil.rmtree(stage, ignore_errors=True)  # a leftover of a killed run with this pid
  stage.mkdir(parents=True)
  try:
    yield stage
    if target.is_dir():
      _merge(stage, target, whole)
    elif any(stage.iterdir()):  # nothing written: nothing created
      os.rename(stage, target)
  except (OSError, SljaxError) as e:  # name the user's file, not the staged one
    _unstage(e, stage, target)
    raise
  finally:
    shutil.rmtree(stage, ignore_errors=True)
    for d in created if not target.exists() else ():  # made for the stage alone
      try:
        d.rmdir()  # only when empty
      except OSError:
        break


def _unstage(e: OSError | SljaxError, stage: Path, target: Path) -> None:
  """Rewrites an error's path below stage as the same path below target."""
  if isinstance(e, OSError):
    if isinstance(e.filename, str) and e.filename.startswith(os.fspath(stage)):
      e.filename = os.fspath(target) + e.filename[len(os.fspath(stage)):]
  elif e.args and isinstance(e.args[0], str):
    e.args = (e.args[0].replace(os.fspath(stage), os.fspath(target)),) + e.args[1:]


def _merge(stage: Path, target: Path, whole: frozenset[str]) -> None:
  """Moves stage's entries into the folder target (see `staged`)."""
  for entry in sorted(stage.iterdir()):
    dest = target / entry.name
    real_dirs = entry.is_dir() and dest.is_dir() and not dest.is_symlink()
    if real_dirs and entry.name not in whole:
      _merge(entry, dest, whole)
    elif dest.is_dir() and not dest.is_symlink():  # a folder replaced: set aside, then dropped
      aside = temp_path(dest.with_name(dest.name + "-old"))
      os.rename(dest, aside)
      os.rename(entry, dest)
      shutil.rmtree(aside, ignore_errors=True)
    else:
      os.replace(entry, dest)


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
  """Writes data to path whole (see `replacing`)."""
  with replacing(path) as (tmp,):
    tmp.write_bytes(data)


def write_text(path: str | os.PathLike, text: str) -> None:
  """Writes UTF-8 text to path whole (see `replacing`)."""
  write_bytes(path, text.encode("utf-8"))


LOCK_FILE = ".sljax.lock"


@contextlib.contextmanager
def exclusive(folder: str | os.PathLike, what: str, active: bool = True) -> Iterator[None]:
  """Holds an advisory lock on folder/.sljax.lock for the block, so that a second sljax process
  writing the same folder (a run started again while the first still goes on) stops with one
  line naming the first, instead of mixing their files. The lock is the kernel's (flock): it
  ends with its process, kill -9 included, so a stale one never needs removing. The lock file
  is removed at the end, and so are folders this call created that the block left empty. Not
  locked: active=False (processes other than the main one) and Windows; where the lock cannot
  be taken (no lock support, another user's lock file) one line on stderr says so, and a
  folder that cannot be written is left to the block's own writes to report."""
  folder = Path(folder)
  created = [d for d in (folder, *folder.parents) if not d.exists()]  # deepest first
  fd = None
  if active and fcntl is not None:
    try:
      folder.mkdir(parents=True, exist_ok=True)
    except OSError:
      pass  # the block's first write names the problem
    else:
      fd = _lock(folder / LOCK_FILE, what)
  try:
    yield
  finally:
    if fd is not None:
      _release(folder / LOCK_FILE, fd)
    for d in created if fd is not None else ():
      try:
        d.rmdir()  # only when empty
      except OSError:
        break


def _release(path: Path, fd: int) -> None:
  """Removes the lock file (if it is still this lock's: someone may have deleted it and
  another process locked a new one) and then unlocks."""
  try:
    if _same_file(path, fd):
      path.unlink(missing_ok=True)  # before the unlock: see _lock
  finally:
    os.close(fd)


def _same_file(path: Path, fd: int) -> bool:
  """Whether path names the file open as fd."""
  try:
    st, fst = os.stat(path), os.fstat(fd)
  except FileNotFoundError:
    return False
  return (st.st_dev, st.st_ino) == (fst.st_dev, fst.st_ino)


def _record(fd: int) -> str:
  """The holder's record in an open lock file."""
  return os.read(fd, 500).decode("utf-8", "replace").strip() or "another process"


def holder(folder: str | os.PathLike) -> str | None:
  """Who holds folder through `exclusive` now (its record: what, pid, host, since), or None."""
  path = Path(folder) / LOCK_FILE
  if fcntl is None:
    return None
  try:
    fd = os.open(path, os.O_RDONLY)
  except OSError:
    return None
  try:
    fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)  # taken (and dropped at close) if unheld
    return None
  except BlockingIOError:
    return _record(fd)
  except OSError:
    return None
  finally:
    os.close(fd)


def _lock(path: Path, what: str) -> int | None:
  """An open descriptor of path holding its flock, with `what` written in it; SljaxError naming
  the holder when another process holds it; None (and a line on stderr) where no lock can be
  taken. A holder removes the file before unlocking, so a lock won on a file that is no longer
  at path is dropped and taken again on the new one. A refusal is retried for 0.2 s: a
  `holder` probe holds the lock shared for a moment."""
  for attempt in range(1000):
    try:
      fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except PermissionError:  # another user's lock file: refuse if it is held, else go on
      busy = holder(path.parent)
      if busy:
        raise _in_use(path.parent, busy) from None
      return _unlocked(path, "cannot open the lock file for writing")
    except OSError:
      return None  # a folder that cannot be written: the block's own writes say so
    try:
      try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
      except BlockingIOError:
        if attempt < 4:
          os.close(fd)
          time.sleep(0.05)
          continue
        raise _in_use(path.parent, _record(fd)) from None
      except OSError as e:  # e.g. a network file system without flock
        os.close(fd)
        return _unlocked(path, e.strerror or type(e).__name__)
      if _same_file(path, fd):
        try:
          os.ftruncate(fd, 0)
          os.write(fd, (f"{what} (pid {os.getpid()} on {socket.gethostname()}, since "
                        f"{time.strftime('%Y-%m-%d %H:%M:%S %Z')})").encode("utf-8"))
        except OSError:  # a full disk: the lock holds, a refused process reads no record
          pass
        return fd
    except BaseException:
      os.close(fd)
      raise
    os.close(fd)
  raise SljaxError(f"{path}: could not be locked (it is replaced again and again)")


def _in_use(folder: Path, record: str) -> SljaxError:
  return SljaxError(f"{folder}: in use by {record}; wait for it to end or stop it (its lock "
                    "ends with it), or choose another folder")


def _unlocked(path: Path, why: str) -> None:
  """Says on stderr that the folder goes unlocked."""
  print(f"sljax: {path}: not locked ({why}); a second process writing {path.parent} would not "
        "be refused", file=sys.stderr)
  return None


def encode_png(image: np.ndarray, path: str | os.PathLike) -> bytes:
  """An 8- or 16-bit image (HxW, or HxWx3 in OpenCV's BGR order) as PNG bytes; SljaxError
  naming path when OpenCV cannot encode it."""
  ok, buf = cv2.imencode(".png", image)
  if not ok:
    raise SljaxError(f"{path}: could not encode a PNG image of shape {np.shape(image)}")
  return buf.tobytes()


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
  """Writes image as a PNG whole. Encoded in memory and written by Python, which reports a
  failed write or close: cv2.imwrite ignores a failing close and calls a file cut short by a
  full disk written."""
  write_bytes(path, encode_png(image, path))


def save_figure(fig, path: str | os.PathLike, dpi: int) -> None:
  """Saves a matplotlib figure whole (the format from path's suffix)."""
  with replacing(path) as (tmp,):
    fig.savefig(tmp, dpi=dpi)


def refuse_existing(paths, overwrite: bool) -> None:
  """SljaxError for an output path that is a folder, or that exists while overwrite is off
  (checked before any work, worded as predict and export word it)."""
  for path in map(Path, paths):
    if path.is_dir():
      raise SljaxError(f"{path}: is a folder; name the file to write")
    if path.exists() and not overwrite:
      raise SljaxError(f"{path}: exists (pass --overwrite to replace it)")


def check_output_folder(out: str | os.PathLike, overwrite: bool, label: str = "--out",
                        must_be_empty: bool = False) -> Path:
  """The output folder (not created here); SljaxError "LABEL OUT: ..." for a file in its place
  or, with must_be_empty, a folder holding anything but leftovers of killed writes unless
  overwrite."""
  out = Path(out)
  if out.exists() and not out.is_dir():
    raise SljaxError(f"{label} {out}: exists and is not a folder")
  if must_be_empty and not overwrite and out.is_dir() and any(
      not is_temporary(p) for p in out.iterdir()):
    raise SljaxError(f"{label} {out}: folder is not empty (pass --overwrite to write into it)")
  return out


def require_folder(path: str | os.PathLike, what: str) -> Path:
  """path as a Path; SljaxError "PATH: is a file, not a WHAT" or "PATH: WHAT does not exist"
  (a file named by mistake is not "missing"); "WHAT must be a folder path" for None, "" or a
  value that is no path."""
  if not isinstance(path, (str, os.PathLike)) or not os.fspath(path):
    raise SljaxError(f"{what} must be a folder path, got {path!r}")
  path = Path(path)
  if not path.is_dir():
    raise SljaxError(f"{path}: " + (f"is a file, not a {what}" if path.exists()
                                    else f"{what} does not exist"))
  return path


def _npz_problem(head: bytes) -> str | None:
  """Why a file that starts with head is no .npz archive (None: it looks like one)."""
  if not head:
    return "empty file (0 bytes)"
  if head.startswith(b"\x93NUMPY"):
    return "a single .npy array; save the arrays with numpy.savez"
  if not head.startswith(b"PK"):
    return "not a zip archive"
  return None


def read_npz(path: str | os.PathLike, what: str) -> dict[str, np.ndarray]:
  """The arrays of an .npz file; SljaxError "PATH: not an .npz archive of WHAT (why)" for an
  empty, truncated or foreign file (numpy raises EOFError, BadZipFile or a misleading
  "pickled data" ValueError for these), and one saying so for an array of Python objects."""
  path = Path(path)
  with open(path, "rb") as f:
    problem = _npz_problem(f.read(6))
  key = None
  try:
    if problem is None:
      with np.load(path, allow_pickle=False) as z:
        out = {}
        for key in z.files:
          out[key] = np.asarray(z[key])
        return out
  except ValueError as e:
    if not str(e).startswith("Object arrays"):
      raise _not_npz(path, what, f"ValueError: {_first_line(e)}") from None
    # A readable archive, but an array of Python objects: loading it would run pickled code.
    raise SljaxError(f"{path}: array {key!r} holds Python objects (dtype object), which are not "
                     f"loaded (unpickling can run code); save {what} as numeric arrays") from None
  except (EOFError, zipfile.BadZipFile, zlib.error) as e:
    problem = f"damaged or truncated: {type(e).__name__}: {_first_line(e)}"
  raise _not_npz(path, what, problem)


def _first_line(e: Exception) -> str:
  return (str(e).splitlines() or [""])[0][:200]


def _not_npz(path: Path, what: str, problem: str) -> SljaxError:
  return SljaxError(f"{path}: not an .npz archive of {what} ({problem})")


def read_json_object(path: str | os.PathLike, where: str) -> dict[str, Any]:
  """Reads a JSON file that must hold an object; errors start with `where` (scene, file)."""
  try:
    value = json.loads(Path(path).read_text(encoding="utf-8"))
  except (OSError, ValueError) as e:
    raise SljaxError(f"{where}: not valid JSON ({e})") from None
  if not isinstance(value, dict):
    raise SljaxError(f"{where}: must hold a JSON object")
  return value
