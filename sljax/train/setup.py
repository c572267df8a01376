"""A run's setup before anything compiles: options, data, split, workdir, model options and
--init-from weights, each checked with one SljaxError line; the run's announcement."""

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from sljax.data import preflight
from sljax.data.dataset import split_indices, take_fraction
from sljax.errors import SljaxError, require
from sljax.models import checkpoint as ckpt
from sljax.models import load as trained
from sljax.nets import detach_sl, registry
from sljax.nets.model_config import ModelConfig, variable_shapes
from sljax.runtime import choices
from sljax.train.config import TrainConfig, validate
from sljax.train.feed import DataInfo, batch_parts, check_source, open_source
from sljax.train.workdir import prepare_workdir


def model_config(config: TrainConfig, info: DataInfo) -> ModelConfig:
  """The run's network, resolved and checked once: the flags' options and the data's channels
  and patterns."""
  options = {"depth": config.unet_depth, "base_width": config.unet_width}
  return ModelConfig(config.net, info.channels, config.maxdisp, info.t,
                     tuple((k, v) for k, v in options.items() if k in config.spec.options),
                     config.model_conv_impl,
                     config.precision)


def load_init(path: str, config: TrainConfig) -> tuple[str, dict[str, Any]]:
  """(source net name, variables) of an --init-from checkpoint/converted PSMNet; a twin's
  checkpoint gives its disparity path to a single-task run."""
  try:
    name, _, variables, _ = trained.load_for_inference(path)
  except SljaxError as e:  # the loader's line ("PATH: does not exist"), naming the flag
    raise SljaxError(f"--init-from {e}") from None
  if registry.spec(name).single == config.net:
    variables, name = detach_sl(variables), config.net
  return name, variables


def merge_init(target: dict[str, Any], source: dict[str, Any], source_name: str,
               config: TrainConfig, where: str) -> dict[str, Any]:
  """Target variables with every leaf the source has replaced; SljaxError on any mismatch.

  Leaves only the target has (the twin's SL path when starting from a plain PSMNet) keep their
  initial values; a source leaf missing from the target or of another shape is an error.
  """
  out = {}
  for col in ("params", "batch_stats"):
    tflat = traverse_util.flatten_dict(dict(target.get(col, {})))
    sflat = traverse_util.flatten_dict(dict(source.get(col, {})))
    extra = sorted(set(sflat) - set(tflat))
    if extra:
      raise SljaxError(f"--init-from {where}: a {source_name} checkpoint does not fit model "
                       f"{config.net}: {col} {'/'.join(extra[0])} has no counterpart")
    for path, v in sflat.items():
      tshape, sshape = tuple(np.shape(tflat[path])), tuple(np.shape(v))
      if tshape != sshape:
        raise SljaxError(f"--init-from {where}: {col} {'/'.join(path)} has shape {sshape} but "
                         f"model {config.net} needs {tshape} (different model or input channels)")
    require(col == "batch_stats" or sflat, f"--init-from {where}: no parameters found")
    merged = dict(tflat)
    merged.update({p: jnp.asarray(v, tflat[p].dtype) for p, v in sflat.items()})
    out[col] = traverse_util.unflatten_dict(merged) if merged else {}
  return out


@dataclasses.dataclass(frozen=True)
class Setup:
  """A checked run: its data, split, workdir and model options (nothing compiled yet)."""
  config: TrainConfig
  workdir: Path
  source: Any
  train_idx: tuple[int, ...]
  val_idx: tuple[int, ...]
  info: DataInfo
  model: ModelConfig
  resume: bool
  init: tuple[str, dict[str, Any]] | None = None  # --init-from: (source net, its variables)
  config_json: dict[str, Any] | None = None  # what write_config writes once the run can start

  @property
  def steps_per_epoch(self) -> int:
    """Full batches per epoch (the remainder of the shuffled scenes is dropped)."""
    return len(self.train_idx) // self.config.batch_size

  @property
  def total_steps(self) -> int:
    """Steps of the whole run: --steps, else the epochs' steps."""
    if self.config.steps is not None:
      return self.config.steps
    return self.steps_per_epoch * self.config.epochs


def resolve_ynn(config: TrainConfig, workdir: Path, resume: bool, overwrite: bool,
                log: Callable[[str], None]) -> TrainConfig:
  """The config with --ynn auto resolved: a resumed run keeps its saved choice (the same
  programs), a new one (or one replacing the old run) takes this CPU's tuned choice."""
  if config.ynn != "auto":
    return config
  if resume and not overwrite and (workdir / ckpt.CONFIG_FILE).is_file():
    return dataclasses.replace(config, ynn=trained.read_config(workdir).get("ynn", "on"))
  return dataclasses.replace(config, ynn=choices.choice(log=log).name)


def _why_no_held_out(source: Any) -> str:
  """Why split_indices held nothing out (--test-fraction is in (0, 1), --max-val >= 1): the
  dataset's own splits, or fewer than two groups, as the split holds out whole groups."""
  if getattr(source, "splits", None):
    return "dataset.json's 'splits' leave no test scene"
  n = len(source)
  groups = {source.group(i) for i in range(n)}
  return (f"its {n} scene(s) form {len(groups)} group(s) (meta.json 'group', else the scene's "
          "name) and whole groups are held out; give scenes of at least 2 groups")


def setup(config: TrainConfig, workdir: Path, resume: bool, overwrite: bool,
          log: Callable[[str], None], preset_note: str = "", source: Any = None,
          progress: bool = False) -> Setup:
  """Checks the options, data and workdir (SljaxError before anything compiles or is tuned:
  a bad file is named in seconds, not after minutes of tuning on a new CPU kind) and announces
  the run; source: the scenes (default open_source); progress: the pre-flight check's bar.
  The caller writes config.json
  (write_config) once the run has passed its checks and restored its checkpoint, so a new run
  that stops before that leaves no config.json (with --overwrite, the caller clears the old run
  once every check has passed: workdir.clear_run)."""
  validate(config)
  n_dev, n_proc = jax.device_count(), jax.process_count()
  require(config.batch_size % n_dev == 0,
          f"--batch-size {config.batch_size}: must be a multiple of the {n_dev} devices")
  require(config.batch_size % n_proc == 0,
          f"--batch-size {config.batch_size}: must be a multiple of the {n_proc} processes")
  source = open_source(config) if source is None else source
  train_idx, val_idx = split_indices(source, config.test_fraction, seed=config.seed)
  train_idx = take_fraction(train_idx, config.fraction, seed=config.seed)
  if config.max_val is not None:
    val_idx = val_idx[:config.max_val]
  require(len(train_idx) >= config.batch_size,
          f"--batch-size {config.batch_size}: larger than the {len(train_idx)} training scenes "
          f"(fraction {config.fraction} of {len(source)} scenes)")
  require(len(val_idx) > 0, f"{config.data or 'synthetic data'}: the held-out split is empty"
          f" ({_why_no_held_out(source)})")
  steps_per_epoch = len(train_idx) // config.batch_size
  log(announce(config, preset_note, steps_per_epoch, len(train_idx), len(val_idx)))
  info = check_source(source, config)
  preflight.check_run(source, [(train_idx, batch_parts(config)),
                               (val_idx, batch_parts(config, validation=info.has_disp))],
                      progress=progress)
  config = resolve_ynn(config, workdir, resume, overwrite, log)  # may compile: after checks
  model_cfg = model_config(config, info)
  config_json = dict(config.to_json(), net=config.net, model_kwargs=model_cfg.saved_kwargs,
                     t=info.t,
                     gray=config.use_gray, steps_per_epoch=steps_per_epoch,
                     n_train=len(train_idx), n_val=len(val_idx))
  do_resume, config_json = prepare_workdir(workdir, config_json, resume, overwrite)
  init = None
  if config.init_from and not do_resume:
    # Shapes are compared on an abstract init, so a mismatch errors before compiling anything.
    abstract = variable_shapes(model_cfg.build(), *config.size, info.channels)
    init = load_init(config.init_from, config)
    merge_init(abstract, init[1], init[0], config, config.init_from)
  return Setup(config, workdir, source, tuple(train_idx), tuple(val_idx), info, model_cfg,
               do_resume, init, config_json)


def announce(config: TrainConfig, preset_note: str, steps_per_epoch: int,
             n_train: int, n_val: int) -> str:
  """The first output line: preset, run shape and the estimated time per epoch."""
  h, w = config.size
  scale = (h * w) / (64 * 64)
  if "maxdisp" in config.spec.options:
    scale *= (0.5 + 0.5 * config.maxdisp / 32)
  per_sample = config.spec.sec_per_sample_64 * scale
  if jax.default_backend() != "cpu":
    per_sample /= 100.0
  est = per_sample * steps_per_epoch * config.batch_size
  strategy = f"/{config.strategy}" if registry.spec(config.model).twin else ""
  return (f"sljax train: preset {config.preset}{preset_note}: {config.net}{strategy}, {h}x{w}, "
          f"maxdisp {config.maxdisp}, {_budget(config, steps_per_epoch)} "
          f"({n_train} train / {n_val} val scenes) on "
          f"{jax.device_count()} {jax.default_backend()} device(s); estimated "
          f"~{_fmt_seconds(est)} per epoch (measured ETA in the progress bar)")


def _budget(config: TrainConfig, steps_per_epoch: int) -> str:
  """The run's length in the announcement, in epochs or (--steps) in steps."""
  if config.steps is None:
    return f"{config.epochs} epochs x {steps_per_epoch} steps of {config.batch_size}"
  return (f"{config.steps} steps of {config.batch_size} ({config.steps / steps_per_epoch:.4g} "
          f"epochs of {steps_per_epoch} steps)")


def _fmt_seconds(s: float) -> str:
  if s < 1:
    return "<1 s"
  if s < 90:
    return f"{s:.0f} s"
  if s < 5400:
    return f"{s / 60:.1f} min"
  return f"{s / 3600:.1f} h"
