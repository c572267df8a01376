"""Trained models read back: a training workdir's config and best (or any) checkpoint, and what
inference needs from a workdir or a converted PyTorch PSMNet (sljax convert-psmnet)."""

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sljax.errors import require
from sljax.io.files import read_json_object
from sljax.losses.weighting import UNCERTAINTY_KEY
from sljax.models.checkpoint import (CHECKPOINT_DIR, CONFIG_FILE, CheckpointUnreadable, print_note,
                                     make_manager, restore, step_entries, verify)
from sljax.nets import convert

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


def load_params(workdir: str | os.PathLike, step: int | None = None, fallback: bool = False,
                note: Callable[[str], None] = print_note
                ) -> tuple[dict[str, Any], dict[str, Any], int]:
  """(config, {'params', 'batch_stats'}, step) of a workdir; step None = best, else that step.
  A damaged checkpoint is refused in one line; with fallback (step None only) a damaged best
  gives way to the newest intact step before it, and a line to `note` names the damaged one."""
  workdir = Path(workdir).absolute()
  config = read_config(workdir)
  checkpoints = workdir / CHECKPOINT_DIR
  manager = make_manager(checkpoints, read_only=True)
  try:
    entries = step_entries(checkpoints)
    if step is not None:
      require(step in entries, f"{checkpoints}: no checkpoint at step {step} (have {entries})")
      state = restore(manager, step, note=note)[0]
    else:
      step, state = _best_intact(manager, entries, fallback, note)
  finally:
    manager.close()
  params = dict(state["params"])
  params.pop(UNCERTAINTY_KEY, None)  # the strategy's own, not the network's
  variables = {"params": params}
  if state.get("batch_stats"):
    variables["batch_stats"] = state["batch_stats"]
  return config, variables, int(step)


BEST_FILES = frozenset({"metrics/metrics"})  # what orbax's choice of the best step reads


def _best_intact(manager, entries: list[int], fallback: bool,
                 note: Callable[[str], None]) -> tuple[int, Any]:
  """(step, state) of the best checkpoint by val MAE, or (fallback) the newest intact before it."""
  checkpoints = Path(manager.directory)
  best = manager.best_step()
  # A newer step that orbax passed over (a file, an emptied folder) or whose metrics changed may
  # have been the best: its structure and metrics are checked (cheap), not all its bytes.
  for step in [s for s in entries if best is None or s > best]:
    try:
      verify(checkpoints, step, only=BEST_FILES)
    except CheckpointUnreadable as e:
      require(fallback, str(e))
      note(f"{e}; using step {best} instead" if best is not None else str(e))
  require(best is not None, f"{checkpoints}: no checkpoint saved yet")
  try:
    return best, restore(manager, best, note=note)[0]
  except CheckpointUnreadable as e:
    if not (fallback and e.damaged):
      raise
    for step in reversed([s for s in manager.all_steps() if s < best]):
      try:
        state = restore(manager, step, note=note)[0]
      except CheckpointUnreadable:
        continue
      note(f"{e}; using step {step}, the newest intact one before it")
      return step, state
    raise


def load_for_inference(path: str | os.PathLike, fallback: bool = False
                       ) -> tuple[str, dict[str, Any], dict[str, Any], dict[str, Any]]:
  """(model_name, model_kwargs, variables, config) of a workdir (its best checkpoint by val
  MAE), its checkpoints dir (the same), one step's checkpoint dir (WORKDIR/checkpoints/STEP),
  or a converted PSMNet dir (sljax.nets.convert). fallback: load_params's (a workdir only; a
  step named by its folder is that step or an error)."""
  path = Path(path).absolute()
  require(path.exists(), f"{path}: does not exist")
  step = None
  if (path.name.isdigit() and path.parent.name == CHECKPOINT_DIR
      and _is_workdir(path.parent.parent)):
    path, step = path.parent.parent, int(path.name)
  if path.name == CHECKPOINT_DIR and _is_workdir(path.parent):
    path = path.parent
  if _is_workdir(path):
    config, variables, step = load_params(path, step, fallback=fallback)
    return config["net"], dict(config["model_kwargs"]), variables, dict(config, step=step)
  name, kwargs, variables = convert.load_converted(path)
  return name, dict(kwargs), variables, {"net": name, "model_kwargs": dict(kwargs),
                                         "source": str(path)}
