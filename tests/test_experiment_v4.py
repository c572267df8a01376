"""The v4 design (docs/plan-v4.md): the pilot's cells with budgets in steps (scene counts by
hand from the split), and v3's rule on steps with the memorisation measure, by hand."""

import dataclasses

import pytest

from sljax.data.dataset import split_indices, take_fraction
from sljax.errors import SljaxError
from sljax.experiment import plans, regime
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
  none = regime.v4_setting({"1/32": {"s200": flat}}, ("1/32", "1/64"), 100)
  assert none["regime"]["fraction"] is None


def _fake(out, name, points):
  import json  # pylint: disable=import-outside-toplevel
  from sljax.experiment import runner  # pylint: disable=import-outside-toplevel
  wd = runner.cell_dir(out, name)
  wd.mkdir(parents=True)
  (wd / "validation.jsonl").write_text("".join(json.dumps(r) + "\n" for r in _rows(points)))
  (wd / runner.DONE_FILE).write_text(json.dumps({"step": points[-1][0]}))


RISING = [(2, 1.0, 5), (4, 0.6, 3), (6, 0.6, 2), (8, 0.9, 1), (10, 1.0, 0.5), (12, 1.1, 0.2)]
FLAT = [(2, 1.0, 5), (4, 0.9, 3), (6, 0.9, 2), (8, 0.9, 2)]


@pytest.mark.parametrize("scratch, finetune, grid", [
    (RISING, RISING, "finetune"), (RISING, FLAT, "scratch"), (FLAT, RISING, "finetune"),
    (FLAT, FLAT, None)])
def test_the_grid_setting_by_the_rule(tmp_path, scratch, finetune, grid):
  """Both settings overfit: fine-tuning; one: that one; none: no grid. Waits for every cell."""
  from sljax.experiment import runner  # pylint: disable=import-outside-toplevel
  plan = plans.build_plan("v4-pilot", "smoke", 1)
  runner.register(tmp_path, plan)
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
  (runner.cell_dir(tmp_path, plan.cells[0].name) / runner.DONE_FILE).unlink()
  assert regime.v4(tmp_path, "smoke", 1)["grid_setting"] is None
  assert regime.v4(tmp_path, "smoke", 1)["missing"] == [plan.cells[0].name]


def test_status_reads_a_step_budget_by_steps():
  from sljax.experiment.status import TRAINING, CellState  # pylint: disable=import-outside-toplevel
  cell = plans.build_plan("v4-pilot", "cpu", 1).cells[0]
  s = CellState(cell, TRAINING, epoch=300, step=675)
  assert s.share == pytest.approx(675 / 2700) and s.where == "step 675 of 2700"
  v3 = plans.build_plan("v3-pilot", "cpu", 1).cells[0]
  e = CellState(v3, TRAINING, epoch=60, step=60)
  assert e.share == pytest.approx(60 / 240) and e.where == "epoch 60 of 240"
