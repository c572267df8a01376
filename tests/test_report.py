"""The experiment report over fake per-cell evaluation files: means, intervals, paired tests,
Holm, the three verdicts, Δm, pattern accuracy and the pairing by seed, against hand
computations (no training)."""

import dataclasses
import json
import math

import pytest

from sljax import cli
from sljax.experiment import records
from sljax.experiment.design import plans
from sljax.experiment.report import build, stats

T975_DF2 = 4.302653  # Student t, 0.975 quantile, 2 degrees of freedom
STL = [1.0, 2.0, 3.0]  # stl's test MAE for seeds 0, 1, 2
# Arm - stl per seed: cg_a and unc better in every seed with a small spread (hold), cg_b worse
# the same way (the opposite is shown), epr mixed (not shown).
OFFSETS = {"stl": [0.0, 0.0, 0.0], "cg_a": [-0.30, -0.32, -0.34], "cg_b": [0.30, 0.32, 0.34],
           "epr": [-0.10, 0.10, 0.05], "unc": [-0.20, -0.21, -0.19]}
PATTERN_ACC = {"cg_a": 90.0, "cg_b": 80.0, "epr": 85.0, "unc": 70.0}


def _write_eval(out, cell, set_name, mae, pattern_acc=None):
  pooled = {"full": {"mae": mae, "bad_2": 100.0 * mae, "iqr": mae / 2, "depth_mae_mm": 10 * mae,
                     "depth_iqr_mm": 5 * mae, "depth_capped": 0.5},
            "seg": {"mae": 2 * mae}}
  if pattern_acc is not None:
    pooled["patterns_left"] = {"pattern_acc": pattern_acc, "pattern_n_pixels": 100}
  path = records.cell_dir(out, cell.name) / records.EVAL_DIR / f"{set_name}.json"
  path.parent.mkdir(parents=True, exist_ok=True)
  path.write_text(json.dumps({"pooled": pooled}))
  (records.cell_dir(out, cell.name) / records.DONE_FILE).write_text(json.dumps({"step": 1}))


@pytest.fixture()
def fake(tmp_path):
  """table2-v2 at the smoke scale, 3 seeds, every cell 'scored' with the values above."""
  plan = plans.build_plan("table2-v2", "smoke", 3)
  out = tmp_path / "out"
  records.register(out, plan)
  for cell in plan.cells:
    mae = STL[cell.seed] + OFFSETS[cell.arm][cell.seed]
    _write_eval(out, cell, "test-objects", mae, PATTERN_ACC.get(cell.arm))
  return out, plan


def _p_df2(diffs):
  """Two-sided paired t p-value for 3 pairs by the closed form of the t(2) CDF."""
  mean = sum(diffs) / 3
  sd = math.sqrt(sum((d - mean) ** 2 for d in diffs) / 2)
  t = mean / (sd / math.sqrt(3))
  return mean, sd, 1.0 - abs(t) / math.sqrt(2.0 + t * t)


def test_means_intervals_and_paired_tests_by_hand(fake):
  out, plan = fake
  agg = build.aggregate(out, plan)
  (group,) = agg["groups"]
  res = group["sets"]["test-objects"]
  stl = res["arms"]["stl"]["mae"]
  # 1, 2, 3: mean 2, SD 1, half width t(0.975, 2) / sqrt(3).
  assert stl["mean"] == pytest.approx(2.0) and stl["sd"] == pytest.approx(1.0)
  assert (stl["lo"], stl["hi"]) == (pytest.approx(2 - T975_DF2 / math.sqrt(3), abs=1e-5),
                                    pytest.approx(2 + T975_DF2 / math.sqrt(3), abs=1e-5))
  cg_a = res["paired"]["cg_a"]["mae"]
  mean, sd, p = _p_df2(OFFSETS["cg_a"])
  assert cg_a["mean"] == pytest.approx(-0.32) and mean == pytest.approx(-0.32)
  assert cg_a["sd"] == pytest.approx(0.02) and sd == pytest.approx(0.02)
  assert cg_a["p"] == pytest.approx(p, rel=1e-8)
  half = T975_DF2 * 0.02 / math.sqrt(3)
  assert (cg_a["lo"], cg_a["hi"]) == (pytest.approx(-0.32 - half, abs=1e-6),
                                      pytest.approx(-0.32 + half, abs=1e-6))
  assert (cg_a["wins"], cg_a["losses"]) == (3, 0)
  # Pattern accuracy is aggregated for the twins (stl has no SL output).
  assert res["arms"]["cg_a"]["pattern_acc"]["mean"] == pytest.approx(90.0)
  assert "pattern_acc" not in res["arms"]["stl"]
  assert res["arms"]["stl"]["depth_capped"]["mean"] == pytest.approx(0.5)


def test_delta_m_is_the_relative_mae_change_by_hand(fake):
  """stl has no SL output, so Δm is over disparity MAE alone (bad-2, which moves 100x more,
  is not in it): seed by seed -(arm - stl) / stl * 100, then the mean over seeds."""
  out, plan = fake
  dm = build.aggregate(out, plan)["groups"][0]["sets"]["test-objects"]["paired"]["cg_a"][
      "delta_m"]
  per_seed = [30.0, 16.0, 34.0 / 3.0]  # 0.30 / 1, 0.32 / 2, 0.34 / 3, in %
  assert dm["mean"] == pytest.approx(sum(per_seed) / 3)
  assert dm["n"] == 3
  # Two SL outputs: pattern accuracy (higher is better) joins disparity MAE.
  assert build.delta_m({"mae": 1.5, "pattern_acc": 90.0, "bad_2": 1.0},
                        {"mae": 2.0, "pattern_acc": 80.0, "bad_2": 50.0}) == pytest.approx(18.75)


def test_holm_and_the_three_verdicts(fake):
  out, plan = fake
  cl = build.claims(plan, build.aggregate(out, plan))
  assert len(cl) == 8  # 4 arms x Full / Seg at 1/16: one family
  by = {(c["arm"], c["metric"]): c for c in cl}
  # Seg MAE is 2 x Full MAE in the fake data: the same t and p for both metrics of an arm.
  raw = {arm: _p_df2(OFFSETS[arm])[2] for arm in ("cg_a", "cg_b", "epr", "unc")}
  ps = [raw[c["arm"]] for c in cl]
  # Holm by hand: the 8 p-values sorted ascending, the i-th (from 0) times 8 - i, running max.
  order = sorted(range(8), key=lambda i: ps[i])
  expected, running = [0.0] * 8, 0.0
  for rank, i in enumerate(order):
    running = max(running, min(1.0, (8 - rank) * ps[i]))
    expected[i] = running
  for c, e in zip(cl, expected):
    assert c["difference"]["p"] == pytest.approx(raw[c["arm"]], rel=1e-8)
    assert c["p_holm"] == pytest.approx(e, rel=1e-8)
  assert by["cg_a", "mae"]["verdict"] == "holds"
  assert by["unc", "mae"]["verdict"] == "holds"
  assert by["cg_b", "mae"]["verdict"] == "does not hold (the opposite is shown)"
  assert by["epr", "mae"]["verdict"].startswith("not shown")
  # Where the paper itself found no gain (cg_b's Seg MAE at 1/16: 0.808 vs stl 0.790).
  assert by["cg_b", "seg_mae"]["paper"] == "no gain" and by["cg_a", "mae"]["paper"] == "gain"
  # The detectable difference comes from the observed SD of the paired differences.
  assert by["cg_a", "mae"]["detectable"] == pytest.approx(
      stats.detectable_difference(0.02, 3), rel=1e-9)
  md = build.write_report(out).read_text()
  assert "Holm p" in md and "detectable (80%)" in md and "pattern acc % (left)" in md
  assert "(the paper found no gain here)" in md
  assert "fixed test set test-objects (20 objects scenes rendered from dataset seed" in md


def test_a_claim_that_holds_unadjusted_can_fail_after_holm():
  """Differences -1, -0.65, -1.35 (p = 0.0385 alone: 'holds' at 0.05 without correction) in a
  family of 3 whose other two claims are null: Holm multiplies the smallest p by 3."""
  gain = stats.paired_test([1.0, 1.35, 0.65], [2.0, 2.0, 2.0])
  mean, sd, p = _p_df2([-1.0, -0.65, -1.35])
  assert gain["p"] == pytest.approx(p, rel=1e-8) and 0.03 < p < 0.05
  null = stats.paired_test([1.0, 2.0, 3.0], [1.1, 1.9, 3.05])
  agg = {"groups": [{"factors": {"data": "objects"}, "sets": {"heldout": {"paired": {
      "unet-sl": {"mae": null, "seg_mae": null}}}}},
                    {"factors": {"data": "tissue"}, "sets": {"heldout": {"paired": {
                        "unet-sl": {"mae": gain}}}}}]}
  cl = build.claims(plans.build_plan("table1", "smoke", 1), agg)
  assert len(cl) == 3
  tissue = cl[-1]
  assert tissue["p_holm"] == pytest.approx(3 * p, rel=1e-8)
  assert tissue["verdict"] == "not shown (Holm-adjusted p >= 0.05)"


def test_a_partial_table_says_its_holm_family_is_interim(tmp_path):
  """Holm leaves claims without results out of m, so a report on part of a table must say its
  adjusted p are interim; the complete table names its whole family."""
  plan = plans.build_plan("table2-v2", "smoke", 3)
  out = tmp_path / "out"
  records.register(out, plan)
  for cell in plan.cells:
    if cell.arm in ("stl", "cg_a"):  # 2 of the family's 8 claims can be tested
      _write_eval(out, cell, "test-objects", STL[cell.seed] + OFFSETS[cell.arm][cell.seed])
  md = build.write_report(out).read_text()
  assert "Holm-adjusted p over its 2 claims with results (the family has 8: until all" in md
  for cell in plan.cells:
    _write_eval(out, cell, "test-objects", STL[cell.seed] + OFFSETS[cell.arm][cell.seed])
  md = build.write_report(out).read_text()
  assert "Holm-adjusted p over its 8 claims; verdicts" in md and "interim" not in md


def test_pairing_is_by_seed_not_by_position(fake):
  """Pairing arm seed 0 with baseline seed 1 would change the spread of the differences: the
  aggregate must give the hand-computed by-seed SD, whatever the order of the plan's cells."""
  out, plan = fake
  shuffled = dataclasses.replace(plan, cells=tuple(reversed(plan.cells)))
  for p in (plan, shuffled):
    cg_a = build.aggregate(out, p)["groups"][0]["sets"]["test-objects"]["paired"]["cg_a"]["mae"]
    assert cg_a["sd"] == pytest.approx(0.02)
  # The same numbers paired one seed apart (arm seed s with baseline seed s + 1) give another
  # SD, so the assertion above discriminates the pairing.
  arm = [STL[s] + OFFSETS["cg_a"][s] for s in range(3)]
  shifted = stats.paired_test(arm, STL[1:] + STL[:1])
  assert shifted["sd"] > 1.0


def test_a_misfiled_seed_is_caught(fake):
  """If cg_a's seed-0 and seed-1 results were swapped (the bug a pairing test must catch), the
  paired SD departs from the by-seed value."""
  out, plan = fake
  by = {(c.arm, c.seed): c for c in plan.cells}
  _write_eval(out, by["cg_a", 0], "test-objects", STL[1] + OFFSETS["cg_a"][1], 90.0)
  _write_eval(out, by["cg_a", 1], "test-objects", STL[0] + OFFSETS["cg_a"][0], 90.0)
  cg_a = build.aggregate(out, plan)["groups"][0]["sets"]["test-objects"]["paired"]["cg_a"]["mae"]
  assert cg_a["sd"] != pytest.approx(0.02)


def test_table3_claims_only_on_other_domains(tmp_path):
  plan = plans.build_plan("table3-v2", "smoke", 2)
  out = tmp_path / "out"
  records.register(out, plan)
  for cell in plan.cells:
    for e in cell.evals:
      _write_eval(out, cell, e.name, 1.0 + 0.1 * cell.seed + (0.05 if cell.arm == "stl" else 0))
  cl = build.claims(plan, build.aggregate(out, plan))
  assert {c["set"] for c in cl} == {"test-tissue"} and len(cl) == 4
  v1 = plans.build_plan("table3", "smoke", 2)
  agg = {"groups": [{"factors": {"data": "all"}, "sets": {
      "heldout": {"paired": {}}, "tissue": {"paired": {}}}}]}
  assert {c["set"] for c in build.claims(v1, agg)} == {"tissue"}


def test_fig7_says_where_the_paper_predicts_no_gain():
  plan = plans.build_plan("fig7-v2", "smoke", 1)
  agg = {"groups": [{"factors": {"data": "tissue"}, "sets": {"test-tissue": {"paired": {}}}}]}
  cl = build.claims(plan, agg)
  assert {c["arm"]: c["paper"] for c in cl} == {"cg_a": "no gain", "cg_b": "no gain",
                                                "epr": "no gain", "unc": "gain"}
  assert all(c["verdict"] == "no results yet" for c in cl)


def test_paper_sized_gain_is_exploratory_and_computed_by_hand(fake):
  """table2 at 1/16: the paper's cg_a gain is (0.496 - 0.549) / 0.549 of stl's MAE; here stl's
  mean is 2.0 px, so a paper-sized difference is -0.193 px; cg_a's interval [-0.37, -0.27]
  does not exclude it, cg_b's (above 0) does."""
  out, plan = fake
  by = {(c["arm"], c["metric"]): c for c in build.claims(plan, build.aggregate(out, plan))}
  assert by["cg_a", "mae"]["paper_sized"] == pytest.approx((0.496 - 0.549) / 0.549 * 2.0)
  assert not by["cg_a", "mae"]["paper_sized_excluded"]
  assert by["cg_b", "mae"]["paper_sized_excluded"]
  assert "paper_sized" not in by["cg_b", "seg_mae"]  # the paper found no gain there
  assert "Exploratory (not a pre-registered test)" in build.write_report(out).read_text()


def test_window_chosen_at_the_edge_is_noted(tmp_path):
  plan = plans.build_plan("table1-v2", "smoke", 1)
  out = tmp_path / "out"
  records.register(out, plan)
  sl = [c for c in plan.cells if c.windows]
  assert len(sl) == 2 and sl[0].windows == (3, 5)
  for cell, chosen in zip(sl, (5, 3)):  # the largest candidate once, the smallest once
    path = records.cell_dir(out, cell.name) / records.EVAL_DIR / records.WINDOWS_FILE
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({"candidates": [3, 5], "chosen": chosen}))
  assert build.window_edges(out, plan) == (1, 2)
  text = build.write_report(out).read_text()
  assert "the largest candidate in 1 of 2 cells" in text


def test_training_time_per_arm_and_cpu_by_hand(fake):
  out, plan = fake
  minutes = {0: 10.0, 1: 20.0, 2: 60.0}
  for cell in plan.cells:
    if cell.arm in ("stl", "unc"):
      done = {"step": 1, "train_seconds": 60 * minutes[cell.seed]}
      if cell.seed != 2:
        done["machine"] = "CPU A"
      (records.cell_dir(out, cell.name) / records.DONE_FILE).write_text(json.dumps(done))
      ynn = {0: "on", 1: "forward-off"}.get(cell.seed)
      if ynn:
        (records.cell_dir(out, cell.name) / "config.json").write_text(json.dumps({"ynn": ynn}))
  times = build.cell_times(out, plan)
  assert set(times) == {("stl", "1/16", "CPU A"), ("stl", "1/16", "not recorded"),
                        ("unc", "1/16", "CPU A"), ("unc", "1/16", "not recorded")}
  # Seeds 0 and 1 (10 and 20 min) on CPU A: mean 15; seed 2 (60 min) apart, not averaged in.
  assert times["stl", "1/16", "CPU A"] == {"n": 2, "mean": pytest.approx(15.0), "min": 10.0,
                                           "max": 20.0, "ynn": ["forward-off", "on"]}
  assert times["stl", "1/16", "not recorded"] == {"n": 1, "mean": pytest.approx(60.0),
                                                  "min": 60.0, "max": 60.0,
                                                  "ynn": ["not recorded"]}
  text = build.write_report(out).read_text()
  assert "| stl | 1/16 | 2 | 15.0 (10.0-20.0) | CPU A | forward-off, on |" in text
  assert "| stl | 1/16 | 1 | 60.0 (60.0-60.0) | not recorded | not recorded |" in text


def test_report_of_named_plans_only(fake, capsys):
  """`report --plans table2-v2` leaves out a plan that runs in the same folder (fig7-v2 here,
  registered, nothing finished); a plan not run there is refused, naming those that were."""
  out, _ = fake
  records.register(out, plans.build_plan("fig7-v2", "smoke", 1))
  assert cli.main(["experiment", "report", str(out)]) == 0
  both = (out / "report.md").read_text()
  assert build.TITLES["table2-v2"] in both and build.TITLES["fig7-v2"] in both
  assert cli.main(["experiment", "report", str(out), "--plans", "table2-v2"]) == 0
  one = (out / "report.md").read_text()
  assert build.TITLES["table2-v2"] in one and build.TITLES["fig7-v2"] not in one
  assert set(json.loads((out / "report.json").read_text())) == {"table2-v2"}
  capsys.readouterr()
  assert cli.main(["experiment", "report", str(out), "--plans", "table3-v2"]) == 2
  err = capsys.readouterr().err
  assert "no plan table3-v2 was run here (plans run: fig7-v2, table2-v2)" in err


def test_a_failed_report_leaves_out_as_it_was(fake, capsys):
  """A damaged score of a plan reported after another: no figures/ of the first plan left
  behind, and with an earlier report its files stay byte for byte."""
  import toys  # pylint: disable=import-outside-toplevel
  out, _ = fake
  fig7 = plans.build_plan("fig7-v2", "smoke", 1)
  records.register(out, fig7)
  cell = next(c for c in fig7.cells if c.evals)
  _write_eval(out, cell, cell.evals[0].name, 1.0)
  bad = records.cell_dir(out, cell.name) / records.EVAL_DIR / f"{cell.evals[0].name}.json"
  bad.write_text('{"pooled": {"full"')  # cut short
  before = toys.tree(out)
  assert cli.main(["experiment", "report", str(out)]) == 2
  assert bad.name in capsys.readouterr().err
  assert toys.tree(out) == before and not (out / "figures").exists()
  assert cli.main(["experiment", "report", str(out), "--plans", "table2-v2"]) == 0
  before = toys.tree(out)
  assert cli.main(["experiment", "report", str(out)]) == 2
  assert toys.tree(out) == before
