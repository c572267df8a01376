"""The training loop: one `for step` loop with periodic work gated by the step number.

Reading order: `train` sets the run up (sljax.train.setup: options, data, split, workdir),
makes the state (`create_train_state`, or `restore_checkpoint` to resume), then runs the global
steps. After a step, gates open by step number: fetch and log the step metrics, checkpoint
(--save-every), and at an epoch's end validate, write the epoch row, checkpoint and compute the
next epoch's task weights (DWA). The rooms around it: feed (batches), workdir (files on disk),
validate (the held-out split), state (TrainState, LoopState), step (the compiled steps).

Determinism: the data order of epoch e is a permutation drawn from (seed, e), the task weights
of epoch e depend only on the epoch-mean losses of epochs < e, and the step needs no PRNG
key, so the global step number alone fixes what a step computes. A resumed run restores the
state and LoopState of the last checkpoint and repeats exactly what the uninterrupted run
would have done.

Step metrics stay on the device and are fetched every `log_every` steps and before every
checkpoint, so the host never waits for a step before dispatching the next one; the NaN check
runs at each fetch, and every step still gets its row in metrics.jsonl.
"""

import dataclasses
import functools
import os
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from sljax.losses import weighting
from sljax.models import checkpoint as ckpt
from sljax.nets import registry
from sljax.nets.model_config import ModelConfig, init_variables, variable_shapes
from sljax.runtime import choices, kept_programs
from sljax.train import state as st
from sljax.train import step as stp
from sljax.train.config import TrainConfig, with_absolute_paths
from sljax.train.feed import open_source, row_caches, train_batches
from sljax.train.interrupt import deferred_interrupt
from sljax.train.profiler import StepProfiler, check_profile_dir
from sljax.train.record import (Recorder, fetch_metrics, rate_after_first_step, save, write_epoch,
                                write_validation)
from sljax.train.resume import fresh_start_note, open_manager, restore_checkpoint
from sljax.train.setup import Setup, merge_init, setup
from sljax.train.state import LoopState
from sljax.train.validate import validate_split
from sljax.train.workdir import (MetricWriter, clear_run, default_workdir, held, restart_logs,
                                 write_config)

__all__ = ["RunResult", "compiled_steps", "create_train_state", "first_step_origin",
           "task_weights", "train"]


# ----------------------------------------------------------------------------- compiled steps


@functools.lru_cache(maxsize=8)
def compiled_steps(model_config: ModelConfig, disp_loss: str, lr: float,
                   lr_drop_step: int | None, mesh, ynn: str = "on") -> tuple[Any, Any, Any, Any]:
  """(model, optimiser, train step, eval step), memoised so runs in one process share the
  compiled steps (tests, notebooks, experiment grids, a resume in the same process); the key
  holds everything that changes a program (the model config with its kernels, and `ynn`, the
  resolved --ynn: sljax.runtime.choices's XLA compiler options)."""
  model = model_config.build()
  choice = choices.KernelChoice.from_name(ynn)
  # Where a command line turned it on, a later run loads the compiled steps instead of
  # tracing, lowering and compiling them (sljax.runtime.kept_programs); each description holds what
  # changes its program beyond the arguments' shapes.
  grad_block_values = choices.grad_blocks_for(choice)
  train = (model_config, disp_loss, lr, lr_drop_step, choice.compiler_options("train"),
           grad_block_values, repr(mesh))
  tx = st.make_optimizer(lr, lr_drop_step)
  # One program for the optimiser's zeros: run op by op it dispatched (and compiled) a
  # zeros_like per parameter leaf, about 1.5 s of a warm start on a 2-core CPU.
  tx = tx._replace(init=kept_programs.Program(jax.jit(tx.init), "optimizer-init",
                                            (lr, lr_drop_step)))
  return (model, tx,
          kept_programs.Program(stp.make_train_step(
              model, model_config, disp_loss=disp_loss, tx=tx, mesh=mesh,
              compiler_options=choice.compiler_options("train"),
              grad_block_values=grad_block_values), "train-step", train).prefetch(),
          kept_programs.Program(stp.make_eval_step(
              model, model_config, mesh=mesh, compiler_options=choice.compiler_options("forward")),
              "eval-step", (model_config, choice.compiler_options("forward"), repr(mesh))))


def step_shapes(run: Setup, model, tx, rows) -> tuple:
  """The training step's arguments (state, batch, weights) as shapes and dtypes, so that its
  program can be compiled while the state is initialised (`kept_programs.Program.ahead`); the
  batch's from one of the run's scenes (`rows` caches it for the first batch)."""
  config = run.config
  variables = variable_shapes(model, *config.size, run.info.channels)
  state = jax.eval_shape(lambda v: st.create_state(v, tx), variables)
  one = rows.batch([run.train_idx[0]])
  batch = {k: jax.ShapeDtypeStruct((config.batch_size, *v.shape[1:]), v.dtype)
           for k, v in one.items()}
  weights = jax.ShapeDtypeStruct((len(registry.TASKS) + 1,), jnp.float32)
  return state, batch, weights


def first_step_origin(train_step) -> str:
  """How the first step's program came, for the progress bar."""
  origin = getattr(train_step, "origin", None)
  if origin == "loaded":
    return "loaded the compiled step"
  return "compiling, or loading from the compile cache"


def task_weights(config: TrainConfig, history: Sequence[Sequence[float]]) -> np.ndarray:
  """The step's [w_sl, w_disp, unc] for the next epoch (single-task nets: their one task)."""
  if config.spec.multi_task:
    return weighting.step_weights(config.strategy, history)
  return np.array([float(t in config.spec.tasks) for t in registry.TASKS] + [0.0], np.float32)


# ----------------------------------------------------------------------------- state


def create_train_state(run: Setup, model, tx) -> st.TrainState:
  """Fresh state: initial weights from the seed, then those of --init-from where given."""
  config = run.config
  variables = init_variables(model, config.seed, *config.size, run.info.channels)
  if run.init is not None:
    variables = merge_init(variables, run.init[1], run.init[0], config, config.init_from)
  return st.create_state(variables, tx)


@dataclasses.dataclass(frozen=True)
class RunResult:
  """What a finished (or stopped) run reports: its workdir, final LoopState and whether `stop`
  ended it early."""
  workdir: Path
  loop: LoopState
  stopped: bool = False
  step = property(lambda self: self.loop.step, doc="Global steps done.")
  epochs_done = property(lambda self: len(self.loop.history), doc="Finished epochs.")
  best_val = property(lambda self: self.loop.best_val, doc="Best validation MAE (px) so far.")
  last_val = property(lambda self: self.loop.last_val, doc="The last validation's MAE (px).")


# ----------------------------------------------------------------------------- train


def train(config: TrainConfig, workdir: str | os.PathLike | None = None, *, resume: bool = False,
          overwrite: bool = False, stop_after: int | None = None, preset_note: str = "",
          profile_dir: str | None = None, log: Callable[[str], None] = functools.partial(
              print, flush=True), progress: bool | Any | None = None,
          stop: Callable[[], bool] | None = None, skip_damaged: bool = False) -> RunResult:
  """Runs (or resumes) training; every bad input raises SljaxError before any compilation.

  stop_after: stop once the global step reaches this value (the last checkpoint is the one
  saved at or before it, as after a crash), for tests and for splitting long runs.
  stop: asked after every step (a worker's stop signal); when it says True, the run saves a
  checkpoint at that step, as a Ctrl-C does, and returns with `stopped` set.
  progress: None (a bar on the main process), True/False, or a bar to drive: an object with
  tqdm's update(steps), set_postfix(**kw) and write(line), e.g. the experiment runner's.
  skip_damaged: a resume whose newest checkpoint is damaged moves it aside (WORKDIR/
  checkpoints/N.damaged, said in a line) and resumes from the newest intact one; without it
  a damaged checkpoint is refused (SljaxError naming it).
  """
  workdir = Path(workdir if workdir is not None else default_workdir(config)).absolute()
  # One run per workdir: a second process (the run started again while it still goes on)
  # would interleave the logs and checkpoints of both.
  with held(workdir, f"sljax train ({config.net})"):
    return _train(config, workdir, resume, overwrite, stop_after, preset_note, profile_dir, log,
                  progress, stop, skip_damaged)


def _train(config: TrainConfig, workdir: Path, resume: bool, overwrite: bool,
           stop_after: int | None, preset_note: str, profile_dir: str | None,
           log: Callable[[str], None], progress: bool | Any | None,
           stop: Callable[[], bool] | None, skip_damaged: bool = False) -> RunResult:
  """train() once its workdir is held."""
  config = with_absolute_paths(config)  # config.json names the folders from anywhere
  check_profile_dir(profile_dir)
  main_process = jax.process_index() == 0
  run = setup(config, workdir, resume, overwrite, log, preset_note, source=open_source(config),
              progress=progress is True or (progress is None and main_process))
  spe = run.steps_per_epoch
  if overwrite:
    clear_run(workdir)  # only now: a run refused by its checks leaves the old one whole

  mesh = stp.make_mesh()
  repl, _ = stp.shardings(mesh)
  drop = None if config.lr_drop_epoch is None else config.lr_drop_epoch * spe
  model, tx, train_step, eval_step = compiled_steps(run.model, config.disp_loss, config.lr,
                                                    drop, mesh, run.config.ynn)
  train_rows, val_rows = row_caches(run.source, config, run.info)
  if (kept_programs.folder() is not None and jax.process_count() == 1
      and not getattr(train_step, "prefetching", True)):
    # Nothing kept to load: XLA compiles the step on another core while the state is made (the
    # same program as the first call's would be), and keeps it.
    train_step.ahead(*step_shapes(run, model, st.make_optimizer(config.lr, drop), train_rows))
  state = create_train_state(run, model, tx)
  manager = open_manager(workdir / ckpt.CHECKPOINT_DIR, config.keep, run.resume and skip_damaged,
                         log)
  loop = LoopState()
  if run.resume:
    state, loop = restore_checkpoint(manager, state, repl, skip_damaged, log)
    log(f"resuming from step {loop.step} (epoch {loop.step // spe + 1})")
  elif resume and not overwrite and fresh_start_note(workdir):
    log(fresh_start_note(workdir))
  # Only now, so that a new run stopped by its checks leaves no config.json (and a corrected
  # rerun is not refused as "another run").
  write_config(workdir, run.config_json)
  restart_logs(workdir, loop.step, spe)
  state = jax.device_put(state, repl)

  batches = train_batches(train_rows, run.train_idx, config, spe, loop.step, run.total_steps,
                          mesh)
  own_bar = progress is None or isinstance(progress, bool)
  bar = tqdm(total=run.total_steps, initial=loop.step, unit="step", dynamic_ncols=True,
             disable=(not main_process) if progress is None else not progress,
             file=sys.stderr) if own_bar else progress
  by_steps = config.val_every_steps is not None
  rec = Recorder(run, MetricWriter(workdir, main_process, config.tensorboard, loop.step,
                                   by_steps), manager, bar)
  profiler = StepProfiler(profile_dir, loop.step, log)
  stop_at = run.total_steps if stop_after is None else min(stop_after, run.total_steps)
  weights = jnp.asarray(task_weights(config, loop.history))
  pending, last, clock = [], {}, (time.perf_counter(), loop.step)
  with deferred_interrupt() as interrupt:  # Ctrl-C: stop after the step (sljax.train.interrupt)
    try:
      first = loop.step + 1
      for step in range(first, stop_at + 1):
        profiler.before(step)
        if step == first:  # the bar would sit at 0 while XLA compiles (77 s on an H100)
          bar.set_postfix(status="compiling the training step", refresh=True)
          t_first = time.perf_counter()
        state, metrics = train_step(state, next(batches), weights)
        if step == first:
          bar.set_postfix(status=f"first step ({first_step_origin(train_step)}) "
                                 f"{time.perf_counter() - t_first:.0f} s", refresh=True)
          rate_after_first_step(bar)
        profiler.after(step, state)
        pending.append((step, metrics))
        final = step == run.total_steps
        # A --steps budget may end part-way through an epoch: that short epoch ends the run.
        epoch_end = step % spe == 0 or final
        validation = (step % config.val_every_steps == 0 or final) if by_steps else False
        saved_anyway = validation or (epoch_end and not by_steps)
        checkpoint = bool(config.save_every) and step % config.save_every == 0 and not saved_anyway
        if (len(pending) == config.log_every or epoch_end or validation or step == stop_at
            or checkpoint):
          loop, last = fetch_metrics(rec, pending, loop)
          pending = []
        if checkpoint:
          save(rec, state, loop)
        if epoch_end:
          loop = loop.close_epoch()
          val: dict[str, float] = {}
          if not by_steps and (len(loop.history) % config.val_every == 0 or final):
            val = validate_split(state, eval_step, val_rows, run.val_idx, config, mesh)
            loop = loop.validated(val.get("val_mae"))
          write_epoch(rec, loop, last, val, time.perf_counter() - clock[0],
                      (step - clock[1]) * config.batch_size)
          if not by_steps:  # by steps, the validations checkpoint (an epoch may be one step)
            save(rec, state, loop, val.get("val_mae", val.get("val_sl")))
          weights = jnp.asarray(task_weights(config, loop.history))  # DWA: from finished epochs
          clock = time.perf_counter(), step
        if validation:
          val = validate_split(state, eval_step, val_rows, run.val_idx, config, mesh)
          write_validation(rec, loop, val)
          loop = loop.validated(val.get("val_mae"))
          save(rec, state, loop, val.get("val_mae", val.get("val_sl")))
        asked = stop is not None and not final and stop()
        if interrupt.asked or asked:  # after the step's own writes, between two steps
          if not (saved_anyway or checkpoint):  # keep this step: nothing is trained twice
            if pending:
              loop, last = fetch_metrics(rec, pending, loop)
              pending = []
            save(rec, state, loop)
          if interrupt.asked:
            raise KeyboardInterrupt
          bar.write(f"stopping at step {loop.step} as asked; its checkpoint is saved")
          return RunResult(workdir, loop, stopped=True)
      if loop.step < run.total_steps:
        bar.write(f"stopping at step {loop.step} as asked (--stop-after)")
      return RunResult(workdir, loop)
    finally:
      batches.close()
      profiler.close()
      if own_bar:
        bar.close()
      try:
        rec.writer.close()
      finally:
        ckpt.finish(manager)
