"""The cells of the v3, v4 and v5 designs (docs/plan-v3.md, plan-v4.md, plan-v5.md): the pilots that look for
where stl overfits (curves only, validated on the whole validation split at a constant learning
rate), and the grids of stl, unc and epr run in the regime a pilot's rule found (the scale's
V3Design.regime, V4Design.regime), scored on the fixed test sets; sljax.experiment.design.plans
says what each plan is.
"""

import dataclasses
from typing import Any

from sljax.errors import require
from sljax.losses.weighting import SINGLE_TASK
from sljax.experiment.design.cells import Cell, Seeded, base_config, psmnet_name, test_set
from sljax.experiment.design.scales import NO_REGIME

V3_ARMS = ("stl", "unc", "epr")


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


def v3_pilot(a: Seeded) -> list[Cell]:
  """stl on objects at each of the design's fractions, constant learning rate, the pilot's
  budget, every validation scene every val_every epochs; curves only (no test set)."""
  design = a.scale.v3
  cells = []
  for fraction in design.fractions:
    config = dataclasses.replace(
        base_config(a.scale, a.seed, design.pilot_epochs), model="psmnet",
        strategy=SINGLE_TASK, fraction=fraction, lr_drop_epoch=None, val_every=design.val_every,
        max_val=None)
    cells.append(Cell("pilot-" + psmnet_name(SINGLE_TASK, "objects", fraction, a.seed),
                      SINGLE_TASK, (("data", fraction),), a.seed, config))
  return cells


def v3_grid(a: Seeded) -> list[Cell]:
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
        base_config(a.scale, a.seed, epochs), model="psmnet", strategy=strategy,
        fraction=fraction, lr_drop_epoch=None, val_every=design.val_every, max_val=None)
    cells.append(Cell(psmnet_name(strategy, "objects", fraction, a.seed), strategy,
                      (("data", fraction),), a.seed, config, evals=evals))
  return cells


def v4_pilot(a: Seeded) -> list[Cell]:
  """stl with budgets in steps, constant learning rates, every validation scene every
  val_every steps; curves only. From scratch on objects at each scratch fraction; and the
  paper's setting: an objects model on all the data, fine-tuned on each tissue fraction."""
  design = a.scale.v4
  base = dataclasses.replace(base_config(a.scale, a.seed), model="psmnet",
                             strategy=SINGLE_TASK, lr_drop_epoch=None, max_val=None)
  cells = []
  for fraction in design.scratch_fractions:
    config = dataclasses.replace(base, fraction=fraction, steps=design.scratch_steps,
                                 val_every_steps=design.val_every)
    cells.append(Cell("pilot4-" + psmnet_name(SINGLE_TASK, "objects", fraction, a.seed),
                      SINGLE_TASK, (("setting", "scratch"), ("data", fraction)), a.seed, config))
  pre = dataclasses.replace(base, steps=design.pretrain_steps,
                            val_every_steps=design.pretrain_val_every)
  pre_name = "pilot4-" + psmnet_name(SINGLE_TASK, "objects", "1", a.seed)
  cells.append(Cell(pre_name, SINGLE_TASK, (("setting", "pretrain"), ("data", "all")), a.seed,
                    pre))
  for fraction in design.finetune_fractions:
    config = dataclasses.replace(pre, domain="tissue", synth_n=a.scale.tissue_n,
                                 fraction=fraction, lr=design.finetune_lr,
                                 steps=design.finetune_steps, val_every_steps=design.val_every)
    cells.append(Cell("pilot4-" + psmnet_name(SINGLE_TASK, "tissue-ft", fraction, a.seed),
                      SINGLE_TASK, (("setting", "finetune"), ("data", fraction)), a.seed, config,
                      init_cell=pre_name))
  return cells


def v4_grid(a: Seeded) -> list[Cell]:
  """stl, unc and epr in the pilot's regime (setting, fraction, steps), constant learning
  rates, every validation scene every val_every steps; the final and the best checkpoint scored
  on the setting's fixed test set. Fine-tuning starts each arm from its own objects model."""
  design = a.scale.v4
  _require_regime("v4", a.scale.name, design.regime, "finish the pilot", "setting")
  setting, fraction, steps = design.regime
  domain = "tissue" if setting == "finetune" else "objects"
  evals = (test_set(domain, a.scale), test_set(domain, a.scale, "best"))
  base = dataclasses.replace(base_config(a.scale, a.seed), model="psmnet", lr_drop_epoch=None,
                             max_val=None)
  factors = (("setting", setting), ("data", fraction))
  cells = []
  for strategy in V3_ARMS:
    arm = dataclasses.replace(base, strategy=strategy)
    if setting == "scratch":
      config = dataclasses.replace(arm, fraction=fraction, steps=steps,
                                   val_every_steps=design.val_every)
      cells.append(Cell("v4-" + psmnet_name(strategy, "objects", fraction, a.seed), strategy,
                        factors, a.seed, config, evals=evals))
      continue
    pre = dataclasses.replace(arm, steps=design.pretrain_steps,
                              val_every_steps=design.pretrain_val_every)
    pre_name = "v4-" + psmnet_name(strategy, "objects", "1", a.seed)
    cells.append(Cell(pre_name, strategy, (("setting", "pretrain"), ("data", "all")), a.seed,
                      pre))
    config = dataclasses.replace(pre, domain="tissue", synth_n=a.scale.tissue_n,
                                 fraction=fraction, lr=design.finetune_lr, steps=steps,
                                 val_every_steps=design.val_every)
    cells.append(Cell("v4-" + psmnet_name(strategy, "tissue-ft", fraction, a.seed), strategy,
                      factors, a.seed, config, init_cell=pre_name, evals=evals))
  return cells


def v5_grid(a: Seeded) -> list[Cell]:
  """Each arm's objects model on all the data (its epochs the calibrated budget, phase
  "objects"), fine-tuned on a few tissue scenes for the design's steps, validated every
  val_every steps on the whole tissue validation split; the final and the best checkpoint
  scored on the fixed tissue test set (docs/plan-v5.md)."""
  design = a.scale.v5
  evals = (test_set("tissue", a.scale), test_set("tissue", a.scale, "best"))
  factors = (("setting", "finetune"), ("data", design.tissue_fraction))
  cells = []
  for strategy in design.arms:
    pre = dataclasses.replace(base_config(a.scale, a.seed, a.epochs(strategy, "objects")),
                              model="psmnet", strategy=strategy, lr_drop_epoch=None)
    pre_name = "v5-" + psmnet_name(strategy, "objects", "1", a.seed)
    cells.append(Cell(pre_name, strategy, (("setting", "pretrain"), ("data", "all")), a.seed,
                      pre))
    config = dataclasses.replace(pre, domain="tissue", synth_n=a.scale.tissue_n,
                                 fraction=design.tissue_fraction, lr=design.finetune_lr,
                                 epochs=a.scale.schedule.finetune_epochs,  # steps rule instead
                                 steps=design.finetune_steps, val_every_steps=design.val_every,
                                 max_val=None)
    cells.append(Cell("v5-" + psmnet_name(strategy, "tissue-ft", design.tissue_fraction, a.seed),
                      strategy, factors, a.seed, config, init_cell=pre_name, evals=evals))
  return cells
