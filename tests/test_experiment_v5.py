"""Calibration as cells of a grid (issue 63, item 1) and plan v5 (docs/plan-v5.md): a plan whose
budgets are not committed runs its calibration cells in its own OUT, the plateau rule writes
calibration-PLAN.json when the last is done, and the plan's cells follow with the budgets
recorded in plan.json; v5's cells, rule and power calculation as pre-registered."""

import json
from pathlib import Path

import pytest

from sljax import cli
from sljax.errors import SljaxError
from sljax.experiment import records
from sljax.experiment.budget import calibrate as cal
from sljax.experiment.design import cells, plans
from sljax.experiment.report import paper_claims, stats
from sljax.experiment.report.build import curve_metrics

import toys

COMMITTED = Path(__file__).resolve().parents[1] / "docs" / "results"


def test_which_plans_calibrate_in_their_own_out():
  assert plans.needs_calibration("v5", "smoke") and plans.needs_calibration("v5", "paper")
  assert plans.needs_calibration("table2-v2", "paper")
  assert not plans.needs_calibration("table2-v2", "cpu")      # committed budgets win
  assert not plans.needs_calibration("table1-v2", "cpu128")
  assert not plans.needs_calibration("fig7", "paper")         # v1: the schedule's epochs
  with pytest.raises(SljaxError, match="no calibrated budget for stl .objects. yet: `sljax "
                                       "experiment run v5 OUT --scale smoke` runs the "
                                       "calibration cells first"):
    plans.build_plan("v5", "smoke", 1)


def test_what_a_cell_waits_for_and_the_provisional_price():
  calib = plans.calibration_plan("v5", "paper")
  assert [c.name for c in calib.cells] == [f"calib-v5-psmnet-{a}-objects"
                                           for a in ("stl", "unc", "cg_a", "cg_b", "epr")]
  assert all(c.config.epochs == 120 and c.seed == 0 and not c.evals for c in calib.cells)
  plan = plans.provisional_plan("v5", "paper", 6)
  names = tuple(c.name for c in calib.cells)
  assert len(plan.cells) == 60 and plan.seeds == tuple(range(500, 506))
  for cell in plan.cells:
    assert cell.waits == names
    assert cells.waits_for(cell) == ((cell.init_cell,) if cell.init_cell else ()) + names
    assert "waits" not in cell.spec()  # scheduling, not the run's identity
  pre, ft = plan.cells[:2]
  assert pre.config.epochs == 120 and pre.config.lr == 1e-4 and pre.config.lr_drop_epoch is None
  assert (ft.config.domain, ft.config.fraction, ft.config.steps, ft.config.val_every_steps,
          ft.config.lr, ft.config.max_val) == ("tissue", "1/16", 4000, 50, 1e-4, None)
  assert [e.name for e in ft.evals] == ["test-tissue", "test-tissue-best"]
  # v2's calibration is unchanged: every phase of the plan, seed 0, no learning-rate drop.
  t1 = plans.calibration_plan("table1-v2", "cpu128")
  assert [c.name for c in t1.cells] == ["calib-unet-sl-objects", "calib-unet-sl-tissue-ft",
                                        "calib-unet-disp-objects", "calib-unet-disp-tissue-ft"]
  assert [c.config.epochs for c in t1.cells] == [60, 120, 60, 120]


def test_v5_seeds_are_pre_registered_and_committed_budgets_win(monkeypatch):
  with pytest.raises(SljaxError, match="plan v5 pre-registered 6 seeds at scale paper"):
    plans.build_plan("v5", "paper", 7, budgets=(), )
  with pytest.raises(SljaxError, match="plan v5 runs at smoke or paper"):
    plans.build_plan("v5", "cpu", 1)
  found = ((("stl", "objects"), 2), (("unc", "objects"), 3))
  plan = plans.build_plan("v5", "smoke", 1, budgets=found)
  assert [c.config.epochs for c in plan.cells if c.init_cell is None] == [2, 3]
  assert plan.budgets == found
  v5 = plans.SCALES["smoke"].v5
  monkeypatch.setitem(plans.SCALES, "smoke", plans.dataclasses.replace(
      plans.SCALES["smoke"], v5=plans.dataclasses.replace(v5, budgets=((("*", "objects"), 5),))))
  assert not plans.needs_calibration("v5", "smoke")
  assert [c.config.epochs for c in plans.build_plan("v5", "smoke", 1, budgets=found).cells
          if c.init_cell is None] == [5, 5]


def test_a_recorded_budget_never_changes(tmp_path):
  out = tmp_path / "out"
  a = plans.build_plan("v5", "smoke", 1, budgets=((("stl", "objects"), 2),
                                                   (("unc", "objects"), 3)))
  records.register(out, a)
  assert records.read_record(out)["plans"]["v5"]["budgets"] == [["stl", "objects", 2],
                                                                ["unc", "objects", 3]]
  assert [p.budgets for p in records.registered_plans(out)] == [a.budgets]
  b = plans.build_plan("v5", "smoke", 1, budgets=((("stl", "objects"), 3),
                                                   (("unc", "objects"), 3)))
  with pytest.raises(SljaxError, match="budgets never change after results"):
    records.register(out, b)


def test_a_damaged_calibration_record_is_one_line_naming_it(tmp_path):
  path = cal.calibration_file(tmp_path, "v5")
  path.write_text(json.dumps({"a": 1}))
  with pytest.raises(SljaxError, match=r"calibration-v5.json: not a calibration record"):
    cal.settled(tmp_path, "v5", "smoke")


def test_a_plan_waits_for_its_calibration(tmp_path):
  out = tmp_path / "out"
  first, then = cal.worker_plan("v5", "smoke", 1, None, (), out)
  assert first.name == "calibrate-v5" and then is not None
  with pytest.raises(SljaxError, match="the calibration of v5 is not finished"):
    then()
  assert not cal.calibration_file(out, "v5").exists()


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
  """v5 at the smoke scale, one seed, through two submitit local workers: the calibration
  cells, then the plan, in one OUT."""
  toys.need_submitit()
  out = tmp_path_factory.mktemp("v5") / "out"
  assert cli.main(["experiment", "submit", "v5", str(out), "--scale", "smoke", "--seeds", "1",
                   "--workers", "2", "--local", "--wait", "--lease", "5"]) == 0
  return out


def test_calibration_then_the_plan_then_the_report_through_two_workers(grid, capsys):
  calib = plans.calibration_plan("v5", "smoke")
  result = json.loads(cal.calibration_file(grid, "v5").read_text())
  assert result["missing"] == [] and set(result["cells"]) == {c.name for c in calib.cells}
  budgets = sorted([a, p, e] for a, p, e in result["budgets"])
  record = records.read_record(grid)
  assert record["plans"]["v5"]["budgets"] == budgets
  assert "budgets" not in record["plans"]["calibrate-v5"]
  found = records.budget_pairs(budgets)
  plan = plans.build_plan("v5", "smoke", 1, budgets=found)
  for cell in calib.cells + plan.cells:
    assert (records.cell_dir(grid, cell.name) / records.DONE_FILE).exists(), cell.name
    assert record["cells"][cell.name] == cell.spec()
  for cell in plan.cells:  # every cell of the plan started after the last calibration cell
    if cell.init_cell is None:
      assert cell.config.epochs == dict(found)[(cell.arm, "objects")]
  # Each cell trained once, whichever worker: the workers' logs say so.
  logs = list((grid / "submitit").rglob("*_log.out"))
  trained = sum(int(l.split("trained ")[1].split(" ")[0]) for log in logs
                for l in log.read_text().splitlines() if l.startswith("v5: trained"))
  assert len(logs) == 2 and trained == len(calib.cells) + len(plan.cells)
  capsys.readouterr()
  assert cli.main(["experiment", "status", str(grid)]) == 0
  status = capsys.readouterr().out
  assert "calibrate-v5 (scale smoke, seed 0): 2 finished of 2 cells" in status
  assert "v5 (scale smoke, seed 500): 4 finished of 4 cells" in status
  assert cli.main(["experiment", "report", str(grid)]) == 0
  md = (grid / "report.md").read_text()
  assert "Budgets set by the plateau rule on this folder's calibration cells" in md
  assert "### The pre-registered outcome (docs/plan-v5.md)" in md
  # A second worker trains nothing; the calibration file is not written again.
  stamp = cal.calibration_file(grid, "v5").stat().st_mtime_ns
  assert cli.main(["experiment", "run", "v5", str(grid), "--scale", "smoke", "--seeds", "1",
                   "--no-progress"]) == 0
  assert "v5: trained 0 cell(s), scored 0 set(s)" in capsys.readouterr().out
  assert cal.calibration_file(grid, "v5").stat().st_mtime_ns == stamp


def test_budgets_other_than_the_recorded_ones_are_refused(grid, tmp_path, capsys):
  out = tmp_path / "out"
  (out / "cells").mkdir(parents=True)
  for name in ("plan.json", "calibration-v5.json"):
    (out / name).write_bytes((grid / name).read_bytes())
  path = cal.calibration_file(out, "v5")
  result = json.loads(path.read_text())
  result["budgets"] = [[a, p, e + 1] for a, p, e in result["budgets"]]
  path.write_text(json.dumps(result))
  capsys.readouterr()
  assert cli.main(["experiment", "run", "v5", str(out), "--scale", "smoke", "--seeds", "1",
                   "--no-progress"]) == 2
  err = capsys.readouterr().err
  assert "budgets never change after results" in err and len(err.strip().splitlines()) == 1


def test_the_outcome_rule_by_hand():
  def curve(values):
    return [{"mean": v, "step": 100 * (i + 1)} for i, v in enumerate(values)]
  flat, rising = curve([1.0, 0.8, 0.7, 0.7, 0.7, 0.7]), curve([1.0, 0.6, 0.6, 0.7, 0.8, 0.9])
  assert paper_claims.curve_rise(flat) == pytest.approx(0.0)
  # Trailing means of 3: ..., 0.7, 0.8 at the end; the lowest 0.6333: a rise of 26%.
  assert paper_claims.curve_rise(rising) == pytest.approx(0.8 / (1.9 / 3) - 1)
  plan = plans.provisional_plan("v5", "smoke", 2)

  def agg(stl, unc, d):
    paired = {"unc": {"rise_rel": {"mean": d, "lo": d - 0.01, "hi": d + 0.01, "sd": 0.01,
                                   "n": 2, "p": 0.001, "t": -9.0, "wins": 2, "losses": 0}}}
    return {"groups": [{"factors": {"setting": "finetune", "data": "1/4"},
                        "curves": {"stl": stl, "unc": unc},
                        "sets": {paper_claims.CURVE_SET: {"paired": paired, "arms": {}}}}]}
  assert "**The mechanism acts**" in paper_claims.mechanism(plan, agg(rising, flat, -0.26))
  assert "**stl did not overfit**" in paper_claims.mechanism(plan, agg(flat, flat, 0.0))
  assert "not shown to prevent it" in paper_claims.mechanism(plan, agg(rising, rising, -0.26))
  assert paper_claims.mechanism(plans.build_plan("table2", "smoke", 1), {"groups": []}) is None


def test_the_power_calculation_of_plan_v5():
  """docs/plan-v5.md, "Power": the paired SDs of the smoothed relative rise in fig7-v2's
  committed fine-tuning cells (5 seeds), and the power at the seeds chosen."""
  out = COMMITTED / "v2-cpu"
  rise = {(arm, s): curve_metrics(out, f"psmnet-{arm}-tissue-ft-s{s}")["rise_rel"]
          for arm in ("stl", "unc", "cg_a", "cg_b", "epr") for s in range(5)}
  sds = {arm: stats.mean_ci([rise[arm, s] - rise["stl", s] for s in range(5)])["sd"]
         for arm in ("unc", "cg_a", "cg_b", "epr")}
  assert {a: round(v, 3) for a, v in sds.items()} == {"unc": 0.030, "cg_a": 0.065,
                                                      "cg_b": 0.054, "epr": 0.058}
  n = plans.SCALES["paper"].v5.seeds
  assert n == 6
  assert round(stats.paired_power(0.24, 0.10, n, 0.025), 2) == 0.98
  assert round(stats.paired_power(0.12, 0.10, n, 0.025), 2) == 0.49
  assert round(stats.detectable_difference(0.10, n, 0.8, 0.025), 3) == 0.171
  assert round(stats.paired_power(0.29, 0.105, n, 0.025), 3) == 0.995
