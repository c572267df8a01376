"""PSMNet: cost volume, regression, interpolation, wiring of the hourglasses, counts, init."""

import importlib

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sljax.errors import SljaxError
from sljax.nets import build_model
from sljax.nets.layers import linear_resize_matrix, linear_resize_phases
from sljax.nets.psmnet import (Hourglass, cost_volume, disparity_regression, reference_key,
                               regress_upsampled, spp_pool, upsample_cost)

H, W, MAXDISP = 32, 64, 16
# unsafe_rbg compiles the initialisers far faster than threefry on the CPU.
KEY = jax.random.key(0, impl="unsafe_rbg")
_CAPTURE = ("dres0", "dres1", "dres2", "dres3", "dres4", "classif1", "classif2", "classif3")


def _count(tree):
  return sum(int(np.prod(x.shape)) for x in jax.tree_util.tree_leaves(tree))


def _torch_linear_1d(n_in, n_out, align_corners):
  """PyTorch's linear interpolation source indices and weights, one output at a time."""
  rows = []
  for o in range(n_out):
    if align_corners:
      src = o * (n_in - 1) / (n_out - 1) if n_out > 1 else 0.0
    else:
      src = max((o + 0.5) * n_in / n_out - 0.5, 0.0)
    i0 = min(int(np.floor(src)), n_in - 1)
    i1 = min(i0 + 1, n_in - 1)
    lam = src - i0
    rows.append((i0, i1, lam))
  return rows


def _naive_trilinear(vol, size, align_corners):
  """Pointwise trilinear interpolation of [D, H, W] (float64 loops)."""
  rd = _torch_linear_1d(vol.shape[0], size[0], align_corners)
  rh = _torch_linear_1d(vol.shape[1], size[1], align_corners)
  rw = _torch_linear_1d(vol.shape[2], size[2], align_corners)
  out = np.zeros(size)
  for a, (d0, d1, ld) in enumerate(rd):
    for b, (h0, h1, lh) in enumerate(rh):
      for c, (w0, w1, lw) in enumerate(rw):
        acc = 0.0
        for di, wd in ((d0, 1 - ld), (d1, ld)):
          for hi, wh in ((h0, 1 - lh), (h1, lh)):
            for wi, ww in ((w0, 1 - lw), (w1, lw)):
              acc += wd * wh * ww * vol[di, hi, wi]
        out[a, b, c] = acc
  return out


def _numpy_head(costs, maxdisp, h, w):
  """Upsample + softmax + regression in float64 NumPy for [D4, h4, w4] costs."""
  up = _naive_trilinear(costs, (maxdisp, h, w), False)
  p = np.exp(up - up.max(axis=0))
  p /= p.sum(axis=0)
  return np.tensordot(np.arange(maxdisp), p, axes=(0, 0))


@pytest.fixture(scope="module")
def images():
  rng = np.random.default_rng(0)
  return (jnp.asarray(rng.random((1, H, W, 3), np.float32)),
          jnp.asarray(rng.random((1, H, W, 3), np.float32)))


@pytest.fixture(scope="module")
def trained(images):
  """Initial variables, train-mode output and captured outputs of the aggregation modules.

  Train mode (BatchNorm on batch statistics) keeps activations at unit scale, so the
  comparisons below have meaningful tolerances; flax does not update batch_stats in init.
  """
  model = build_model("psmnet", maxdisp=MAXDISP)
  only = lambda mdl, method: mdl.name in _CAPTURE and method == "__call__"
  fn = jax.jit(lambda k, a, b: model.init_with_output(k, a, b, train=True,
                                                      capture_intermediates=only))
  out, variables = fn(KEY, *images)
  inter = variables.pop("intermediates")
  return model, variables, out, {k: v["__call__"][0] for k, v in inter.items()}


def _rel_err(a, b):
  a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
  return np.abs(a - b).max() / np.abs(b).max()


def test_parameter_count_rgb_and_gray():
  x = jax.ShapeDtypeStruct((1, 256, 256, 3), jnp.float32)
  shapes = jax.eval_shape(lambda a: build_model("psmnet").init(KEY, a, a), x)
  assert _count(shapes["params"]) == 5_224_768
  g = jax.ShapeDtypeStruct((1, 256, 256, 1), jnp.float32)
  gshapes = jax.eval_shape(lambda a: build_model("psmnet", gray=True).init(KEY, a, a), g)
  # Only the first 3x3 conv sees the input: 2 fewer input channels x 9 x 32.
  assert _count(gshapes["params"]) == 5_224_768 - 2 * 9 * 32


def test_cost_volume_matches_naive_loop():
  rng = np.random.default_rng(1)
  left = rng.normal(size=(2, 3, 7, 4)).astype(np.float32)
  right = rng.normal(size=(2, 3, 7, 4)).astype(np.float32)
  d_max = 5
  vol = np.asarray(cost_volume(jnp.asarray(left), jnp.asarray(right), d_max))
  want = np.zeros((2, d_max, 3, 7, 8), np.float32)
  for d in range(d_max):
    for x in range(7):
      if x >= d:
        want[:, d, :, x, :4] = left[:, :, x]
        want[:, d, :, x, 4:] = right[:, :, x - d]
  assert vol.shape == want.shape
  np.testing.assert_array_equal(vol, want)


def test_disparity_regression_hand_computed():
  # Pixel 0: probabilities 0.1, 0.2, 0.3, 0.4 -> 0*.1 + 1*.2 + 2*.3 + 3*.4 = 2.0.
  # Pixel 1: equal costs -> mean of 0..3 = 1.5. Pixel 2: one dominant cost at d = 1.
  c = np.zeros((1, 4, 1, 3), np.float32)
  c[0, :, 0, 0] = np.log([1.0, 2.0, 3.0, 4.0])
  c[0, :, 0, 2] = [0.0, 50.0, 0.0, 0.0]
  d = np.asarray(disparity_regression(jnp.asarray(c)))
  np.testing.assert_allclose(d[0, 0], [2.0, 1.5, 1.0], rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("align_corners", [False, True])
def test_trilinear_upsampling_matches_pytorch_formula(align_corners):
  rng = np.random.default_rng(2)
  vol = rng.normal(size=(1, 3, 4, 5)).astype(np.float32)
  got = np.asarray(upsample_cost(jnp.asarray(vol), 12, 16, 20, align_corners))
  want = _naive_trilinear(vol[0].astype(np.float64), (12, 16, 20), align_corners)
  np.testing.assert_allclose(got[0], want, rtol=1e-5, atol=1e-5)


def test_spp_pool_reference_kernels_and_shrinking():
  x = np.random.default_rng(3).normal(size=(1, 10, 20, 2)).astype(np.float32)
  # Kernel 8 on 10x20: floor mode drops the remainder (rows 8-9, columns 16-19).
  got = np.asarray(spp_pool(jnp.asarray(x), 8))
  want = np.stack([x[0, :8, 8 * j:8 * j + 8].mean(axis=(0, 1)) for j in range(2)])[None, None]
  np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
  # Kernel 64 exceeds both sides: a global average.
  got = np.asarray(spp_pool(jnp.asarray(x), 64))
  np.testing.assert_allclose(got[0, 0, 0], x[0].mean(axis=(0, 1)), rtol=1e-5, atol=1e-6)


def test_eval_output(trained, images):
  model, variables, _, _ = trained
  out = jax.jit(lambda v, a, b: model.apply(v, a, b, train=False))(variables, *images)
  assert set(out) == {"disparity"}
  d = np.asarray(out["disparity"])
  assert d.shape == (1, H, W)
  assert np.isfinite(d).all() and d.min() >= 0 and d.max() <= MAXDISP - 1


def test_hourglass_skip_links(trained):
  """The third hourglass must get (out2 + cost0, pre1, post2): would fail with pre2."""
  _, variables, _, cap = trained
  cost0 = cap["dres1"] + cap["dres0"]
  out1, pre1, post1 = cap["dres2"]
  out2, pre2, post2 = cap["dres3"]
  out3 = cap["dres4"][0]
  hg = Hourglass()
  run = jax.jit(lambda v, x, pre, post: hg.apply(v, x, pre, post, train=True,
                                                 mutable=["batch_stats"])[0][0])

  def sub(name):
    return {"params": variables["params"][name], "batch_stats": variables["batch_stats"][name]}

  assert _rel_err(run(sub("dres3"), out1 + cost0, pre1, post1), out2) < 1e-5
  want3 = run(sub("dres4"), out2 + cost0, pre1, post2)
  assert _rel_err(out3, want3) < 1e-5
  wrong = run(sub("dres4"), out2 + cost0, pre2, post2)
  assert _rel_err(wrong, want3) > 1e-2  # the check above can tell pre1 from pre2


def test_cumulative_classifier_costs_and_head(trained):
  _, _, out, cap = trained
  c1, c2, c3 = (np.asarray(cap[f"classif{i}"][0], np.float64) for i in (1, 2, 3))
  for got, total in zip(out["disparities"], (c1, c1 + c2, c1 + c2 + c3)):
    want = _numpy_head(total, MAXDISP, H, W)
    np.testing.assert_allclose(np.asarray(got[0]), want, rtol=1e-4, atol=1e-3)


def test_reference_initialisation(trained):
  _, variables, _, _ = trained
  p = variables["params"]
  k = np.asarray(p["dres2"]["conv2"]["conv"]["kernel"])  # 3x3x3, 64 -> 64
  assert abs(k.mean()) < 2e-3 and k.std() == pytest.approx(np.sqrt(2 / (27 * 64)), rel=0.02)
  k = np.asarray(p["feature_extraction"]["layer3_0"]["conv2"]["conv"]["kernel"])  # 3x3, 128
  assert k.std() == pytest.approx(np.sqrt(2 / (9 * 128)), rel=0.02)
  # Transposed convs keep PyTorch's default U(-b, b), b = 1 / sqrt(cout * 27).
  k = np.asarray(p["dres2"]["conv5"]["conv"]["kernel"])
  b = 1 / np.sqrt(64 * 27)
  assert np.abs(k).max() <= b and k.std() == pytest.approx(b / np.sqrt(3), rel=0.02)
  bn = p["dres3"]["conv1"]["bn"]
  np.testing.assert_array_equal(bn["scale"], 1.0)
  np.testing.assert_array_equal(bn["bias"], 0.0)


def test_train_mode_returns_three_predictions(trained):
  _, _, out, _ = trained
  assert set(out) == {"disparity", "disparities"} and len(out["disparities"]) == 3
  for d in out["disparities"]:
    d = np.asarray(d)
    assert d.shape == (1, H, W) and np.isfinite(d).all()
    assert d.min() >= 0 and d.max() <= MAXDISP - 1
  np.testing.assert_array_equal(out["disparity"], out["disparities"][2])


@pytest.mark.parametrize("shape_l, shape_r, kwargs, match", [
    ((1, 40, 64, 3), (1, 40, 64, 3), {}, "multiple of 16"),
    ((1, 32, 64, 3), (1, 32, 48, 3), {}, "same shape"),
    ((1, 32, 64, 1), (1, 32, 64, 1), {}, "channel"),
])
def test_bad_inputs_raise(shape_l, shape_r, kwargs, match):
  model = build_model("psmnet", maxdisp=16, **kwargs)
  a = jax.ShapeDtypeStruct(shape_l, jnp.float32)
  b = jax.ShapeDtypeStruct(shape_r, jnp.float32)
  with pytest.raises(SljaxError, match=match):
    jax.eval_shape(lambda x, y: model.init(KEY, x, y), a, b)


def test_reference_keys():
  x = jax.ShapeDtypeStruct((1, 256, 256, 3), jnp.float32)
  shapes = jax.eval_shape(lambda a: build_model("psmnet").init(KEY, a, a), x)
  keys = []
  for col in ("params", "batch_stats"):
    for path, _ in jax.tree_util.tree_flatten_with_path(shapes[col])[0]:
      keys.append(reference_key(tuple(p.key for p in path)))
  assert len(keys) == len(set(keys))
  for k in ["feature_extraction.firstconv.0.0.weight", "feature_extraction.firstconv.4.1.bias",
            "feature_extraction.layer1.2.conv1.0.0.weight",
            "feature_extraction.layer2.0.downsample.0.weight",
            "feature_extraction.layer2.15.conv2.1.running_var",
            "feature_extraction.layer4.2.conv2.1.weight",
            "feature_extraction.branch1.1.0.weight", "feature_extraction.branch4.1.1.running_mean",
            "feature_extraction.lastconv.0.0.weight", "feature_extraction.lastconv.2.weight",
            "dres0.0.0.weight", "dres0.2.1.bias", "dres1.2.0.weight",
            "dres2.conv1.0.0.weight", "dres3.conv2.1.weight", "dres4.conv4.0.1.running_var",
            "dres4.conv5.0.weight", "dres2.conv6.1.bias", "classif1.0.0.weight",
            "classif3.2.weight"]:
    assert k in keys, k
  # 16 + 3 + 3 + 3 residual blocks, no layer1 / layer4 downsample.
  assert not any(k.startswith(("feature_extraction.layer1.0.downsample",
                               "feature_extraction.layer4.0.downsample")) for k in keys)


@pytest.mark.parametrize("n_in,n_out", [(4, 16), (3, 12), (24, 96), (5, 10), (3, 9)])
def test_linear_resize_phases_rebuild_the_matrix(n_in, n_out):
  """Each phase (s, w0, w1) reproduces its rows of the interpolation matrix, edges included."""
  phases = linear_resize_phases(n_in, n_out, False)
  m = linear_resize_matrix(n_in, n_out, False)
  f = n_out // n_in
  for i in range(n_in):
    for r, (s, w0, w1) in enumerate(phases):
      row = np.zeros(n_in)
      row[min(max(i + s, 0), n_in - 1)] += w0
      row[min(max(i + s + 1, 0), n_in - 1)] += w1
      np.testing.assert_allclose(m[f * i + r], row, atol=1e-6)
  assert linear_resize_phases(n_in, n_out, True) is None  # align_corners: the fallback
  assert linear_resize_phases(4, 10, False) is None       # no integer factor


@pytest.mark.parametrize("d4,maxdisp,align_corners", [(4, 16, False), (3, 12, False),
                                                      (4, 16, True), (4, 14, False)])
def test_regress_upsampled_equals_the_composition(d4, maxdisp, align_corners):
  """The phase head gives disparity_regression(upsample_cost(...)), value and gradient."""
  rng = np.random.RandomState(3)
  cost = jnp.asarray(rng.randn(2, d4, 5, 6).astype(np.float32) * 3)
  w = jnp.asarray(rng.randn(2, 20, 24).astype(np.float32))

  def ref(c):
    return disparity_regression(upsample_cost(c, maxdisp, 20, 24, align_corners))

  def fast(c):
    return regress_upsampled(c, maxdisp, 20, 24, align_corners)

  def value_and_grad(f):
    return jax.jit(jax.value_and_grad(lambda c: jnp.sum(f(c) * w)))(cost)

  (want, want_grad), (got, got_grad) = value_and_grad(ref), value_and_grad(fast)
  np.testing.assert_allclose(float(got), float(want), rtol=1e-5)
  np.testing.assert_allclose(np.asarray(jax.jit(fast)(cost)), np.asarray(jax.jit(ref)(cost)),
                             rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(np.asarray(got_grad), np.asarray(want_grad), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("shape", [(6, 5, 7, 4), (4, 3, 5, 6, 3)])
def test_grouped_batch_norm_equals_one_call_per_group(shape):
  """BatchNorm(groups=2) on a stacked batch equals two calls of the plain layer, one per half,
  in order (the reference's left then right): outputs, running mean and (unbiased) running
  variance in training; the plain layer in evaluation; and parameters the same."""
  from sljax.nets.layers import batch_norm
  x = jnp.asarray(np.random.default_rng(0).normal(2.0, 3.0, shape), jnp.float32)
  x = x.at[shape[0] // 2:].mul(0.5)  # the two groups' statistics differ
  plain, grouped = batch_norm(), batch_norm(groups=2)
  v = plain.init(jax.random.PRNGKey(0), x[:1], use_running_average=False)
  v = {"params": {"scale": v["params"]["scale"] + 0.3, "bias": v["params"]["bias"] - 0.2},
       "batch_stats": {"mean": jnp.full(shape[-1], 0.5), "var": jnp.full(shape[-1], 2.0)}}
  assert jax.tree.structure(grouped.init(jax.random.PRNGKey(0), x, use_running_average=False)
                            ) == jax.tree.structure(v)
  half = shape[0] // 2
  stats, outs = v["batch_stats"], []
  for part in (x[:half], x[half:]):
    y, upd = plain.apply({**v, "batch_stats": stats}, part, use_running_average=False,
                         mutable=["batch_stats"])
    outs.append(y)
    stats = upd["batch_stats"]
  y, upd = grouped.apply(v, x, use_running_average=False, mutable=["batch_stats"])
  np.testing.assert_allclose(y, jnp.concatenate(outs), rtol=1e-5, atol=1e-5)
  for k in ("mean", "var"):
    np.testing.assert_allclose(upd["batch_stats"][k], stats[k], rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(grouped.apply(v, x, use_running_average=True),
                             plain.apply(v, x, use_running_average=True), rtol=0, atol=0)
  with pytest.raises(ValueError, match="groups=2"):
    grouped.apply(v, x[:3], use_running_average=False, mutable=["batch_stats"])


def test_batch_norm_in_training_is_flaxs_with_pytorchs_running_variance():
  """In training sljax's BatchNorm (one jitted function) gives flax's nn.BatchNorm output and
  running mean bit for bit, and a running variance that averages in the unbiased batch
  variance (float64 NumPy reference); the normalisation itself against NumPy too."""
  from sljax.nets.layers import BN_EPSILON, BN_MOMENTUM, batch_norm
  rng = np.random.default_rng(3)
  x = jnp.asarray(rng.normal(1.5, 2.0, (3, 4, 5, 6)), jnp.float32)
  c = x.shape[-1]
  v = {"params": {"scale": jnp.asarray(rng.uniform(0.5, 1.5, c), jnp.float32),
                  "bias": jnp.asarray(rng.normal(0, 1, c), jnp.float32)},
       "batch_stats": {"mean": jnp.asarray(rng.normal(0, 1, c), jnp.float32),
                       "var": jnp.asarray(rng.uniform(1, 2, c), jnp.float32)}}
  def train(module):  # jitted, as a training step runs it (XLA fuses either the same way)
    return jax.jit(lambda v, x: module.apply(v, x, use_running_average=False,
                                             mutable=["batch_stats"]))(v, x)
  ours, upd = train(batch_norm())
  theirs, flax_upd = train(nn.BatchNorm(momentum=BN_MOMENTUM, epsilon=BN_EPSILON))
  np.testing.assert_array_equal(ours, theirs)
  np.testing.assert_array_equal(upd["batch_stats"]["mean"], flax_upd["batch_stats"]["mean"])
  x64 = np.asarray(x, np.float64).reshape(-1, c)
  n, mean, var = x64.shape[0], x64.mean(0), x64.var(0)
  old = np.asarray(v["batch_stats"]["var"], np.float64)
  np.testing.assert_allclose(upd["batch_stats"]["var"],
                             BN_MOMENTUM * old + (1 - BN_MOMENTUM) * var * n / (n - 1),
                             rtol=1e-5)
  want = ((x64 - mean) / np.sqrt(var + BN_EPSILON) * np.asarray(v["params"]["scale"])
          + np.asarray(v["params"]["bias"]))
  np.testing.assert_allclose(np.asarray(ours).reshape(-1, c), want, rtol=1e-4, atol=1e-5)


def _batch_norm_float64(x, scale, bias, ra_mean, ra_var, groups):
  """A float64 reference of sljax's training BatchNorm: per group, two-pass statistics, the
  normalisation, and PyTorch's running averages in order."""
  xs = jnp.reshape(x, (groups, -1, x.shape[-1]))
  ys = []
  for g in range(groups):
    n = xs[g].shape[0]
    mean = xs[g].mean(0)
    var = ((xs[g] - mean) ** 2).mean(0)
    ys.append((xs[g] - mean) / jnp.sqrt(var + 1e-5) * scale + bias)
    ra_mean = 0.9 * ra_mean + 0.1 * mean
    ra_var = 0.9 * ra_var + 0.1 * var * n / (n - 1)
  return jnp.concatenate(ys).reshape(x.shape), ra_mean, ra_var


@pytest.mark.parametrize("groups,dtype", [(1, "float32"), (2, "float32"), (2, "bfloat16")])
def test_batch_norm_gradient_is_autodiffs_of_a_float64_reference(groups, dtype):
  """BatchNorm's own gradient in training (`_normalized`) equals autodiff of a float64
  reference, for the input, scale and bias, through the output and through the running
  statistics too (a loss may read them), per group; bfloat16 input within its rounding."""
  from sljax.nets.layers import batch_norm
  rng = np.random.default_rng(5)
  shape = (4, 3, 5, 6)
  x = rng.normal(1.5, 2.0, shape)
  x[shape[0] // 2:] *= 0.5  # the groups' statistics differ
  w = rng.normal(size=shape)
  scale, bias = rng.uniform(0.5, 1.5, 6), rng.normal(0, 1, 6)
  ra_mean, ra_var = rng.normal(0, 1, 6), rng.uniform(1, 2, 6)
  a, b = rng.normal(size=6), rng.normal(size=6)
  module = batch_norm(groups=groups)

  def loss(x, scale, bias):
    v = {"params": {"scale": scale, "bias": bias},
         "batch_stats": {"mean": jnp.asarray(ra_mean, jnp.float32),
                         "var": jnp.asarray(ra_var, jnp.float32)}}
    y, upd = module.apply(v, x, use_running_average=False, mutable=["batch_stats"])
    s = upd["batch_stats"]
    return jnp.sum(jnp.sin(y) * w) + jnp.sum(a * s["mean"]) + jnp.sum(b * s["var"])

  got = jax.jit(jax.grad(loss, (0, 1, 2)))(jnp.asarray(x, dtype), jnp.asarray(scale, jnp.float32),
                                            jnp.asarray(bias, jnp.float32))
  with jax.enable_x64(True):
    def ref_loss(x, scale, bias):
      y, m, v = _batch_norm_float64(x, scale, bias, ra_mean, ra_var, groups)
      return jnp.sum(jnp.sin(y) * w) + jnp.sum(a * m) + jnp.sum(b * v)
    x_in = np.asarray(jnp.asarray(x, dtype).astype(jnp.float32), np.float64)  # what ours saw
    want = [np.asarray(g) for g in jax.grad(ref_loss, (0, 1, 2))(x_in, scale, bias)]
  assert got[0].dtype == jnp.dtype(dtype) and got[1].dtype == got[2].dtype == jnp.float32
  tol = 1e-4 if dtype == "float32" else 1e-2
  for g, ref in zip(got, want):
    np.testing.assert_allclose(np.asarray(g, np.float64), ref, rtol=tol,
                               atol=tol * np.abs(ref).max())


def test_batch_norm_backward_takes_two_reductions_per_group():
  """The gradient of a training BatchNorm reduces twice per group (the sums of dy and of
  dy * x_hat) and the forward twice (mean and mean square): each reduction is a YNNPACK thunk
  of the step's, which costs load time and a first-run set-up (autodiff's backward took three)."""
  from sljax.nets.layers import batch_norm
  x = jnp.ones((4, 3, 5, 6), jnp.float32)
  for groups in (1, 2):
    module = batch_norm(groups=groups)
    v = module.init(jax.random.PRNGKey(0), x, use_running_average=False)

    def loss(params, x, module=module, v=v):
      y, _ = module.apply({**v, "params": params}, x, use_running_average=False,
                          mutable=["batch_stats"])
      return jnp.sum(y * y)
    forward = str(jax.make_jaxpr(loss)(v["params"], x))
    both = str(jax.make_jaxpr(jax.grad(loss, (0, 1)))(v["params"], x))
    count = lambda text: text.count("reduce_sum[")
    # the loss's own sum once in each, its cotangent a broadcast
    assert count(forward) == 2 + 1 and count(both) == 2 + 2 + 1, (groups, count(both))


def test_layers_of_one_shape_are_traced_once(monkeypatch):
  """A network's BatchNorms and fast convolutions of one shape are traced (and differentiated)
  once, not once per layer: they are jitted (issue 49: half of the twin's step tracing).
  Counted are their Python bodies run while a training gradient is traced."""
  from flax.linen import normalization
  from sljax.kernels import conv3d, conv_transpose3d
  from sljax.nets.layers import BatchNorm
  c3 = importlib.import_module("sljax.kernels.conv3d")  # the module, not its function
  traced = {"stats": 0, "fold": 0}

  def counting(name, f):
    def wrapped(*args, **kwargs):
      traced[name] += 1
      return f(*args, **kwargs)
    return wrapped

  monkeypatch.setattr(normalization, "_compute_stats",
                      counting("stats", normalization._compute_stats))
  monkeypatch.setattr(c3, "fold_forward", counting("fold", c3.fold_forward))

  # PSMNet's BatchNorms: one trace per distinct (shape, groups), of many more layers.
  model = build_model("psmnet", maxdisp=MAXDISP, conv_impl="fast")
  left = right = jnp.zeros((1, H, W, 3), jnp.float32)
  variables = jax.jit(model.init)(KEY, left, right)
  norms = []

  def record(next_fun, args, kwargs, context):
    if context.method_name == "__call__" and isinstance(context.module, BatchNorm):
      norms.append((args[0].shape, context.module.groups))
    return next_fun(*args, **kwargs)

  def loss(params):
    out, _ = model.apply({**variables, "params": params}, left, right, train=True,
                         mutable=["batch_stats"])
    return sum(jnp.sum(d) for d in out["disparities"])

  jax.clear_caches()  # jitted layers traced by earlier tests would not be traced again
  with nn.intercept_methods(record):
    jax.make_jaxpr(jax.grad(loss))(variables["params"])
  assert len(norms) > 2 * len(set(norms))  # many layers share a shape
  # Twice per shape: BatchNorm's own gradient (a custom_vjp) traces its function and its
  # forward rule once each.
  assert traced["stats"] == 2 * len(set(norms))

  # Folded convolutions (forwards and, in the backward, input gradients): as many traces for
  # four hourglass-like blocks as for two (the first block's cotangents differ in kind from a
  # later one's, so one block alone traces one signature fewer).
  def blocks(n):
    def f(x, k, kd, ku):
      for _ in range(n):
        y = conv3d(conv3d(x, k, impl="fast"), kd, (2, 2, 2), impl="fast")
        x = x + conv_transpose3d(y, ku, impl="fast")
      return jnp.sum(x)
    return f

  x = jnp.ones((1, 4, 8, 8, 2))
  ks = (jnp.ones((3, 3, 3, 2, 2)), jnp.ones((3, 3, 3, 2, 2)), jnp.ones((3, 3, 3, 2, 2)))
  counts = []
  for n in (2, 4):
    jax.clear_caches()
    traced["fold"] = 0
    jax.make_jaxpr(jax.grad(blocks(n), argnums=(1, 2, 3)))(x, *ks)
    counts.append(traced["fold"])
  assert counts[0] > 0 and counts[1] == counts[0], counts
