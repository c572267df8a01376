"""The paper's claims checked on an experiment's aggregate: one family per table (plan).

Each claim is a paired comparison of one arm against the other on one metric and set. A
claim "A beats B" holds when its Holm-adjusted p (over the plan's claims) is below ALPHA and
the mean difference favours A, is contradicted ("does not hold") when the adjusted p is below
ALPHA and it favours B, and is not shown otherwise. Each also carries the smallest true
difference its test had POWER to detect, whether the paper itself found a gain, and
(exploratory) whether a gain of the paper's relative size is excluded.
"""

import math
from typing import Any

from sljax.experiment.design.cells import HELDOUT, Plan
from sljax.experiment.report import stats
from sljax.losses.weighting import MULTI_TASK

ALPHA = 0.05
MARGIN = 0.10  # v5: a smoothed curve overfits when it ends this far above its minimum
CURVE_SET = "validation-curve"  # v3: each cell's own validation curve (report.py)
POWER = 0.8
# The paper's numbers (SPEC 5 and 2), for the tables' reference columns.
PAPER = {
    "table2": {"all": {"cg_b": (0.203, 0.380), "unc": (0.207, 0.381), "stl": (0.208, 0.382),
                       "epr": (0.217, 0.384), "cg_a": (0.217, 0.389)},
               "1/16": {"cg_a": (0.496, 0.745), "cg_b": (0.504, 0.808), "unc": (0.516, 0.778),
                        "epr": (0.522, 0.781), "stl": (0.549, 0.790)}},
    "table1": {"objects": {"unet-sl": (1.72, 1.45), "unet-disp": (0.52, 0.75)},
               "tissue": {"unet-sl": (2.36, None), "unet-disp": (5.89, None)}},
}


def _verdict(diff: dict[str, float], p_adjusted: float) -> str:
  if diff["n"] < 2 or math.isnan(p_adjusted):
    return "not testable (fewer than 2 seeds)"
  if p_adjusted < ALPHA:
    return "holds" if diff["mean"] < 0 else "does not hold (the opposite is shown)"
  return f"not shown (Holm-adjusted p >= {ALPHA:g})"


def _paper_gain(table: str, frac: str, arm: str, metric: str) -> bool:
  """Whether the paper's table shows the arm better than stl on the metric."""
  idx = 0 if metric == "mae" else 1
  return PAPER[table][frac][arm][idx] < PAPER[table][frac]["stl"][idx]


def _paper_relative(table: str, where: str, better: str, other: str, metric: str) -> float:
  """The paper's relative difference (better - other) / other on a metric (< 0: a gain)."""
  idx = 0 if metric == "mae" else 1
  b, o = PAPER[table][where][better][idx], PAPER[table][where][other][idx]
  return (b - o) / o


def claims(plan: Plan, agg: dict[str, Any]) -> list[dict[str, Any]]:
  """The paper's claims for this plan (one family), each with the measured paired difference,
  its Holm-adjusted p over the family, the difference it could detect and a verdict."""
  out: list[dict[str, Any]] = []
  v2 = plan.name.endswith("-v2")
  base_name = plan.name.removesuffix("-v2")

  def group(**factors):
    for g in agg["groups"]:
      if all(g["factors"].get(k) == v for k, v in factors.items()):
        return g
    return None

  def add(text: str, g, set_name: str, arm: str, metric: str, sign: int = 1,
          paper_gain: bool = True, paper_rel: float | None = None):
    if g is None or set_name not in g["sets"]:
      return
    diff = g["sets"][set_name]["paired"].get(arm, {}).get(metric)
    row = {"claim": text, "metric": metric, "set": set_name, "arm": arm,
           "paper": "gain" if paper_gain else "no gain"}
    if diff is None or diff["n"] == 0:
      out.append(dict(row, verdict="no results yet"))
      return
    d = dict(diff)
    if sign < 0:  # the claim is "baseline beats arm": test baseline - arm
      d.update(mean=-diff["mean"], lo=-diff["hi"], hi=-diff["lo"], wins=diff.get("losses"),
               losses=diff["wins"], t=-diff["t"])
    row.update(difference=d, detectable=stats.detectable_difference(d["sd"], d["n"], POWER,
                                                                    ALPHA))
    other = plan.baseline if sign > 0 else arm
    other_mean = g["sets"][set_name].get("arms", {}).get(other, {}).get(metric, {}).get("mean")
    if paper_rel is not None and paper_rel < 0 and other_mean is not None:
      # Exploratory: the paper's relative gain at this scale, and whether the interval lies
      # wholly above it (a gain that large excluded).
      row["paper_sized"] = paper_rel * other_mean
      row["paper_sized_excluded"] = bool(d["lo"] > row["paper_sized"])
    out.append(row)

  if base_name == "table2":
    for frac in (("1/16",) if v2 else ("all", "1/16")):
      g = group(data=frac)
      set_name = "test-objects" if v2 else HELDOUT
      for arm in MULTI_TASK:
        for metric, label in (("mae", "Full"), ("seg_mae", "Seg")):
          add(f"{frac} data: {arm} has a lower {label} MAE than stl", g, set_name, arm, metric,
              paper_gain=_paper_gain("table2", frac, arm, metric),
              paper_rel=_paper_relative("table2", frac, arm, "stl", metric))
  elif base_name == "table1":
    for where in ("objects", "tissue", "data"):
      g = group(data=where)
      if g is None:
        continue
      set_name = f"test-{where}" if v2 else HELDOUT
      if where == "objects":
        add("objects: the direct network (unet-disp) has a lower Full MAE than unet-sl "
            "(paper: 0.52 vs 1.72 px)", g, set_name, "unet-sl", "mae", sign=-1,
            paper_rel=_paper_relative("table1", "objects", "unet-disp", "unet-sl", "mae"))
        add("objects: unet-disp has a lower Seg MAE than unet-sl (paper: 0.75 vs 1.45 px)", g,
            set_name, "unet-sl", "seg_mae", sign=-1,
            paper_rel=_paper_relative("table1", "objects", "unet-disp", "unet-sl", "seg_mae"))
      else:
        add(f"{where} (fine-tuned on scarce data): unet-sl's correlation disparity has a lower "
            "MAE than unet-disp (paper: 2.36 vs 5.89 px)", g, set_name, "unet-sl", "mae",
            paper_rel=_paper_relative("table1", "tissue", "unet-sl", "unet-disp", "mae"))
  elif base_name == "table3":
    g = agg["groups"][0]
    in_domain = ("test-objects",) if v2 else (HELDOUT,)
    for set_name in g["sets"]:
      if set_name in in_domain:  # table3 is about other domains; in-domain is table2's
        continue
      for arm in MULTI_TASK:
        add(f"{set_name}: {arm} has a lower MAE than stl (paper: stl last everywhere)", g,
            set_name, arm, "mae")
  elif plan.name == "v3":
    # docs/plan-v3.md: one family of two claims; epr (exploratory) is reported, not tested.
    g = agg["groups"][0] if agg["groups"] else None
    add("objects test set, final checkpoint: unc has a lower Full MAE than stl", g,
        "test-objects", "unc", "mae")
    add("validation: unc's overfitting rise (final minus lowest validation Full MAE) is "
        "smaller than stl's", g, CURVE_SET, "unc", "rise")
  elif plan.name == "v4":
    # docs/plan-v4.md: v3's family of two, on the regime setting's own test set.
    setting = plan.scale.v4.regime[0]
    where = "tissue" if setting == "finetune" else "objects"
    g = group(setting=setting)
    add(f"{where} test set, final checkpoint: unc has a lower Full MAE than stl", g,
        f"test-{where}", "unc", "mae")
    add("validation: unc's overfitting rise (final minus lowest validation Full MAE) is "
        "smaller than stl's", g, CURVE_SET, "unc", "rise")
  elif plan.name == "v5":
    # docs/plan-v5.md: one family of two; cg_a, cg_b and epr against stl are exploratory.
    g = group(setting="finetune")
    add("tissue test set, final checkpoint: unc has a lower Full MAE than stl", g,
        "test-tissue", "unc", "mae")
    add("validation: unc's smoothed rise (final over lowest, relative) is smaller than stl's",
        g, CURVE_SET, "unc", "rise_rel")
  elif base_name == "fig7":
    for where in ("tissue", "data"):
      g = group(data=where)
      if g is None:
        continue
      set_name = "test-tissue" if v2 else HELDOUT
      for arm in MULTI_TASK:
        add(f"{where} fine-tuning: {arm} ends with a lower MAE than stl (paper: only unc)", g,
            set_name, arm, "mae", paper_gain=arm == "unc")
  adjusted = stats.holm([c["difference"]["p"] if "difference" in c else math.nan for c in out])
  for c, p_adj in zip(out, adjusted):
    if "difference" in c:
      c["p_holm"] = p_adj
      c["verdict"] = _verdict(c["difference"], p_adj)
  return out


def curve_rise(points: list[dict[str, Any]]) -> float | None:
  """A mean curve's smoothed rise: its last trailing mean of 3 over its lowest, minus 1."""
  values = [p["mean"] for p in points if p.get("mean") is not None and math.isfinite(p["mean"])]
  if not values:
    return None
  smoothed = [sum(values[max(0, i - 2):i + 1]) / len(values[max(0, i - 2):i + 1])
              for i in range(len(values))]
  return smoothed[-1] / min(smoothed) - 1.0


def mechanism(plan: Plan, agg: dict[str, Any]) -> str | None:
  """v5's pre-registered outcome in one paragraph: the mechanism acts when stl's seed-mean
  curve rises by MARGIN, unc's does not, and claim (b) holds; None for other plans."""
  if plan.name != "v5":
    return None
  g = next((g for g in agg["groups"] if g["factors"].get("setting") == "finetune"), None)
  curves = {} if g is None else g.get("curves", {})
  stl, unc = curve_rise(curves.get("stl", [])), curve_rise(curves.get("unc", []))
  if stl is None or unc is None:
    return "No outcome yet: stl's or unc's fine-tuning cells have not finished."
  (b,) = [c for c in claims(plan, agg) if c["metric"] == "rise_rel"] or [{}]
  said = (f"stl's seed-mean validation curve (smoothed, trailing mean of 3) ends {stl:+.1%} "
          f"above its minimum, unc's {unc:+.1%} (margin {MARGIN:.0%}); claim (b): "
          f"{b.get('verdict', 'no results yet')}. ")
  if stl < MARGIN:
    return said + ("**stl did not overfit**: the mechanism had nothing to prevent here, so "
                   "it is not tested (as in v3 and v4).")
  if unc < MARGIN and b.get("verdict") == "holds":
    return said + "**The mechanism acts**: stl overfits, unc does not, and (b) holds."
  return said + "**stl overfits and unc is not shown to prevent it.**"
