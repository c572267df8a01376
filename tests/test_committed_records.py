"""The committed grid records (docs/results/v2-*, v3-*) were produced by code frozen at one
commit; the report that turns them into docs/results.md runs on main's code. These tests
guard that main still builds the same cells (a changed default, budget or scale would make
the report read the records as another plan), that every committed cell is complete, and that
main writes the committed reports (which docs/results.md quotes) byte for byte."""

import json
import lzma
import shutil
from pathlib import Path

import pytest

from sljax.experiment.budget import regime
from sljax.experiment.design.plans import build_plan
from sljax.experiment.report import build

ROOT = Path(__file__).resolve().parents[1]
GRIDS = sorted((ROOT / "docs" / "results").glob("v[234]-*"))


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
  scored = {c.name for name, args in record["plans"].items()
            for c in build_plan(name, args["scale"], args["seeds"], args["data"],
                                tuple(args["eval_data"])).cells if c.evals}
  cells = sorted(p for p in (grid / "cells").iterdir())
  assert cells
  for cell in cells:
    assert cell.name in record["cells"], cell
    done = json.loads((cell / "done.json").read_text())
    assert done["machine"] and done["step"] > 0, cell  # the CPU is named beside the times
    config = json.loads((cell / "config.json").read_text())
    assert config["seed"] == record["cells"][cell.name]["config"]["seed"], cell
    assert cell.name not in scored or list((cell / "eval").glob("*.json*")), cell  # scored


@pytest.mark.parametrize("grid", [g for g in GRIDS if (g / "report.json").exists()],
                         ids=lambda p: p.name)
def test_main_writes_the_committed_report_byte_for_byte(grid, tmp_path):
  """docs/results.md quotes these reports: a change to the metrics, statistics or report code
  that would move a published number fails here (regenerate the report on purpose and say
  so in docs/results.md)."""
  out = tmp_path / grid.name
  shutil.copytree(grid, out, ignore=shutil.ignore_patterns("figures"))
  plans = list(json.loads((grid / "report.json").read_text()))
  build.write_report(out, plans)
  for name in ("report.md", "report.json"):
    assert (out / name).read_bytes() == (grid / name).read_bytes(), (grid.name, name)


def test_the_committed_grids_fit_in_a_clone():
  """The committed records stay small enough for every clone to carry (issue 60: <= 20 MB);
  the per-scene evaluation reports and the training logs are kept compressed."""
  tree = ROOT / "docs" / "results"
  size = sum(p.stat().st_size for p in tree.rglob("*") if p.is_file())
  assert size <= 20e6, f"docs/results holds {size / 1e6:.1f} MB"
  plain = [p for g in GRIDS for p in g.glob("cells/*/eval/*.json") if p.name != "windows.json"]
  assert not plain, f"uncompressed evaluation reports: {plain[:3]}"


@pytest.mark.parametrize("grid", [g for g in GRIDS if (g / "report.json").exists()][:1],
                         ids=lambda p: p.name)
def test_an_uncompressed_folder_gives_the_same_report(grid, tmp_path):
  """Folders written before the records were compressed (SET.json, epochs.jsonl) still read:
  the grid decompressed in place reports byte for byte as committed."""
  out = tmp_path / grid.name
  shutil.copytree(grid, out, ignore=shutil.ignore_patterns("figures"))
  for xz in out.glob("cells/**/*.xz"):
    xz.with_name(xz.name[:-len(".xz")]).write_bytes(lzma.decompress(xz.read_bytes()))
    xz.unlink()
  plans = list(json.loads((grid / "report.json").read_text()))
  build.write_report(out, plans)
  for name in ("report.md", "report.json"):
    assert (out / name).read_bytes() == (grid / name).read_bytes(), (grid.name, name)


@pytest.mark.parametrize("grid", [g for g in GRIDS if (g / "regime.json").exists()],
                         ids=lambda p: p.name)
def test_main_writes_the_committed_regime_byte_for_byte(grid, tmp_path):
  """The pilots' regime reports (docs/plan-v3.md, plan-v4.md) rebuild from the committed,
  compressed training logs as committed."""
  out = tmp_path / grid.name
  shutil.copytree(grid, out, ignore=shutil.ignore_patterns("figures"))
  regime.write(out, "cpu", 2)
  for name in ("regime.md", "regime.json"):
    assert (out / name).read_bytes() == (grid / name).read_bytes(), (grid.name, name)
