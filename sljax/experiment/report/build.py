"""Experiment reports: every cell of every plan under OUT, means and 95% intervals over seeds,
paired comparisons against the baseline arm, the paper's claims checked, figures.

Writes OUT/report.md, OUT/report.json and OUT/figures/*.png. Everything in them is computed
from the cells' evaluation files and training logs, so a report is a pure function of the
finished cells: the same cells give the same report (timings are kept out of it; they are in
each cell's done.json). Unfinished cells are listed as missing, never dropped silently.

Statistics (sljax.experiment.report.stats): per arm, the mean over seeds with a Student-t 95%
interval; per arm against the baseline, the mean of the per-seed differences (paired by seed:
same seed = same data, split, subset, order and shared initial weights) with its t interval,
the paired t-test's two-sided p and the number of seeds where the arm was better. The claims of
one table (plan) are one family: their p-values are Holm-adjusted together, and a claim "A
beats B" holds when its adjusted p < ALPHA and the mean difference favours A, is contradicted
("does not hold") when the adjusted p < ALPHA and it favours B, and is not shown otherwise.
Each claim also gives the smallest true difference its test had 80% power to detect (two-sided
paired t at ALPHA, unadjusted, from the observed SD of the differences): a "not shown" with a
large detectable difference means the design could not answer. Where the paper itself found no
gain for an arm, the claim says so beside the verdict. Statements that a gain of some size is
excluded are exploratory (no test was pre-registered for them).
"""

import math
from pathlib import Path
from collections.abc import Callable
from typing import Any, Sequence

import numpy as np

from sljax.errors import SljaxError
from sljax.evaluation.scoring import json_safe
from sljax.experiment.design.cells import FIXED, HELDOUT, TEST_SEED, Cell, Plan
from sljax.experiment.budget.calibrate import smooth
from sljax.experiment.design.plans import PLANS
from sljax.experiment.report import figures, stats
from sljax.experiment.report.paper_claims import (ALPHA, CURVE_SET, PAPER, POWER, claims,
                                                  mechanism)
from sljax.experiment.records import (DONE_FILE, EVAL_DIR, WINDOWS_FILE, cell_dir, curve,
                                      plan_args, read_done, read_eval, read_json,
                                      registered_plans, train_curve)
from sljax.experiment.running.runner import diverged
from sljax.io import files, tables
from sljax.train.config import dumps

# (key, header) of the metrics every table shows; lower is better except HIGHER_BETTER.
METRICS = (("mae", "Full MAE px"), ("seg_mae", "Seg MAE px"), ("bad_2", "bad-2 %"),
           ("iqr", "IQR px"), ("pattern_acc", "pattern acc % (left)"),
           ("pattern_acc_right", "pattern acc % (right)"))
# v3's pseudo set (claims.CURVE_SET): a cell's own validation curve, with its overfitting rise
# (final minus lowest validation Full MAE).
CURVE_METRICS = (("rise", "overfitting rise px"), ("final_val", "final validation MAE px"),
                 ("min_val", "lowest validation MAE px"),
                 ("rise_rel", "smoothed rise (x its minimum)"))
DEPTH_METRICS = (("depth_mae_mm", "depth MAE mm (capped)"), ("depth_iqr_mm", "depth IQR mm"),
                 ("depth_capped", "depth capped %"))
HIGHER_BETTER = ("pattern_acc", "pattern_acc_right")
# Each task's primary metric for Delta_m: disparity MAE, and the SL patterns' accuracy where
# both arms predict patterns.
PRIMARY = ("mae", "pattern_acc")
TITLES = {
    "table1": "Table 1: disparity from the SL network's patterns (unet-sl, by correlation) vs "
              "the direct network (unet-disp)",
    "table2": "Table 2: the five loss-weighting strategies on all and on 1/16 of the training "
              "split",
    "table3": "Table 3: generalisation of the full-data models to other data",
    "fig7": "Fig. 7: fine-tuning the full-data models on scarce data",
}
TITLES.update({f"{k}-v2": f"{v} (v2: fixed test sets)" for k, v in TITLES.items()})
TITLES["v3"] = ("v3: stl, unc and epr where stl overfits (the pilot's regime; "
                "docs/plan-v3.md)")
TITLES["v4"] = ("v4: stl, unc and epr where stl overfits, budgets in steps (the pilot's "
                "regime; docs/plan-v4.md)")
TITLES["v5"] = ("v5: the paper's mechanism: fine-tuning on a few tissue scenes at the paper's "
                "scale (docs/plan-v5.md)")
CURVE_PLANS = ("v3", "v4", "v5")  # plans whose claims read each cell's own validation curve


def curve_metrics(out: Path, name: str) -> dict[str, float] | None:
  """A finished cell's validation curve: its last value, its lowest and the rise between them
  (px; None when the cell has not finished)."""
  if not (cell_dir(out, name) / DONE_FILE).exists():
    return None
  values = [v for _, v in sorted(curve(out, name)) if v is not None and math.isfinite(v)]
  if not values:
    return None
  smoothed = smooth(values)  # v5's rise (docs/plan-v5.md): smoothed, relative to the minimum
  return {"rise": values[-1] - min(values), "final_val": values[-1], "min_val": min(values),
          "rise_rel": (smoothed[-1] - min(smoothed)) / min(smoothed)}


def nonfinite_curves(out: Path, cells: Sequence[Cell]) -> list[str]:
  """The finished cells whose validation curve holds a NaN or inf (a diverged run): their
  rise is taken over the finite values only, so the report names them."""
  return [c.name for c in cells if (cell_dir(out, c.name) / DONE_FILE).exists()
          and any(v is None or not math.isfinite(v) for _, v in curve(out, c.name))]


def cell_metrics(out: Path, name: str, set_name: str) -> dict[str, float] | None:
  """The pooled metrics of a cell's final checkpoint on a set, or its curve's (CURVE_SET);
  None when not scored yet."""
  if set_name == CURVE_SET:
    return curve_metrics(out, name)
  rep = read_eval(out, name, set_name)
  if rep is None:
    return None
  pooled = rep["pooled"]
  full, seg = pooled.get("full", {}), pooled.get("seg", {})
  m = {k: full.get(k) for k in ("mae", "bad_2", "iqr", "depth_mae_mm", "depth_iqr_mm",
                                "depth_capped")}
  m["seg_mae"] = seg.get("mae")
  m["pattern_acc"] = pooled.get("patterns_left", {}).get("pattern_acc")
  m["pattern_acc_right"] = pooled.get("patterns_right", {}).get("pattern_acc")
  return {k: v for k, v in m.items() if v is not None}


def chosen_window(out: Path, name: str) -> int | None:
  """The correlation window a v2 unet-sl cell chose on validation (None: none chosen)."""
  rec = read_json(cell_dir(out, name) / EVAL_DIR / WINDOWS_FILE)
  return None if rec is None else int(rec["chosen"])


def window_edges(out: Path, plan: Plan) -> tuple[int, int]:
  """(cells whose window chosen on validation is the largest candidate, cells that chose one):
  a choice at the edge of the pre-registered set says a larger window might do better."""
  chosen = [(chosen_window(out, c.name), max(c.windows)) for c in plan.cells if c.windows]
  chosen = [(w, top) for w, top in chosen if w is not None]
  return sum(w == top for w, top in chosen), len(chosen)


def cell_times(out: Path, plan: Plan) -> dict[tuple[str, str, str], dict[str, Any]]:
  """Training minutes of the finished cells per (arm, factors, CPU): mean, min, max and the XLA
  settings (config.json's `ynn`) they ran with. Kept apart per CPU, since a mean over two CPUs
  times neither."""
  groups: dict[tuple[str, str, str], dict[str, Any]] = {}
  for c in plan.cells:
    done = read_done(out, c.name)
    if done is None or done.get("train_seconds") is None:
      continue
    key = (c.arm, ", ".join(v for _, v in c.factors), done.get("machine", "not recorded"))
    g = groups.setdefault(key, {"minutes": [], "ynn": set()})
    g["minutes"].append(done["train_seconds"] / 60)
    config = read_json(cell_dir(out, c.name) / "config.json") or {}
    g["ynn"].add(str(config.get("ynn", "not recorded")))
  return {k: {"n": len(g["minutes"]), "mean": float(np.mean(g["minutes"])),
              "min": min(g["minutes"]), "max": max(g["minutes"]),
              "ynn": sorted(g["ynn"])} for k, g in groups.items()}


def _time_lines(out: Path, plan: Plan) -> list[str]:
  times = cell_times(out, plan)
  if not times:
    return []
  rows = [[arm, factors, str(t["n"]), f"{t['mean']:.1f} ({t['min']:.1f}-{t['max']:.1f})", cpu,
           ", ".join(t["ynn"])] for (arm, factors, cpu), t in times.items()]
  return ["Training time per cell and CPU (the epochs' seconds from done.json; a cell paused or "
          "sharing its CPU counts that time too; XLA: the YNNPACK setting tuned for that CPU, "
          "config.json's `ynn`):", ""] + _md_table(
              ["arm", "data", "cells", "minutes, mean (range)", "CPU", "XLA"], rows)


def _fmt(x: float | None, digits: int = 3) -> str:
  return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def _fmt_ci(s: dict[str, float], digits: int = 3) -> str:
  if s["n"] == 0:
    return "-"
  if s["n"] == 1 or math.isnan(s["lo"]):
    return _fmt(s["mean"], digits)
  return f"{_fmt(s['mean'], digits)} [{_fmt(s['lo'], digits)}, {_fmt(s['hi'], digits)}]"


def _md_table(header: list[str], rows: list[list[str]]) -> list[str]:
  return tables.table(header, rows) + [""]


# ----------------------------------------------------------------------------- aggregation


def _groups(plan: Plan) -> list[tuple[tuple[str, str], ...]]:
  """The distinct factor tuples of a plan's cells, in plan order."""
  seen: list[tuple[tuple[str, str], ...]] = []
  for c in plan.cells:
    if c.factors not in seen:
      seen.append(c.factors)
  return seen


def _arms(plan: Plan) -> list[str]:
  arms: list[str] = []
  for c in plan.cells:
    if c.arm not in arms:
      arms.append(c.arm)
  return arms


def delta_m(arm: dict[str, float], base: dict[str, float]) -> float:
  """Delta_m (%) of one seed: each task's primary metric both arms have (disparity MAE; SL
  pattern accuracy where both predict patterns); > 0 is better."""
  keys = [k for k in PRIMARY if k in arm and k in base]
  if not keys:  # a set without a task's primary metric (v3's validation curve)
    return math.nan
  return stats.delta_m({k: arm[k] for k in keys}, {k: base[k] for k in keys},
                       higher_better=HIGHER_BETTER)


def _mean_curves(cells: list[Cell], arms: list[str], read: Callable[[str], list],
                 unit: str) -> dict[str, list[dict[str, Any]]]:
  """Per arm, the seeds' mean and 95% interval at every point all its finished cells share."""
  curves = {}
  for a in arms:
    per_seed = [read(c.name) for c in cells if c.arm == a]
    per_seed = [cv for cv in per_seed if cv]
    if per_seed:
      points = sorted(set.intersection(*[{e for e, _ in cv} for cv in per_seed]))
      curves[a] = [dict(stats.mean_ci([dict(cv)[e] for cv in per_seed]), **{unit: e})
                   for e in points]
  return curves


def aggregate(out: Path, plan: Plan) -> dict[str, Any]:
  """Per factor group and evaluation set: per-arm summaries and paired differences."""
  result: dict[str, Any] = {"groups": []}
  arms = _arms(plan)
  left_out = diverged(out, plan)
  for factors in _groups(plan):
    cells = [c for c in plan.cells if c.factors == factors]
    scored = [e.name for e in cells[0].evals]
    sets = scored + ([CURVE_SET] if plan.name in CURVE_PLANS and scored else [])
    group = {"factors": dict(factors), "sets": {}}
    for set_name in sets:
      per_arm: dict[str, dict[int, dict[str, float]]] = {a: {} for a in arms}
      missing = []
      for c in cells:
        if c.name in left_out:
          continue
        m = cell_metrics(out, c.name, set_name)
        if m is None:
          missing.append(c.name)
        else:
          per_arm[c.arm][c.seed] = m
      keys = [k for k, _ in METRICS + DEPTH_METRICS + CURVE_METRICS
              if any(k in m for seeds in per_arm.values() for m in seeds.values())]
      summary = {a: {k: dict(stats.mean_ci([m[k] for m in seeds.values() if k in m]),
                             values={s: m.get(k) for s, m in sorted(seeds.items())})
                     for k in keys if any(k in m for m in seeds.values())}
                 for a, seeds in per_arm.items() if seeds}
      paired = {}
      base = per_arm.get(plan.baseline, {})
      for a, seeds in per_arm.items():
        if a == plan.baseline or not seeds:
          continue
        common = sorted(set(seeds) & set(base))
        # Paired by seed: the arm's seed s against the baseline's seed s, never by position.
        # Per metric over the seeds where both have it: a NaN score (None in its report) in
        # one seed leaves that seed out of that pair, not the metric out of the report.
        has = {k: [s for s in common if k in seeds[s] and k in base[s]] for k in keys}
        paired[a] = {k: stats.paired_test([seeds[s][k] for s in has[k]],
                                          [base[s][k] for s in has[k]])
                     for k in keys if has[k]}
        paired[a]["delta_m"] = stats.mean_ci([delta_m(seeds[s], base[s]) for s in common])
      group["sets"][set_name] = {"arms": summary, "paired": paired, "missing": missing}
      out_here = [c.name for c in cells if c.name in left_out]
      if out_here:  # only then: reports of grids with none stay as they were
        group["sets"][set_name]["diverged"] = out_here
    unit = "step" if any(c.config.val_every_steps for c in cells) else "epoch"
    kept = [c for c in cells if c.name not in left_out]  # a diverged curve would cut the means
    group["curves"] = _mean_curves(kept, arms, lambda name: curve(out, name), unit)
    if unit == "step":  # the training loss between validations (validation.jsonl)
      group["train_curves"] = _mean_curves(kept, arms, lambda name: train_curve(out, name),
                                           unit)
    result["groups"].append(group)
  done = sum((cell_dir(out, c.name) / DONE_FILE).exists() for c in plan.cells)
  result.update(cells=len(plan.cells), trained=done)
  return result


# ----------------------------------------------------------------------------- markdown


def _family(cl: list[dict[str, Any]]) -> str:
  """The Holm family's size as used: claims without results yet are left out of m, so an
  incomplete table's adjusted p are interim (smaller than the complete family's can be)."""
  tested = sum(1 for c in cl if math.isfinite(c.get("difference", {}).get("p", math.nan)))
  if tested == len(cl):
    return f"{len(cl)} claims"
  return (f"{tested} claims with results (the family has {len(cl)}: until all have results "
          "these adjusted p are interim and smaller than the complete family's can be)")


def _plan_markdown(out: Path, plan: Plan, agg: dict[str, Any], cl: list[dict[str, Any]],
                   figs: list[str]) -> list[str]:
  sc = plan.scale
  lines = [f"## {TITLES[plan.name]}", "",
           f"Scale `{sc.name}`: {sc.size}x{sc.size}, {sc.t} patterns per view, maxdisp "
           f"{sc.maxdisp}, batch {sc.batch_size}, Adam {sc.lr:g}; {sc.note}. Seeds "
           f"{', '.join(map(str, plan.seeds))}; {agg['trained']} of {agg['cells']} cells "
           f"trained." + (f" Data: `{plan.data}`." if plan.data else ""), ""]
  if plan.budgets:  # calibrated in this OUT (calibration-PLAN.json), recorded in plan.json
    lines += ["Budgets set by the plateau rule on this folder's calibration cells "
              f"(calibration-{plan.name}.json): " + ", ".join(
                  f"{arm} {phase} {epochs} epochs" for (arm, phase), epochs in plan.budgets)
              + ".", ""]
  outcome = mechanism(plan, agg)
  if outcome is not None:
    lines += ["### The pre-registered outcome (docs/plan-v5.md)", "", outcome, ""]
  if cl:
    lines += ["### The paper's claims at this scale", "",
              f"One family: Holm-adjusted p over its {_family(cl)}; verdicts on the adjusted "
              f"p at {ALPHA:g}. Difference: the claimed better arm minus the other (< 0 "
              "supports the claim), mean over seeds with its unadjusted 95% interval. "
              f"Detectable: the smallest true difference the paired t-test had {POWER:.0%} "
              f"power to detect at {ALPHA:g} (two-sided, unadjusted) from the observed SD.", ""]
    rows = []
    for c in cl:
      d = c.get("difference")
      interval = (f"{_fmt(d['mean'])} [{_fmt(d['lo'])}, {_fmt(d['hi'])}], better in "
                  f"{d['wins']}/{d['n']} seeds" if d else "-")
      verdict = c["verdict"] + (" (the paper found no gain here)" if c["paper"] == "no gain"
                                else "")
      rows.append([c["claim"], interval, _fmt(d["p"]) if d else "-",
                   _fmt(c.get("p_holm")) if d else "-",
                   _fmt(c.get("detectable")) if d else "-", verdict])
    lines += _md_table(["claim", "difference px [95% CI]", "p", "Holm p",
                        "detectable (80%)", "verdict"], rows)
    sized = [c for c in cl if "paper_sized" in c]
    if sized:
      lines += ["Exploratory (not a pre-registered test): the paper's relative gain at this "
                "scale's means, and whether the 95% interval excludes a gain that large:", ""]
      lines += [f"- {c['claim']}: a paper-sized difference is {_fmt(c['paper_sized'])} px; "
                + ("excluded" if c["paper_sized_excluded"] else "not excluded") for c in sized]
      lines += [""]
  for g in agg["groups"]:
    label = ", ".join(f"{k} {v}" for k, v in g["factors"].items())
    for set_name, res in g["sets"].items():
      lines += [f"### {label}: scored on {_set_label(plan, set_name)}", ""]
      keys = [k for k, _ in METRICS + DEPTH_METRICS + CURVE_METRICS
              if any(k in a for a in res["arms"].values())]
      headers = dict(METRICS + DEPTH_METRICS + CURVE_METRICS)
      rows = [[a, str(next(iter(s.values()))["n"])] + [_fmt_ci(s[k]) if k in s else "-"
                                                         for k in keys]
              for a, s in res["arms"].items()]
      lines += ["Mean [95% interval] over seeds:", ""]
      lines += _md_table(["arm", "seeds"] + [headers[k] for k in keys], rows)
      if res["paired"] and set_name == CURVE_SET:
        prow = [[a, f"{_fmt_ci(p['rise'])}; p = {_fmt(p['rise']['p'])}; {p['rise']['wins']}/"
                 f"{p['rise']['n']}"] for a, p in res["paired"].items() if "rise" in p]
        lines += [f"Paired against {plan.baseline} (arm - {plan.baseline}; negative = a "
                  "smaller rise; p: paired t-test, unadjusted; seeds where the arm rose less):",
                  ""]
        lines += _md_table(["arm", "Δ overfitting rise px"], prow)
        diverged = nonfinite_curves(out, [c for c in plan.cells
                                          if dict(c.factors) == g["factors"]])
        if diverged:
          lines += [f"Not finite at some validation (diverged; the rise above is over the "
                    f"finite values only, so it understates theirs): {', '.join(diverged)}.", ""]
      elif res["paired"]:
        prow = []
        for a, p in res["paired"].items():
          cells = [a]
          for k in ("mae", "seg_mae"):
            if k in p:
              cells.append(f"{_fmt_ci(p[k])}; p = {_fmt(p[k]['p'])}; {p[k]['wins']}/"
                           f"{p[k]['n']}")
            else:
              cells.append("-")
          cells.append(_fmt(p["pattern_acc"]["mean"], 2) if "pattern_acc" in p else "-")
          cells.append(_fmt_ci(p["delta_m"], 2))
          prow.append(cells)
        lines += [f"Paired against {plan.baseline} (arm - {plan.baseline}; negative = better "
                  "for MAE; p: paired t-test, unadjusted; seeds where the arm was better). Δm: "
                  "the mean relative gain over each task's primary metric both arms have "
                  "(disparity MAE; pattern accuracy where both predict patterns), > 0 better:",
                  ""]
        lines += _md_table(["arm", "Δ Full MAE px", "Δ Seg MAE px", "Δ pattern acc %",
                            "Δm %"], prow)
      if res["missing"]:
        lines += [f"Not scored yet: {', '.join(res['missing'])}.", ""]
      if res.get("diverged"):
        lines += [f"Left out, diverged (the training loss, or the pretraining's, went NaN or "
                  f"infinite: not scored, and the seed is left out of that arm's pairs): "
                  f"{', '.join(res['diverged'])}.", ""]
  if plan.name.removesuffix("-v2") in PAPER:
    lines += _rank_table(plan, agg)
  lines += ["### Every seed", ""]
  rows = []
  shown = [(k, h) for k, h in METRICS + (("depth_capped", "depth capped %"),)]
  for c in plan.cells:
    window = chosen_window(out, c.name)
    for e in c.evals:
      m = cell_metrics(out, c.name, e.name) or {}
      cv = curve(out, c.name)
      rows.append([c.name, e.name, str(c.seed)] + [_fmt(m.get(k)) for k, _ in shown]
                  + [_fmt(min((v for _, v in cv), default=None)),
                     "-" if window is None else str(window)])
  lines += _md_table(["cell", "set", "seed"] + [h for _, h in shown]
                     + ["best val MAE", "corr window (on validation)"], rows)
  edge, chose = window_edges(out, plan)
  if edge:
    lines += [f"The correlation window chosen on validation is the largest candidate in {edge} "
              f"of {chose} cells: a larger window might do better there. The set was fixed "
              "before the runs (docs/plan-v2.md), so this is noted, not acted on.", ""]
  lines += _time_lines(out, plan)
  lines += [f"![{f}](figures/{f})" for f in figs] + [""]
  return lines


def _set_label(plan: Plan, set_name: str) -> str:
  if set_name == CURVE_SET:
    return ("each cell's own validation curve (every validation scene; the rise is the final "
            "value minus the lowest)")
  if set_name == HELDOUT:
    return "the held-out split (v1: also the split training validated on)"
  for c in plan.cells:
    for e in c.evals:
      if e.name == set_name and e.kind == FIXED:
        which = ("" if e.checkpoint == "final" else
                 f"; each cell's {e.checkpoint} checkpoint by validation MAE")
        return (f"the fixed test set {set_name} ({e.n} {e.domain} scenes rendered from dataset "
                f"seed {TEST_SEED}, the same for every seed and arm{which})")
  return set_name


def _rank_table(plan: Plan, agg: dict[str, Any]) -> list[str]:
  """Arms ranked by mean Full MAE per group, beside the paper's ranking."""
  lines = ["### Ranking (the paper's table form; mean over seeds, then the paper's value)", ""]
  for g in agg["groups"]:
    where = next(iter(g["factors"].values()))
    paper = PAPER[plan.name.removesuffix("-v2")].get(where)
    res = g["sets"].get(HELDOUT) or next(iter(g["sets"].values()), None)
    if res is None or paper is None:
      continue
    for k, label, idx in (("mae", "Full", 0), ("seg_mae", "Seg", 1)):
      ours = sorted((s[k]["mean"], a) for a, s in res["arms"].items() if k in s)
      theirs = sorted((v[idx], a) for a, v in paper.items() if v[idx] is not None)
      if not ours:
        continue
      rows = [[str(i + 1), f"{a} {_fmt(m)}" if i < len(ours) else "-",
               f"{theirs[i][1]} {theirs[i][0]:.3f}" if i < len(theirs) else "-"]
              for i, (m, a) in enumerate(ours)]
      lines += [f"{where}, {label} MAE (px):", ""]
      lines += _md_table(["rank", "sljax", "paper"], rows)
  return lines


def write_report(out: str | Path, only: Sequence[str] | None = None) -> Path:
  """Writes OUT/report.md, OUT/report.json and OUT/figures/ for the plans registered under OUT
  (or the named ones of them); returns the report.md path."""
  out = Path(out)
  registered = {plan.name: plan for plan in registered_plans(out)}
  unknown = sorted(set(only or ()) - set(registered))
  if unknown:
    raise SljaxError(f"{out}: no plan {', '.join(unknown)} was run here (plans run: "
                     f"{', '.join(sorted(registered)) or 'none'})")
  if only:
    registered = {name: plan for name, plan in registered.items() if name in only}
  lines = ["# Experiment report", "",
           "Every cell is scored with its final checkpoint, through sljax's one metrics "
           "function: v1 plans on the cell's held-out split (which training also validated "
           "on), v2 plans on fixed test sets rendered from their own dataset seed (every "
           "choice made on validation; docs/plan-v2.md). Intervals are 95% Student-t "
           "intervals over seeds; paired differences compare arms trained on the same seed "
           "(same data, split, subset, order and shared initial weights). The claims of each "
           "table are Holm-adjusted together and judged on the adjusted p; 'detectable' is the "
           "difference the test had 80% power to detect. Depth: predicted depth capped at "
           "2x the scene's farthest ground truth (sljax.evaluation.metrics), the capped share shown. Any "
           "statement that a gain of a given size is excluded is exploratory.", ""]
  data: dict[str, Any] = {}
  # The figures go to a hidden folder and the two files to temporaries, all moved in together
  # at the end: a failed report leaves OUT as it was (no figures/ of a report never written).
  with files.staged(out / "figures") as fig_dir, \
       files.replacing(out / "report.md", out / "report.json") as (md, js):
    for name in PLANS:  # in the paper's order
      if name not in registered or not any(c.evals for c in registered[name].cells):
        continue  # a plan that scores no set (the v3 pilot) is reported by its own command
      plan, args = registered[name], plan_args(registered[name])
      agg = aggregate(out, plan)
      cl = claims(plan, agg)
      figs = figures.write(plan, agg, fig_dir)
      lines += _plan_markdown(out, plan, agg, cl, figs)
      data[name] = {"args": args, "aggregate": agg, "claims": cl, "figures": figs}
    md.write_bytes("\n".join(lines).encode("utf-8"))
    js.write_bytes((dumps(json_safe(data)) + "\n").encode("utf-8"))
  return out / "report.md"
