"""The v4 design (docs/plan-v4.md): the pilot's cells with budgets in steps (scene counts by
hand from the split), and v3's rule on steps with the memorisation measure, by hand."""

import dataclasses

import pytest

from sljax.data.dataset import split_indices, take_fraction
from sljax.errors import SljaxError
from sljax.experiment import records
from sljax.experiment.budget import regime
from sljax.experiment.design import cells, plans
from sljax.train.feed import open_source


def _scenes(config) -> int:
  """Training scenes of a config, counted from its split and fraction."""
  train_idx, _ = split_indices(open_source(config), config.test_fraction, seed=config.seed)
  return len(take_fraction(train_idx, config.fraction, seed=config.seed))


def test_pilot_cells_at_the_cpu_scale():
  """The plan's cells with the budgets docs/plan-v4.md's rule set after the timing run (6,000,
  2,400 and 4,000 steps times r = 0.441, rounded up to the validation cadences)."""
  plan = plans.build_plan("v4-pilot", "cpu", 2)
  plans.check_unique(plan)
  assert plan.seeds == (200, 201)  # new: neither v3's pilot (100, 101) nor a test seed
  by = {(dict(c.factors)["setting"], dict(c.factors)["data"], c.seed): c for c in plan.cells}
  assert len(by) == len(plan.cells) == 10
  for seed in plan.seeds:
    pre = by[("pretrain", "all", seed)]
    for (setting, fraction, s), cell in by.items():
      if s != seed:
        continue
      c = cell.config
      assert (c.model, c.strategy, c.size, c.maxdisp, c.batch_size) == ("psmnet", "stl",
                                                                         (64, 64), 16, 4)
      assert c.lr_drop_epoch is None and c.max_val is None and cell.evals == ()
      if setting == "scratch":
        assert (c.domain, c.lr, c.steps, c.val_every_steps) == ("objects", 1e-3, 2700, 100)
        assert cell.init_cell is None
      elif setting == "pretrain":
        assert (c.domain, c.fraction, c.lr, c.steps, c.val_every_steps) == (
            "objects", "1", 1e-3, 1200, 200)
      else:
        assert (c.domain, c.synth_n, c.lr, c.steps, c.val_every_steps) == (
            "tissue", 80, 1e-4, 1800, 100)
        assert cell.init_cell == pre.name
  # The scene counts the plan names: 10 and 5 objects scenes, 10 and 5 tissue scenes.
  counts = {k[:2]: _scenes(c.config) for k, c in by.items() if k[2] == 200}
  assert counts == {("scratch", "1/32"): 10, ("scratch", "1/64"): 5, ("pretrain", "all"): 320,
                    ("finetune", "1/6"): 10, ("finetune", "1/12"): 5}
  # Budgets in steps change the cell's identity; nothing else differs from v3's pilot cell.
  v3 = plans.build_plan("v3-pilot", "cpu", 1).cells_of(data="1/32")[0].config
  v4 = by[("scratch", "1/32", 200)].config
  diff = {k for k, v in v4.to_json().items() if v3.to_json()[k] != v}
  assert diff == {"seed", "epochs", "steps", "val_every", "val_every_steps"}


def test_pilot_is_refused_at_a_scale_without_a_v4_design():
  with pytest.raises(SljaxError, match="v4-pilot runs at"):
    plans.build_plan("v4-pilot", "cpu128", 2)


def _rows(points):
  """validation.jsonl rows from (step, val_mae, train_loss_disp)."""
  return [{"step": s, "val_mae": v, "train_loss_disp": t} for s, v, t in points]


def test_memorisation_by_hand():
  rows = _rows([(100, 2.0, 9.0), (200, 1.0, 4.0), (300, 1.0, 3.0), (400, 1.5, 1.0)])
  m = regime.memorisation(rows)
  # The minimum 1.0 first at step 200 (training loss 4.0); at the end 1.0: ratio 1/4.
  assert m == {"min_step": 200, "train_at_min": 4.0, "train_final": 1.0, "ratio": 0.25}
  assert regime.memorisation([])["ratio"] is None


def test_v3_rule_on_steps_by_hand():
  # Seeds' mean: 1.0, 0.8, 0.6, 0.7, 0.8, 0.9 at steps 100..600; smoothed 1.0, 0.9, 0.8, 0.7,
  # 0.7, 0.8: the minimum 0.7 first at step 400, final 0.8 (+14.3%): overfits; budget 800.
  a = _rows([(100, 1.2, 5), (200, 0.8, 4), (300, 0.5, 3), (400, 0.7, 2), (500, 0.9, 1),
             (600, 0.8, 1)])
  b = _rows([(100, 0.8, 5), (200, 0.8, 4), (300, 0.7, 3), (400, 0.7, 2), (500, 0.7, 1),
             (600, 1.0, 0.5)])
  flat = _rows([(100, 1.0, 5), (200, 1.0, 4), (300, 1.0, 3), (400, 1.0, 3)])
  out = regime.v4_setting({"1/32": {"s200": flat, "s201": flat}, "1/64": {"s200": a, "s201": b}},
                          ("1/32", "1/64"), 100)
  assert not out["fractions"]["1/32"]["overfits"]
  r = out["fractions"]["1/64"]
  assert r["overfits"] and r["min_step"] == 400
  assert r["rise"] == pytest.approx(0.8 / 0.7 - 1)
  assert out["regime"] == {"fraction": "1/64", "budget_steps": 800, "min_step": 400}
  assert r["memorisation"]["s200"]["ratio"] == pytest.approx(1 / 3)  # min at 300 (0.5)
  # s201's minimum 0.7 first at 300 (training loss 3), 0.5 at the end: 1/6; the mean 1/4.
  assert r["memorisation_mean"] == pytest.approx((1 / 3 + 1 / 6) / 2)
  none = regime.v4_setting({"1/32": {"s200": flat}}, ("1/32", "1/64"), 100)
  assert none["regime"]["fraction"] is None


def _fake(out, name, points):
  import json  # pylint: disable=import-outside-toplevel
  from sljax.experiment import records
  wd = records.cell_dir(out, name)
  wd.mkdir(parents=True)
  (wd / "validation.jsonl").write_text("".join(json.dumps(r) + "\n" for r in _rows(points)))
  (wd / records.DONE_FILE).write_text(json.dumps({"step": points[-1][0]}))


RISING = [(2, 1.0, 5), (4, 0.6, 3), (6, 0.6, 2), (8, 0.9, 1), (10, 1.0, 0.5), (12, 1.1, 0.2)]
FLAT = [(2, 1.0, 5), (4, 0.9, 3), (6, 0.9, 2), (8, 0.9, 2)]


@pytest.mark.parametrize("scratch, finetune, grid", [
    (RISING, RISING, "finetune"), (RISING, FLAT, "scratch"), (FLAT, RISING, "finetune"),
    (FLAT, FLAT, None)])
def test_the_grid_setting_by_the_rule(tmp_path, scratch, finetune, grid):
  """Both settings overfit: fine-tuning; one: that one; none: no grid. Waits for every cell."""
  plan = plans.build_plan("v4-pilot", "smoke", 1)
  records.register(tmp_path, plan)
  for cell in plan.cells:
    setting = dict(cell.factors)["setting"]
    _fake(tmp_path, cell.name, {"scratch": scratch, "finetune": finetune}.get(setting, FLAT))
  result = regime.write(tmp_path, "smoke", 1)
  assert result["grid_setting"] == grid and not result["missing"]
  if grid is not None:  # smoothed 1.0, 0.8, 0.733, 0.7, 0.833, 1.0: minimum at step 8 (+43%)
    fractions = getattr(plans.SCALES["smoke"].v4, f"{grid}_fractions")
    assert result["settings"][grid]["regime"] == {"fraction": fractions[0], "budget_steps": 16,
                                                  "min_step": 8}
  assert (tmp_path / "regime.md").exists() and (tmp_path / "figures" / "v4-pilot_curves.png")
  # One cell missing: no decision yet.
  (records.cell_dir(tmp_path, plan.cells[0].name) / records.DONE_FILE).unlink()
  assert regime.v4(tmp_path, "smoke", 1)["grid_setting"] is None
  assert regime.v4(tmp_path, "smoke", 1)["missing"] == [plan.cells[0].name]
  md = regime.markdown_v4(regime.v4(tmp_path, "smoke", 1))
  assert "Regime: fraction" not in "\n".join(md)
  assert md.count("Regime: decided once every cell has finished.") == 2


def test_status_reads_a_step_budget_by_steps():
  from sljax.experiment.running.status import TRAINING, CellState  # pylint: disable=import-outside-toplevel
  cell = plans.build_plan("v4-pilot", "cpu", 1).cells[0]
  s = CellState(cell, TRAINING, epoch=300, step=675)
  assert s.share == pytest.approx(675 / 2700) and s.where == "step 675 of 2700"
  v3 = plans.build_plan("v3-pilot", "cpu", 1).cells[0]
  e = CellState(v3, TRAINING, epoch=60, step=60)
  assert e.share == pytest.approx(60 / 240) and e.where == "epoch 60 of 240"


# ---- the test grid ---------------------------------------------------------------------------


def _by(plan):
  return {(c.arm, dict(c.factors)["setting"], c.seed): c for c in plan.cells}


def test_grid_cells_in_the_finetune_regime():
  """Each arm fine-tunes its own objects model (the twin for unc and epr) trained as the
  pilot's pretraining; the regime's fraction and steps; final and best on the tissue test set."""
  plan = plans.build_plan("v4", "smoke", 3)
  plans.check_unique(plan)
  design = plans.SCALES["smoke"].v4
  setting, fraction, steps = design.regime
  assert setting == "finetune" and plan.seeds == (300, 301, 302) and plan.baseline == "stl"
  by = _by(plan)
  assert len(by) == len(plan.cells) == 3 * 3 * 2
  pilot_pre = plans.build_plan("v4-pilot", "smoke", 1).cells_of(setting="pretrain")[0]
  for (arm, where, seed), cell in by.items():
    c = cell.config
    assert (c.model, c.strategy, c.seed, c.lr_drop_epoch, c.max_val) == (
        "psmnet", arm, seed, None, None)
    if where == "pretrain":
      assert cell.evals == () and cell.init_cell is None
      # The pilot's pretraining with the arm's strategy and the grid's seed, nothing else.
      mine = cell.spec()["config"]
      pilot = dataclasses.replace(pilot_pre.config, strategy=arm, seed=seed)
      assert mine == cells.Cell("x", arm, (), seed, pilot).spec()["config"]
      continue
    assert cell.init_cell == by[(arm, "pretrain", seed)].name
    assert (c.domain, c.fraction, c.lr, c.steps, c.val_every_steps) == (
        "tissue", fraction, design.finetune_lr, steps, design.val_every)
    assert [(e.name, e.kind, e.domain, e.checkpoint) for e in cell.evals] == [
        ("test-tissue", "fixed", "tissue", "final"),
        ("test-tissue-best", "fixed", "tissue", "best")]
    assert dict(cell.factors) == {"setting": "finetune", "data": fraction}
  # Seeds pair the arms: the same seed's cells differ only in the strategy.
  stl, unc = by[("stl", "finetune", 300)].config, by[("unc", "finetune", 300)].config
  assert dataclasses.replace(stl, strategy="unc") == unc


def test_grid_cells_from_scratch(monkeypatch):
  smoke = plans.SCALES["smoke"]
  monkeypatch.setitem(plans.SCALES, "smoke", dataclasses.replace(
      smoke, v4=dataclasses.replace(smoke.v4, regime=("scratch", "1/8", 6))))
  plan = plans.build_plan("v4", "smoke", 3)
  assert len(plan.cells) == 9 and [c.arm for c in plan.cells[:3]] == ["stl", "unc", "epr"]
  for cell in plan.cells:
    c = cell.config
    assert cell.init_cell is None and dict(cell.factors) == {"setting": "scratch", "data": "1/8"}
    assert (c.domain, c.fraction, c.lr, c.steps, c.val_every_steps) == (
        "objects", "1/8", smoke.lr, 6, smoke.v4.val_every)
    assert [e.name for e in cell.evals] == ["test-objects", "test-objects-best"]


@pytest.mark.parametrize("change, seeds, message", [
    ({"regime": None}, 3, "no regime yet"),
    ({"regime": plans.NO_REGIME}, 3, "found no setting where stl overfits"),
    ({"grid_seeds": None}, 3, "number of seeds at scale smoke is not committed"),
    ({}, 4, "--seeds 4: plan v4 runs the 3 seeds committed")])
def test_grid_is_refused_until_the_pilot_and_the_seed_rule_are_committed(monkeypatch, change,
                                                                         seeds, message):
  smoke = plans.SCALES["smoke"]
  monkeypatch.setitem(plans.SCALES, "smoke", dataclasses.replace(
      smoke, v4=dataclasses.replace(smoke.v4, **change)))
  with pytest.raises(SljaxError, match=message):
    plans.build_plan("v4", "smoke", seeds)


def _measured(monkeypatch, step_seconds):
  smoke = plans.SCALES["smoke"]
  design = dataclasses.replace(smoke.v4, step_seconds=step_seconds, val_seconds=8.0,
                               val_scenes=80, arm_ratios=(("stl", 1.0, 1.0),
                                                          ("unc", 1.5, 2.0), ("epr", 1.5, 2.0)))
  monkeypatch.setitem(plans.SCALES, "smoke", dataclasses.replace(smoke, v4=design))
  return design


def test_the_seed_rule_by_hand(monkeypatch):
  """One seed's hours: per arm the pretraining's and fine-tuning's steps at the arm's step
  ratio, and each validation's and test scoring's scenes at its validation ratio."""
  design = _measured(monkeypatch, 100.0)
  smoke = plans.SCALES["smoke"]
  pilot = plans.build_plan("v4-pilot", "smoke", 1)
  pre = dataclasses.replace(pilot.cells_of(setting="pretrain")[0].config, seed=300)
  ft = dataclasses.replace(pilot.cells_of(setting="finetune")[0].config, seed=300)

  def n_val(config):
    return len(split_indices(open_source(config), config.test_fraction, seed=config.seed)[1])

  per_scene = 8.0 / 80
  # Fine-tuning 4 steps validates at 2 and 4; 5 steps at 2, 4 and the last, 5.
  for steps, ft_validations in ((4, 2), (5, 3)):
    seconds = 0.0
    for step_ratio, val_ratio in ((1.0, 1.0), (1.5, 2.0), (1.5, 2.0)):
      seconds += step_ratio * 100.0 * (4 + steps)  # the pretraining's 4 steps, the regime's
      seconds += val_ratio * per_scene * (2 * n_val(pre) + ft_validations * n_val(ft)
                                          + 2 * smoke.v2.test_n)
    rule = regime.grid_seeds("smoke", ("finetune", "1/2", steps))
    assert rule["hours_per_seed"] == pytest.approx(seconds / 3600)
    assert rule["seeds"] == min(10, max(3, int(24 // (seconds / 3600))))
    assert [c["steps"] for c in rule["cells"]] == [4, steps] * 3
  # The clip: cheap seeds stop at 10, dear ones still run 3.
  _measured(monkeypatch, 1.0)
  assert regime.grid_seeds("smoke", design.regime)["seeds"] == 10
  _measured(monkeypatch, 10_000.0)
  assert regime.grid_seeds("smoke", design.regime)["seeds"] == 3


def test_the_seed_rule_in_between(monkeypatch):
  """A seed of about 5 hours gives n = 4 (24 // 5)."""
  _measured(monkeypatch, 1.0)
  base = regime.grid_seeds("smoke", ("finetune", "1/2", 4))["hours_per_seed"]
  steps_hours = 1.0 * 8 * (1 + 1.5 + 1.5) / 3600
  # Scale the step cost so that a seed takes 5 h: the validations' share stays.
  s = (5.0 - (base - steps_hours)) / (8 * 4.0 / 3600)
  _measured(monkeypatch, s)
  rule = regime.grid_seeds("smoke", ("finetune", "1/2", 4))
  assert rule["hours_per_seed"] == pytest.approx(5.0) and rule["seeds"] == 4


def test_the_pilot_outcome_names_n_when_measured(tmp_path, monkeypatch):
  _measured(monkeypatch, 1.0)
  plan = plans.build_plan("v4-pilot", "smoke", 1)
  records.register(tmp_path, plan)
  for cell in plan.cells:
    _fake(tmp_path, cell.name, RISING if dict(cell.factors)["setting"] == "finetune" else FLAT)
  result = regime.write(tmp_path, "smoke", 1)
  assert result["grid_setting"] == "finetune"
  assert result["grid_seeds"] == regime.grid_seeds("smoke", ("finetune", "1/2", 16))
  assert "**n = 10**" in (tmp_path / "regime.md").read_text()


def test_grid_claims_on_fake_records(tmp_path):
  """v3's family of two on the fine-tuning setting: (a) the tissue test set's final Full MAE,
  (b) the rise of each fine-tuning cell's own curve by steps; hand-computed differences."""
  import json  # pylint: disable=import-outside-toplevel
  import numpy as np  # pylint: disable=import-outside-toplevel
  from sljax.experiment.report import build, paper_claims, stats  # pylint: disable=import-outside-toplevel
  plan = plans.build_plan("v4", "smoke", 3)
  records.register(tmp_path, plan)
  mae = {"stl": [1.0, 1.2, 1.1], "unc": [0.9, 1.0, 1.05], "epr": [1.0, 1.1, 1.2]}
  rise = {"stl": [0.3, 0.2, 0.4], "unc": [0.1, 0.1, 0.2], "epr": [0.3, 0.3, 0.3]}
  for cell in plan.cells:
    k = cell.seed - 300
    if dict(cell.factors)["setting"] == "pretrain":  # another curve: the claims must not read it
      _fake(tmp_path, cell.name, [(2, 1.0, 3), (4, 0.2, 2), (6, 2.0, 1)])
      continue
    _fake(tmp_path, cell.name, [(2, 1.0, 3 + k), (4, 0.5, 2), (6, 0.5 + rise[cell.arm][k], 1)])
    for e in cell.evals:
      path = records.cell_dir(tmp_path, cell.name) / "eval" / f"{e.name}.json"
      path.parent.mkdir(exist_ok=True)
      path.write_text(json.dumps({"pooled": {"full": {"mae": mae[cell.arm][k]}}}))
  agg = build.aggregate(tmp_path, plan)
  cl = paper_claims.claims(plan, agg)
  assert [c["set"] for c in cl] == ["test-tissue", "validation-curve"]
  assert cl[0]["difference"]["mean"] == pytest.approx(np.mean(np.subtract(mae["unc"], mae["stl"])))
  assert cl[1]["difference"]["mean"] == pytest.approx(np.mean(np.subtract(rise["unc"],
                                                                          rise["stl"])))
  assert [c["p_holm"] for c in cl] == pytest.approx(stats.holm([c["difference"]["p"]
                                                                for c in cl]))
  # The pretraining cells score nothing: their group has no set, the curves are by step.
  pre = next(g for g in agg["groups"] if g["factors"]["setting"] == "pretrain")
  assert pre["sets"] == {} and [p["step"] for p in pre["curves"]["stl"]] == [2, 4, 6]
  # The training loss between validations, the seeds' mean per arm (secondary): 3, 4 and 5.
  ft = next(g for g in agg["groups"] if g["factors"]["setting"] == "finetune")
  assert [(p["step"], p["mean"]) for p in ft["train_curves"]["unc"]] == [(2, 4), (4, 2), (6, 1)]
  md = build.write_report(tmp_path).read_text()
  assert "v4: stl, unc and epr" in md and "overfitting rise" in md
  assert (tmp_path / "figures" / "v4_curves.png").exists()
  assert "Not finite at some validation" not in md
  # A diverged cell (a NaN validation) is named: its rise counts the finite values only.
  name = plan.cells_of(setting="finetune")[0].name
  import shutil  # pylint: disable=import-outside-toplevel
  shutil.rmtree(records.cell_dir(tmp_path, name))
  _fake(tmp_path, name, [(2, 1.0, 3), (4, 0.5, 2), (6, float("nan"), 1)])
  md = build.write_report(tmp_path).read_text()
  assert f"(diverged; the rise above is over the finite values only, so it understates theirs): " \
         f"{name}." in md


def test_the_committed_regime_is_the_rules_on_the_committed_pilot():
  """scales.py's v4 regime and n are what main's rule gives on docs/results/v4-pilot: none
  before every pilot cell is committed; afterwards the chosen setting, fraction, budget and n."""
  from pathlib import Path  # pylint: disable=import-outside-toplevel
  records = Path(__file__).resolve().parents[1] / "docs" / "results" / "v4-pilot"
  design = plans.SCALES["cpu"].v4
  result = regime.v4(records, "cpu", 2)
  if result["missing"]:
    assert design.regime is None and design.grid_seeds is None, result["missing"]
    return
  if result["grid_setting"] is None:
    assert design.regime == plans.NO_REGIME and design.grid_seeds is None
    return
  chosen = result["settings"][result["grid_setting"]]["regime"]
  assert design.regime == (result["grid_setting"], chosen["fraction"], chosen["budget_steps"])
  assert design.grid_seeds == result["grid_seeds"]["seeds"]


def test_a_diverged_grid_cell_is_left_out_and_the_grid_goes_on(tmp_path, monkeypatch):
  """A cell whose training loss goes non-finite is recorded (diverged.json) and the runner goes
  on without it and the cells fine-tuned from it; a rerun keeps them out; status and the
  report name them, and the pairs leave their seeds out (docs/plan-v4.md's addendum)."""
  import json  # pylint: disable=import-outside-toplevel
  from sljax.experiment.report import build  # pylint: disable=import-outside-toplevel
  from sljax.experiment.running import runner, status
  from sljax.train.record import TrainingDiverged  # pylint: disable=import-outside-toplevel
  plan = plans.build_plan("v4", "smoke", 3)
  by = _by(plan)
  blows_up = {by[("stl", "pretrain", 300)].name, by[("epr", "finetune", 302)].name}
  trained = []

  def fake_train(out, cell, bar, weight, on_step=None, stop=None):  # pylint: disable=unused-argument
    trained.append(cell.name)
    if cell.name in blows_up:  # one validation before the loss went NaN
      wd = records.cell_dir(out, cell.name)
      wd.mkdir(parents=True)
      (wd / "validation.jsonl").write_text(json.dumps(_rows([(2, 1.0, 3)])[0]) + "\n")
      raise TrainingDiverged(f"non-finite loss (nan) at step 3 in {cell.name}")
    _fake(out, cell.name, [(2, 1.0, 3), (4, 0.5, 2), (6, 0.6, 1)])
    return {"step": 6}

  def fake_evaluate(out, cell, evalset):
    rep = {"pooled": {"full": {"mae": 1.0 + 0.1 * (cell.seed - 300)
                               - 0.2 * (cell.arm != "stl")}}}
    path = records.cell_dir(out, cell.name) / "eval" / f"{evalset.name}.json"
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps(rep))
    return rep

  monkeypatch.setattr(runner, "train_cell", fake_train)
  monkeypatch.setattr(runner, "evaluate_cell", fake_evaluate)
  res = runner.run(plan, tmp_path, progress=False, log=lambda _: None)
  stl_ft = by[("stl", "finetune", 300)].name
  assert set(res["diverged"]) == blows_up | {stl_ft}
  assert res["diverged"][stl_ft] == f"fine-tuned from {by[('stl', 'pretrain', 300)].name}, " \
                                    "which diverged"
  assert stl_ft not in trained and res["trained"] == len(plan.cells) - 3
  for name in blows_up:
    rec = json.loads((records.cell_dir(tmp_path, name) / records.DIVERGED_FILE).read_text())
    assert name in rec["message"] and "machine" in rec
    assert not (records.cell_dir(tmp_path, name) / records.DONE_FILE).exists()
  assert not (records.cell_dir(tmp_path, stl_ft) / records.DIVERGED_FILE).exists()
  # Run again: nothing to do, the same three left out.
  trained.clear()
  again = runner.run(plan, tmp_path, progress=False, log=lambda _: None)
  assert trained == [] and again["trained"] == again["evaluated"] == 0
  assert again["diverged"].keys() == res["diverged"].keys()
  states = status.plan_status(tmp_path, plan)
  assert {s.cell.name for s in states if s.state == status.DIVERGED} == set(res["diverged"])
  text = status.format_status(plan, states, "here")
  assert "3 left out (diverged)" in text and "Training left" not in text
  # The report: named, not "not scored yet", and the pairs over the seeds both arms have.
  agg = build.aggregate(tmp_path, plan)
  ft = next(g for g in agg["groups"] if g["factors"]["setting"] == "finetune")
  test = ft["sets"]["test-tissue"]
  assert test["missing"] == [] and set(test["diverged"]) == {stl_ft, by[("epr", "finetune",
                                                                          302)].name}
  assert test["paired"]["unc"]["mae"]["n"] == 2  # seeds 301 and 302 (stl's 300 left out)
  assert test["paired"]["epr"]["mae"]["n"] == 1  # seed 301 only
  assert test["paired"]["unc"]["mae"]["mean"] == pytest.approx(-0.2)
  assert [p["n"] for p in ft["curves"]["stl"]] == [2, 2, 2]
  # epr's mean curve over its two finished seeds, not cut to the diverged cell's one step.
  assert [(p["step"], p["n"]) for p in ft["curves"]["epr"]] == [(2, 2), (4, 2), (6, 2)]
  md = build.write_report(tmp_path).read_text()
  assert "Left out, diverged" in md and stl_ft in md


def test_a_nan_score_leaves_its_seed_out_of_that_pair_only(tmp_path):
  """A finished cell scored NaN (None in its report) on the test set: that seed drops out of
  that metric's pair; the claim is still computed over the other seeds."""
  import json  # pylint: disable=import-outside-toplevel
  from sljax.experiment.report import build, paper_claims  # pylint: disable=import-outside-toplevel
  plan = plans.build_plan("v4", "smoke", 3)
  records.register(tmp_path, plan)
  mae = {"stl": [1.0, 1.2, None], "unc": [0.9, 1.0, 1.05], "epr": [1.0, 1.1, 1.2]}
  for cell in plan.cells:
    _fake(tmp_path, cell.name, [(2, 1.0, 3), (4, 0.5, 2), (6, 0.6, 1)])
    for e in cell.evals:
      path = records.cell_dir(tmp_path, cell.name) / "eval" / f"{e.name}.json"
      path.parent.mkdir(exist_ok=True)
      path.write_text(json.dumps({"pooled": {"full": {
          "mae": mae[cell.arm][cell.seed - 300], "bad_2": 0.1}}}))
  agg = build.aggregate(tmp_path, plan)
  ft = next(g for g in agg["groups"] if g["factors"]["setting"] == "finetune")
  unc = ft["sets"]["test-tissue"]["paired"]["unc"]
  assert unc["mae"]["n"] == 2 and unc["mae"]["mean"] == pytest.approx(-0.15)
  assert unc["bad_2"]["n"] == 3
  assert paper_claims.claims(plan, agg)[0]["difference"]["n"] == 2
