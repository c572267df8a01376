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

Calibration as cells of the grid: at a scale whose budgets for a plan are not committed in
scales.py, `sljax experiment run PLAN OUT` (and every worker `submit` starts) runs the plan's
calibration cells in OUT like any other cells (claims, leases, resume); when the last is done
the rule writes OUT/calibration-PLAN.json once, and the plan's cells are built from its
budgets, recorded in OUT/plan.json (a plan already recorded with other budgets is refused),
and run (`worker_plan`).
"""

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sljax.errors import require
from sljax.experiment import records
from sljax.experiment.design import plans
from sljax.experiment.design.cells import Plan
from sljax.experiment.running import runner, workers

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
    phase, curve = plans.phase_of(cell), records.curve(out, cell.name)
    res = plateau(curve, cell.config.epochs, drop=plan.scale.lr_drop and phase != "finetune")
    rows[cell.name] = dict(res, arm=cell.arm, phase=phase, epochs=cell.config.epochs,
                           curve=curve)
  return {"plan": plan.name, "scale": plan.scale.name, "tolerance": PLATEAU_TOL,
          "smooth": SMOOTH, "cells": rows, "missing": missing,
          "budgets": [[r["arm"], r["phase"], r["budget"]] for r in rows.values()]}


def calibration_file(out: Path, name: str) -> Path:
  """OUT/calibration-NAME.json."""
  return out / f"calibration-{name}.json"


def settled(out: Path, name: str, scale: str) -> dict[str, Any] | None:
  """OUT's calibration of a plan once complete: calibration-NAME.json, written by the rule
  when the last calibration cell is done (once: a complete file is never rewritten); None
  while a cell is unfinished. SljaxError when a cell diverged (the rule has no budget then)."""
  path = calibration_file(out, name)
  with workers.plan_lock(out):
    result = records.read_json(path)
    if result is not None:
      ok = isinstance(result.get("missing"), list) and isinstance(result.get("budgets"), list) \
          and all(isinstance(r, list) and len(r) == 3 for r in result["budgets"])
      require(ok, f"{path}: not a calibration record (delete it to apply the rule again)")
      if not result["missing"]:
        return result
    plan = plans.calibration_plan(name, scale)
    left_out = runner.diverged(out, plan)
    require(not left_out, f"{out}: calibration cell {next(iter(left_out), '')} diverged, so "
            f"the plateau rule gives no budget for it (docs/plan-v2.md); plan {name} cannot run "
            "at this scale in this OUT")
    result = budgets(out, plan)
    if result["missing"]:
      return None
    records.write_json(path, result)
  return result


def calibrated_plan(name: str, scale: str, seeds: int, data: str | None,
                    eval_data: tuple[str, ...], out: Path) -> Plan:
  """The plan with the budgets OUT's complete calibration gave, registered in OUT/plan.json
  (refused there if it was recorded with other budgets)."""
  result = settled(out, name, scale)
  require(result is not None, f"{out}: the calibration of {name} is not finished")
  plan = plans.build_plan(name, scale, seeds, data, eval_data,
                          records.budget_pairs(result["budgets"]))
  with workers.plan_lock(out):
    records.register(out, plan)
  return plan


def worker_plan(name: str, scale: str, seeds: int, data: str | None,
                eval_data: tuple[str, ...], out: str | Path):
  """(plan, then) for a worker of `experiment run` under OUT: the plan and None; or, at a scale
  without committed budgets for it, its calibration cells and the function that builds and
  registers the calibrated plan once they are done (runner.run's `then`); or the calibrated
  plan itself when OUT's calibration is already complete."""
  out = Path(out)
  if not plans.needs_calibration(name, scale):
    return plans.build_plan(name, scale, seeds, data, eval_data), None
  plans.provisional_plan(name, scale, seeds, data, eval_data)  # bad arguments: refused now
  if calibration_file(out, name).exists() and settled(out, name, scale) is not None:
    return calibrated_plan(name, scale, seeds, data, eval_data, out), None
  return plans.calibration_plan(name, scale), lambda: calibrated_plan(
      name, scale, seeds, data, eval_data, out)


def calibrate(name: str, scale: str, out: str | Path, *, progress: bool = True,
              log=print) -> dict[str, Any]:
  """Runs (or resumes) the calibration cells of a calibrated plan under OUT and writes
  OUT/calibration-NAME.json (once complete, never again); returns its content."""
  out = Path(out)
  plan = plans.calibration_plan(name, scale)
  runner.run(plan, out, progress=progress, log=log)
  result = settled(out, name, scale)
  if result is None:  # other workers still train some: what is done so far, not written
    result = budgets(out, plan)
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
