"""What a plan will cost before it runs (`sljax experiment run|submit --dry-run`): its cells,
what each waits for, their steps, validation and scoring passes, GPU-hours from the measured
step times of a GPU kind (sljax.experiment.running.gpu_figures) or of this machine (its
finished cells under OUT), and the wall time on N workers by a list schedule that keeps
fine-tuning cells after their base. Reads only; writes nothing.
"""

import dataclasses
import heapq
import math
from collections.abc import Callable
from pathlib import Path

from sljax.errors import SljaxError, require
from sljax.experiment.design.cells import FIXED, Cell, Plan, waits_for
from sljax.experiment.design.plans import (CALIB_PREFIX, build_plan, calibration_plan,
                                           describe, needs_calibration, provisional_plan)
from sljax.experiment.records import (DONE_FILE, PLAN_FILE, cell_dir, eval_record, read_done,
                                      read_record)
from sljax.experiment.running import gpu_figures as gf
from sljax.experiment.running.runner import cell_steps, eval_scenes, validation_indices
from sljax.runtime import machine
from sljax.train.config import QUICK

# A scene's forward pass as a share of a training sample's step where none was measured: the
# runner's progress weights take the same third (forward only, no backward or Adam).
FORWARD_SHARE = 1 / 3
MEASURE_HINT = ("measure it with `python benchmarks/bench_nets.py --part all --models "
                "psmnet,psmnet-mtl,unet-sl` (or `python benchmarks/bench_train.py --preset "
                "paper --step-only --net NET` on a GPU), or run a cell under OUT first")


@dataclasses.dataclass(frozen=True)
class NetFigure:
  """A network's seconds a training step and a scene's forward pass, and where they are from
  (a stand-in says so)."""
  net: str
  step_s: float
  forward_s: float
  step_from: str
  forward_from: str
  validation_in_step: bool = False  # a finished cell's seconds a step include its validation


@dataclasses.dataclass(frozen=True)
class Figures:
  """The figures a plan is priced with: per network, and a cell's start."""
  where: str
  nets: tuple[NetFigure, ...]
  start_s: float = 0.0
  start_from: str = "not counted"
  missing: str = ""        # why a network without a figure has none, and how to measure it

  def of(self, net: str) -> NetFigure | None:
    """The figure of a network, or None."""
    return next((f for f in self.nets if f.net == net), None)


@dataclasses.dataclass(frozen=True)
class CellCost:
  """One cell's work and, where its network has a figure, its seconds."""
  name: str
  net: str
  waits_for: tuple[str, ...]
  steps: int
  val_passes: int
  val_scenes: int
  score_scenes: int
  figure: NetFigure | None
  start_s: float
  done: bool = False       # finished under OUT already: costs nothing more

  def _seconds(self, value: Callable[[NetFigure], float]) -> float | None:
    return None if self.figure is None else 0.0 if self.done else value(self.figure)

  @property
  def train_s(self) -> float | None:
    """Seconds of training steps."""
    return self._seconds(lambda f: self.steps * f.step_s)

  @property
  def val_s(self) -> float | None:
    """Seconds of validation (0 where the step's figure already includes it)."""
    return self._seconds(lambda f: 0.0 if f.validation_in_step
                         else self.val_passes * self.val_scenes * f.forward_s)

  @property
  def score_s(self) -> float | None:
    """Seconds of scoring (the evaluation sets, and a v2 unet-sl's window choice)."""
    return self._seconds(lambda f: self.score_scenes * f.forward_s)

  @property
  def total_s(self) -> float | None:
    """The cell's seconds from its start to its last score."""
    parts = (self.train_s, self.val_s, self.score_s)
    return None if None in parts else 0.0 if self.done else sum(parts) + self.start_s


# ----------------------------------------------------------------------------- counting


def validation_passes(cell: Cell) -> int:
  """How many times training validates: every val_every epochs and at the end, or every
  val_every_steps steps and at the end (sljax.train.loop)."""
  config = cell.config
  if config.val_every_steps is not None:
    return math.ceil(cell_steps(cell) / config.val_every_steps)
  return math.ceil(config.epochs / config.val_every)


def validation_scenes(cell: Cell) -> int:
  """Scenes a validation pass predicts: the validation split, at most max_val."""
  n = len(validation_indices(cell)[1])
  return n if cell.config.max_val is None else min(n, cell.config.max_val)


def scoring_scenes(cell: Cell) -> int:
  """Scenes scored after training: every evaluation set, and for a v2 unet-sl cell its whole
  validation split once per candidate window (runner.choose_window)."""
  windows = len(cell.windows) * len(validation_indices(cell)[1]) if cell.windows else 0
  # A fixed test set is every one of its n scenes (n = 0 where a scale commits none yet).
  return sum(e.n if e.kind == FIXED else len(eval_scenes(cell, e)) for e in cell.evals) + windows


def cell_cost(cell: Cell, figures: Figures, done: bool = False) -> CellCost:
  """What one cell costs with these figures."""
  net = cell.config.net
  return CellCost(cell.name, net, waits_for(cell), cell_steps(cell), validation_passes(cell),
                  validation_scenes(cell), scoring_scenes(cell), figures.of(net),
                  figures.start_s, done)


def finished(out: Path, cell: Cell) -> bool:
  """Whether OUT already holds the cell trained and scored on every set."""
  return ((cell_dir(out, cell.name) / DONE_FILE).exists()
          and all(eval_record(out, cell.name, e.name) is not None for e in cell.evals))


# ----------------------------------------------------------------------------- wall time


def wall_time(costs: list[CellCost], workers: int) -> float:
  """Seconds until the last cell ends on `workers` workers: each free worker takes the first
  cell in plan order whose dependencies have ended (as the runner's workers claim), or waits
  for the next one to end. A dependency outside the plan counts as available."""
  require(workers >= 1, f"--workers {workers}: at least 1")
  names = {c.name for c in costs}
  end = {c.name: 0.0 for c in costs if c.done}
  left = [c for c in costs if not c.done]
  free = [0.0] * workers
  while left:
    t = heapq.heappop(free)
    ready = [c for c in left
             if all(d not in names or end.get(d, math.inf) <= t for d in c.waits_for)]
    if not ready:
      later = [e for e in end.values() if e > t]
      if not later:
        raise SljaxError("the plan's dependencies never end: "
                         + ", ".join(f"{c.name} waits for {', '.join(c.waits_for)}"
                                     for c in left[:3]))
      heapq.heappush(free, min(later))
      continue
    cell = ready[0]
    left.remove(cell)
    end[cell.name] = t + cell.total_s
    heapq.heappush(free, end[cell.name])
  return max(end.values(), default=0.0)


def critical_path(costs: list[CellCost]) -> float:
  """Seconds of the longest chain of cells each waiting for the one before: no number of
  workers finishes sooner."""
  by_name, longest = {c.name: c for c in costs}, {}
  for c in costs:  # a plan lists a cell after those it waits for (plans.check_unique)
    longest[c.name] = c.total_s + max((longest.get(d, 0.0) for d in c.waits_for
                                       if d in by_name), default=0.0)
  return max(longest.values(), default=0.0)


# ----------------------------------------------------------------------------- figures


def _other(gpu: str) -> str:
  return next(g for g in gf.GPUS if g != gpu)


def _measured_or_scaled(gpu: str, net: str, what: str) -> tuple[float, str] | None:
  """A network's step or forward on a GPU: measured; else unet-sl's for unet-disp (the same
  UNet with a disparity head); else the other GPU's, scaled by PSMNet's step there and here;
  else None."""
  m = gf.measured(gpu, net, what)
  if m is not None:
    return m.seconds, "measured: " + m.cite()
  if net == "unet-disp":
    s, _ = _measured_or_scaled(gpu, "unet-sl", what)
    return s, f"STAND-IN: unet-sl's {what} (the same UNet with a disparity head)"
  other = _other(gpu)
  there = gf.measured(other, net, what)
  if there is None:
    return None
  ratio = gf.measured(gpu, "psmnet", "step").seconds / gf.measured(other, "psmnet", "step").seconds
  return there.seconds * ratio, (f"STAND-IN: the {other.upper()}'s {there.seconds:.4g} s x "
                                 f"{ratio:.3f}, PSMNet's step {gpu.upper()}/{other.upper()}")


def _gpu_step(gpu: str, net: str) -> tuple[float, str]:
  """A network's step on a GPU: measured, else the stand-in rule."""
  found = _measured_or_scaled(gpu, net, "step")
  require(found is not None, f"no step time of {net} on any GPU measured")
  return found


def _gpu_forward(gpu: str, net: str) -> tuple[float, str]:
  """A scene's forward pass of a network on a GPU: measured, else the stand-in rules."""
  found = _measured_or_scaled(gpu, net, "forward")
  if found is not None:
    return found
  if net == "psmnet-mtl":
    base, ratio = _gpu_forward(gpu, "psmnet")[0], _gpu_step(gpu, net)[0] / _gpu_step(gpu, "psmnet")[0]
    return base * ratio, f"STAND-IN: PSMNet's forward x {ratio:.3f}, the twin's step / PSMNet's"
  step = _gpu_step(gpu, net)[0]
  return step / gf.SHAPE[2] * FORWARD_SHARE, "STAND-IN: a third of a training sample's step"


def _net_figure(gpu: str, net: str) -> NetFigure:
  step, step_from = _gpu_step(gpu, net)
  forward, forward_from = _gpu_forward(gpu, net)
  return NetFigure(net, step, forward, step_from, forward_from)


def gpu_figures(gpu: str, plan: Plan) -> Figures:
  """The figures of a GPU kind for the plan's networks; SljaxError when the plan's shape is
  not the one they were measured at."""
  require(gpu in gf.GPUS, f"--gpu {gpu}: choose from {', '.join(gf.GPUS)}")
  sc = plan.scale
  size, maxdisp, batch = gf.SHAPE
  nets = sorted({c.config.net for c in plan.cells})
  where = f"{gf.GPUS[gpu]} ({size}x{size}, maxdisp {maxdisp}, batch {batch}, TF32)"
  if (sc.size, sc.maxdisp, sc.batch_size) != gf.SHAPE:
    return Figures(where, (), missing=(
        f"the {gpu.upper()}'s figures were measured at {size}x{size}, maxdisp {maxdisp}, "
        f"batch {batch} (the paper scale), not at scale {sc.name}'s {sc.size}x{sc.size}, "
        f"maxdisp {sc.maxdisp}, batch {sc.batch_size}; {MEASURE_HINT}"))
  figs = tuple(_net_figure(gpu, n) for n in nets)
  start = gf.measured(gpu, "psmnet-mtl", "start") or gf.measured(_other(gpu), "psmnet-mtl",
                                                                 "start")
  start_from = ("measured: " if start.gpu == gpu else f"STAND-IN: the {start.gpu.upper()}'s, ") \
      + start.cite() + "; taken for every network"
  return Figures(where, figs, start.seconds, start_from)


def machine_figures(out: Path, plan: Plan) -> Figures:
  """This machine's figures: each network's seconds a step in cells finished here under OUT
  (validation included), none where OUT has no such cell."""
  here = machine.cpu_description()
  record = read_record(out) if out.is_dir() else None
  seconds: dict[str, list[float]] = {}
  steps: dict[str, list[int]] = {}
  for name, spec in (record or {}).get("cells", {}).items():
    done = read_done(out, name)  # a damaged one: one line naming it
    if done is None or done.get("machine") != here or not done.get("step"):
      continue
    config = spec.get("config") if isinstance(spec, dict) else None
    require(isinstance(config, dict), f"{out / PLAN_FILE}: cell {name} has no configuration")
    net = dataclasses.replace(QUICK, model=config.get("model", QUICK.model),
                              strategy=config.get("strategy", QUICK.strategy)).net
    seconds.setdefault(net, []).append(float(done.get("train_seconds") or 0.0))
    steps.setdefault(net, []).append(int(done["step"]))
  batch = plan.scale.batch_size
  figs = []
  for net in sorted(seconds):
    step_s = sum(seconds[net]) / sum(steps[net])
    figs.append(NetFigure(
        net, step_s, step_s / batch * FORWARD_SHARE,
        f"measured: {len(seconds[net])} cell(s) finished here under {out}, validation "
        "included", "STAND-IN: a third of a training sample's step", validation_in_step=True))
  return Figures(f"this machine ({here})", tuple(figs),
                 missing=f"no cell of it finished on this machine under {out}: "
                         f"unknown; {MEASURE_HINT}")


def price(plan: Plan, figures: Figures, out: Path | None = None) -> list[CellCost]:
  """Every cell's cost in plan order (cells finished under OUT cost nothing more)."""
  return [cell_cost(c, figures, out is not None and finished(out, c)) for c in plan.cells]


# ----------------------------------------------------------------------------- the dry run


def _hours(seconds: float | None) -> str:
  return "unknown" if seconds is None else f"{seconds / 3600:.2f}"


def _sum(values) -> float | None:
  values = list(values)
  return None if None in values else sum(values)


def _waits(names: tuple[str, ...]) -> str:
  """What a cell waits for, in a table cell: its base, and its calibration cells counted."""
  calib = [n for n in names if n.startswith(CALIB_PREFIX)]
  other = [n for n in names if not n.startswith(CALIB_PREFIX)]
  return ", ".join(other + ([f"the {len(calib)} calibration cells"] if calib else [])) or "-"


def _cell_rows(costs: list[CellCost]) -> list[str]:
  rows = ["| cell | network | waits for | steps | validation (passes x scenes) | scored scenes "
          "| hours |", "| --- | --- | --- | ---: | ---: | ---: | ---: |"]
  rows += [f"| {c.name} | {c.net} | {_waits(c.waits_for)} | {c.steps:,} | "
           f"{c.val_passes} x {c.val_scenes:,} | {c.score_scenes:,} | "
           + ("finished" if c.done else _hours(c.total_s)) + " |" for c in costs]
  return rows


def _net_rows(costs: list[CellCost]) -> list[str]:
  rows = ["| network | cells | steps | training GPU-h | validation GPU-h | scoring GPU-h | "
          "starts GPU-h | total GPU-h |", "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
  for net in sorted({c.net for c in costs}):
    mine = [c for c in costs if c.net == net and not c.done]
    starts = _sum(None if c.figure is None else c.start_s for c in mine)
    rows.append(f"| {net} | {len(mine)} | {sum(c.steps for c in mine):,} | "
                + " | ".join(_hours(_sum(getattr(c, k) for c in mine))
                             for k in ("train_s", "val_s", "score_s"))
                + f" | {_hours(starts)} | {_hours(_sum(c.total_s for c in mine))} |")
  return rows


def _figure_lines(figures: Figures, costs: list[CellCost]) -> list[str]:
  lines = [f"Figures: {figures.where}:"]
  for f in figures.nets:
    lines.append(f"  {f.net}: {f.step_s:.4g} s a training step ({f.step_from}); "
                 f"{f.forward_s * 1000:.3g} ms a scene's forward pass ({f.forward_from})")
  lines.append(f"  a cell's start: {figures.start_s:.3g} s ({figures.start_from})")
  unknown = sorted({c.net for c in costs if c.figure is None})
  if unknown:
    lines.append(f"  {', '.join(unknown)}: no figure ({figures.missing})")
  return lines


def plan_to_price(name: str, scale: str, seeds: int, data: str | None = None,
                  eval_data: tuple[str, ...] = ()) -> tuple[Plan, int]:
  """What a grid of the plan trains, and how many of its cells are calibration cells: a plan
  whose budgets its OUT calibrates first (`needs_calibration`) is its calibration cells, then
  its cells at the long runs' epochs (the most the plateau rule can give: an upper bound)."""
  if not needs_calibration(name, scale):
    return build_plan(name, scale, seeds, data, eval_data), 0
  calib = calibration_plan(name, scale)
  grid = provisional_plan(name, scale, seeds, data, eval_data)
  return dataclasses.replace(grid, cells=calib.cells + grid.cells), len(calib.cells)


def format_price(plan: Plan, costs: list[CellCost], figures: Figures, workers: int,
                 calibrating: int = 0) -> str:
  """The dry run's text: the plan, its calibration, figures, a row per cell and per network,
  the GPU-hours and the wall time on `workers` workers."""
  lines = ["Dry run: nothing is trained, submitted or written.", describe(plan) + "."]
  if calibrating:
    lines.append(
        f"UPPER BOUND: scale {plan.scale.name} has no committed budgets for {plan.name}, so "
        f"its OUT calibrates them first: {calibrating} calibration cell(s) (calib-*, the "
        "plateau rule of docs/plan-v2.md), then the plan's cells, which wait for them, priced "
        "at the long runs' epochs, the most the rule can give.")
  if plan.scale.v2.test_n == 0 and any(e.kind == "fixed" for c in plan.cells for e in c.evals):
    lines.append(f"Scale {plan.scale.name} commits no fixed test-set size (V2Design.test_n = "
                 "0): the test sets are priced at 0 scenes.")
  lines += _figure_lines(figures, costs) + [""] + _cell_rows(costs) + [""] + _net_rows(costs)
  left = [c for c in costs if not c.done]
  total = _sum(c.total_s for c in left)
  done = len(costs) - len(left)
  lines.append("")
  lines.append(f"GPU-hours: {_hours(total)} for {len(left)} cell(s)"
               + (f" ({done} already finished under OUT)" if done else "")
               + f": training {_hours(_sum(c.train_s for c in left))}, validation "
               f"{_hours(_sum(c.val_s for c in left))}, scoring "
               f"{_hours(_sum(c.score_s for c in left))}, starts "
               f"{_hours(_sum(None if c.figure is None else c.start_s for c in left))}.")
  if total is None:
    lines.append(f"Wall time on {workers} worker(s): unknown (a network has no figure).")
  else:
    wall, chain = wall_time(costs, workers), critical_path(costs)
    lines.append(f"Wall time on {workers} worker(s): about {_hours(wall)} h (a list schedule: "
                 "each free worker takes the next cell in plan order whose base is trained); "
                 f"the longest chain of dependent cells {_hours(chain)} h; total / workers "
                 f"{_hours(total / workers)} h. Queueing and cold compiles not counted.")
  return "\n".join(lines)


def dry_run(plan: Plan, out: str | Path, workers: int, gpu: str | None = None,
            calibrating: int = 0) -> str:
  """The dry run of a plan under OUT (read, never written) on `workers` workers of a GPU kind
  (None: this machine)."""
  out = Path(out)
  figures = gpu_figures(gpu, plan) if gpu else machine_figures(out, plan)
  return format_price(plan, price(plan, figures, out), figures, workers, calibrating)
