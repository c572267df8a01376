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
PLANS = V1_PLANS + V2_PLANS + V3_PLANS + V4_PLANS
PHASES = ("objects", "1/16", "finetune")  # the budgets of a scale: all data, 1/16, fine-tuning

# Each shipped plan: its cells for one seed, and the arm the others are compared with.
BUILDERS: dict[str, tuple[Callable[[Seeded], list[Cell]], str]] = {
    "table1": (paper_tables.table1, "unet-disp"), "table2": (paper_tables.table2, SINGLE_TASK),
    "table3": (paper_tables.table3, SINGLE_TASK), "fig7": (paper_tables.fig7, SINGLE_TASK),
    "table1-v2": (paper_tables.table1_v2, "unet-disp"), "table2-v2": (paper_tables.table2_v2, SINGLE_TASK),
    "table3-v2": (paper_tables.table3_v2, SINGLE_TASK), "fig7-v2": (paper_tables.fig7_v2, SINGLE_TASK),
    V3_PILOT: (overfitting.v3_pilot, SINGLE_TASK), "v3": (overfitting.v3_grid, SINGLE_TASK),
    V4_PILOT: (overfitting.v4_pilot, SINGLE_TASK), V4: (overfitting.v4_grid, SINGLE_TASK),
}


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
           V4: lambda: SCALES[scale].v4.grid_first_seed}.get(name, lambda: 0)()
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


def build_plan(name: str, scale: str = "cpu", seeds: int = 3, data: str | None = None,
               eval_data: tuple[str, ...] = ()) -> Plan:
  """The cells of a shipped plan; SljaxError for an unknown plan or scale, or a v2 plan at a
  scale without calibrated budgets."""
  _check_args(name, scale, seeds, data, eval_data)
  sc = dataclasses.replace(SCALES[scale], t=_pattern_count(data, SCALES[scale]))
  return _build(name, sc, seeds, data, eval_data,
                _v1_epochs(sc) if name in V1_PLANS else sc.budget)


def stand_in_plan(name: str, scale: str = "cpu", seeds: int = 3, data: str | None = None,
                  eval_data: tuple[str, ...] = ()) -> tuple[Plan, tuple[tuple[str, str], ...]]:
  """The plan as build_plan makes it, except that a v2 plan's budgets the scale has not
  committed yet are v1's epochs of the phase (for pricing only: `run` refuses such a plan);
  with the (arm, phase) pairs stood in for."""
  _check_args(name, scale, seeds, data, eval_data)
  sc = dataclasses.replace(SCALES[scale], t=_pattern_count(data, SCALES[scale]))
  if name in V1_PLANS:
    return _build(name, sc, seeds, data, eval_data, _v1_epochs(sc)), ()
  table, v1, missing = dict(sc.v2.budgets), _v1_epochs(sc), []

  def epochs(arm: str, phase: str) -> int:
    committed = table.get((arm, phase), table.get(("*", phase)))
    if committed is None and (arm, phase) not in missing:
      missing.append((arm, phase))
    return v1(arm, phase) if committed is None else committed

  return _build(name, sc, seeds, data, eval_data, epochs), tuple(missing)


def _build(name: str, sc: Scale, seeds: int, data: str | None, eval_data: tuple[str, ...],
           epochs: Epochs) -> Plan:
  """The plan's cells at a scale, with these budgets."""
  build, baseline = BUILDERS[name]
  seed_list = plan_seeds(name, sc.name, seeds)
  cells = [c for seed in seed_list
           for c in build(Seeded(sc, seed, data, tuple(eval_data), epochs))]
  return Plan(name, sc, seed_list, tuple(cells), baseline, data, tuple(eval_data))


def _calib_phases(name: str, sc: Scale) -> set[str]:
  """The budget phases (PHASES) whose epochs a v2 plan's cells ask for."""
  asked: set[str] = set()
  BUILDERS[name][0](Seeded(sc, 0, None, (), lambda arm, phase: asked.add(phase) or 1))
  return asked


def calibration_plan(name: str, scale: str) -> Plan:
  """The long runs that set a v2 plan's budgets (docs/plan-v2.md): one cell per arm and phase of
  the plan, seed 0, at the scale's calibration epochs, fixed learning rate, every validation
  scene; a fine-tuning run starts from the same arm's long objects run."""
  require(name in V2_PLANS, f"calibrate: {name!r} is not a v2 plan; choose from "
          f"{', '.join(V2_PLANS)}")
  _check_args(name, scale, 1, None, ())
  able = [s.name for s in SCALES.values()
          if _calib_phases(name, s) <= set(dict(s.v2.calib_epochs))]
  require(scale in able, f"calibrate --scale {scale}: the scale has no calibration epochs for "
          f"plan {name}; calibrate it at {', '.join(able[:-1])} or {able[-1]}")
  sc = SCALES[scale]
  long_epochs = dict(sc.v2.calib_epochs)
  build, baseline = BUILDERS[name]
  cells = [dataclasses.replace(
      c, name="calib-" + c.name.removesuffix("-s0"), evals=(), windows=(),
      init_cell=None if c.init_cell is None else "calib-" + c.init_cell.removesuffix("-s0"),
      config=dataclasses.replace(c.config, lr_drop_epoch=None, max_val=None))
      for c in build(Seeded(sc, 0, None, (), lambda arm, phase: long_epochs[phase]))]
  return Plan(f"calibrate-{name}", sc, (0,), tuple(cells), baseline)


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
