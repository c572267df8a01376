"""Experiment plans: the grids of training runs behind the paper's tables, at three scales.

A plan expands into cells, one training run each (a TrainConfig plus what the runner needs:
the cell it fine-tunes from, the sets it is scored on). Cells are named from their
coordinates, so plans that share a run (table3 and fig7 reuse table2's full-data models)
share the cell when they run under one OUT.

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
from pathlib import Path
from typing import Any

from sljax.data.dataset import FolderSource
from sljax.errors import SljaxError, require
from sljax.io import files
from sljax.losses.weighting import SINGLE_TASK, STRATEGIES
from sljax.train.config import FIELDS, LATER_FIELDS, QUICK, TrainConfig
from sljax.train.state import LR_DROP
# The scales and their designs live in scales.py; plans.SCALES and plans.NO_REGIME stay public.
from sljax.experiment.design.scales import NO_REGIME, SCALES, Scale

V1_PLANS = ("table1", "table2", "table3", "fig7")
V2_PLANS = ("table1-v2", "table2-v2", "table3-v2", "fig7-v2")
V3_PILOT = "v3-pilot"
V3_PLANS = (V3_PILOT, "v3")
V4_PILOT = "v4-pilot"
V4 = "v4"
V4_PLANS = (V4_PILOT, V4)
V3_ARMS = ("stl", "unc", "epr")
PLANS = V1_PLANS + V2_PLANS + V3_PLANS + V4_PLANS
HELDOUT = "heldout"
FIXED = "fixed"           # EvalSet kind of a v2 test set
TEST_SEED = 1_000_003     # dataset seed of the v2 test sets (no training seed is near it)
PHASES = ("objects", "1/16", "finetune")  # the budgets of a scale: all data, 1/16, fine-tuning




@dataclasses.dataclass(frozen=True)
class EvalSet:
  """Scenes a cell is scored on: its own held-out split, the held-out split of a synthetic
  domain (rendered from the cell's seed), a fixed test set (every scene of a synthetic domain
  rendered from TEST_SEED at the cell's size and pattern count), or every scene of a
  folder; scored with the cell's final checkpoint, or its best by validation MAE."""
  name: str
  kind: str                # "heldout" | "synthetic" | "fixed" | "folder"
  domain: str | None = None
  n: int | None = None
  path: str | None = None
  checkpoint: str = "final"  # "final" | "best"


@dataclasses.dataclass(frozen=True)
class Cell:
  """One training run of a plan."""
  name: str
  arm: str                 # the row it reports under: a strategy or a model
  factors: tuple[tuple[str, str], ...]  # the other coordinates, e.g. (("data", "1/16"),)
  seed: int
  config: TrainConfig      # init_from is filled in by the runner from init_cell
  init_cell: str | None = None
  evals: tuple[EvalSet, ...] = ()
  windows: tuple[int, ...] = ()  # unet-sl, v2: correlation windows chosen from on validation

  def spec(self) -> dict[str, Any]:
    """What identifies the run (plan.json): a changed spec under one name is refused. The
    evaluation sets are not part of it: a trained cell can be scored on more sets later."""
    # Not the run's identity (older plan.json lack the last two): init_from is init_cell's,
    # tensorboard is an output only, ynn and conv_impl change float rounding only (the fast
    # kernels equal lax's) and are chosen per machine (each cell's config.json keeps them).
    config = {k: v for k, v in self.config.to_json().items()
              if k not in ("init_from", "tensorboard", "ynn", "conv_impl")
              and not (k in LATER_FIELDS and v == FIELDS[k].default)}
    return {"arm": self.arm, "factors": [list(f) for f in self.factors], "seed": self.seed,
            "config": config, "init_cell": self.init_cell}


@dataclasses.dataclass(frozen=True)
class Plan:
  """A grid of cells and how its report compares them."""
  name: str
  scale: Scale
  seeds: tuple[int, ...]
  cells: tuple[Cell, ...]
  baseline: str            # the arm every other arm is compared with (paired by seed)
  data: str | None = None
  eval_data: tuple[str, ...] = ()

  def cells_of(self, **factors: str) -> list[Cell]:
    """The cells whose factors include the given ones."""
    return [c for c in self.cells if all((k, v) in c.factors for k, v in factors.items())]


# ----------------------------------------------------------------------------- configurations


def _frac_label(fraction: str) -> str:
  return "all" if fraction == "1" else fraction


def _drop(scale: Scale, epochs: int) -> int | None:
  return epochs - epochs // 4 if scale.lr_drop else None


def _base(scale: Scale, seed: int, epochs: int | None = None) -> TrainConfig:
  """The scale's TrainConfig for objects training (paper losses and strategies)."""
  epochs = scale.schedule.epochs if epochs is None else epochs
  return dataclasses.replace(
      QUICK, preset=f"experiment-{scale.name}", seed=seed, size=(scale.size, scale.size),
      synth_size=scale.size, synth_t=scale.t, maxdisp=scale.maxdisp, synth_n=scale.objects_n,
      epochs=epochs, batch_size=scale.batch_size, lr=scale.lr, lr_drop_epoch=_drop(scale, epochs),
      corr_window=scale.corr_window, unet_width=scale.unet_width, unet_depth=scale.unet_depth,
      val_every=scale.schedule.val_every, max_val=scale.max_val, keep=2, ynn=scale.ynn,
      conv_impl=scale.conv_impl)


def _on_target(config: TrainConfig, scale: Scale, data: str | None,
               epochs: int | None = None) -> TrainConfig:
  """The config moved to the fine-tuning target (scarce synthetic tissue, or the user's data):
  every epoch validated, the learning rate where pretraining ended."""
  lr = config.lr * (LR_DROP if config.lr_drop_epoch is not None else 1.0)
  moved = dataclasses.replace(
      config, epochs=scale.schedule.finetune_epochs if epochs is None else epochs, val_every=1,
      lr=lr, lr_drop_epoch=None)
  if data is not None:
    return dataclasses.replace(moved, data=data)
  return dataclasses.replace(moved, domain="tissue", synth_n=scale.tissue_n)


def _psmnet_name(strategy: str, where: str, fraction: str, seed: int) -> str:
  frac = "" if fraction == "1" else "-f" + fraction.replace("/", "_")
  return f"psmnet-{strategy}-{where}{frac}-s{seed}"


def test_set(domain: str, scale: Scale, checkpoint: str = "final") -> EvalSet:
  """The fixed v2 test set of a synthetic domain at a scale (scoring the final checkpoint, or
  the best by validation: set name suffixed "-best")."""
  suffix = "" if checkpoint == "final" else f"-{checkpoint}"
  return EvalSet(f"test-{domain}{suffix}", FIXED, domain=domain, n=scale.v2.test_n,
                 checkpoint=checkpoint)


def _folders(eval_data: tuple[str, ...]) -> tuple[EvalSet, ...]:
  """Scoring sets of whole scene-format folders (table3's --eval-data)."""
  return tuple(EvalSet(Path(p).name, "folder", path=str(Path(p).resolve())) for p in eval_data)


# ----------------------------------------------------------------------------- cells by plan


Epochs = Callable[[str, str], int]  # (arm, phase) -> training epochs


@dataclasses.dataclass(frozen=True)
class Seeded:
  """What a plan's cells of one seed are made from."""
  scale: Scale
  seed: int
  data: str | None
  eval_data: tuple[str, ...]
  epochs: Epochs           # v1: the scale's schedule; v2: its calibrated budgets


def _v1_epochs(scale: Scale) -> Epochs:
  s = scale.schedule
  by_phase = {"objects": s.epochs, "1/16": s.small_epochs, "finetune": s.finetune_epochs}
  return lambda arm, phase: by_phase[phase]


def _strategy_cells(a: Seeded, data: str | None, fractions: tuple[str, ...],
                    evals: tuple[EvalSet, ...]) -> list[Cell]:
  """table2's cells: every strategy at each training fraction, on objects (or `data`)."""
  sc, where = a.scale, "data" if data else "objects"
  cells = []
  for fraction in fractions:
    small = fraction != "1"
    for strategy in STRATEGIES:
      config = dataclasses.replace(
          _base(sc, a.seed, a.epochs(strategy, "1/16" if small else "objects")),
          model="psmnet", strategy=strategy, fraction=fraction, data=data,
          val_every=sc.schedule.small_val_every if small else sc.schedule.val_every)
      cells.append(Cell(_psmnet_name(strategy, where, fraction, a.seed), strategy,
                        (("data", _frac_label(fraction)),), a.seed, config, evals=evals))
  return cells


def _fine_tuned(a: Seeded, pretrained: list[Cell], target: str, data: str | None,
                evals: tuple[EvalSet, ...]) -> list[Cell]:
  """fig7's cells: each pretrained PSMNet fine-tuned on the target."""
  return [Cell(_psmnet_name(pre.arm, f"{target}-ft", "1", a.seed), pre.arm,
               (("data", target),), a.seed,
               _on_target(pre.config, a.scale, data, a.epochs(pre.arm, "finetune")),
               init_cell=pre.name, evals=evals) for pre in pretrained]


def _unets(a: Seeded, target: str, data: str | None, pre_evals: tuple[EvalSet, ...],
           ft_evals: tuple[EvalSet, ...], windows: tuple[int, ...]) -> list[Cell]:
  """table1's cells: unet-sl and unet-disp on objects, then fine-tuned on the target."""
  cells = []
  for model in ("unet-sl", "unet-disp"):
    chosen = windows if model == "unet-sl" else ()
    pre = dataclasses.replace(_base(a.scale, a.seed, a.epochs(model, "objects")), model=model,
                              strategy=SINGLE_TASK)
    pre_name = f"{model}-objects-s{a.seed}"
    cells.append(Cell(pre_name, model, (("data", "objects"),), a.seed, pre, evals=pre_evals,
                      windows=chosen))
    cells.append(Cell(f"{model}-{target}-ft-s{a.seed}", model, (("data", target),), a.seed,
                      _on_target(pre, a.scale, data, a.epochs(model, "finetune")),
                      init_cell=pre_name, evals=ft_evals, windows=chosen))
  return cells


HELD = (EvalSet(HELDOUT, "heldout"),)


def _table1(a: Seeded) -> list[Cell]:
  target = "data" if a.data else "tissue"
  return _unets(a, target, a.data, HELD, HELD, ())


def _table2(a: Seeded) -> list[Cell]:
  return _strategy_cells(a, a.data, ("1", "1/16"), HELD)


def _table3(a: Seeded) -> list[Cell]:
  tissue = EvalSet("tissue", "synthetic", domain="tissue", n=a.scale.tissue_n)
  return _strategy_cells(a, a.data, ("1",), HELD + (tissue,) + _folders(a.eval_data))


def _fig7(a: Seeded) -> list[Cell]:
  pretrained = _strategy_cells(a, None, ("1",), HELD)
  return pretrained + _fine_tuned(a, pretrained, "data" if a.data else "tissue", a.data, HELD)


def _table1_v2(a: Seeded) -> list[Cell]:
  objects, tissue = test_set("objects", a.scale), test_set("tissue", a.scale)
  return _unets(a, "tissue", None, (objects,), (tissue,), a.scale.v2.windows)


def _table2_v2(a: Seeded) -> list[Cell]:
  return _strategy_cells(a, None, ("1/16",), (test_set("objects", a.scale),))


def _table3_v2(a: Seeded) -> list[Cell]:
  evals = (test_set("tissue", a.scale), test_set("objects", a.scale)) + _folders(a.eval_data)
  return _strategy_cells(a, None, ("1",), evals)


def _fig7_v2(a: Seeded) -> list[Cell]:
  pretrained = _strategy_cells(a, None, ("1",), (test_set("objects", a.scale),))
  return pretrained + _fine_tuned(a, pretrained, "tissue", None,
                                  (test_set("tissue", a.scale),))


def _v3_pilot(a: Seeded) -> list[Cell]:
  """stl on objects at each of the design's fractions, constant learning rate, the pilot's
  budget, every validation scene every val_every epochs; curves only (no test set)."""
  design = a.scale.v3
  cells = []
  for fraction in design.fractions:
    config = dataclasses.replace(
        _base(a.scale, a.seed, design.pilot_epochs), model="psmnet", strategy=SINGLE_TASK,
        fraction=fraction, lr_drop_epoch=None, val_every=design.val_every, max_val=None)
    cells.append(Cell("pilot-" + _psmnet_name(SINGLE_TASK, "objects", fraction, a.seed),
                      SINGLE_TASK, (("data", fraction),), a.seed, config))
  return cells


def _require_regime(plan: str, scale: str, regime: Any, run: str, where: str) -> None:
  """SljaxError while a grid's pilot has no committed regime, or when it found none."""
  require(regime is not None,
          f"plan {plan}: scale {scale} has no regime yet: {run} (`sljax experiment run "
          f"{plan}-pilot`), apply the rule (`sljax experiment regime`) and commit the regime "
          f"with the outcome in docs/plan-{plan}.md")
  require(regime != NO_REGIME,
          f"plan {plan}: at scale {scale} the pilot found no {where} where stl overfits "
          f"(docs/plan-{plan}.md, the pilot's outcome), so by the pre-registered rule {plan} "
          "ends there and no test cell runs")


def _v3(a: Seeded) -> list[Cell]:
  """stl, unc and epr in the pilot's regime (fraction and budget), constant learning rate,
  every validation scene every val_every epochs; scored on the fixed test sets."""
  design = a.scale.v3
  _require_regime("v3", a.scale.name, design.regime, "run the pilot", "training fraction")
  fraction, epochs = design.regime
  evals = (test_set("objects", a.scale), test_set("tissue", a.scale),
           test_set("objects", a.scale, "best"))
  cells = []
  for strategy in V3_ARMS:
    config = dataclasses.replace(
        _base(a.scale, a.seed, epochs), model="psmnet", strategy=strategy, fraction=fraction,
        lr_drop_epoch=None, val_every=design.val_every, max_val=None)
    cells.append(Cell(_psmnet_name(strategy, "objects", fraction, a.seed), strategy,
                      (("data", fraction),), a.seed, config, evals=evals))
  return cells


def _v4_pilot(a: Seeded) -> list[Cell]:
  """stl with budgets in steps, constant learning rates, every validation scene every
  val_every steps; curves only. From scratch on objects at each scratch fraction; and the
  paper's setting: an objects model on all the data, fine-tuned on each tissue fraction."""
  design = a.scale.v4
  base = dataclasses.replace(_base(a.scale, a.seed), model="psmnet", strategy=SINGLE_TASK,
                             lr_drop_epoch=None, max_val=None)
  cells = []
  for fraction in design.scratch_fractions:
    config = dataclasses.replace(base, fraction=fraction, steps=design.scratch_steps,
                                 val_every_steps=design.val_every)
    cells.append(Cell("pilot4-" + _psmnet_name(SINGLE_TASK, "objects", fraction, a.seed),
                      SINGLE_TASK, (("setting", "scratch"), ("data", fraction)), a.seed, config))
  pre = dataclasses.replace(base, steps=design.pretrain_steps,
                            val_every_steps=design.pretrain_val_every)
  pre_name = "pilot4-" + _psmnet_name(SINGLE_TASK, "objects", "1", a.seed)
  cells.append(Cell(pre_name, SINGLE_TASK, (("setting", "pretrain"), ("data", "all")), a.seed,
                    pre))
  for fraction in design.finetune_fractions:
    config = dataclasses.replace(pre, domain="tissue", synth_n=a.scale.tissue_n,
                                 fraction=fraction, lr=design.finetune_lr,
                                 steps=design.finetune_steps, val_every_steps=design.val_every)
    cells.append(Cell("pilot4-" + _psmnet_name(SINGLE_TASK, "tissue-ft", fraction, a.seed),
                      SINGLE_TASK, (("setting", "finetune"), ("data", fraction)), a.seed, config,
                      init_cell=pre_name))
  return cells


def _v4(a: Seeded) -> list[Cell]:
  """stl, unc and epr in the pilot's regime (setting, fraction, steps), constant learning
  rates, every validation scene every val_every steps; the final and the best checkpoint scored
  on the setting's fixed test set. Fine-tuning starts each arm from its own objects model."""
  design = a.scale.v4
  _require_regime("v4", a.scale.name, design.regime, "finish the pilot", "setting")
  setting, fraction, steps = design.regime
  domain = "tissue" if setting == "finetune" else "objects"
  evals = (test_set(domain, a.scale), test_set(domain, a.scale, "best"))
  base = dataclasses.replace(_base(a.scale, a.seed), model="psmnet", lr_drop_epoch=None,
                             max_val=None)
  factors = (("setting", setting), ("data", fraction))
  cells = []
  for strategy in V3_ARMS:
    arm = dataclasses.replace(base, strategy=strategy)
    if setting == "scratch":
      config = dataclasses.replace(arm, fraction=fraction, steps=steps,
                                   val_every_steps=design.val_every)
      cells.append(Cell("v4-" + _psmnet_name(strategy, "objects", fraction, a.seed), strategy,
                        factors, a.seed, config, evals=evals))
      continue
    pre = dataclasses.replace(arm, steps=design.pretrain_steps,
                              val_every_steps=design.pretrain_val_every)
    pre_name = "v4-" + _psmnet_name(strategy, "objects", "1", a.seed)
    cells.append(Cell(pre_name, strategy, (("setting", "pretrain"), ("data", "all")), a.seed,
                      pre))
    config = dataclasses.replace(pre, domain="tissue", synth_n=a.scale.tissue_n,
                                 fraction=fraction, lr=design.finetune_lr, steps=steps,
                                 val_every_steps=design.val_every)
    cells.append(Cell("v4-" + _psmnet_name(strategy, "tissue-ft", fraction, a.seed), strategy,
                      factors, a.seed, config, init_cell=pre_name, evals=evals))
  return cells


# Each shipped plan: its cells for one seed, and the arm the others are compared with.
BUILDERS: dict[str, tuple[Callable[[Seeded], list[Cell]], str]] = {
    "table1": (_table1, "unet-disp"), "table2": (_table2, SINGLE_TASK),
    "table3": (_table3, SINGLE_TASK), "fig7": (_fig7, SINGLE_TASK),
    "table1-v2": (_table1_v2, "unet-disp"), "table2-v2": (_table2_v2, SINGLE_TASK),
    "table3-v2": (_table3_v2, SINGLE_TASK), "fig7-v2": (_fig7_v2, SINGLE_TASK),
    V3_PILOT: (_v3_pilot, SINGLE_TASK), "v3": (_v3, SINGLE_TASK),
    V4_PILOT: (_v4_pilot, SINGLE_TASK), V4: (_v4, SINGLE_TASK),
}


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
  build, baseline = BUILDERS[name]
  epochs = _v1_epochs(sc) if name in V1_PLANS else sc.budget
  seed_list = plan_seeds(name, scale, seeds)
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
