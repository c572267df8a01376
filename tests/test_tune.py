"""The per-CPU kernel tuner: the choice rule, the cache, the switch, and that every candidate
computes the same function."""

import json
import os

import jax
import numpy as np
import pytest

from sljax import cli, machine, tune


def timings(table):
  """A fake measurement: seconds per (impl, block, ynn, kind), 1.0 where the table is silent."""
  return lambda impl, block, kind, ynn: table.get((impl, block, ynn, kind), 1.0)


def test_default_kept_when_nothing_is_clearly_faster():
  best, table = tune.measure(timings=timings({("fast", 1 << 19, True, "train"): 0.97}))
  assert best == tune.KernelChoice(conv_impl="fast", block_values=tune.DEFAULT.block_values)
  assert len(table) == 2 * len(tune.candidates(True))


def test_a_clearly_faster_block_and_ynn_setting_win_per_kind():
  fast = {("fast", 1 << 19, True, "train"): 0.6, ("fast", 1 << 19, True, "forward"): 0.8,
          ("fast", 1 << 19, False, "forward"): 0.5, ("fast", 1 << 19, False, "train"): 0.9}
  best, _ = tune.measure(timings=timings(fast))
  assert best == tune.KernelChoice("fast", 1 << 19, forward_ynn=False, train_ynn=True)
  assert best.compiler_options("forward") == tune.YNN_OFF
  assert best.compiler_options("train") is None


def test_lax_wins_where_it_is_faster():
  # forward + train: lax 0.4 + 0.4 against the default's 1 + 1
  best, _ = tune.measure(timings=timings({("lax", tune.c3.BLOCK_VALUES, y, k): 0.4
                                         for y in (True, False) for k in ("forward", "train")}))
  assert best.conv_impl == "lax" and best.forward_ynn and best.train_ynn


def test_pair_is_chosen_on_the_sum_of_both_kinds():
  # block 32 Ki: much faster forward, slower training; the sum decides (0.5 + 1.2 < 2)
  slow_train = {("fast", 1 << 15, y, "train"): 1.2 for y in (True, False)}
  best, _ = tune.measure(timings=timings({("fast", 1 << 15, True, "forward"): 0.5, **slow_train}))
  assert best.block_values == 1 << 15
  best, _ = tune.measure(timings=timings({("fast", 1 << 15, True, "forward"): 0.9, **slow_train}))
  assert best.block_values == tune.DEFAULT.block_values


def test_format_table_marks_the_choice():
  best, table = tune.measure(timings=timings({("fast", 1 << 15, False, "forward"): 0.5,
                                              ("fast", 1 << 15, True, "train"): 0.5}))
  text = tune.format_table(table, best)
  assert text.count("(chosen)") == 2
  assert "| forward | fast | 32 | off | 500.0 | 1.00x (chosen) |" in text


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
  monkeypatch.setenv(tune.ENV_CACHE, str(tmp_path / "cache"))
  monkeypatch.delenv(tune.ENV_TUNE, raising=False)
  return tmp_path / "cache"


def test_cache_round_trip_keyed_by_cpu_and_versions(cache_dir):
  choice = tune.KernelChoice("fast", 1 << 15, False, True)
  path = tune.write_cache(tune.cache_key(), choice, [{"x": 1}], 12.3)
  assert path == cache_dir / "tune.json"
  assert tune.cached_choice() == choice
  key = tune.cache_key()
  assert machine.cpu_key() in key and jax.__version__ in key
  data = json.loads(path.read_text())
  assert data[key]["seconds"] == 12.3 and data[key]["table"] == [{"x": 1}]
  # another CPU kind's entry is kept beside it, not overwritten
  tune.write_cache("other-cpu jax-0 jaxlib-0", tune.DEFAULT, [], 1.0)
  assert set(json.loads(path.read_text())) == {key, "other-cpu jax-0 jaxlib-0"}
  assert tune.cached_choice() == choice


def test_corrupt_cache_is_ignored(cache_dir):
  cache_dir.mkdir()
  (cache_dir / "tune.json").write_text("{not json")
  assert tune.read_cache() == {} and tune.cached_choice() is None
  (cache_dir / "tune.json").write_text(json.dumps({tune.cache_key(): {"choice": {"bogus": 1}}}))
  assert tune.cached_choice() is None


def test_choice_measures_once_then_uses_the_cache(cache_dir, monkeypatch):
  calls = []
  picked = tune.KernelChoice("fast", 1 << 19, False, True)
  monkeypatch.setattr(tune, "measure", lambda: calls.append(1) or (picked, []))
  lines = []
  assert tune.choice(log=lines.append) == picked
  assert tune.choice(log=lines.append) == picked
  assert calls == [1] and (cache_dir / "tune.json").exists()
  assert "SLJAX_TUNE=0" in lines[0]


def test_choice_off_by_flag_or_environment(cache_dir, monkeypatch):
  monkeypatch.setattr(tune, "measure", lambda: pytest.fail("must not measure"))
  assert tune.choice(tune=False) == tune.DEFAULT
  monkeypatch.setenv(tune.ENV_TUNE, "0")
  assert tune.choice() == tune.DEFAULT
  assert not (cache_dir / "tune.json").exists()


def test_unwritable_cache_does_not_stop_a_run(cache_dir, monkeypatch):
  picked = tune.KernelChoice("fast", 1 << 15, True, True)
  monkeypatch.setattr(tune, "measure", lambda: (picked, []))

  def refuse(*args, **kwargs):
    raise OSError(30, "Read-only file system")
  monkeypatch.setattr(tune, "write_cache", refuse)
  lines = []
  assert tune.choice(log=lines.append) == picked
  assert "not cached" in lines[-1] and "Read-only" in lines[-1]


def test_every_candidate_computes_the_same_function():
  """Values and gradients of the workload under each candidate (tiny shapes, a block small
  enough to split the planes) against the lax convolutions without YNNPACK changes."""
  fn, args = tune.workload(batch=1, depth=4, size=8, channels=4)
  ref = {kind: tune._compiled(fn, args, "lax", tune.c3.BLOCK_VALUES, kind, True)(*args)
         for kind in ("forward", "train")}
  for impl, block, ynn in [("fast", 64, True), ("fast", 64, False), ("fast", 1 << 17, True),
                           ("lax", 1 << 17, False)]:
    for kind in ("forward", "train"):
      out = tune._compiled(fn, args, impl, block, kind, ynn)(*args)
      for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(ref[kind])):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-4, atol=1e-3)
  assert tune.c3.BLOCK_VALUES == tune.DEFAULT.block_values  # restored after tracing


def test_cli_show_without_cache_is_one_line(cache_dir, capsys):
  assert cli.main(["tune", "--show"]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and "no choice cached" in err[0] and "sljax tune" in err[0]


def test_cli_show_prints_the_cached_table(cache_dir, capsys):
  best, table = tune.measure(timings=timings({("fast", 1 << 15, False, "forward"): 0.5}))
  tune.write_cache(tune.cache_key(), best, table, 42.0)
  assert cli.main(["tune", "--show"]) == 0
  out = capsys.readouterr().out
  assert "in 42.0 s" in out and "(chosen)" in out and "blocks of 32 Ki" in out
  assert os.path.basename(str(tune.cache_path())) in out
