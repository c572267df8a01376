"""Orbax checkpoints of training runs and loading trained models for inference.

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
raised from anywhere in orbax or TensorStore (an OSError, or TensorStore's ValueError carrying
the OS error code, possibly from a background thread at a later save or wait) becomes one
SljaxError line naming what failed, where, and the last good checkpoint (`storage_failure`).
"""

import contextlib
import errno
import itertools
import json
import logging
import math
import os
import re
import sys
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
from flax import traverse_util
from orbax.checkpoint.checkpoint_managers import preservation_policy as pp

from sljax.files import read_json_object
from sljax.errors import SljaxError, require
from sljax.nets import convert

CHECKPOINT_DIR = "checkpoints"
CONFIG_FILE = "config.json"
BEST_METRIC = "val_mae"
LAYOUT_KEY = "packed_layout"  # in meta: [[path parts], dtype, shape] per leaf


# OS errors that mean "this storage does not take the write" (not a bug in the caller).
STORAGE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG)
_TS_CODE = re.compile(r"os_error_code='?(\d+)")  # TensorStore's errors carry the OS error code
_QUOTED_PATH = re.compile(r'"(/[^"]+)"')
SAVING = "saving a checkpoint"
_HINT = {errno.ENOSPC: "free some space", errno.EDQUOT: "free some space (disk quota)",
         errno.EFBIG: "free some space", errno.EROFS: "make it writable",
         errno.EACCES: "make it writable (permissions)",
         errno.EPERM: "make it writable (permissions)"}


def _causes(exc: BaseException):
  """exc, its causes and contexts, and the members of exception groups (each once)."""
  todo, seen = [exc], set()
  while todo:
    e = todo.pop(0)
    if e is None or id(e) in seen:
      continue
    seen.add(id(e))
    yield e
    todo += [e.__cause__, e.__context__, *getattr(e, "exceptions", ())]


def storage_errno(exc: BaseException) -> tuple[int, str | None] | None:
  """(errno, path or None) of a full-disk / read-only / permission failure inside exc (its
  chain, exception groups, or TensorStore's message), else None."""
  for e in _causes(exc):
    if isinstance(e, OSError) and e.errno in STORAGE_ERRNOS:
      return e.errno, e.filename and os.fspath(e.filename)
    text = str(e)
    m = _TS_CODE.search(text)
    codes = [int(m.group(1))] if m else [c for c in STORAGE_ERRNOS if os.strerror(c) in text]
    if codes and codes[0] in STORAGE_ERRNOS:
      paths = _QUOTED_PATH.findall(text)
      return codes[0], paths[-1] if paths else None
  return None


def last_good_step(directory: str | os.PathLike) -> int | None:
  """The step a --resume would restore: the latest finalised checkpoint (None: none)."""
  directory = Path(directory)
  steps = [int(p.name) for p in directory.iterdir() if p.name.isdigit() and p.is_dir()] \
      if directory.is_dir() else []
  return max(steps, default=None)


def storage_failure(exc: BaseException, what: str, checkpoints: str | os.PathLike
                    ) -> SljaxError | None:
  """The one-line SljaxError for a failed write (what: e.g. 'saving checkpoint 120'), or None
  when exc is not a storage failure."""
  found = storage_errno(exc)
  if found is None:
    return None
  code, path = found
  checkpoints = Path(checkpoints)
  step = re.search(r"/(\d+)\.orbax-checkpoint-tmp", path or "")
  if what.startswith("saving") and step:
    # Orbax reports a failed background save at the next save or wait: name the failed one.
    what = f"saving checkpoint {step.group(1)}"
  where = path or str(checkpoints)
  good = last_good_step(checkpoints)
  kept = (f"the last good checkpoint is step {good} ({checkpoints / str(good)}), intact"
          if good is not None else "no checkpoint was saved yet")
  again = "continue with --resume" if good is not None else "run again"
  return SljaxError(f"{what} failed: {os.strerror(code)} ({where}); stopped, {kept}; "
                    f"{_HINT[code]} and {again}")


@contextlib.contextmanager
def storage_guard(what: str, checkpoints: str | os.PathLike):
  """Turns a storage failure inside the block into storage_failure's SljaxError."""
  try:
    yield
  except SljaxError:
    raise
  except Exception as e:  # pylint: disable=broad-except
    failure = storage_failure(e, what, checkpoints)
    if failure is None:
      raise
    raise failure from None


class _QuietStorageFailures(logging.Filter):
  """Drops orbax's ERROR logs (with tracebacks, one per thread) of a storage failure: the same
  failure is raised to the caller, who reports it in one line."""

  def filter(self, record: logging.LogRecord) -> bool:
    exc = record.exc_info[1] if record.exc_info else None
    if exc is not None and storage_errno(exc) is not None:
      return False
    try:
      message = record.getMessage()
    except Exception:  # pylint: disable=broad-except
      return True
    return not (record.levelno >= logging.ERROR and "orbax" in record.pathname
                and storage_errno(Exception(message)) is not None)


_QUIET = _QuietStorageFailures()


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
  logging.getLogger("absl").addFilter(_QUIET)  # idempotent: a filter is added once
  options = ocp.CheckpointManagerOptions(
      preservation_policy=None if read_only else policy, best_fn=_val_mae, best_mode="min",
      keep_checkpoints_without_metrics=True, create=not read_only, read_only=read_only,
      enable_async_checkpointing=not read_only)
  with storage_guard("creating the checkpoint folder", directory):
    return ocp.CheckpointManager(directory, options=options, item_names=("state", "meta"))


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
  meta = dict(meta, **{LAYOUT_KEY: layout(state)})
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


def restore(manager: ocp.CheckpointManager, step: int,
            abstract_state: Any | None = None) -> tuple[Any, dict[str, Any]]:
  """(state, meta) saved at step; with abstract_state the arrays get its structure/shardings,
  else they land on this process's first device (also for checkpoints written by several
  processes, whose saved shardings name devices this process does not have). A checkpoint
  whose files do not restore raises CheckpointUnreadable naming its folder."""
  # Installed before the restore, not after its failure: a late read can finish while orbax
  # is still raising, before any except clause here runs (seen on a busy 2-core CPU).
  _drop_late_read_callbacks()
  logging.getLogger("asyncio").addFilter(_QUIET_LATE_READS)  # idempotent, like _QUIET
  try:
    return _restore(manager, step, abstract_state)
  except SljaxError:
    raise
  except RESTORE_ERRORS as e:
    raise unreadable(manager.directory, step, e) from None


# What orbax and TensorStore raise for damaged or missing files (TensorStore's DATA_LOSS,
# OUT_OF_RANGE and FAILED_PRECONDITION arrive as ValueError, a garbage JSON item as
# JSONDecodeError, a missing item as KeyError). Anything else (a device out of memory while
# the arrays are placed, a bug) is not the checkpoint's fault and keeps its own error.
RESTORE_ERRORS = (ValueError, KeyError, TypeError, EOFError, OSError)


def _late_read_callback(unraisable: Any) -> bool:
  """Whether an unraisable exception is a TensorStore read finishing after orbax's event loop
  closed: when one array of a restore fails, orbax closes its loop while the reads of the
  others are in flight, and each one's completion prints a traceback (after our one line)."""
  exc, tb = unraisable.exc_value, unraisable.exc_traceback
  while tb is not None and tb.tb_next is not None:
    tb = tb.tb_next
  return (isinstance(exc, RuntimeError) and str(exc) == "Event loop is closed"
          and tb is not None and "asyncio" in tb.tb_frame.f_code.co_filename)


class _QuietLateReadFailures(logging.Filter):
  """Drops asyncio's 'Task exception was never retrieved' for an orbax read: orbax gathers the
  reads of a restore without return_exceptions, so when one array fails the restore raises
  (reported in one line) and the other reads' failures, unretrieved, are logged with a
  traceback when their tasks are collected, possibly long after (seen in CI on a busy Zen 3)."""

  def filter(self, record: logging.LogRecord) -> bool:
    exc = record.exc_info[1] if record.exc_info else None
    return not (isinstance(exc, RESTORE_ERRORS) and _raised_in_orbax(exc)
                and str(record.msg).startswith("Task exception was never retrieved"))


def _raised_in_orbax(exc: BaseException) -> bool:
  """Whether exc's traceback passes through orbax's checkpoint package."""
  tb = exc.__traceback__
  while tb is not None:
    if "orbax" in Path(tb.tb_frame.f_code.co_filename).parts:
      return True
    tb = tb.tb_next
  return False


_QUIET_LATE_READS = _QuietLateReadFailures()


def _drop_late_read_callbacks() -> None:
  """Installs (once) an unraisable hook that drops _late_read_callback's tracebacks only."""
  previous = sys.unraisablehook
  if getattr(previous, "sljax_drops_late_reads", False):
    return

  def hook(unraisable: Any) -> None:
    if not _late_read_callback(unraisable):
      previous(unraisable)
  hook.sljax_drops_late_reads = True
  sys.unraisablehook = hook


def _restore(manager: ocp.CheckpointManager, step: int,
             abstract_state: Any | None) -> tuple[Any, dict[str, Any]]:
  meta = manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
  if not isinstance(meta, dict):  # valid JSON but not the loop's object: damage too
    raise unreadable(manager.directory, step, ValueError("meta is not a JSON object"))
  meta = dict(meta)
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


def read_config(workdir: str | os.PathLike) -> dict[str, Any]:
  """The resolved training config saved in a workdir."""
  path = Path(workdir) / CONFIG_FILE
  require(path.is_file(), f"{path}: missing (not a training workdir)")
  return read_json_object(path, str(path))


def _is_workdir(path: Path) -> bool:
  cfg = path / CONFIG_FILE
  if not (cfg.is_file() and (path / CHECKPOINT_DIR).is_dir()):
    return False
  try:
    return "strategy" in json.loads(cfg.read_text())
  except (OSError, json.JSONDecodeError):
    return False


def load_params(workdir: str | os.PathLike,
                step: int | None = None) -> tuple[dict[str, Any], dict[str, Any], int]:
  """(config, {'params', 'batch_stats'}, step) of a workdir; step None = best, else latest."""
  workdir = Path(workdir).absolute()
  config = read_config(workdir)
  manager = make_manager(workdir / CHECKPOINT_DIR, read_only=True)
  try:
    if step is None:
      step = manager.best_step()
    require(step is not None, f"{workdir / CHECKPOINT_DIR}: no checkpoint saved yet")
    require(step in manager.all_steps(),
            f"{workdir / CHECKPOINT_DIR}: no checkpoint at step {step} "
            f"(have {sorted(manager.all_steps())})")
    state, _ = restore(manager, step)
  finally:
    manager.close()
  params = dict(state["params"])
  params.pop("uncertainty", None)
  variables = {"params": params}
  if state.get("batch_stats"):
    variables["batch_stats"] = state["batch_stats"]
  return config, variables, int(step)


def load_for_inference(path: str | os.PathLike) -> tuple[str, dict[str, Any], dict[str, Any],
                                                          dict[str, Any]]:
  """(model_name, model_kwargs, variables, config) of a workdir (its best checkpoint by val
  MAE), its checkpoints dir (the same), one step's checkpoint dir (WORKDIR/checkpoints/STEP),
  or a converted PSMNet dir (sljax.nets.convert)."""
  path = Path(path).absolute()
  require(path.exists(), f"{path}: does not exist")
  step = None
  if path.name.isdigit() and path.parent.name == CHECKPOINT_DIR and _is_workdir(path.parent.parent):
    path, step = path.parent.parent, int(path.name)
  if path.name == CHECKPOINT_DIR and _is_workdir(path.parent):
    path = path.parent
  if _is_workdir(path):
    config, variables, step = load_params(path, step)
    return config["net"], dict(config["model_kwargs"]), variables, dict(config, step=step)
  name, kwargs, variables = convert.load_converted(path)
  return name, dict(kwargs), variables, {"net": name, "model_kwargs": dict(kwargs),
                                         "source": str(path)}
