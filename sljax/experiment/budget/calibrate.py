"""Budget calibration for the v2 plans (docs/plan-v2.md): one long run per arm and phase, on the
validation split, and a pre-registered plateau rule that turns its curve into epochs.

The rule (plateau):
1. The curve is the validation Full MAE at each validated epoch of the long run (fixed
   learning rate; seed 0; every validation scene).
2. Smooth it with a trailing mean over the last SMOOTH validations (fewer at the start), so one
   noisy epoch neither ends nor extends the budget.
3. The plateau epoch P is the first validated epoch whose smoothed MAE is within PLATEAU_TOL
   (5%) of the lowest smoothed MAE of the whole run.
4. The run reached a plateau when P <= 3/4 of its epochs (the last quarter or more improved by
   at most 5%); otherwise the budget is the long run's epochs and the result says "no plateau".
5. Budget: phases whose schedule drops the learning rate 10x for the last quarter (objects and
   1/16 at the cpu scales) train ceil(4 P / 3) epochs, so P epochs at the full rate then a
   third as many at the low rate; fine-tuning (already at the low rate) trains P epochs.

OUT/calibration-PLAN.json keeps every curve, the smoothed values, P, the budget and the flag.
"""

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sljax.experiment import records
from sljax.experiment.design import plans
from sljax.experiment.design.cells import Plan
from sljax.experiment.running import runner

PLATEAU_TOL = 0.05
SMOOTH = 3


def smooth(values: Sequence[float], window: int = SMOOTH) -> list[float]:
  """Trailing mean over the last `window` values (fewer at the start): rule 2, also v3's."""
  v = np.asarray(values, float)
  return [float(v[max(0, i - window + 1):i + 1].mean()) for i in range(len(v))]


def plateau(curve: Sequence[tuple[int, float]], epochs: int, drop: bool) -> dict[str, Any]:
  """The rule above applied to (epoch, validation MAE) pairs of a run of `epochs` epochs;
  `drop`: the phase's schedule drops the learning rate for its last quarter."""
  pts = sorted((int(e), float(v)) for e, v in curve if v is not None and math.isfinite(v))
  if not pts:
    return {"plateau_epoch": None, "reached": False, "budget": epochs, "smoothed": []}
  smoothed = smooth([v for _, v in pts])
  best = min(smoothed)
  first = next(i for i, s in enumerate(smoothed) if s <= (1.0 + PLATEAU_TOL) * best)
  p = pts[first][0]
  reached = p <= 0.75 * epochs
  budget = (math.ceil(4 * p / 3) if drop else p) if reached else epochs
  return {"plateau_epoch": p, "reached": reached, "budget": budget, "best_smoothed": best,
          "smoothed": [[e, s] for (e, _), s in zip(pts, smoothed)]}


def budgets(out: Path, plan: Plan) -> dict[str, Any]:
  """The rule applied to every finished calibration cell of a plan (missing ones listed)."""
  rows, missing = {}, []
  for cell in plan.cells:
    if not (records.cell_dir(out, cell.name) / records.DONE_FILE).exists():
      missing.append(cell.name)
      continue
    phase = plans.phase_of(cell)
    res = plateau(records.curve(out, cell.name), cell.config.epochs,
                  drop=plan.scale.lr_drop and phase != "finetune")
    rows[cell.name] = dict(res, arm=cell.arm, phase=phase, epochs=cell.config.epochs,
                           curve=records.curve(out, cell.name))
  return {"plan": plan.name, "scale": plan.scale.name, "tolerance": PLATEAU_TOL,
          "smooth": SMOOTH, "cells": rows, "missing": missing,
          "budgets": [[r["arm"], r["phase"], r["budget"]] for r in rows.values()]}


def calibrate(name: str, scale: str, out: str | Path, *, progress: bool = True,
              log=print) -> dict[str, Any]:
  """Runs (or resumes) the calibration cells of a v2 plan under OUT and writes
  OUT/calibration-NAME.json; returns its content."""
  out = Path(out)
  plan = plans.calibration_plan(name, scale)
  runner.run(plan, out, progress=progress, log=log)
  result = budgets(out, plan)
  records.write_json(out / f"calibration-{name}.json", result)
  return result


def budget_lines(result: dict[str, Any]) -> list[str]:
  """What to commit into the scale's budgets, one line per arm and phase, with the evidence."""
  lines = []
  for name, r in result["cells"].items():
    flag = "" if r["reached"] else "  # no plateau within the long run"
    lines.append(f"(({r['arm']!r}, {r['phase']!r}), {r['budget']}),  # {name}: plateau epoch "
                 f"{r['plateau_epoch']} of {r['epochs']}, best smoothed validation MAE "
                 f"{r.get('best_smoothed', float('nan')):.3f} px{flag}")
  return lines
