"""The training loop's machinery: exact resume after kill -9 mid-epoch and during a checkpoint
save (stl, epr, unc), background data overlapping the steps, LoopState, bf16 training."""

import dataclasses
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from sljax.data.scene import Scene
from sljax.io import files
from sljax.models import checkpoint as ckpt
from sljax.nets import ModelConfig
from sljax.train import loop
from sljax.train import step as stp
from sljax.train.config import TrainConfig
from sljax.train.feed import prefetch
from sljax.train.state import LoopState
from sljax.train.workdir import EPOCHS_FILE, METRICS_FILE

import toys

ROOT = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent


def _scene(i: int, size: int = 32, t: int = 4) -> Scene:
  rng = np.random.default_rng(i)
  im = rng.random((size, size, 3)).astype(np.float32)
  d = np.full((size, size), 2.0 + i % 4, np.float32)
  d[:, :3] = np.inf
  pat = (rng.random((size, size, t)) > 0.5).astype(np.float32)
  return Scene(name=f"s{i}", im0=im, im1=np.roll(im, -2, axis=1), disp0=d, sl0=pat,
               sl1=pat.copy(), meta={"group": f"g{i // 2}"})


class MemorySource:
  """Scenes made in memory, optionally slow to load (sleep seconds per scene)."""

  def __init__(self, n: int = 16, sleep: float = 0.0):
    self.n, self.sleep = n, sleep

  def __len__(self):
    return self.n

  def group(self, i):
    return f"g{i // 2}"

  def name(self, i):
    return f"s{i}"

  def __getitem__(self, i):
    time.sleep(self.sleep)
    return _scene(i)


def _config(strategy: str, **kw) -> TrainConfig:
  base = dict(strategy=strategy, size=(32, 32), maxdisp=16, epochs=4, batch_size=2, lr=3e-2,
              max_val=2, preset="quick", log_every=3)
  return TrainConfig(**dict(base, **kw))


def _final(workdir: Path):
  m = ckpt.make_manager(workdir / "checkpoints", read_only=True)
  try:
    return m.latest_step(), ckpt.restore(m, m.latest_step())[0]
  finally:
    m.close()


def _assert_same_run(a: Path, b: Path) -> None:
  (sa, ta), (sb, tb) = _final(a), _final(b)
  assert sa == sb
  for x, y in zip(jax.tree.leaves(ta), jax.tree.leaves(tb), strict=True):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
  for name in (METRICS_FILE, EPOCHS_FILE):
    rows = [[{k: v for k, v in json.loads(l).items() if k not in ("seconds", "samples_per_s")}
             for l in (wd / name).read_text().splitlines()] for wd in (a, b)]
    assert rows[0] == rows[1], name


# A child process that trains TinyTwin on MemorySource and SIGKILLs itself at a chosen point:
# "step N" right after step N's metrics are fetched (log_every 1), or "save N" inside orbax's
# finalisation of checkpoint N (its files written, not yet renamed into place).
_CHILD = textwrap.dedent("""
    import json, os, signal, sys
    sys.path.insert(0, sys.argv[4])
    import toys, test_loop
    from orbax.checkpoint._src.path import atomicity
    from sljax.train import loop
    from sljax.train.config import config_from_json
    loop.compiled_steps = toys.tiny_steps
    loop.open_source = lambda config: test_loop.MemorySource()
    kind, n = sys.argv[3].split()
    n = int(n)
    if kind == "step":
      fetch = loop.fetch_metrics
      def fetch_then_die(ctx, pending, loop_state):
        loop_state, last = fetch(ctx, pending, loop_state)
        if loop_state.step >= n:
          ctx.manager.wait_until_finished()  # the checkpoint before step n is complete
          os.kill(os.getpid(), signal.SIGKILL)
        return loop_state, last
      loop.fetch_metrics = fetch_then_die
    else:
      finalize = atomicity.AtomicRenameTemporaryPath.finalize
      async def die_in_finalize(self):
        if self._final_path.name == str(n):
          os.kill(os.getpid(), signal.SIGKILL)
        return await finalize(self)
      atomicity.AtomicRenameTemporaryPath.finalize = die_in_finalize
    config = config_from_json(json.loads(sys.argv[1]))
    loop.train(config, sys.argv[2], log=lambda line: None, progress=False)
""")


@pytest.fixture
def tiny(monkeypatch):
  monkeypatch.setattr(loop, "compiled_steps", toys.tiny_steps)
  monkeypatch.setattr(loop, "open_source", lambda config: MemorySource())


@pytest.mark.parametrize("strategy", ["stl", "epr", "unc"])
def test_exact_resume_after_kill_mid_epoch_and_during_a_save(strategy, tiny, tmp_path):
  """A run SIGKILLed mid-epoch, or while orbax finalises a checkpoint, and resumed ends
  bit-identical to the uninterrupted run: parameters, optimiser state, batch statistics, the
  unc sigmas, DWA weights and every logged row."""
  cfg = _config(strategy, save_every=4)  # 6 steps per epoch: saves at 4, 6, 8, 12, 16, 18, ...
  quiet = dict(log=lambda line: None, progress=False)
  full = loop.train(cfg, tmp_path / "full", **quiet)
  assert full.step == 4 * 6
  env = toys.same_device_env()
  # Killed at step 17 (epoch 3 of 4) it resumes from the mid-epoch checkpoint 16; killed while
  # checkpoint 16 is being finalised, from 12.
  for kind, n, left in (("step", 17, 16), ("save", 16, 12)):
    wd = tmp_path / kind
    child_cfg = dataclasses.replace(cfg, log_every=1)  # resumable: may differ from the resume
    proc = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(child_cfg.to_json()),
                           str(wd), f"{kind} {n}", str(TESTS)], env=env, cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    assert _final(wd)[0] == left, kind  # the last complete checkpoint
    if kind == "save":  # orbax's unfinished checkpoint directory is there, and ignored
      assert any(".orbax-checkpoint-tmp" in p.name for p in (wd / "checkpoints").iterdir())
    result = loop.train(cfg, wd, resume=True, **quiet)
    assert result.step == full.step
    _assert_same_run(tmp_path / "full", wd)


def test_a_stop_saves_its_step_and_the_resumed_run_is_the_uninterrupted_one(tiny, tmp_path):
  """train(stop=...) asked after every step: when it says yes mid-epoch, between two
  checkpoints and with metrics still unfetched, the run saves that step and returns stopped;
  resumed, it ends bit-identical to the uninterrupted run (no step trained twice)."""
  cfg = _config("epr", save_every=4)  # 6 steps per epoch, a fetch every 3: saves at 4, 6, 8, 12
  quiet = dict(log=lambda line: None, progress=False)
  full = loop.train(cfg, tmp_path / "full", **quiet)
  asked = []

  def stop():
    asked.append(True)
    return len(asked) == 10
  part = loop.train(cfg, tmp_path / "part", stop=stop, **quiet)
  assert part.stopped and part.step == 10 and len(asked) == 10
  assert _final(tmp_path / "part")[0] == 10
  rows = (tmp_path / "part" / METRICS_FILE).read_text().splitlines()
  assert json.loads(rows[-1])["step"] == 10
  done = loop.train(cfg, tmp_path / "part", resume=True, stop=lambda: False, **quiet)
  assert not done.stopped and done.step == full.step
  _assert_same_run(tmp_path / "full", tmp_path / "part")


def test_loading_overlaps_the_steps(tiny, monkeypatch, tmp_path):
  """With a source that takes S seconds per batch and a step that takes T, an epoch takes
  about max(S, T) per step, not S + T: batches are built while the step runs."""
  s_per_scene, t_step = 0.06, 0.12
  monkeypatch.setattr(loop, "open_source", lambda config: MemorySource(40, s_per_scene))
  model, tx, step, evaluate = toys.tiny_steps(
      ModelConfig("psmnet", in_channels=3, maxdisp=16), "l2", 3e-2, None, stp.make_mesh())

  def slow_step(state, batch, weights):
    time.sleep(t_step)
    return step(state, batch, weights)

  monkeypatch.setattr(loop, "compiled_steps", lambda *a: (model, tx, slow_step, evaluate))
  cfg = _config("stl", epochs=1, max_val=2, log_every=10)
  loop.train(cfg, tmp_path / "warm", log=lambda line: None, progress=False)  # compiles
  cfg = dataclasses.replace(cfg, seed=1)
  loop.train(cfg, tmp_path / "run", log=lambda line: None, progress=False)
  rec = json.loads((tmp_path / "run" / EPOCHS_FILE).read_text().splitlines()[0])
  steps = rec["step"]
  source_time = steps * cfg.batch_size * s_per_scene  # 0.12 s per batch, as long as a step
  assert steps >= 14
  assert rec["seconds"] < 0.75 * (source_time + steps * t_step), rec
  assert rec["seconds"] > 0.9 * max(source_time, steps * t_step), rec


def test_prefetch_keeps_order_and_stops_early():
  calls = []

  def slow_square(x):
    calls.append(x)
    time.sleep(0.01 * (x % 3))
    return x * x

  gen = prefetch(slow_square, iter(range(100)), ahead=4, threads=3)
  assert [next(gen) for _ in range(10)] == [x * x for x in range(10)]
  gen.close()
  assert len(calls) <= 10 + 4 + 3  # stopped: no work far beyond what was asked


def test_loop_state_bookkeeping_and_metadata_round_trip():
  s = LoopState()
  for l_sl, l_disp in ((1.0, 4.0), (3.0, 2.0)):
    s = s.add_step(l_sl, l_disp)
  assert s.step == 2 and s.partial == (4.0, 6.0, 2)
  s = s.close_epoch().validated(0.5).validated(0.7).add_step(1.0, 1.0)
  assert s.history == ((2.0, 3.0),) and s.partial == (1.0, 1.0, 1)
  assert (s.best_val, s.last_val) == (0.5, 0.7)
  meta = json.loads(json.dumps(s.to_meta()))
  assert LoopState.from_meta(meta) == s
  old = {"step": 3, "history": [[2.0, 3.0]], "partial": [1.0, 1.0, 1], "best_val": 0.5}
  assert LoopState.from_meta(old).last_val is None  # checkpoints of earlier versions


def test_bf16_training_learns(tmp_path):
  """--precision bf16 on a small UNet: float32 parameters in the checkpoint, validation MAE
  falls, and the first step's losses are close to those of float32."""
  cfg = TrainConfig(model="unet-disp", unet_depth=2, unet_width=8, synth_n=40, synth_size=32,
                    size=(32, 32), epochs=6, batch_size=4, lr=3e-3, max_val=8, preset="quick",
                    precision="bf16")
  quiet = dict(log=lambda line: None, progress=False)
  loop.train(cfg, tmp_path / "bf16", **quiet)
  loop.train(dataclasses.replace(cfg, precision="fp32", epochs=1), tmp_path / "fp32", **quiet)
  epochs = [json.loads(l) for l in (tmp_path / "bf16" / EPOCHS_FILE).read_text().splitlines()]
  assert epochs[-1]["val_mae"] < 0.8 * epochs[0]["val_mae"], epochs
  _, state = _final(tmp_path / "bf16")
  assert {np.asarray(x).dtype for x in jax.tree.leaves(state["params"])} == {np.dtype(np.float32)}
  first = [json.loads((tmp_path / p / METRICS_FILE).read_text().splitlines()[0])
           for p in ("bf16", "fp32")]
  assert first[0]["loss_disp"] != first[1]["loss_disp"]  # really computed in bfloat16
  np.testing.assert_allclose(first[0]["loss_disp"], first[1]["loss_disp"], rtol=0.05)


def test_profile_writes_a_trace(tiny, tmp_path):
  cfg = _config("stl", epochs=1)
  lines = []
  loop.train(cfg, tmp_path / "w", profile_dir=str(tmp_path / "prof"), log=lines.append,
             progress=False)
  traces = list((tmp_path / "prof").rglob("*.xplane.pb"))
  assert traces and any("profile of steps 3-5" in l for l in lines), lines


_PROCESS = textwrap.dedent("""
    import json, sys
    import jax
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    n, i = int(sys.argv[3]), int(sys.argv[4])
    if n > 1:
      jax.distributed.initialize(f"localhost:{sys.argv[5]}", num_processes=n, process_id=i)
    sys.path.insert(0, sys.argv[6])
    import toys, test_loop
    from sljax.train import loop
    from sljax.train.config import config_from_json
    loop.compiled_steps = toys.tiny_steps
    loop.open_source = lambda config: test_loop.MemorySource()
    result = loop.train(config_from_json(json.loads(sys.argv[1])), sys.argv[2],
                        log=lambda line: None, progress=False)
    print("steps", result.step, "processes", jax.process_count(), "devices", jax.device_count())
""")


def _launcher(tmp_path):
  """run(workdir name, processes, index) -> a child training the unc twin (2 epochs) there,
  joined with the other processes of its run through one coordinator port."""
  import socket  # pylint: disable=import-outside-toplevel
  with socket.socket() as s:
    s.bind(("localhost", 0))
    port = s.getsockname()[1]
  cfg = json.dumps(_config("unc", epochs=2, batch_size=4, log_every=2).to_json())
  env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT))
  env.pop("XLA_FLAGS", None)  # one device per process
  return lambda wd, n, i: subprocess.Popen(
      [sys.executable, "-c", _PROCESS, cfg, str(tmp_path / wd), str(n), str(i), str(port),
       str(TESTS)], env=env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
      text=True)


def test_two_processes_equal_one(tmp_path):
  """Two CPU processes joined by jax.distributed (gloo collectives), each loading its half of
  every global batch, end with the parameters of one process training on the same global
  batch (up to the order of the cross-process sums)."""
  run = _launcher(tmp_path)
  procs = [run("two", 2, 0), run("two", 2, 1), run("one", 1, 0)]
  outs = [p.communicate(timeout=300) for p in procs]
  for p, (out, err) in zip(procs, outs):
    assert p.returncode == 0, err[-3000:]
  assert "processes 2 devices 2" in outs[0][0] and "processes 1 devices 1" in outs[2][0]
  (s2, t2), (s1, t1) = _final(tmp_path / "two"), _final(tmp_path / "one")
  assert s1 == s2 == 2 * 3
  for a, b in zip(jax.tree.leaves(t2["params"]), jax.tree.leaves(t1["params"]), strict=True):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=2e-5)
  rows = [[json.loads(l) for l in (tmp_path / wd / METRICS_FILE).read_text().splitlines()]
          for wd in ("two", "one")]
  assert [r["step"] for r in rows[0]] == [r["step"] for r in rows[1]] == list(range(1, 7))
  np.testing.assert_allclose([r["loss"] for r in rows[0]], [r["loss"] for r in rows[1]],
                             rtol=1e-4)


def test_lr_drop_schedule_by_hand():
  """--lr-drop-epoch: Adam's update is lr * m_hat / (sqrt(v_hat) + eps); with a constant
  gradient m_hat / sqrt(v_hat) = 1, so each step moves a parameter by lr before the drop
  step and by lr / 10 from it on."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  import optax  # pylint: disable=import-outside-toplevel
  from sljax.train.state import make_optimizer  # pylint: disable=import-outside-toplevel
  tx = make_optimizer(1e-2, drop_step=3)
  params = {"w": jnp.zeros(())}
  opt = tx.init(params)
  moves = []
  for _ in range(6):
    updates, opt = tx.update({"w": jnp.ones(())}, opt, params)
    params = optax.apply_updates(params, updates)
    moves.append(-float(updates["w"]))
  np.testing.assert_allclose(moves, [1e-2] * 3 + [1e-3] * 3, rtol=1e-4)  # float32 Adam


class _Bar:
  """A progress bar that records what the loop shows on it."""

  def __init__(self):
    self.events = []

  def update(self, n):
    self.events.append(("update", n))

  def set_postfix(self, refresh=False, **kw):
    self.events.append(("postfix", kw))

  def write(self, line):
    self.events.append(("write", line))


def test_the_bar_says_it_is_compiling_then_how_long_the_first_step_took(monkeypatch, tmp_path):
  model, tx, step, evaluate = toys.tiny_steps(
      ModelConfig("psmnet", in_channels=3, maxdisp=16), "l2", 3e-2, None, stp.make_mesh())
  calls = []

  def first_slow(state, batch, weights):  # the first call stands for XLA compiling
    calls.append(1)
    if len(calls) == 1:
      time.sleep(1.2)
    return step(state, batch, weights)

  monkeypatch.setattr(loop, "compiled_steps", lambda *a: (model, tx, first_slow, evaluate))
  monkeypatch.setattr(loop, "open_source", lambda config: MemorySource(12, 0.0))
  bar = _Bar()
  loop.train(_config("stl", epochs=1, max_val=2), tmp_path / "run", log=lambda line: None,
             progress=bar)
  postfix = [kw for kind, kw in bar.events if kind == "postfix"]
  assert postfix[0] == {"status": "compiling the training step"}
  kinds = [kind for kind, _ in bar.events]
  assert kinds[:2] == ["postfix", "postfix"] and "update" in kinds  # both before any step counts
  first = postfix[1]["status"]
  assert first.startswith("first step (compiling, or loading from the compile cache) ")
  assert int(first.split()[-2]) >= 1 and first.endswith(" s")  # the 1.2 s stand-in at least
  assert all("epoch" in kw for kw in postfix[2:]) and len(postfix) > 3  # then the loss lines


def test_the_bars_rate_and_time_left_leave_out_the_first_steps_compile(monkeypatch, tmp_path):
  import io
  from tqdm import tqdm
  model, tx, step, evaluate = toys.tiny_steps(
      ModelConfig("psmnet", in_channels=3, maxdisp=16), "l2", 3e-2, None, stp.make_mesh())
  rates = []

  class Bar(tqdm):  # records the rate it shows after each update
    def update(self, n=1):
      super().update(n)
      rates.append((self.n, self.format_dict["rate"], self.format_dict["elapsed"]))

  bar = Bar(total=5, file=io.StringIO(), mininterval=0, miniters=1)
  clock = [bar.start_t]
  bar._time = lambda: clock[0]
  bar.last_print_t = clock[0]

  calls = []

  def timed(state, batch, weights):  # the bar's clock: 100 s to compile, then 1 s a step
    clock[0] += 1 if calls else 100
    calls.append(1)
    return step(state, batch, weights)

  monkeypatch.setattr(loop, "compiled_steps", lambda *a: (model, tx, timed, evaluate))
  monkeypatch.setattr(loop, "open_source", lambda config: MemorySource(12, 0.0))
  loop.train(_config("stl", epochs=1, max_val=2), tmp_path / "run", log=lambda line: None,
             progress=bar)
  assert [n for n, _, _ in rates] == [3, 5]  # log_every 3, 5 steps in the epoch
  assert [rate for _, rate, _ in rates] == [pytest.approx(1.0)] * 2  # steps 2-3, then 4-5
  assert rates[-1][2] == pytest.approx(104)  # elapsed stays the wall clock's


# A child process that runs train.py's main on TinyTwin/MemorySource and sends itself SIGINT
# once step N is fetched, from inside a garbage-collector callback of the main thread: where
# a KeyboardInterrupt is dropped ("Exception ignored in ... KeyboardInterrupt"), as it was when
# Ctrl-C landed in jax's `_xla_gc_callback` and training ran on to the end.
_SIGINT_CHILD = textwrap.dedent("""
    import gc, os, signal, sys, threading
    signal.signal(signal.SIGINT, signal.default_int_handler)  # a terminal's, however launched
    sys.path.insert(0, sys.argv[1])
    import toys, test_loop
    from sljax.train import cli, loop
    loop.compiled_steps = toys.tiny_steps
    loop.open_source = lambda config: test_loop.MemorySource()
    n, fetch, armed = int(sys.argv[2]), loop.fetch_metrics, []
    def fetch_then_arm(ctx, pending, loop_state):
      loop_state, last = fetch(ctx, pending, loop_state)
      if loop_state.step >= n and not armed:
        armed.append(True)
        gc.callbacks.append(in_gc)
        gc.collect()  # a collection now, in the main thread: the signal arrives in in_gc
      return loop_state, last
    def in_gc(phase, info):
      if threading.current_thread() is threading.main_thread() and armed[-1]:
        armed.append(False)
        os.kill(os.getpid(), signal.SIGINT)
    loop.fetch_metrics = fetch_then_arm
    raise SystemExit(cli.main(sys.argv[3:]))
""")


def test_ctrl_c_stops_after_the_step_and_resumes_exactly(tmp_path, monkeypatch):
  """A Ctrl-C that lands where Python drops a KeyboardInterrupt still stops the run after its
  step: exit 130, "interrupted (continue with --resume)", the SIGINT handler of before put
  back; --resume then ends bit-identical to an uninterrupted run."""
  monkeypatch.setattr(loop, "compiled_steps", toys.tiny_steps)
  monkeypatch.setattr(loop, "open_source", lambda config: MemorySource())
  flags = ["--size", "32", "--maxdisp", "16", "--epochs", "4", "--batch-size", "2", "--lr",
           "3e-2", "--max-val", "2", "--preset", "quick", "--log-every", "1", "--save-every",
           "4", "--ynn", "on", "--no-progress"]  # 6 steps per epoch, 24 in all
  env = toys.same_device_env()
  wd = tmp_path / "interrupted"
  proc = subprocess.run([sys.executable, "-c", _SIGINT_CHILD, str(TESTS), "9", *flags,
                         "--workdir", str(wd)], env=env, cwd=tmp_path, capture_output=True,
                        text=True, timeout=300)
  assert proc.returncode == 130, proc.stderr[-3000:]
  assert "train.py: interrupted (continue with --resume)" in proc.stderr
  assert "KeyboardInterrupt" not in proc.stderr  # nothing dropped, no traceback
  rows = (wd / METRICS_FILE).read_text().splitlines()
  assert 9 <= json.loads(rows[-1])["step"] < 24  # it stopped after the step it was in
  assert _final(wd)[0] == json.loads(rows[-1])["step"]  # ... and saved that step

  from sljax.train import cli  # pylint: disable=import-outside-toplevel
  handler = signal.getsignal(signal.SIGINT)
  assert cli.main([*flags, "--workdir", str(tmp_path / "full")]) == 0
  assert signal.getsignal(signal.SIGINT) is handler
  assert cli.main(["--workdir", str(wd), "--resume", "--no-progress"]) == 0
  _assert_same_run(tmp_path / "full", wd)


def test_a_ctrl_c_during_cleanup_still_interrupts_and_an_ignored_sigint_stays_ignored():
  """The flag set after the loop's last check (while async saves finish) raises on leaving the
  block, so a run is never reported done after a Ctrl-C; a background job that inherited
  SIGINT ignored keeps ignoring it. (The suite itself may run as such a job, `pytest &` in a
  script: each case sets the SIGINT disposition it is about.)"""
  from sljax.train.interrupt import deferred_interrupt
  previous = signal.signal(signal.SIGINT, signal.default_int_handler)
  try:
    with pytest.raises(KeyboardInterrupt):
      with deferred_interrupt() as flag:
        os.kill(os.getpid(), signal.SIGINT)  # the handler sets the flag; nothing checks it
        assert flag.asked
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with deferred_interrupt() as flag:
      os.kill(os.getpid(), signal.SIGINT)
    assert not flag.asked and signal.getsignal(signal.SIGINT) is signal.SIG_IGN
  finally:
    signal.signal(signal.SIGINT, previous)


def test_a_held_workdir_stops_every_process_of_a_multi_process_run(tmp_path):
  """Only process 0 takes the workdir's lock; when it is refused, process 1 must stop too
  (it waited for process 0 at the next sync until the coordinator gave up)."""
  run = _launcher(tmp_path)
  holder = toys.hold(tmp_path / "two", "sljax train (the first run)")
  try:
    procs = [run("two", 2, 0), run("two", 2, 1)]
    errs = [p.communicate(timeout=120)[1] for p in procs]
  finally:
    holder.kill()
    holder.wait()
  assert [p.returncode for p in procs] == [1, 1], errs
  assert f"in use by sljax train (the first run) (pid {holder.pid} on " in errs[0], errs[0][-2000:]
  assert (f"{tmp_path / 'two'}: in use by another run (process 0 found it held and names it)"
          in errs[1]), errs[1][-2000:]
  assert os.listdir(tmp_path / "two") == [files.LOCK_FILE]  # nothing written by either
