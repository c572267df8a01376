"""Several checkpoints with different validation MAEs: which one is kept, loaded and served.

Every other test has one checkpoint, so picking the best by the *highest* MAE, or keeping the
wrong ones, passed them all. Each checkpoint's parameters here are filled with its own step
number, so the step that comes back is visible in the values.
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sljax.inference
from sljax.nets import build_model
from sljax.models import checkpoint as ckpt
from sljax.models import load as trained

MODEL, KWARGS = "unet-disp", {"depth": 2, "base_width": 4, "gray": True}
# step -> validation MAE (None: a mid-epoch checkpoint, saved without validation)
RUN = {1: 0.9, 2: 0.4, 3: 0.7, 4: None, 5: 0.6}


def _variables(value: float) -> dict:
  shapes = jax.eval_shape(
      lambda x: build_model(MODEL, **KWARGS).init(jax.random.PRNGKey(0), x, x),
      jax.ShapeDtypeStruct((1, 16, 16, 1), jnp.float32))
  return jax.tree.map(lambda s: jnp.full(s.shape, value, s.dtype), shapes)


def _workdir(tmp_path, run, keep):
  workdir = tmp_path / "run"
  workdir.mkdir()
  (workdir / ckpt.CONFIG_FILE).write_text(json.dumps({
      "strategy": "stl", "net": MODEL, "model_kwargs": KWARGS, "size": [16, 16],
      "gray": True}))
  manager = ckpt.make_manager(workdir / ckpt.CHECKPOINT_DIR, keep=keep)
  for step, mae in run.items():
    ckpt.save(manager, step, dict(_variables(float(step)), step=jnp.int32(step)),
              {"step": step}, mae)
    manager.wait_until_finished()
  manager.close()
  return workdir


def _steps(workdir):
  return sorted(int(p.name) for p in (workdir / ckpt.CHECKPOINT_DIR).iterdir()
                if p.name.isdigit())


def _value(variables):
  """The one value every leaf holds (the step whose checkpoint it came from)."""
  values = np.unique(np.concatenate([np.ravel(a) for a in jax.tree.leaves(variables)]))
  assert len(values) == 1, values
  return float(values[0])


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
  return _workdir(tmp_path_factory.mktemp("ckpt"), RUN, keep=2)


def test_keeps_the_last_n_plus_the_lowest_validation_mae(workdir):
  # last 2 (4: no metric, 5: 0.6) and the best (2: 0.4); 1 and 3 are gone.
  assert _steps(workdir) == [2, 4, 5]


def test_load_params_returns_the_lowest_validation_mae(workdir):
  config, variables, step = trained.load_params(workdir)
  assert step == 2 and config["net"] == MODEL
  assert _value(variables) == 2.0
  assert set(variables) == {"params", "batch_stats"}
  # An explicit step still loads that step.
  _, variables, step = trained.load_params(workdir, step=5)
  assert step == 5 and _value(variables) == 5.0


def test_inference_load_serves_the_best_checkpoint(workdir):
  predictor = sljax.inference.load(workdir)
  assert predictor.train_config["step"] == 2
  assert _value(predictor.variables) == 2.0
  # The checkpoints folder is the same; one step's folder is that step.
  assert sljax.inference.load(workdir / ckpt.CHECKPOINT_DIR).train_config["step"] == 2
  one = sljax.inference.load(workdir / ckpt.CHECKPOINT_DIR / "5")
  assert one.train_config["step"] == 5 and _value(one.variables) == 5.0


def test_best_among_the_last_is_kept_once(tmp_path):
  workdir = _workdir(tmp_path, {1: 0.5, 2: 0.8, 3: 0.3, 4: 0.6}, keep=2)
  assert _steps(workdir) == [3, 4]
  assert trained.load_params(workdir)[2] == 3


def test_best_that_is_not_the_first(tmp_path):
  """A later, lower MAE replaces the best; the old best is dropped once outside the last N."""
  workdir = _workdir(tmp_path, {1: 0.5, 2: 0.2, 3: 0.9, 4: 0.1, 5: 0.7, 6: 0.8}, keep=1)
  assert _steps(workdir) == [4, 6]
  assert trained.load_params(workdir)[2] == 4


def test_default_keeps_the_last_three_plus_the_best(tmp_path):
  manager = ckpt.make_manager(tmp_path / "c")
  for step, mae in {1: 0.1, 2: 0.5, 3: 0.6, 4: 0.7, 5: 0.8}.items():
    ckpt.save(manager, step, {"w": jnp.full(2, float(step))}, {"step": step}, mae)
    manager.wait_until_finished()
  manager.close()
  assert sorted(int(p.name) for p in (tmp_path / "c").iterdir() if p.name.isdigit()) == [
      1, 3, 4, 5]


def test_checkpoint_with_fewer_leaves_than_the_model_is_named(tmp_path):
  """The model has a leaf after the checkpoint's last one: a one-line error, not IndexError."""
  manager = ckpt.make_manager(tmp_path / "c")
  ckpt.save(manager, 1, {"a": jnp.zeros(2)}, {"step": 1}, 0.5)
  manager.wait_until_finished()
  bigger = {"a": jax.ShapeDtypeStruct((2,), jnp.float32,
                                      sharding=jax.sharding.SingleDeviceSharding(
                                          jax.devices()[0])),
            "b": jax.ShapeDtypeStruct((3,), jnp.float32,
                                      sharding=jax.sharding.SingleDeviceSharding(
                                          jax.devices()[0]))}
  with pytest.raises(ckpt.SljaxError, match=r"leaf 1: checkpoint has \(none\), model expects b"):
    ckpt.restore(manager, 1, bigger)
  manager.close()


def test_loading_a_workdir_without_checkpoints_writes_nothing(tmp_path):
  workdir = tmp_path / "run"
  workdir.mkdir()
  (workdir / ckpt.CONFIG_FILE).write_text(json.dumps({"strategy": "stl", "net": MODEL,
                                                      "model_kwargs": KWARGS}))
  with pytest.raises(ckpt.SljaxError, match="no checkpoint saved yet"):
    trained.load_params(workdir)
  assert [p.name for p in workdir.iterdir()] == [ckpt.CONFIG_FILE]


def _converted(folder):
  from sljax.nets import convert
  return convert.save_converted(folder, {"params": {"w": np.ones(2, np.float32)}},
                                {"maxdisp": 32})


def test_converted_folder_named_like_a_step_is_not_a_step(tmp_path, workdir):
  """Only WORKDIR/checkpoints/STEP is a step; a converted model in a folder named "7", or
  one inside a workdir's other subfolders, is read as the converted model."""
  for folder in (tmp_path / "7", workdir / "exported" / "model"):
    _converted(folder)
    name, kwargs, variables, config = trained.load_for_inference(folder)
    assert (name, kwargs, config["source"]) == ("psmnet", {"maxdisp": 32}, str(folder))
    np.testing.assert_array_equal(variables["params"]["w"], [1.0, 1.0])
