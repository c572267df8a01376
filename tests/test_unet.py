"""UNet: heads, odd sizes (pad and crop), parameter counts, train mode, errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sljax.errors import SljaxError
from sljax.nets import build_model

KEY = jax.random.key(0, impl="unsafe_rbg")
H, W, T = 21, 30, 4  # odd sizes: not multiples of 2^depth
SMALL = {"depth": 2, "base_width": 4}


def _count(tree):
  return sum(int(np.prod(x.shape)) for x in jax.tree_util.tree_leaves(tree))


def _hand_count(c, depth, base, out):
  """UNet parameters by hand: double convs (conv + BN scale/bias), up-convs with bias, 1x1 head."""
  def dc(cin, cout):
    return 9 * cin * cout + 2 * cout + 9 * cout * cout + 2 * cout
  n, cin = 0, 2 * c
  for level in range(depth + 1):
    n += dc(cin, base * 2 ** level)
    cin = base * 2 ** level
  for level in reversed(range(depth)):
    f = base * 2 ** level
    n += 4 * (2 * f) * f + f + dc(2 * f, f)
  return n + base * out + out


@pytest.fixture(scope="module")
def pair():
  rng = np.random.default_rng(0)
  return (jnp.asarray(rng.random((2, H, W, 1), np.float32)),
          jnp.asarray(rng.random((2, H, W, 1), np.float32)))


@pytest.fixture(scope="module")
def sl_model(pair):
  model = build_model("unet-sl", t=T, gray=True, **SMALL)
  out, variables = jax.jit(lambda k, a, b: model.init_with_output(k, a, b))(KEY, *pair)
  return model, variables, out


@pytest.mark.parametrize("name, gray, out", [("unet-sl", True, 16), ("unet-sl", False, 16),
                                             ("unet-disp", True, 1), ("unet-disp", False, 1)])
def test_default_parameter_counts(name, gray, out):
  c = 1 if gray else 3
  x = jax.ShapeDtypeStruct((1, 64, 64, c), jnp.float32)
  shapes = jax.eval_shape(lambda a: build_model(name, t=8, gray=gray).init(KEY, a, a), x)
  assert _count(shapes["params"]) == _hand_count(c, 4, 32, out)


def test_sl_head_odd_size(sl_model):
  _, _, out = sl_model
  assert set(out) == {"sl_logits", "sl_logits_right"}
  for k in out:
    assert out[k].shape == (2, H, W, T) and np.isfinite(np.asarray(out[k])).all()


def test_odd_size_is_pad_then_crop(sl_model, pair):
  """Output on 21x30 equals the output on the edge-padded 24x32 pair, cropped."""
  model, variables, out = sl_model
  pad = lambda x: jnp.pad(x, ((0, 0), (0, 3), (0, 2), (0, 0)), mode="edge")
  full = jax.jit(lambda v, a, b: model.apply(v, a, b))(variables, pad(pair[0]), pad(pair[1]))
  for k in out:
    np.testing.assert_allclose(out[k], full[k][:, :H, :W], rtol=1e-5, atol=1e-5)


def test_train_mode_updates_batch_stats(sl_model, pair):
  model, variables, _ = sl_model
  out, state = jax.jit(lambda v, a, b: model.apply(v, a, b, train=True,
                                                   mutable=["batch_stats"]))(variables, *pair)
  assert out["sl_logits"].shape == (2, H, W, T)
  before = variables["batch_stats"]["down0"]["convbn_0"]["bn"]["mean"]
  after = state["batch_stats"]["down0"]["convbn_0"]["bn"]["mean"]
  assert not np.allclose(before, after)


def test_disp_head_range_and_width_scale(pair):
  model = build_model("unet-disp", gray=True, **SMALL)
  out, variables = jax.jit(lambda k, a, b: model.init_with_output(k, a, b))(KEY, *pair)
  d = np.asarray(out["disparity"])
  assert set(out) == {"disparity"} and d.shape == (2, H, W)
  assert (d > 0).all() and (d < W).all()
  # disparity = sigmoid(z) * W: recover z from the head's captured output.
  only_head = lambda m, _: m.name == "head"
  _, inter = jax.jit(lambda v, a, b: model.apply(v, a, b, capture_intermediates=only_head,
                                                 mutable=["intermediates"]))(variables, *pair)
  z = np.asarray(inter["intermediates"]["head"]["__call__"][0][..., 0], np.float64)
  np.testing.assert_allclose(d, W / (1 + np.exp(-z)), rtol=1e-5)


def test_rgb_pair():
  model = build_model("unet-sl", t=T, **SMALL)
  x = jax.ShapeDtypeStruct((1, 17, 33, 3), jnp.float32)
  out = jax.eval_shape(lambda a: model.init_with_output(KEY, a, a)[0], x)
  assert out["sl_logits_right"].shape == (1, 17, 33, T)


@pytest.mark.parametrize("kwargs, shapes, match", [
    ({}, ((1, 16, 16, 3), (1, 16, 16, 1)), "same shape"),
    ({"gray": True}, ((1, 16, 16, 3), (1, 16, 16, 3)), "channel"),
    ({"depth": 0}, ((1, 16, 16, 3), (1, 16, 16, 3)), "depth"),
])
def test_bad_inputs_raise(kwargs, shapes, match):
  model = build_model("unet-sl", **kwargs)
  a, b = (jax.ShapeDtypeStruct(s, jnp.float32) for s in shapes)
  with pytest.raises(SljaxError, match=match):
    jax.eval_shape(lambda x, y: model.init(KEY, x, y), a, b)


def test_upconv_equals_flax_conv_transpose():
  """UpConv2x2 (a product and a reshape) is nn.ConvTranspose 2x2 stride 2: values, grads."""
  import flax.linen as nn
  from sljax.nets.layers import UpConv2x2
  rng = np.random.RandomState(0)
  x = jnp.asarray(rng.randn(2, 3, 5, 4), jnp.float32)
  theirs = nn.ConvTranspose(6, (2, 2), strides=(2, 2), padding="VALID")
  v = theirs.init(jax.random.PRNGKey(0), x)
  v = jax.tree.map(lambda a: jnp.asarray(rng.randn(*a.shape), jnp.float32), v)
  ours = UpConv2x2(6)
  assert jax.tree.map(jnp.shape, ours.init(jax.random.PRNGKey(0), x)) == \
      jax.tree.map(jnp.shape, v)
  w = jnp.asarray(rng.randn(2, 6, 10, 6), jnp.float32)

  def value_and_grads(m):
    return jax.value_and_grad(lambda v, x: jnp.sum(m.apply(v, x) * w), argnums=(0, 1))(v, x)

  (a, (ga_v, ga_x)), (b, (gb_v, gb_x)) = value_and_grads(ours), value_and_grads(theirs)
  np.testing.assert_allclose(np.asarray(ours.apply(v, x)), np.asarray(theirs.apply(v, x)),
                             rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(float(a), float(b), rtol=1e-5)
  np.testing.assert_allclose(np.asarray(ga_x), np.asarray(gb_x), rtol=1e-5, atol=1e-5)
  for p, q in zip(jax.tree.leaves(ga_v), jax.tree.leaves(gb_v)):
    np.testing.assert_allclose(np.asarray(p), np.asarray(q), rtol=1e-5, atol=1e-5)


def test_max_pool_equals_flax_max_pool():
  """max_pool_2x2 equals nn.max_pool, values and gradients, ties included (first maximum)."""
  import flax.linen as nn
  from sljax.kernels import max_pool_2x2
  rng = np.random.RandomState(1)
  x = rng.randn(2, 6, 8, 3).astype(np.float32)
  x[0, :2, :2] = 1.5   # ties: a flat window, and a window with two equal maxima
  x[1, 2:4, 4:6] = np.maximum(x[1, 2:4, 4:6], 0)
  x[1, 2, 5] = x[1, 3, 4] = 9.0
  x = jnp.asarray(x)
  w = jnp.asarray(rng.randn(2, 3, 4, 3), jnp.float32)
  ref = lambda x: nn.max_pool(x, (2, 2), strides=(2, 2))
  np.testing.assert_array_equal(np.asarray(max_pool_2x2(x)), np.asarray(ref(x)))
  g = [jax.grad(lambda x: jnp.sum(f(x) * w))(x) for f in (max_pool_2x2, ref)]
  np.testing.assert_array_equal(np.asarray(g[0]), np.asarray(g[1]))
