"""Orbax checkpoints of training runs and loading trained models for inference.

WORKDIR/checkpoints/<step>/ holds {'state': TrainState pytree, 'meta': loop bookkeeping JSON}.
Retention: the last `keep` checkpoints plus the best one by validation MAE (lowest).
"""

import json
import os
from pathlib import Path
from typing import Any

import jax
import orbax.checkpoint as ocp
from orbax.checkpoint.checkpoint_managers import preservation_policy as pp

from sljax.errors import require

CHECKPOINT_DIR = "checkpoints"
CONFIG_FILE = "config.json"
BEST_METRIC = "val_mae"


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
  options = ocp.CheckpointManagerOptions(
      preservation_policy=None if read_only else policy, best_fn=_val_mae, best_mode="min",
      keep_checkpoints_without_metrics=True, create=not read_only, read_only=read_only,
      enable_async_checkpointing=not read_only)
  return ocp.CheckpointManager(directory, options=options, item_names=("state", "meta"))


def save(manager: ocp.CheckpointManager, step: int, state: Any, meta: dict[str, Any],
         val_mae: float | None = None) -> None:
  """Starts an async save of the state and loop metadata at step (wait_until_finished later)."""
  metrics = None if val_mae is None else {BEST_METRIC: float(val_mae)}
  manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                              meta=ocp.args.JsonSave(meta)),
               metrics=metrics, force=True)


def restore(manager: ocp.CheckpointManager, step: int,
            abstract_state: Any | None = None) -> tuple[Any, dict[str, Any]]:
  """(state, meta) saved at step; with abstract_state the arrays get its structure/shardings,
  else they land on this process's first device (also for checkpoints written by several
  processes, whose saved shardings name devices this process does not have)."""
  if abstract_state is None:
    saved = ocp.StandardCheckpointer().metadata(
        Path(manager.directory) / str(step) / "state").item_metadata
    device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    abstract_state = jax.tree.map(
        lambda leaf: jax.ShapeDtypeStruct(leaf.shape, leaf.dtype, sharding=device), saved)
  out = manager.restore(step, args=ocp.args.Composite(
      state=ocp.args.StandardRestore(abstract_state), meta=ocp.args.JsonRestore()))
  return out["state"], dict(out["meta"])


def read_config(workdir: str | os.PathLike) -> dict[str, Any]:
  """The resolved training config saved in a workdir."""
  from sljax.data.scene import read_json_object  # pylint: disable=import-outside-toplevel
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
  from sljax.nets import convert  # pylint: disable=import-outside-toplevel
  name, kwargs, variables = convert.load_converted(path)
  return name, dict(kwargs), variables, {"net": name, "model_kwargs": dict(kwargs),
                                         "source": str(path)}
