"""Main renders the scenes the committed v2 grids trained and were scored on: a few scenes of
each plan's training data (and its training subset and validation split) and of every fixed
test set, fingerprinted by the code the grids ran on (tests/data/v2_scenes.json, written by
tools/scene_fingerprints.py at that commit). A renderer or split change that moved the test
sets under the committed records fails here."""

import json
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from sljax.experiment.design.plans import build_plan
from sljax.experiment.running import runner
from sljax.train.feed import open_source

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
import scene_fingerprints  # noqa: E402  (tools/ is on the path above)

RECORD = json.loads((ROOT / "tests" / "data" / "v2_scenes.json").read_text())
STORED = RECORD["scenes"]


def _cell(where):
  """The cell at `where`, built by main's code from the grid's plan.json."""
  args = json.loads((ROOT / "docs" / "results" / where["grid"] / "plan.json").read_text())[
      "plans"][where["plan"]]
  plan = build_plan(where["plan"], args["scale"], args["seeds"], args["data"],
                    tuple(args["eval_data"]))
  return next(c for c in plan.cells if c.name == where["cell"])


def _scene(where):
  """The scene at `where`, rendered by main's code on the CPU (as the grids ran; a GPU's
  transcendental functions differ in the last bits)."""
  with jax.default_device(jax.devices("cpu")[0]):
    return _render(where)


def _render(where):
  cell = _cell(where)
  if where["set"] == "train":
    return open_source(cell.config)[where["index"]]
  evalset = next(e for e in cell.evals if e.name == where["set"])
  source, indices = runner._eval_source(cell, evalset)
  assert where["index"] in indices
  return source[where["index"]]


def test_every_grid_and_fixed_test_set_is_fingerprinted_by_the_grids_code():
  assert RECORD["code"].startswith("c353bc7")  # the commit the v2 grids ran on (plan-v2.md)
  covered = {(w["grid"], w["set"]) for w in STORED}
  for grid in ("v2-cpu", "v2-cpu128"):
    assert {(grid, "train"), (grid, "test-objects"), (grid, "test-tissue")} <= covered


@pytest.mark.parametrize("where", STORED, ids=lambda w: f"{w['grid']}-{w['cell']}-{w['set']}-"
                                                       f"{w['index']}")
def test_main_renders_the_grids_scenes(where):
  if where["set"] == "train":  # the same scenes train and validate, in the same order
    assert scene_fingerprints.split(_cell(where).config) == where["split"]
  got = scene_fingerprints.fingerprint(_scene(where))
  assert sorted(got) == sorted(where["parts"])
  stats = {k: v for k, v in where["parts"].items() if not k.endswith("_patch")}
  for part, (n, mean, std) in stats.items():
    # XLA's compiler options and the CPU's vector width move float32 renders in the last bit,
    # and the 8-bit sensor quantisation turns a few of those into one grey level (this suite
    # compiles with fewer optimisations: up to 1.4e-5 here; with XLA's defaults the frozen
    # and main code agree exactly, Intel Xeon f6 m167); a pixel becoming known or unknown moves
    # the statistics by about its value over n. A changed scene moves them far more.
    dn = abs(got[part][0] - n)
    assert dn <= max(2, n // 1000), (part, got[part][0], n)
    tol = 1e-4 + 2 * dn * (abs(mean) + 4 * std) / n
    np.testing.assert_allclose(got[part][1:], [mean, std], rtol=0, atol=tol, err_msg=part)
  for view in ("im0_patch", "im1_patch"):
    # Rounding moves a pixel by at most one level and rarely (2 of 256 at most, seen with
    # AVX2-only and fast-compiled renders); a change of the sensor noise (0.002 -> 0.003)
    # moves about a fifth of them.
    diff = np.abs(np.subtract(got[view], where["parts"][view]))
    assert diff.max() <= 1 and np.count_nonzero(diff) <= 4, (view, np.count_nonzero(diff))
