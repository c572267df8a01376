"""The multi-task twin: parameter layout, detach equivalence, SL output."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sljax.errors import SljaxError
from sljax.nets import build_model, detach_sl

H, W, MAXDISP, T = 32, 64, 16, 5
KEY = jax.random.key(0, impl="unsafe_rbg")


def _count(tree):
  return sum(int(np.prod(x.shape)) for x in jax.tree_util.tree_leaves(tree))


def _sl_head_params(t):
  """Hand count of the SL head (see sljax.nets.psmnet_mtl)."""
  head_convbn = 27 * 32 * 32 + 2 * 32
  attention = 27 * 32
  up1 = 9 * 33 * 32 + 2 * 32  # 32 pooled features + expected disparity
  up2 = 9 * 32 * 32 + 2 * 32
  logits = 32 * t + t
  return head_convbn + attention + up1 + up2 + logits


@pytest.fixture(scope="module")
def images():
  rng = np.random.default_rng(0)
  return (jnp.asarray(rng.random((1, H, W, 3), np.float32)),
          jnp.asarray(rng.random((1, H, W, 3), np.float32)))


@pytest.fixture(scope="module")
def twin(images):
  """Twin variables (random running statistics, so each BN layer differs) + train output."""
  model = build_model("psmnet-mtl", maxdisp=MAXDISP, t=T)
  train_out, variables = jax.jit(lambda k, a, b: model.init_with_output(k, a, b, train=True))(
      KEY, *images)
  rng = np.random.default_rng(1)

  def randomise(path, x):
    lo, hi = (0.5, 2.0) if path[-1].key == "var" else (-0.5, 0.5)
    return jnp.asarray(rng.uniform(lo, hi, x.shape).astype(np.float32))

  stats = jax.tree_util.tree_map_with_path(randomise, variables["batch_stats"])
  return model, {"params": variables["params"], "batch_stats": stats}, train_out


def test_parameter_layout_and_counts():
  x = jax.ShapeDtypeStruct((1, 256, 256, 3), jnp.float32)
  twin = jax.eval_shape(lambda a: build_model("psmnet-mtl", t=8).init(KEY, a, a), x)
  plain = jax.eval_shape(lambda a: build_model("psmnet").init(KEY, a, a), x)
  detached = detach_sl(twin)
  # Same names, same shapes, in both collections: the disparity path is exactly PSMNet.
  assert (jax.tree_util.tree_structure(detached) == jax.tree_util.tree_structure(plain))
  assert jax.tree_util.tree_map(lambda a: a.shape, detached) == jax.tree_util.tree_map(
      lambda a: a.shape, plain)
  assert _count(detached["params"]) == 5_224_768
  sl = twin["params"]["sl"]
  # The SL aggregation duplicates PSMNet's dres0..dres4.
  for k in ("dres0", "dres1", "dres2", "dres3", "dres4"):
    assert _count(sl[k]) == _count(plain["params"][k])
  head = _count({k: v for k, v in sl.items() if not k.startswith("dres")})
  assert head == _sl_head_params(8) == 47_688
  assert _count(twin["params"]) == 5_224_768 + _count(sl)


def test_detach_gives_bit_identical_disparity(twin, images):
  model, variables, _ = twin
  out = jax.jit(lambda v, a, b: model.apply(v, a, b, train=False))(variables, *images)
  plain = build_model("psmnet", maxdisp=MAXDISP)
  ref = jax.jit(lambda v, a, b: plain.apply(v, a, b, train=False))(detach_sl(variables), *images)
  assert set(out) == {"disparity", "sl_logits"} and set(ref) == {"disparity"}
  np.testing.assert_array_equal(np.asarray(out["disparity"]), np.asarray(ref["disparity"]))
  logits = np.asarray(out["sl_logits"])
  assert logits.shape == (1, H, W, T) and np.isfinite(logits).all()


def test_train_outputs(twin):
  _, _, out = twin
  assert set(out) == {"disparity", "disparities", "sl_logits"}
  assert [d.shape for d in out["disparities"]] == [(1, H, W)] * 3
  assert out["sl_logits"].shape == (1, H, W, T)
  # Different pixels get different logits (the head is not constant over the image).
  assert np.asarray(out["sl_logits"]).std(axis=(1, 2)).min() > 0


def test_detach_rejects_plain_variables():
  with pytest.raises(SljaxError, match="no structured-light path"):
    detach_sl({"params": {"feature_extraction": {}}, "batch_stats": {}})
  with pytest.raises(SljaxError, match="variables"):
    detach_sl([1, 2])
