"""sljax experiment: a smoke plan end to end, idempotence, exact continuation after kill -9,
the pairing of stl and the multi-task strategies, refusal of a changed plan."""

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest

from sljax import cli
from sljax.data.dataset import epoch_order
from sljax.errors import SljaxError
from sljax.experiment import records
from sljax.experiment.design import cells, plans
from sljax.experiment.report import build
from sljax.experiment.running import claims, runner, workers
from sljax.nets import build_model, detach_sl
from sljax.nets.model_config import init_variables
from sljax.runtime import machine
from sljax.train.feed import RowCache, batch_parts, open_source
from sljax.train.setup import setup

import toys


@pytest.fixture(scope="module")
def smoke_out(tmp_path_factory):
  """table1 at the smoke scale, one seed, run uninterrupted."""
  out = tmp_path_factory.mktemp("exp") / "out"
  assert cli.main(["experiment", "run", "table1", str(out), "--scale", "smoke", "--seeds", "1",
                   "--no-progress"]) == 0
  assert cli.main(["experiment", "report", str(out)]) == 0
  return out


def test_smoke_plan_runs_end_to_end_and_a_second_run_trains_nothing(smoke_out, capsys):
  plan = plans.build_plan("table1", "smoke", 1)
  for cell in plan.cells:
    wd = records.cell_dir(smoke_out, cell.name)
    assert (wd / records.DONE_FILE).exists()
    assert records.stored(wd / "eval" / "heldout.json") is not None  # SET.json.xz
    done = json.loads((wd / records.DONE_FILE).read_text())
    final = done["step"]
    assert done["machine"] == machine.cpu_description()  # a grid may span CPUs
    assert [p.name for p in (wd / "checkpoints").iterdir() if p.name.isdigit()] == [str(final)]
  # The tissue cells started from the objects cells' final checkpoints.
  cfg = json.loads((records.cell_dir(smoke_out, "unet-sl-tissue-ft-s0") / "config.json")
                   .read_text())
  assert cfg["init_from"].endswith("cells/unet-sl-objects-s0/checkpoints/30")
  assert cfg["domain"] == "tissue" and cfg["synth_t"] == 5
  # Smoke builds lax models (compiling sljax's kernels costs more than they save at 32 px), in
  # training and in scoring alike.
  assert cfg["conv_impl"] == "lax" and cfg["ynn"] == "on"
  cell = next(c for c in plan.cells if c.name == "unet-sl-tissue-ft-s0")
  assert runner._predictor(smoke_out, cell).model.conv_impl == "lax"
  md = (smoke_out / "report.md").read_text()
  assert "Table 1" in md and "unet-sl" in md and "figures/table1_bars.png" in md
  assert (smoke_out / "figures" / "table1_bars.png").stat().st_size > 1000
  capsys.readouterr()
  before = {p: p.stat().st_mtime_ns for p in smoke_out.rglob("*") if p.is_file()}
  assert cli.main(["experiment", "run", "table1", str(smoke_out), "--scale", "smoke",
                   "--seeds", "1", "--no-progress"]) == 0
  assert "trained 0 cell(s), scored 0 set(s)" in capsys.readouterr().out
  after = {p: p.stat().st_mtime_ns for p in smoke_out.rglob("*") if p.is_file()}
  changed = [p for p in before if after.get(p) != before[p] and p.name != records.PLAN_FILE]
  assert not changed, changed


_KILLED = textwrap.dedent("""
    import os, signal, sys
    from sljax.experiment.design import plans
    from sljax.experiment.running import runner
    from sljax.train import loop
    fetch = loop.fetch_metrics
    def fetch_then_die(ctx, pending, state):
      state, last = fetch(ctx, pending, state)
      if ctx.run.workdir.name == "unet-disp-objects-s0" and state.step >= 17:
        ctx.manager.wait_until_finished()  # resume from the checkpoint of step 15
        os.kill(os.getpid(), signal.SIGKILL)
      return state, last
    loop.fetch_metrics = fetch_then_die
    runner.run(plans.build_plan("table1", "smoke", 1), sys.argv[1], progress=False)
""")


def _without_times(report: str) -> str:
  """The report less its training-time table: wall time differs between two runs of the same
  cells (CI once saw 0.0 against 0.1 minutes), everything else must not."""
  kept, skipping = [], False
  for line in report.splitlines():
    if line.startswith("Training time per cell"):
      skipping = True
      kept.append("<training times>")
      continue
    if skipping and (not line.strip() or line.startswith("|")):
      continue
    skipping = False
    kept.append(line)
  return "\n".join(kept)


def test_killed_runner_continues_to_the_same_report(smoke_out, tmp_path):
  out = tmp_path / "out"
  proc = subprocess.run([sys.executable, "-c", _KILLED, str(out)], env=toys.same_device_env(),
                        capture_output=True,
                        text=True, timeout=600)
  assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
  killed = records.cell_dir(out, "unet-disp-objects-s0")
  assert not (killed / records.DONE_FILE).exists() and (killed / "checkpoints" / "15").is_dir()
  assert cli.main(["experiment", "run", "table1", str(out), "--scale", "smoke", "--seeds", "1",
                   "--no-progress"]) == 0
  assert cli.main(["experiment", "report", str(out)]) == 0
  for name in ("report.json", "report.md"):
    a = _without_times((smoke_out / name).read_text().replace(str(smoke_out), "OUT"))
    b = _without_times((out / name).read_text().replace(str(out), "OUT"))
    assert a == b, name


def test_changed_plan_under_an_existing_out_is_refused(smoke_out, capsys, tmp_path):
  out = tmp_path / "out"
  out.mkdir()
  record = json.loads((smoke_out / records.PLAN_FILE).read_text())
  record["cells"]["unet-sl-objects-s0"]["config"]["lr"] = 0.5
  (out / records.PLAN_FILE).write_text(json.dumps(record))
  code = cli.main(["experiment", "run", "table1", str(out), "--scale", "smoke", "--seeds", "1"])
  err = capsys.readouterr().err
  assert code == 2 and err.count("\n") == 1, err
  assert "cell unet-sl-objects-s0 was run with another configuration (config.lr: 0.5 -> 0.001)" \
      in err
  code = cli.main(["experiment", "run", "table1", str(smoke_out), "--scale", "cpu"])
  err = capsys.readouterr().err
  assert code == 2 and err.count("\n") == 1 and "another configuration" in err, err


def test_bad_plan_arguments(capsys, tmp_path):
  for argv, needle in ((["nope", "o"], "unknown plan 'nope'"),
                       (["table2", "o", "--scale", "huge"], "--scale huge"),
                       (["table2", "o", "--seeds", "0"], "--seeds 0"),
                       (["table2", "o", "--data", str(tmp_path / "none")], "does not exist"),
                       (["table2", "o", "--eval-data", str(tmp_path)], "--eval-data applies")):
    assert cli.main(["experiment", "run", *argv]) == 2
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1, err
  assert cli.main(["experiment", "report", str(tmp_path)]) == 2
  assert "not an experiment folder" in capsys.readouterr().err


@pytest.mark.parametrize("record", [{}, {"plans": [], "cells": {}},
                                    {"plans": {"table2": {"scale": "smoke"}}, "cells": {}}],
                         ids=["empty object", "plans a list", "no seeds"])
def test_foreign_plan_json_is_one_line_and_left_alone(record, capsys, tmp_path):
  # Another program's plan.json in OUT ended run, status and report in a KeyError traceback.
  path = tmp_path / records.PLAN_FILE
  path.write_text(json.dumps(record))
  for argv in (["run", "table2", str(tmp_path), "--scale", "smoke"], ["status", str(tmp_path)],
               ["report", str(tmp_path)]):
    assert cli.main(["experiment", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"sljax experiment: error: {path}: not an sljax experiment record ("), err
    assert err.count("\n") == 1, err
  assert json.loads(path.read_text()) == record and os.listdir(tmp_path) == [records.PLAN_FILE]


def test_stl_and_unc_are_paired_within_a_seed(tmp_path):
  """At one seed, stl and unc train on the same scenes, split, subset and order (batches
  identical in what they share), and start from equal disparity-path weights; seeds differ."""
  plan = plans.build_plan("table2", "smoke", 2)
  by = {(c.arm, c.factors, c.seed): c for c in plan.cells}
  small = (("data", "1/16"),)
  stl, unc = by["stl", small, 0], by["unc", small, 0]
  assert stl.config.net == "psmnet" and unc.config.net == "psmnet-mtl"
  runs = [setup(c.config, tmp_path / c.name, resume=False, overwrite=False,
                log=lambda line: None) for c in (stl, unc, by["stl", small, 1])]
  (tr_s, va_s), (tr_u, va_u), (tr_1, _) = [(r.train_idx, r.val_idx) for r in runs]
  assert tr_s == tr_u and va_s == va_u and tr_s != tr_1
  for epoch in range(3):
    assert epoch_order(tr_s, 0, epoch) == epoch_order(tr_u, 0, epoch)
  rows = [RowCache(open_source(c.config), c.config, batch_parts(c.config), False)
          .batch(epoch_order(tr_s, 0, 0)[:2]) for c in (stl, unc)]
  for part in ("left", "right", "disp"):
    np.testing.assert_array_equal(rows[0][part], rows[1][part])
  assert "sl" in rows[1] and "sl" not in rows[0]
  # Initial weights: everything stl has, unc has with equal values (the twin's extra SL path
  # aside); another seed differs.
  h, w = stl.config.size
  inits = [init_variables(build_model(c.config.net, maxdisp=c.config.maxdisp,
                                                  t=c.config.synth_t), c.config.seed, h, w, 3)
           for c in (stl, unc, by["stl", small, 1])]
  plain, twin, other = inits[0], detach_sl(inits[1]), inits[2]
  leaves = jax.tree.leaves_with_path(plain)
  assert len(leaves) == len(jax.tree.leaves(twin)) > 100
  for (path, a), b in zip(leaves, jax.tree.leaves(twin), strict=True):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=str(path))
  assert any(not np.array_equal(a, b) for a, b in zip(jax.tree.leaves(plain),
                                                      jax.tree.leaves(other)))


def test_every_plan_builds_at_every_scale():
  for name in plans.PLANS:
    for scale in plans.SCALES:
      try:
        plan = plans.build_plan(name, scale, 2)
      except SljaxError as e:
        if name in plans.V3_PLANS:  # v3: scales with a v3 design, and a regime for the tests
          design = plans.SCALES[scale].v3
          assert ("runs at" in str(e) if design is None else
                  "no regime yet" in str(e) if design.regime is None else
                  design.regime == plans.NO_REGIME and "found no" in str(e)), (name, scale, e)
          continue
        if name in plans.V4_PLANS:  # v4: scales with a v4 design only; the grid waits for
          design = plans.SCALES[scale].v4  # the regime and its committed number of seeds
          assert ("runs at" in str(e) if design is None else
                  name == plans.V4 and (
                      "no regime yet" in str(e) if design.regime is None else
                      "found no setting" in str(e) if design.regime == plans.NO_REGIME else
                      f"runs the {design.grid_seeds} seeds committed" in str(e))), (name, scale, e)
          continue
        if name == plans.V5 and plans.SCALES[scale].v5 is None:
          assert "runs at" in str(e), (name, scale, e)
          continue
        # a calibrated plan whose arms this scale has not calibrated yet: its calibration
        # cells run first in its OUT (calibrate.worker_plan)
        assert name in plans.CALIBRATED and "no calibrated budget" in str(e), (name, scale, e)
        assert plans.needs_calibration(name, scale), (name, scale)
        assert not plans.SCALES[scale].v2.budgets or scale == "cpu128" or name == plans.V5
        continue
      plans.check_unique(plan)
      assert len({c.seed for c in plan.cells}) == 2
      if scale != "paper":  # (the paper scale's 8000 scenes take long to split here)
        assert all(runner.cell_steps(c) > 0 for c in plan.cells), (name, scale)
  t2 = plans.build_plan("table2", "cpu", 3)
  assert len(t2.cells) == 30 and {c.arm for c in t2.cells} == set(
      ("stl", "cg_a", "cg_b", "epr", "unc"))
  fig7 = plans.build_plan("fig7", "cpu", 1)
  shared = {c.name for c in fig7.cells} & {c.name for c in t2.cells}
  assert len(shared) == 5  # fig7 fine-tunes table2's full-data cells, it does not retrain them
  t3 = plans.build_plan("table3", "cpu", 1)
  assert {c.name for c in t3.cells} <= {c.name for c in t2.cells}
  assert {e.name for e in t3.cells[0].evals} == {"heldout", "tissue"}


def test_report_of_partial_results_lists_the_missing(tmp_path):
  out = tmp_path / "out"
  records.register(out, plans.build_plan("table2", "smoke", 1))
  path = build.write_report(out)
  md = path.read_text()
  assert "0 of 10 cells trained" in md and "Not scored yet" in md
  assert "no results yet" in md


def test_v2_plan_reuses_the_v1_cells_and_scores_them_on_the_fixed_test_sets(smoke_out, tmp_path,
                                                                           capsys):
  """table1-v2 at the smoke scale trains exactly as table1: run into a copy of table1's OUT it
  trains nothing, chooses unet-sl's window on validation and scores the fixed test sets."""
  out = tmp_path / "out"
  shutil.copytree(smoke_out, out)
  capsys.readouterr()
  assert cli.main(["experiment", "run", "table1-v2", str(out), "--scale", "smoke", "--seeds",
                   "1", "--no-progress"]) == 0
  assert "trained 0 cell(s), scored 4 set(s)" in capsys.readouterr().out
  for cell in plans.build_plan("table1-v2", "smoke", 1).cells:
    wd = records.cell_dir(out, cell.name)
    (evalset,) = cell.evals
    rep = records.read_json(wd / "eval" / f"{evalset.name}.json")
    assert rep["n_scenes"] == 20 and rep["dataset_seed"] == cells.TEST_SEED
    if cell.arm == "unet-sl":
      windows = json.loads((wd / "eval" / records.WINDOWS_FILE).read_text())
      maes = windows["validation_mae"]
      assert windows["chosen"] == min((3, 5), key=lambda w: (maes[str(w)], w))
      assert rep["corr_window"] == windows["chosen"]
      assert rep["pooled"]["patterns_left"]["pattern_acc"] > 0
  assert cli.main(["experiment", "report", str(out)]) == 0
  md = (out / "report.md").read_text()
  assert "(v2: fixed test sets)" in md and "Holm p" in md and "corr window" in md


def _claims(out, cell):
  """The records of a cell's claim files, in order."""
  return [json.loads(p.read_text())
          for p in sorted(claims.claims_dir(out, cell).glob("[0-9]*.json"))]


def _same_cells(a, b, plan):
  """Every cell of b trained as in a: metrics rows bit for bit, steps, scores."""
  for cell in plan.cells:
    wa, wb = records.cell_dir(a, cell.name), records.cell_dir(b, cell.name)
    assert (wa / "metrics.jsonl").read_text() == (wb / "metrics.jsonl").read_text(), cell.name
    assert (json.loads((wa / records.DONE_FILE).read_text())["step"]
            == json.loads((wb / records.DONE_FILE).read_text())["step"])
    ra, rb = (records.read_json(w / "eval" / "heldout.json")["pooled"] for w in (wa, wb))
    assert ra == rb, cell.name


def test_three_submitit_local_workers_train_each_cell_once_as_one_runner(smoke_out, tmp_path,
                                                                         capsys):
  """`experiment submit --local --workers 3`: three worker processes on one OUT train every
  cell exactly once, to the records of one runner; status and report follow."""
  toys.need_submitit()
  out = tmp_path / "out"
  capsys.readouterr()
  assert cli.main(["experiment", "submit", "table1", str(out), "--scale", "smoke", "--seeds",
                   "1", "--workers", "3", "--local", "--wait", "--lease", "5"]) == 0
  text = capsys.readouterr().out
  assert text.startswith(f"started 3 local worker(s) on {out} through submitit's local "), text
  assert text.count("ended: exit code 0") == 3, text
  assert f"follow with: sljax experiment status {out}" in text
  logs = [Path(line.split(" log ")[1].split(",")[0]) for line in text.splitlines()
          if line.startswith("  job ") and " log " in line]
  assert len(logs) == 3 and all(log.exists() for log in logs)
  trained = sum(int(l.split("trained ")[1].split(" ")[0]) for log in logs
                for l in log.read_text().splitlines() if l.startswith("table1: trained"))
  assert trained == 4  # each cell once, whichever worker
  plan = plans.build_plan("table1", "smoke", 1)
  for cell in plan.cells:
    claims = _claims(out, cell.name)
    # Claim, release, in turn; one worker trained and scored it ("finished"), any other claim
    # found it finished (a worker may claim between another's last write and its release).
    assert [c["kind"] for c in claims] == ["claim", "release"] * (len(claims) // 2), claims
    whys = [c["why"] for c in claims[1::2]]
    assert whys.count("finished") == 1 and set(whys) <= {"finished", "finished by another "
                                                         "worker"}, whys
    assert all(c["took_over"] is None for c in claims[::2])
  _same_cells(smoke_out, out, plan)
  assert cli.main(["experiment", "status", str(out)]) == 0
  status = capsys.readouterr().out
  assert status.startswith("table1 (scale smoke, seed 0): 4 finished of 4 cells"), status
  assert "held by" not in status and "Workers:" not in status and "No worker" not in status
  assert cli.main(["experiment", "report", str(out)]) == 0
  a = _without_times((smoke_out / "report.md").read_text().replace(str(smoke_out), "OUT"))
  b = _without_times((out / "report.md").read_text().replace(str(out), "OUT"))
  assert a == b


# The killed runner above as a worker with a 2 s lease (its host is set by the caller).
_KILLED_ELSEWHERE = _KILLED.replace("progress=False)", "progress=False, lease=2)")


def test_a_killed_workers_cell_is_finished_by_another_after_the_lease(smoke_out, tmp_path,
                                                                      monkeypatch):
  """kill -9 of a worker "on another host" mid-cell: a second worker waits (the cell fine-tuned
  from it is left), takes the cell over once the lease is over, and finishes it with the rows
  of the uninterrupted run."""
  out = tmp_path / "out"
  env = dict(toys.same_device_env(), SLJAX_WORKER_HOST="host-a")
  proc = subprocess.run([sys.executable, "-c", _KILLED_ELSEWHERE, str(out)], env=env,
                        capture_output=True, text=True, timeout=600)
  assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
  killed = "unet-disp-objects-s0"
  assert _claims(out, killed)[-1]["host"] == "host-a"
  slept = []
  real_sleep = runner.time.sleep

  def sleep(seconds):  # a lease that never expires would wait here for ever
    slept.append(seconds)
    assert sum(slept) < 30, "waited 30 s for a lease of 2 s"
    real_sleep(seconds)
  monkeypatch.setattr(runner.time, "sleep", sleep)
  lines = []
  res = runner.run(plans.build_plan("table1", "smoke", 1), out, progress=False,
                   log=lines.append, lease=2.0)
  assert res["trained"] == 2 and not res["left"] and slept  # it waited for the lease
  claims = _claims(out, killed)
  assert [c["host"] for c in claims] == ["host-a", workers.host_name(), workers.host_name()]
  assert "over its 2 s lease" in claims[1]["took_over"] and claims[2]["why"] == "finished"
  log = (records.cell_dir(out, killed) / records.LOG_FILE).read_text()
  assert "resuming from step 15" in log
  _same_cells(smoke_out, out, plans.build_plan("table1", "smoke", 1))


_TERMINATED = textwrap.dedent("""
    import os, signal, sys
    from sljax.experiment.design import plans
    from sljax.experiment.running import runner
    from sljax.train import loop
    fetch = loop.fetch_metrics
    def term_then_fetch(ctx, pending, state):
      if pending and pending[-1][0] == 25:  # a fetch mid-epoch (epochs of 15 steps)
        os.kill(os.getpid(), signal.SIGTERM)
      return fetch(ctx, pending, state)
    loop.fetch_metrics = term_then_fetch
    res = runner.run(plans.build_plan("table1", "smoke", 1), sys.argv[1], progress=False)
    sys.exit(128 + signal.SIGTERM if res["stopped"] == "SIGTERM" else 1)
""")


def test_sigterm_mid_cell_saves_its_step_and_releases_the_cell(smoke_out, tmp_path):
  """A real worker gets SIGTERM mid-epoch: it stops after that step, saves a checkpoint there
  (beside the epoch's) and releases its claim with the step it reached."""
  out = tmp_path / "out"
  proc = subprocess.run([sys.executable, "-c", _TERMINATED, str(out)],
                        env=toys.same_device_env(), capture_output=True, text=True, timeout=600)
  assert proc.returncode == 128 + signal.SIGTERM, proc.stderr[-2000:]
  assert "SIGTERM: stopping after this step" in proc.stderr
  cell = "unet-sl-objects-s0"
  wd = records.cell_dir(out, cell)
  assert {p.name for p in (wd / "checkpoints").iterdir() if p.name.isdigit()} == {"15", "25"}
  assert not (wd / records.DONE_FILE).exists()
  (claim, release) = _claims(out, cell)
  assert release["why"] == "stopped by SIGTERM" and release["step"] == 25
  rows = (wd / "metrics.jsonl").read_text().splitlines()
  assert rows == (records.cell_dir(smoke_out, cell) / "metrics.jsonl").read_text().splitlines()[:25]


def test_a_cell_scored_on_its_best_checkpoint_keeps_it(tmp_path):
  """v3 scores the best checkpoint by validation too: the finished cell keeps its final and its
  best checkpoint (the lowest validation MAE of epochs.jsonl) and scores each."""
  import dataclasses
  sc = plans.SCALES["smoke"]
  base = plans.build_plan("table1", "smoke", 1).cells[0]  # unet-sl on objects: compiled above
  config = dataclasses.replace(base.config, model="unet-disp", epochs=4, val_every=1)
  evals = (cells.test_set("objects", sc), cells.test_set("objects", sc, "best"))
  cell = dataclasses.replace(base, name="unet-disp-best-s0", arm="unet-disp", config=config,
                             evals=evals, windows=())
  plan = cells.Plan("v3", sc, (0,), (cell,), "unet-disp")
  runner.run(plan, tmp_path, progress=False, log=lambda line: None)
  wd = records.cell_dir(tmp_path, cell.name)
  done = json.loads((wd / records.DONE_FILE).read_text())
  rows = [json.loads(l) for l in (wd / "epochs.jsonl").read_text().splitlines()]
  spe = done["step"] // 4
  best = min(rows, key=lambda r: r["val_mae"])
  assert done["best_step"] == best["epoch"] * spe
  kept = {int(p.name) for p in (wd / "checkpoints").iterdir() if p.name.isdigit()}
  assert kept == {done["step"], done["best_step"]}
  final = records.read_json(wd / "eval" / "test-objects.json")
  at_best = records.read_json(wd / "eval" / "test-objects-best.json")
  assert at_best["checkpoint"] == "best by validation MAE"
  assert "checkpoint" not in final
  if done["best_step"] == done["step"]:
    assert at_best["pooled"]["full"]["mae"] == final["pooled"]["full"]["mae"]
  with pytest.raises(SljaxError, match="kept no best checkpoint"):
    (wd / records.DONE_FILE).write_text(json.dumps(dict(done, best_step=None)))
    records.final_checkpoint(tmp_path, cell.name, "best")


def test_a_cell_validated_by_steps_fine_tunes_and_keeps_its_best(tmp_path):
  """v4's cells: a pretraining by steps, then a fine-tuning by steps from its final checkpoint,
  scored on its final and its best checkpoint (the lowest MAE of validation.jsonl)."""
  import dataclasses
  sc = plans.SCALES["smoke"]
  base = plans.build_plan("table1", "smoke", 1).cells[0]  # unet-sl on objects: compiled above
  pre_config = dataclasses.replace(base.config, model="unet-disp", steps=6, val_every_steps=2)
  pre = dataclasses.replace(base, name="unet-disp-pre-s0", arm="unet-disp", config=pre_config,
                            evals=(), windows=())
  ft_config = dataclasses.replace(pre_config, domain="tissue", synth_n=sc.tissue_n, lr=1e-4,
                                  steps=4)
  evals = (cells.test_set("tissue", sc), cells.test_set("tissue", sc, "best"))
  ft = dataclasses.replace(pre, name="unet-disp-ft-s0", config=ft_config, init_cell=pre.name,
                           evals=evals)
  plan = cells.Plan("v4", sc, (0,), (pre, ft), "unet-disp")
  runner.run(plan, tmp_path, progress=False, log=lambda line: None)
  wd = records.cell_dir(tmp_path, ft.name)
  done = json.loads((wd / records.DONE_FILE).read_text())
  assert json.loads((wd / "config.json").read_text())["init_from"] == str(
      records.final_checkpoint(tmp_path, pre.name))
  rows = [json.loads(l) for l in (wd / "validation.jsonl").read_text().splitlines()]
  assert [r["step"] for r in rows] == [2, 4] and done["step"] == 4
  assert records.curve(tmp_path, ft.name) == [(r["step"], r["val_mae"]) for r in rows]
  best = min(rows, key=lambda r: (r["val_mae"], r["step"]))
  assert done["best_step"] == best["step"]
  kept = {int(p.name) for p in (wd / "checkpoints").iterdir() if p.name.isdigit()}
  assert kept == {done["step"], done["best_step"]}
  assert {p.name for p in (wd / "eval").iterdir()} >= {"test-tissue.json.xz",
                                                       "test-tissue-best.json.xz"}
