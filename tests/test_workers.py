"""Workers sharing one experiment folder (sljax.experiment.running.workers): claims made at the same
instant by several processes never overlap, a dead worker's claim is taken over (its pid gone,
its lease over, an earlier run of its job) and a live one's is not, a superseded holder gives
its cell up, a fine-tuning cell never starts before its base, and the SLURM parameters that
`experiment submit` builds from its command line. No training here: tests/test_experiment.py
runs real workers on a smoke grid."""

import json
import multiprocessing
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from sljax import cli
from sljax.errors import SljaxError
from sljax.experiment import records
from sljax.experiment.design import plans
from sljax.experiment.running import claims, runner, submit, workers

import claim_race
import toys


ROUNDS, PROCESSES = 20, 4


def test_workers_started_at_the_same_instant_never_claim_the_same_cell(tmp_path):
  cells = [f"cell-{k}" for k in range(12)]
  ctx = multiprocessing.get_context("spawn")
  barrier, results = ctx.Barrier(PROCESSES), ctx.Queue()
  procs = [ctx.Process(target=claim_race.claim_all,
                       args=(str(tmp_path), cells, barrier, k, results, ROUNDS))
           for k in range(PROCESSES)]
  for p in procs:
    p.start()
  won = [results.get(timeout=120) for _ in range(ROUNDS * PROCESSES)]
  for p in procs:
    p.join(timeout=60)
  assert sum(bool(c) for _, c in won) >= 2  # they did contend
  for round_ in range(ROUNDS):
    claimed = [cell for r, cells_won in won if r == round_ for cell in cells_won]
    assert sorted(claimed) == sorted(cells), (round_, won)  # each cell exactly once
    for cell in cells:  # one claim file each, the winner's
      folder = claims.claims_dir(tmp_path / f"round{round_}", cell)
      assert [p.name for p in folder.glob("*.json")] == ["0000.json"]


def _claim(out: Path, host: str, job: str | None = None, lease: float = 2.0,
           pid: int = 1) -> Path:
  """A claim of cell "c" as another worker's."""
  path = claims.claim_path(out, "c", claims.top(out, "c").number + 1)
  record = dict(token="other", host=host, pid=pid, started=None, job=job, lease=lease,
                since=time.time(), kind=claims.CLAIM)
  assert claims.create_exclusive(path, record)
  return path


def _backdate(path: Path, seconds: float) -> None:
  t = time.time() - seconds
  os.utime(path, (t, t))


@pytest.fixture
def me(tmp_path):
  """A worker under tmp_path on this host, lease 2 s."""
  with workers.Worker(tmp_path, workers.identity(lease=2.0)) as worker:
    yield worker


def test_a_claim_on_another_host_is_taken_over_after_its_lease_only(tmp_path, me):
  claim = _claim(tmp_path, "elsewhere")
  assert not me.claim("c")              # fresh heartbeat: held
  _backdate(claim, 1.5)
  assert not me.claim("c")              # late, within its lease: still held
  assert workers.late_holders(tmp_path, ["c"], me.clock()) == ["c"]
  _backdate(claim, 2.5)
  assert me.claim("c")                  # over the lease: taken over, the next number
  rec = claims.read_claim(claims.claim_path(tmp_path, "c", 1))
  assert rec["token"] == me.me.token and "over its 2 s lease" in rec["took_over"]
  assert claims.top(tmp_path, "c").record["token"] == me.me.token


def test_a_heartbeat_keeps_a_claim_and_a_dead_pid_loses_it_at_once(tmp_path, me):
  claim = _claim(tmp_path, "elsewhere")
  _backdate(claim, 10)
  claims.beat_path(claim).write_text("{}")  # the holder's heartbeat file renewed just now
  assert not me.claim("c")
  # This host: a pid that ended is gone at once, whatever its heartbeat; a live one is not.
  proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
  try:
    live = tmp_path / "live"
    path = claims.claim_path(live, "c", 0)
    claims.create_exclusive(path, dict(token="t", host=workers.host_name(), pid=proc.pid,
                                       started=workers.process_started(proc.pid),
                                       job=None, lease=2.0, since=0, kind=claims.CLAIM))
    _backdate(path, 100)
    with workers.Worker(live, workers.identity(2.0)) as other:
      assert not other.claim("c")
      proc.kill()
      proc.wait()
      assert other.claim("c")
      assert "has ended" in claims.read_claim(claims.claim_path(live, "c", 1))["took_over"]
  finally:
    proc.kill()


def test_an_earlier_run_of_the_same_job_is_gone(tmp_path, monkeypatch):
  monkeypatch.setenv("SLURM_ARRAY_JOB_ID", "77")
  monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "3")
  _claim(tmp_path, "node-a", job="77_3", lease=300)  # before the requeue, on another node
  with workers.Worker(tmp_path, workers.identity(300)) as worker:
    assert worker.me.job == "77_3" and worker.claim("c")
  _claim(tmp_path, "node-b", job="77_4", lease=300)  # another task of the array: held
  with workers.Worker(tmp_path, workers.identity(300)) as worker:
    assert not worker.claim("c")


def test_a_superseded_holder_gives_its_cell_up_and_release_lets_the_next_claim(tmp_path):
  with workers.Worker(tmp_path, workers.identity(2.0)) as a:
    assert a.claim("c")
    a.progress(7)
    a._renew()  # pylint: disable=protected-access
    assert workers.holders(tmp_path, ["c"])["c"][1] == 7
    # Another host took it over (this worker stalled past its lease).
    _claim(tmp_path, "elsewhere", lease=2.0)
    a._renew()  # pylint: disable=protected-access
    assert a.lost
    a.release("finished")               # not its claim any more: nothing written
    assert claims.top(tmp_path, "c").record["host"] == "elsewhere"
  with workers.Worker(tmp_path / "b", workers.identity(2.0)) as b:
    assert b.claim("c")
    b.release("stopped by SIGTERM")
    top = claims.top(tmp_path / "b", "c")
    assert top.number == 1 and top.record["why"] == "stopped by SIGTERM" and not top.held
    assert b.claim("c") and claims.top(tmp_path / "b", "c").number == 2


def test_a_foreign_claim_file_is_one_line(tmp_path, me):
  path = claims.claim_path(tmp_path, "c", 0)
  path.parent.mkdir(parents=True)
  path.write_text("hello")
  with pytest.raises(SljaxError, match=f"{path}: not an sljax claim"):
    me.claim("c")


def _fake_cells(out, started, lock):
  """train_cell and evaluate_cell stand-ins that record when each cell trained."""
  def train_cell(out_, cell, bar, weight, on_step=lambda s: None, stop=None):
    with lock:
      started.append((cell.name, "start", time.monotonic()))
    if cell.init_cell is not None:
      records.final_checkpoint(out_, cell.init_cell)  # the base must be done
    time.sleep(0.3)
    on_step(1)
    done = {"step": 1}
    records.cell_dir(out_, cell.name).mkdir(parents=True, exist_ok=True)
    records.write_json(records.cell_dir(out_, cell.name) / records.DONE_FILE, done)
    with lock:
      started.append((cell.name, "end", time.monotonic()))
    return done

  def evaluate_cell(out_, cell, evalset):
    path = records.cell_dir(out_, cell.name) / records.EVAL_DIR / f"{evalset.name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    records.write_json(path, {"pooled": {}})
    return {"pooled": {}}
  return train_cell, evaluate_cell


def test_a_fine_tuning_cell_never_starts_before_its_base(tmp_path, monkeypatch):
  """Three workers (threads) on table1's two bases and two fine-tuning cells: each cell trains
  once, every fine-tuning cell after its base ended, and the idle workers wait for it."""
  out = tmp_path / "out"
  plan = plans.build_plan("table1", "smoke", 1)
  events, lock = [], threading.Lock()
  train_cell, evaluate_cell = _fake_cells(out, events, lock)
  monkeypatch.setattr(runner, "train_cell", train_cell)
  monkeypatch.setattr(runner, "evaluate_cell", evaluate_cell)
  results = []
  threads = [threading.Thread(target=lambda: results.append(runner.run(
      plan, out, progress=False, log=lambda line: None, lease=2.0, poll=0.05)))
             for _ in range(3)]
  for t in threads:
    t.start()
  for t in threads:
    t.join(timeout=60)
  assert len(results) == 3 and sum(r["trained"] for r in results) == 4
  when = {(name, what): t for name, what, t in events}
  assert len(when) == len(events) == 8  # each cell started and ended once
  for cell in plan.cells:
    if cell.init_cell is not None:
      assert when[cell.name, "start"] >= when[cell.init_cell, "end"], cell.name


def test_a_worker_with_another_plan_is_refused_in_one_line(tmp_path, capsys):
  out = tmp_path / "out"
  records.register(out, plans.build_plan("table1", "smoke", 1))
  with workers.Worker(out, workers.identity(2.0)) as other:  # a live worker holds a cell
    assert other.claim("unet-sl-objects-s0")
    assert cli.main(["experiment", "run", "table1", str(out), "--scale", "cpu",
                     "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "another configuration" in err and str(out) in err, err
    record = json.loads((out / records.PLAN_FILE).read_text())
    assert record["plans"]["table1"]["scale"] == "smoke"  # the plan stays as written once
    assert [p.name for p in (out / workers.WORKERS_DIR).iterdir()] == [other.file.name]


_FAKE_SBATCH = """#!/bin/sh
cp "$1" "$(dirname "$0")/submitted.sh"
echo "Submitted batch job 4242"
"""


@pytest.fixture
def fake_slurm(tmp_path, monkeypatch):
  """sbatch and srun stand-ins first on PATH (sbatch keeps the script it is given in
  submitted.sh beside itself); their folder."""
  bin_ = tmp_path / "bin"
  bin_.mkdir()
  (bin_ / "sbatch").write_text(_FAKE_SBATCH)
  (bin_ / "srun").write_text("#!/bin/sh\nexit 1\n")
  for tool in ("sbatch", "srun"):
    (bin_ / tool).chmod(0o755)
  monkeypatch.setenv("PATH", f"{bin_}:{os.environ['PATH']}")
  return bin_


def test_the_slurm_job_array_from_a_command_line(tmp_path, capsys, fake_slurm):
  """`experiment submit` on a SLURM login node, with sbatch and srun stand-ins on PATH: the
  job script submitit gives sbatch for the command line's options, the array, the job id,
  the logs. Not run on a real SLURM cluster here."""
  toys.need_submitit()
  bin_ = fake_slurm
  out = tmp_path / "out"
  assert cli.main(["experiment", "submit", "table1", str(out), "--scale", "smoke", "--workers",
                   "32", "--partition", "gpu-preempt", "--gpus-per-worker", "1",
                   "--cpus-per-worker", "8", "--time", "1-02:30:00", "--account", "lab42",
                   "--sbatch", "qos=low", "--sbatch", "constraint=h100", "--sbatch",
                   "exclusive", "--setup", "module load cuda", "--lease", "600"]) == 0
  text = capsys.readouterr().out.splitlines()
  logs = f"{out.absolute()}/submitit/4242_<task>/4242_<task>_0_log.out"
  assert text == [f"submitted job 4242: an array of 32 worker(s) on {out}",
                  f"  logs: {logs} (and .err beside it), task 0 to 31",
                  f"follow with: sljax experiment status {out}; squeue -j 4242; tail -f {logs}"]
  script = (bin_ / "submitted.sh").read_text().splitlines()
  for line in ("#SBATCH --partition=gpu-preempt", "#SBATCH --gpus-per-node=1",
               "#SBATCH --cpus-per-task=8", "#SBATCH --time=1590", "#SBATCH --account=lab42",
               "#SBATCH --array=0-31%32", "#SBATCH --signal=USR2@120", "#SBATCH --requeue",
               "#SBATCH --qos=low", "#SBATCH --constraint=h100", "#SBATCH --exclusive",
               "#SBATCH --job-name=sljax-table1", "#SBATCH --nodes=1",
               "#SBATCH --ntasks-per-node=1", "module load cuda"):
    assert line in script, (line, script)
  assert any(l.startswith("srun ") and "submitit.core._submit" in l for l in script), script
  # Each task runs this worker (the pickled job submitit's tasks load).
  from submitit.core import utils  # pylint: disable=import-outside-toplevel
  pickled = next((out / "submitit").rglob("*_submitted.pkl"))
  job = utils.DelayedSubmission.load(pickled).function
  assert isinstance(job, submit.WorkerJob) and job.entry is cli.main
  assert job.argv == ["experiment", "run", "table1", str(out.absolute()), "--scale", "smoke",
                      "--seeds", "1", "--no-progress", "--lease", "600"]
  assert json.loads((out / records.PLAN_FILE).read_text())["plans"]["table1"]["scale"] == "smoke"


def test_time_and_sbatch_options_are_parsed_or_refused_in_one_line(capsys, tmp_path):
  assert [submit.parse_minutes(t) for t in ("90", "2:00:00", "1-0", "0:30", "1-02:30:00")] == [
      90, 120, 1440, 1, 1590]
  assert submit.parse_sbatch(["qos=low", "--exclusive"]) == (("qos", "low"), ("exclusive", ""))
  toys.need_submitit()
  for argv, needle in ((["--time", "soon"], "--time soon: use minutes"),
                       (["--sbatch", "QOS low"], "--sbatch QOS low: expected NAME=VALUE"),
                       (["--workers", "0"], "--workers 0: at least 1")):
    args = ["experiment", "submit", "table1", str(tmp_path / "o"), "--scale", "smoke", "--local"]
    if "--workers" not in argv:
      args += ["--workers", "2"]
    assert cli.main(args + argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and needle in err, err
    assert not (tmp_path / "o").exists()  # refused before anything is written


def test_submit_without_slurm_is_one_line_and_writes_nothing(tmp_path, capsys, monkeypatch):
  toys.need_submitit()
  monkeypatch.setattr(submit.shutil, "which", lambda name: None)
  out = tmp_path / "out"
  assert cli.main(["experiment", "submit", "table1", str(out), "--scale", "smoke",
                   "--workers", "4"]) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and "no SLURM here (sbatch and srun not found)" in err, err
  assert "--local" in err
  assert not out.exists()


def _stopping_run(out, monkeypatch, sig):
  """runner.run on table1 with stand-in training that receives `sig` in its first cell."""
  plan = plans.build_plan("table1", "smoke", 1)
  events, lock = [], threading.Lock()
  train_cell, evaluate_cell = _fake_cells(out, events, lock)

  def train_then_signal(out_, cell, bar, weight, on_step=lambda s: None, stop=None):
    on_step(3)
    os.kill(os.getpid(), sig)  # the handler only sets a flag
    on_step(4)  # the trainer finishes its step, saves it and returns stopped (train_cell's end)
    stop.check()
    raise AssertionError("not stopped")
  monkeypatch.setattr(runner, "train_cell", train_then_signal)
  monkeypatch.setattr(runner, "evaluate_cell", evaluate_cell)
  return runner.run(plan, out, progress=False, log=lambda line: None, lease=2.0)


def test_sigterm_releases_the_claim_and_the_command_says_so(tmp_path, monkeypatch, capfd):
  out = tmp_path / "out"
  res = _stopping_run(out, monkeypatch, signal.SIGTERM)
  assert res["stopped"] == "SIGTERM" and res["trained"] == 0
  top = claims.top(out, "unet-sl-objects-s0")
  assert top.record["why"] == "stopped by SIGTERM" and top.record["step"] == 4
  assert not any(claims.top(out, c).number >= 0 for c in ("unet-disp-objects-s0",))
  assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # put back
  assert not list((out / workers.WORKERS_DIR).iterdir())
  assert "SIGTERM: stopping after this step" in capfd.readouterr().err
  # The command: the signal's exit code, and what to do.
  assert cli.main(["experiment", "run", "table1", str(out), "--scale", "smoke",
                   "--no-progress"]) == 128 + signal.SIGTERM
  said = capfd.readouterr().out
  assert "unet-sl-objects-s0: stopped by SIGTERM; its checkpoint is kept and its claim " \
      "released" in said
  assert said.rstrip().endswith("stopped by SIGTERM: run the same command to go on"), said
  assert claims.top(out, "unet-sl-objects-s0").number == 3  # claimed and released again


def test_slurms_warning_checkpoints_through_submitit_and_requeues(tmp_path, monkeypatch):
  """SIGUSR2 with submitit's handler installed (as in a SLURM job): the worker stops at a step
  and releases its cell, then submitit's handler calls WorkerJob.checkpoint, saves the
  requeued job and exits with the local executor's requeue code."""
  toys.need_submitit()
  submit._submitit()  # imported as sljax imports it  # pylint: disable=protected-access
  monkeypatch.setenv("SUBMITIT_LOCAL_JOB_ID", "42")
  from submitit.core import job_environment, utils  # pylint: disable=import-outside-toplevel
  from submitit.local import local  # pylint: disable=import-outside-toplevel
  argv = ["experiment", "run", "table1", str(tmp_path / "out"), "--scale", "smoke"]
  delayed = utils.DelayedSubmission(submit.WorkerJob(argv, cli.main))
  delayed.set_timeout(60, 3)
  paths = utils.JobPaths(tmp_path / "job", job_id="42")
  paths.folder.mkdir(parents=True)
  handler = job_environment.SignalHandler(local.LocalJobEnvironment(), paths, delayed)
  previous = signal.signal(signal.SIGUSR2, handler.checkpoint_and_try_requeue)
  try:
    with pytest.raises(SystemExit) as exit_:
      _stopping_run(tmp_path / "out", monkeypatch, signal.SIGUSR2)
  finally:
    signal.signal(signal.SIGUSR2, previous)
  assert exit_.value.code == local.LOCAL_REQUEUE_RETURN_CODE
  top = claims.top(tmp_path / "out", "unet-sl-objects-s0")
  assert top.record["why"] == "stopped by SIGUSR2"  # released before the requeue
  requeued = utils.DelayedSubmission.load(paths.submitted_pickle)
  assert isinstance(requeued.function, submit.WorkerJob) and requeued.function.argv == argv
  assert requeued.function.entry is cli.main


def test_a_worker_with_nothing_to_claim_says_what_is_left_and_who_holds_it(tmp_path,
                                                                          monkeypatch):
  """table1 with its two bases trained and both fine-tuning cells held by a live worker on
  another host: nothing can come to this worker, so it exits at once and names the holder."""
  out = tmp_path / "out"
  plan = plans.build_plan("table1", "smoke", 1)
  records.register(out, plan)
  for cell in plan.cells:
    wd = records.cell_dir(out, cell.name)
    if cell.init_cell is None:
      (wd / records.EVAL_DIR).mkdir(parents=True)
      records.write_json(wd / records.DONE_FILE, {"step": 30})
      records.write_json(wd / records.EVAL_DIR / "heldout.json", {"pooled": {}})
    else:
      path = claims.claim_path(out, cell.name, 0)
      claims.create_exclusive(path, dict(token="t", host="node-3", pid=77, started=None,
                                         job="9_1", lease=300.0, since=0, kind=claims.CLAIM))
      claims.beat_path(path).write_text(json.dumps({"step": 5, "token": "t"}))
  monkeypatch.setattr(runner.time, "sleep", lambda s: pytest.fail("waited"))
  res = runner.run(plan, out, progress=False, log=lambda line: None, lease=300.0)
  assert res["trained"] == 0 and set(res["left"]) == {"unet-sl-tissue-ft-s0",
                                                      "unet-disp-tissue-ft-s0"}
  assert all(who.startswith("held by node-3 pid 77, job 9_1 since ") and who.endswith(", step 5")
             for who in res["left"].values()), res["left"]


def test_ctrl_c_releases_the_claim_too(tmp_path, monkeypatch):
  out = tmp_path / "out"
  plan = plans.build_plan("table1", "smoke", 1)

  def interrupted(out_, cell, bar, weight, on_step=lambda s: None, stop=None):
    on_step(3)
    raise KeyboardInterrupt  # what the trainer raises after a Ctrl-C, at a step
  monkeypatch.setattr(runner, "train_cell", interrupted)
  with pytest.raises(KeyboardInterrupt):
    runner.run(plan, out, progress=False, log=lambda line: None, lease=2.0)
  top = claims.top(out, "unet-sl-objects-s0")
  assert top.record["kind"] == claims.RELEASE and top.record["why"] == "interrupted"
  assert top.record["step"] == 3 and not list((out / workers.WORKERS_DIR).iterdir())


def test_a_worker_that_lost_its_cell_stops_training_it_and_goes_on(tmp_path, monkeypatch):
  """Another host took this worker's cell over (it stalled past its lease): at its next
  heartbeat the worker sees the later claim, stops that cell at the next fetch without
  releasing the other's claim, trains the cells it can, and names the holder at the end."""
  out = tmp_path / "out"
  plan = plans.build_plan("table1", "smoke", 1)
  events, lock = [], threading.Lock()
  train_cell, evaluate_cell = _fake_cells(out, events, lock)
  taken = "unet-sl-tissue-ft-s0"

  def train_or_lose(out_, cell, bar, weight, on_step=lambda s: None, stop=None):
    if cell.name != taken:
      return train_cell(out_, cell, bar, weight, on_step)
    _claim_as(out_, cell.name, "elsewhere")  # the take-over
    for step in range(1, 200):
      on_step(step)
      time.sleep(0.01)
    raise AssertionError("not stopped")
  monkeypatch.setattr(runner, "train_cell", train_or_lose)
  monkeypatch.setattr(runner, "evaluate_cell", evaluate_cell)
  res = runner.run(plan, out, progress=False, log=lambda line: None, lease=0.6)
  assert res["trained"] == 3 and set(res["left"]) == {taken}
  assert res["left"][taken].startswith("held by elsewhere pid 1")
  records = [json.loads(p.read_text()) for p in
             sorted(claims.claims_dir(out, taken).glob("*.json"))]
  assert [c["host"] for c in records] == [workers.host_name(), "elsewhere"]  # not released


def _claim_as(out: Path, cell: str, host: str) -> None:
  """The next claim of a cell, by a live worker on another host (lease 300 s)."""
  path = claims.claim_path(out, cell, claims.top(out, cell).number + 1)
  assert claims.create_exclusive(path, dict(token="other", host=host, pid=1, started=None,
                                            job=None, lease=300.0, since=time.time(),
                                            kind=claims.CLAIM))


def test_local_workers_get_one_gpu_each_where_there_are_several():
  res = submit.Resources(3, setup=("source venv/bin/activate",))
  cpu = submit.local_parameters(res, [])
  assert [p["gpus_per_node"] for p in cpu] == [0, 0, 0]  # no GPU: CUDA_VISIBLE_DEVICES=""
  four = submit.local_parameters(res, ["0", "1", "2", "3"])
  assert [p["visible_gpus"] for p in four] == [(0,), (1,), (2,), (3,)][:3]
  assert all(p["setup"] == ["source venv/bin/activate"] for p in four)
  two = submit.local_parameters(res, ["4", "6"])  # CUDA_VISIBLE_DEVICES=4,6: shared
  assert [p["visible_gpus"] for p in two] == [(4,), (6,), (4,)]
  assert "export XLA_PYTHON_CLIENT_PREALLOCATE=false" in two[0]["setup"]
  uuids = submit.local_parameters(submit.Resources(1), ["GPU-a1", "GPU-b2"])
  assert uuids[0]["gpus_per_node"] == 0
  assert uuids[0]["setup"][-1] == "export CUDA_VISIBLE_DEVICES=GPU-a1"
  with pytest.raises(SljaxError, match="--gpus-per-worker 2: this machine has 0 GPU"):
    submit.local_parameters(submit.Resources(1, gpus_per_worker=2), [])


def test_one_slurm_worker_is_a_single_job(tmp_path, capsys, fake_slurm):
  toys.need_submitit()
  bin_ = fake_slurm
  out = tmp_path / "out"
  assert cli.main(["experiment", "submit", "table1", str(out), "--scale", "smoke", "--workers",
                   "1"]) == 0
  text = capsys.readouterr().out.splitlines()
  log = f"{out.absolute()}/submitit/4242/4242_0_log.out"
  assert text[:2] == [f"submitted job 4242: 1 worker on {out}", f"  log: {log} (and .err beside "
                      "it)"], text
  assert not any(l.startswith("#SBATCH --array") for l in
                 (bin_ / "submitted.sh").read_text().splitlines())
