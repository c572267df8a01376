"""Budgets in optimizer steps (--steps) and validation every K steps (--val-every-steps): the
rows of validation.jsonl against metrics.jsonl by hand, the short last epoch, the checkpoints
(each validation's, the best by validation MAE) and exact resume after kill -9."""

import dataclasses
import json
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sljax.errors import SljaxError
from sljax.experiment.design import plans
from sljax.models import checkpoint as ckpt
from sljax.train import loop
from sljax.train.config import TrainConfig, validate
from sljax.train.state import LoopState
from sljax.train.workdir import EPOCHS_FILE, METRICS_FILE

import test_loop
import toys

TESTS = Path(__file__).resolve().parent
QUIET = dict(log=lambda line: None, progress=False)
SPE = 6  # test_loop.MemorySource: 12 training scenes, batch 2


@pytest.fixture
def tiny(monkeypatch):
  monkeypatch.setattr(loop, "compiled_steps", toys.tiny_steps)
  monkeypatch.setattr(loop, "open_source", lambda config: test_loop.MemorySource())


def _rows(path: Path) -> list[dict]:
  return [json.loads(l) for l in path.read_text().splitlines()]


def _mean(rows: list[dict], key: str, first: int, last: int) -> float:
  """The mean of a metrics.jsonl column over steps first..last, by hand."""
  values = [r[key] for r in rows if first <= r["step"] <= last]
  assert len(values) == last - first + 1
  return float(np.mean(values))


def test_validation_every_k_steps_with_the_training_loss_since_the_last(tiny, tmp_path):
  cfg = test_loop._config("epr", epochs=99, steps=15, val_every_steps=4)
  result = loop.train(cfg, tmp_path / "w", **QUIET)
  assert result.step == 15  # --steps wins over --epochs
  wd = tmp_path / "w"
  metrics, val = _rows(wd / METRICS_FILE), _rows(wd / "validation.jsonl")
  assert [r["step"] for r in metrics] == list(range(1, 16))
  assert [r["step"] for r in val] == [4, 8, 12, 15]  # every 4 steps, and the last
  prev = 0
  for r in val:
    assert r["train_steps"] == r["step"] - prev
    for key in ("loss_sl", "loss_disp"):
      assert r[f"train_{key}"] == pytest.approx(_mean(metrics, key, prev + 1, r["step"]),
                                                rel=1e-12)
    assert r["epoch"] == pytest.approx(r["step"] / SPE)
    assert np.isfinite(r["val_mae"])
    prev = r["step"]
  # Epochs still close (DWA reads them); the budget ends the third part-way, after 3 steps.
  epochs = _rows(wd / EPOCHS_FILE)
  assert [(r["epoch"], r["step"]) for r in epochs] == [(1, 6), (2, 12), (3, 15)]
  assert epochs[2]["loss_disp"] == pytest.approx(_mean(metrics, "loss_disp", 13, 15), rel=1e-12)
  assert not any("val_mae" in r for r in epochs)  # validation rows live in validation.jsonl
  # A checkpoint at each validation (not at epoch ends): the last, and the best by MAE kept.
  best = min(val, key=lambda r: r["val_mae"])["step"]
  kept = sorted(int(p.name) for p in (wd / ckpt.CHECKPOINT_DIR).iterdir() if p.name.isdigit())
  assert set(kept) <= {4, 8, 12, 15} and 15 in kept and best in kept, (kept, best)
  assert result.best_val == pytest.approx(min(r["val_mae"] for r in val))


def test_a_steps_budget_validating_by_epochs_validates_its_short_last_epoch(tiny, tmp_path):
  cfg = test_loop._config("stl", epochs=99, steps=9, val_every=1)
  result = loop.train(cfg, tmp_path / "w", **QUIET)
  epochs = _rows(tmp_path / "w" / EPOCHS_FILE)
  assert result.step == 9 and [(r["epoch"], r["step"]) for r in epochs] == [(1, 6), (2, 9)]
  assert all(np.isfinite(r["val_mae"]) for r in epochs)
  assert not (tmp_path / "w" / "validation.jsonl").exists()
  assert test_loop._final(tmp_path / "w")[0] == 9


@pytest.mark.parametrize("strategy", ["epr", "unc"])
def test_a_steps_budget_resumes_exactly_after_kill(strategy, tiny, tmp_path):
  """Killed at step 11 (between validations 8 and 12, mid-epoch), resumed from the --save-every
  checkpoint 9: parameters, optimiser state, every metrics, epochs and validation row as the
  uninterrupted run (validation 12's interval sums continue from checkpoint 9's)."""
  cfg = test_loop._config(strategy, epochs=99, steps=17, val_every_steps=4, save_every=3)
  full = loop.train(cfg, tmp_path / "full", **QUIET)
  wd = tmp_path / "killed"
  child = dataclasses.replace(cfg, log_every=1)
  proc = subprocess.run([sys.executable, "-c", test_loop._CHILD, json.dumps(child.to_json()),
                         str(wd), "step 11", str(TESTS)], env=toys.same_device_env(),
                        cwd=tmp_path, capture_output=True, text=True, timeout=300)
  assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
  assert test_loop._final(wd)[0] == 9
  steps = sorted(int(p.name) for p in (wd / ckpt.CHECKPOINT_DIR).iterdir() if p.name.isdigit())
  assert {6, 8, 9} <= set(steps), steps  # --save-every at an epoch end too (6)
  assert [r["step"] for r in _rows(wd / "validation.jsonl")] == [4, 8]
  result = loop.train(cfg, wd, resume=True, **QUIET)
  assert result.step == full.step == 17
  test_loop._assert_same_run(tmp_path / "full", wd)
  assert _rows(wd / "validation.jsonl") == _rows(tmp_path / "full" / "validation.jsonl")


def test_step_options_are_checked_and_kept_out_of_older_cells_specs():
  for name in ("steps", "val_every_steps"):
    with pytest.raises(SljaxError, match=f"--{name.replace('_', '-')} 0: must be positive"):
      validate(TrainConfig(**{name: 0}))
  cell = plans.build_plan("table2", "smoke", 1).cells[0]
  assert "steps" not in cell.spec()["config"]  # committed plan.json files name the same runs
  stepped = dataclasses.replace(cell, config=dataclasses.replace(cell.config, steps=10,
                                                                 val_every_steps=5))
  assert stepped.spec()["config"]["steps"] == 10 and stepped.spec() != cell.spec()


def test_loop_state_interval_sums_reset_at_each_validation_and_round_trip():
  s = LoopState()
  for l_sl, l_disp in ((1.0, 4.0), (3.0, 2.0)):
    s = s.add_step(l_sl, l_disp)
  assert s.interval_means() == (2.0, 3.0)
  s = s.validated(0.5).add_step(5.0, 7.0)
  assert s.since_val == (5.0, 7.0, 1) and s.partial == (9.0, 13.0, 3)
  assert LoopState.from_meta(json.loads(json.dumps(s.to_meta()))) == s
  old = {"step": 3, "history": [], "partial": [1.0, 1.0, 1], "best_val": 0.5}
  assert LoopState.from_meta(old).since_val == (0.0, 0.0, 0)  # earlier checkpoints
