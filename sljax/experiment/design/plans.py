"""Experiment plans: the grids of training runs behind the paper's tables, at three scales.

A plan expands into cells, one training run each (a TrainConfig plus what the runner needs:
the cell it fine-tunes from, the sets it is scored on). Cells are named from their
coordinates, so plans that share a run (table3 and fig7 reuse table2's full-data models)
share the cell when they run under one OUT. The cells, their evaluation sets and the plan are
sljax.experiment.design.cells; each plan's cells of one seed are defined in
sljax.experiment.design.paper_tables (v1 and v2) and sljax.experiment.design.overfitting (v3 and v4).

Pairing: within a seed every arm of a plan trains on the same synthetic scenes (rendered from
that seed), the same group-level split, the same training subset and scene order (drawn from
the seed), and starts from the same initial weights for every parameter it shares with the
other arms (flax derives each module's initial values from the seed and the module's name,
and the twin's disparity path has PSMNet's names). Seeds differ in all of these.

Two designs. v1 (table1, table2, table3, fig7) scores every cell on its own held-out split,
which training also validates on. v2 (table1-v2, ...; docs/plan-v2.md pre-registers it)
separates the three: training on the training split, every choice (epochs, correlation window)
on the validation split (the training source's held-out groups), and the score on a large
fixed test set per domain, rendered from its own dataset seed (TEST_SEED), the same for every
seed and arm and disjoint from every training source at the group level. A v2 cell trains
exactly as the v1 cell of the same name (same spec): the designs differ in what is scored.

Plans:
- table1: unet-sl (disparity by correlating its predicted patterns) vs unet-disp, trained on
  objects, then fine-tuned on scarce tissue (or on --data) from the objects model.
- table2: the five strategies x {all, 1/16 of the training split} on objects (or --data).
- table3: table2's full-data models scored on the tissue domain and on --eval-data folders.
- fig7: table2's full-data models fine-tuned on scarce tissue (or --data), with curves.
- table1-v2: table1 scored on the fixed objects and tissue test sets; unet-sl's correlation
  window chosen per cell on validation from the scale's pre-registered windows.
- table2-v2: table2 at 1/16 only, scored on the fixed objects test set.
- table3-v2: table2's full-data models scored on the fixed tissue test set (the claims; another
  domain) and the fixed objects test set (in-domain, descriptive), and on --eval-data folders.
- fig7-v2: fig7 scored on the fixed tissue test set.
- v3-pilot: stl on objects at a few small training fractions, a constant learning rate and a
  long fixed budget, validated every few epochs on the whole validation split: the curves
  from which docs/plan-v3.md's regime rule picks where stl overfits (sljax.experiment.budget.regime).
  Its seeds (100, 101, ...) are never used by a test cell.
- v3: stl, unc and epr in the regime the pilot found (the scale's V3Design.regime: a training
  fraction and a budget), constant learning rate, validated as the pilot; the final checkpoint
  scored on the fixed objects and tissue test sets, and the best checkpoint by validation on
  the objects test set.
- v4-pilot: stl with budgets in optimizer steps (docs/plan-v4.md), validated every few steps:
  from scratch on objects with a few training scenes, and the paper's setting (an objects model
  of all the data fine-tuned on a few tissue scenes); curves only. Seeds 200, 201, ...
- v4: stl, unc and epr in the setting, fraction and step budget the v4 pilot's rule chose (the
  scale's V4Design.regime), constant learning rates, validated as the pilot. Fine-tuning: each
  arm fine-tunes its own objects model (the twin for unc and epr, pretrained with the same
  strategy, as the pilot's pretraining). The final and the best checkpoint scored on the
  setting's fixed test set (tissue when fine-tuning, objects from scratch). Seeds 300, 301, ...,
  as many as the plan's 24-hour rule committed (V4Design.grid_seeds).
- v5: the paper's mechanism at the paper's scale (docs/plan-v5.md): each strategy's objects
  model on all the data, trained for its calibrated budget, fine-tuned on a few tissue scenes
  for a long fixed number of steps, validated every few steps; the final and the best
  checkpoint scored on the fixed tissue test set. Seeds 500, 501, ...

Calibration in the grid's folder (docs/plan-v2.md's plateau rule): a v2 plan or v5 at a scale
whose budgets are not committed in scales.py first runs its calibration cells (calibration_plan:
one long run per arm and phase, seed 0) in the same OUT; the plan's cells are built from the
budgets the rule gives (build_plan's `budgets`) and each waits for those cells (Cell.waits,
cells.waits_for). provisional_plan prices them before then.
"""



import dataclasses
from collections.abc import Callable

from sljax.data.dataset import FolderSource
from sljax.errors import SljaxError, require
from sljax.io import files
from sljax.losses.weighting import SINGLE_TASK
from sljax.experiment.design import overfitting, paper_tables
from sljax.experiment.design.cells import Cell, Epochs, Plan, Seeded
# The scales and their designs live in scales.py; plans.SCALES and plans.NO_REGIME stay public.
from sljax.experiment.design.scales import NO_REGIME, SCALES, Scale

V1_PLANS = ("table1", "table2", "table3", "fig7")
V2_PLANS = ("table1-v2", "table2-v2", "table3-v2", "fig7-v2")
V3_PILOT = "v3-pilot"
V3_PLANS = (V3_PILOT, "v3")
V4_PILOT = "v4-pilot"
V4 = "v4"
V4_PLANS = (V4_PILOT, V4)
V5 = "v5"
PLANS = V1_PLANS + V2_PLANS + V3_PLANS + V4_PLANS + (V5,)
CALIB_PREFIX = "calib-"  # a calibration cell's name: this, then the cell it calibrates
CALIBRATED = V2_PLANS + (V5,)   # plans whose epochs come from the plateau rule
CALIBRATE = "calibrate-"        # a calibration plan's name: CALIBRATE + the plan's
PHASES = ("objects", "1/16", "finetune")  # the budgets of a scale: all data, 1/16, fine-tuning

# Each shipped plan: its cells for one seed, and the arm the others are compared with.
BUILDERS: dict[str, tuple[Callable[[Seeded], list[Cell]], str]] = {
    "table1": (paper_tables.table1, "unet-disp"), "table2": (paper_tables.table2, SINGLE_TASK),
    "table3": (paper_tables.table3, SINGLE_TASK), "fig7": (paper_tables.fig7, SINGLE_TASK),
    "table1-v2": (paper_tables.table1_v2, "unet-disp"), "table2-v2": (paper_tables.table2_v2, SINGLE_TASK),
    "table3-v2": (paper_tables.table3_v2, SINGLE_TASK), "fig7-v2": (paper_tables.fig7_v2, SINGLE_TASK),
    V3_PILOT: (overfitting.v3_pilot, SINGLE_TASK), "v3": (overfitting.v3_grid, SINGLE_TASK),
    V4_PILOT: (overfitting.v4_pilot, SINGLE_TASK), V4: (overfitting.v4_grid, SINGLE_TASK),
    V5: (overfitting.v5_grid, SINGLE_TASK),
}
Budgets = tuple[tuple[tuple[str, str], int], ...]  # ((arm, phase), epochs)


def _v1_epochs(scale: Scale) -> Epochs:
  s = scale.schedule
  by_phase = {"objects": s.epochs, "1/16": s.small_epochs, "finetune": s.finetune_epochs}
  return lambda arm, phase: by_phase[phase]


# ----------------------------------------------------------------------------- plans


def _pattern_count(data: str | None, scale: Scale) -> int:
  """Patterns per view: the user's folder's (so pretraining matches it), else the scale's."""
  if data is None:
    return scale.t
  t = FolderSource(data).num_patterns
  return scale.t if t is None else t


def plan_seeds(name: str, scale: str, seeds: int) -> tuple[int, ...]:
  """The seeds of a plan run with --seeds N: 0..N-1, or from a pilot's first seed."""
  first = {V3_PILOT: lambda: SCALES[scale].v3.first_seed,
           V4_PILOT: lambda: SCALES[scale].v4.first_seed,
           V4: lambda: SCALES[scale].v4.grid_first_seed,
           V5: lambda: SCALES[scale].v5.first_seed}.get(name, lambda: 0)()
  return tuple(range(first, first + seeds))


def _check_args(name: str, scale: str, seeds: int, data: str | None,
                eval_data: tuple[str, ...]) -> None:
  require(name in PLANS, f"unknown plan {name!r}; choose from {', '.join(PLANS)}")
  require(scale in SCALES, f"--scale {scale}: choose from {', '.join(SCALES)}")
  v3_scales = [s.name for s in SCALES.values() if s.v3 is not None]
  require(name not in V3_PLANS or scale in v3_scales,
          f"--scale {scale}: plan {name} runs at {' or '.join(v3_scales)} (docs/plan-v3.md)")
  v4_scales = [s.name for s in SCALES.values() if s.v4 is not None]
  require(name not in V4_PLANS or scale in v4_scales,
          f"--scale {scale}: plan {name} runs at {' or '.join(v4_scales)} (docs/plan-v4.md)")
  require(seeds >= 1, f"--seeds {seeds}: must be at least 1")
  v5_scales = [s.name for s in SCALES.values() if s.v5 is not None]
  require(name != V5 or scale in v5_scales,
          f"--scale {scale}: plan v5 runs at {' or '.join(v5_scales)} (docs/plan-v5.md)")
  if name == V5:
    require(seeds <= SCALES[scale].v5.seeds,
            f"--seeds {seeds}: plan v5 pre-registered {SCALES[scale].v5.seeds} seeds at scale "
            f"{scale} (docs/plan-v5.md); fewer run a part of them")
  design = SCALES[scale].v4
  if name == V4 and design.regime not in (None, NO_REGIME):
    require(design.grid_seeds is not None,
            f"plan v4: the number of seeds at scale {scale} is not committed yet: `sljax "
            "experiment regime` prints n by the plan's 24-hour rule; commit it (V4Design."
            "grid_seeds, docs/plan-v4.md) before the first grid cell runs")
    require(seeds == design.grid_seeds,
            f"--seeds {seeds}: plan v4 runs the {design.grid_seeds} seeds committed at scale "
            f"{scale} by the plan's 24-hour rule (docs/plan-v4.md)")
  require(name in ("table3", "table3-v2") or not eval_data,
          "--eval-data applies to the table3 plans (scoring trained models on other data)")
  require(name in V1_PLANS or data is None,
          f"--data: plan {name} scores on fixed synthetic test sets; training on your folder "
          "needs its own test groups kept out of training, which the v1 plans' held-out split "
          "does not do (use a v1 plan, or score your data with table3-v2's --eval-data)")
  for folder in (data, *eval_data):
    if folder is not None:
      files.require_folder(folder, "dataset folder")


def committed(name: str, sc: Scale) -> dict[tuple[str, str], int]:
  """{(arm or "*", phase): epochs} committed in scales.py for a plan's design (v5 its own)."""
  return dict(sc.v5.budgets if name == V5 and sc.v5 is not None else sc.v2.budgets)


def _epochs(name: str, sc: Scale, found: Budgets) -> Epochs:
  """A calibrated plan's epochs: committed budgets win, else the ones its OUT's calibration
  found; SljaxError for an arm and phase with neither."""
  table, here = committed(name, sc), dict(found)

  def epochs(arm: str, phase: str) -> int:
    for key in ((arm, phase), ("*", phase)):
      if key in table:
        return table[key]
    require((arm, phase) in here,
            f"scale {sc.name} has no calibrated budget for {arm} ({phase}) yet: `sljax "
            f"experiment run {name} OUT --scale {sc.name}` runs the calibration cells first "
            "(docs/plan-v2.md)")
    return here[(arm, phase)]
  return epochs


def asked(name: str, sc: Scale) -> set[tuple[str, str]]:
  """The (arm, phase) budgets a calibrated plan's cells ask for."""
  found: set[tuple[str, str]] = set()
  BUILDERS[name][0](Seeded(sc, 0, None, (), lambda arm, phase: found.add((arm, phase)) or 1))
  return found


def needs_calibration(name: str, scale: str) -> bool:
  """Whether a plan's cells wait for calibration cells in its OUT: a calibrated plan (v2, v5)
  with an (arm, phase) that the scale has no committed budget for."""
  if name not in CALIBRATED:
    return False
  sc, table = SCALES[scale], committed(name, SCALES[scale])
  return any(k not in table and ("*", k[1]) not in table for k in asked(name, sc))


def build_plan(name: str, scale: str = "cpu", seeds: int = 3, data: str | None = None,
               eval_data: tuple[str, ...] = (), budgets: Budgets = ()) -> Plan:
  """The cells of a shipped plan; budgets: those its OUT's calibration found (plan.json). Each
  cell of a plan calibrated in its OUT waits for the calibration cells. SljaxError for an
  unknown plan or scale, or a calibrated plan without a budget for one of its cells."""
  _check_args(name, scale, seeds, data, eval_data)
  sc = dataclasses.replace(SCALES[scale], t=_pattern_count(data, SCALES[scale]))
  build, baseline = BUILDERS[name]
  epochs = _v1_epochs(sc) if name not in CALIBRATED else _epochs(name, sc, budgets)
  seed_list = plan_seeds(name, scale, seeds)
  cells = [c for seed in seed_list
           for c in build(Seeded(sc, seed, data, tuple(eval_data), epochs))]
  if needs_calibration(name, scale):
    waits = tuple(c.name for c in calibration_plan(name, scale).cells)
    cells = [dataclasses.replace(c, waits=waits) for c in cells]
  return Plan(name, sc, seed_list, tuple(cells), baseline, data, tuple(eval_data),
              tuple(sorted(budgets)) if needs_calibration(name, scale) else ())


def provisional_plan(name: str, scale: str, seeds: int, data: str | None = None,
                     eval_data: tuple[str, ...] = ()) -> Plan:
  """Before its calibration: the plan with every uncalibrated budget at its long run's epochs
  (the most the plateau rule can give), each cell waiting for the calibration cells. For
  pricing a grid; never registered or run."""
  long_epochs = dict(SCALES[scale].v2.calib_epochs)
  found = tuple(((arm, phase), long_epochs[phase]) for arm, phase in asked(name, SCALES[scale]))
  return build_plan(name, scale, seeds, data, eval_data, found)


def calibration_plan(name: str, scale: str) -> Plan:
  """The long runs that set a calibrated plan's budgets (docs/plan-v2.md): one cell per arm and
  phase the plan asks a budget for, seed 0, at the scale's calibration epochs, fixed learning
  rate, every validation scene; a fine-tuning run starts from the same arm's long objects run."""
  require(name in CALIBRATED, f"calibrate: {name!r} is not a calibrated plan; choose from "
          f"{', '.join(CALIBRATED)}")
  _check_args(name, scale, 1, None, ())
  able = [s.name for s in SCALES.values() if (name != V5 or s.v5 is not None)
          and {p for _, p in asked(name, s)} <= set(dict(s.v2.calib_epochs))]
  require(scale in able, f"calibrate --scale {scale}: the scale has no calibration epochs for "
          f"plan {name}; calibrate it at {', '.join(able[:-1])} or {able[-1]}")
  sc = SCALES[scale]
  long_epochs = dict(sc.v2.calib_epochs)
  phases = {p for _, p in asked(name, sc)}
  build, baseline = BUILDERS[name]
  # v5's cells ask no budget for fine-tuning (a fixed number of steps): only the phases asked.
  cells = [dataclasses.replace(
      c, name=CALIB_PREFIX + c.name.removesuffix("-s0"), evals=(), windows=(),
      init_cell=None if c.init_cell is None else CALIB_PREFIX + c.init_cell.removesuffix("-s0"),
      config=dataclasses.replace(c.config, lr_drop_epoch=None, max_val=None))
      for c in build(Seeded(sc, 0, None, (), lambda arm, phase: long_epochs[phase]))
      if phase_of(c) in phases]
  return Plan(CALIBRATE + name, sc, (0,), tuple(cells), baseline)


def phase_of(cell: Cell) -> str:
  """The budget phase of a cell: objects (all data), 1/16 or finetune."""
  if cell.init_cell is not None:
    return "finetune"
  return "1/16" if cell.config.fraction != "1" else "objects"


def check_unique(plan: Plan) -> None:
  """Every cell name once, and fine-tuning cells come after the cell they start from."""
  seen: set[str] = set()
  for cell in plan.cells:
    if cell.name in seen:
      raise SljaxError(f"plan {plan.name}: cell {cell.name} appears twice")
    require(cell.init_cell is None or cell.init_cell in seen,
            f"plan {plan.name}: cell {cell.name} fine-tunes {cell.init_cell}, which comes later")
    seen.add(cell.name)


def describe(plan: Plan) -> str:
  """One paragraph: the plan, its scale and its size."""
  sc = plan.scale
  return (f"plan {plan.name}, scale {sc.name} ({sc.size}x{sc.size}, t = {sc.t}, maxdisp "
          f"{sc.maxdisp}, batch {sc.batch_size}, Adam {sc.lr:g}; {sc.note}): "
          f"{len(plan.cells)} cells over {len(plan.seeds)} seed(s)"
          + (f", data {plan.data}" if plan.data else ""))
