"""The v3 design (docs/plan-v3.md): the pilot's cells and the regime rule, checked by hand."""

import dataclasses
import json

import numpy as np
import pytest

from sljax.errors import SljaxError
from sljax.experiment import records
from sljax.experiment.budget import regime
from sljax.experiment.design import plans
from sljax.experiment.report import stats


def test_pilot_cells_at_the_cpu_scale():
  plan = plans.build_plan("v3-pilot", "cpu", 2)
  assert plan.seeds == (100, 101)
  assert len(plan.cells) == 6
  assert {c.factors for c in plan.cells} == {(("data", f),) for f in ("1/16", "1/32", "1/64")}
  for cell in plan.cells:
    c = cell.config
    assert (c.model, c.strategy, c.domain, c.size, c.synth_n) == ("psmnet", "stl", "objects",
                                                                   (64, 64), 400)
    assert c.epochs == 240 and c.val_every == 4 and c.max_val is None
    assert c.lr == 1e-3 and c.lr_drop_epoch is None  # constant learning rate
    assert cell.evals == () and cell.init_cell is None
    assert cell.name.startswith("pilot-psmnet-stl-objects-f1_")
  # No pilot seed is a test seed (v2 and v3 test cells use seeds 0..9).
  assert not set(plan.seeds) & set(range(10))
  # Every pilot cell differs only in the fraction and the seed from the v2 1/16 stl cell, apart
  # from the budget and the schedule.
  v2 = plans.build_plan("table2-v2", "cpu", 1).cells_of(data="1/16")[0]
  pilot = plans.build_plan("v3-pilot", "cpu", 1).cells[0]
  diff = {k for k, v in pilot.config.to_json().items() if v2.config.to_json()[k] != v}
  assert diff == {"seed", "epochs", "lr_drop_epoch", "val_every", "max_val"}


def test_pilot_is_refused_at_a_scale_without_a_v3_design():
  with pytest.raises(SljaxError, match="v3-pilot runs at"):
    plans.build_plan("v3-pilot", "cpu128", 2)


def test_mean_curve_keeps_the_common_epochs():
  a = [(4, 1.0), (8, 0.8), (12, 0.9)]
  b = [(4, 3.0), (8, 1.2)]
  assert regime.mean_curve([a, b]) == [(4, 2.0), (8, 1.0)]


def test_regime_rule_by_hand():
  # Smoothed (trailing mean of 3): 1.0, 0.9, 0.8, 0.7, 0.7, 0.8 -> minimum 0.7 first at epoch
  # 16, final 0.8: +14.3% >= 10%: overfits.
  curve = [(4, 1.0), (8, 0.8), (12, 0.6), (16, 0.7), (20, 0.8), (24, 0.9)]
  r = regime.fraction_rise(curve)
  assert r["min_epoch"] == 16 and r["overfits"]
  assert r["rise"] == pytest.approx(0.8 / 0.7 - 1)
  # A rise of 5% does not overfit.
  flat = [(4, 1.0), (8, 1.0), (12, 1.0), (16, 1.05), (20, 1.05), (24, 1.05)]
  assert not regime.fraction_rise(flat)["overfits"]
  rows = {"1/16": regime.fraction_rise(flat), "1/32": r, "1/64": r}
  # The largest overfitting fraction, budget 2 x 16 = 32 (already a multiple of 4); with a
  # cadence of 5, 32 rounds up to 35.
  assert regime.choose(rows, ("1/16", "1/32", "1/64"), 4) == {
      "fraction": "1/32", "budget": 32, "min_epoch": 16}
  assert regime.choose(rows, ("1/16", "1/32", "1/64"), 5)["budget"] == 35
  assert regime.choose({"1/16": rows["1/16"]}, ("1/16",), 4)["fraction"] is None


def _fake_cell(out, name, curve):
  wd = records.cell_dir(out, name)
  wd.mkdir(parents=True)
  (wd / "epochs.jsonl").write_text("".join(
      json.dumps({"epoch": e, "val_mae": v}) + "\n" for e, v in curve))
  (wd / records.DONE_FILE).write_text(json.dumps({"step": 1}))


def test_regime_reads_the_pilot_records_and_waits_for_every_cell(tmp_path):
  plan = plans.build_plan("v3-pilot", "smoke", 2)
  rising = [(2, 1.0), (4, 0.5), (6, 0.5), (8, 0.5), (10, 0.9), (12, 1.0)]
  flat = [(2, 1.0), (4, 0.9), (6, 0.9), (8, 0.9), (10, 0.9), (12, 0.9)]
  first, *rest = plan.cells
  for cell in rest:
    _fake_cell(tmp_path, cell.name, rising if cell.factors == (("data", "1/8"),) else flat)
  res = regime.regime(tmp_path, "smoke", 2)
  assert res["regime"] is None and res["missing"] == [first.name]
  _fake_cell(tmp_path, first.name, flat)
  res = regime.write(tmp_path, "smoke", 2)
  # 1/4 does not overfit (flat). 1/8, smoothed by hand: 1.0, 0.75, 2/3, 0.5, 1.9/3, 0.8: the
  # minimum 0.5 at epoch 8, final 0.8 (+60%): it overfits; budget 2 x 8 = 16 (cadence 2).
  smoothed = res["fractions"]["1/8"]["smoothed"]
  assert [e for e, _ in smoothed] == [2, 4, 6, 8, 10, 12]
  assert [v for _, v in smoothed] == pytest.approx([1.0, 0.75, 2 / 3, 0.5, 1.9 / 3, 0.8])
  assert not res["fractions"]["1/4"]["overfits"]
  assert res["regime"] == {"fraction": "1/8", "budget": 16, "min_epoch": 8}
  assert "Regime: fraction 1/8, budget 16 epochs" in (tmp_path / "regime.md").read_text()
  assert (tmp_path / "figures" / "v3-pilot_curves.png").stat().st_size > 0


# ---- the test grid ---------------------------------------------------------------------------


def test_v3_cells_train_in_the_regime_and_score_final_and_best():
  plan = plans.build_plan("v3", "smoke", 2)
  assert plan.seeds == (0, 1) and plan.baseline == "stl"
  assert [c.arm for c in plan.cells[:3]] == ["stl", "unc", "epr"]
  fraction, epochs = plans.SCALES["smoke"].v3.regime
  for cell in plan.cells:
    c = cell.config
    assert c.fraction == fraction and c.epochs == epochs and c.lr_drop_epoch is None
    assert c.val_every == plans.SCALES["smoke"].v3.val_every and c.max_val is None
    assert [(e.name, e.checkpoint) for e in cell.evals] == [
        ("test-objects", "final"), ("test-tissue", "final"), ("test-objects-best", "best")]
  # The objects test set is v2's: the same scenes (dataset seed, size, count).
  v2 = plans.build_plan("table2-v2", "smoke", 1).cells[0].evals[0]
  assert dataclasses.replace(plan.cells[0].evals[0], checkpoint="final") == v2


def test_v3_waits_for_the_regime_and_ends_without_one(monkeypatch):
  cpu = plans.SCALES["cpu"]
  # The committed outcome: the pilot found no fraction where stl overfits (docs/plan-v3.md).
  assert cpu.v3.regime == plans.NO_REGIME
  with pytest.raises(SljaxError, match="found no training fraction where stl overfits"):
    plans.build_plan("v3", "cpu", 10)
  waiting = dataclasses.replace(cpu, v3=dataclasses.replace(cpu.v3, regime=None))
  monkeypatch.setitem(plans.SCALES, "cpu", waiting)
  with pytest.raises(SljaxError, match="no regime yet"):
    plans.build_plan("v3", "cpu", 10)


def test_the_committed_pilot_gives_the_committed_outcome():
  """The rule applied by main's code to the committed pilot records: no regime, as committed."""
  from pathlib import Path
  records = Path(__file__).resolve().parents[1] / "docs" / "results" / "v3-pilot"
  res = regime.regime(records, "cpu", 2)
  assert not res["missing"] and res["regime"]["fraction"] is None
  committed = json.loads((records / "regime.json").read_text())
  assert {f: r["rise"] for f, r in res["fractions"].items()} == pytest.approx(
      {f: r["rise"] for f, r in committed["fractions"].items()})


def test_v3_claims_on_fake_records(tmp_path):
  """The family of two: (a) final test Full MAE, (b) the overfitting rise from each cell's own
  curve; hand-computed differences; epr is in the tables but not a claim."""
  from sljax.experiment.report import build, paper_claims
  plan = plans.build_plan("v3", "smoke", 3)
  records.register(tmp_path, plan)
  mae = {"stl": [1.0, 1.2, 1.1], "unc": [0.9, 1.0, 1.05], "epr": [1.0, 1.1, 1.2]}
  rise = {"stl": [0.3, 0.2, 0.4], "unc": [0.1, 0.1, 0.2], "epr": [0.3, 0.3, 0.3]}
  for cell in plan.cells:
    k = cell.seed
    _fake_cell(tmp_path, cell.name, [(2, 1.0), (4, 0.5), (6, 0.5 + rise[cell.arm][k])])
    for e in cell.evals:
      path = records.cell_dir(tmp_path, cell.name) / "eval" / f"{e.name}.json"
      path.parent.mkdir(exist_ok=True)
      path.write_text(json.dumps({"pooled": {"full": {"mae": mae[cell.arm][k]}}}))
  agg = build.aggregate(tmp_path, plan)
  cl = paper_claims.claims(plan, agg)
  assert [c["set"] for c in cl] == ["test-objects", "validation-curve"]
  assert cl[0]["difference"]["mean"] == pytest.approx(np.mean(np.subtract(mae["unc"], mae["stl"])))
  assert cl[1]["difference"]["mean"] == pytest.approx(np.mean(np.subtract(rise["unc"], rise["stl"])))
  assert cl[1]["difference"]["wins"] == 3
  ps = [c["difference"]["p"] for c in cl]
  assert [c["p_holm"] for c in cl] == pytest.approx(stats.holm(ps))
  curve_set = agg["groups"][0]["sets"]["validation-curve"]
  assert curve_set["arms"]["epr"]["rise"]["mean"] == pytest.approx(0.3)
  md = (build.write_report(tmp_path)).read_text()
  assert "overfitting rise" in md and "v3: stl, unc and epr" in md
