"""The v2 design: three group-level splits, fixed test sets identical across seeds and arms,
the cpu128 scale's pattern count, the calibration rule (no training here)."""

import dataclasses
import math

import numpy as np
import pytest

from sljax.data.dataset import split_indices, split_three
from sljax.errors import SljaxError
from sljax.experiment import records
from sljax.experiment.budget import calibrate
from sljax.experiment.design import cells, plans
from sljax.experiment.running import runner
from sljax.render.synthetic import SynthConfig, render_scene
from sljax.train.feed import open_source


class _Groups:
  """A source of n scenes in groups of k (group names only; nothing is rendered)."""

  def __init__(self, n, k):
    self.n, self.k = n, k

  def __len__(self):
    return self.n

  def group(self, i):
    return f"g{i // self.k:03d}"


@pytest.mark.parametrize("seed", [0, 1, 5])
def test_three_splits_are_disjoint_groups_and_the_test_part_ignores_the_seed(seed):
  src = _Groups(200, 10)  # 20 groups
  train, val, test = split_three(src, 0.25, 0.2, seed=seed, test_seed=7)
  assert sorted(train + val + test) == list(range(200))
  parts = [{src.group(i) for i in part} for part in (train, val, test)]
  assert not (parts[0] & parts[1] or parts[0] & parts[2] or parts[1] & parts[2])
  assert len(parts[2]) == 4 and len(parts[1]) == 4  # 20% of 20; 25% of the remaining 16
  # The test part is split_indices' held-out part for the test seed, whatever the seed.
  assert test == split_indices(src, 0.2, seed=7)[1]
  assert test == split_three(src, 0.25, 0.2, seed=seed + 1, test_seed=7)[2]
  # Validation does depend on the seed.
  assert len({tuple(split_three(src, 0.25, 0.2, seed=s, test_seed=7)[1]) for s in range(6)}) > 1
  with pytest.raises(SljaxError, match="validation fraction"):
    split_three(src, 1.0, 0.2, seed=seed)


def test_the_old_two_way_split_is_unchanged():
  """split_indices keeps its v1 behaviour (v1 results stay reproducible): the naive rule."""
  import hashlib
  src = _Groups(70, 10)
  for seed in range(4):
    unique = sorted({src.group(i) for i in range(70)}, key=lambda g: (int.from_bytes(
        hashlib.sha256(f"{seed}\x00{g}".encode()).digest()[:8], "big"), g))
    held = set(unique[:1])  # round(0.2 * 7) = 1
    assert split_indices(src, 0.2, seed)[1] == [i for i in range(70) if src.group(i) in held]


def test_v2_test_sets_are_the_same_for_every_seed_and_arm_and_disjoint_from_training():
  plan = plans.build_plan("table1-v2", "smoke", 3)
  by_set: dict[str, set] = {}
  for cell in plan.cells:
    for e in cell.evals:
      source, idx = runner._eval_source(cell, e)  # pylint: disable=protected-access
      assert e.kind == cells.FIXED and source.seed == cells.TEST_SEED
      assert idx == list(range(plan.scale.v2.test_n))
      by_set.setdefault(e.name, set()).add((source.seed, source.config, tuple(idx)))
      test_groups = {source.group(i) for i in idx}
      train = open_source(cell.config)
      train_groups = {train.group(i) for i in range(len(train))}
      assert not test_groups & train_groups, cell.name
      assert len(test_groups) >= 2
  assert set(by_set) == {"test-objects", "test-tissue"}
  assert all(len(v) == 1 for v in by_set.values())  # one test set per domain
  # Two cells (arms, seeds) score the very same scenes: rendered equal.
  a, b = plan.cells[0], plan.cells[-2]
  assert a.seed != b.seed and a.arm != b.arm and a.evals == b.evals
  sa, ia = runner._eval_source(a, a.evals[0])  # pylint: disable=protected-access
  sb, ib = runner._eval_source(b, b.evals[0])  # pylint: disable=protected-access
  np.testing.assert_array_equal(sa[ia[3]].im0, sb[ib[3]].im0)
  np.testing.assert_array_equal(sa[ia[3]].disp0, sb[ib[3]].disp0)


def test_v2_plans_at_the_cpu_scales():
  cpu = plans.SCALES["cpu"]
  assert cpu.v2.test_n >= 400 and cpu.v2.test_n // SynthConfig().views_per_object >= 40
  assert 17 in plans.SCALES["cpu128"].v2.windows
  # A v2 cell trains exactly as the v1 cell of the same name: the designs share training runs.
  v1 = {c.name: c for c in plans.build_plan("table2", "cpu", 2).cells}
  v2 = plans.build_plan("table2-v2", "cpu", 2).cells
  assert len(v2) == 10 and all(c.config.fraction == "1/16" for c in v2)
  assert all(c.spec() == v1[c.name].spec() for c in v2)
  # table1-v2's cpu128 budgets are calibrated (no plateau: the whole long runs); table2-v2's
  # at cpu128 are not yet.
  t1_128 = plans.build_plan("table1-v2", "cpu128", 5)
  assert {(c.arm, c.config.epochs) for c in t1_128.cells} == {
      ("unet-sl", 60), ("unet-sl", 120), ("unet-disp", 60), ("unet-disp", 120)}
  with pytest.raises(SljaxError, match="no calibrated budget for"):
    plans.build_plan("table2-v2", "cpu128", 5)
  with pytest.raises(SljaxError, match="--data: plan table2-v2"):
    plans.build_plan("table2-v2", "smoke", 1, data=".")
  t1 = plans.build_plan("table1-v2", "smoke", 1)
  assert {c.name: c.windows for c in t1.cells} == {
      "unet-sl-objects-s0": (3, 5), "unet-sl-tissue-ft-s0": (3, 5),
      "unet-disp-objects-s0": (), "unet-disp-tissue-ft-s0": ()}


def test_cpu128_finest_stripe_is_resolved():
  """Binary code, 2^7 columns over the 70 degree projector: one column is f tan(35) / 64 =
  1.2 * 128 * 0.7002 / 64 = 1.68 px at the camera, so the finest pattern is known about as
  often as the coarsest (the renderer marks stripes narrower than 1 px unknown); 8 patterns
  would give 0.84 px stripes, which alias."""
  sc = plans.SCALES["cpu128"]
  assert 1.2 * sc.size * math.tan(math.radians(35.0)) / 2 ** (sc.t - 1) == pytest.approx(
      1.68, abs=0.01)
  assert 1.2 * sc.size * math.tan(math.radians(35.0)) / 2 ** sc.t < 1.0  # 8 patterns alias
  known = []
  for i in range(2):
    sl = render_scene(i, 0, SynthConfig(size=sc.size, domain="objects", t=sc.t)).sl0
    known.append(np.isfinite(sl[..., -1]).sum() / np.isfinite(sl[..., 0]).sum())
  assert min(known) > 0.9


def test_plateau_rule_by_hand():
  # v1's stl calibration at 1/16 (fixed lr until epoch 72): trailing means of 3 validations
  # reach 0.748 at epoch 56 and a minimum of 0.737 at 64 (mean of epochs 48, 56, 64); 1.05 x
  # 0.737 = 0.774 is first met at 56 (48: 0.783): P = 56, the budget ceil(4 x 56 / 3) = 75
  # with the drop.
  curve = [(8, 1.378), (16, 0.938), (24, 0.814), (32, 0.802), (40, 0.788), (48, 0.760),
           (56, 0.697), (64, 0.753), (72, 0.770)]
  res = calibrate.plateau(curve, 96, drop=True)
  assert res["smoothed"][6] == [56, pytest.approx((0.788 + 0.760 + 0.697) / 3)]
  assert res["plateau_epoch"] == 56 and res["reached"] and res["budget"] == 75
  assert res["best_smoothed"] == pytest.approx((0.760 + 0.697 + 0.753) / 3)
  assert calibrate.plateau(curve, 96, drop=False)["budget"] == 56
  # Still falling at the end of the long run: no plateau, the budget is the long run's.
  falling = [(e, 2.0 / e) for e in range(1, 41)]
  res = calibrate.plateau(falling, 40, drop=True)
  assert not res["reached"] and res["budget"] == 40


def test_calibration_plan():
  cal = plans.calibration_plan("table1-v2", "cpu128")
  names = [c.name for c in cal.cells]
  assert names == ["calib-unet-sl-objects", "calib-unet-sl-tissue-ft", "calib-unet-disp-objects",
                   "calib-unet-disp-tissue-ft"]
  by = {c.name: c for c in cal.cells}
  pre, ft = by["calib-unet-sl-objects"], by["calib-unet-sl-tissue-ft"]
  assert pre.config.epochs == 60 and pre.config.lr == 1e-3 and pre.config.lr_drop_epoch is None
  assert ft.init_cell == pre.name and ft.config.epochs == 120 and ft.config.lr == pytest.approx(
      1e-4)
  assert all(c.seed == 0 and c.config.max_val is None and not c.evals for c in cal.cells)
  with pytest.raises(SljaxError, match="not a calibrated plan"):
    plans.calibration_plan("table1", "cpu128")


@pytest.mark.parametrize("plan", ["table1-v2", "table2-v2", "table3-v2"])
def test_calibrate_at_a_scale_without_calibration_epochs(plan, capsys, monkeypatch):
  """A scale without calibration epochs (the paper scale had none before issue 63): one line
  naming the scales that have them (was a KeyError '1/16' / 'objects'), exit 2, nothing
  written."""
  from sljax import cli
  monkeypatch.setitem(plans.SCALES, "paper", dataclasses.replace(
      plans.SCALES["paper"], v2=dataclasses.replace(plans.SCALES["paper"].v2, calib_epochs=())))
  assert cli.main(["experiment", "calibrate", plan, "/nonexistent/cal", "--scale", "paper"]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert err == [f"sljax experiment: error: calibrate --scale paper: the scale has no "
                 f"calibration epochs for plan {plan}; calibrate it at smoke, cpu or cpu128"]


def test_a_chosen_window_is_kept_and_a_changed_window_set_refused(tmp_path):
  cell = plans.build_plan("table1-v2", "smoke", 1).cells[0]
  assert cell.arm == "unet-sl" and cell.windows == (3, 5)
  path = records.cell_dir(tmp_path, cell.name) / records.EVAL_DIR / records.WINDOWS_FILE
  path.parent.mkdir(parents=True)
  path.write_text('{"candidates": [3, 5], "chosen": 5}')
  assert runner.choose_window(tmp_path, cell) == 5  # kept: nothing re-scored
  path.write_text('{"candidates": [3], "chosen": 3}')
  with pytest.raises(SljaxError, match="chose its window from \\[3\\]"):
    runner.choose_window(tmp_path, cell)
  other = plans.build_plan("table1-v2", "smoke", 1).cells[2]
  assert other.arm == "unet-disp" and runner.choose_window(tmp_path, other) is None
