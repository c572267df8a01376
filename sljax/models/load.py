"""Trained models read back: a training workdir's config and best (or any) checkpoint, and what
inference needs from a workdir or a converted PyTorch PSMNet (sljax convert-psmnet)."""

import json
import os
from pathlib import Path
from typing import Any

from sljax.errors import require
from sljax.io.files import read_json_object
from sljax.losses.weighting import UNCERTAINTY_KEY
from sljax.models.checkpoint import CHECKPOINT_DIR, CONFIG_FILE, make_manager, restore
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
  params.pop(UNCERTAINTY_KEY, None)  # the strategy's own, not the network's
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
