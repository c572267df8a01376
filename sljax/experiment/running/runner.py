"""The experiment runner: trains and scores every cell of a plan under OUT, resumably.

What it writes where: sljax.experiment.records. Idempotent and resumable: a cell with done.json is not trained again, one with checkpoints
continues exactly (train's --resume), an evaluation already written is not redone. A cell
whose spec changed under an existing OUT is refused, never mixed in. Cells are scored with
their final checkpoint (the last step), not the best by validation: in v1 validation uses the
held-out split that is also scored, and choosing on it would leak the test set into the
result. In v2 the held-out split is validation only (the window is chosen there) and the
score comes from a fixed test set, touched once per cell. v3 also scores each cell's best
checkpoint by validation MAE (what early stopping would give) as a secondary set. A finished
cell keeps its final checkpoint (and that best one) only, about 55-85 MB for a PSMNet at the
cpu scale.
"""

import dataclasses
import json
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tqdm import tqdm

from sljax import inference
from sljax.data.dataset import FolderSource, parse_fraction, split_indices
from sljax.errors import require
from sljax.evaluation.scoring import evaluate, json_safe
from sljax.experiment.design.cells import (FIXED, HELDOUT, TEST_SEED, Cell, EvalSet, Plan,
                                           waits_for)
from sljax.experiment.design.plans import describe
from sljax.experiment.records import (DIVERGED_FILE, DONE_FILE, EVAL_DIR, LOG_FILE, WINDOWS_FILE,
                                      cell_dir, eval_record, final_checkpoint, read_done, read_json,
                                      register, write_eval, write_json)
from sljax.experiment.running import workers
from sljax.models import checkpoint as ckpt
from sljax.models import load as trained
from sljax.render.synthetic import SynthConfig, SyntheticSource
from sljax.runtime import choices, machine
from sljax.train.config import config_from_json
from sljax.train.feed import open_source
from sljax.train.loop import train
from sljax.train.record import TrainingDiverged

# ----------------------------------------------------------------------------- cost estimates


def _seconds_per_step(cell: Cell) -> float:
  """A rough CPU cost per training step, used to weigh the progress bar across cells."""
  config = cell.config
  h, w = config.size
  scale = h * w / (64 * 64)
  if "maxdisp" in config.spec.options:
    scale *= 0.5 + 0.5 * config.maxdisp / 32
  return config.spec.sec_per_sample_64 * scale * config.batch_size


def _n_train(cell: Cell) -> int:
  source = open_source(cell.config)
  return len(split_indices(source, cell.config.test_fraction, seed=cell.config.seed)[0])


def cell_steps(cell: Cell) -> int:
  """Training steps of the cell."""
  if cell.config.steps is not None:
    return cell.config.steps
  used = max(1, int(round(parse_fraction(cell.config.fraction) * _n_train(cell))))
  return used // cell.config.batch_size * cell.config.epochs


def _advance(bar, amount: float) -> None:
  """Moves the bar on, never past its total (the totals are estimates in float seconds)."""
  bar.update(max(0.0, min(amount, bar.total - bar.n)))


class _CellBar:
  """The grid's bar as one cell's train() sees it: a step adds the cell's estimated seconds;
  the epoch lines go to the cell's log file."""

  def __init__(self, bar, cell: Cell, weight: float, logfile, step: int,
               on_step: Callable[[int], None]):
    self.bar, self.cell, self.weight, self.logfile = bar, cell, weight, logfile
    self.step, self.on_step = step, on_step

  def update(self, n: int) -> None:
    """n training steps done (on_step may stop the training here, between two steps)."""
    _advance(self.bar, n * self.weight)
    self.step += n
    self.on_step(self.step)

  def set_postfix(self, refresh: bool = False, **kw) -> None:
    """Shows the cell and its epoch/loss."""
    self.bar.set_postfix(cell=self.cell.name, **kw, refresh=refresh)

  def write(self, line: str) -> None:
    """A line of training output, to the cell's log."""
    self.logfile.write(line + "\n")
    self.logfile.flush()


# ----------------------------------------------------------------------------- running


def validation_indices(cell: Cell) -> tuple[Any, list[int]]:
  """(source, indices) of the cell's validation split: the held-out groups of its training
  source (all of them, not the training curves' max_val)."""
  source = open_source(cell.config)
  return source, split_indices(source, cell.config.test_fraction, seed=cell.config.seed)[1]


def eval_scenes(cell: Cell, evalset: EvalSet) -> list[int]:
  """The scene indices a cell is scored on for a set."""
  return list(_eval_source(cell, evalset)[1])


def fixed_test_source(evalset: EvalSet, size: int, t: int | None) -> SyntheticSource:
  """A fixed v2 test set: every scene of a synthetic domain rendered from TEST_SEED."""
  synth = SynthConfig(size=size, domain=evalset.domain, t=t)
  return SyntheticSource(evalset.n, seed=TEST_SEED, config=synth)


def _eval_source(cell: Cell, evalset: EvalSet):
  """(source, scene indices) of an evaluation set for a cell."""
  config = cell.config
  if evalset.kind == HELDOUT:
    return validation_indices(cell)
  if evalset.kind == "synthetic":
    synth = SynthConfig(size=config.synth_size, domain=evalset.domain, t=config.synth_t)
    source = SyntheticSource(evalset.n, seed=config.seed, config=synth)
    return source, split_indices(source, config.test_fraction, seed=config.seed)[1]
  if evalset.kind == FIXED:
    source = fixed_test_source(evalset, config.synth_size, config.synth_t)
    return source, list(range(len(source)))
  source = FolderSource(evalset.path)
  return source, list(range(len(source)))


def _predictor(out: Path, cell: Cell, which: str = "final") -> inference.Predictor:
  """The cell's final (or best) checkpoint (resize protocol) with the compiler and kernel
  choices it trained with: scoring never tunes, and at the smoke scale nothing is tuned."""
  saved = trained.read_config(cell_dir(out, cell.name))
  return inference.load(final_checkpoint(out, cell.name, which), mode="resize",
                        kernels=choices.KernelChoice.from_name(saved.get("ynn", "on")),
                        conv_impl=config_from_json(
                            saved, str(cell_dir(out, cell.name) / trained.CONFIG_FILE)
                        ).model_conv_impl)


def choose_window(out: Path, cell: Cell) -> int | None:
  """The correlation window of a v2 unet-sl cell, chosen on its validation split from the
  plan's candidates (the lowest Full MAE; ties: the smaller window), kept in
  eval/windows.json; None for cells without candidates (the training config's window)."""
  if not cell.windows:
    return None
  path = cell_dir(out, cell.name) / EVAL_DIR / WINDOWS_FILE
  saved = read_json(path)
  if saved is not None:
    require(saved["candidates"] == list(cell.windows),
            f"{path}: cell {cell.name} chose its window from {saved['candidates']}, the plan "
            f"now lists {list(cell.windows)}; use another OUT for the changed plan")
    return int(saved["chosen"])
  source, indices = validation_indices(cell)
  maes = {}
  predictor = _predictor(out, cell)
  for window in cell.windows:
    rep = evaluate(predictor.with_options(window=window), source, indices, progress=False)
    maes[window] = rep["pooled"]["full"]["mae"]
  chosen = min(cell.windows, key=lambda w: (maes[w], w))
  path.parent.mkdir(parents=True, exist_ok=True)
  write_json(path, json_safe({"candidates": list(cell.windows), "validation_mae": {
      str(w): maes[w] for w in cell.windows}, "chosen": chosen, "n_scenes": len(indices)}))
  return chosen


def evaluate_cell(out: Path, cell: Cell, evalset: EvalSet) -> dict[str, Any]:
  """Scores the cell's final (or best) checkpoint on a set (resize protocol, the one metrics
  function; a v2 unet-sl cell with the window chosen on validation); writes eval/SET.json."""
  window = choose_window(out, cell)
  source, indices = _eval_source(cell, evalset)
  predictor = _predictor(out, cell, evalset.checkpoint)
  info = {"cell": cell.name, "set": evalset.name, "kind": evalset.kind}
  if evalset.checkpoint != "final":
    info["checkpoint"] = f"{evalset.checkpoint} by validation MAE"
  if window is not None:
    predictor = predictor.with_options(window=window)
    info["corr_window"] = window
  if evalset.kind == FIXED:
    info["dataset_seed"] = TEST_SEED
  report = evaluate(predictor, source, indices, progress=False, info=info)
  write_eval(out, cell.name, evalset.name, json_safe(report))
  return report


def train_cell(out: Path, cell: Cell, bar, weight: float,
               on_step: Callable[[int], None] = lambda step: None,
               stop: workers.Stop | None = None) -> dict[str, Any]:
  """Trains (or resumes) one cell and writes done.json; on_step(step) after each fetch of the
  step metrics (it may raise to stop the training there). A signal `stop` caught ends the
  training after its step with a checkpoint there, and raises workers.Stopped."""
  wd = cell_dir(out, cell.name)
  config = cell.config
  if cell.init_cell is not None:
    config = dataclasses.replace(config, init_from=str(final_checkpoint(out, cell.init_cell)))
  ckpt_dir = wd / ckpt.CHECKPOINT_DIR
  saved = [int(p.name) for p in ckpt_dir.iterdir() if p.name.isdigit()] if ckpt_dir.is_dir() else []
  wd.mkdir(parents=True, exist_ok=True)
  t0 = time.perf_counter()
  with open(wd / LOG_FILE, "a", encoding="utf-8") as logfile:
    cell_bar = _CellBar(bar, cell, weight, logfile, max(saved, default=0), on_step)
    _advance(bar, max(saved, default=0) * weight)  # a resumed cell's steps already done
    # resume=True also restarts a cell killed before its first checkpoint (nothing to keep).
    result = train(config, wd, resume=True, log=cell_bar.write, progress=cell_bar,
                   stop=None if stop is None else lambda: stop.signum is not None)
  if result.stopped:
    stop.check()
  # A finished cell needs its final checkpoint only, and its best when the plan scores it.
  best = best_step(ckpt_dir) if any(e.checkpoint == "best" for e in cell.evals) else None
  for path in ckpt_dir.iterdir():
    if path.name.isdigit() and int(path.name) not in (result.step, best):
      shutil.rmtree(path)
  epochs = [json.loads(l) for l in (wd / "epochs.jsonl").read_text().splitlines()]
  done = {"step": result.step, "epochs": result.epochs_done, "last_val_mae": result.last_val,
          "train_seconds": sum(r["seconds"] for r in epochs),
          "wall_seconds_last_call": time.perf_counter() - t0,
          "machine": machine.cpu_description()}  # a grid may span machines
  if best is not None:
    done["best_step"] = best
  write_json(wd / DONE_FILE, done)
  return done


def best_step(checkpoints: Path) -> int:
  """The step of a finished run's best checkpoint by validation MAE (orbax's record)."""
  manager = ckpt.make_manager(checkpoints, read_only=True)
  try:
    step = manager.best_step()
  finally:
    manager.close()
  require(step is not None, f"{checkpoints}: no checkpoint with a validation MAE")
  return int(step)


def _after_diverged(init_cell: str) -> str:
  """Why a cell fine-tuned from a diverged one is left out."""
  return f"fine-tuned from {init_cell}, which diverged"


def diverged(out: Path, plan: Plan) -> dict[str, str]:
  """The cells that will not be trained, with why: those whose training loss went non-finite
  (diverged.json) and, after them, every cell fine-tuned from one."""
  why = {}
  for cell in plan.cells:  # a cell's init_cell comes before it in the plan
    rec = read_json(cell_dir(out, cell.name) / DIVERGED_FILE)
    if rec is not None:
      why[cell.name] = str(rec.get("message", "diverged"))
    elif cell.init_cell in why:
      why[cell.name] = _after_diverged(cell.init_cell)
  return why


def pending(out: Path, plan: Plan,
            left_out: dict[str, str]) -> list[tuple[Cell, bool, list[EvalSet]]]:
  """(cell, needs training, evaluation sets still to score) for every unfinished cell not
  left out (`diverged`)."""
  todo = []
  for cell in plan.cells:
    if cell.name in left_out:
      continue
    wd = cell_dir(out, cell.name)
    trained = (wd / DONE_FILE).exists()
    evals = [e for e in cell.evals if eval_record(out, cell.name, e.name) is None]
    if not trained or evals:
      todo.append((cell, not trained, evals))
  return todo


def run(plan: Plan, out: str | os.PathLike, *, progress: bool = True,
        log: Callable[[str], None] = print, lease: float = workers.LEASE_S,
        poll: float | None = None, log_path: str | None = None,
        then: Callable[[], Plan] | None = None) -> dict[str, Any]:
  """Trains and scores the plan's unfinished cells under OUT as one worker among any number on
  the same folder (sljax.experiment.running.workers): each cell claimed by one, a cell once
  the cells it waits for are done (cells.waits_for). Returns {'trained', 'evaluated',
  'seconds', 'diverged' (the cells left out, with why), 'left' (unfinished cells other workers
  hold, with who), 'stopped' (the signal that stopped this worker, or None)}. lease: seconds
  without a heartbeat after which a worker on another host counts as gone; poll: seconds
  between looks while waiting (lease/6, at most 10 s); log_path: this worker's log, for
  `experiment status`; then: the plan that follows once every cell of this one is finished
  (a calibration's grid, built and registered by sljax.experiment.budget.calibrate): the
  worker waits for the cells others hold instead of ending, then goes on with it."""
  out = Path(out)
  with workers.plan_lock(out):
    register(out, plan)
  wait = min(10.0, lease / 6) if poll is None else poll
  with workers.Stop() as stop, workers.Worker(out, workers.identity(lease), log_path) as worker:
    result = _run(plan, out, worker, stop, progress, log, wait, then is not None)
    if then is not None and stop.signum is None and not result["left"]:
      more = _run(then(), out, worker, stop, progress, log, wait, False)
      result = dict(more, trained=result["trained"] + more["trained"],
                    evaluated=result["evaluated"] + more["evaluated"],
                    seconds=result["seconds"] + more["seconds"],
                    diverged={**result["diverged"], **more["diverged"]})
  if stop.signum is not None:
    stop.hand_over()  # under submitit: its checkpoint() and the job's requeue
  return result


def _base_done(out: Path, cell: Cell) -> bool:
  """Whether a cell may start: every cell it waits for (its base, its calibration) is trained."""
  return all((cell_dir(out, name) / DONE_FILE).exists() for name in waits_for(cell))


def _left_to_do(out: Path, cell: Cell) -> tuple[bool, list[EvalSet]] | None:
  """(needs training, evaluation sets to score) of a cell as its files show it now; None when
  it is finished or left out (diverged)."""
  wd = cell_dir(out, cell.name)
  evals = [e for e in cell.evals if eval_record(out, cell.name, e.name) is None]
  needs = not (wd / DONE_FILE).exists()
  return None if (wd / DIVERGED_FILE).exists() or not (needs or evals) else (needs, evals)


def _claim_next(out: Path, todo, worker: workers.Worker):
  """(cell, needs training, evaluation sets) of the first unfinished cell this worker could
  claim, read again once claimed (another worker may have just finished it); None if none."""
  for cell, _, _ in todo:
    # Read again just before claiming: another worker may have finished it since `pending`.
    if not _base_done(out, cell) or _left_to_do(out, cell) is None:
      continue
    if not worker.claim(cell.name):
      continue
    left = _left_to_do(out, cell)
    if left is None:
      worker.release("finished by another worker")
      continue
    return (cell, *left)
  return None


def _why_wait(out: Path, todo, worker: workers.Worker, all_of: bool = False) -> str | None:
  """Why a worker with nothing to claim should wait: a cell waiting for one another worker
  trains, a holder that missed its heartbeats (the lease will tell whether it is gone), or
  (all_of) any unfinished cell, since a plan follows them; None when nothing left can come to
  this worker."""
  blocked = [c for c, _, _ in todo if not _base_done(out, c)]
  if blocked:
    first = next(n for n in waits_for(blocked[0])
                 if not (cell_dir(out, n) / DONE_FILE).exists())
    return f"{blocked[0].name} waits for {first}"
  late = workers.late_holders(out, [c.name for c, _, _ in todo], worker.clock())
  if late:
    return f"the worker of {late[0]} missed its heartbeats"
  return (f"the next plan waits for {todo[0][0].name}, which another worker holds"
          if all_of and todo else None)


def _run(plan: Plan, out: Path, worker: workers.Worker, stop: workers.Stop, progress: bool,
         log: Callable[[str], None], poll: float, all_of: bool) -> dict[str, Any]:
  """run() as a worker; all_of: wait until every cell is finished (a plan follows them)."""
  skipped = diverged(out, plan)
  todo = pending(out, plan, skipped)
  log(describe(plan) + f"; {len(plan.cells) - len(todo) - len(skipped)} cell(s) already "
      f"finished under {out}" + (f"; {len(skipped)} left out, diverged: {', '.join(skipped)}"
                                 if skipped else ""))
  weights = {cell.name: _seconds_per_step(cell) for cell, _, _ in todo}
  # Scoring a scene costs about a third of a training sample.
  eval_cost = {(c.name, e.name): weights[c.name] / c.config.batch_size / 3
               * len(_eval_source(c, e)[1]) for c, _, evals in todo for e in evals}
  total = (sum(cell_steps(c) * weights[c.name] for c, needs, _ in todo if needs)
           + sum(eval_cost.values()))
  t0 = time.perf_counter()
  trained = evaluated = k = 0
  left: dict[str, str] = {}
  bar = tqdm(total=total, disable=not progress or not todo, dynamic_ncols=True,
             bar_format="{l_bar}{bar}| {percentage:3.0f}% [{elapsed}<{remaining}] {postfix}",
             desc=f"{plan.name} ({len(todo)} cells)")

  def on_step(step: int) -> None:
    """The cell's training reached step: its heartbeat shows it; a lost claim stops it here
    (a signal stops it after its step, with a checkpoint there: `train_cell`'s stop)."""
    worker.progress(step)
    if worker.lost:
      raise workers.Stopped("lost")

  try:
    while stop.signum is None:
      skipped.update(diverged(out, plan))  # other workers' cells may have diverged
      now_todo = pending(out, plan, skipped)
      claimed = _claim_next(out, now_todo, worker) if now_todo else None
      if claimed is None:
        waiting = _why_wait(out, now_todo, worker, all_of) if now_todo else None
        if waiting is None:
          left = workers.held_by(out, [c.name for c, _, _ in now_todo])
          break
        time.sleep(poll)
        continue
      cell, needs_training, evals = claimed
      k += 1
      t_cell, why = time.perf_counter(), "interrupted"
      try:
        if needs_training:
          try:
            done = train_cell(out, cell, bar, weights.get(cell.name, 0.0), on_step, stop=stop)
          except TrainingDiverged as e:
            # One diverged cell must not stop a grid of many; docs/plan-v4.md says how the
            # report treats it.
            path = cell_dir(out, cell.name) / DIVERGED_FILE
            path.parent.mkdir(parents=True, exist_ok=True)
            write_json(path, {"message": str(e), "machine": machine.cpu_description()})
            skipped[cell.name] = str(e)
            why = "diverged"
            bar.write(f"[{k}/{len(todo)}] {cell.name}: diverged ({e}). Recorded in {path}; the "
                      "run goes on without it and the cells fine-tuned from it (delete that "
                      "file to train it again)")
            continue
          trained += 1
        else:
          done = read_done(out, cell.name)
        worker.progress(done["step"])
        scores = []
        for evalset in evals:
          stop.check()
          report = evaluate_cell(out, cell, evalset)
          _advance(bar, eval_cost.get((cell.name, evalset.name), 0.0))
          evaluated += 1
          full = report["pooled"].get("full", {})
          if full.get("mae") is not None:
            scores.append(f"{evalset.name} MAE {full['mae']:.3f} px")
        why = "finished"
        bar.write(f"[{k}/{len(todo)}] {cell.name}: step {done['step']}"
                  + (f"; {', '.join(scores)}" if scores else "")
                  + f" ({(time.perf_counter() - t_cell) / 60:.1f} min)")
      except Exception as e:
        why = f"failed: {type(e).__name__}"  # the traceback or one line says more
        raise
      except workers.Stopped as e:
        why = f"stopped by {e}" if str(e) != "lost" else why
        bar.write(f"[{k}/{len(todo)}] {cell.name}: " + (
            f"stopped by {e}; its checkpoint is kept and its claim released"
            if str(e) != "lost" else "taken over by another worker (this one missed its "
            "lease); going on with another cell"))
      finally:
        try:
          worker.release(why)
        except OSError:  # a full disk: the claim is taken over once this worker has ended
          pass
  finally:
    bar.close()
  return {"trained": trained, "evaluated": evaluated, "seconds": time.perf_counter() - t0,
          "diverged": skipped, "left": left, "stopped": stop.name}
