"""The training loop: data, validation, JSONL logs, checkpoints and exact resume.

Determinism: the data order of epoch e is a permutation drawn from (seed, e), the task weights
of epoch e depend only on the epoch-mean losses of epochs < e, and the step needs no PRNG
key, so the global step number alone fixes what a step computes. A resumed run restores the
state and loop bookkeeping of the last checkpoint and repeats exactly what the uninterrupted
run would have done.
"""

import dataclasses
import functools
import json
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from sljax.errors import SljaxError, require
from sljax.losses import weighting
from sljax.train import checkpoint as ckpt
from sljax.train.config import TrainConfig, diff_configs, dumps, validate

METRICS_FILE = "metrics.jsonl"
EPOCHS_FILE = "epochs.jsonl"
# Rough CPU seconds per training sample at 64x64 (maxdisp 32 for PSMNets) on a 2-core laptop,
# used only for the first line's estimate; the progress bar then shows the measured ETA.
_SEC_PER_SAMPLE_64 = {"psmnet": 0.11, "psmnet-mtl": 0.18, "unet-sl": 0.02, "unet-disp": 0.02}
_CACHE_BYTES = 2 << 30


class TrainingDiverged(SljaxError):
  """The loss became NaN or infinite."""


# ----------------------------------------------------------------------------- data


def open_source(config: TrainConfig):
  """The scene source: a scene-format folder or synthetic 'objects' scenes rendered on the fly."""
  if config.data is not None:
    from sljax.data.dataset import FolderSource  # pylint: disable=import-outside-toplevel
    return FolderSource(config.data)
  from sljax.data import synthetic  # pylint: disable=import-outside-toplevel
  synth_cfg = synthetic.SynthConfig(size=config.synth_size, domain="objects")
  return synthetic.SyntheticSource(config.synth_n, seed=config.seed, config=synth_cfg)


def batch_parts(config: TrainConfig, validation: bool = False) -> tuple[str, ...]:
  """Batch keys to load; validation of an SL network also loads disparity when it exists."""
  from sljax.train.step import BATCH_PARTS  # pylint: disable=import-outside-toplevel
  parts = BATCH_PARTS[config.net]
  if validation and "disp" not in parts:
    parts = parts + ("disp",)
  return parts


def check_source(source, config: TrainConfig) -> dict[str, Any]:
  """Checks the first scene has what the network trains on; returns {'t', 'channels', 'has_disp'}."""
  require(len(source) > 0, f"{config.data or 'synthetic data'}: no scenes")
  scene = source[0]
  where = config.data or "synthetic data"
  name = getattr(source, "name", None)
  label = name(0) if callable(name) else scene.name
  needs_sl, needs_disp = config.tasks
  if needs_disp:
    require(scene.disp0 is not None,
            f"{where}: scene {label} has no disparity (disp0.pfm), which model {config.net} "
            f"trains on")
  if needs_sl:
    require(scene.sl0 is not None,
            f"{where}: scene {label} has no structured-light patterns (sl0/), which model "
            f"{config.net} trains on")
  if config.net == "unet-sl":
    require(scene.sl1 is not None,
            f"{where}: scene {label} has no right-view patterns (sl1/), which unet-sl trains on")
  t = None if scene.sl0 is None else int(scene.sl0.shape[-1])
  return {"t": t, "channels": 1 if config.use_gray else 3, "has_disp": scene.disp0 is not None}


class RowCache:
  """Per-scene resized rows kept in RAM (the quick preset revisits every scene each epoch)."""

  def __init__(self, source, config: TrainConfig, parts: Sequence[str], enabled: bool):
    self.source, self.config, self.parts, self.enabled = source, config, tuple(parts), enabled
    self.rows: dict[int, dict[str, np.ndarray]] = {}

  def batch(self, indices: Sequence[int]) -> dict[str, np.ndarray]:
    """Stacked batch of the given scene indices (resized to config.size)."""
    from sljax.data.dataset import load_batch  # pylint: disable=import-outside-toplevel
    if not self.enabled:
      return load_batch(self.source, list(indices), size=self.config.size,
                        gray=self.config.use_gray, parts=self.parts)
    missing = [i for i in indices if i not in self.rows]
    if missing:
      loaded = load_batch(self.source, missing, size=self.config.size,
                          gray=self.config.use_gray, parts=self.parts)
      for k, i in enumerate(missing):
        self.rows[i] = {p: loaded[p][k] for p in self.parts}
    return {p: np.stack([self.rows[i][p] for i in indices]) for p in self.parts}


def bytes_per_scene(config: TrainConfig, t: int | None) -> int:
  """Approximate RAM of one cached resized scene."""
  h, w = config.size
  c = 1 if config.use_gray else 3
  return 4 * h * w * (2 * c + 2 + 2 * (t or 0))


def epoch_order(train_idx: Sequence[int], seed: int, epoch: int) -> list[int]:
  """Scene order of an epoch: a permutation drawn from (seed, epoch) only."""
  perm = np.random.default_rng([seed, epoch]).permutation(len(train_idx))
  return [int(train_idx[k]) for k in perm]


# ----------------------------------------------------------------------------- model


def model_kwargs(config: TrainConfig, channels: int, t: int | None) -> dict[str, Any]:
  """Keyword arguments of sljax.nets.build_model for this run."""
  kw: dict[str, Any] = {"in_channels": channels}
  if config.net.startswith("psmnet"):
    kw["maxdisp"] = config.maxdisp
  if config.net in ("psmnet-mtl", "unet-sl"):
    kw["t"] = t
  if config.net.startswith("unet"):
    kw["depth"], kw["base_width"] = config.unet_depth, config.unet_width
  return kw


@functools.lru_cache(maxsize=8)
def compiled_steps(net: str, kwargs: tuple[tuple[str, Any], ...], maxdisp: int, disp_loss: str,
                   lr: float, mesh) -> tuple[Any, Any, Any, Any]:
  """(model, optimiser, train step, eval step), memoised so runs in one process share the
  compiled steps (tests, notebooks, a resume in the same process)."""
  # pylint: disable=import-outside-toplevel
  from sljax.nets import build_model
  from sljax.train import state as st
  from sljax.train import step as stp
  model = build_model(net, **dict(kwargs))
  tx = st.make_optimizer(lr)
  return (model, tx,
          stp.make_train_step(model, net=net, maxdisp=maxdisp, disp_loss=disp_loss, tx=tx,
                              mesh=mesh),
          stp.make_eval_step(model, net=net, mesh=mesh))


def _flatten(tree: Any) -> dict[tuple[str, ...], Any]:
  out = {}
  def walk(node, path):
    if isinstance(node, dict) or hasattr(node, "items"):
      for k, v in node.items():
        walk(v, path + (str(k),))
    else:
      out[path] = node
  walk(tree, ())
  return out


def _unflatten(flat: dict[tuple[str, ...], Any]) -> dict[str, Any]:
  root: dict[str, Any] = {}
  for path, v in flat.items():
    node = root
    for k in path[:-1]:
      node = node.setdefault(k, {})
    node[path[-1]] = v
  return root


def load_init(path: str, config: TrainConfig) -> tuple[str, dict[str, Any]]:
  """(source net name, variables) of an --init-from checkpoint/converted PSMNet."""
  name, _, variables, _ = ckpt.load_for_inference(path)
  if config.net == "psmnet" and name == "psmnet-mtl":
    from sljax.nets import detach_sl  # pylint: disable=import-outside-toplevel
    variables, name = detach_sl(variables), "psmnet"
  return name, variables


def merge_init(target: dict[str, Any], source: dict[str, Any], source_name: str,
               config: TrainConfig, where: str) -> dict[str, Any]:
  """Target variables with every leaf the source has replaced; SljaxError on any mismatch.

  Leaves only the target has (the twin's SL path when starting from a plain PSMNet) keep their
  initial values; a source leaf missing from the target or of another shape is an error.
  """
  out = {}
  for col in ("params", "batch_stats"):
    tflat = _flatten(target.get(col, {}))
    sflat = _flatten(source.get(col, {}))
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
    out[col] = _unflatten(merged) if merged else {}
  return out


# ----------------------------------------------------------------------------- workdir


def default_workdir(config: TrainConfig) -> Path:
  """runs/<model>-<strategy>-<seed> (UNets: runs/<model>-<seed>)."""
  name = (f"{config.model}-{config.strategy}-{config.seed}" if config.model == "psmnet"
          else f"{config.model}-{config.seed}")
  return Path("runs") / name


def prepare_workdir(workdir: Path, config_json: dict[str, Any], resume: bool,
                    overwrite: bool) -> bool:
  """Checks the workdir against the run; returns whether there is a checkpoint to resume."""
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
  if overwrite:
    for name in (ckpt.CHECKPOINT_DIR,):
      shutil.rmtree(workdir / name, ignore_errors=True)
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


def _finite(x: float) -> float | None:
  return float(x) if math.isfinite(float(x)) else None


# ----------------------------------------------------------------------------- main loop


@dataclasses.dataclass
class RunResult:
  """What a finished (or stopped) run reports."""
  workdir: Path
  step: int
  epochs_done: int
  best_val_mae: float | None
  last_val_mae: float | None
  history: list[list[float]]


def announce(config: TrainConfig, preset_note: str, steps_per_epoch: int,
             n_train: int, n_val: int) -> str:
  """The first output line: preset, run shape and the estimated time per epoch."""
  h, w = config.size
  scale = (h * w) / (64 * 64)
  if config.net.startswith("psmnet"):
    scale *= (0.5 + 0.5 * config.maxdisp / 32)
  per_sample = _SEC_PER_SAMPLE_64[config.net] * scale
  if jax.default_backend() != "cpu":
    per_sample /= 100.0
  est = per_sample * steps_per_epoch * config.batch_size
  return (f"sljax train: preset {config.preset}{preset_note}: {config.net}"
          f"{'/' + config.strategy if config.model == 'psmnet' else ''}, {h}x{w}, maxdisp "
          f"{config.maxdisp}, {config.epochs} epochs x {steps_per_epoch} steps of "
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


def train(config: TrainConfig, workdir: str | os.PathLike | None = None, *, resume: bool = False,
          overwrite: bool = False, stop_after: int | None = None, preset_note: str = "",
          log: Callable[[str], None] = functools.partial(print, flush=True), progress: bool | None = None) -> RunResult:
  """Runs (or resumes) training; every bad input raises SljaxError before any compilation.

  stop_after: stop once the global step reaches this value (as an interruption would; the last
  checkpoint is the one saved at or before it), for tests and for splitting long runs.
  """
  # pylint: disable=import-outside-toplevel
  from sljax.data.dataset import split_indices, take_fraction
  from sljax.nets import build_model
  from sljax.train import state as st
  from sljax.train import step as stp

  validate(config)
  workdir = Path(workdir if workdir is not None else default_workdir(config)).absolute()
  main_process = jax.process_index() == 0
  n_dev = jax.device_count()
  require(config.batch_size % n_dev == 0,
          f"--batch-size {config.batch_size}: must be a multiple of the {n_dev} devices")
  require(config.batch_size % jax.process_count() == 0,
          f"--batch-size {config.batch_size}: must be a multiple of the {jax.process_count()} processes")

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
  total_steps = steps_per_epoch * config.epochs
  log(announce(config, preset_note, steps_per_epoch, len(train_idx), len(val_idx)))
  info = check_source(source, config)

  kwargs = model_kwargs(config, info["channels"], info["t"])
  config_json = dict(config.to_json(), net=config.net, model_kwargs=kwargs, t=info["t"],
                     gray=config.use_gray, steps_per_epoch=steps_per_epoch,
                     n_train=len(train_idx), n_val=len(val_idx))
  do_resume = prepare_workdir(workdir, config_json, resume, overwrite)
  model = build_model(config.net, **kwargs)
  h, w = config.size
  init_vars = None
  if config.init_from and not do_resume:
    # Shapes are compared on an abstract init, so a mismatch errors before compiling anything.
    x = jax.ShapeDtypeStruct((1, h, w, info["channels"]), jnp.float32)
    abstract = jax.eval_shape(
        lambda a, b: model.init(jax.random.PRNGKey(0), a, b, train=False), x, x)
    src_name, src_vars = load_init(config.init_from, config)
    merge_init(dict(abstract), src_vars, src_name, config, config.init_from)
    init_vars = src_vars

  if main_process:
    workdir.mkdir(parents=True, exist_ok=True)
    (workdir / ckpt.CONFIG_FILE).write_text(dumps(config_json) + "\n")

  # ---- state
  mesh = stp.make_mesh()
  repl, _ = stp.shardings(mesh)
  model, tx, train_step, eval_step = compiled_steps(
      config.net, tuple(sorted(kwargs.items())), config.maxdisp, config.disp_loss, config.lr,
      mesh)
  variables = st.init_variables(model, config.seed, h, w, info["channels"])
  if init_vars is not None:
    variables = merge_init(variables, init_vars, "", config, config.init_from)
  state = st.create_state(variables, tx)
  manager = ckpt.make_manager(workdir / ckpt.CHECKPOINT_DIR, keep=config.keep)
  history: list[list[float]] = []
  partial = [0.0, 0.0, 0]
  best_val: float | None = None
  start_step = 0
  if do_resume:
    last = manager.latest_step()
    abstract_state = jax.tree.map(
        lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=repl), state)
    state, meta = ckpt.restore(manager, last, abstract_state)
    history = [list(map(float, e)) for e in meta["history"]]
    partial = list(meta["partial"])
    best_val = meta.get("best_val")
    start_step = int(meta["step"])
    require(start_step == int(state.step), f"{workdir}: checkpoint {last} is inconsistent")
    log(f"resuming from step {start_step} (epoch {start_step // steps_per_epoch + 1})")
    if main_process:
      _truncate_jsonl(workdir / METRICS_FILE, lambda r: r.get("step", 0) <= start_step)
      _truncate_jsonl(workdir / EPOCHS_FILE,
                      lambda r: r.get("epoch", 0) <= start_step // steps_per_epoch)
  elif main_process:
    # A fresh start (possibly of a run killed before its first checkpoint): no stale lines.
    for name in (METRICS_FILE, EPOCHS_FILE):
      (workdir / name).unlink(missing_ok=True)
  state = jax.device_put(state, repl)

  cache_ok = len(source) * bytes_per_scene(config, info["t"]) < _CACHE_BYTES
  train_rows = RowCache(source, config, batch_parts(config), cache_ok and config.data is None)
  val_rows = RowCache(source, config, batch_parts(config, validation=info["has_disp"]),
                      cache_ok)
  rows = stp.process_rows(config.batch_size)

  def save(step: int, val_mae: float | None):
    meta = {"step": step, "history": history, "partial": partial, "best_val": best_val}
    ckpt.save(manager, step, state, meta, val_mae)

  metrics_f = open(workdir / METRICS_FILE, "a") if main_process else None
  epochs_f = open(workdir / EPOCHS_FILE, "a") if main_process else None
  from tqdm import tqdm  # pylint: disable=import-outside-toplevel
  bar = tqdm(total=total_steps, initial=start_step, unit="step", dynamic_ncols=True,
             disable=(not main_process) if progress is None else not progress, file=sys.stderr)
  last_val: float | None = None
  step = start_step
  try:
    while step < total_steps:
      epoch = step // steps_per_epoch
      k0 = step % steps_per_epoch
      order = epoch_order(train_idx, config.seed, epoch)
      weights = jnp.asarray(task_weights(config, history))
      t_epoch, n_samples = time.perf_counter(), 0
      for k in range(k0, steps_per_epoch):
        idx = order[k * config.batch_size:(k + 1) * config.batch_size]
        batch = stp.put_batch(train_rows.batch(idx[rows]), mesh)
        state, m = train_step(state, batch, weights)
        m = {key: float(v) for key, v in jax.device_get(m).items()
             if config.strategy == "unc" or not key.startswith("sigma")}
        step += 1
        n_samples += config.batch_size
        if not math.isfinite(m["loss"]):
          manager.wait_until_finished()
          good = manager.latest_step()
          raise TrainingDiverged(
              f"non-finite loss ({m['loss']}) at step {step} (epoch {epoch + 1}); stopped. "
              + (f"The last good checkpoint is step {good} in {workdir / ckpt.CHECKPOINT_DIR}"
                 if good is not None else "No checkpoint was saved yet")
              + "; try a lower --lr")
        partial[0] += m["loss_sl"]
        partial[1] += m["loss_disp"]
        partial[2] += 1
        if metrics_f:
          metrics_f.write(json.dumps({"step": step, "epoch": epoch + 1, **m}) + "\n")
        bar.set_postfix(epoch=epoch + 1, loss=f"{m['loss']:.4g}", refresh=False)
        bar.update(1)
        end_of_epoch = k == steps_per_epoch - 1
        if end_of_epoch:
          history.append([partial[0] / partial[2], partial[1] / partial[2]])
          partial = [0.0, 0.0, 0]
          elapsed = time.perf_counter() - t_epoch
          val = None
          if (epoch + 1) % config.val_every == 0 or step == total_steps:
            val = validate_split(eval_step, state, val_rows, val_idx, config, mesh, info)
            last_val = val.get("val_mae")
            if last_val is not None and (best_val is None or last_val < best_val):
              best_val = last_val
          if metrics_f:
            metrics_f.flush()
          rec = {"epoch": epoch + 1, "step": step, "loss_sl": history[-1][0],
                 "loss_disp": history[-1][1], "w_sl": m["w_sl"], "w_disp": m["w_disp"],
                 "samples_per_s": n_samples / max(elapsed, 1e-9), "seconds": elapsed}
          for key in ("sigma_sl", "sigma_disp"):
            if key in m:
              rec[key] = m[key]
          if val:
            rec.update(val)
          if epochs_f:
            epochs_f.write(json.dumps(rec) + "\n")
            epochs_f.flush()
          mae_txt = "" if not val or val.get("val_mae") is None else f" val MAE {val['val_mae']:.3f} px"
          sl_txt = "" if not val or val.get("val_sl") is None else f" val L_sl {val['val_sl']:.4f}"
          needs_sl, needs_disp = config.tasks
          loss_txt = " ".join(t for t, keep in ((f"L_sl {history[-1][0]:.4g}", needs_sl),
                                                (f"L_disp {history[-1][1]:.4g}", needs_disp)) if keep)
          bar.write(f"epoch {epoch + 1}/{config.epochs}: {loss_txt}{mae_txt}{sl_txt} "
                    f"({rec['samples_per_s']:.1f} samples/s)")
          save(step, None if not val else val.get("val_mae", val.get("val_sl")))
        elif config.save_every and step % config.save_every == 0:
          save(step, None)
        if stop_after is not None and step >= stop_after:
          bar.write(f"stopping at step {step} as asked (--stop-after)")
          return RunResult(workdir, step, len(history), best_val, last_val, history)
    return RunResult(workdir, step, len(history), best_val, last_val, history)
  finally:
    bar.close()
    manager.wait_until_finished()
    manager.close()
    for f in (metrics_f, epochs_f):
      if f:
        f.close()


def task_weights(config: TrainConfig, history: Sequence[Sequence[float]]) -> np.ndarray:
  """The step's [w_sl, w_disp, unc] for the next epoch (UNets: their single task)."""
  if config.net == "unet-sl":
    return np.array([1.0, 0.0, 0.0], np.float32)
  if config.net == "unet-disp":
    return np.array([0.0, 1.0, 0.0], np.float32)
  return weighting.step_weights(config.strategy, history)


def _gather(x: jax.Array) -> np.ndarray:
  if jax.process_count() == 1:
    return np.asarray(jax.device_get(x))
  from jax.experimental import multihost_utils  # pylint: disable=import-outside-toplevel
  return np.asarray(multihost_utils.process_allgather(x, tiled=True))


def validate_split(eval_step, state, rows: RowCache, val_idx: Sequence[int], config: TrainConfig,
                   mesh, info: dict[str, Any]) -> dict[str, float]:
  """Validation MAE (px, over valid GT) of the final disparity, and SL metrics for SL nets.

  For unet-sl the disparity comes from the predicted patterns by correlation (SPEC 2).
  """
  # pylint: disable=import-outside-toplevel
  from sljax.losses.sl import sl_loss
  from sljax.metrics import DisparityAccumulator
  from sljax.train import step as stp
  b = config.batch_size
  disp_metrics = DisparityAccumulator()  # the same metrics as `sljax evaluate`
  sl_sum, sl_n = 0.0, 0
  rows_slice = stp.process_rows(b)
  for start in range(0, len(val_idx), b):
    idx = list(val_idx[start:start + b])
    n_real = len(idx)
    idx = idx + [idx[-1]] * (b - n_real)  # pad to the sharded batch size; padding ignored below
    host = rows.batch(idx)
    out = eval_step(state.params, state.batch_stats, stp.put_batch(
        {k: v[rows_slice] for k, v in host.items()}, mesh))
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
        from sljax.corr.correlation import sl_disparity
        probs = [np.asarray(jax.nn.sigmoid(out[k])) for k in ("sl_logits", "sl_logits_right")]
        pred = sl_disparity(*probs)[0]
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
