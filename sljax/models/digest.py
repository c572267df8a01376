"""Checkpoints know their bytes: a SHA-256 of every file of a step folder, written with it and
checked before anything of it is read.

When it is written: inside the temporary folder, just before orbax renames it to its step
(`DigestedRename.finalize`), so that a checkpoint is either complete with its digest or not a
checkpoint at all (a save cut short leaves <step>.orbax-checkpoint-tmp, which nobody reads).
Writing it after the rename would leave a window in which a finished checkpoint has no digest,
and a checkpoint without one could not be told from one written before digests. By then every
item (state, meta, metrics) is finalised by orbax; the only files still changing are the two
that orbax's own rename step writes at the step's top level (COMMIT_FILES: the step metadata's
commit time and commit_success.txt), orbax's bookkeeping, not read for the weights, so they are
left out of the digest. A checkpoint written before digests has no DIGEST_FILE and still
restores, unchecked (sljax.models.checkpoint says so in one line).
"""

import hashlib
import json
import os
from pathlib import Path

from orbax.checkpoint._src.path import atomicity

DIGEST_FILE = "sljax_digest.json"
FORMAT = "sljax-checkpoint-digest-1"
# Written by orbax's rename step after the digest (see the module docstring).
COMMIT_FILES_METADATA = "_CHECKPOINT_METADATA"  # checked as JSON (checkpoint.check_step_metadata)
COMMIT_FILES = frozenset({COMMIT_FILES_METADATA, "commit_success.txt"})
_CHUNK = 1 << 20


def sha256(path: Path) -> str:
  """The SHA-256 of a file's bytes, read in chunks (a checkpoint file can be GBs)."""
  h = hashlib.sha256()
  with open(path, "rb") as f:
    for chunk in iter(lambda: f.read(_CHUNK), b""):
      h.update(chunk)
  return h.hexdigest()


def _digested(folder: Path) -> list[Path]:
  """The files of a step folder the digest covers, sorted (all but the digest and COMMIT_FILES)."""
  return sorted(p for p in folder.rglob("*") if not p.is_dir()
                and p.relative_to(folder).as_posix() not in COMMIT_FILES | {DIGEST_FILE})


def file_digests(folder: Path) -> dict[str, str]:
  """{relative path: SHA-256} of every file the digest covers."""
  return {p.relative_to(folder).as_posix(): sha256(p) for p in _digested(folder)}


def write_digest(folder: Path) -> None:
  """Writes DIGEST_FILE into a (temporary) step folder, flushed to the disk before the rename."""
  text = json.dumps({"format": FORMAT, "files": file_digests(folder)}, indent=1)
  with open(folder / DIGEST_FILE, "w") as f:
    f.write(text)
    f.flush()
    os.fsync(f.fileno())


def read_digest(folder: Path) -> dict[str, str] | None:
  """The {file: SHA-256} a step folder was written with; None when it has no DIGEST_FILE (a
  checkpoint from before digests); ValueError when the digest itself is damaged."""
  path = folder / DIGEST_FILE
  if not path.exists():
    return None
  try:
    saved = json.loads(path.read_bytes())
  except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
    raise ValueError(f"{DIGEST_FILE}: unreadable ({type(e).__name__})") from None
  files = saved.get("files") if isinstance(saved, dict) else None
  if (not isinstance(saved, dict) or saved.get("format") != FORMAT or not isinstance(files, dict)
      or not all(isinstance(v, str) for v in files.values())):
    raise ValueError(f"{DIGEST_FILE}: not a digest written by sljax")
  return files


def first_difference(folder: Path, expected: dict[str, str], extra: bool = True) -> str | None:
  """'FILE: problem' for the first file whose bytes differ from those written (missing, a
  folder where the file was, changed, or with `extra` one not written by the save), else None."""
  for name, want in sorted(expected.items()):
    path = folder / name
    if path.is_dir():
      return f"{name}: a folder where the checkpoint wrote a file"
    if not path.is_file():
      return f"{name}: missing"
    if sha256(path) != want:
      size = path.stat().st_size
      return f"{name}: its bytes differ from those written" + (" (it is empty)" if not size
                                                                else "")
  added = [p.relative_to(folder).as_posix() for p in _digested(folder)
           if p.relative_to(folder).as_posix() not in expected] if extra else []
  if added:
    return f"{added[0]}: not written by the save"
  return None


class DigestedRename(atomicity.AtomicRenameTemporaryPath):
  """Orbax's atomic rename of a step's temporary folder, with the digest written just before."""

  async def finalize(self):
    # Only the step folder (named by its number); item folders (state, meta) are inside it.
    if self.get_final().name.isdigit():
      write_digest(Path(self.get()))
    await super().finalize()
