"""train.py on a bad day: damaged checkpoints, a --resume of the wrong folder or of a run whose
config.json is gone, a run resumed from another directory, bad numbers, an unwritable
--profile folder. Each ends in one line (exit 2) and leaves the workdir as it was."""

import asyncio
import gc
import hashlib
import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sljax.data.scene import Scene, write_scene
from sljax.errors import SljaxError
from sljax.models import checkpoint as ckpt
from sljax.models import load as trained
from sljax.train import cli, loop
from sljax.train.config import TrainConfig
from sljax.train.profiler import StepProfiler

import toys

ROOT = Path(__file__).resolve().parents[1]


def _dataset(root: Path) -> Path:
  rng = np.random.default_rng(0)
  for i in range(8):
    im = rng.random((32, 32, 3)).astype(np.float32)
    write_scene(root / f"s{i:02d}", Scene(
        name=f"s{i}", im0=im, im1=np.roll(im, -2, axis=1),
        disp0=np.full((32, 32), 2.0 + i % 3, np.float32), meta={"group": f"g{i // 2}"}))
  return root


def _flags(data) -> list[str]:
  """A TinyTwin run: 6 training scenes, 3 steps per epoch, checkpoints at 2, 3, 4, 6
  (the last 3 kept)."""
  return ["--data", str(data), "--size", "32", "--maxdisp", "16", "--epochs", "2",
          "--batch-size", "2", "--max-val", "2", "--preset", "quick", "--save-every", "2",
          "--ynn", "on", "--no-progress"]


@pytest.fixture(autouse=True)
def tiny(monkeypatch):
  monkeypatch.setattr(loop, "compiled_steps", toys.tiny_steps)


def _run(argv, capsys):
  code = cli.main(argv)
  out = capsys.readouterr()
  return code, out.out, out.err


@pytest.fixture(scope="module")
def base(tmp_path_factory):
  """(data folder, a finished run's workdir): copy the workdir before changing it."""
  root = tmp_path_factory.mktemp("faults")
  data = _dataset(root / "data")
  with pytest.MonkeyPatch.context() as mp:
    mp.setattr(loop, "compiled_steps", toys.tiny_steps)
    assert cli.main([*_flags(data), "--workdir", str(root / "run")]) == 0
  return data, root / "run"


def _copy(base, tmp_path) -> Path:
  wd = tmp_path / "wd"
  shutil.copytree(base[1], wd)
  return wd


def _digest(folder: Path) -> dict[str, str]:
  """md5 of every file under folder (the names of empty folders too)."""
  return {str(p.relative_to(folder)): hashlib.md5(p.read_bytes()).hexdigest() if p.is_file()
          else "dir" for p in sorted(folder.rglob("*"))}


def _data_file(step_dir: Path) -> Path:
  files = sorted((step_dir / "state" / "d").iterdir(), key=lambda p: -p.stat().st_size)
  return files[0]


def _flip(step_dir: Path) -> None:
  path = _data_file(step_dir)
  raw = bytearray(path.read_bytes())
  raw[40::7] = bytes(b ^ 0xFF for b in raw[40::7])
  path.write_bytes(bytes(raw))


DAMAGE = {
    "flipped": _flip,
    "truncated": lambda d: _data_file(d).write_bytes(_data_file(d).read_bytes()[:30]),
    "emptied": lambda d: _data_file(d).write_bytes(b""),
    "garbage manifest": lambda d: (d / "state" / "manifest.ocdbt").write_bytes(b"garbage\n"),
    "garbage meta": lambda d: (d / "meta" / "metadata").write_text("{garbage"),
    "meta not an object": lambda d: (d / "meta" / "metadata").write_text("[1, 2]"),
    "empty folder": lambda d: [shutil.rmtree(p) if p.is_dir() else p.unlink()
                               for p in list(d.iterdir())],
}


@pytest.mark.parametrize("damage", DAMAGE)
def test_damaged_checkpoint_is_one_line_naming_it(damage, base, tmp_path, capsys):
  wd = _copy(base, tmp_path)
  checkpoints = wd / "checkpoints"
  steps = sorted(int(p.name) for p in checkpoints.iterdir() if p.name.isdigit())
  assert steps == [3, 4, 6]  # the last 3 (6 is also the best)
  DAMAGE[damage](checkpoints / "6")
  before = _digest(wd)
  code, _, err = _run(["--workdir", str(wd), "--resume", "--epochs", "3", "--no-progress"],
                      capsys)
  assert code == 2, err
  assert f"{checkpoints / '6'}: checkpoint 6 is damaged or incomplete" in err
  assert (f"earlier checkpoints: steps 3, 4; delete the damaged folder {checkpoints / '6'} "
          "to resume from step 4") in err
  assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
  assert _digest(wd) == before  # nothing written, nothing deleted
  # predict / evaluate / export / --init-from load through load_params: the same message.
  with pytest.raises(SljaxError, match=r"checkpoints/6: checkpoint 6 is damaged or incomplete"):
    trained.load_params(wd, 6)


def test_damaged_only_checkpoint_says_there_is_no_earlier_one(base, tmp_path, capsys):
  wd = _copy(base, tmp_path)
  for step in (3, 4):
    shutil.rmtree(wd / "checkpoints" / str(step))
  DAMAGE["garbage meta"](wd / "checkpoints" / "6")
  code, _, err = _run(["--workdir", str(wd), "--resume", "--no-progress"], capsys)
  assert code == 2
  assert "checkpoint 6 is damaged or incomplete" in err
  assert "no earlier checkpoint exists; start again with --overwrite" in err


def test_no_late_tracebacks_after_a_failed_restore(base, tmp_path):
  """A failed restore leaves TensorStore reads in flight that used to print 'RuntimeError:
  Event loop is closed' tracebacks after the one line (about half the time): none now."""
  wd = _copy(base, tmp_path)
  DAMAGE["garbage manifest"](wd / "checkpoints" / "6")
  DAMAGE["flipped"](wd / "checkpoints" / "4")
  script = ("import sys\nfrom sljax.models import load as trained\n"
            "for i in range(6):\n"
            "  try:\n    trained.load_params(sys.argv[1], (6, 4)[i % 2])\n"
            "  except Exception as e:\n    print(type(e).__name__, 'damaged' in str(e))\n")
  env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT))
  proc = subprocess.run([sys.executable, "-c", script, str(wd)], env=env, capture_output=True,
                        text=True, timeout=300)
  assert proc.stdout.split("\n")[:6] == ["CheckpointUnreadable True"] * 6, proc.stderr[-2000:]
  assert "Traceback" not in proc.stderr and "Event loop is closed" not in proc.stderr


def _unretrieved_failure(folder: Path) -> None:
  """A task whose coroutine (in a file under folder) fails and whose exception nobody
  retrieves, then collected: what orbax leaves when one read of a gathered restore fails."""
  folder.mkdir(parents=True)
  ns: dict = {}
  exec(compile("async def read():\n  raise ValueError('Error opening \"zarr\" driver')\n",
               str(folder / "serialization.py"), "exec"), ns)
  loop = asyncio.new_event_loop()
  task = loop.create_task(ns["read"]())
  loop.run_until_complete(asyncio.sleep(0.01))
  loop.close()
  del task
  gc.collect()


def test_unretrieved_orbax_read_failures_after_a_restore_are_not_logged(base, tmp_path,
                                                                        caplog):
  """The cause of the traceback test above's CI failure, made deterministic: asyncio logs an
  unretrieved read failure whenever its task is collected, after the restore's one line."""
  wd = _copy(base, tmp_path)
  DAMAGE["garbage manifest"](wd / "checkpoints" / "6")
  with pytest.raises(SljaxError, match="damaged"):
    trained.load_params(wd, 6)
  with caplog.at_level(logging.ERROR, logger="asyncio"):
    _unretrieved_failure(tmp_path / "site-packages" / "orbax" / "checkpoint")
    assert not caplog.records
    _unretrieved_failure(tmp_path / "mine")  # not orbax's: still logged
    assert [r.getMessage().splitlines()[0] for r in caplog.records] == [
        "Task exception was never retrieved"]


def test_resume_refuses_a_missing_workdir_and_a_run_without_config(base, tmp_path, capsys):
  typo = tmp_path / "typo_wd"
  code, _, err = _run(["--workdir", str(typo), "--resume", "--no-progress"], capsys)
  assert code == 2 and f"--resume: {typo} does not exist; nothing to resume" in err
  assert not typo.exists()
  empty = tmp_path / "empty"
  empty.mkdir()
  code, _, err = _run(["--workdir", str(empty), "--resume"], capsys)
  assert code == 2 and "holds no run (no config.json); nothing to resume" in err
  assert list(empty.iterdir()) == []

  wd = _copy(base, tmp_path)
  (wd / "config.json").unlink()
  before = _digest(wd)
  code, _, err = _run(["--workdir", str(wd), "--resume", "--no-progress"], capsys)
  assert code == 2
  assert (f"{wd}: has checkpoints but no config.json, so the run they belong to is unknown; "
          "put its config.json back (to --resume it), or pass --overwrite") in err
  assert _digest(wd) == before  # no default run started, no epochs.jsonl rows lost
  # The library refuses too (the experiment runner calls train(resume=True)).
  config = TrainConfig(data=str(base[0]), size=(32, 32), maxdisp=16, batch_size=2,
                       max_val=2, ynn="on")
  with pytest.raises(SljaxError, match="has checkpoints but no config.json"):
    loop.train(config, wd, resume=True, log=lambda line: None, progress=False)
  assert _digest(wd) == before
  # A new run there is refused too: it would write its config.json beside another run's
  # checkpoints (and a later --resume would load them into it).
  code, _, err = _run([*_flags(base[0]), "--workdir", str(wd)], capsys)
  assert code == 2 and "has checkpoints but no config.json" in err, err
  assert _digest(wd) == before


def test_resume_and_overwrite_exclude_each_other(tmp_path, capsys):
  with pytest.raises(SystemExit) as stop:
    cli.main(["--workdir", str(tmp_path / "w"), "--resume", "--overwrite"])
  assert stop.value.code == 2
  assert "argument --overwrite: not allowed with argument --resume" in capsys.readouterr().err


def test_resume_without_a_checkpoint_says_it_starts_from_step_0(base, tmp_path, capsys):
  wd = _copy(base, tmp_path)
  shutil.rmtree(wd / "checkpoints")
  code, out, err = _run(["--workdir", str(wd), "--resume", "--no-progress"], capsys)
  assert code == 0, err
  assert (f"--resume: no checkpoint in {wd / 'checkpoints'} yet; starting from step 0 "
          "(replacing the 6 row(s) of metrics.jsonl and 2 row(s) of epochs.jsonl written "
          "without one)") in out
  # The same run again: the same rows (the step is deterministic).
  for name in ("metrics.jsonl",):
    rows = [[{k: v for k, v in json.loads(l).items() if k not in ("seconds", "samples_per_s")}
             for l in (w / name).read_text().splitlines()] for w in (base[1], wd)]
    assert rows[0] == rows[1]


def test_data_path_is_recorded_absolute_and_old_relative_runs_resume(base, tmp_path,
                                                                      monkeypatch, capsys):
  data = base[0]
  monkeypatch.chdir(data.parent)
  wd = tmp_path / "new"
  assert cli.main([*_flags("data"), "--epochs", "1", "--workdir", str(wd)]) == 0
  assert json.loads((wd / "config.json").read_text())["data"] == str(data.resolve())

  # A run recorded before: data as typed, relative to the folder it started in.
  old = _copy(base, tmp_path)
  cfg = json.loads((old / "config.json").read_text())
  (old / "config.json").write_text(json.dumps(dict(cfg, data="data"), indent=2))
  # From its own folder it resumes as before; config.json keeps its relative path.
  assert cli.main(["--workdir", str(old), "--resume", "--epochs", "3", "--no-progress"]) == 0
  assert json.loads((old / "config.json").read_text())["data"] == "data"
  capsys.readouterr()

  elsewhere = tmp_path / "elsewhere"
  elsewhere.mkdir()
  monkeypatch.chdir(elsewhere)
  before = _digest(old)
  code, _, err = _run(["--workdir", str(old), "--resume", "--epochs", "4"], capsys)
  assert code == 2
  assert (f"the run's data 'data' was relative to the folder the run started in, and "
          f"{elsewhere / 'data'} does not exist from here; run from that folder or pass "
          "--data with the data folder's path") in err
  assert _digest(old) == before
  # Another folder called 'data' here: a different run, with where the path points said.
  _dataset(elsewhere / "data")
  (elsewhere / "data" / "s07").rename(elsewhere / "data" / "x07")
  shutil.rmtree(elsewhere / "data" / "s06")
  code, _, err = _run(["--workdir", str(old), "--resume", "--epochs", "4"], capsys)
  assert code == 2 and "holds another run" in err
  assert (f"(n_train: 6 -> 5, steps_per_epoch: 3 -> 2; its data 'data' is (a path relative to "
          f"the folder the run started in: {elsewhere / 'data'} from here)); choose another "
          "--workdir") in err
  assert _digest(old) == before
  shutil.rmtree(elsewhere / "data")
  # The data folder given: resumed, and recorded absolute from now on.
  code, out, err = _run(["--workdir", str(old), "--resume", "--epochs", "4", "--data",
                         str(data), "--no-progress"], capsys)
  assert code == 0, err
  assert "resuming from step 9" in out
  assert json.loads((old / "config.json").read_text())["data"] == str(data.resolve())


@pytest.mark.parametrize("flag, needle", [
    (["--seed", "-1"], "--seed -1: must be in 0..4294967295"),
    (["--seed", str(2**32)], f"--seed {2**32}: must be in 0..4294967295"),
    (["--max-val", "0"], "--max-val 0: leaves no validation scene; give at least 1"),
    (["--profile", "FILE/trace"], "--profile FILE/trace: cannot write a trace there"),
])
def test_bad_values_are_one_line_before_anything_is_written(flag, needle, base, tmp_path,
                                                             monkeypatch, capsys):
  monkeypatch.chdir(tmp_path)
  Path("FILE").write_text("a file where --profile wants a folder")
  code, _, err = _run([*_flags(base[0]), *flag, "--workdir", "wd"], capsys)
  assert code == 2 and needle in err, err
  assert not Path("wd").exists()


def test_one_group_says_why_nothing_is_held_out(tmp_path, capsys):
  # Every scene of one object (one meta.json group): the line used to blame --max-val 2.
  data = _dataset(tmp_path / "data")
  for meta in data.glob("*/meta.json"):
    meta.write_text(json.dumps({"group": "one"}))
  code, _, err = _run([*_flags(data), "--workdir", str(tmp_path / "wd")], capsys)
  assert code == 2 and err == (
      f"train.py: error: {data}: the held-out split is empty (its 8 scene(s) form 1 group(s) "
      "(meta.json 'group', else the scene's name) and whole groups are held out; give scenes of "
      "at least 2 groups)\n"), err
  assert not (tmp_path / "wd").exists()
  every = [f"s{i:02d}" for i in range(8)]
  (data / "dataset.json").write_text(json.dumps({"splits": {"train": every}}))
  code, _, err = _run([*_flags(data), "--workdir", str(tmp_path / "wd")], capsys)
  assert code == 2 and err.endswith(
      "the held-out split is empty (dataset.json's 'splits' leave no test scene)\n"), err


def test_failed_preflight_leaves_no_config_behind(base, tmp_path, capsys):
  data = tmp_path / "data"
  shutil.copytree(base[0], data)
  victim = data / "s07" / "im0.png"  # not the first scene: found by the check before training
  victim.write_bytes(victim.read_bytes()[:-20])
  wd = tmp_path / "wd"
  code, _, err = _run([*_flags(data), "--workdir", str(wd)], capsys)
  assert code == 2 and f"{victim}: truncated" in err, err
  assert not (wd / "config.json").exists()
  # The corrected run (other data, another config.json) is not "another run".
  code, _, err = _run([*_flags(base[0]), "--epochs", "1", "--workdir", str(wd)], capsys)
  assert code == 0, err


def test_overwrite_refused_by_its_checks_keeps_the_old_run(base, tmp_path, capsys):
  """--overwrite deletes the old run only once the new one has passed every check: a damaged
  scene (found by preflight) or a wrong --init-from must not cost the user the old run."""
  data = tmp_path / "data"
  shutil.copytree(base[0], data)
  victim = data / "s07" / "im0.png"
  victim.write_bytes(victim.read_bytes()[:-20])
  wd = _copy(base, tmp_path)
  before = _digest(wd)
  code, _, err = _run([*_flags(data), "--workdir", str(wd), "--overwrite"], capsys)
  assert code == 2 and f"{victim}: truncated" in err, err
  assert _digest(wd) == before
  code, _, err = _run([*_flags(base[0]), "--workdir", str(wd), "--overwrite", "--init-from",
                       str(tmp_path / "nowhere")], capsys)
  assert code == 2 and "--init-from" in err, err
  assert _digest(wd) == before
  # Accepted: the old run (6 steps) is replaced by a new one of 3.
  code, _, err = _run([*_flags(base[0]), "--epochs", "1", "--workdir", str(wd), "--overwrite"],
                      capsys)
  assert code == 0, err
  assert sorted(int(p.name) for p in (wd / "checkpoints").iterdir()) == [2, 3]
  assert len((wd / "metrics.jsonl").read_text().splitlines()) == 3


def test_a_trace_that_cannot_be_written_is_a_warning(monkeypatch):
  def fail(*a, **k):
    raise RuntimeError("PERMISSION_DENIED: cannot write /x/trace.pb\nmore")
  lines = []
  monkeypatch.setattr("jax.profiler.start_trace", lambda d: None)
  monkeypatch.setattr("jax.profiler.stop_trace", fail)
  prof = StepProfiler("/x", 0, lines.append)
  for step in range(1, 9):
    prof.before(step)
    prof.after(step, np.zeros(1))
  prof.close()
  assert lines == ["warning: --profile /x: the trace was not written (PERMISSION_DENIED: "
                   "cannot write /x/trace.pb); training goes on"]
  monkeypatch.setattr("jax.profiler.start_trace", fail)
  lines.clear()
  prof = StepProfiler("/x", 0, lines.append)
  for step in range(1, 9):
    prof.before(step)
    prof.after(step, np.zeros(1))
  assert lines == ["warning: --profile /x: could not start the trace (PERMISSION_DENIED: "
                   "cannot write /x/trace.pb); training goes on"]


def test_an_absolute_data_path_spelled_another_way_is_the_same_run(base, tmp_path, capsys):
  """A run that recorded its data as typed ('/x/data/' from tab completion, or through a
  symlink) resumes with the resolved path every new call records; its config.json keeps its
  own spelling."""
  data = base[0]
  link = tmp_path / "link"
  link.symlink_to(data.parent)
  for spelling in (str(data) + "/", str(link / data.name), str(data.parent / "." / data.name)):
    wd = _copy(base, tmp_path / spelling.replace("/", "_"))
    cfg = json.loads((wd / "config.json").read_text())
    (wd / "config.json").write_text(json.dumps(dict(cfg, data=spelling), indent=2))
    code, _, err = _run(["--workdir", str(wd), "--resume", "--epochs", "3", "--no-progress"],
                        capsys)
    assert code == 0, (spelling, err)
    assert json.loads((wd / "config.json").read_text())["data"] == spelling


def test_a_restore_failing_for_another_reason_keeps_its_error(base, tmp_path, monkeypatch):
  """Only damaged files read as a damaged checkpoint: a device out of memory while the arrays
  are placed (a RuntimeError here) surfaces as itself, and a permission problem says 'cannot
  be read' without advice to delete the checkpoint."""
  wd = _copy(base, tmp_path)

  def oom(*args, **kwargs):
    raise RuntimeError("RESOURCE_EXHAUSTED: out of memory")
  monkeypatch.setattr(ckpt, "_restore", oom)
  with pytest.raises(RuntimeError, match="RESOURCE_EXHAUSTED"):
    trained.load_params(wd, 6)

  def denied(*args, **kwargs):
    raise PermissionError(13, "Permission denied", str(wd / "checkpoints" / "6" / "meta"))
  monkeypatch.setattr(ckpt, "_restore", denied)
  with pytest.raises(SljaxError) as e:
    trained.load_params(wd, 6)
  assert "checkpoint 6 cannot be read: Permission denied" in str(e.value)
  assert "delete" not in str(e.value)


def test_a_run_started_again_while_the_first_goes_on_is_refused(base, tmp_path, capsys):
  # Two processes in one workdir interleaved their logs and checkpoints; the second now stops.
  wd = _copy(base, tmp_path)
  proc = toys.hold(wd, "sljax train (psmnet-mtl)")
  try:
    before = _digest(wd)
    code, _, err = _run(["--workdir", str(wd), "--resume", "--no-progress"], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert (f"{wd}: in use by sljax train (psmnet-mtl) (pid {proc.pid} on ") in err
    assert "wait for it to end or stop it (its lock ends with it)" in err
    code, _, err = _run([*_flags(base[0]), "--workdir", str(wd), "--overwrite"], capsys)
    assert code == 2 and f"(pid {proc.pid} on " in err  # --overwrite deletes nothing either
    assert _digest(wd) == before
  finally:
    proc.kill()
    proc.wait()
  # Once the holder is gone (killed: no stale lock to remove), the run resumes.
  code, _, err = _run(["--workdir", str(wd), "--resume", "--epochs", "3", "--no-progress"],
                      capsys)
  assert code == 0, err
  assert not (wd / ".sljax.lock").exists()
  assert [json.loads(x)["epoch"] for x in (wd / "epochs.jsonl").read_text().splitlines()] == [
      1, 2, 3]
