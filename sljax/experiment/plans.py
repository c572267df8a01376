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

Plans:
- table1: unet-sl (disparity by correlating its predicted patterns) vs unet-disp, trained on
  objects, then fine-tuned on scarce tissue (or on --data) from the objects model.
- table2: the five strategies x {all, 1/16 of the training split} on objects (or --data).
- table3: table2's full-data models scored on the tissue domain and on --eval-data folders.
- fig7: table2's full-data models fine-tuned on scarce tissue (or --data), with curves.
"""

import dataclasses
from pathlib import Path
from typing import Any

from sljax.errors import SljaxError, require
from sljax.losses.weighting import STRATEGIES
from sljax.train.config import QUICK, TrainConfig
from sljax.train.state import LR_DROP

PLANS = ("table1", "table2", "table3", "fig7")
HELDOUT = "heldout"


@dataclasses.dataclass(frozen=True)
class Scale:
  """The sizes of a plan: image and pattern counts, data, epochs, optimiser."""
  name: str
  size: int                # training = render size (square)
  t: int                   # patterns per view, both domains (objects binary, tissue Gray)
  maxdisp: int
  objects_n: int           # synthetic objects scenes (train + held-out)
  tissue_n: int            # synthetic tissue scenes: the scarce fine-tuning set
  epochs: int              # objects training, all of the training split
  small_epochs: int        # objects training on 1/16 of it
  finetune_epochs: int
  batch_size: int
  lr: float
  lr_drop: bool            # lr 10x lower for the last quarter of the epochs; fine-tuning
                           # continues at the lower rate (else fixed, as the paper)
  corr_window: int         # unet-sl's correlation window (17 at 256 px, scaled with size)
  unet_width: int
  unet_depth: int
  val_every: int           # epochs between validations (training curves)
  small_val_every: int
  max_val: int | None      # validation scenes for the curves (the report scores all)
  note: str


SCALES = {s.name: s for s in (
    Scale("smoke", size=32, t=5, maxdisp=16, objects_n=40, tissue_n=20, epochs=2,
          small_epochs=2, finetune_epochs=2, batch_size=2, lr=1e-3, lr_drop=False,
          corr_window=3, unet_width=4, unet_depth=2, val_every=1, small_val_every=1,
          max_val=4, note="a few minutes on a CPU; the tests run it"),
    Scale("cpu", size=64, t=6, maxdisp=16, objects_n=400, tissue_n=80, epochs=12,
          small_epochs=96, finetune_epochs=40, batch_size=4, lr=1e-3, lr_drop=True,
          corr_window=5, unet_width=16, unet_depth=4, val_every=1, small_val_every=8,
          max_val=40,
          note="fits a 2-core CPU: 64x64 with 6 patterns keeps the finest stripe about "
               "1.5 px wide, as 8 patterns at 256x256; Adam 1e-3 dropping to 1e-4 for the "
               "last quarter of the epochs brings validation to a plateau within the budget; "
               "the 1/16 runs take 8x the epochs (half the full runs' steps), which their "
               "plateau needs"),
    Scale("paper", size=256, t=8, maxdisp=96, objects_n=8000, tissue_n=500, epochs=120,
          small_epochs=120, finetune_epochs=40, batch_size=12, lr=1e-4, lr_drop=False,
          corr_window=17, unet_width=32, unet_depth=4, val_every=1, small_val_every=1,
          max_val=None,
          note="the paper's sizes (256x256, maxdisp 96, 120 epochs, Adam 1e-4); for an "
               "accelerator"),
)}


@dataclasses.dataclass(frozen=True)
class EvalSet:
  """Scenes a cell is scored on: its own held-out split, the held-out split of a synthetic
  domain (rendered from the cell's seed), or every scene of a folder."""
  name: str
  kind: str                # "heldout" | "synthetic" | "folder"
  domain: str | None = None
  n: int | None = None
  path: str | None = None


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

  def spec(self) -> dict[str, Any]:
    """What identifies the run (plan.json): a changed spec under one name is refused. The
    evaluation sets are not part of it: a trained cell can be scored on more sets later."""
    # Not the run's identity (older plan.json lack the last two): init_from is init_cell's,
    # tensorboard is an output only, ynn changes float rounding only and is resolved per
    # machine (each cell's config.json keeps it).
    config = {k: v for k, v in self.config.to_json().items()
              if k not in ("init_from", "tensorboard", "ynn")}
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


def _frac_label(fraction: str) -> str:
  return "all" if fraction == "1" else fraction


def _drop(scale: Scale, epochs: int) -> int | None:
  return epochs - epochs // 4 if scale.lr_drop else None


def _base(scale: Scale, seed: int, epochs: int | None = None) -> TrainConfig:
  """The scale's TrainConfig for objects training (paper losses and strategies)."""
  epochs = scale.epochs if epochs is None else epochs
  return dataclasses.replace(
      QUICK, preset=f"experiment-{scale.name}", seed=seed, size=(scale.size, scale.size),
      synth_size=scale.size, synth_t=scale.t, maxdisp=scale.maxdisp, synth_n=scale.objects_n,
      epochs=epochs, batch_size=scale.batch_size, lr=scale.lr, lr_drop_epoch=_drop(scale, epochs),
      corr_window=scale.corr_window, unet_width=scale.unet_width, unet_depth=scale.unet_depth,
      val_every=scale.val_every, max_val=scale.max_val, keep=2)


def _on_target(config: TrainConfig, scale: Scale, data: str | None) -> TrainConfig:
  """The config moved to the fine-tuning target (scarce synthetic tissue, or the user's data):
  every epoch validated, the learning rate where pretraining ended."""
  lr = config.lr * (LR_DROP if config.lr_drop_epoch is not None else 1.0)
  moved = dataclasses.replace(config, epochs=scale.finetune_epochs, val_every=1, lr=lr,
                              lr_drop_epoch=None)
  if data is not None:
    return dataclasses.replace(moved, data=data)
  return dataclasses.replace(moved, domain="tissue", synth_n=scale.tissue_n)


def _psmnet_name(strategy: str, where: str, fraction: str, seed: int) -> str:
  frac = "" if fraction == "1" else "-f" + fraction.replace("/", "_")
  return f"psmnet-{strategy}-{where}{frac}-s{seed}"


def _table2_cells(scale: Scale, seed: int, data: str | None, fractions: tuple[str, ...],
                  evals: tuple[EvalSet, ...]) -> list[Cell]:
  where = "data" if data else "objects"
  cells = []
  for fraction in fractions:
    small = fraction != "1"
    for strategy in STRATEGIES:
      config = dataclasses.replace(
          _base(scale, seed, scale.small_epochs if small else scale.epochs), model="psmnet",
          strategy=strategy, fraction=fraction, data=data,
          val_every=scale.small_val_every if small else scale.val_every)
      cells.append(Cell(_psmnet_name(strategy, where, fraction, seed), strategy,
                        (("data", _frac_label(fraction)),), seed, config, evals=evals))
  return cells


def _pattern_count(data: str | None, scale: Scale) -> int:
  """Patterns per view: the user's folder's (so pretraining matches it), else the scale's."""
  if data is None:
    return scale.t
  from sljax.data.dataset import FolderSource  # pylint: disable=import-outside-toplevel
  t = FolderSource(data).num_patterns
  return scale.t if t is None else t


def build_plan(name: str, scale: str = "cpu", seeds: int = 3, data: str | None = None,
               eval_data: tuple[str, ...] = ()) -> Plan:
  """The cells of a shipped plan; SljaxError for an unknown plan or scale."""
  require(name in PLANS, f"unknown plan {name!r}; choose from {', '.join(PLANS)}")
  require(scale in SCALES, f"--scale {scale}: choose from {', '.join(SCALES)}")
  require(seeds >= 1, f"--seeds {seeds}: must be at least 1")
  require(name == "table3" or not eval_data,
          "--eval-data applies to the table3 plan (scoring trained models on other data)")
  for folder in (data, *eval_data):
    require(folder is None or Path(folder).is_dir(), f"{folder}: dataset folder does not exist")
  sc = dataclasses.replace(SCALES[scale], t=_pattern_count(data, SCALES[scale]))
  heldout = EvalSet(HELDOUT, "heldout")
  cells: list[Cell] = []
  for seed in range(seeds):
    if name == "table1":
      for model in ("unet-sl", "unet-disp"):
        pre = dataclasses.replace(_base(sc, seed), model=model, strategy="stl")
        pre_name = f"{model}-objects-s{seed}"
        cells.append(Cell(pre_name, model, (("data", "objects"),), seed, pre, evals=(heldout,)))
        target = "data" if data else "tissue"
        cells.append(Cell(f"{model}-{target}-ft-s{seed}", model, (("data", target),), seed,
                          _on_target(pre, sc, data), init_cell=pre_name, evals=(heldout,)))
    elif name == "table2":
      cells += _table2_cells(sc, seed, data, ("1", "1/16"), (heldout,))
    elif name == "table3":
      evals = (heldout, EvalSet("tissue", "synthetic", domain="tissue", n=sc.tissue_n))
      evals += tuple(EvalSet(Path(p).name, "folder", path=str(Path(p).resolve()))
                     for p in eval_data)
      cells += _table2_cells(sc, seed, data, ("1",), evals)
    else:  # fig7
      pretrained = _table2_cells(sc, seed, None, ("1",), (heldout,))
      cells += pretrained
      target = "data" if data else "tissue"
      for pre in pretrained:
        cells.append(Cell(_psmnet_name(pre.arm, f"{target}-ft", "1", seed), pre.arm,
                          (("data", target),), seed, _on_target(pre.config, sc, data),
                          init_cell=pre.name, evals=(heldout,)))
  baseline = "unet-disp" if name == "table1" else "stl"
  return Plan(name, sc, tuple(range(seeds)), tuple(cells), baseline, data, tuple(eval_data))


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
