"""Copies the records of finished experiment cells from a running grid's folder into the
committed results folder (what docs/results.md is written from), and optionally commits them.

    python tools/grid_records.py runs/v2-cpu docs/results/v2-cpu [--commit "message"]

Per finished cell (done.json present and nothing left to score): config.json, epochs.jsonl,
train.log, notes.txt and eval/*.json, and done.json with the CPU it ran on added (`machine`,
when the runner did not record it; written back to the grid's folder too). Checkpoints and
metrics.jsonl stay behind. A cell whose training diverged (diverged.json) comes over with
that file and its logs, so that a report written from the records names it too. A cell
already copied gets only its new evaluation files (a plan that scores trained cells on more
test sets, e.g. table3-v2 after fig7-v2). plan.json is copied as it is. Safe beside the
running grid: it reads finished cells only.
"""

import argparse
import json
import lzma
import shutil
import subprocess
import sys
from pathlib import Path

from sljax.experiment import records
from sljax.experiment.running import runner
from sljax.runtime.machine import cpu_description

KEPT = ("config.json", "epochs.jsonl", "validation.jsonl", "train.log", "notes.txt")
# Training logs are most of a cell's bytes after its evaluation reports: kept compressed, as
# the runner writes the reports (every reader takes NAME or NAME.xz; sljax.experiment.records).
COMPRESSED = ("epochs.jsonl", "validation.jsonl")


def _copy_kept(s: Path, d: Path, names: tuple[str, ...]) -> None:
  """Copies those of `names` that cell folder s holds into d (training logs compressed)."""
  d.mkdir(parents=True, exist_ok=True)
  for name in names:
    if (s / name).exists() and name in COMPRESSED:
      (d / (name + records.COMPRESSED)).write_bytes(lzma.compress((s / name).read_bytes()))
    elif (s / name).exists():
      shutil.copy(s / name, d / name)


def copy_finished(src: Path, dst: Path) -> list[str]:
  """Copies what is new of every finished cell of the plans registered in src; returns
  'cell' (a new cell) or 'cell: eval/x.json' (new scores of a copied cell) per change."""
  changes = []
  dst.mkdir(parents=True, exist_ok=True)
  shutil.copy(src / records.PLAN_FILE, dst / records.PLAN_FILE)
  seen = set()
  for plan in records.registered_plans(src):
    left_out = runner.diverged(src, plan)
    waiting = {cell.name for cell, _, _ in runner.pending(src, plan, left_out)}
    for cell in plan.cells:
      s, d = records.cell_dir(src, cell.name), records.cell_dir(dst, cell.name)
      if (s / records.DIVERGED_FILE).exists() and not (d / records.DIVERGED_FILE).exists():
        # The report written from the records must name it, as it would from the grid's folder.
        _copy_kept(s, d, KEPT + (records.DIVERGED_FILE,))
        changes.append(f"{cell.name}: diverged")
        continue
      if cell.name in seen or cell.name in waiting or not (s / records.DONE_FILE).exists():
        continue
      seen.add(cell.name)
      if not (d / records.DONE_FILE).exists():
        _copy_kept(s, d, KEPT)
        done = records.read_done(src, cell.name)  # a damaged one: one line naming it
        if not done.get("machine"):
          done["machine"] = cpu_description()
          (s / records.DONE_FILE).write_text(json.dumps(done, indent=1))
        (d / records.DONE_FILE).write_text(json.dumps(done, indent=1))
        changes.append(cell.name)
      (d / records.EVAL_DIR).mkdir(exist_ok=True)
      for f in sorted((s / records.EVAL_DIR).glob("*.json*")):  # reports: SET.json.xz
        if not (d / records.EVAL_DIR / f.name).exists():
          shutil.copy(f, d / records.EVAL_DIR / f.name)
          if changes[-1:] != [cell.name]:
            changes.append(f"{cell.name}: {records.EVAL_DIR}/{f.name}")
  return changes


def main(argv: list[str] | None = None) -> int:
  """Copies, prints what changed, and commits the results folder when asked."""
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("src", type=Path, help="the grid's experiment folder (runs/...)")
  p.add_argument("dst", type=Path, help="the committed records (docs/results/...)")
  p.add_argument("--commit", metavar="MESSAGE", help="git add DST and commit with MESSAGE")
  args = p.parse_args(argv)
  changes = copy_finished(args.src, args.dst)
  print("\n".join(changes) if changes else "nothing new")
  if changes and args.commit:
    subprocess.run(["git", "add", str(args.dst)], check=True)
    subprocess.run(["git", "commit", "-qm", args.commit], check=True)
  return 0


if __name__ == "__main__":
  sys.exit(main())
