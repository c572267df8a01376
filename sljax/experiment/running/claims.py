"""The claim files of the cells of a shared experiment folder, as the workers
(sljax.experiment.running.workers) write and read them: created exclusively, never rewritten,
numbered so that the highest holds the cell.

OUT/claims/CELL/NNNN.json   the cell's claims, in order: each one created exclusively (a hard
                            link of a complete file, which no two processes can both make, on
                            a local disk or NFS), never rewritten. The highest holds the cell:
                            {"kind": "claim", the worker's host, pid, job, token, since, lease}
                            or {"kind": "release", ...} once its holder let go (done, stopped,
                            diverged). A dead holder's claim is superseded by the next number.
OUT/claims/CELL/NNNN.beat   the holder's heartbeat: its mtime is renewed every lease/3 s, and it
                            holds the cell's last training step (for `experiment status`)

Ages are measured between two mtimes on the shared file system (fs_now), so the hosts' clocks
need not agree.
"""

import dataclasses
import errno
import json
import math
import os
import secrets
import time
from pathlib import Path
from typing import Any

from sljax.errors import SljaxError

CLAIMS_DIR = "claims"
CLAIM, RELEASE = "claim", "release"


def claims_dir(out: Path, cell: str) -> Path:
  """The folder of a cell's claims."""
  return out / CLAIMS_DIR / cell


def claim_path(out: Path, cell: str, number: int) -> Path:
  """The claim file number `number` of a cell."""
  return claims_dir(out, cell) / f"{number:04d}.json"


def beat_path(claim: Path) -> Path:
  """The heartbeat file of a claim."""
  return claim.with_suffix(".beat")


def create_exclusive(path: Path, record: dict[str, Any]) -> bool:
  """Creates path holding record, complete, unless it exists; True when this call made it.
  Written to a unique file and hard-linked into place: link() fails when the name exists, on
  NFS too, and the link count tells whether ours won even where a retried link() reports
  EEXIST for its own success (open(2), O_EXCL)."""
  path.parent.mkdir(parents=True, exist_ok=True)
  tmp = path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp")
  tmp.write_text(json.dumps(record) + "\n", encoding="utf-8")
  try:
    try:
      os.link(tmp, path)
    except FileExistsError:
      pass
    return os.stat(tmp).st_nlink == 2
  finally:
    tmp.unlink(missing_ok=True)


def read_claim(path: Path) -> dict[str, Any] | None:
  """A claim file's record (None when absent); a file that is not a JSON object is an error
  naming it."""
  try:
    text = path.read_text(encoding="utf-8")
  except FileNotFoundError:
    return None
  except (OSError, ValueError):  # a folder in its place, non-UTF-8 bytes
    text = ""
  try:
    rec = json.loads(text)
  except ValueError:
    rec = None
  if not isinstance(rec, dict) or rec.get("kind") not in (CLAIM, RELEASE) or not is_identity(rec):
    raise SljaxError(f"{path}: not an sljax claim (delete it if nothing else wrote it)")
  return rec


# The fields of a worker's identity (workers.Identity) that take-over and status compute with,
# and the types they must have: a hand-edited or foreign file would otherwise end in a TypeError.
_IDENTITY = {"token": (str,), "host": (str,), "pid": (int,), "started": (str, type(None)),
             "job": (str, type(None)), "lease": (int, float), "since": (int, float, type(None))}


def is_identity(rec: dict[str, Any]) -> bool:
  """Whether a claim or worker record's identity fields (those present) have their types, with
  a pid and a lease in range and finite times."""
  for key, types in _IDENTITY.items():
    if key in rec and (type(rec[key]) not in types):
      return False
  numbers = [rec.get(k) for k in ("lease", "since") if isinstance(rec.get(k), (int, float))]
  return (all(math.isfinite(v) and abs(v) < 1e12 for v in numbers)
          and 0 < rec.get("pid", 1) < 2**31 and rec.get("lease", 1) > 0)


@dataclasses.dataclass(frozen=True)
class Top:
  """A cell's latest claim: its number, record and heartbeat mtime (number -1: none yet)."""
  number: int
  record: dict[str, Any] | None
  beat: float | None

  @property
  def held(self) -> bool:
    """Whether a worker claims the cell (alive or not)."""
    return self.record is not None and self.record["kind"] == CLAIM


def top(out: Path, cell: str) -> Top:
  """The latest claim of a cell."""
  folder = claims_dir(out, cell)
  numbers = sorted(int(p.stem) for p in folder.glob("[0-9][0-9][0-9][0-9].json")) \
      if folder.is_dir() else []
  number = numbers[-1] if numbers else -1
  # The listing may be stale (NFS caches folders); names are probed upwards until absent.
  while claim_path(out, cell, number + 1).exists():
    number += 1
  if number < 0:
    return Top(-1, None, None)
  path = claim_path(out, cell, number)
  rec = read_claim(path)
  return Top(number, rec, beat_mtime(path))


def beat_mtime(claim: Path) -> float | None:
  """When a claim's holder last showed life: its heartbeat file's mtime, else the claim's."""
  for path in (beat_path(claim), claim):
    try:
      return path.stat().st_mtime
    except FileNotFoundError:
      continue
  return None


def read_beat(claim: Path) -> dict[str, Any]:
  """A claim's heartbeat record ({} when absent or being replaced)."""
  try:
    rec = json.loads(beat_path(claim).read_text(encoding="utf-8"))
  except (OSError, ValueError):
    return {}
  return rec if isinstance(rec, dict) else {}


def fs_now(out: Path) -> float:
  """Now on the file system holding OUT (a probe file's mtime, in the claims' folder that the
  workers made), for readers that are no worker (`experiment status`); the local clock where
  that folder cannot be written."""
  probe = out / CLAIMS_DIR / f".clock-{os.getpid()}"
  try:
    probe.touch()
    try:
      return probe.stat().st_mtime
    finally:
      probe.unlink(missing_ok=True)
  except OSError as e:
    if e.errno not in (errno.EACCES, errno.EROFS, errno.EPERM, errno.ENOENT):
      raise
    return time.time()
