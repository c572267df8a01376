"""The cells of the paper's tables and figure 7, in both designs: v1 (table1, table2, table3,
fig7: each cell scored on its own held-out split) and v2 (table1-v2, ...: scored on the fixed
test sets). A v2 cell trains exactly as the v1 cell of the same name; sljax.experiment.design.plans
says what each plan is.
"""

import dataclasses
from pathlib import Path

from sljax.losses.weighting import SINGLE_TASK, STRATEGIES
from sljax.train.config import TrainConfig
from sljax.train.state import LR_DROP
from sljax.experiment.design.cells import (HELDOUT, Cell, EvalSet, Seeded, base_config,
                                           psmnet_name, test_set)
from sljax.experiment.design.scales import Scale

HELD = (EvalSet(HELDOUT, "heldout"),)


def _frac_label(fraction: str) -> str:
  return "all" if fraction == "1" else fraction


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


def _folders(eval_data: tuple[str, ...]) -> tuple[EvalSet, ...]:
  """Scoring sets of whole scene-format folders (table3's --eval-data)."""
  return tuple(EvalSet(Path(p).name, "folder", path=str(Path(p).resolve())) for p in eval_data)


def _strategy_cells(a: Seeded, data: str | None, fractions: tuple[str, ...],
                    evals: tuple[EvalSet, ...]) -> list[Cell]:
  """table2's cells: every strategy at each training fraction, on objects (or `data`)."""
  sc, where = a.scale, "data" if data else "objects"
  cells = []
  for fraction in fractions:
    small = fraction != "1"
    for strategy in STRATEGIES:
      config = dataclasses.replace(
          base_config(sc, a.seed, a.epochs(strategy, "1/16" if small else "objects")),
          model="psmnet", strategy=strategy, fraction=fraction, data=data,
          val_every=sc.schedule.small_val_every if small else sc.schedule.val_every)
      cells.append(Cell(psmnet_name(strategy, where, fraction, a.seed), strategy,
                        (("data", _frac_label(fraction)),), a.seed, config, evals=evals))
  return cells


def _fine_tuned(a: Seeded, pretrained: list[Cell], target: str, data: str | None,
                evals: tuple[EvalSet, ...]) -> list[Cell]:
  """fig7's cells: each pretrained PSMNet fine-tuned on the target."""
  return [Cell(psmnet_name(pre.arm, f"{target}-ft", "1", a.seed), pre.arm,
               (("data", target),), a.seed,
               _on_target(pre.config, a.scale, data, a.epochs(pre.arm, "finetune")),
               init_cell=pre.name, evals=evals) for pre in pretrained]


def _unets(a: Seeded, target: str, data: str | None, pre_evals: tuple[EvalSet, ...],
           ft_evals: tuple[EvalSet, ...], windows: tuple[int, ...]) -> list[Cell]:
  """table1's cells: unet-sl and unet-disp on objects, then fine-tuned on the target."""
  cells = []
  for model in ("unet-sl", "unet-disp"):
    chosen = windows if model == "unet-sl" else ()
    pre = dataclasses.replace(base_config(a.scale, a.seed, a.epochs(model, "objects")),
                              model=model, strategy=SINGLE_TASK)
    pre_name = f"{model}-objects-s{a.seed}"
    cells.append(Cell(pre_name, model, (("data", "objects"),), a.seed, pre, evals=pre_evals,
                      windows=chosen))
    cells.append(Cell(f"{model}-{target}-ft-s{a.seed}", model, (("data", target),), a.seed,
                      _on_target(pre, a.scale, data, a.epochs(model, "finetune")),
                      init_cell=pre_name, evals=ft_evals, windows=chosen))
  return cells


# ----------------------------------------------------------------------------- v1


def table1(a: Seeded) -> list[Cell]:
  """table1's cells of one seed: unet-sl and unet-disp, fine-tuned on tissue or --data."""
  target = "data" if a.data else "tissue"
  return _unets(a, target, a.data, HELD, HELD, ())


def table2(a: Seeded) -> list[Cell]:
  """table2's cells of one seed: the five strategies on all and on 1/16 of the training split."""
  return _strategy_cells(a, a.data, ("1", "1/16"), HELD)


def table3(a: Seeded) -> list[Cell]:
  """table3's cells of one seed: table2's full-data models, also scored on tissue and folders."""
  tissue = EvalSet("tissue", "synthetic", domain="tissue", n=a.scale.tissue_n)
  return _strategy_cells(a, a.data, ("1",), HELD + (tissue,) + _folders(a.eval_data))


def fig7(a: Seeded) -> list[Cell]:
  """fig7's cells of one seed: table2's full-data models and their fine-tuned twins."""
  pretrained = _strategy_cells(a, None, ("1",), HELD)
  return pretrained + _fine_tuned(a, pretrained, "data" if a.data else "tissue", a.data, HELD)


# ----------------------------------------------------------------------------- v2


def table1_v2(a: Seeded) -> list[Cell]:
  """table1-v2's cells of one seed: table1's, scored on the fixed objects and tissue sets."""
  objects, tissue = test_set("objects", a.scale), test_set("tissue", a.scale)
  return _unets(a, "tissue", None, (objects,), (tissue,), a.scale.v2.windows)


def table2_v2(a: Seeded) -> list[Cell]:
  """table2-v2's cells of one seed: table2's at 1/16, scored on the fixed objects set."""
  return _strategy_cells(a, None, ("1/16",), (test_set("objects", a.scale),))


def table3_v2(a: Seeded) -> list[Cell]:
  """table3-v2's cells of one seed: scored on the fixed tissue and objects sets and folders."""
  evals = (test_set("tissue", a.scale), test_set("objects", a.scale)) + _folders(a.eval_data)
  return _strategy_cells(a, None, ("1",), evals)


def fig7_v2(a: Seeded) -> list[Cell]:
  """fig7-v2's cells of one seed: fig7's, the fine-tuned ones scored on the fixed tissue set."""
  pretrained = _strategy_cells(a, None, ("1",), (test_set("objects", a.scale),))
  return pretrained + _fine_tuned(a, pretrained, "tissue", None,
                                  (test_set("tissue", a.scale),))
