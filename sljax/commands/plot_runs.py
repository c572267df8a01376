"""`sljax plot-runs WORKDIR... --out PNG`: validation MAE against epoch for several runs."""

import argparse
import json
import math
import os
from pathlib import Path
from typing import Any

from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from sljax.errors import SljaxError
from sljax.io import files, tables
from sljax.io.files import read_json_object
from sljax.nets.registry import NETS

EPOCHS_FILE = "epochs.jsonl"
CONFIG_FILE = "config.json"


def register(subparsers) -> None:
  """Adds the `plot-runs` subcommand."""
  p = subparsers.add_parser(
      "plot-runs",
      description="Reads WORKDIR/epochs.jsonl ('epoch', 'val_mae', other 'val_*' keys) and "
                  "WORKDIR/config.json (label = model/strategy) of each run, draws validation "
                  "MAE against epoch in one figure (like the paper's Fig. 7) and prints a "
                  "Markdown table of the final metrics, also written beside the PNG (.md).",
      formatter_class=argparse.ArgumentDefaultsHelpFormatter)
  p.add_argument("workdirs", nargs="+", metavar="WORKDIR", help="training workdirs")
  p.add_argument("--out", required=True, help="PNG to write; the table goes to the same name .md")
  p.add_argument("--title", default="Validation MAE", help="figure title")
  p.add_argument("--log", action="store_true", help="logarithmic MAE axis")
  p.add_argument("--overwrite", action="store_true", help="replace an existing PNG and .md")
  p.set_defaults(func=run)


def run_label(config: dict[str, Any], workdir: Path) -> str:
  """model/strategy for PSMNet runs, the model for the UNets, else the folder name."""
  model = config.get("model")
  strategy = config.get("strategy")
  if model is None:
    return workdir.name
  if model in NETS and NETS[model].twin and strategy:
    return f"{model}/{strategy}"
  return str(model)


def read_run(workdir: str | os.PathLike) -> dict[str, Any]:
  """{'workdir', 'label', 'records'} of one run; SljaxError naming a missing/bad file."""
  workdir = Path(workdir)
  path = workdir / EPOCHS_FILE
  if not path.is_file():
    raise SljaxError(f"{workdir}: no {EPOCHS_FILE} (not a training workdir, or no epoch "
                     "finished yet)")
  records = []
  for n, raw in enumerate(path.read_bytes().splitlines(), 1):
    if not raw.strip():
      continue
    try:
      rec = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as e:
      raise SljaxError(f"{path}: line {n} is not UTF-8 text (byte {e.start + 1} of the line)") \
          from None
    except json.JSONDecodeError as e:
      raise SljaxError(f"{path}: line {n} is not JSON ({e.msg})") from None
    if not isinstance(rec, dict) or "epoch" not in rec:
      raise SljaxError(f"{path}: line {n} has no 'epoch' key")
    records.append(rec)
  config: dict[str, Any] = {}
  cfg_path = workdir / CONFIG_FILE
  if cfg_path.is_file():
    config = read_json_object(cfg_path, str(cfg_path))
  return {"workdir": str(workdir), "label": run_label(config, workdir), "records": records}


def _finite(v: Any) -> bool:
  return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def summary_table(runs: list[dict[str, Any]]) -> str:
  """Markdown table: final and best validation MAE and the final epoch's other val_* metrics."""
  extra: list[str] = []
  for r in runs:
    vals = [rec for rec in r["records"] if _finite(rec.get("val_mae"))]
    final = vals[-1] if vals else {}
    for k in final:
      if k.startswith("val_") and k != "val_mae" and _finite(final[k]) and k not in extra:
        extra.append(k)
  header = ["run", "workdir", "epochs", "final val MAE px", "best val MAE px (epoch)"] + extra
  rows = []
  for r in runs:
    vals = [rec for rec in r["records"] if _finite(rec.get("val_mae"))]
    epochs = max((rec["epoch"] for rec in r["records"]), default=0)
    if vals:
      final = vals[-1]
      best = min(vals, key=lambda rec: rec["val_mae"])
      cells = [f"{final['val_mae']:.3f}", f"{best['val_mae']:.3f} ({best['epoch']})"]
      cells += [f"{final[k]:.4g}" if _finite(final.get(k)) else "-" for k in extra]
    else:
      cells = ["-", "-"] + ["-"] * len(extra)
    rows.append([r["label"], f"`{r['workdir']}`", str(epochs)] + cells)
  return "\n".join(tables.table(header, rows)) + "\n"


def plot(runs: list[dict[str, Any]], out: str | os.PathLike, title: str = "Validation MAE",
         log: bool = False) -> None:
  """One line per run: validation MAE (px) against epoch."""
  fig = Figure(figsize=(6.4, 4.2))
  ax = fig.subplots()
  for r in runs:
    pts = [(rec["epoch"], rec["val_mae"]) for rec in r["records"] if _finite(rec.get("val_mae"))]
    if pts:
      xs, ys = zip(*pts)
      ax.plot(xs, ys, marker="o", markersize=3, label=r["label"])
  ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # epochs are whole numbers
  ax.set_xlabel("epoch")
  ax.set_ylabel("validation MAE (px)")
  if log:
    ax.set_yscale("log")
  ax.set_title(title)
  ax.grid(alpha=0.3)
  ax.legend()
  fig.tight_layout()
  Path(out).parent.mkdir(parents=True, exist_ok=True)
  files.save_figure(fig, out, dpi=120)


def run(args) -> int:
  """Reads the runs, writes the PNG and the table, prints the table."""
  out = Path(args.out)
  if out.suffix.lower() != ".png":
    raise SljaxError(f"--out {out}: expected a .png file name")
  files.refuse_existing([out, out.with_suffix(".md")], args.overwrite)
  runs = [read_run(w) for w in args.workdirs]
  labels = [r["label"] for r in runs]
  for r in runs:  # several runs of one configuration: tell them apart by folder name
    if labels.count(r["label"]) > 1:
      r["label"] = f"{r['label']} ({Path(r['workdir']).name})"
  if not any(_finite(rec.get("val_mae")) for r in runs for rec in r["records"]):
    raise SljaxError("no run has a 'val_mae' in its epochs.jsonl: nothing to plot")
  plot(runs, out, args.title, args.log)
  table = summary_table(runs)
  files.write_text(out.with_suffix(".md"), table)
  print(table, end="")
  print(f"wrote {out} and {out.with_suffix('.md')}")
  return 0
