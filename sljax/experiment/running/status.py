"""Where a grid stands: which cells are finished, training or waiting, how long the finished
ones took, and about how long the rest will take.

Reads only what the workers write (plan.json, each cell's done.json, eval/ and epochs.jsonl:
sljax.experiment.records; their claims and heartbeats: sljax.experiment.running.claims and
workers), so it can be run beside a grid that is training, from any host that sees the folder. Estimates come from finished cells of the same
arm and factors, preferring those finished on this CPU kind (a mean over two CPUs times
neither); a group with no finished cell has no estimate and is counted as such.
"""

import dataclasses
import json
from pathlib import Path

from sljax.experiment.design.cells import Cell, Plan
from sljax.experiment.records import (cell_dir, eval_record, read_done, read_text,
                                      registered_plans)
from sljax.experiment.running import workers
from sljax.experiment.running.runner import diverged
from sljax.models.checkpoint import CHECKPOINT_DIR
from sljax.runtime import machine
from sljax.train.workdir import EPOCHS_FILE

DONE, SCORING, TRAINING, WAITING = "finished", "trained, not scored", "training", "waiting"
DIVERGED = "left out (diverged)"  # its training loss, or its pretraining's, went non-finite


@dataclasses.dataclass(frozen=True)
class CellState:
  """One cell's progress as its files show it."""
  cell: Cell
  state: str
  epoch: int = 0             # last epoch logged (training cells)
  seconds: float | None = None  # training seconds (finished cells)
  step: int = 0              # the step of that epoch's end
  machine: str | None = None    # the CPU it finished on

  @property
  def share(self) -> float:
    """The share of its budget (steps, else epochs) a training cell has done."""
    config = self.cell.config
    return self.step / config.steps if config.steps is not None else self.epoch / config.epochs

  @property
  def where(self) -> str:
    """"epoch E of N", or "step S of N" for a budget in steps."""
    config = self.cell.config
    return (f"step {self.step} of {config.steps}" if config.steps is not None
            else f"epoch {self.epoch} of {config.epochs}")

  @property
  def group(self) -> tuple:
    """What cells are compared by for estimates: the arm and the other factors."""
    return (self.cell.arm,) + tuple(v for _, v in self.cell.factors)


def last_epoch(workdir: Path) -> tuple[int, int]:
  """The last (epoch, step) in the workdir's epochs.jsonl ((0, 0) when none)."""
  text = read_text(workdir / EPOCHS_FILE)
  if text is None:
    return 0, 0
  lines = [line for line in text.splitlines() if line.strip()]
  for line in reversed(lines[-2:]):  # the last may be being written right now
    try:
      row = json.loads(line)
      return int(row["epoch"]), int(row.get("step", 0))
    except (ValueError, KeyError, TypeError, OverflowError):  # OverflowError: int(Infinity)
      continue
  return 0, 0


def cell_state(out: Path, cell: Cell) -> CellState:
  """The state of one cell under OUT."""
  wd = cell_dir(out, cell.name)
  done = read_done(out, cell.name)
  if done is None:
    epoch, step = last_epoch(wd)
    return CellState(cell, TRAINING if epoch or (wd / CHECKPOINT_DIR).exists() else WAITING,
                     epoch=epoch, step=step)
  scored = all(eval_record(out, cell.name, e.name) is not None for e in cell.evals)
  seconds = done.get("train_seconds")
  return CellState(cell, DONE if scored else SCORING, epoch=cell.config.epochs,
                   step=cell.config.steps or 0,
                   seconds=None if seconds is None else float(seconds),
                   machine=done.get("machine"))


def plan_status(out: Path, plan: Plan) -> list[CellState]:
  """Every cell's state, in the plan's order."""
  left_out = diverged(out, plan)
  return [CellState(cell, DIVERGED) if cell.name in left_out else cell_state(out, cell)
          for cell in plan.cells]


def _mean_here(states: list[CellState], value, here: str) -> float:
  """The mean of value(state) over the states finished on this CPU, else over all of them."""
  values = [value(s) for s in states if s.machine == here] or [value(s) for s in states]
  return sum(values) / len(values)


def seconds_left(states: list[CellState], here: str) -> tuple[float, int]:
  """(estimated training seconds left, unfinished cells with no estimate)."""
  # A group's estimate is the mean of its finished cells (on this CPU where it has some); a
  # cell budgeted in steps whose group has none is estimated at its arm's seconds a step in
  # finished cells budgeted in steps (the v4 settings differ in steps, not in the step's
  # cost); a training cell counts the share of its budget still to run.
  timed = [s for s in states if s.seconds is not None]
  mean = {g: _mean_here([s for s in timed if s.group == g], lambda s: s.seconds, here)
          for g in {s.group for s in timed}}
  stepped = [s for s in timed if s.cell.config.steps]
  per_step = {a: _mean_here([s for s in stepped if s.cell.arm == a],
                            lambda s: s.seconds / s.cell.config.steps, here)
              for a in {s.cell.arm for s in stepped}}
  left, unknown = 0.0, 0
  for s in states:
    if s.state in (DONE, SCORING, DIVERGED):
      continue
    if s.group in mean:
      left += mean[s.group] * (1 - s.share)
    elif s.cell.config.steps and s.cell.arm in per_step:
      left += per_step[s.cell.arm] * s.cell.config.steps * (1 - s.share)
    else:
      unknown += 1
  return left, unknown


def holder_text(held: tuple[dict, int | None, float]) -> str:
  """Who holds a cell, since when, its last step and heartbeat."""
  rec, step, age = held
  return (f"held by {workers.describe(rec)} since {workers.when(rec.get('since'))}"
          + (f", last step {step}" if step is not None else "")
          + f", heartbeat {age:.0f} s ago"
          + (" (late: its worker may be gone; the lease decides)"
             if age > 2 * float(rec.get("lease", workers.LEASE_S)) / 3 else ""))


def format_status(plan: Plan, states: list[CellState], here: str,
                  held: dict[str, tuple[dict, int | None, float]] | None = None) -> str:
  """The plan's lines: counts, cells in progress and who holds them (held: workers.holders),
  a table per group, what is left."""
  held = held or {}
  count = {k: sum(s.state == k for s in states)
           for k in (DONE, SCORING, TRAINING, WAITING, DIVERGED)}
  seeds = (f"seeds {plan.seeds[0]}-{plan.seeds[-1]}" if len(plan.seeds) > 1
           else f"seed {plan.seeds[0]}")
  lines = [f"{plan.name} (scale {plan.scale.name}, {seeds}): "
           + ", ".join(f"{n} {k}" for k, n in count.items() if n) + f" of {len(states)} cells"]
  doing = {TRAINING: "training", WAITING: "starting", SCORING: "scoring", DONE: "finishing"}
  lines += [f"  {doing.get(s.state, 'holding')}: {s.cell.name}"
            + (f", {s.where}" if s.state == TRAINING else "")
            + (f"; {holder_text(held[s.cell.name])}" if s.cell.name in held else "")
            for s in states if s.state == TRAINING or s.cell.name in held]
  lines += [f"  left out (diverged): {s.cell.name}" for s in states if s.state == DIVERGED]
  lines += ["", "| arm | factors | finished | seeds finished | minutes a cell on this CPU, "
            "mean (range) | elsewhere, range |", "| --- | --- | --- | --- | --- | --- |"]
  groups: dict[tuple, list[CellState]] = {}
  for s in states:
    groups.setdefault(s.group, []).append(s)
  span = lambda t: f"{min(t):.1f}-{max(t):.1f}" if t else "-"
  for group, members in groups.items():
    here_min = [s.seconds / 60 for s in members if s.seconds is not None and s.machine == here]
    other = [s.seconds / 60 for s in members if s.seconds is not None and s.machine != here]
    seeds_done = ", ".join(str(s.cell.seed) for s in members if s.state == DONE) or "-"
    mean = f"{sum(here_min) / len(here_min):.1f} ({span(here_min)})" if here_min else "-"
    lines.append(f"| {group[0]} | {', '.join(group[1:]) or '-'} | "
                 f"{sum(s.state == DONE for s in members)} of {len(members)} | {seeds_done} | "
                 f"{mean} | {span(other)} |")
  cpus: dict[str, int] = {}
  for s in states:
    if s.seconds is not None:
      key = s.machine or "CPU not recorded"
      cpus[key] = cpus.get(key, 0) + 1
  if cpus:
    lines += ["", f"This CPU: {here}. Cells trained on: "
              + "; ".join(f"{m} ({n})" for m, n in cpus.items())]
  left, unknown = seconds_left(states, here)
  if count[TRAINING] + count[WAITING]:
    when = f"{left / 3600:.1f} h" if left >= 3600 else f"{left / 60:.0f} min"
    lines.append(f"Training left: about {when}, at this CPU's pace where it finished cells of "
                 "the arm, else at other CPUs' (budgets in steps: at the arm's seconds a step)"
                 + (f"; {unknown} cell(s) of arms with no finished cell not counted"
                    if unknown else "") + "; scoring adds minutes a cell")
  return "\n".join(lines)


def grid_status(out: str | Path, seeds: int | None = None) -> str:
  """The status of every plan run under OUT (with `seeds` seeds where given), who holds which
  cell, and the workers."""
  out, here = Path(out), machine.cpu_description()
  plans = registered_plans(out, seeds)
  held = workers.holders(out, sorted({c.name for plan in plans for c in plan.cells}))
  states = [(plan, plan_status(out, plan)) for plan in plans]
  text = "\n\n".join(format_status(plan, s, here, held) for plan, s in states)
  live = workers.live_workers(out)
  if live:
    text += "\n\nWorkers: " + "; ".join(live)
  unfinished = any(c.state in (TRAINING, WAITING, SCORING) for _, s in states for c in s)
  if unfinished and not held:
    return text + ("\n\nNo worker holds a cell now: run `sljax experiment run` (or `submit`) "
                   "again to go on (finished cells are kept; a cell in training continues from "
                   "its last checkpoint).")
  return text
