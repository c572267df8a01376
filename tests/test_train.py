"""train.py / sljax.train.loop: CLI bad input (before any compilation), workdir safety, exact
resume after kill -9, checkpoints for inference."""

import json
import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from sljax.data.dataset import epoch_order
from sljax.data.scene import Scene, write_scene
from sljax.errors import SljaxError
from sljax.models import checkpoint as ckpt
from sljax.models import load as trained
from sljax.train import cli, loop
from sljax.train.config import TrainConfig
from sljax.train.setup import merge_init

import toys

ROOT = Path(__file__).resolve().parents[1]


def _scene(i: int, size: int = 32, t: int = 5, disp: bool = True, sl: bool = True) -> Scene:
  rng = np.random.default_rng(i)
  im = rng.random((size, size, 3)).astype(np.float32)
  d = np.full((size, size), 2.0 + i % 4, np.float32)
  d[:, :3] = np.inf
  pat = (rng.random((size, size, t)) > 0.5).astype(np.float32)
  return Scene(name=f"s{i}", im0=im, im1=np.roll(im, -2, axis=1), disp0=d if disp else None,
               sl0=pat if sl else None, sl1=pat.copy() if sl else None,
               meta={"group": f"g{i // 2}"})


def _dataset(root: Path, n: int = 12, **kw) -> Path:
  for i in range(n):
    write_scene(root / f"s{i:02d}", _scene(i, **kw))
  return root


@pytest.fixture(scope="module")
def data_full(tmp_path_factory):
  return _dataset(tmp_path_factory.mktemp("full"))


@pytest.fixture(scope="module")
def data_nodisp(tmp_path_factory):
  return _dataset(tmp_path_factory.mktemp("nodisp"), n=4, disp=False)


@pytest.fixture(scope="module")
def data_nosl(tmp_path_factory):
  return _dataset(tmp_path_factory.mktemp("nosl"), n=4, sl=False)


@pytest.fixture
def no_compile(monkeypatch):
  """Fails the test if training gets as far as initialising (compiling) the model."""
  def boom(*a, **k):
    raise AssertionError("reached model initialisation")
  monkeypatch.setattr(loop, "init_variables", boom)


def _run(argv, capsys):
  code = cli.main(argv)
  out = capsys.readouterr()
  return code, out.out, out.err


@pytest.mark.parametrize("flag", [["--strategy", "nope"], ["--model", "resnet"],
                                  ["--preset", "huge"]])
def test_unknown_choice_is_argparse_error(flag, capsys):
  with pytest.raises(SystemExit) as e:
    cli.main(flag)
  assert e.value.code == 2
  assert "invalid choice" in capsys.readouterr().err


@pytest.mark.parametrize("argv, needle", [
    (["--maxdisp", "20"], "--maxdisp 20: must be a positive multiple of 16"),
    (["--size", "40"], "multiples of 16"),
    (["--model", "unet-sl", "--strategy", "epr"], "apply to the PSMNet twin"),
    (["--batch-size", "64"], "larger than the"),
    (["--fraction", "2"], "fraction"),
])
def test_bad_options(argv, needle, data_full, tmp_path, capsys, no_compile):
  code, _, err = _run(["--data", str(data_full), "--workdir", str(tmp_path / "w"),
                       "--size", "32", "--maxdisp", "16", "--preset", "quick"] + argv, capsys)
  assert code == 2, err
  assert needle in err and "Traceback" not in err


@pytest.mark.parametrize("which, argv, needle", [
    ("nodisp", ["--model", "psmnet"], "has no disparity (disp0.pfm)"),
    ("nodisp", ["--model", "unet-disp"], "has no disparity"),
    ("nosl", ["--strategy", "cg_a"], "has no structured-light patterns (sl0/)"),
    ("nosl", ["--model", "unet-sl"], "has no structured-light patterns"),
])
def test_dataset_lacking_targets(which, argv, needle, data_nodisp, data_nosl, tmp_path, capsys,
                                 no_compile):
  root = data_nodisp if which == "nodisp" else data_nosl
  code, _, err = _run(["--data", str(root), "--workdir", str(tmp_path / "w"), "--size", "32",
                       "--maxdisp", "16", "--batch-size", "2"] + argv, capsys)
  assert code == 2 and needle in err and str(root) in err, err


def _fake_workdir(path: Path, net: str, params: dict) -> Path:
  """A workdir with one checkpoint of the given parameters (no training needed)."""
  path.mkdir(parents=True)
  (path / "config.json").write_text(json.dumps({"strategy": "stl", "net": net,
                                                "model_kwargs": {"in_channels": 3}}))
  manager = ckpt.make_manager(path / "checkpoints")
  state = {"step": np.int32(1), "params": params, "batch_stats": {}, "opt_state": {}}
  ckpt.save(manager, 1, state, {"step": 1}, 1.0)
  manager.wait_until_finished()
  manager.close()
  return path


def test_init_from_checkpoint_of_other_model(data_full, tmp_path, capsys, no_compile):
  src = _fake_workdir(tmp_path / "other", "unet-disp",
                      {"enc0": {"kernel": np.zeros((3, 3, 6, 8), np.float32)}})
  code, _, err = _run(["--data", str(data_full), "--workdir", str(tmp_path / "w"), "--size",
                       "32", "--maxdisp", "16", "--batch-size", "2", "--init-from", str(src)],
                      capsys)
  assert code == 2 and "--init-from" in err and "does not fit model psmnet" in err, err


def test_workdir_of_another_run_is_not_overwritten(data_full, tmp_path, capsys, no_compile):
  wd = tmp_path / "w"
  wd.mkdir()
  (wd / "config.json").write_text(json.dumps({"model": "unet-sl", "strategy": "stl"}))
  code, _, err = _run(["--data", str(data_full), "--workdir", str(wd), "--size", "32",
                       "--maxdisp", "16", "--batch-size", "2"], capsys)
  assert code == 2 and "holds another run" in err and "--overwrite" in err
  assert json.loads((wd / "config.json").read_text())["model"] == "unet-sl"


def test_dwa_weights_of_a_config_follow_history():
  cfg = TrainConfig(strategy="epr")
  np.testing.assert_array_equal(loop.task_weights(cfg, []), [1, 1, 0])
  cfg = TrainConfig(model="unet-sl")
  np.testing.assert_array_equal(loop.task_weights(cfg, [(1, 1), (2, 2)]), [1, 0, 0])


def test_epoch_order_depends_only_on_seed_and_epoch():
  a = epoch_order(list(range(10, 30)), 3, 5)
  assert a == epoch_order(list(range(10, 30)), 3, 5)
  assert sorted(a) == list(range(10, 30)) and a != epoch_order(list(range(10, 30)), 3, 6)


def _latest(ckpt_dir: Path) -> int:
  steps = [int(p.name) for p in ckpt_dir.glob("*") if p.name.isdigit()] if ckpt_dir.is_dir() else []
  return max(steps, default=-1)


def test_exact_resume_after_kill_9(data_full, tmp_path, capsys):
  """A run killed with SIGKILL mid-training and resumed ends bit-identical to an uninterrupted
  run (parameters, batch statistics, optimiser state and every logged step metric)."""
  common = ["--data", str(data_full), "--model", "unet-disp", "--unet-depth", "2",
            "--unet-width", "8", "--size", "32", "--maxdisp", "16", "--batch-size", "2",
            "--epochs", "6", "--lr", "1e-3", "--save-every", "2", "--no-progress",
            "--preset", "quick"]
  killed = tmp_path / "killed"
  proc = subprocess.Popen([sys.executable, "train.py", *common, "--workdir", str(killed)],
                          cwd=ROOT, env=toys.same_device_env(), stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT)
  deadline = time.time() + 300
  while _latest(killed / "checkpoints") < 5 and proc.poll() is None and time.time() < deadline:
    time.sleep(0.02)
  proc.send_signal(signal.SIGKILL)
  out = proc.communicate()[0].decode()
  assert proc.returncode == -signal.SIGKILL, out  # still running when killed
  killed_at = _latest(killed / "checkpoints")
  assert 5 <= killed_at < 30, out

  full = tmp_path / "full"
  assert cli.main([*common, "--workdir", str(full)]) == 0
  assert cli.main([*common, "--workdir", str(killed)]) == 2  # not without --resume
  assert "--resume" in capsys.readouterr().err
  assert cli.main(["--workdir", str(killed), "--resume", "--no-progress"]) == 0
  assert "resuming from step" in capsys.readouterr().out

  manager_steps = []
  trees = []
  for wd in (full, killed):
    m = ckpt.make_manager(wd / "checkpoints", read_only=True)
    manager_steps.append(m.latest_step())
    trees.append(ckpt.restore(m, m.latest_step())[0])
    m.close()
  assert manager_steps == [30, 30]
  leaves = [jax.tree.leaves(t) for t in trees]
  assert len(leaves[0]) == len(leaves[1]) > 10
  for a, b in zip(*leaves):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  lines = [[json.loads(l) for l in (wd / "metrics.jsonl").read_text().splitlines()]
           for wd in (full, killed)]
  assert [r["step"] for r in lines[1]] == list(range(1, 31))
  assert lines[0] == lines[1]


def test_load_for_inference_of_a_workdir(data_full, tmp_path):
  """Checkpoint + config of a short run load back as (name, kwargs, variables, config)."""
  wd = tmp_path / "run"
  assert cli.main(["--data", str(data_full), "--model", "unet-sl", "--unet-depth", "2",
                   "--unet-width", "8", "--size", "32", "--maxdisp", "16", "--batch-size", "2",
                   "--epochs", "1", "--workdir", str(wd), "--no-progress"]) == 0
  for path in (wd, wd / "checkpoints"):
    name, kwargs, variables, config = trained.load_for_inference(path)
    assert name == "unet-sl" and kwargs == {"in_channels": 1, "t": 5, "depth": 2, "base_width": 8}
    assert config["size"] == [32, 32] and config["strategy"] == "stl" and config["gray"] is True
    assert "uncertainty" not in variables["params"] and "batch_stats" in variables
  # Validation of the SL UNet: its SL loss, and the MAE of the disparity correlated from the
  # predicted patterns.
  epochs = [json.loads(l) for l in (wd / "epochs.jsonl").read_text().splitlines()]
  assert len(epochs) == 1 and np.isfinite(epochs[0]["val_mae"]) and epochs[0]["val_sl"] > 0
  with pytest.raises(SljaxError, match="does not exist"):
    trained.load_for_inference(tmp_path / "nope")


class _NaNSource:
  """In-memory scenes whose images are NaN: the first step's loss is NaN."""

  def __len__(self):
    return 12

  def group(self, i):
    return f"g{i // 2}"

  def __getitem__(self, i):
    s = _scene(i)
    s.im0 = np.full_like(s.im0, np.nan)
    return s


def test_nan_loss_stops_with_clear_message(tmp_path, monkeypatch, capsys):
  monkeypatch.setattr(loop, "open_source", lambda config: _NaNSource())
  code, _, err = _run(["--model", "unet-disp", "--unet-depth", "2", "--unet-width", "8",
                       "--size", "32", "--maxdisp", "16", "--batch-size", "2", "--epochs", "1",
                       "--workdir", str(tmp_path / "w"), "--no-progress"], capsys)
  assert code == 2 and "non-finite loss" in err and "step 1" in err, err
  assert _latest(tmp_path / "w" / "checkpoints") == -1


def test_merge_init_keeps_twin_sl_path_and_checks_shapes():
  cfg = TrainConfig(strategy="cg_a")
  target = {"params": {"feat": {"kernel": np.zeros((3, 3, 3, 4), np.float32)},
                       "sl": {"kernel": np.full((2, 2), 7.0, np.float32)}},
            "batch_stats": {"bn": {"mean": np.zeros(4, np.float32)}}}
  source = {"params": {"feat": {"kernel": np.ones((3, 3, 3, 4), np.float32)}},
            "batch_stats": {"bn": {"mean": np.full(4, 2.0, np.float32)}}}
  out = merge_init(target, source, "psmnet", cfg, "ckpt")
  np.testing.assert_array_equal(out["params"]["feat"]["kernel"], 1.0)  # from the checkpoint
  np.testing.assert_array_equal(out["params"]["sl"]["kernel"], 7.0)    # kept (new SL path)
  np.testing.assert_array_equal(out["batch_stats"]["bn"]["mean"], 2.0)
  bad = {"params": {"feat": {"kernel": np.ones((3, 3, 1, 4), np.float32)}}}
  with pytest.raises(SljaxError, match=r"feat/kernel has shape \(3, 3, 1, 4\)"):
    merge_init(target, bad, "psmnet", cfg, "ckpt")
  extra = {"params": {"other": {"kernel": np.ones(2, np.float32)}}}
  with pytest.raises(SljaxError, match="does not fit"):
    merge_init(target, extra, "unet-disp", cfg, "ckpt")


def test_resume_uses_the_saved_config(tmp_path):
  wd = tmp_path / "w"
  wd.mkdir()
  saved = TrainConfig(strategy="epr", size=(32, 32), maxdisp=16, epochs=3)
  (wd / "config.json").write_text(json.dumps(saved.to_json()))
  args = cli.build_parser().parse_args(["--workdir", str(wd), "--resume", "--epochs", "5"])
  config, note, workdir = cli.resolve(args, "cpu")
  assert config.strategy == "epr" and config.size == (32, 32) and config.epochs == 5
  assert "resumed" in note and workdir == wd
  args = cli.build_parser().parse_args(["--strategy", "unc", "--maxdisp", "48"])
  config, note, workdir = cli.resolve(args, "cpu")
  assert (config.preset, config.strategy, config.maxdisp) == ("quick", "unc", 48)
  assert workdir == Path("runs/psmnet-unc-0") and "no accelerator" in note
  config, _, _ = cli.resolve(cli.build_parser().parse_args([]), "gpu")
  assert config.preset == "paper" and config.size == (256, 256) and config.epochs == 120


def test_epr_loop_uses_dwa_of_epoch_mean_training_losses_and_resumes_exactly(
    data_full, tmp_path, monkeypatch):
  """The loop feeds the step DWA weights that are constant within an epoch, 1 for the first two
  epochs, then computed by hand from the two previous epochs' mean training losses; a run
  stopped mid-epoch (partial epoch sums in its checkpoint) resumes bit-identically."""
  monkeypatch.setattr(loop, "compiled_steps", toys.tiny_steps)
  cfg = TrainConfig(strategy="epr", data=str(data_full), size=(32, 32), maxdisp=16,
                         epochs=5, batch_size=2, lr=3e-2, save_every=3, max_val=2, preset="quick")
  quiet = dict(log=lambda line: None, progress=False)
  loop.train(cfg, tmp_path / "full", **quiet)
  steps = [json.loads(l) for l in (tmp_path / "full" / "metrics.jsonl").read_text().splitlines()]
  epochs = [json.loads(l) for l in (tmp_path / "full" / "epochs.jsonl").read_text().splitlines()]
  assert len(epochs) == 5
  spe = len(steps) // 5
  for e, rec in enumerate(epochs):
    rows = [r for r in steps if r["epoch"] == e + 1]
    assert len(rows) == spe
    # Epoch means of the (unweighted) training task losses, not of validation.
    np.testing.assert_allclose(rec["loss_sl"], np.mean([r["loss_sl"] for r in rows]), rtol=1e-9)
    np.testing.assert_allclose(rec["loss_disp"], np.mean([r["loss_disp"] for r in rows]),
                               rtol=1e-9)
    w = {(r["w_sl"], r["w_disp"]) for r in rows}
    assert len(w) == 1, w  # constant within the epoch
    if e < 2:
      want = [1.0, 1.0]
    else:
      r_sl = epochs[e - 1]["loss_sl"] / epochs[e - 2]["loss_sl"]
      r_d = epochs[e - 1]["loss_disp"] / epochs[e - 2]["loss_disp"]
      z = math.exp(2 * r_sl) + math.exp(2 * r_d)
      want = [2 * math.exp(2 * r_sl) / z, 2 * math.exp(2 * r_d) / z]
    np.testing.assert_allclose(list(w.pop()), want, rtol=1e-6)
  assert epochs[2]["w_sl"] != epochs[3]["w_sl"]  # the weights do move

  # Stop one step after a mid-epoch checkpoint of epoch 3 or later, then resume.
  ckpt_at = next(s for s in range(2 * spe + 1, 5 * spe) if s % 3 == 0 and s % spe
                 and (s + 1) % spe)
  part = tmp_path / "part"
  loop.train(cfg, part, stop_after=ckpt_at + 1, **quiet)
  assert _latest(part / "checkpoints") == ckpt_at
  loop.train(cfg, part, resume=True, **quiet)
  trees = []
  for wd in (tmp_path / "full", part):
    m = ckpt.make_manager(wd / "checkpoints", read_only=True)
    trees.append(ckpt.restore(m, m.latest_step())[0])
    m.close()
  for a, b in zip(jax.tree.leaves(trees[0]), jax.tree.leaves(trees[1]), strict=True):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  assert ((part / "metrics.jsonl").read_text() == (tmp_path / "full" / "metrics.jsonl").read_text())
