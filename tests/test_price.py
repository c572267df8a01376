"""`sljax experiment run|submit --dry-run`: the price of a plan (sljax.experiment.running.price),
worked out by hand on a small plan, the GPU figures against their records, and that a dry run
writes and submits nothing."""

import hashlib
import json
from pathlib import Path

import pytest

from sljax import cli
from sljax.errors import SljaxError
from sljax.experiment.design import cells, plans
from sljax.experiment.records import DONE_FILE, cell_dir, register, write_json
from sljax.experiment.running import gpu_figures as gf, price, submit
from sljax.runtime import machine

REPO = Path(__file__).resolve().parent.parent

# Round figures so that every cost below is worked out by hand.
FIGURES = price.Figures("by hand", (
    price.NetFigure("unet-sl", 1.0, 0.1, "hand", "hand"),
    price.NetFigure("unet-disp", 2.0, 0.2, "hand", "hand")), start_s=5.0, start_from="hand")


@pytest.fixture(scope="module")
def costs():
  return price.price(plans.build_plan("table1-v2", "smoke", 1), FIGURES)


def test_the_small_plan_by_hand(costs):
  # table1-v2 at the smoke scale, seed 0: unet-sl and unet-disp on objects (40 scenes: 30 train,
  # 10 validation; batch 2, 2 epochs: 15 x 2 = 30 steps), each fine-tuned on tissue (20 scenes:
  # 10 train: 5 x 2 = 10 steps). Every epoch validates, on at most max_val = 4 scenes. Scoring:
  # the fixed test set of 20 scenes; unet-sl also chooses its window from (3, 5) on its whole
  # validation split (10 scenes) once per window: 20 more.
  assert [(c.name, c.net, c.waits_for, c.steps, c.val_passes, c.val_scenes, c.score_scenes)
          for c in costs] == [
      ("unet-sl-objects-s0", "unet-sl", (), 30, 2, 4, 40),
      ("unet-sl-tissue-ft-s0", "unet-sl", ("unet-sl-objects-s0",), 10, 2, 4, 40),
      ("unet-disp-objects-s0", "unet-disp", (), 30, 2, 4, 20),
      ("unet-disp-tissue-ft-s0", "unet-disp", ("unet-disp-objects-s0",), 10, 2, 4, 20)]
  # Seconds: steps x step + passes x scenes x forward + scored x forward + a start of 5 s.
  # unet-sl-objects 30 + 0.8 + 4 + 5 = 39.8; its fine-tuning 10 + 0.8 + 4 + 5 = 19.8;
  # unet-disp-objects 60 + 1.6 + 4 + 5 = 70.6; its fine-tuning 20 + 1.6 + 4 + 5 = 30.6.
  assert [c.total_s for c in costs] == pytest.approx([39.8, 19.8, 70.6, 30.6])
  # GPU-hours of training steps: (30 + 10) x 1 s + (30 + 10) x 2 s = 120 s.
  assert sum(c.train_s for c in costs) / 3600 == pytest.approx(120 / 3600)
  assert sum(c.total_s for c in costs) == pytest.approx(160.8)


def test_the_wall_time_by_hand(costs):
  # One worker: everything in a row, 160.8 s.
  assert price.wall_time(costs, 1) == pytest.approx(160.8)
  # Two: worker 1 takes unet-sl-objects (0-39.8); worker 2 cannot take its fine-tuning yet and
  # takes unet-disp-objects (0-70.6); worker 1 fine-tunes unet-sl (39.8-59.6), then waits for
  # unet-disp-objects and fine-tunes it (70.6-101.2).
  assert price.wall_time(costs, 2) == pytest.approx(101.2)
  # Many: the chain unet-disp-objects then its fine-tuning, 70.6 + 30.6 = 101.2 s, cannot be
  # shortened; total / workers (160.8 / 8 = 20.1 s) would be far too low.
  assert price.wall_time(costs, 8) == pytest.approx(101.2)
  assert price.critical_path(costs) == pytest.approx(101.2)


def test_finished_cells_cost_nothing_and_their_dependants_may_start(costs):
  import dataclasses
  done = [dataclasses.replace(c, done=c.name == "unet-disp-objects-s0") for c in costs]
  # Left: 39.8 + 19.8 + 30.6 = 90.2 s; on two workers unet-sl's chain (59.6) beside 30.6.
  assert price.wall_time(done, 1) == pytest.approx(90.2)
  assert price.wall_time(done, 2) == pytest.approx(59.6)


def _record_row(m: gf.Measured) -> dict:
  records = [json.loads(line) for line in (REPO / m.source).read_text().splitlines() if line]
  rec = next(r for r in records if r["time"] == m.time)
  assert rec["commit"] == m.commit
  rows = [r for r in rec["rows"] if all(r.get(k) == v for k, v in m.row)]
  assert len(rows) == 1, (m, rows)
  return rows[0]


@pytest.mark.parametrize("m", gf.MEASURED, ids=lambda m: f"{m.gpu}-{m.net}-{m.what}")
def test_the_gpu_figures_agree_with_their_records(m):
  if m.source.endswith(".jsonl"):
    assert _record_row(m)[m.field] == m.raw
  else:  # the H100's PSMNet step: a row of docs/benchmarks/gpu.md's H100 table
    page = (REPO / m.source.split(" ")[0]).read_text()
    rows = [line for line in page.splitlines()
            if all(str(v) in line for _, v in m.row) and line.startswith("|")]
    assert len(rows) == 1, rows
    assert f"| {m.raw} |" in rows[0]
  expected = {("step", False): m.raw, ("step", True): 1 / m.raw, ("forward", False): m.raw / 4,
              ("start", False): m.raw}[(m.what, m.rate)]
  assert m.seconds == pytest.approx(expected)


def test_a_plan_its_out_calibrates_is_priced_with_its_calibration_first():
  """table2-v2 at the paper scale has no committed budgets: the dry run prices its calibration
  cells, then its cells at the long runs' epochs (an upper bound), each waiting for them."""
  plan, calibrating = price.plan_to_price("table2-v2", "paper", 3)
  calib = plans.calibration_plan("table2-v2", "paper")
  assert calibrating == len(calib.cells) > 0
  assert plan.cells[:calibrating] == calib.cells
  long_epochs = dict(plans.SCALES["paper"].v2.calib_epochs)
  for cell in plan.cells[calibrating:]:
    assert cell.config.epochs == long_epochs[plans.phase_of(cell)], cell.name
    assert set(cells.waits_for(cell)) >= {c.name for c in calib.cells}, cell.name
  text = price.dry_run(plan, "/nonexistent/out", 32, "h200", calibrating)
  assert "UPPER BOUND" in text and f"{calibrating} calibration cell(s)" in text
  assert "psmnet: 0.1077 s a training step (measured" in text
  assert "psmnet-mtl: 0.1424 s a training step (measured" in text
  assert "unet" not in text.split("| cell |")[0]
  assert price.plan_to_price("table1-v2", "smoke", 1)[1] == 0  # committed budgets: no calibration


def test_this_machine_without_finished_cells_is_unknown(tmp_path):
  text = price.dry_run(plans.build_plan("table1-v2", "smoke", 1), tmp_path / "out", 2)
  assert "no figure" in text and "bench_nets.py" in text and "Wall time on 2 worker(s): unknown" in text


def _tree(path: Path) -> dict[str, tuple[str, int]]:
  return {str(p.relative_to(path)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
          for p in sorted(path.rglob("*")) if p.is_file()} | {
          str(p.relative_to(path)) + "/": ("dir", 0) for p in path.rglob("*") if p.is_dir()}


def test_dry_run_writes_nothing(tmp_path, capsys):
  out = tmp_path / "absent"
  assert cli.main(["experiment", "run", "table1-v2", str(out), "--scale", "smoke",
                   "--dry-run", "--workers", "2"]) == 0
  assert not out.exists()
  # An OUT with a plan and a cell finished on this machine: priced from it, left as it was.
  out = tmp_path / "grid"
  plan = plans.build_plan("table1-v2", "smoke", 1)
  register(out, plan)
  cell_dir(out, "unet-sl-objects-s0").mkdir(parents=True)
  write_json(cell_dir(out, "unet-sl-objects-s0") / DONE_FILE,
             {"step": 30, "train_seconds": 60.0, "machine": machine.cpu_description()})
  before = _tree(out)
  capsys.readouterr()
  assert cli.main(["experiment", "run", "table1-v2", str(out), "--scale", "smoke",
                   "--dry-run"]) == 0
  text = capsys.readouterr().out
  assert "unet-sl: 2 s a training step (measured: 1 cell(s) finished here" in text
  assert "unet-disp: no figure" in text
  assert _tree(out) == before


def test_a_damaged_done_json_is_one_line_naming_it(tmp_path):
  out = tmp_path / "grid"
  register(out, plans.build_plan("table1-v2", "smoke", 1))
  cell_dir(out, "unet-sl-objects-s0").mkdir(parents=True)
  write_json(cell_dir(out, "unet-sl-objects-s0") / DONE_FILE,
             {"step": 30, "train_seconds": "x", "machine": machine.cpu_description()})
  with pytest.raises(SljaxError, match=r"unet-sl-objects-s0/done.json: not a record"):
    price.dry_run(plans.build_plan("table1-v2", "smoke", 1), out, 2)


def test_submit_dry_run_submits_nothing(tmp_path, monkeypatch, capsys):
  def refuse(*args, **kwargs):
    raise AssertionError("submitted")
  monkeypatch.setattr(submit, "submit_grid", refuse)
  monkeypatch.setattr(submit, "submit", refuse)
  monkeypatch.setattr(submit, "check_available", refuse)
  out = tmp_path / "out"
  assert cli.main(["experiment", "submit", "table2-v2", str(out), "--scale", "paper",
                   "--workers", "32", "--gpu", "h100", "--dry-run"]) == 0
  assert not out.exists()
  assert "Wall time on 32 worker(s): about" in capsys.readouterr().out
