"""Output files written whole: to temporary files beside them, renamed into place when complete.

A full disk or an error then leaves the earlier file (with --overwrite) or nothing, never a
truncated file; files written together are renamed only once all are complete (one after the
other, so only a kill between two renames can mix old and new). A kill while writing leaves a
hidden temporary file (.NAME.tmpPID.EXT) beside the output.
"""

import contextlib
import os
import zipfile
import zlib
from pathlib import Path
from typing import Iterator

import numpy as np

from sljax.errors import SljaxError


def temp_path(path: str | os.PathLike) -> Path:
  """A hidden temporary name in path's folder with path's suffix (cv2.imwrite and savefig pick
  the format by it); the same folder, so that the rename is atomic."""
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


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
  """Writes data to path whole (see `replacing`)."""
  with replacing(path) as (tmp,):
    tmp.write_bytes(data)


def write_text(path: str | os.PathLike, text: str) -> None:
  """Writes UTF-8 text to path whole (see `replacing`)."""
  write_bytes(path, text.encode("utf-8"))


def refuse_existing(paths, overwrite: bool) -> None:
  """SljaxError for an output path that is a folder, or that exists while overwrite is off
  (checked before any work, worded as predict and export word it)."""
  for path in map(Path, paths):
    if path.is_dir():
      raise SljaxError(f"{path}: is a folder; name the file to write")
    if path.exists() and not overwrite:
      raise SljaxError(f"{path}: exists (pass --overwrite to replace it)")


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
  "pickled data" ValueError for these)."""
  path = Path(path)
  with open(path, "rb") as f:
    problem = _npz_problem(f.read(6))
  try:
    if problem is None:
      with np.load(path, allow_pickle=False) as z:
        return {k: np.asarray(z[k]) for k in z.files}
  except (ValueError, EOFError, zipfile.BadZipFile, zlib.error) as e:
    damaged = "" if isinstance(e, ValueError) else "damaged or truncated: "
    problem = f"{damaged}{type(e).__name__}: {(str(e).splitlines() or [''])[0][:200]}"
  raise SljaxError(f"{path}: not an .npz archive of {what} ({problem})")
