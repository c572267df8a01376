"""Orbax checkpoints of training runs: saving, retention and restoring a TrainState.

WORKDIR/checkpoints/<step>/ holds 'state', the TrainState packed into one vector per dtype, and
'meta', the loop's bookkeeping JSON with the packing's layout (each leaf's path, dtype and
shape, in flattening order). Packed because orbax / TensorStore spend about 1 ms of CPU per
array: the twin's state is ~1240 arrays, 1.4 s of CPU per save, against 0.2 s for two vectors
(a per-epoch cost that competed with training on small CPUs). Checkpoints written before
packing (the state as a tree, no layout) still restore.
Retention: the last `keep` checkpoints plus the best one by validation MAE (lowest).

Failed saves: orbax writes a checkpoint under <step>.orbax-checkpoint-tmp and renames it to
<step> once every file is written, so a save cut short (a full disk, a read-only or
unwritable workdir, a killed process) leaves a tmp folder that a resume ignores, and the
previous checkpoints stay (old ones are deleted only after a save is finalised). A failure
becomes one SljaxError line naming what failed, where, and the last good checkpoint
(sljax.models.failures).

Digests: each step folder holds sljax_digest.json, the SHA-256 of its files, written inside the
temporary folder just before orbax's rename (sljax.models.digest says why there), so a finished
checkpoint always has one. `restore` checks it before orbax reads a byte: a file changed, cut
short, emptied, missing, or a folder where a file was (or a file where the step's folder should
be) is CheckpointUnreadable naming the step and the file. A checkpoint whose meta says it was
written with a digest but has none is damaged too; one from before digests restores unchecked,
with one line saying so.
"""

import itertools
import json
import math
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
from flax import traverse_util
from orbax.checkpoint.checkpoint_managers import preservation_policy as pp

from sljax.errors import SljaxError
from sljax.models import digest
from sljax.models.failures import (RESTORE_ERRORS, SAVING, quiet_late_reads, quiet_storage_logs,
                                   storage_errno, storage_guard)

CHECKPOINT_DIR = "checkpoints"
CONFIG_FILE = "config.json"
BEST_METRIC = "val_mae"
LAYOUT_KEY = "packed_layout"  # in meta: [[path parts], dtype, shape] per leaf
DIGEST_KEY = "digest"  # in meta: the digest format, so a lost digest file is damage, not age


def _val_mae(metrics: dict[str, Any]) -> float:
  return float(metrics[BEST_METRIC])


def make_manager(directory: str | os.PathLike, keep: int = 3,
                 read_only: bool = False) -> ocp.CheckpointManager:
  """A CheckpointManager on an absolute path keeping the last `keep` plus the best by val MAE."""
  directory = Path(directory).absolute()
  policy = pp.AnyPreservationPolicy([
      pp.LatestN(n=max(1, keep)),
      pp.BestN(get_metric_fn=_val_mae, reverse=True, n=1,
               keep_checkpoints_without_metrics=False),
  ])
  quiet_storage_logs()
  check_step_metadata(directory)
  options = ocp.CheckpointManagerOptions(
      preservation_policy=None if read_only else policy, best_fn=_val_mae, best_mode="min",
      keep_checkpoints_without_metrics=True, create=not read_only, read_only=read_only,
      enable_async_checkpointing=not read_only, temporary_path_class=digest.DigestedRename)
  with storage_guard("creating the checkpoint folder", directory):
    return ocp.CheckpointManager(directory, options=options, item_names=("state", "meta"))


def check_step_metadata(directory: Path) -> None:
  """CheckpointUnreadable for the first step whose orbax step metadata is not a JSON object:
  orbax reads every step's when it opens the folder, and fails with a JSONDecodeError traceback
  (the one file the digest leaves out, sljax.models.digest)."""
  for step in step_entries(directory):
    path = directory / str(step) / digest.COMMIT_FILES_METADATA
    try:
      ok = not path.is_file() or isinstance(json.loads(path.read_bytes()), dict)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
      ok = False
    if not ok:
      raise damaged(directory, step, f"{path.name}: not the JSON object orbax wrote")


def _key_name(key: Any) -> str:
  for attr in ("key", "name", "idx"):
    if hasattr(key, attr):
      return str(getattr(key, attr))
  return str(key)


def layout(tree: Any) -> list[list[Any]]:
  """[[path parts], dtype, shape] of each leaf of tree, in flattening order."""
  return [[[_key_name(k) for k in path], str(jax.dtypes.canonicalize_dtype(leaf.dtype)),
           list(np.shape(leaf))]
          for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]]


@jax.jit
def pack(tree: Any) -> dict[str, jax.Array]:
  """The leaves of tree raveled and concatenated, one vector per dtype (flattening order)."""
  leaves = [jnp.asarray(x) for x in jax.tree.leaves(tree)]
  return {str(dt): jnp.concatenate([x.ravel() for x in leaves if x.dtype == dt])
          for dt in sorted({x.dtype for x in leaves}, key=str)}


def unpack(packed: dict[str, jax.Array], lay: list[list[Any]],
           sharding: jax.sharding.Sharding) -> list[jax.Array]:
  """The leaves that pack concatenated, given their layout (inverse of pack), placed with
  `sharding`. Sliced on the host: as one XLA program the few hundred slices of a long vector
  took 27 s to compile for PSMNet and 47 s for its twin (a 2-core Zen 3), longer than a
  smoke-scale training run."""
  # The state is replicated (train/step.py), so every device holds the whole vector.
  host = {dt: np.asarray(v.addressable_data(0)) for dt, v in packed.items()}
  offsets = dict.fromkeys(packed, 0)
  leaves = []
  for _, dtype, shape in lay:
    n = math.prod(shape)
    leaf = host[dtype][offsets[dtype]:offsets[dtype] + n].reshape(shape)
    leaves.append(jax.make_array_from_callback(tuple(shape), sharding,
                                               lambda index, leaf=leaf: leaf[index]))
    offsets[dtype] += n
  return leaves


def save(manager: ocp.CheckpointManager, step: int, state: Any, meta: dict[str, Any],
         val_mae: float | None = None) -> None:
  """Starts an async save of the state (packed) and loop metadata at step (`finish` or
  `check` later); a failure of this save or of the previous one (orbax reports it here) is
  storage_failure's SljaxError."""
  metrics = None if val_mae is None else {BEST_METRIC: float(val_mae)}
  meta = dict(meta, **{LAYOUT_KEY: layout(state), DIGEST_KEY: digest.FORMAT})
  with storage_guard(f"saving checkpoint {step}", manager.directory):
    manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(pack(state)),
                                                meta=ocp.args.JsonSave(meta)),
                 metrics=metrics, force=True)


def check(manager: ocp.CheckpointManager) -> None:
  """Raises storage_failure's SljaxError now if a finished background save failed (instead
  of at the next save, an epoch later); free when nothing failed."""
  if not manager.is_saving_in_progress():
    with storage_guard(SAVING, manager.directory):
      manager.wait_until_finished()


def finish(manager: ocp.CheckpointManager) -> None:
  """Waits for the pending save and closes the manager (also when the save failed: then
  storage_failure's SljaxError)."""
  try:
    with storage_guard(SAVING, manager.directory):
      manager.wait_until_finished()
  finally:
    manager.close()


def _restore_packed(manager: ocp.CheckpointManager, step: int, lay: list[list[Any]],
                    abstract_state: Any | None) -> Any:
  """The state of a packed checkpoint, as abstract_state's tree with its shardings (else nested
  dicts on this process's first device)."""
  if abstract_state is None:
    sharding = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
  else:
    want = layout(abstract_state)
    if lay != want:
      i = next(i for i, (a, b) in enumerate(itertools.zip_longest(lay, want)) if a != b)
      leaf = lambda entries: "/".join(entries[i][0]) if i < len(entries) else "(none)"
      raise SljaxError(f"{manager.directory}/{step}: the checkpoint does not match the model "
                       f"(leaf {i}: checkpoint has {leaf(lay)}, model expects {leaf(want)})")
    sharding = jax.tree.leaves(abstract_state)[0].sharding
  sizes: dict[str, int] = {}
  for _, dtype, shape in lay:
    sizes[dtype] = sizes.get(dtype, 0) + math.prod(shape)
  abstract = {dt: jax.ShapeDtypeStruct((n,), dt, sharding=sharding) for dt, n in sizes.items()}
  packed = manager.restore(step, args=ocp.args.Composite(
      state=ocp.args.StandardRestore(abstract)))["state"]
  leaves = unpack(packed, lay, sharding)
  if abstract_state is not None:
    return jax.tree.unflatten(jax.tree.structure(abstract_state), leaves)
  return traverse_util.unflatten_dict({tuple(parts): leaf for (parts, _, _), leaf
                                       in zip(lay, leaves)})


class CheckpointUnreadable(SljaxError):
  """A checkpoint that cannot be restored (damaged, incomplete or unreadable files)."""

  def __init__(self, message: str, directory: Path, step: int, damaged: bool = True):
    super().__init__(message)
    # damaged: the files are broken (deleting the step is the remedy); else unreadable here.
    self.directory, self.step, self.damaged = directory, step, damaged


def unreadable(directory: str | os.PathLike, step: int, exc: BaseException) -> CheckpointUnreadable:
  """The one-line error for a checkpoint whose restore failed with exc (orbax and TensorStore
  raise anything from KeyError to JSONDecodeError, with tracebacks of ~150 lines)."""
  folder = Path(directory) / str(step)
  found = storage_errno(exc)
  if found is not None:  # a permission problem, not damage: say so
    code, path = found
    return CheckpointUnreadable(f"{folder}: checkpoint {step} cannot be read: "
                                f"{os.strerror(code)} ({path or folder})", Path(directory), step,
                                damaged=False)
  reason = (str(exc).strip().splitlines() or [""])[0]
  reason = reason if len(reason) <= 160 else reason[:160] + "..."
  reason = type(exc).__name__ + (f": {reason}" if reason else "")
  return CheckpointUnreadable(f"{folder}: checkpoint {step} is damaged or incomplete (its files "
                              f"do not restore: {reason})", Path(directory), step)


def damaged(directory: str | os.PathLike, step: int, problem: str) -> CheckpointUnreadable:
  """The one-line error for a step whose files are not those written ('FILE: problem')."""
  folder = Path(directory) / str(step)
  return CheckpointUnreadable(f"{folder}: checkpoint {step} is damaged or incomplete ({problem})",
                              Path(directory), step)


def step_entries(directory: str | os.PathLike) -> list[int]:
  """Every step named in a checkpoints folder, sorted: folders and also what orbax skips (a file
  where a step's folder should be, an emptied folder), so that none is passed over unsaid."""
  directory = Path(directory)
  return sorted(int(p.name) for p in directory.iterdir() if p.name.isdigit()) \
      if directory.is_dir() else []


def verify(directory: str | os.PathLike, step: int, only: frozenset[str] | None = None) -> bool:
  """True when every file of the step (or those of `only` it has) is the bytes written; False
  when it has no digest (saved before digests); else CheckpointUnreadable naming the first file
  that differs."""
  folder = Path(directory) / str(step)
  if not folder.exists():
    raise damaged(directory, step, "its folder is missing")
  if not folder.is_dir():
    raise damaged(directory, step, f"{folder.name}: a file where the checkpoint's folder "
                  "should be")
  if not any(folder.iterdir()):
    raise damaged(directory, step, "an empty folder")
  try:
    expected = digest.read_digest(folder)
  except ValueError as e:
    raise damaged(directory, step, str(e)) from None
  if expected is None:
    return False
  if only is not None:
    expected = {k: v for k, v in expected.items() if k in only}
  problem = digest.first_difference(folder, expected, extra=only is None)
  if problem is not None:
    raise damaged(directory, step, problem)
  return True


def print_note(line: str) -> None:
  """Prints a note line (an unchecked or skipped checkpoint) on stderr, beside the errors."""
  print(line, file=sys.stderr, flush=True)


def restore(manager: ocp.CheckpointManager, step: int, abstract_state: Any | None = None,
            note: Callable[[str], None] = print_note) -> tuple[Any, dict[str, Any]]:
  """(state, meta) saved at step; with abstract_state the arrays get its structure/shardings,
  else they land on this process's first device (also for checkpoints written by several
  processes, whose saved shardings name devices this process does not have). The step's bytes
  are checked against its digest first; a checkpoint that is damaged or whose files do not
  restore raises CheckpointUnreadable naming its folder (and the file); one saved before
  digests restores unchecked, with a line to `note`."""
  # Installed before the restore, not after its failure: a late read can finish while orbax
  # is still raising, before any except clause here runs (seen on a busy 2-core CPU).
  quiet_late_reads()
  try:
    checked = verify(manager.directory, step)
    return _restore(manager, step, abstract_state, checked, note)
  except SljaxError:
    raise
  except RESTORE_ERRORS as e:
    raise unreadable(manager.directory, step, e) from None


def _restore(manager: ocp.CheckpointManager, step: int, abstract_state: Any | None,
             checked: bool, note: Callable[[str], None]) -> tuple[Any, dict[str, Any]]:
  meta = manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
  if not isinstance(meta, dict):  # valid JSON but not the loop's object: damage too
    raise unreadable(manager.directory, step, ValueError("meta is not a JSON object"))
  meta = dict(meta)
  if not checked:
    if meta.pop(DIGEST_KEY, None) is not None:  # saved with a digest that is gone: not age
      raise damaged(manager.directory, step, f"{digest.DIGEST_FILE}: missing")
    note(f"{Path(manager.directory) / str(step)}: checkpoint {step} has no digest (saved before "
         "sljax recorded checkpoint bytes); restoring it unchecked")
  meta.pop(DIGEST_KEY, None)
  if LAYOUT_KEY in meta:
    return _restore_packed(manager, step, meta.pop(LAYOUT_KEY), abstract_state), meta
  if abstract_state is None:  # a checkpoint written as a tree, before packing
    saved = ocp.StandardCheckpointer().metadata(
        Path(manager.directory) / str(step) / "state").item_metadata
    device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    abstract_state = jax.tree.map(
        lambda leaf: jax.ShapeDtypeStruct(leaf.shape, leaf.dtype, sharding=device), saved)
  out = manager.restore(step, args=ocp.args.Composite(
      state=ocp.args.StandardRestore(abstract_state)))
  return out["state"], meta
