"""Checkpoints: the packed state restores to the saved leaves exactly, in either form; checkpoints
written as a tree (before packing) still restore; a model mismatch is a one-line error."""

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest

from sljax.errors import SljaxError
from sljax.models import checkpoint as ckpt
from sljax.models import load as trained
from sljax.train import state as st


def _state(seed: int = 0) -> st.TrainState:
  """A small TrainState with float and int leaves, a scalar, an empty dict and Adam state."""
  rng = np.random.default_rng(seed)
  params = {"conv": {"kernel": jnp.asarray(rng.normal(size=(3, 3, 2, 4)), jnp.float32),
                     "bias": jnp.asarray(rng.normal(size=(4,)), jnp.float32)},
            "head": {"kernel": jnp.asarray(rng.normal(size=(4, 1)), jnp.float32)}}
  tx = st.make_optimizer(1e-3)
  state = st.create_state({"params": params, "batch_stats": {"bn": {"mean": jnp.ones(4)}}}, tx)
  # Adam moments that differ from the parameters, so a mixed-up leaf order would show.
  opt = jax.tree.map(lambda x: x + 0.5 if x.dtype == jnp.float32 else x + 7, state.opt_state)
  return state.replace(step=jnp.int32(41), opt_state=opt)


def _abstract(state):
  return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding),
                      state)


def _save(directory: Path, state, step: int = 1, meta=None):
  manager = ckpt.make_manager(directory)
  ckpt.save(manager, step, state, meta or {"step": step}, 1.0)
  manager.wait_until_finished()
  return manager


def test_packed_state_restores_every_leaf_exactly(tmp_path):
  state = _state()
  manager = _save(tmp_path / "c", state, meta={"step": 41, "best_val": 0.5})
  restored, meta = ckpt.restore(manager, 1, _abstract(state))
  assert meta == {"step": 41, "best_val": 0.5}  # the layout stays inside the checkpoint
  assert jax.tree.structure(restored) == jax.tree.structure(state)
  for (path, a), b in zip(jax.tree_util.tree_flatten_with_path(state)[0],
                          jax.tree.leaves(restored)):
    assert a.dtype == b.dtype and a.shape == b.shape, path
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=str(path))
  manager.close()


def test_packed_checkpoint_is_two_vectors_and_a_layout(tmp_path):
  state = _state()
  _save(tmp_path / "c", state).close()
  saved = ocp.StandardCheckpointer().metadata(tmp_path / "c" / "1" / "state").item_metadata
  n_float = sum(x.size for x in jax.tree.leaves(state) if x.dtype == jnp.float32)
  assert {k: tuple(v.shape) for k, v in saved.items()} == {"float32": (n_float,), "int32": (2,)}
  assert ckpt.layout(state)[0] == [["step"], "int32", []]


def test_without_the_model_params_come_back_as_nested_dicts(tmp_path):
  state = _state()
  manager = _save(tmp_path / "c", state)
  restored, _ = ckpt.restore(manager, 1)
  np.testing.assert_array_equal(restored["params"]["conv"]["kernel"],
                                state.params["conv"]["kernel"])
  np.testing.assert_array_equal(restored["batch_stats"]["bn"]["mean"], np.ones(4))
  assert int(restored["step"]) == 41
  manager.close()


def test_tree_checkpoints_written_before_packing_still_restore(tmp_path):
  state = _state()
  directory = tmp_path / "c"
  manager = ckpt.make_manager(directory)
  manager.save(3, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                           meta=ocp.args.JsonSave({"step": 3})),
               metrics={"val_mae": 1.0}, force=True)
  manager.wait_until_finished()
  for abstract in (_abstract(state), None):
    restored, meta = ckpt.restore(manager, 3, abstract)
    assert meta == {"step": 3}
    got = restored.params if abstract is not None else restored["params"]
    np.testing.assert_array_equal(got["head"]["kernel"], state.params["head"]["kernel"])
  manager.close()
  config = {"strategy": "stl", "net": "unet-disp", "model_kwargs": {}}
  (tmp_path / "config.json").write_text(json.dumps(config))
  directory.rename(tmp_path / "checkpoints")
  _, variables, step = trained.load_params(tmp_path)
  assert step == 3 and set(variables) == {"params", "batch_stats"}


def test_restoring_into_another_model_names_the_first_difference(tmp_path):
  manager = _save(tmp_path / "c", _state())
  other = _state()
  other = other.replace(params={**other.params, "extra": jnp.zeros(2)})
  with pytest.raises(SljaxError, match=r"does not match the model \(leaf .*extra"):
    ckpt.restore(manager, 1, _abstract(other))
  manager.close()
