"""The GPU forms of the stride-2 transposed 3D convolution ("gpu", "gpu-phase") equal lax's
in value and in both gradients, give XLA:GPU the convolution patterns cuDNN runs natively, and
leave PSMNet's function and parameters unchanged."""

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from sljax import kernels as c3
from sljax.nets.model_config import ModelConfig
from sljax.nets.psmnet import Hourglass

DIMS = ("NDHWC", "DHWIO", "NDHWC")
GPU_FORMS = ("gpu", "gpu-phase")
KEY = jax.random.key(3, impl="unsafe_rbg")  # compiles the initialisers fast on the CPU

# (x shape, kernel shape, strides, lax padding of the dilated input): PSMNet's hourglass conv5
# (64 -> 64) and conv6 (64 -> 32) made tiny (PyTorch padding 1, output padding 1), then odd
# sizes without output padding, a negative adjoint padding (high padding past k - 1) and mixed
# kernel sizes and strides.
CASES = [
    ((2, 3, 4, 4, 6), (3, 3, 3, 6, 6), (2, 2, 2), c3.transpose_padding((3, 3, 3), 1, 1)),
    ((1, 3, 4, 4, 6), (3, 3, 3, 6, 3), (2, 2, 2), c3.transpose_padding((3, 3, 3), 1, 1)),
    ((1, 3, 5, 7, 3), (3, 3, 3, 3, 2), (2, 2, 2), c3.transpose_padding((3, 3, 3), 1, 0)),
    ((1, 2, 3, 4, 2), (3, 3, 3, 2, 3), (2, 2, 2), ((1, 3), (0, 0), (2, 1))),
    ((1, 3, 4, 5, 3), (4, 3, 2, 3, 2), (2, 3, 2), ((0, 1), (2, 2), (1, 0))),
]


def _lax_form(strides, padding):
  """The reference: lax's convolution of the s-dilated input with the unflipped kernel."""
  return lambda x, k: lax.conv_general_dilated(x, k, (1, 1, 1), padding, lhs_dilation=strides,
                                               dimension_numbers=DIMS)


def _value_and_grads(f, x, k, w):
  """f(x, k) and its two gradients against the output weights w, compiled."""
  def run(x, k):
    y, vjp = jax.vjp(f, x, k)
    return (y,) + vjp(w)
  return jax.jit(run)(x, k)


@pytest.mark.parametrize("impl", GPU_FORMS)
@pytest.mark.parametrize("x_shape,k_shape,strides,padding", CASES)
def test_gpu_forms_equal_lax_in_value_and_both_gradients(impl, x_shape, k_shape, strides,
                                                         padding):
  """In float64 the forms agree with lax to 1e-12 of each result's scale: the same function,
  not an approximation; in float32 to the suite's float tolerance (2e-5)."""
  rng = np.random.RandomState(sum(x_shape) + len(impl))
  x, k = rng.randn(*x_shape), rng.randn(*k_shape)
  ref = _lax_form(strides, padding)
  w = rng.randn(*jax.eval_shape(ref, x, k).shape)

  def form(x, k):
    return c3.conv_transpose3d(x, k, strides, padding, impl=impl)

  for dtype, tol in ((jnp.float64, 1e-12), (jnp.float32, 2e-5)):
    with jax.enable_x64(dtype == jnp.float64):
      args = [jnp.asarray(a, dtype) for a in (x, k, w)]
      got, want = _value_and_grads(form, *args), _value_and_grads(ref, *args)
    for name, a, b in zip(("value", "dL/dx", "dL/dkernel"), got, want):
      assert a.dtype == dtype and a.shape == b.shape, name
      scale = float(np.abs(np.asarray(b, np.float64)).max())
      err = float(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)).max())
      assert err <= tol * scale, (name, dtype, err / scale)


@pytest.mark.parametrize("impl", GPU_FORMS)
def test_gpu_forms_keep_bfloat16_in_value_and_gradients(impl):
  """--precision bf16 casts inputs and kernels: the value and both gradients stay bfloat16
  (a custom VJP must return its inputs' dtypes) and near lax's bfloat16 results."""
  strides, padding = (2, 2, 2), c3.transpose_padding((3, 3, 3), 1, 1)
  rng = np.random.RandomState(5)
  x, k, w = (jnp.asarray(rng.randn(*s), jnp.bfloat16)
             for s in ((1, 2, 3, 4, 4), (3, 3, 3, 4, 2), (1, 4, 6, 8, 2)))
  got = _value_and_grads(lambda x, k: c3.conv_transpose3d(x, k, strides, padding, impl=impl),
                         x, k, w)
  want = _value_and_grads(_lax_form(strides, padding), x, k, w)
  for a, b in zip(got, want):
    assert a.dtype == jnp.bfloat16 and a.shape == b.shape
    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    assert np.abs(a - b).max() <= 0.02 * np.abs(b).max()


def _convs(jaxpr) -> list[dict]:
  """Every convolution of a jaxpr (nested ones included): its dilations and strides, and what
  produced its kernel operand ('rev' of a 'barrier' output, 'rev', or None)."""
  out = []
  producers = {}
  for eqn in jaxpr.eqns:
    for v in eqn.outvars:
      producers[v] = eqn
    if eqn.primitive.name == "conv_general_dilated":
      p = eqn.params
      src = producers.get(eqn.invars[1])
      kernel = None
      if src is not None and src.primitive.name == "rev":
        spatial = set(p["dimension_numbers"].rhs_spec[2:])
        inner = producers.get(src.invars[0])
        behind = inner is not None and inner.primitive.name == "optimization_barrier"
        kernel = ("rev of barrier" if behind else "rev") if set(
            src.params["dimensions"]) == spatial else "partial rev"
      out.append({"lhs_dilation": tuple(p["lhs_dilation"]),
                  "rhs_dilation": tuple(p["rhs_dilation"]),
                  "strides": tuple(p["window_strides"]), "kernel": kernel})
    for sub in jax.extend.core.jaxprs_in_params(eqn.params):
      out += _convs(sub)
  return out


@pytest.mark.parametrize("impl", ("lax",) + GPU_FORMS)
def test_programs_have_the_convolution_patterns_cudnn_runs_natively(impl):
  """XLA:GPU hands a convolution to cuDNN's native kernels when it is a forward one (no input
  dilation), a backward-data one (input dilation and a kernel reversed in the program) or a
  weight gradient (stride 1, kernel dilation, no input dilation); a convolution with input
  dilation and an unreversed kernel is computed on the explicitly dilated input, and when its
  kernel is an output gradient as large as the output (the lax form's kernel gradient), in a
  slow fallback (issue 36: 65% of PSMNet's GPU step). The GPU forms have none such; the
  backward-data form's reversed kernel sits behind a barrier so that XLA cannot fold the
  double reversal away. This pins the diagnosis and the fix; the speed is measured on a GPU
  (benchmarks/bench_convT.py)."""
  strides, padding = (2, 2, 2), c3.transpose_padding((3, 3, 3), 1, 1)
  x, k = jnp.ones((1, 3, 4, 4, 6)), jnp.ones((3, 3, 3, 6, 3))
  w = jnp.ones((1, 6, 8, 8, 3))

  def run(x, k):
    y, vjp = jax.vjp(lambda x, k: c3.conv_transpose3d(x, k, strides, padding, impl=impl), x, k)
    return (y,) + vjp(w)

  convs = _convs(jax.make_jaxpr(run)(x, k).jaxpr)
  assert len(convs) == 3  # forward, dL/dx, dL/dkernel
  dilated = [c for c in convs if c["lhs_dilation"] != (1, 1, 1)]
  weight_grads = [c for c in convs if c["rhs_dilation"] == strides]
  if impl == "lax":  # the forward and the kernel gradient dilate the input, unreversed
    assert len(dilated) == 2 and all(c["kernel"] is None for c in dilated)
    assert not weight_grads
    return
  assert len(weight_grads) == 1 and weight_grads[0]["strides"] == (1, 1, 1)
  assert [c["strides"] for c in convs].count(strides) == 1  # dL/dx: the adjoint strided conv
  if impl == "gpu":
    assert len(dilated) == 1 and dilated[0]["kernel"] == "rev of barrier"
  else:
    assert not dilated  # the phases: stride-1 convolutions of the undilated input


@pytest.mark.parametrize("impl", GPU_FORMS)
def test_conv_transpose_module_keeps_flax_parameters(impl):
  """ConvTranspose3D with a GPU form: nn.ConvTranspose's parameter tree, lax's output."""
  x = jnp.asarray(np.random.RandomState(7).randn(1, 3, 4, 5, 4), jnp.float32)
  ours = c3.ConvTranspose3D(3, use_bias=True, impl=impl)
  theirs = c3.ConvTranspose3D(3, use_bias=True, impl="lax")
  shapes = jax.eval_shape(theirs.init, KEY, x)
  assert jax.tree.map(jnp.shape, jax.eval_shape(ours.init, KEY, x)) == \
      jax.tree.map(jnp.shape, shapes)
  rng = np.random.RandomState(8)
  v = jax.tree.map(lambda s: jnp.asarray(rng.randn(*s.shape), jnp.float32), shapes)
  np.testing.assert_allclose(np.asarray(jax.jit(ours.apply)(v, x)),
                             np.asarray(jax.jit(theirs.apply)(v, x)), rtol=0, atol=2e-5 * float(
                                 np.abs(np.asarray(jax.jit(theirs.apply)(v, x))).max()))


@pytest.mark.parametrize("impl", GPU_FORMS)
def test_psmnet_hourglass_with_gpu_forms_equals_lax(impl):
  """PSMNet's hourglass (strided convs, conv5 and conv6 transposed, BatchNorm with batch
  statistics) built with a GPU form and with "lax": in float64 equal outputs (out, pre, post),
  gradients for the input and every parameter, to 1e-9 of each result's scale. The whole
  network's float64 gradient programs take minutes to compile on a CPU; the network's output
  with the form is checked against the PyTorch reference itself
  (tests/test_reference_psmnet.py)."""
  rng = np.random.RandomState(1)
  x = rng.randn(2, 4, 8, 8, 4)
  lax_hg, form_hg = (Hourglass(inplanes=4, conv_impl=i) for i in ("lax", impl))
  with jax.enable_x64(True):
    x = jnp.asarray(x, jnp.float64)
    shapes = jax.eval_shape(lambda x: lax_hg.init(KEY, x, None, None, False), x)
    assert jax.tree.map(jnp.shape, jax.eval_shape(
        lambda x: form_hg.init(KEY, x, None, None, False), x)) == jax.tree.map(jnp.shape, shapes)
    variables = jax.tree.map(lambda s: jnp.asarray(0.3 * rng.randn(*s.shape), jnp.float64),
                             shapes)

    def run(module):
      def loss(params, x):
        outs, _ = module.apply({**variables, "params": params}, x, None, None, True,
                               mutable=["batch_stats"])
        return sum(jnp.sum(o * jnp.cos(jnp.arange(o.size).reshape(o.shape))) for o in outs), outs
      (_, outs), grads = jax.jit(jax.value_and_grad(loss, (0, 1), has_aux=True))(
          variables["params"], x)
      return jax.tree.map(np.asarray, (outs, grads))

    want, got = run(lax_hg), run(form_hg)
  leaves_want, leaves_got = jax.tree.leaves(want), jax.tree.leaves(got)
  assert len(leaves_want) == len(leaves_got) > 20
  for a, b in zip(leaves_got, leaves_want):
    scale = max(float(np.abs(b).max()), 1e-12)
    np.testing.assert_allclose(a / scale, b / scale, rtol=0, atol=1e-9)


def test_every_impl_gives_the_same_parameter_tree_and_saved_config():
  """Checkpoints and converted weights (sljax convert-psmnet) load into a model of any
  convolution choice: the variable trees (names, shapes) are equal, and the configuration a
  checkpoint saves leaves the choice out."""
  x = jax.ShapeDtypeStruct((1, 16, 16, 3), jnp.float32)
  trees, saved = [], []
  for impl in ("lax",) + GPU_FORMS:
    config = ModelConfig.of("psmnet", conv_impl=impl, maxdisp=16)
    model = config.build()
    assert model.conv_impl == impl
    trees.append(jax.tree.map(jnp.shape, jax.eval_shape(model.init, KEY, x, x)))
    saved.append(config.saved_kwargs)
  assert all(t == trees[0] for t in trees) and all(s == saved[0] for s in saved)
