"""The fast convolution kernels equal lax.conv_general_dilated, forward and gradients."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from sljax import kernels as c3

DIMS = ("NDHWC", "DHWIO", "NDHWC")


def _data(seed, x_shape, k_shape):
  rng = np.random.RandomState(seed)
  return (jnp.asarray(rng.randn(*x_shape).astype(np.float32)),
          jnp.asarray(rng.randn(*k_shape).astype(np.float32)))


def _assert_close(a, b, rtol=2e-5):
  a, b = np.asarray(a), np.asarray(b)
  assert a.shape == b.shape
  scale = max(np.abs(b).max(), 1e-6)
  np.testing.assert_allclose(a / scale, b / scale, atol=rtol)


def _value_and_grads(f, w):
  def run(x, k):
    y, vjp = jax.vjp(f, x, k)
    return (y,) + vjp(w)
  return run


def _check_against(ref, fast, x, k, seed):
  """Compares outputs and both gradients of fast vs ref, each side compiled once."""
  w = jnp.asarray(np.random.RandomState(seed).randn(*jax.eval_shape(ref, x, k).shape),
                  jnp.float32)
  for a, b in zip(*(jax.jit(_value_and_grads(f, w))(x, k) for f in (fast, ref))):
    _assert_close(a, b)


def _loops(f, x, k):
  """Loops in the program of f's value and gradients (several blocks run in a loop)."""
  w = jnp.zeros(jax.eval_shape(f, x, k).shape, x.dtype)
  text = str(jax.make_jaxpr(_value_and_grads(f, w))(x, k))
  return text.count("scan[") + text.count("while[")  # fori_loop: a scan (static trip count)


# (x shape, kernel shape, strides, padding): PSMNet's cases first, then odd ones.
CONV_CASES = [
    ((1, 6, 8, 8, 6), (3, 3, 3, 6, 4), (1, 1, 1), ((1, 1),) * 3),     # convbn_3d
    ((1, 6, 8, 8, 4), (3, 3, 3, 4, 1), (1, 1, 1), ((1, 1),) * 3),     # classifier 32 -> 1
    ((2, 6, 8, 8, 3), (3, 3, 3, 3, 5), (2, 2, 2), ((1, 1),) * 3),     # hourglass stride 2
    ((1, 5, 7, 9, 3), (3, 3, 3, 3, 2), (2, 2, 2), ((1, 1),) * 3),     # odd sizes
    ((1, 5, 6, 7, 2), (3, 2, 3, 2, 3), (2, 1, 2), ((0, 2), (1, 0), (2, 1))),
    ((1, 5, 6, 7, 2), (3, 3, 3, 2, 3), (2, 2, 2), "SAME"),
    # depth-stride-1 layers are computed by pairs of planes (fold.pair_forward): an odd count
    ((2, 5, 7, 6, 3), (3, 3, 3, 3, 2), (1, 2, 1), ((2, 0), (0, 2), (1, 1))),
]


@pytest.mark.parametrize("x_shape,k_shape,strides,padding", CONV_CASES)
def test_conv3d_forward_and_grads_equal_lax(x_shape, k_shape, strides, padding):
  x, k = _data(0, x_shape, k_shape)

  def ref(x, k):
    return lax.conv_general_dilated(x, k, strides, padding, dimension_numbers=DIMS)

  def fast(x, k):
    return c3.conv3d(x, k, strides, padding, impl="fast")

  _check_against(ref, fast, x, k, seed=1)


TRANSPOSE_CASES = [
    # PSMNet's hourglass conv5 / conv6 first.
    ((1, 3, 4, 4, 4), (3, 3, 3, 4, 3), (2, 2, 2), c3.transpose_padding((3, 3, 3), 1, 1)),
    ((2, 3, 4, 5, 3), (3, 3, 3, 3, 2), (2, 2, 2), c3.transpose_padding((3, 3, 3), 1, 0)),
    ((1, 3, 4, 5, 3), (4, 3, 2, 3, 2), (2, 3, 2), ((0, 1), (2, 2), (1, 0))),
]


@pytest.mark.parametrize("x_shape,k_shape,strides,padding", TRANSPOSE_CASES)
def test_conv_transpose3d_forward_and_grads_equal_lax(x_shape, k_shape, strides, padding):
  x, k = _data(2, x_shape, k_shape)

  def ref(x, k):
    return lax.conv_general_dilated(x, k, (1, 1, 1), padding, lhs_dilation=strides,
                                    dimension_numbers=DIMS)

  def fast(x, k):
    return c3.conv_transpose3d(x, k, strides, padding, impl="fast")

  _check_against(ref, fast, x, k, seed=3)


def _naive_torch_conv_transpose(x, w_torch, stride, padding, output_padding):
  """PyTorch ConvTranspose3d semantics by scattering: x NDHWC, w (cin, cout, kd, kh, kw)."""
  n, d, h, wd, _ = x.shape
  _, cout, kd, kh, kw = w_torch.shape
  op = output_padding
  full = np.zeros((n, (d - 1) * stride + kd + op, (h - 1) * stride + kh + op,
                   (wd - 1) * stride + kw + op, cout))
  for i in range(d):
    for j in range(h):
      for l in range(wd):
        contrib = np.einsum("nc,cokpq->nkpqo", x[:, i, j, l], w_torch)
        full[:, i * stride:i * stride + kd, j * stride:j * stride + kh,
             l * stride:l * stride + kw] += contrib
  out = [(s - 1) * stride - 2 * padding + k + op for s, k in ((d, kd), (h, kh), (wd, kw))]
  p = padding
  return full[:, p:p + out[0], p:p + out[1], p:p + out[2]]


@pytest.mark.parametrize("impl", ["lax", "fast"])
def test_conv_transpose_module_matches_pytorch_semantics(impl):
  rng = np.random.RandomState(4)
  x = rng.randn(1, 3, 4, 5, 3)
  w_torch = rng.randn(3, 2, 3, 3, 3)  # PyTorch layout (cin, cout, kd, kh, kw)
  kernel = np.flip(w_torch, (2, 3, 4)).transpose(2, 3, 4, 0, 1)
  module = c3.ConvTranspose3D(2, impl=impl)
  y = module.apply({"params": {"kernel": jnp.asarray(kernel, jnp.float32)}},
                   jnp.asarray(x, jnp.float32))
  expected = _naive_torch_conv_transpose(x, w_torch, 2, 1, 1)
  assert y.shape == (1, 6, 8, 10, 2)
  np.testing.assert_allclose(np.asarray(y), expected, rtol=1e-4, atol=1e-4)


def test_modules_have_flax_parameters_and_outputs():
  x, _ = _data(5, (1, 4, 6, 6, 3), (1,))
  key = jax.random.PRNGKey(0)  # only traced (eval_shape): flax's init compiles slowly
  for ours, theirs in [
      (c3.Conv3D(4, strides=2, padding=1, use_bias=True, impl="fast"),
       nn.Conv(4, (3, 3, 3), strides=2, padding=((1, 1),) * 3)),
      (c3.ConvTranspose3D(4, use_bias=True, impl="fast"),
       nn.ConvTranspose(4, (3, 3, 3), strides=(2, 2, 2), padding=((1, 2),) * 3)),
  ]:
    shapes = jax.eval_shape(theirs.init, key, x)
    assert jax.tree.map(jnp.shape, jax.eval_shape(ours.init, key, x)) == \
        jax.tree.map(jnp.shape, shapes)
    rng = np.random.RandomState(6)
    v = jax.tree.map(lambda s: jnp.asarray(rng.randn(*s.shape), jnp.float32), shapes)
    _assert_close(jax.jit(ours.apply)(v, x), jax.jit(theirs.apply)(v, x))


def test_impl_selection(monkeypatch):
  assert c3.conv_impl("lax") == "lax"
  monkeypatch.setenv("SLJAX_CONV3D", "lax")
  assert c3.conv_impl() == "lax"
  monkeypatch.setenv("SLJAX_CONV3D", "auto")
  assert c3.conv_impl() == c3.auto_impl(jax.default_backend())
  monkeypatch.setenv("SLJAX_CONV3D", "gpu-phase")
  assert c3.conv_impl() == "gpu-phase" and c3.conv_impl("gpu") == "gpu"
  # auto: the exact CPU kernels on a CPU, the native transposed conv on a GPU, else XLA's.
  assert [c3.auto_impl(b) for b in ("cpu", "gpu", "cuda", "rocm", "tpu")] == [
      "fast", "gpu", "gpu", "gpu", "lax"]
  with pytest.raises(ValueError, match="auto, lax, fast, gpu or gpu-phase"):
    c3.conv_impl("bogus")


def test_bfloat16_inputs_compute_in_bfloat16():
  """--precision bf16 casts inputs and kernels: every path keeps bfloat16 (no silent float32
  promotion) and stays close to the float32 result."""
  rng = np.random.default_rng(0)
  x = rng.standard_normal((1, 4, 6, 6, 3)).astype(np.float32)
  k = rng.standard_normal((3, 3, 3, 3, 5)).astype(np.float32)
  for fn, kw in ((c3.conv3d, {}), (c3.conv_transpose3d, {})):
    for impl in ("lax", "fast", "gpu", "gpu-phase"):
      want = fn(jnp.asarray(x), jnp.asarray(k), impl=impl, **kw)
      got = fn(jnp.asarray(x, jnp.bfloat16), jnp.asarray(k, jnp.bfloat16), impl=impl, **kw)
      assert got.dtype == jnp.bfloat16
      np.testing.assert_allclose(np.asarray(got, np.float32), np.asarray(want), rtol=0.05,
                                 atol=0.15)


# Block sizes (in values of one input plane) that force every blocking of `blocked`: one
# plane per block, chunks of planes, whole batch items, and one block for everything.
BLOCKINGS = [1, 2, 3, 10 ** 9]


@pytest.mark.parametrize("planes", BLOCKINGS)
@pytest.mark.parametrize("x_shape,k_shape,strides,padding", CONV_CASES[:4] + CONV_CASES[-1:])
def test_blocked_folded_conv_equals_lax(planes, x_shape, k_shape, strides,
                                        padding):
  """Every block shape (loops over batch items and plane chunks) gives lax's conv and grads."""
  block = planes * int(np.prod(x_shape[2:]))
  x, k = _data(7, x_shape, k_shape)

  def ref(x, k):
    return lax.conv_general_dilated(x, k, strides, padding, dimension_numbers=DIMS)

  fast = lambda x, k: c3.conv3d(x, k, strides, padding, impl="fast", block_values=block)
  _check_against(ref, fast, x, k, 8)


@pytest.mark.parametrize("planes", [1, 10 ** 9])
def test_blocked_transposed_conv_equals_lax(planes):
  x_shape, k_shape, strides, padding = TRANSPOSE_CASES[1]
  block = planes * int(np.prod(x_shape[2:]))
  x, k = _data(9, x_shape, k_shape)

  def ref(x, k):
    return lax.conv_general_dilated(x, k, (1, 1, 1), padding, lhs_dilation=strides,
                                    dimension_numbers=DIMS)

  fast = lambda x, k: c3.conv_transpose3d(x, k, strides, padding, impl="fast",
                                          block_values=block)
  _check_against(ref, fast, x, k, 10)


@pytest.mark.parametrize("padding", [((1, 1),) * 3, ((0, 2), (1, 0), (2, 1))])
def test_tap_products_path_for_few_outputs_equals_lax(padding):
  """PSMNet's 32 -> 1 classifiers take the tap-product path (27 taps x 1 output <= 32)."""
  x, k = _data(11, (2, 4, 5, 6, 32), (3, 3, 3, 32, 1))

  def ref(x, k):
    return lax.conv_general_dilated(x, k, (1, 1, 1), padding, dimension_numbers=DIMS)

  _check_against(ref, lambda x, k: c3.tap_products_conv3d(x, k, padding), x, k, 12)
  _check_against(ref, lambda x, k: c3.conv3d(x, k, (1, 1, 1), padding, impl="fast"), x, k, 12)


@pytest.mark.parametrize("rows", [1, 2, 10 ** 9])
@pytest.mark.parametrize("strides,padding,dilation", [
    ((1, 1), ((1, 1), (1, 1)), (1, 1)),
    ((2, 2), ((1, 1), (1, 1)), (1, 1)),       # PSMNet's firstconv stride 2
    ((1, 1), ((2, 2), (2, 2)), (2, 2)),       # dilated residual blocks
    ((2, 1), ((0, 2), (1, 0)), (1, 3)),       # odd ones
    ((1, 1), "SAME", (1, 1)),
])
def test_blocked_conv2d_equals_lax(rows, strides, padding, dilation):
  """conv2d's row-blocked kernel gradient equals XLA's, for every blocking."""
  x, k = _data(13, (2, 9, 7, 3), (3, 3, 3, 4))
  block = rows * 9 * 3

  def ref(x, k):
    return lax.conv_general_dilated(x, k, strides, padding, rhs_dilation=dilation,
                                    dimension_numbers=("NHWC", "HWIO", "NHWC"))

  fast = lambda x, k: c3.conv2d(x, k, strides, padding, dilation, impl="fast",
                                block_values=block)
  _check_against(ref, fast, x, k, 14)


def test_block_values_reaches_the_blocking():
  """block_values is the kernels' argument: one-plane blocks run in loops, the default in one
  block, and both equal lax (the module field too)."""
  x, k = _data(17, (1, 6, 8, 8, 6), (3, 3, 3, 6, 4))
  x2, k2 = _data(18, (2, 9, 7, 3), (3, 3, 3, 4))
  cases = [
      (lambda b: lambda x, k: c3.conv3d(x, k, impl="fast", block_values=b),
       lambda x, k: c3.lax_conv3d(x, k, (1, 1, 1), ((1, 1),) * 3), x, k),
      (lambda b: lambda x, k: c3.conv_transpose3d(x, k, impl="fast", block_values=b),
       lambda x, k: c3.lax_conv3d(x, k, (1, 1, 1), ((1, 2),) * 3, (2, 2, 2)), x, k),
      (lambda b: lambda x, k: c3.conv2d(x, k, impl="fast", block_values=b),
       lambda x, k: lax.conv_general_dilated(x, k, (1, 1), ((1, 1),) * 2,
                                             dimension_numbers=("NHWC", "HWIO", "NHWC")), x2, k2),
      (lambda b: lambda x, k: c3.Conv3D(4, impl="fast", block_values=b).apply(
          {"params": {"kernel": k}}, x),
       lambda x, k: c3.lax_conv3d(x, k, (1, 1, 1), ((1, 1),) * 3), x, k),
  ]
  for fast, ref, x, k in cases:
    assert _loops(fast(1), x, k) > 0 and _loops(fast(c3.BLOCK_VALUES), x, k) == 0
    _check_against(ref, fast(1), x, k, 19)


def test_conv2d_module_equals_flax_conv():
  x = jnp.asarray(np.random.RandomState(15).randn(2, 8, 8, 3), jnp.float32)
  ours = c3.Conv2D(4, (3, 3), strides=2, padding=((1, 1), (1, 1)), kernel_dilation=1)
  theirs = nn.Conv(4, (3, 3), strides=2, padding=((1, 1), (1, 1)))
  v = theirs.init(jax.random.PRNGKey(0), x)
  assert jax.tree.map(jnp.shape, ours.init(jax.random.PRNGKey(0), x)) == \
      jax.tree.map(jnp.shape, v)
  _assert_close(ours.apply(v, x), theirs.apply(v, x))
  # As nn.Conv: bfloat16 parameters and input (what --precision bf16 passes) stay bfloat16.
  vb = jax.tree.map(lambda a: a.astype(jnp.bfloat16), v)
  assert ours.apply(vb, x.astype(jnp.bfloat16)).dtype == jnp.bfloat16


def test_grad_blocks_set_the_kernel_gradients_blocks():
  """grad_blocks gives the kernel gradients traced inside blocks of their own (one-plane blocks
  run in loops, where the layer's default block has none) and leaves every value lax's; outside
  it, and after it, the layer's block_values serve again."""
  x, k = _data(21, (1, 6, 8, 8, 6), (3, 3, 3, 6, 4))
  x2, k2 = _data(22, (2, 9, 7, 3), (3, 3, 3, 4))
  cases = [
      (lambda x, k: c3.conv3d(x, k, impl="fast"),
       lambda x, k: c3.lax_conv3d(x, k, (1, 1, 1), ((1, 1),) * 3), x, k),
      (lambda x, k: c3.conv3d(x, k, (2, 2, 2), impl="fast"),
       lambda x, k: c3.lax_conv3d(x, k, (2, 2, 2), ((1, 1),) * 3), x, k),
      (lambda x, k: c3.conv_transpose3d(x, k, impl="fast"),
       lambda x, k: c3.lax_conv3d(x, k, (1, 1, 1), ((1, 2),) * 3, (2, 2, 2)), x, k),
      (lambda x, k: c3.conv2d(x, k, impl="fast"),
       lambda x, k: lax.conv_general_dilated(x, k, (1, 1), ((1, 1),) * 2,
                                             dimension_numbers=("NHWC", "HWIO", "NHWC")), x2, k2),
  ]
  for fast, ref, x, k in cases:
    assert _loops(fast, x, k) == 0
    with c3.grad_blocks(1):
      assert _loops(fast, x, k) > 0
      _check_against(ref, fast, x, k, 23)
    with c3.grad_blocks(None):
      assert _loops(fast, x, k) == 0
    assert _loops(fast, x, k) == 0
  # The layer's blocks stay the forward's: one-plane forward blocks keep their loops while the
  # kernel gradient runs in one block.
  x, k = _data(21, (1, 6, 8, 8, 6), (3, 3, 3, 6, 4))
  one_plane = lambda x, k: c3.conv3d(x, k, impl="fast", block_values=1)
  loops = _loops(one_plane, x, k)
  with c3.grad_blocks(c3.BLOCK_VALUES):
    assert 0 < _loops(one_plane, x, k) < loops
  with pytest.raises(RuntimeError), c3.grad_blocks(1):
    raise RuntimeError
  assert c3.grad_block_values(5) == 5
