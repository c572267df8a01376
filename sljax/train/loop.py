"""The training loop: setup, state, epochs of prefetched steps, validation, logs, checkpoints.

Reading order: `train` runs a whole run in a few calls: `setup` (options, source, split,
workdir), `create_train_state` or `restore_checkpoint`, then per epoch `run_epoch` (the
steps) and `end_of_epoch` (validate, log, save). `LoopState` is the loop's bookkeeping and
each checkpoint's metadata.

Determinism: the data order of epoch e is a permutation drawn from (seed, e), the task weights
of epoch e depend only on the epoch-mean losses of epochs < e, and the step needs no PRNG
key, so the global step number alone fixes what a step computes. Batches are built ahead by
background threads, but batch k of epoch e is a function of (seed, e, k) only. A resumed run
restores the state and LoopState of the last checkpoint and repeats exactly what the
uninterrupted run would have done.

Step metrics stay on the device and are fetched every `log_every` steps and before every
checkpoint, so the host never waits for a step before dispatching the next one; the NaN check
runs at each fetch, and every step still gets its row in metrics.jsonl.
"""

import collections
import concurrent.futures
import dataclasses
import functools
import itertools
import json
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util
from tqdm import tqdm

from sljax import tune
from sljax.corr.correlation import sl_disparity
from sljax.data import preflight, synthetic
from sljax.data.dataset import (PART_FIELD, FolderSource, epoch_order, load_batch,
                                split_indices, take_fraction)
from sljax.errors import SljaxError, require
from sljax.losses import weighting
from sljax.losses.sl import sl_loss
from sljax.metrics import DisparityAccumulator
from sljax.nets import build_model, detach_sl, registry
from sljax.train import checkpoint as ckpt
from sljax.train import state as st
from sljax.train import step as stp
from sljax.train.config import TrainConfig, diff_configs, dumps, validate
from sljax.train.tensorboard import TensorBoardWriter

METRICS_FILE = "metrics.jsonl"
EPOCHS_FILE = "epochs.jsonl"
PREFETCH = 3          # batches built ahead of the step that needs them
LOADER_THREADS = 2    # threads building them (decoding, resizing and rendering release the GIL)
PROFILE_STEPS = (2, 5)  # --profile traces these steps after the run's (re)start: compiled by then
_CACHE_BYTES = 2 << 30
_TARGET_TEXT = {"disp": "disparity (disp0.pfm)", "sl": "structured-light patterns (sl0/)",
                "sl_right": "right-view structured-light patterns (sl1/)"}


class TrainingDiverged(SljaxError):
  """The loss became NaN or infinite."""


# ----------------------------------------------------------------------------- data


def open_source(config: TrainConfig):
  """The scene source: a scene-format folder or synthetic scenes rendered on the fly."""
  if config.data is not None:
    return FolderSource(config.data)
  synth = synthetic.SynthConfig(size=config.synth_size, domain=config.domain, t=config.synth_t)
  return synthetic.SyntheticSource(config.synth_n, seed=config.seed, config=synth)


def batch_parts(config: TrainConfig, validation: bool = False) -> tuple[str, ...]:
  """Batch keys to load; validation of an SL network also loads disparity when it exists."""
  parts = config.spec.parts
  if validation and "disp" not in parts:
    parts = parts + ("disp",)
  return parts


@dataclasses.dataclass(frozen=True)
class DataInfo:
  """What the first scene says about the data: patterns per view, input channels, disparity."""
  t: int | None
  channels: int
  has_disp: bool


def check_source(source, config: TrainConfig) -> DataInfo:
  """Checks the first scene has every target the network trains on (SljaxError naming it)."""
  where = config.data or "synthetic data"
  require(len(source) > 0, f"{where}: no scenes")
  scene = source[0]
  name = getattr(source, "name", None)
  label = name(0) if callable(name) else scene.name
  for part in config.spec.parts:
    if part in _TARGET_TEXT:
      require(getattr(scene, PART_FIELD[part][0]) is not None,
              f"{where}: scene {label} has no {_TARGET_TEXT[part]}, which model {config.net} "
              f"trains on")
  t = None if scene.sl0 is None else int(scene.sl0.shape[-1])
  return DataInfo(t, 1 if config.use_gray else 3, scene.disp0 is not None)


class RowCache:
  """Per-scene resized rows kept in RAM (small runs revisit every scene each epoch); safe to
  call from the loader threads (at worst two threads load one scene twice)."""

  def __init__(self, source, config: TrainConfig, parts: Sequence[str], enabled: bool):
    self.source, self.config, self.parts, self.enabled = source, config, tuple(parts), enabled
    self.rows: dict[int, dict[str, np.ndarray]] = {}

  def batch(self, indices: Sequence[int]) -> dict[str, np.ndarray]:
    """Stacked batch of the given scene indices (resized to config.size)."""
    load = functools.partial(load_batch, self.source, size=self.config.size,
                             gray=self.config.use_gray, parts=self.parts)
    if not self.enabled:
      return load(list(indices))
    missing = [i for i in indices if i not in self.rows]
    if missing:
      loaded = load(missing)
      for k, i in enumerate(missing):
        self.rows[i] = {p: loaded[p][k] for p in self.parts}
    return {p: np.stack([self.rows[i][p] for i in indices]) for p in self.parts}


def bytes_per_scene(config: TrainConfig, t: int | None) -> int:
  """Approximate RAM of one cached resized scene."""
  h, w = config.size
  c = 1 if config.use_gray else 3
  return 4 * h * w * (2 * c + 2 + 2 * (t or 0))


def prefetch(fn: Callable[[Any], Any], items: Iterator[Any], ahead: int = PREFETCH,
             threads: int = LOADER_THREADS) -> Iterator[Any]:
  """fn(item) for each item, in order, computed by background threads `ahead` items early."""
  items = iter(items)
  with concurrent.futures.ThreadPoolExecutor(threads, thread_name_prefix="sljax-data") as pool:
    queue = collections.deque(pool.submit(fn, x) for x in itertools.islice(items, ahead))
    try:
      while queue:
        result = queue.popleft().result()
        queue.extend(pool.submit(fn, x) for x in itertools.islice(items, 1))
        yield result
    finally:
      for future in queue:
        future.cancel()


# ----------------------------------------------------------------------------- model and state


def model_kwargs(config: TrainConfig, channels: int, t: int | None) -> dict[str, Any]:
  """Keyword arguments of sljax.nets.build_model for this run (the options the net takes)."""
  values = {"maxdisp": config.maxdisp, "t": t, "depth": config.unet_depth,
            "base_width": config.unet_width}
  kw: dict[str, Any] = {"in_channels": channels}
  kw.update({k: v for k, v in values.items() if k in config.spec.options})
  return kw


@functools.lru_cache(maxsize=8)
def compiled_steps(net: str, kwargs: tuple[tuple[str, Any], ...], maxdisp: int, disp_loss: str,
                   lr: float, lr_drop_step: int | None, precision: str,
                   mesh, ynn: str = "on") -> tuple[Any, Any, Any, Any]:
  """(model, optimiser, train step, eval step), memoised so runs in one process share the
  compiled steps (tests, notebooks, experiment grids, a resume in the same process); `ynn` is
  the resolved --ynn (sljax.tune), the steps' XLA compiler options."""
  model = build_model(net, **dict(kwargs))
  tx = st.make_optimizer(lr, lr_drop_step)
  dtype = stp.COMPUTE_DTYPES[precision]
  choice = tune.KernelChoice.from_name(ynn)
  return (model, tx,
          stp.make_train_step(model, net=net, maxdisp=maxdisp, disp_loss=disp_loss, tx=tx,
                              mesh=mesh, dtype=dtype,
                              compiler_options=choice.compiler_options("train")),
          stp.make_eval_step(model, net=net, mesh=mesh, dtype=dtype,
                             compiler_options=choice.compiler_options("forward")))


def resolve_ynn(config: TrainConfig, workdir: Path, resume: bool,
                log: Callable[[str], None]) -> TrainConfig:
  """The config with --ynn auto resolved: a resumed run keeps its saved choice (the same
  programs), a new one takes this CPU's tuned choice (sljax.tune)."""
  if config.ynn != "auto":
    return config
  saved = workdir / ckpt.CONFIG_FILE
  if resume and saved.exists():
    return dataclasses.replace(config, ynn=ckpt.read_config(workdir).get("ynn", "on"))
  return dataclasses.replace(config, ynn=tune.choice(log=log).name)


def load_init(path: str, config: TrainConfig) -> tuple[str, dict[str, Any]]:
  """(source net name, variables) of an --init-from checkpoint/converted PSMNet; a twin's
  checkpoint gives its disparity path to a single-task run."""
  name, _, variables, _ = ckpt.load_for_inference(path)
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


def task_weights(config: TrainConfig, history: Sequence[Sequence[float]]) -> np.ndarray:
  """The step's [w_sl, w_disp, unc] for the next epoch (single-task nets: their one task)."""
  if config.spec.multi_task:
    return weighting.step_weights(config.strategy, history)
  return np.array([float(t in config.spec.tasks) for t in registry.TASKS] + [0.0], np.float32)


# ----------------------------------------------------------------------------- workdir


def default_workdir(config: TrainConfig) -> Path:
  """runs/<model>-<strategy>-<seed> (single-task models: runs/<model>-<seed>)."""
  strategies = registry.spec(config.model).twin is not None
  name = (f"{config.model}-{config.strategy}-{config.seed}" if strategies
          else f"{config.model}-{config.seed}")
  return Path("runs") / name


def _sync(name: str) -> None:
  """Waits for every process (multi-process runs), e.g. between workdir checks and writes."""
  if jax.process_count() > 1:
    from jax.experimental import multihost_utils  # pylint: disable=import-outside-toplevel
    multihost_utils.sync_global_devices(name)


def prepare_workdir(workdir: Path, config_json: dict[str, Any], resume: bool,
                    overwrite: bool) -> bool:
  """Checks the workdir against the run (every process, before any writes), then clears it
  for --overwrite (the main process); returns whether there is a checkpoint to resume."""
  cfg_path = workdir / ckpt.CONFIG_FILE
  ckpt_dir = workdir / ckpt.CHECKPOINT_DIR
  has_ckpt = ckpt_dir.is_dir() and any(p.name.isdigit() for p in ckpt_dir.iterdir())
  if cfg_path.exists() and not overwrite:
    saved = ckpt.read_config(workdir)
    diff = diff_configs(saved, config_json)
    if diff:
      detail = ", ".join(f"{k}: {saved.get(k)!r} -> {config_json.get(k)!r}" for k in diff[:4])
      raise SljaxError(f"{workdir}: holds another run ({detail}); choose another --workdir or "
                       "pass --overwrite to replace it")
    if not resume and (has_ckpt or (workdir / METRICS_FILE).exists()):
      raise SljaxError(f"{workdir}: holds this run already; pass --resume to continue it or "
                       "--overwrite to start again")
  _sync("sljax-workdir-checked")
  if overwrite:
    if jax.process_index() == 0:
      shutil.rmtree(ckpt_dir, ignore_errors=True)
      for name in (METRICS_FILE, EPOCHS_FILE, ckpt.CONFIG_FILE):
        (workdir / name).unlink(missing_ok=True)
    has_ckpt = False
  return has_ckpt and resume


def _truncate_jsonl(path: Path, keep: Callable[[dict[str, Any]], bool]) -> None:
  """Drops lines written after the checkpoint a run resumes from (and a torn last line)."""
  if not path.exists():
    return
  lines = []
  for line in path.read_text().splitlines():
    try:
      rec = json.loads(line)
    except json.JSONDecodeError:
      continue
    if keep(rec):
      lines.append(line)
  path.write_text("".join(l + "\n" for l in lines))


# ----------------------------------------------------------------------------- bookkeeping


@dataclasses.dataclass(frozen=True)
class LoopState:
  """The loop's bookkeeping beside the TrainState; each checkpoint's metadata.

  history: epoch-mean training (L_sl, L_disp) of the finished epochs (DWA reads it);
  partial: (sum L_sl, sum L_disp, steps) of the current epoch so far.
  """
  step: int = 0
  history: tuple[tuple[float, float], ...] = ()
  partial: tuple[float, float, int] = (0.0, 0.0, 0)
  best_val: float | None = None
  last_val: float | None = None

  def add_step(self, loss_sl: float, loss_disp: float) -> "LoopState":
    """After one step with these (unweighted) training losses."""
    s_sl, s_disp, n = self.partial
    return dataclasses.replace(self, step=self.step + 1,
                               partial=(s_sl + loss_sl, s_disp + loss_disp, n + 1))

  def close_epoch(self) -> "LoopState":
    """The epoch's mean losses join the history; the partial sums restart."""
    s_sl, s_disp, n = self.partial
    return dataclasses.replace(self, history=self.history + ((s_sl / n, s_disp / n),),
                               partial=(0.0, 0.0, 0))

  def validated(self, val_mae: float | None) -> "LoopState":
    """After a validation that measured val_mae (None: nothing measured)."""
    best = self.best_val
    if val_mae is not None and (best is None or val_mae < best):
      best = val_mae
    return dataclasses.replace(self, last_val=val_mae, best_val=best)

  def to_meta(self) -> dict[str, Any]:
    """JSON metadata saved with a checkpoint."""
    return {"step": self.step, "history": [list(e) for e in self.history],
            "partial": list(self.partial), "best_val": self.best_val, "last_val": self.last_val}

  @classmethod
  def from_meta(cls, meta: dict[str, Any]) -> "LoopState":
    """The LoopState saved by to_meta (runs saved before last_val existed: None)."""
    s_sl, s_disp, n = meta["partial"]
    return cls(step=int(meta["step"]),
               history=tuple((float(a), float(b)) for a, b in meta["history"]),
               partial=(float(s_sl), float(s_disp), int(n)), best_val=meta.get("best_val"),
               last_val=meta.get("last_val"))


class MetricWriter:
  """The run's JSON lines: metrics.jsonl (a row per step), epochs.jsonl (a row per epoch),
  mirrored to TensorBoard event files with --tensorboard. Writes on the main process only; a
  full or read-only disk ends the run with one line (ckpt.storage_guard)."""

  def __init__(self, workdir: Path, enabled: bool, tensorboard: bool = False,
               first_step: int = 0):
    self.checkpoints = workdir / ckpt.CHECKPOINT_DIR
    with ckpt.storage_guard("opening the run's logs", self.checkpoints):
      self.files = ({name: open(workdir / name, "a", encoding="utf-8")
                     for name in (METRICS_FILE, EPOCHS_FILE)} if enabled else {})
      self.tensorboard = TensorBoardWriter(workdir, first_step) if enabled and tensorboard \
          else None

  def write(self, name: str, rows: Sequence[dict[str, Any]]) -> None:
    """Appends rows to one of the files and flushes it."""
    with ckpt.storage_guard(f"writing {name}", self.checkpoints):
      if name in self.files:
        self.files[name].write("".join(json.dumps(r) + "\n" for r in rows))
        self.files[name].flush()
      if self.tensorboard is not None:
        self.tensorboard.write(name, rows)

  def close(self) -> None:
    """Closes the files."""
    with ckpt.storage_guard("closing the run's logs", self.checkpoints):
      for f in self.files.values():
        f.close()
      if self.tensorboard is not None:
        self.tensorboard.close()


class StepProfiler:
  """--profile: a jax.profiler trace of steps PROFILE_STEPS after the run's first step."""

  def __init__(self, directory: str | None, first_step: int, log: Callable[[str], None]):
    self.directory, self.log, self.active = directory, log, False
    self.start, self.stop = (first_step + s for s in PROFILE_STEPS)

  def before(self, step: int) -> None:
    """Called before dispatching global step `step` (1-based)."""
    if self.directory and step == self.start + 1:
      jax.profiler.start_trace(self.directory)
      self.active = True

  def after(self, step: int, state: Any) -> None:
    """Called after dispatching step `step`: ends the trace once its steps have run."""
    if self.active and step == self.stop:
      jax.block_until_ready(state)
      self.close()
      self.log(f"profile of steps {self.start + 1}-{self.stop} written to {self.directory}")

  def close(self) -> None:
    """Ends an open trace."""
    if self.active:
      jax.profiler.stop_trace()
      self.active = False


# ----------------------------------------------------------------------------- setup


@dataclasses.dataclass(frozen=True)
class Setup:
  """A checked run: its data, split, workdir and model options (nothing compiled yet)."""
  config: TrainConfig
  workdir: Path
  source: Any
  train_idx: tuple[int, ...]
  val_idx: tuple[int, ...]
  info: DataInfo
  kwargs: dict[str, Any]
  resume: bool
  init: tuple[str, dict[str, Any]] | None = None  # --init-from: (source net, its variables)

  @property
  def steps_per_epoch(self) -> int:
    """Full batches per epoch (the remainder of the shuffled scenes is dropped)."""
    return len(self.train_idx) // self.config.batch_size

  @property
  def total_steps(self) -> int:
    """Steps of the whole run."""
    return self.steps_per_epoch * self.config.epochs


def setup(config: TrainConfig, workdir: Path, resume: bool, overwrite: bool,
          log: Callable[[str], None], preset_note: str = "") -> Setup:
  """Checks the options, data and workdir (SljaxError before anything compiles), writes the
  resolved config.json and announces the run."""
  validate(config)
  config = resolve_ynn(config, workdir, resume, log)
  n_dev, n_proc = jax.device_count(), jax.process_count()
  require(config.batch_size % n_dev == 0,
          f"--batch-size {config.batch_size}: must be a multiple of the {n_dev} devices")
  require(config.batch_size % n_proc == 0,
          f"--batch-size {config.batch_size}: must be a multiple of the {n_proc} processes")
  source = open_source(config)
  train_idx, val_idx = split_indices(source, config.test_fraction, seed=config.seed)
  train_idx = take_fraction(train_idx, config.fraction, seed=config.seed)
  if config.max_val is not None:
    val_idx = val_idx[:config.max_val]
  require(len(train_idx) >= config.batch_size,
          f"--batch-size {config.batch_size}: larger than the {len(train_idx)} training scenes "
          f"(fraction {config.fraction} of {len(source)} scenes)")
  require(len(val_idx) > 0, f"{config.data or 'synthetic data'}: the held-out split is empty")
  steps_per_epoch = len(train_idx) // config.batch_size
  log(announce(config, preset_note, steps_per_epoch, len(train_idx), len(val_idx)))
  info = check_source(source, config)
  kwargs = model_kwargs(config, info.channels, info.t)
  config_json = dict(config.to_json(), net=config.net, model_kwargs=kwargs, t=info.t,
                     gray=config.use_gray, steps_per_epoch=steps_per_epoch,
                     n_train=len(train_idx), n_val=len(val_idx))
  do_resume = prepare_workdir(workdir, config_json, resume, overwrite)
  init = None
  if config.init_from and not do_resume:
    # Shapes are compared on an abstract init, so a mismatch errors before compiling anything.
    model = build_model(config.net, **kwargs)
    x = jax.ShapeDtypeStruct((1, *config.size, info.channels), jnp.float32)
    abstract = jax.eval_shape(
        lambda a, b: model.init(jax.random.PRNGKey(0), a, b, train=False), x, x)
    init = load_init(config.init_from, config)
    merge_init(dict(abstract), init[1], init[0], config, config.init_from)
  if jax.process_index() == 0:
    with ckpt.storage_guard(f"writing {ckpt.CONFIG_FILE}", workdir / ckpt.CHECKPOINT_DIR):
      workdir.mkdir(parents=True, exist_ok=True)
      (workdir / ckpt.CONFIG_FILE).write_text(dumps(config_json) + "\n")
  _sync("sljax-workdir-ready")
  return Setup(config, workdir, source, tuple(train_idx), tuple(val_idx), info, kwargs,
               do_resume, init)


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
          f"maxdisp {config.maxdisp}, {config.epochs} epochs x {steps_per_epoch} steps of "
          f"{config.batch_size} ({n_train} train / {n_val} val scenes) on "
          f"{jax.device_count()} {jax.default_backend()} device(s); estimated "
          f"~{_fmt_seconds(est)} per epoch (measured ETA in the progress bar)")


def _fmt_seconds(s: float) -> str:
  if s < 1:
    return "<1 s"
  if s < 90:
    return f"{s:.0f} s"
  if s < 5400:
    return f"{s / 60:.1f} min"
  return f"{s / 3600:.1f} h"


# ----------------------------------------------------------------------------- state


def create_train_state(run: Setup, model, tx) -> st.TrainState:
  """Fresh state: initial weights from the seed, then those of --init-from where given."""
  config = run.config
  variables = st.init_variables(model, config.seed, *config.size, run.info.channels)
  if run.init is not None:
    variables = merge_init(variables, run.init[1], run.init[0], config, config.init_from)
  return st.create_state(variables, tx)


def restore_checkpoint(manager, state: st.TrainState, sharding) -> tuple[st.TrainState,
                                                                           LoopState]:
  """The TrainState and LoopState of the manager's latest checkpoint."""
  step = manager.latest_step()
  abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding),
                          state)
  state, meta = ckpt.restore(manager, step, abstract)
  loop = LoopState.from_meta(meta)
  require(loop.step == int(state.step), f"{manager.directory}: checkpoint {step} is inconsistent")
  return state, loop


def _restart_logs(run: Setup, loop: LoopState) -> None:
  """Drops the log lines after the checkpoint resumed from (all of them for a fresh start)."""
  if jax.process_index() != 0:
    return
  spe = run.steps_per_epoch
  _truncate_jsonl(run.workdir / METRICS_FILE, lambda r: r.get("step", 0) <= loop.step)
  _truncate_jsonl(run.workdir / EPOCHS_FILE, lambda r: r.get("epoch", 0) <= loop.step // spe)


# ----------------------------------------------------------------------------- the loop


@dataclasses.dataclass(frozen=True)
class Context:
  """What the epoch functions share: the run, its compiled steps, data, logs and checkpoints."""
  run: Setup
  mesh: Any
  train_step: Any
  eval_step: Any
  train_rows: RowCache
  val_rows: RowCache
  manager: Any
  writer: MetricWriter
  bar: Any
  profiler: StepProfiler


def train_batches(ctx: Context, first_step: int) -> Iterator[dict[str, jax.Array]]:
  """Device batches of the global steps first_step + 1, ..., built ahead in the background."""
  run = ctx.run
  b, spe = run.config.batch_size, run.steps_per_epoch
  rows = stp.process_rows(b)

  @functools.lru_cache(maxsize=2)
  def order(epoch: int) -> list[int]:
    return epoch_order(run.train_idx, run.config.seed, epoch)

  def build(step: int) -> dict[str, jax.Array]:
    epoch, k = divmod(step, spe)
    idx = order(epoch)[k * b:(k + 1) * b]
    return stp.put_batch(ctx.train_rows.batch(idx[rows]), ctx.mesh)

  return prefetch(build, range(first_step, run.total_steps))


def fetch_metrics(ctx: Context, pending: list[tuple[int, Any]],
                  loop: LoopState) -> tuple[LoopState, dict[str, float]]:
  """Fetches the pending steps' metrics, checks them, logs a row per step and adds their
  losses to the epoch sums; returns the new LoopState and the last row."""
  config, spe = ctx.run.config, ctx.run.steps_per_epoch
  rows = []
  for step, m in zip([s for s, _ in pending], jax.device_get([m for _, m in pending])):
    m = {k: float(v) for k, v in m.items() if config.strategy == "unc" or not k.startswith("sigma")}
    if not math.isfinite(m["loss"]):
      ctx.writer.write(METRICS_FILE, rows)
      ctx.manager.wait_until_finished()
      good = ctx.manager.latest_step()
      raise TrainingDiverged(
          f"non-finite loss ({m['loss']}) at step {step} (epoch {(step - 1) // spe + 1}); "
          "stopped. " + (f"The last good checkpoint is step {good} in "
                         f"{ctx.run.workdir / ckpt.CHECKPOINT_DIR}" if good is not None
                         else "No checkpoint was saved yet") + "; try a lower --lr")
    rows.append({"step": step, "epoch": (step - 1) // spe + 1, **m})
    loop = loop.add_step(m["loss_sl"], m["loss_disp"])
  ctx.writer.write(METRICS_FILE, rows)
  ckpt.check(ctx.manager)  # a failed background save ends the run now, not an epoch later
  ctx.bar.set_postfix(epoch=rows[-1]["epoch"], loss=f"{rows[-1]['loss']:.4g}", refresh=False)
  ctx.bar.update(len(rows))
  return loop, rows[-1]


def save(ctx: Context, state: st.TrainState, loop: LoopState, val: float | None = None) -> None:
  """Starts an async checkpoint of the state with the loop state as its metadata."""
  ckpt.save(ctx.manager, loop.step, state, loop.to_meta(), val)


def run_epoch(ctx: Context, state: st.TrainState, loop: LoopState,
              batches: Iterator[dict[str, jax.Array]], stop_at: int
              ) -> tuple[st.TrainState, LoopState, dict[str, float]]:
  """The steps from loop.step to the end of its epoch (or stop_at); returns the new state,
  loop state and the last step's metrics row."""
  config, spe = ctx.run.config, ctx.run.steps_per_epoch
  weights = jnp.asarray(task_weights(config, loop.history))
  end = min((loop.step // spe + 1) * spe, stop_at)
  pending, last = [], {}
  for step in range(loop.step + 1, end + 1):
    ctx.profiler.before(step)
    state, m = ctx.train_step(state, next(batches), weights)
    ctx.profiler.after(step, state)
    pending.append((step, m))
    checkpoint = bool(config.save_every) and step % config.save_every == 0 and step % spe
    if len(pending) == config.log_every or step == end or checkpoint:
      loop, last = fetch_metrics(ctx, pending, loop)
      pending = []
    if checkpoint:
      save(ctx, state, loop)
  return state, loop, last


def end_of_epoch(ctx: Context, state: st.TrainState, loop: LoopState, last: dict[str, float],
                 seconds: float, samples: int) -> LoopState:
  """Closes the epoch: validation when due, its epochs.jsonl row and line, a checkpoint."""
  config = ctx.run.config
  loop = loop.close_epoch()
  epoch = len(loop.history)
  val: dict[str, float] = {}
  if epoch % config.val_every == 0 or loop.step == ctx.run.total_steps:
    val = validate_split(ctx, state)
    loop = loop.validated(val.get("val_mae"))
  rec = {"epoch": epoch, "step": loop.step, "loss_sl": loop.history[-1][0],
         "loss_disp": loop.history[-1][1], "w_sl": last["w_sl"], "w_disp": last["w_disp"],
         "samples_per_s": samples / max(seconds, 1e-9), "seconds": seconds}
  rec.update({k: last[k] for k in ("sigma_sl", "sigma_disp") if k in last})
  rec.update(val)
  ctx.writer.write(EPOCHS_FILE, [rec])
  needs_sl, needs_disp = config.tasks
  text = [f"L_sl {rec['loss_sl']:.4g}"] * needs_sl + [f"L_disp {rec['loss_disp']:.4g}"] * needs_disp
  if val.get("val_mae") is not None:
    text.append(f"val MAE {val['val_mae']:.3f} px")
  if val.get("val_sl") is not None:
    text.append(f"val L_sl {val['val_sl']:.4f}")
  ctx.bar.write(f"epoch {epoch}/{config.epochs}: {' '.join(text)} "
                f"({rec['samples_per_s']:.1f} samples/s)")
  save(ctx, state, loop, val.get("val_mae", val.get("val_sl")))
  return loop


@dataclasses.dataclass(frozen=True)
class RunResult:
  """What a finished (or stopped) run reports."""
  workdir: Path
  loop: LoopState

  @property
  def step(self) -> int:
    """Global steps done."""
    return self.loop.step

  @property
  def epochs_done(self) -> int:
    """Finished epochs."""
    return len(self.loop.history)

  @property
  def best_val(self) -> float | None:
    """Best validation MAE (px) so far."""
    return self.loop.best_val

  @property
  def last_val(self) -> float | None:
    """The last validation's MAE (px)."""
    return self.loop.last_val


def train(config: TrainConfig, workdir: str | os.PathLike | None = None, *, resume: bool = False,
          overwrite: bool = False, stop_after: int | None = None, preset_note: str = "",
          profile_dir: str | None = None, log: Callable[[str], None] = functools.partial(
              print, flush=True), progress: bool | Any | None = None) -> RunResult:
  """Runs (or resumes) training; every bad input raises SljaxError before any compilation.

  stop_after: stop once the global step reaches this value (as an interruption would; the last
  checkpoint is the one saved at or before it), for tests and for splitting long runs.
  progress: None (a bar on the main process), True/False, or a bar to drive: an object with
  tqdm's update(steps), set_postfix(**kw) and write(line), e.g. the experiment runner's.
  """
  workdir = Path(workdir if workdir is not None else default_workdir(config)).absolute()
  run = setup(config, workdir, resume, overwrite, log, preset_note)
  main_process = jax.process_index() == 0
  preflight.check_run(run.source, [(run.train_idx, batch_parts(config)), (
      run.val_idx, batch_parts(config, validation=run.info.has_disp))],
                      progress=progress is True or (progress is None and main_process))

  # ---- compiled steps and state
  mesh = stp.make_mesh()
  repl, _ = stp.shardings(mesh)
  drop = None if config.lr_drop_epoch is None else config.lr_drop_epoch * run.steps_per_epoch
  model, tx, train_step, eval_step = compiled_steps(
      config.net, tuple(sorted(run.kwargs.items())), config.maxdisp, config.disp_loss,
      config.lr, drop, config.precision, mesh, run.config.ynn)
  state = create_train_state(run, model, tx)
  manager = ckpt.make_manager(workdir / ckpt.CHECKPOINT_DIR, keep=config.keep)
  loop = LoopState()
  if run.resume:
    state, loop = restore_checkpoint(manager, state, repl)
    log(f"resuming from step {loop.step} (epoch {loop.step // run.steps_per_epoch + 1})")
  _restart_logs(run, loop)
  state = jax.device_put(state, repl)

  # ---- data and logs
  cache_ok = len(run.source) * bytes_per_scene(config, run.info.t) < _CACHE_BYTES
  own_bar = progress is None or isinstance(progress, bool)
  bar = tqdm(total=run.total_steps, initial=loop.step, unit="step", dynamic_ncols=True,
             disable=(not main_process) if progress is None else not progress,
             file=sys.stderr) if own_bar else progress
  ctx = Context(run=run, mesh=mesh, train_step=train_step, eval_step=eval_step,
                train_rows=RowCache(run.source, config, batch_parts(config),
                                    cache_ok and config.data is None),
                val_rows=RowCache(run.source, config,
                                  batch_parts(config, validation=run.info.has_disp), cache_ok),
                manager=manager, bar=bar,
                writer=MetricWriter(workdir, main_process, config.tensorboard, loop.step),
                profiler=StepProfiler(profile_dir, loop.step, log))
  stop_at = run.total_steps if stop_after is None else min(stop_after, run.total_steps)
  batches = train_batches(ctx, loop.step)

  # ---- epochs
  try:
    while loop.step < stop_at:
      t0, first = time.perf_counter(), loop.step
      state, loop, last = run_epoch(ctx, state, loop, batches, stop_at)
      if loop.step % run.steps_per_epoch == 0:
        loop = end_of_epoch(ctx, state, loop, last, time.perf_counter() - t0,
                            (loop.step - first) * config.batch_size)
    if loop.step < run.total_steps:
      bar.write(f"stopping at step {loop.step} as asked (--stop-after)")
    return RunResult(workdir, loop)
  finally:
    batches.close()
    ctx.profiler.close()
    if own_bar:
      bar.close()
    try:
      ctx.writer.close()
    finally:
      ckpt.finish(manager)


# ----------------------------------------------------------------------------- validation


def _gather(x: jax.Array) -> np.ndarray:
  if jax.process_count() == 1:
    return np.asarray(jax.device_get(x))
  from jax.experimental import multihost_utils  # pylint: disable=import-outside-toplevel
  return np.asarray(multihost_utils.process_allgather(x, tiled=True))


def validate_split(ctx: Context, state: st.TrainState) -> dict[str, float]:
  """Validation MAE (px, over valid GT) of the final disparity, and SL metrics for SL nets.

  For unet-sl the disparity comes from the predicted patterns by correlation (SPEC 2).
  """
  config, val_idx = ctx.run.config, ctx.run.val_idx
  b = config.batch_size
  disp_metrics = DisparityAccumulator()  # the same metrics as `sljax evaluate`
  sl_sum, sl_n = 0.0, 0
  rows = stp.process_rows(b)

  def load(start: int) -> tuple[int, dict[str, np.ndarray]]:
    idx = list(val_idx[start:start + b])
    n_real = len(idx)
    idx = idx + [idx[-1]] * (b - n_real)  # pad to the sharded batch size; padding ignored below
    return n_real, ctx.val_rows.batch(idx)

  for n_real, host in prefetch(load, range(0, len(val_idx), b)):
    out = ctx.eval_step(state.params, state.batch_stats,
                        stp.put_batch({k: v[rows] for k, v in host.items()}, ctx.mesh))
    out = {k: _gather(v)[:n_real] for k, v in out.items()}
    if "sl_logits" in out:
      logits, targets = out["sl_logits"], host["sl"][:n_real]
      if "sl_logits_right" in out:
        logits = np.concatenate([logits, out["sl_logits_right"]], -1)
        targets = np.concatenate([targets, host["sl_right"][:n_real]], -1)
      sl_sum += float(sl_loss(logits, targets)) * n_real
      sl_n += n_real
    if "disp" in host:
      if "disparity" in out:
        pred = out["disparity"]
      else:  # unet-sl: disparity from the predicted patterns by correlation (SPEC 2)
        probs = [np.asarray(jax.nn.sigmoid(out[k])) for k in ("sl_logits", "sl_logits_right")]
        pred = sl_disparity(*probs, window=config.corr_window)[0]
      gt = host["disp"][:n_real]
      # Scored where the training loss is: finite ground truth in [0, maxdisp).
      disp_metrics.add(pred, gt, mask=(gt >= 0) & (gt < config.maxdisp), name="validation")
  res = {}
  if disp_metrics.n_pixels:
    m = disp_metrics.result()
    res["val_mae"] = m["mae"]
    res["val_bad_3"] = m["bad_3"]
  if sl_n:
    res["val_sl"] = sl_sum / sl_n
  return res
