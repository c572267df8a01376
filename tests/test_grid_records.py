"""The committed v2 grid records (docs/results/v2-*) were produced by code frozen at one
commit; the report that turns them into docs/results.md runs on main's code. These tests
guard that main still builds the same cells (a changed default, budget or scale would make
the report read the records as another plan) and that every committed cell is complete."""

import json
from pathlib import Path

import pytest

from sljax.experiment.plans import build_plan

ROOT = Path(__file__).resolve().parents[1]
GRIDS = sorted((ROOT / "docs" / "results").glob("v2-*"))


@pytest.mark.parametrize("grid", GRIDS, ids=lambda p: p.name)
def test_main_builds_the_cells_the_grid_was_run_with(grid):
  record = json.loads((grid / "plan.json").read_text())
  assert record["plans"], grid
  for name, args in record["plans"].items():
    plan = build_plan(name, args["scale"], args["seeds"], args["data"],
                      tuple(args["eval_data"]))
    for cell in plan.cells:
      assert cell.spec() == record["cells"][cell.name], (grid.name, cell.name)


@pytest.mark.parametrize("grid", GRIDS, ids=lambda p: p.name)
def test_every_committed_cell_is_complete_and_named_by_its_plan(grid):
  record = json.loads((grid / "plan.json").read_text())
  cells = sorted(p for p in (grid / "cells").iterdir())
  assert cells
  for cell in cells:
    assert cell.name in record["cells"], cell
    done = json.loads((cell / "done.json").read_text())
    assert done["machine"] and done["step"] > 0, cell  # the CPU is named beside the times
    config = json.loads((cell / "config.json").read_text())
    assert config["seed"] == record["cells"][cell.name]["config"]["seed"], cell
    assert list((cell / "eval").glob("*.json")), cell  # scored
