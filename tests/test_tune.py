"""The per-CPU compiler tuner (sljax.runtime.choices): the choice rule, the cache, the switch, that both
settings compute the same function, and that training and inference use the choice."""

import dataclasses
import importlib
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sljax import cli, inference
from sljax.models import checkpoint as ckpt
from sljax.nets import ModelConfig
from sljax.nets.model_config import init_variables
from sljax.runtime import choices, compile_cache, machine, measuring
from sljax.train import loop
from sljax.train import step as stp
from sljax.train.config import QUICK, config_from_json
from sljax.train.setup import resolve_ynn


def fake(table):
  """A fake measurement: seconds per (kind, ynn), 1.0 where the table is silent."""
  return lambda kind, ynn: table.get((kind, ynn), 1.0)


def test_names_round_trip():
  for name in ("on", "off", "forward-off", "train-off"):
    assert choices.KernelChoice.from_name(name).name == name
  assert choices.DEFAULT.name == "on"
  assert choices.KernelChoice(False, True).compiler_options("forward") == choices.YNN_OFF
  assert choices.KernelChoice(False, True).compiler_options("train") is None


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="XLA:CPU's fusions")
def test_off_keeps_ynnpack_for_reductions_only():
  """'off' hands BatchNorm-like statistics to YNNPACK (XLA's own reduce-window is ~10x slower)
  and keeps the convolution XLA's; both compute what float64 NumPy does."""
  rng = np.random.default_rng(0)
  x = rng.standard_normal((2, 6, 40, 40, 32)).astype(np.float32)
  k = rng.standard_normal((3, 3, 32, 32)).astype(np.float32) / 16

  def program(x, k):
    y = jax.lax.conv_general_dilated(x.reshape(12, 40, 40, 32), k, (1, 1), "SAME",
                                     dimension_numbers=("NHWC", "HWIO", "NHWC"))
    return y.sum(axis=(0, 1, 2)), (y * y).sum(axis=(0, 1, 2))

  options = choices.KernelChoice.from_name("off").compiler_options("train")
  compiled = jax.jit(program, compiler_options=options).lower(x, k).compile()
  text = compiled.as_text()
  ynn = [line for line in text.splitlines() if "__ynn_fusion" in line and " fusion(" in line]
  assert ynn and all("reduce" in line for line in ynn)  # the sums, not the convolution
  assert "reduce-window" not in text
  assert any("convolution(" in line for line in text.splitlines())
  y = np.zeros((12, 40, 40, 32))
  xp = np.pad(x.reshape(12, 40, 40, 32).astype(np.float64), ((0, 0), (1, 1), (1, 1), (0, 0)))
  for i, j in np.ndindex(3, 3):
    y += np.einsum("bhwc,co->bhwo", xp[:, i:i + 40, j:j + 40], k[i, j].astype(np.float64))
  s1, s2 = compiled(x, k)
  np.testing.assert_allclose(s1, y.sum(axis=(0, 1, 2)), rtol=1e-4, atol=1e-3)
  np.testing.assert_allclose(s2, (y * y).sum(axis=(0, 1, 2)), rtol=1e-4)


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="XLA:CPU's fusions")
def test_the_measured_programs_take_the_choice_they_time(monkeypatch):
  """`sljax tune` times what runs: each program compiled with that setting's options (off:
  YNNPACK for the reductions only), the training one traced with that setting's kernel-gradient
  blocks (choices.grad_blocks_for), the forward one with a plain program's (no gradient runs
  there); and it runs."""
  from sljax import kernels
  seen, jit = {}, jax.jit
  monkeypatch.setattr(choices, "grad_blocks_for", lambda k: 1000 + k.train_ynn)
  kernels.blocks.context_free_blocks.cache_clear()
  monkeypatch.setattr(kernels.blocks, "context_free_blocks", lambda: 7)

  def spy(fn, **kw):
    seen["options"] = kw.get("compiler_options")
    return jit(fn, **kw)
  monkeypatch.setattr(jax, "jit", spy)
  x = np.random.default_rng(1).standard_normal((8, 64)).astype(np.float32)

  def traced(kind):
    def program(a):
      seen[kind] = kernels.grad_block_values(7)
      return (a * a).sum(axis=0)
    return program
  fns = {kind: traced(kind) for kind in choices.KINDS}
  for kind in choices.KINDS:
    for ynn in (True, False):
      compiled = measuring._compiled(fns, (x,), kind, ynn)  # pylint: disable=protected-access
      assert seen["options"] == (None if ynn else choices.YNN_OFF), (kind, ynn)
      assert seen[kind] == (1000 + ynn if kind == "train" else 7), (kind, ynn, seen)
      np.testing.assert_allclose(compiled(x), (x.astype(np.float64) ** 2).sum(0), rtol=1e-5)


def test_default_kept_unless_clearly_faster():
  best, table = measuring.measure(timings=fake({("forward", False): 0.97, ("train", False): 0.96}))
  assert best == choices.DEFAULT  # 3-4% is within the margin
  assert [(r["kind"], r["ynn"]) for r in table] == [("forward", True), ("forward", False),
                                                     ("train", True), ("train", False)]
  best, _ = measuring.measure(timings=fake({("forward", False): 0.5}))
  assert best == choices.KernelChoice(forward_ynn=False, train_ynn=True) and best.name == "forward-off"
  best, _ = measuring.measure(timings=fake({("train", False): 0.9, ("forward", True): 0.5}))
  assert best.name == "train-off"


def test_a_choice_cached_under_another_rule_is_measured_again(cache_dir):
  best, table = measuring.measure(timings=fake({("forward", False): 0.5}))
  path = choices.write_measurement(choices.measurement_key(), best, table, 1.0)
  assert choices.measured_choice() == best
  data = json.loads(path.read_text())
  data[choices.measurement_key()]["rule"] = choices.RULE - 1
  path.write_text(json.dumps(data))
  assert choices.measured_choice() is None


def test_a_round_that_disagrees_keeps_the_default():
  on = [1.0, 1.0, 1.0, 1.0, 1.0]
  consistent = {("forward", True): on, ("forward", False): [0.6, 0.7, 0.62, 0.65, 0.9],
                ("train", True): on, ("train", False): [0.9, 0.91, 0.92, 0.9, 0.93]}
  assert measuring.choose(consistent) == choices.KernelChoice(forward_ynn=False, train_ynn=False)
  # Faster in the median round, slower in one (a burst of load): not consistent evidence.
  burst = {**consistent, ("forward", False): [0.6, 0.7, 1.05, 0.65, 0.6]}
  assert measuring.choose(burst).forward_ynn
  # Faster in every round but within the margin in the median one.
  small = {**consistent, ("train", False): [0.99, 0.9, 0.97, 0.96, 0.98]}
  assert measuring.choose(small).train_ynn


def test_verdict_by_hand():
  assert measuring.verdict([0.6, 0.7, 0.62, 0.65, 0.9]) == "off"
  assert measuring.verdict([0.6, 0.7, 1.05, 0.65, 0.6]) == "undecided"  # median 0.65, one round 1.05
  assert measuring.verdict([0.99, 0.9, 0.97, 0.96, 0.98]) == "on"  # median 0.97: within 5%
  assert measuring.verdict([0.7, 1.2, 1.1, 1.3, 0.6]) == "on"      # median 1.1


def scripted(batches_of_forward_off):
  """A fake measurement whose forward-off calls follow a script (one list per batch of 5
  rounds); every other program takes 1.0 s. Returns (timings, calls made per program)."""
  script = [t for batch in batches_of_forward_off for t in batch]
  calls = {}
  def timings(kind, ynn):
    calls[(kind, ynn)] = calls.get((kind, ynn), 0) + 1
    if (kind, ynn) == ("forward", False):
      return script[calls[(kind, ynn)] - 1]
    return 1.0
  return timings, calls


def test_rounds_that_disagree_are_measured_again():
  burst = [0.7, 0.7, 1.05, 0.7, 0.66]  # a burst of load in the third round
  timings, calls = scripted([burst, [0.7, 0.71, 0.69, 0.72, 0.7]])
  best, table = measuring.measure(timings=timings)
  assert best.name == "forward-off"
  # Only the undecided kind is measured again, on and off alike; training is decided at once.
  assert calls == {("forward", True): 10, ("forward", False): 10,
                   ("train", True): 5, ("train", False): 5}
  rows = {(r["kind"], r["ynn"]): r for r in table}
  assert rows[("forward", False)]["batches"] == 2 and rows[("train", False)]["batches"] == 1
  assert rows[("forward", False)]["off_vs_on"] == [0.7, 0.71, 0.69, 0.72, 0.7]  # the last batch
  assert rows[("forward", False)]["verdict"] == "off" and measuring.undecided_note(table) == ""
  assert "forward: the first rounds disagreed, measured again (2 batches" in \
      measuring.format_table(table, best)


@pytest.fixture
def on_cpu(monkeypatch):
  """choice() tunes only when jax computes on the CPU; its logic is tested wherever the suite
  runs (on a GPU too), with the measurement scripted."""
  monkeypatch.setattr(choices.jax, "default_backend", lambda: "cpu")


def test_rounds_that_keep_disagreeing_keep_the_default_and_say_so(tmp_path, monkeypatch, on_cpu,
                                                                   capsys):
  burst = [0.7, 0.7, 1.05, 0.7, 0.66]
  timings, calls = scripted([burst] * (1 + measuring.RETRIES))
  best, table = measuring.measure(timings=timings)
  assert best == choices.DEFAULT
  assert calls[("forward", False)] == 5 * (1 + measuring.RETRIES)
  note = measuring.undecided_note(table)
  assert note.startswith("forward: the rounds disagreed") and "sljax tune" in note
  # `sljax tune` prints it, so a user knows the default was kept, not chosen.
  monkeypatch.setenv(compile_cache.ENV_DIR, str(tmp_path))
  monkeypatch.setattr(measuring, "tuned",
                      lambda workload, repeats, blocks: (best, table, None, None))
  assert cli.main(["tune", "--repeats", "1"]) == 0
  assert note in capsys.readouterr().out


def test_format_table_marks_the_choice():
  best, table = measuring.measure(timings=fake({("forward", False): 0.5}))
  text = measuring.format_table(table, best)
  assert text.count("(chosen)") == 2
  assert "| forward | off | 500.0 | 1.00x (chosen) | 0.50-0.50 |" in text
  assert "| forward | on | 1000.0 | 2.00x |  |" in text


@pytest.fixture
def cache_dir(tmp_path, monkeypatch, on_cpu):
  monkeypatch.setenv(compile_cache.ENV_DIR, str(tmp_path / "cache"))
  monkeypatch.setenv(choices.ENV_TUNE, "1")
  # The load beside a fake measurement is no measurement: the tests that want one set it.
  monkeypatch.setattr(choices.machine, "cpu_snapshot", lambda: None)
  return tmp_path / "cache"


def test_cache_round_trip_keyed_by_cpu_and_versions(cache_dir):
  choice = choices.KernelChoice(False, True)
  path = choices.write_measurement(choices.measurement_key(), choice, [{"x": 1}], 12.3)
  assert path == cache_dir / "tune.json"
  assert choices.measured_choice() == choice
  key = choices.measurement_key()
  assert machine.cpu_key() in key and jax.__version__ in key
  data = json.loads(path.read_text())
  assert data[key]["seconds"] == 12.3 and data[key]["table"] == [{"x": 1}]
  choices.write_measurement("other-cpu jax-0 jaxlib-0", choices.DEFAULT, [], 1.0)  # kept beside it
  assert set(json.loads(path.read_text())) == {key, "other-cpu jax-0 jaxlib-0"}
  assert choices.measured_choice() == choice


def test_corrupt_cache_is_ignored(cache_dir):
  cache_dir.mkdir()
  (cache_dir / "tune.json").write_text("{not json")
  assert choices.read_measurements() == {} and choices.measured_choice() is None
  (cache_dir / "tune.json").write_text(json.dumps({choices.measurement_key(): {"choice": {"bogus": 1}}}))
  assert choices.measured_choice() is None


def test_a_run_takes_the_table_and_never_measures(cache_dir, monkeypatch):
  """Issue 49: a CPU kind measured before starts at once with its choice, one never measured
  with UNKNOWN; nothing is measured or written, and the line says how to measure."""
  monkeypatch.setattr(measuring, "measure", lambda *_, **__: pytest.fail("a run must not measure"))
  monkeypatch.setattr(choices, "write_measurement", lambda *a, **k: pytest.fail("nor write"))
  monkeypatch.setitem(choices.KNOWN, "amd-epyc-f26-m2-avx512", ("forward-off", "Zen 5, by hand"))
  monkeypatch.setattr(choices.machine, "cpu_key", lambda: "amd-epyc-f26-m2-avx512")
  lines = []
  assert choices.choice(log=lines.append) == choices.KernelChoice(False, True)  # the table's entry
  assert "measured on this CPU kind (Zen 5, by hand)" in lines[-1] and "`sljax tune`" in lines[-1]
  monkeypatch.setattr(choices.machine, "cpu_key", lambda: "amd-epyc-f25-m1-avx2")
  assert choices.choice(log=lines.append) == choices.KernelChoice(False, False)  # Zen 3: off
  monkeypatch.setattr(choices, "UNKNOWN", "train-off")
  monkeypatch.setattr(choices.machine, "cpu_key", lambda: "some-future-cpu-avx10")
  assert choices.choice(log=lines.append) == choices.KernelChoice(True, False)
  assert "not measured yet" in lines[-1]
  assert not (cache_dir / "tune.json").exists()


def test_the_table_names_real_choices_and_cpu_keys():
  for key, (name, where) in choices.KNOWN.items():
    assert choices.KernelChoice.from_name(name).name == name and where
    assert key == key.lower() and key.endswith(("-avx2", "-avx512"))  # cpu_key's form
  assert choices.UNKNOWN in choices.NAMES.values()
  cpu = {"model": "AMD EPYC", "family": 25, "model_number": 1, "isa": ["AVX2"]}
  assert machine.cpu_key(cpu) in choices.KNOWN  # the kind of the fresh Zen 3


def test_a_measured_entry_wins_over_the_table(cache_dir, monkeypatch):
  monkeypatch.setattr(choices.machine, "cpu_key", lambda: "amd-epyc-f25-m1-avx2")  # table: off
  measured = choices.KernelChoice(True, False)
  choices.write_measurement(choices.measurement_key(), measured, [], 1.0)
  lines = []
  assert choices.choice(log=lines.append) == measured and lines == []


def test_choice_off_by_flag_or_environment(cache_dir, monkeypatch):
  monkeypatch.setattr(measuring, "measure", lambda *_, **__: pytest.fail("must not measure"))
  assert choices.choice(tune=False) == choices.DEFAULT
  monkeypatch.setenv(choices.ENV_TUNE, "0")
  assert choices.choice() == choices.DEFAULT
  assert not (cache_dir / "tune.json").exists()


def test_no_tuning_off_the_cpu(tmp_path, monkeypatch):
  """On an accelerator the CPU kernels' choice does not matter: the default, nothing measured
  or cached."""
  monkeypatch.setenv(compile_cache.ENV_DIR, str(tmp_path))
  monkeypatch.setenv(choices.ENV_TUNE, "1")
  monkeypatch.setattr(choices.jax, "default_backend", lambda: "gpu")
  monkeypatch.setattr(measuring, "measure", lambda *_, **__: pytest.fail("must not measure"))
  assert choices.choice() == choices.DEFAULT
  assert not (tmp_path / "tune.json").exists()


def test_both_settings_compute_the_same_function():
  """Values and gradients of a UNet (2D convolutions, the fusions' domain) with the fusions on
  and off agree to float32 rounding. (A randomly initialised PSMNet is a poor probe: its
  near-flat disparity softmax turns rounding into tenths of a pixel at ties.)"""
  from sljax.nets import build_model
  model = build_model("unet-disp", in_channels=3, depth=2, base_width=4)
  rng = np.random.default_rng(0)
  x, y = (rng.random((2, 16, 16, 3), np.float32) for _ in range(2))
  variables = init_variables(model, 0, 16, 16, 3)

  def f(params):
    out = model.apply({**variables, "params": params}, x, y, train=False)["disparity"]
    return (out ** 2).mean(), out
  results = []
  for choice in (choices.DEFAULT, choices.KernelChoice(forward_ynn=False, train_ynn=False)):
    fwd = jax.jit(f, compiler_options=choice.compiler_options("forward"))
    grad = jax.jit(jax.grad(lambda p: f(p)[0]), compiler_options=choice.compiler_options("train"))
    results.append((np.asarray(fwd(variables["params"])[1]), grad(variables["params"])))
  (a, ga), (b, gb) = results
  np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)
  for u, v in zip(jax.tree.leaves(ga), jax.tree.leaves(gb)):
    u, v = np.asarray(u), np.asarray(v)  # sums of many terms: rounding relative to the leaf
    np.testing.assert_allclose(u, v, rtol=1e-4, atol=1e-4 * np.abs(v).max())


def test_training_steps_get_the_choice_as_compiler_options(monkeypatch):
  seen = {}
  monkeypatch.setattr(stp, "make_train_step", lambda *a, **k: seen.setdefault("train", k["compiler_options"]))
  monkeypatch.setattr(stp, "make_eval_step", lambda *a, **k: seen.setdefault("eval", k["compiler_options"]))
  loop.compiled_steps.__wrapped__(ModelConfig("unet-disp", 1, 16), "l2", 1e-3, None, None,
                                  "forward-off")
  assert seen == {"train": None, "eval": choices.YNN_OFF}


def test_auto_resolves_once_and_a_resume_keeps_the_saved_choice(tmp_path, monkeypatch):
  monkeypatch.setattr(choices, "choice", lambda log=print: choices.KernelChoice(False, True))
  config = dataclasses.replace(QUICK, ynn="auto")
  assert resolve_ynn(config, tmp_path, False, False, print).ynn == "forward-off"
  off = dataclasses.replace(config, ynn="off")
  assert resolve_ynn(off, tmp_path, False, False, print).ynn == "off"
  (tmp_path / ckpt.CONFIG_FILE).write_text(json.dumps({"ynn": "train-off"}))
  assert resolve_ynn(config, tmp_path, True, False, print).ynn == "train-off"  # kept
  # A run that replaces the old one (--overwrite) tunes anew, even a damaged config.json.
  (tmp_path / ckpt.CONFIG_FILE).write_text("{damaged")
  assert resolve_ynn(config, tmp_path, True, True, print).ynn == "forward-off"
  # a config.json written before the option existed ran with XLA's default
  assert config_from_json({"model": "psmnet"}).ynn == "on"


def test_inference_runs_its_forward_with_the_choice(monkeypatch):
  got = []
  real = inference.predictor.forward
  monkeypatch.setattr(inference.predictor, "forward", lambda *a: got.append(a[-1]) or real(*a))
  kw = {"in_channels": 1, "depth": 2, "base_width": 4}
  from sljax.nets import build_model
  model = build_model("unet-disp", **kw)
  variables = init_variables(model, 0, 16, 16, 1)
  pred = inference.make_predictor("unet-disp", kw, variables, mode="pad",
                                  kernels=choices.KernelChoice(forward_ynn=False))
  out = pred(np.zeros((16, 16), np.float32), np.zeros((16, 16), np.float32))
  assert out["disparity"].shape == (16, 16) and got and all(v is False for v in got)


def test_cli_show_without_a_measurement_names_what_runs_take(cache_dir, capsys, monkeypatch):
  monkeypatch.setattr(choices.machine, "cpu_key", lambda: "amd-epyc-f26-m2-avx512")
  assert cli.main(["tune", "--show"]) == 0
  out = capsys.readouterr().out
  assert "not measured on this machine: runs take YNNPACK fusions off in forward programs, off " \
         "in training (--ynn off), measured on this CPU kind (Zen 5" in out


def test_cli_show_prints_the_cached_table(cache_dir, capsys):
  best, table = measuring.measure(timings=fake({("forward", False): 0.5}))
  choices.write_measurement(choices.measurement_key(), best, table, 42.0)
  assert cli.main(["tune", "--show"]) == 0
  out = capsys.readouterr().out
  assert "in 42.0 s" in out and "(chosen)" in out and "--ynn forward-off" in out
  assert Path(str(choices.measurements_path())).name in out


def test_cli_show_an_entry_edited_into_nonsense_is_one_line(cache_dir, capsys):
  """A choice that is not true/false (a hand edit): one line, as runs ignore it."""
  choices.write_measurement(choices.measurement_key(), choices.KernelChoice(True, True), [], 1.0)
  path = choices.measurements_path()
  data = json.loads(path.read_text())
  data[choices.measurement_key()]["choice"]["forward_ynn"] = "yes"
  path.write_text(json.dumps(data))
  assert cli.main(["tune", "--show"]) == 2
  err = capsys.readouterr().err
  assert "has no readable choice" in err and len(err.strip().splitlines()) == 1
  assert choices.measured_choice() is None


def test_cli_show_a_hand_written_entry_shows_its_note(cache_dir, capsys):
  """An entry whose table holds a note, not measurements (was KeyError 'ynn')."""
  note = "set by hand to the setting of every earlier cell, not measured"
  choices.write_measurement(choices.measurement_key(), choices.KernelChoice(True, True), [{"note": note}], 0.0)
  assert cli.main(["tune", "--show"]) == 0
  out = capsys.readouterr().out
  assert f"in 0.0 s\n\nnote: {note}\n\nchoice: " in out
  # A measured table with a note row keeps its table and adds the note.
  best, table = measuring.measure(timings=fake({("forward", False): 0.5}))
  text = measuring.format_table(table + [{"note": "checked by hand"}], best)
  assert text.startswith(measuring.format_table(table, best)) and text.endswith("\n\nnote: checked "
                                                                            "by hand")
  # A measurement edited into nonsense is shown as a note, not a TypeError.
  bad = dict(table[0], seconds="fast")
  text = measuring.format_table([bad] + table[1:], best)
  assert f"note: {bad}" in text and "| forward | on |" not in text
  path = choices.measurements_path()
  path.write_text(json.dumps({choices.measurement_key(): {"choice": "on", "table": []}}))
  assert cli.main(["tune", "--show"]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and "has no readable choice; run `sljax tune`" in err[0]


def test_a_choice_measured_beside_other_work_is_provisional(cache_dir, monkeypatch, capsys):
  """Load through the whole measurement fools every round alike (a 2-core Zen 4 beside a
  training run chose the fusions, idle it drops them): `sljax tune` keeps such a choice and
  says so; it serves runs while the machine stays busy, the table once it is quiet."""
  snapshots = iter([(0.0, 0.0, 0.0), (100.0, 90.0, 50.0)])  # others: 40 of 100 CPU-seconds
  monkeypatch.setattr(choices.machine, "cpu_snapshot", lambda: next(snapshots))
  monkeypatch.setattr(choices.machine, "cpu_key", lambda: "amd-epyc-f25-m1-avx2")  # table: off
  busy_pick = choices.KernelChoice(True, True)
  monkeypatch.setattr(measuring, "measure", lambda *_, **__: (busy_pick, []))
  assert cli.main(["tune", "--repeats", "1"]) == 0
  out = capsys.readouterr().out
  assert "40% of the CPUs" in out and "provisional" in out
  assert choices.read_measurements()[choices.measurement_key()]["others"] == 0.4
  monkeypatch.setattr(measuring, "measure", lambda *_, **__: pytest.fail("a run must not measure"))
  lines = []
  # Still busy: the provisional choice serves.
  monkeypatch.setattr(choices.machine, "others_now", lambda: 0.5)
  assert choices.choice(log=lines.append) == busy_pick and lines == []
  # Quiet now: the CPU kind's table, and the line says how to measure.
  monkeypatch.setattr(choices.machine, "others_now", lambda: 0.01)
  assert choices.choice(log=lines.append) == choices.KernelChoice(False, False)
  assert "`sljax tune`" in lines[-1]
  # Measured again on the quiet machine: final, no look at the load any more.
  snapshots = iter([(0.0, 0.0, 0.0), (100.0, 51.0, 50.0)])
  monkeypatch.setattr(measuring, "tuned", lambda workload, repeats, blocks: (
      choices.KernelChoice(False, True), [], 0.01, None))
  assert cli.main(["tune", "--repeats", "1"]) == 0
  monkeypatch.setattr(choices.machine, "others_now", lambda: pytest.fail("a kept choice is final"))
  assert choices.choice(log=lines.append) == choices.KernelChoice(False, True)


def test_busy_threshold_and_unknown_load():
  assert choices.busy(0.4) and not choices.busy(choices.BUSY) and not choices.busy(0.02)
  assert not choices.busy(None) and not choices.busy("high")  # unknown (no /proc/stat): not provisional
  for odd in (5.0, float("inf"), float("nan"), -0.2, True):  # edited by hand: no share
    assert not choices.busy(odd)
  assert measuring.busy_note(None) == "" and measuring.busy_note(0.05) == ""


def test_cli_tune_says_the_load_beside_it(cache_dir, capsys, monkeypatch):
  best, table = measuring.measure(timings=fake({("forward", False): 0.5}))
  monkeypatch.setattr(measuring, "tuned", lambda workload, repeats, blocks: (best, table, 0.62, None))
  assert cli.main(["tune", "--repeats", "1"]) == 0
  out = capsys.readouterr().out
  assert "other processes using 62% of the CPUs meanwhile" in out and "provisional" in out
  assert choices.read_measurements()[choices.measurement_key()]["others"] == 0.62
  assert cli.main(["tune", "--show"]) == 0
  out = capsys.readouterr().out
  assert "other processes using 62% of the CPUs meanwhile" in out and "provisional" in out


def test_grad_blocks_follow_the_fusions_unless_measured_here(cache_dir, monkeypatch):
  """The kernel gradients' blocks: 1 Mi values without the fusions, 128 Ki with them (every kind
  measured agrees); `sljax tune`'s measurement for the same fusions' setting wins; an entry of
  another setting, rule or an edited value does not; off the CPU none."""
  on, off = choices.KernelChoice(), choices.KernelChoice.from_name("off")
  assert choices.grad_blocks_for(on) == 1 << 17 and choices.grad_blocks_for(off) == 1 << 20
  blocks = {"train_ynn": True, "values": 1 << 20, "table": []}
  choices.write_measurement(choices.measurement_key(), on, [], 1.0, blocks=blocks)
  assert choices.grad_blocks_for(on) == 1 << 20  # measured for the fusions on
  assert choices.grad_blocks_for(off) == 1 << 20  # the rule: not measured for off
  for edit in ({"values": 12345}, {"values": "1048576"}, {"train_ynn": 1}, {"values": True}):
    choices.write_measurement(choices.measurement_key(), on, [], 1.0, blocks={**blocks, **edit})
    assert choices.grad_blocks_for(on) == 1 << 17, edit
  choices.write_measurement(choices.measurement_key(), on, [], 1.0, blocks=blocks)
  data = json.loads(choices.measurements_path().read_text())
  data[choices.measurement_key()]["rule"] = choices.RULE - 1
  choices.measurements_path().write_text(json.dumps(data))
  assert choices.grad_blocks_for(on) == 1 << 17
  monkeypatch.setattr(choices.jax, "default_backend", lambda: "gpu")
  assert choices.grad_blocks_for(on) is None


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the CPU kernels' blocks")
def test_a_gradient_traced_without_a_context_takes_this_machines_blocks(cache_dir):
  """A plain `jax.jit(jax.grad(...))` takes the blocks training takes with XLA's default options
  (the fusions on), `sljax tune`'s measured ones included; a context still wins, and so does a
  layer's own choice; the value is the same to float rounding whatever the blocks."""
  from sljax import kernels
  default = kernels.BLOCK_VALUES  # a layer that chose nothing
  kernels.blocks.context_free_blocks.cache_clear()
  try:
    assert kernels.grad_block_values(default) == choices.grad_blocks_for(choices.DEFAULT)
    assert choices.grad_blocks_for(choices.DEFAULT) == 1 << 17
    with kernels.grad_blocks(5):
      assert kernels.grad_block_values(default) == kernels.grad_block_values(7) == 5
    blocks = {"train_ynn": True, "values": 1 << 20, "table": []}
    choices.write_measurement(choices.measurement_key(), choices.DEFAULT, [], 1.0, blocks=blocks)
    kernels.blocks.context_free_blocks.cache_clear()  # read once per process
    assert kernels.grad_block_values(default) == 1 << 20
    assert kernels.grad_block_values(7) == 7  # the layer's own choice
    seen = []
    real = kernels.blocks.grad_block_values

    def spy(values):
      seen.append(real(values))
      return seen[-1]
    rng = np.random.default_rng(0)
    x = rng.standard_normal((1, 4, 8, 8, 3)).astype(np.float32)
    k = rng.standard_normal((3, 3, 3, 3, 4)).astype(np.float32)
    loss = lambda k: jnp.sum(kernels.conv3d(x, k, (1, 1, 1), ((1, 1),) * 3) ** 2)
    ref = lambda k: jnp.sum(kernels.lax_conv3d(x, k, (1, 1, 1), ((1, 1),) * 3) ** 2)
    conv3d_module = importlib.import_module("sljax.kernels.conv3d")  # the name is a function too
    with pytest.MonkeyPatch.context() as mp:
      mp.setattr(conv3d_module, "grad_block_values", spy)
      g = jax.jit(jax.grad(loss))(k)
    assert seen and set(seen) == {1 << 20}
    np.testing.assert_allclose(g, jax.grad(ref)(k), rtol=1e-4, atol=1e-3)
  finally:
    kernels.blocks.context_free_blocks.cache_clear()


def _fake_blocks(table):
  """A fake block timing: seconds per block size, 1.0 where the table is silent."""
  return lambda values: table.get(values, 1.0)


def test_blocks_measured_keep_the_default_unless_clearly_faster():
  small, large = choices.BLOCK_CANDIDATES
  got = measuring.measure_blocks(None, train_ynn=False, timings=_fake_blocks({small: 1.6}))
  assert got["values"] == large and got["train_ynn"] is False  # the default without fusions
  got = measuring.measure_blocks(None, train_ynn=True, timings=_fake_blocks({large: 0.97}))
  assert got["values"] == small  # 3% is within the margin
  got = measuring.measure_blocks(None, train_ynn=True, timings=_fake_blocks({large: 0.6}))
  assert got["values"] == large
  assert [r["values"] for r in got["table"]] == list(choices.BLOCK_CANDIDATES)
  times = iter([1.0, 0.6, 1.0, 0.6, 1.0, 1.2])  # rounds (small, large): the last disagrees
  got = measuring.measure_blocks(None, train_ynn=True, timings=lambda values: next(times))
  assert got["values"] == small
  table = measuring.format_blocks(measuring.measure_blocks(None, False, timings=_fake_blocks({})))
  assert "1024 Ki values (chosen)" in table and "128 Ki values" in table
  assert measuring.format_blocks({"values": "x", "table": []}) == ""


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="XLA:CPU's fusions")
def test_the_block_measurement_compiles_what_it_times(monkeypatch):
  """Each candidate is compiled with the training fusions' options and traced in its blocks."""
  from sljax import kernels
  seen, jit = [], jax.jit

  def spy(fn, **kw):
    seen.append(kw.get("compiler_options"))
    return jit(fn, **kw)
  monkeypatch.setattr(jax, "jit", spy)
  traced = []
  x = np.ones((4, 4), np.float32)

  def workload():
    def fn(a):
      traced.append(kernels.grad_block_values(7))
      return a * 2
    return fn, (x,)
  got = measuring.measure_blocks(workload, train_ynn=False, repeats=1)
  assert seen == [choices.YNN_OFF] * 2 and traced == list(choices.BLOCK_CANDIDATES)
  assert got["values"] in choices.BLOCK_CANDIDATES and len(got["table"]) == 2


def test_cli_tune_keeps_and_shows_the_blocks_it_measured(cache_dir, capsys, monkeypatch):
  """`sljax tune` prints the block table, keeps the size where training finds it, and --show
  prints it again."""
  best, table = measuring.measure(timings=fake({("train", False): 0.5, ("forward", False): 0.5}))
  # Without the fusions the rule says 1 Mi; this machine measured 128 Ki faster.
  blocks = measuring.measure_blocks(None, best.train_ynn,
                                  timings=_fake_blocks({choices.BLOCK_CANDIDATES[0]: 0.5}))
  monkeypatch.setattr(measuring, "tuned", lambda workload, repeats, gradients: (
      best, table, 0.0, blocks))
  assert cli.main(["tune", "--repeats", "1"]) == 0
  out = capsys.readouterr().out
  assert "| 128 Ki values (chosen) |" in out
  assert "kernel-gradient blocks: 128 Ki values in training programs with the fusions off" in out
  assert choices.grad_blocks_for(best) == 1 << 17  # the measurement, not the rule
  assert cli.main(["tune", "--show"]) == 0
  assert "| 128 Ki values (chosen) |" in capsys.readouterr().out


def test_the_block_workload_is_the_layers_gradients():
  """`gradient_workload` (what `sljax tune` times the block sizes on) is the gradient of its
  layers' summed squares, input and kernel, as lax's convolutions give it."""
  from sljax import kernels
  from sljax.nets.workload import gradient_workload
  layers = (("conv", 1, 4, 6, 6, 3, 2, 1), ("convT", 1, 2, 3, 3, 2, 2, 2))
  fn, args = gradient_workload(layers)

  def reference(args):
    (x0, k0), (x1, k1) = args
    y0 = kernels.lax_conv3d(x0, k0, (1, 1, 1), ((1, 1),) * 3)
    y1 = kernels.lax_conv3d(x1, k1, (1, 1, 1), ((1, 2),) * 3, (2, 2, 2))
    return jnp.sum(y0 * y0) + jnp.sum(y1 * y1)
  got, want = fn(*args), jax.grad(reference)(*args)
  for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4)
