"""The v3 regime rule (docs/plan-v3.md): where does stl overfit, and for how long to train there.

The pilot (plans.V3_PILOT) trains stl at a few small training fractions with a constant
learning rate and a long fixed budget, validating every few epochs on the whole validation
split. The rule, pre-registered before the pilot ran:
1. Per fraction, the curve is the mean over the pilot's seeds of the validation Full MAE at
   each validated epoch that every seed reached.
2. Smooth it with a trailing mean over the last SMOOTH validations (fewer at the start), as v2's
   calibration rule does, so that one noisy validation neither makes nor hides a rise.
3. The fraction overfits when its smoothed final value is at least OVERFIT_RISE (10%) above
   the smoothed curve's minimum; the minimum's epoch is the first validated epoch holding it.
4. The regime is the largest fraction that overfits; its budget is twice the epoch of its
   minimum, rounded up to a validation point (a multiple of the validation cadence).
5. If no fraction overfits, there is no regime, and v3 ends with that finding.

OUT/regime.json keeps every curve, the smoothed values, the minima and rises and the choice;
OUT/regime.md says it in a table and OUT/figures/v3-pilot_curves.png draws it.
"""

import dataclasses
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from sljax.errors import require
from sljax.experiment import records
from sljax.experiment.budget.calibrate import SMOOTH, plateau, smooth
from sljax.experiment.design import plans
from sljax.experiment.design.cells import Cell, Seeded
from sljax.experiment.running import runner
from sljax.io import files

OVERFIT_RISE = 0.10
GRID_HOURS = 24.0       # docs/plan-v4.md: the grid's seeds fit about 24 hours of running,
GRID_SEEDS = (3, 10)    # at least 3 and at most 10

Curve = Sequence[tuple[int, float]]


def mean_curve(curves: Sequence[Curve]) -> list[tuple[int, float]]:
  """(epoch, mean over the curves) at the validated epochs every curve has."""
  tables = [{int(e): float(v) for e, v in c if v is not None and math.isfinite(v)}
            for c in curves]
  if not tables:
    return []
  common = sorted(set.intersection(*(set(t) for t in tables)))
  return [(e, float(np.mean([t[e] for t in tables]))) for e in common]


def fraction_rise(curve: Curve) -> dict[str, Any]:
  """Steps 2-3 of the rule on one fraction's mean curve."""
  if not curve:
    return {"overfits": False, "min_epoch": None, "rise": None, "smoothed": []}
  epochs = [e for e, _ in curve]
  s = smooth([v for _, v in curve])
  lowest = min(s)
  i_min = s.index(lowest)
  rise = s[-1] / lowest - 1.0
  return {"overfits": bool(rise >= OVERFIT_RISE), "min_epoch": epochs[i_min],
          "min_smoothed": lowest, "final_smoothed": s[-1], "final_epoch": epochs[-1],
          "rise": rise, "smoothed": [[e, v] for e, v in zip(epochs, s)]}


def choose(rows: Mapping[str, dict[str, Any]], fractions: Sequence[str],
           val_every: int) -> dict[str, Any]:
  """Steps 4-5: the largest overfitting fraction (fractions are given largest first) and its
  budget, or no regime."""
  for fraction in fractions:
    row = rows.get(fraction)
    if row is not None and row["overfits"]:
      budget = math.ceil(2 * row["min_epoch"] / val_every) * val_every
      return {"fraction": fraction, "budget": budget, "min_epoch": row["min_epoch"]}
  return {"fraction": None, "budget": None, "min_epoch": None}


def regime(out: str | Path, scale: str = "cpu", seeds: int = 2) -> dict[str, Any]:
  """The rule applied to the pilot under OUT (finished cells only; missing ones listed)."""
  out = Path(out)
  plan = plans.build_plan(plans.V3_PILOT, scale, seeds)
  design = plan.scale.v3
  rows, missing = {}, []
  for fraction in design.fractions:
    cells = plan.cells_of(data=fraction)
    done = [c for c in cells if (records.cell_dir(out, c.name) / records.DONE_FILE).exists()]
    missing += [c.name for c in cells if c not in done]
    if len(done) < len(cells):
      continue
    curves = {c.name: records.curve(out, c.name) for c in done}
    mean = mean_curve(list(curves.values()))
    rows[fraction] = dict(fraction_rise(mean), curves={k: [list(p) for p in v]
                                                       for k, v in curves.items()},
                          mean=[list(p) for p in mean])
  chosen = choose(rows, design.fractions, design.val_every) if not missing else None
  return {"plan": plan.name, "scale": scale, "seeds": list(plan.seeds),
          "epochs": design.pilot_epochs, "val_every": design.val_every, "smooth": SMOOTH,
          "overfit_rise": OVERFIT_RISE, "fractions": rows, "missing": missing,
          "regime": chosen}


def memorisation(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
  """v4's memorisation measure of one cell (docs/plan-v4.md; beside the rule, not part of it):
  the mean training disparity loss over the last validation interval against its value over
  the interval ending at the cell's own (unsmoothed) validation minimum."""
  rows = [r for r in rows if r.get("val_mae") is not None and math.isfinite(r["val_mae"])]
  if not rows:
    return {"min_step": None, "train_at_min": None, "train_final": None, "ratio": None}
  at_min = min(rows, key=lambda r: (r["val_mae"], r["step"]))  # the first step holding it
  final = rows[-1]
  return {"min_step": at_min["step"], "train_at_min": at_min["train_loss_disp"],
          "train_final": final["train_loss_disp"],
          "ratio": final["train_loss_disp"] / at_min["train_loss_disp"]}


def v4_setting(curves: Mapping[str, Mapping[str, Sequence[dict[str, Any]]]],
               fractions: Sequence[str], val_every: int) -> dict[str, Any]:
  """v3's rule on steps for one v4 setting: curves[fraction][cell] = its validation.jsonl rows
  (every seed's cell finished); per fraction the seeds' mean curve, its rise and the cells'
  memorisation; the regime (largest overfitting fraction, budget twice its minimum's step)."""
  rows = {}
  for fraction in fractions:
    cells = curves.get(fraction)
    if not cells:
      continue
    pts = {name: [(r["step"], r["val_mae"]) for r in rs] for name, rs in cells.items()}
    mean = mean_curve(list(pts.values()))
    rise = fraction_rise(mean)
    per_cell = {n: memorisation(rs) for n, rs in cells.items()}
    ratios = [m["ratio"] for m in per_cell.values() if m["ratio"] is not None]
    rows[fraction] = dict(rise, min_step=rise.pop("min_epoch"), mean=[list(p) for p in mean],
                          memorisation=per_cell,
                          memorisation_mean=sum(ratios) / len(ratios) if ratios else None)
  chosen = choose({f: dict(r, min_epoch=r["min_step"]) for f, r in rows.items()}, fractions,
                  val_every)
  return {"fractions": rows, "regime": {"fraction": chosen["fraction"],
                                        "budget_steps": chosen["budget"],
                                        "min_step": chosen["min_epoch"]}}


V4_SETTINGS = ("scratch", "finetune")  # where the rule looks; "pretrain" starts "finetune"


def v4(out: str | Path, scale: str = "cpu", seeds: int = 2) -> dict[str, Any]:
  """docs/plan-v4.md's rule applied to the v4 pilot under OUT (finished cells only; the regime
  waits for every cell): per setting the fractions' rises, memorisation and the regime; the
  pretraining's curve with v2's plateau rule (reported, changes nothing)."""
  out = Path(out)
  plan = plans.build_plan(plans.V4_PILOT, scale, seeds)
  design = plan.scale.v4
  done = {c.name for c in plan.cells if (records.cell_dir(out, c.name) / records.DONE_FILE).exists()}
  missing = [c.name for c in plan.cells if c.name not in done]
  settings = {}
  for setting, fractions in zip(V4_SETTINGS, (design.scratch_fractions,
                                              design.finetune_fractions)):
    curves = {}
    for fraction in fractions:
      cells = plan.cells_of(setting=setting, data=fraction)
      if all(c.name in done for c in cells):
        curves[fraction] = {c.name: records.step_curve(out, c.name) for c in cells}
    settings[setting] = v4_setting(curves, fractions, design.val_every)
    settings[setting]["curves"] = curves
  pretrain = {}
  for c in plan.cells_of(setting="pretrain"):
    if c.name in done:
      pts = [(r["step"], r["val_mae"]) for r in records.step_curve(out, c.name)]
      pretrain[c.name] = dict(plateau(pts, design.pretrain_steps, drop=False), curve=pts)
  both = all(settings[s]["regime"]["fraction"] is not None for s in V4_SETTINGS)
  grid = None
  if not missing:  # rule: fine-tuning when both overfit, else the one that does, else none
    grid = next((s for s in ("finetune", "scratch")
                 if settings[s]["regime"]["fraction"] is not None), None)
  seeds_rule = None
  if grid is not None and design.step_seconds is not None:
    chosen = settings[grid]["regime"]
    seeds_rule = grid_seeds(scale, (grid, chosen["fraction"], chosen["budget_steps"]))
  return {"plan": plan.name, "scale": scale, "seeds": list(plan.seeds),
          "val_every": design.val_every, "smooth": SMOOTH, "overfit_rise": OVERFIT_RISE,
          "settings": settings, "pretrain": pretrain, "missing": missing,
          "grid_setting": grid, "both_overfit": both, "grid_seeds": seeds_rule}


def _grid_cells(scale: str, regime_: tuple[str, str, int]) -> list[Cell]:
  """One seed's cells of the v4 grid at a scale, were the rule to choose regime_."""
  sc = plans.SCALES[scale]
  sc = dataclasses.replace(sc, v4=dataclasses.replace(sc.v4, regime=regime_))
  # The builder itself, not build_plan: n is what build_plan would refuse without.
  build = plans.BUILDERS[plans.V4][0]
  return build(Seeded(sc, sc.v4.grid_first_seed, None, (), sc.budget))


def grid_seeds(scale: str, regime_: tuple[str, str, int]) -> dict[str, Any]:
  """docs/plan-v4.md's seed rule: the hours of one seed of the grid and n, the seeds that fit."""
  # Every cell's steps, validations and test scorings at stl's measured seconds times the arm's
  # measured ratio; n = GRID_HOURS // hours, clipped to GRID_SEEDS.
  design = plans.SCALES[scale].v4
  require(design.step_seconds is not None and design.val_seconds is not None
          and design.arm_ratios,
          f"scale {scale}: the grid's cost is not measured (V4Design.step_seconds, "
          "val_seconds, arm_ratios; docs/plan-v4.md)")
  ratios = {arm: (step, val) for arm, step, val in design.arm_ratios}
  per_scene = design.val_seconds / design.val_scenes
  cells = []
  for cell in _grid_cells(scale, regime_):
    step_ratio, val_ratio = ratios[cell.arm]
    steps = runner.cell_steps(cell)
    n_val = len(runner.validation_indices(cell)[1])
    validations = math.ceil(steps / cell.config.val_every_steps)
    scored = sum(len(runner.eval_scenes(cell, e)) for e in cell.evals)
    seconds = (step_ratio * design.step_seconds * steps
               + val_ratio * per_scene * (n_val * validations + scored))
    cells.append({"cell": cell.name, "arm": cell.arm, "steps": steps, "validations":
                  validations, "validation_scenes": n_val, "scored_scenes": scored,
                  "hours": seconds / 3600})
  hours = sum(c["hours"] for c in cells)
  lo, hi = GRID_SEEDS
  return {"cells": cells, "hours_per_seed": hours, "budget_hours": GRID_HOURS,
          "seeds": min(hi, max(lo, int(GRID_HOURS // hours)))}


def markdown_v4(result: dict[str, Any]) -> list[str]:
  """The v4 outcome: a table per setting (rise, regime, memorisation) and the decision."""
  lines = [f"# v4 pilot: where stl overfits, in steps (scale {result['scale']}, seeds "
           f"{', '.join(map(str, result['seeds']))}, validated every {result['val_every']} "
           "steps)", ""]
  for setting in V4_SETTINGS:
    r = result["settings"][setting]
    lines += [f"## {setting}", "", "| fraction | minimum (smoothed mean) | its step | final "
              "(smoothed mean) | rise | overfits (rise >= 10%) | training loss at the end / at "
              "the minimum, per seed (mean) |", "| --- | ---: | ---: | ---: | ---: | --- | --- |"]
    for fraction, f in r["fractions"].items():
      ratios = ", ".join("-" if m["ratio"] is None else f"{m['ratio']:.2f}"
                         for m in f["memorisation"].values())
      if f["memorisation_mean"] is not None:
        ratios += f" ({f['memorisation_mean']:.2f})"
      lines.append(f"| {fraction} | {f['min_smoothed']:.3f} px | {f['min_step']} | "
                   f"{f['final_smoothed']:.3f} px | {100 * f['rise']:+.1f}% | "
                   f"{'yes' if f['overfits'] else 'no'} | {ratios} |")
    chosen = r["regime"]
    if result["missing"]:  # a fraction not finished yet could still take the regime
      verdict = "Regime: decided once every cell has finished."
    elif chosen["fraction"]:
      verdict = (f"Regime: fraction {chosen['fraction']}, budget {chosen['budget_steps']} steps "
                 f"(twice the minimum's step {chosen['min_step']}).")
    else:
      verdict = "No fraction overfits here."
    lines += ["", verdict, ""]
  for name, p in result["pretrain"].items():
    lines.append(f"Pretraining {name}: v2's plateau rule " + (
        f"reached at step {p['plateau_epoch']}." if p["reached"] else
        "found no plateau in the last quarter (reported; the plan changes nothing for it)."))
  lines.append("")
  if result["missing"]:
    lines.append(f"Not finished: {', '.join(result['missing'])}.")
  elif result["grid_setting"] is None:
    lines.append("**No setting overfits**: by the pre-registered rule v4 reports the curves and "
                 "the memorisation evidence and stops (no test cell runs).")
  else:
    chosen = result["settings"][result["grid_setting"]]["regime"]
    lines.append(f"**The test grid runs in the {result['grid_setting']} setting** (rule: "
                 f"fine-tuning when both overfit), fraction {chosen['fraction']}, "
                 f"{chosen['budget_steps']} steps.")
    rule = result.get("grid_seeds")
    if rule is not None:
      lines.append(f"Seeds by the 24-hour rule: one seed's cells take about "
                   f"{rule['hours_per_seed']:.1f} h, so **n = {rule['seeds']}** (at least "
                   f"{GRID_SEEDS[0]}, at most {GRID_SEEDS[1]}; {rule['seeds']} seeds about "
                   f"{rule['seeds'] * rule['hours_per_seed']:.0f} h).")
  return lines + [""]


def _panels(n: int) -> tuple[Figure, np.ndarray]:
  """A figure of n panels in a row (at least one)."""
  fig = Figure(figsize=(4.2 * max(1, n), 3.4))
  return fig, fig.subplots(1, max(1, n), squeeze=False)[0]


def _rule_lines(ax, r: dict[str, Any], unit: str) -> None:
  """The seeds' mean curve, its trailing mean (what the rule reads) and the minimum's x."""
  x, v = np.array(r["mean"]).T
  ax.plot(x, v, color="k", lw=1.5, label="mean of seeds")
  x, v = np.array(r["smoothed"]).T
  ax.plot(x, v, "--", color="0.4", lw=1.2, label=f"trailing mean of {SMOOTH}")
  ax.axvline(r[f"min_{unit}"], color="0.5", lw=0.8, label=f"minimum ({unit} {r[f'min_{unit}']})")


def _save(fig: Figure, title: str, path: Path) -> None:
  fig.suptitle(title, fontsize=10)
  fig.tight_layout()
  path.parent.mkdir(parents=True, exist_ok=True)
  files.save_figure(fig, path, dpi=110)


def figure_v4(result: dict[str, Any], path: Path) -> None:
  """Per setting and fraction: each seed's validation MAE (thin) and training disparity loss
  between validations (dotted, right axis), the seeds' mean and its trailing mean, the minimum."""
  panels = [(s, f, r) for s in V4_SETTINGS
            for f, r in result["settings"][s]["fractions"].items()]
  if not panels:
    return
  fig, axes = _panels(len(panels))
  for ax, (setting, fraction, r) in zip(axes, panels):
    twin = ax.twinx()
    for k, rows in enumerate(result["settings"][setting]["curves"][fraction].values()):
      steps = [row["step"] for row in rows]
      ax.plot(steps, [row["val_mae"] for row in rows], color=f"C{k}", lw=0.8)
      twin.plot(steps, [row["train_loss_disp"] for row in rows], ":", color=f"C{k}", lw=1.0)
    _rule_lines(ax, r, "step")
    ax.set_title(f"{setting} {fraction}: rise {100 * r['rise']:+.1f}%", fontsize=9)
    ax.set_xlabel("step")
    ax.set_ylabel("validation Full MAE (px)")
    ax.legend(fontsize=7)
    twin.set_ylabel("training L_disp, dotted (log)")
    twin.set_yscale("log")
  _save(fig, "v4 pilot: stl's validation error and training loss (seeds in colour)", path)


def markdown(result: dict[str, Any]) -> list[str]:
  """The rule's outcome as a table and a sentence."""
  lines = [f"# v3 pilot: where stl overfits (scale {result['scale']}, seeds "
           f"{', '.join(map(str, result['seeds']))}, {result['epochs']} epochs, validated every "
           f"{result['val_every']})", "",
           "| fraction | minimum (smoothed mean) | its epoch | final (smoothed mean) | rise | "
           "overfits (rise >= 10%) |", "| --- | ---: | ---: | ---: | ---: | --- |"]
  for fraction, r in result["fractions"].items():
    lines.append(f"| {fraction} | {r['min_smoothed']:.3f} px | {r['min_epoch']} | "
                 f"{r['final_smoothed']:.3f} px | {100 * r['rise']:+.1f}% | "
                 f"{'yes' if r['overfits'] else 'no'} |")
  lines.append("")
  chosen = result["regime"]
  if chosen is None:
    lines.append(f"Not finished: {', '.join(result['missing'])}.")
  elif chosen["fraction"] is None:
    lines.append("**No fraction overfits**: by the pre-registered rule v3 ends with this "
                 "finding (no test cell runs).")
  else:
    lines.append(f"**Regime: fraction {chosen['fraction']}, budget {chosen['budget']} epochs** "
                 f"(twice the minimum's epoch {chosen['min_epoch']}, rounded up to a multiple "
                 f"of {result['val_every']}).")
  return lines + [""]


def figure(result: dict[str, Any], path: Path) -> None:
  """Each fraction's seeds (thin), mean (thick) and smoothed mean (dashed), minimum marked."""
  rows = result["fractions"]
  fig, axes = _panels(len(rows))
  for ax, (fraction, r) in zip(axes, rows.items()):
    for name, pts in r["curves"].items():
      e, v = np.array(pts).T
      ax.plot(e, v, color="0.7", lw=0.8)
    _rule_lines(ax, r, "epoch")
    ax.set_title(f"{fraction}: rise {100 * r['rise']:+.1f}%", fontsize=9)
    ax.set_xlabel("epoch")
    ax.set_ylabel("validation Full MAE (px)")
    ax.legend(fontsize=7)
  _save(fig, "v3 pilot: stl's validation MAE at a constant learning rate", path)


def write(out: str | Path, scale: str = "cpu", seeds: int = 2) -> dict[str, Any]:
  """Writes OUT/regime.json, OUT/regime.md and the figure (v3's pilot, or v4's when OUT holds
  the v4 pilot); returns the result."""
  out = Path(out)
  record = records.read_record(out) or {"plans": {}}
  if plans.V4_PILOT in record["plans"]:
    result = v4(out, scale, seeds)
    records.write_json(out / "regime.json", result)
    files.write_text(out / "regime.md", "\n".join(markdown_v4(result)))
    figure_v4(result, out / "figures" / "v4-pilot_curves.png")
    return result
  result = regime(out, scale, seeds)
  records.write_json(out / "regime.json", result)
  files.write_text(out / "regime.md", "\n".join(markdown(result)))
  if result["fractions"]:
    figure(result, out / "figures" / "v3-pilot_curves.png")
  return result
