"""What a plan is made of: its cells (one training run each), the sets a cell is scored on,
the plan itself, and the scale's training configuration every cell starts from.

The plans (sljax.experiment.design.plans) build these from a scale; the cells of the paper's
tables are defined in sljax.experiment.design.paper_tables, those of the v3 and v4 designs in
sljax.experiment.design.overfitting.
"""

import dataclasses
from collections.abc import Callable
from typing import Any

from sljax.train.config import FIELDS, LATER_FIELDS, QUICK, TrainConfig
from sljax.experiment.design.scales import Scale

HELDOUT = "heldout"
FIXED = "fixed"           # EvalSet kind of a v2 test set
TEST_SEED = 1_000_003     # dataset seed of the v2 test sets (no training seed is near it)


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
  # Cells that must be trained before this one starts, besides init_cell: the calibration
  # cells whose budgets set its epochs (a plan calibrated in its own OUT). Scheduling only, not
  # the run's identity: not in spec().
  waits: tuple[str, ...] = ()

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
  # ((arm, phase), epochs) the plateau rule gave in this plan's OUT (calibration-PLAN.json),
  # recorded in OUT/plan.json; () where the scale's committed budgets set every epoch.
  budgets: tuple[tuple[tuple[str, str], int], ...] = ()

  def cells_of(self, **factors: str) -> list[Cell]:
    """The cells whose factors include the given ones."""
    return [c for c in self.cells if all((k, v) in c.factors for k, v in factors.items())]


def waits_for(cell: Cell) -> tuple[str, ...]:
  """The cells that must be trained before this one may start: the cell it fine-tunes, and the
  calibration cells its budget comes from."""
  return ((cell.init_cell,) if cell.init_cell is not None else ()) + cell.waits


Epochs = Callable[[str, str], int]  # (arm, phase) -> training epochs


@dataclasses.dataclass(frozen=True)
class Seeded:
  """What a plan's cells of one seed are made from."""
  scale: Scale
  seed: int
  data: str | None
  eval_data: tuple[str, ...]
  epochs: Epochs           # v1: the scale's schedule; v2: its calibrated budgets


# ----------------------------------------------------------------------------- configurations


def _drop(scale: Scale, epochs: int) -> int | None:
  return epochs - epochs // 4 if scale.lr_drop else None


def base_config(scale: Scale, seed: int, epochs: int | None = None) -> TrainConfig:
  """The scale's TrainConfig for objects training (paper losses and strategies)."""
  epochs = scale.schedule.epochs if epochs is None else epochs
  return dataclasses.replace(
      QUICK, preset=f"experiment-{scale.name}", seed=seed, size=(scale.size, scale.size),
      synth_size=scale.size, synth_t=scale.t, maxdisp=scale.maxdisp, synth_n=scale.objects_n,
      epochs=epochs, batch_size=scale.batch_size, lr=scale.lr, lr_drop_epoch=_drop(scale, epochs),
      corr_window=scale.corr_window, unet_width=scale.unet_width, unet_depth=scale.unet_depth,
      val_every=scale.schedule.val_every, max_val=scale.max_val, keep=2, ynn=scale.ynn,
      conv_impl=scale.conv_impl)


def psmnet_name(strategy: str, where: str, fraction: str, seed: int) -> str:
  """The name of a PSMNet cell: its strategy, where it trains, its fraction and seed."""
  frac = "" if fraction == "1" else "-f" + fraction.replace("/", "_")
  return f"psmnet-{strategy}-{where}{frac}-s{seed}"


def test_set(domain: str, scale: Scale, checkpoint: str = "final") -> EvalSet:
  """The fixed v2 test set of a synthetic domain at a scale (scoring the final checkpoint, or
  the best by validation: set name suffixed "-best")."""
  suffix = "" if checkpoint == "final" else f"-{checkpoint}"
  return EvalSet(f"test-{domain}{suffix}", FIXED, domain=domain, n=scale.v2.test_n,
                 checkpoint=checkpoint)
