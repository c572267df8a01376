"""Fingerprints of the scenes the committed v2 grids trained and were scored on.

The grids ran on code frozen at one commit and their records are committed; the report and
any later re-scoring run on main. tests/test_committed_records.py checks that main still builds the
same cells (configurations); this checks that main still renders the same scenes for them, so
that a change to the renderer, the split or a plan's data that would move the test sets under
the records fails a test instead of passing unnoticed. Per scene: pixel count, mean and
standard deviation of each view, the known disparities and the patterns, and the 8-bit grey
levels of a centre crop of each view (compared with a tolerance: float32 renders can differ in
the last bit between CPUs and compiler options, where a byte hash would fail).

    PYTHONPATH=<checkout of the grids' commit> python tools/scene_fingerprints.py \\
        > tests/data/v2_scenes.json

Run it with the code the grids ran on (docs/plan-v2.md names the commit); the test recomputes
every entry with main's code.
"""

import hashlib
import json
import subprocess
import sys
from pathlib import Path
from typing import Any, Iterator

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
GRIDS = ROOT / "docs" / "results"


PATCH = 16  # side of the centre crop kept as 8-bit grey levels


def fingerprint(scene: Any) -> dict[str, list]:
  """{part: [known values, mean, std]} of a scene's views, disp0 and sl0 (float64), and
  {view_patch: 8-bit levels of the first channel's centre PATCH x PATCH crop} of each view:
  the statistics see changes to geometry and splits, the levels see changes to the noise."""
  out: dict[str, list] = {}
  for name in ("im0", "im1", "disp0", "sl0"):
    a = getattr(scene, name, None)
    if a is None:
      continue
    known = np.asarray(a, np.float64)
    known = known[np.isfinite(known)]
    out[name] = [int(known.size), float(known.mean()), float(known.std())]
  for name in ("im0", "im1"):
    a = np.asarray(getattr(scene, name), np.float64)
    y, x = (a.shape[0] - PATCH) // 2, (a.shape[1] - PATCH) // 2
    out[f"{name}_patch"] = np.rint(a[y:y + PATCH, x:x + PATCH, 0] * 255).astype(int).ravel(
        ).tolist()
  return out


def split(config: Any) -> dict[str, Any]:
  """The training subset and the validation split a cell's training used (as setup does):
  their sizes and a SHA-256 of each index list (order included)."""
  from sljax.data.dataset import split_indices, take_fraction
  from sljax.train.feed import open_source

  train, val = split_indices(open_source(config), config.test_fraction, seed=config.seed)
  train = take_fraction(train, config.fraction, seed=config.seed)
  digest = lambda v: hashlib.sha256(json.dumps([int(i) for i in v]).encode()).hexdigest()
  return {"n_train": len(train), "train": digest(train), "n_val": len(val), "val": digest(val)}


def scenes() -> Iterator[tuple[dict[str, Any], Any]]:
  """(where, scene) for a few scenes of every grid's plans: the first training scene of each
  plan's first and last cell (with its split), and the first and last scene of each fixed test
  set."""
  from sljax.experiment.design.cells import FIXED
  from sljax.experiment.design.plans import build_plan
  from sljax.experiment.running import runner
  from sljax.train.feed import open_source

  seen = set()
  for grid in sorted(GRIDS.glob("v2-*")):
    record = json.loads((grid / "plan.json").read_text())
    for name, args in sorted(record["plans"].items()):
      plan = build_plan(name, args["scale"], args["seeds"], args["data"],
                        tuple(args["eval_data"]))
      for cell in (plan.cells[0], plan.cells[-1]):
        where = dict(grid=grid.name, plan=name, cell=cell.name, set="train", index=0,
                     split=split(cell.config))
        yield where, open_source(cell.config)[0]
        for evalset in cell.evals:
          if evalset.kind != FIXED:
            continue
          source, indices = runner._eval_source(cell, evalset)
          for i in (indices[0], indices[-1]):
            key = (evalset.name, cell.config.synth_size, cell.config.synth_t, i)
            if key not in seen:
              seen.add(key)
              yield dict(grid=grid.name, plan=name, cell=cell.name, set=evalset.name,
                         index=i), source[i]


def code_commit() -> str:
  """The git commit of the sljax package imported here (the code that rendered the scenes)."""
  import sljax
  folder = Path(sljax.__file__).resolve().parents[1]
  head = subprocess.run(["git", "-C", str(folder), "rev-parse", "HEAD"], capture_output=True,
                        text=True)
  return head.stdout.strip() or f"unknown ({folder})"


def main() -> int:
  """Writes the fingerprints as JSON to stdout."""
  rows = [json.dumps(dict(where, parts=fingerprint(scene))) for where, scene in scenes()]
  print(f'{{"code": {json.dumps(code_commit())}, "scenes": [\n' + ",\n".join(rows)
        + "\n]}")  # a scene a line
  return 0


if __name__ == "__main__":
  sys.exit(main())
