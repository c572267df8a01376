"""A report's figures: per plan, bar charts of each arm's mean with its 95% interval and the
seeds as dots, and the validation (and training) curves with their bands over seeds."""

import math
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from sljax.experiment.design.plans import Plan
from sljax.io import files


def write(plan: Plan, agg: dict[str, Any], fig_dir: Path) -> list[str]:
  """Bar charts with 95% intervals and validation curves; returns the file names."""
  fig_dir.mkdir(parents=True, exist_ok=True)
  names = []
  groups = agg["groups"]
  panels = [(g, s) for g in groups for s in g["sets"]]
  fig = Figure(figsize=(3.2 * max(1, len(panels)) + 1, 3.4))
  axes = fig.subplots(1, max(1, len(panels)), squeeze=False)
  for ax, (g, set_name) in zip(axes[0], panels):
    arms = [a for a in g["sets"][set_name]["arms"]]
    for i, a in enumerate(arms):
      s = g["sets"][set_name]["arms"][a].get("mae")
      if not s or s["n"] == 0:
        continue
      err = None if math.isnan(s["lo"]) else [[s["mean"] - s["lo"]], [s["hi"] - s["mean"]]]
      color = "0.6" if a == plan.baseline else "C0"
      ax.bar(i, s["mean"], yerr=err, capsize=4, color=color)
      vals = [v for v in s["values"].values() if v is not None]
      ax.plot([i] * len(vals), vals, "k.", ms=4)
    ax.set_xticks(range(len(arms)), arms, rotation=30)
    ax.set_title(f"{', '.join(g['factors'].values())}: {set_name}", fontsize=9)
    ax.set_ylabel("Full MAE (px)")
  fig.suptitle(f"{plan.name}: mean and 95% interval over seeds (dots: seeds)", fontsize=10)
  fig.tight_layout()
  name = f"{plan.name}_bars.png"
  files.save_figure(fig, fig_dir / name, dpi=110)
  names.append(name)
  with_curves = [g for g in groups if g["curves"]]
  if with_curves:
    # A second row, the training loss between validations, where the cells validated by steps.
    rows = [("curves", "validation MAE (px)")] + (
        [("train_curves", "training L_disp (log)")]
        if any(g.get("train_curves") for g in with_curves) else [])
    fig = Figure(figsize=(4.5 * len(with_curves), 3.4 * len(rows)))
    axes = fig.subplots(len(rows), len(with_curves), squeeze=False)
    for r, (key, label) in enumerate(rows):
      for ax, g in zip(axes[r], with_curves):
        _curve_panel(ax, g.get(key, {}), plan.baseline, _unit(g))
        ax.set_xlabel(_unit(g))
        ax.set_ylabel(label)
        if key == "train_curves":
          ax.set_yscale("log")
        ax.set_title(", ".join(g["factors"].values()), fontsize=9)
        ax.legend(fontsize=7)
    unit = _unit(with_curves[0])
    what = "validation MAE" + (" and training loss" if len(rows) > 1 else "")
    fig.suptitle(f"{plan.name}: {what} per {unit} (mean, 95% band over seeds)", fontsize=10)
    fig.tight_layout()
    name = f"{plan.name}_curves.png"
    files.save_figure(fig, fig_dir / name, dpi=110)
    names.append(name)
  return names


def _unit(group: dict[str, Any]) -> str:
  """The x axis of a group's curves: steps where its cells validated by steps, else epochs."""
  return "step" if any("step" in pts[0] for pts in group["curves"].values()) else "epoch"


def _curve_panel(ax, curves: dict[str, list[dict[str, Any]]], baseline: str, unit: str) -> None:
  """Each arm's mean curve (the baseline dashed) and its 95% band."""
  for k, (a, pts) in enumerate(curves.items()):
    e = np.array([p[unit] for p in pts])
    ax.plot(e, [p["mean"] for p in pts], "--" if a == baseline else "-", color=f"C{k}",
            label=a)
    lo = np.array([p["lo"] for p in pts], float)
    hi = np.array([p["hi"] for p in pts], float)
    if np.isfinite(lo).all():
      ax.fill_between(e, lo, hi, color=f"C{k}", alpha=0.15)
