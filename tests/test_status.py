"""`sljax experiment status`: cell states read off the runner's files, minutes per arm, and the
time left, checked on a hand-made experiment folder against hand-computed estimates."""

import json
import os
import time

import pytest

from sljax import cli
from sljax.experiment import records
from sljax.experiment.design import plans
from sljax.experiment.running import claims, status, workers

X, Y = "CPU X", "CPU Y"


def _done(out, name, seconds, machine, scored=True, evals=("heldout",)):
  wd = records.cell_dir(out, name)
  (wd / records.EVAL_DIR).mkdir(parents=True)
  records.write_json(wd / records.DONE_FILE, {"step": 4, "train_seconds": seconds,
                                            "machine": machine})
  if scored:
    for e in evals:
      records.write_json(wd / records.EVAL_DIR / f"{e}.json", {"pooled": {}})


def _training(out, name, epoch):
  wd = records.cell_dir(out, name)
  wd.mkdir(parents=True)
  lines = [json.dumps({"epoch": k, "loss": 1.0}) for k in range(1, epoch + 1)]
  (wd / "epochs.jsonl").write_text("\n".join(lines) + "\n{\"epoch\": ", encoding="utf-8")


@pytest.fixture
def grid(tmp_path):
  """table2 at the smoke scale (2 epochs a cell), 3 seeds, in every state."""
  out = tmp_path / "grid"
  records.register(out, plans.build_plan("table2", "smoke", 2))  # the target is passed later
  _done(out, "psmnet-stl-objects-s0", 600.0, X)
  _done(out, "psmnet-stl-objects-s1", 1200.0, Y)
  _training(out, "psmnet-stl-objects-s2", 1)          # half its 2 epochs
  _done(out, "psmnet-unc-objects-s0", 300.0, X, scored=False)
  return out


def test_states_and_time_left_by_hand(grid):
  plan = plans.build_plan("table2", "smoke", 3)
  states = {s.cell.name: s for s in status.plan_status(grid, plan)}
  assert states["psmnet-stl-objects-s0"].state == status.DONE
  assert states["psmnet-stl-objects-s2"].state == status.TRAINING
  assert states["psmnet-stl-objects-s2"].epoch == 1   # the half-written line is not an epoch
  assert states["psmnet-unc-objects-s0"].state == status.SCORING
  assert states["psmnet-cg_a-objects-s0"].state == status.WAITING
  all_states = list(states.values())
  # stl/all on CPU X: its own mean (600 s) for s2's remaining half; other groups: unc/all's
  # 300 s for its 3 cells (s0 is trained), every other group has no finished cell.
  left, unknown = status.seconds_left(all_states, X)
  assert left == pytest.approx(600 * 0.5 + 300 * 2)
  assert unknown == 30 - 4 - 2  # 30 cells; 4 with files; unc s1, s2 estimated
  # On a third CPU: every finished stl cell counts, mean (600 + 1200) / 2.
  left_z, _ = status.seconds_left(all_states, "CPU Z")
  assert left_z == pytest.approx(900 * 0.5 + 300 * 2)


def test_the_table_and_the_command(grid, capsys, monkeypatch):
  monkeypatch.setattr(status.machine, "cpu_description", lambda: X)
  assert cli.main(["experiment", "status", str(grid), "--seeds", "3"]) == 0
  text = capsys.readouterr().out
  assert text.startswith("table2 (scale smoke, seeds 0-2): 2 finished, 1 trained, not scored, "
                         "1 training, 26 waiting of 30 cells")
  assert "  training: psmnet-stl-objects-s2, epoch 1 of 2" in text
  assert "| stl | all | 2 of 3 | 0, 1 | 10.0 (10.0-10.0) | 20.0-20.0 |" in text
  assert "| unc | all | 0 of 3 | - | 5.0 (5.0-5.0) | - |" in text
  assert "Cells trained on: CPU X (2); CPU Y (1)" in text
  assert "Training left: about 15 min, at this CPU's pace" in text
  assert "24 cell(s) of arms with no finished cell not counted" in text


def test_not_an_experiment_folder_is_one_line(tmp_path, capsys):
  assert cli.main(["experiment", "status", str(tmp_path)]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and "no plan.json" in err[0] and str(tmp_path) in err[0]


def test_edge_cases_of_the_files(grid):
  plan = plans.build_plan("table2", "smoke", 2)
  wd = records.cell_dir(grid, "psmnet-cg_a-objects-s0")
  (wd / "checkpoints").mkdir(parents=True)            # started, no epoch logged yet
  (wd / "epochs.jsonl").write_text("", encoding="utf-8")
  s = status.cell_state(grid, plan.cells[1])
  assert (s.cell.name, s.state, s.epoch) == ("psmnet-cg_a-objects-s0", status.TRAINING, 0)
  (wd / "epochs.jsonl").write_text("null\n", encoding="utf-8")  # not an object: not an epoch
  assert status.cell_state(grid, plan.cells[1]).epoch == 0
  _done(grid, "psmnet-cg_b-objects-s0", None, X)      # done.json without its seconds
  s = status.cell_state(grid, plan.cells[2])
  assert s.state == status.DONE and s.seconds is None
  assert "| cg_b | all | 1 of 2 | 0 | - | - |" in status.grid_status(grid)


def test_fewer_seeds_than_were_run_keep_every_cell(grid, capsys):
  records.register(grid, plans.build_plan("table2", "smoke", 3))
  assert len(records.registered_plans(grid, 1)[0].cells) == 30  # never shrinks the plan
  assert len(records.registered_plans(grid, 4)[0].cells) == 40
  assert cli.main(["experiment", "status", str(grid), "--seeds", "0"]) == 2
  assert "--seeds 0: at least 1" in capsys.readouterr().err


def test_says_who_holds_which_cell_since_when_and_its_last_step(grid, capsys):
  # After a dropped connection the files alone cannot tell a running grid from a stopped one.
  assert cli.main(["experiment", "status", str(grid), "--seeds", "3"]) == 0
  text = capsys.readouterr().out
  assert text.endswith("\n\nNo worker holds a cell now: run `sljax experiment run` (or "
                       "`submit`) again to go on (finished cells are kept; a cell in training "
                       "continues from its last checkpoint).\n"), text[-300:]
  # A worker of an array job on another node trains stl s2 (step 7), another is starting
  # cg_a s0 and has missed its heartbeats.
  since = time.mktime((2026, 11, 27, 9, 30, 0, 0, 0, -1))
  for cell, host, job, step, age in (("psmnet-stl-objects-s2", "node-7", "123_4", 7, 0),
                                     ("psmnet-cg_a-objects-s0", "node-9", "123_5", 0, 250)):
    path = claims.claim_path(grid, cell, 0)
    assert claims.create_exclusive(path, dict(token=job, host=host, pid=4242, started=None,
                                              job=job, lease=300.0, since=since,
                                              kind=claims.CLAIM))
    claims.beat_path(path).write_text(json.dumps({"step": step, "token": job}))
    t = time.time() - age
    os.utime(claims.beat_path(path), (t, t))
  me = workers.Worker(grid, workers.identity(300.0), log_path="/logs/123_4_0_log.out")
  with me:
    assert cli.main(["experiment", "status", str(grid), "--seeds", "3"]) == 0
    text = capsys.readouterr().out
  assert ("  training: psmnet-stl-objects-s2, epoch 1 of 2; held by node-7 pid 4242, job 123_4 "
          "since 2026-11-27 09:30, last step 7, heartbeat 0 s ago\n") in text, text
  assert ("  starting: psmnet-cg_a-objects-s0; held by node-9 pid 4242, job 123_5 since "
          "2026-11-27 09:30, last step 0, heartbeat 250 s ago (late: its worker may be gone; "
          "the lease decides)\n") in text, text
  assert f"\n\nWorkers: {me.me.name} since " in text
  assert ", log /logs/123_4_0_log.out" in text and "No worker holds" not in text
  plan = plans.build_plan("table2", "smoke", 2)  # the seeds registered
  for cell in plan.cells:  # every cell finished: nothing to say about workers
    if not (records.cell_dir(grid, cell.name) / records.DONE_FILE).exists():
      _done(grid, cell.name, 60.0, X)
    records.write_json(records.cell_dir(grid, cell.name) / records.EVAL_DIR / "heldout.json", {})
    claims.create_exclusive(claims.claim_path(grid, cell.name, 1), {"kind": claims.RELEASE})
  assert cli.main(["experiment", "status", str(grid)]) == 0
  text = capsys.readouterr().out
  assert "held by" not in text and "No worker" not in text and "Workers" not in text


def test_cells_budgeted_in_steps_are_estimated_at_the_arms_seconds_a_step(tmp_path):
  """The v4 pilot at the cpu scale: one from-scratch cell finished (2,700 steps in 2,700 s on
  this CPU, 1 s a step): every other stl cell, of any setting, counts its steps at 1 s; the
  fine-tuning cells' own group has no finished cell."""
  plan = plans.build_plan("v4-pilot", "cpu", 2)
  out = tmp_path / "v4"
  records.register(out, plan)
  first = plan.cells[0]
  _done(out, first.name, 2700.0, X, evals=())
  states = status.plan_status(out, plan)
  left, unknown = status.seconds_left(states, X)
  assert unknown == 0
  assert left == pytest.approx(sum(c.config.steps for c in plan.cells[1:]) * 1.0)
  # Another finished cell of the same group as a waiting one: that group's own mean wins.
  _done(out, plan.cells[1].name, 5400.0, X, evals=())  # 2 s a step in the 1/64 group
  states = status.plan_status(out, plan)
  left, _ = status.seconds_left(states, X)
  per_step = (1.0 + 2.0) / 2
  twin_1_64 = next(c for c in plan.cells[2:] if c.factors == plan.cells[1].factors)
  twin_1_32 = next(c for c in plan.cells[2:] if c.factors == plan.cells[0].factors)
  rest = [c for c in plan.cells[2:] if c not in (twin_1_64, twin_1_32)]
  assert left == pytest.approx(5400.0 + 2700.0 + per_step * sum(c.config.steps for c in rest))
