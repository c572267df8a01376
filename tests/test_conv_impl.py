"""The convolution implementation is the model's explicit choice: "lax" and "fast" models live
side by side in one process, and $SLJAX_CONV3D is only the default, read when a model is built."""

import re

import flax.linen as nn
import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np
import pytest

from sljax.errors import SljaxError
from sljax.kernels import ConvBase
from sljax.nets import PSMNetMTL, UNet, build_model
from sljax.nets.model_config import INIT_COMPILER_OPTIONS

SIZE, MAXDISP = 32, 16
# unsafe_rbg compiles the initialisers far faster than threefry on the CPU.
KEY = jax.random.key(1, impl="unsafe_rbg")


def _pair(channels=3, seed=0):
  rng = np.random.RandomState(seed)
  return tuple(jnp.asarray(rng.rand(1, SIZE, SIZE, channels).astype(np.float32))
               for _ in range(2))


def _conv_ranks(model, left, right, variables) -> list[int]:
  """Spatial ranks (2 or 3) of the convolutions in the model's evaluation program."""
  text = str(jax.make_jaxpr(lambda v: model.apply(v, left, right))(variables))
  return [len(spec.split(",")) - 2 for spec in re.findall(r"lhs_spec=\(([\d, ]+)\)", text)]


def _custom_vjps(model, left, right, variables) -> int:
  """Custom-VJP calls in the model's evaluation program (the fast kernels are custom VJPs),
  counted per call: a jitted kernel's calls share one jaxpr, which the printed program shows
  once."""
  def count(jaxpr) -> int:
    return sum((eqn.primitive.name == "custom_vjp_call")
               + sum(count(sub) for sub in jax.extend.core.jaxprs_in_params(eqn.params))
               for eqn in jaxpr.eqns)
  return count(jax.make_jaxpr(lambda v: model.apply(v, left, right))(variables).jaxpr)


def _impls_seen(model, left, right) -> list[str | None]:
  """The `impl` of every convolution module the model calls (traced only)."""
  seen = []

  def record(next_fun, args, kwargs, context):
    if isinstance(context.module, ConvBase) and context.method_name == "__call__":
      seen.append(context.module.impl)
    return next_fun(*args, **kwargs)

  with nn.intercept_methods(record):
    jax.eval_shape(model.init, KEY, left, right)
  return seen


def _assert_trees_close(a, b, tol):
  """Leaf by leaf, relative to each leaf's largest magnitude."""
  leaves_a, leaves_b = jax.tree.leaves(a), jax.tree.leaves(b)
  assert len(leaves_a) == len(leaves_b) > 0
  for x, y in zip(leaves_a, leaves_b):
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    scale = max(np.abs(y).max(), 1e-12)
    np.testing.assert_allclose(x / scale, y / scale, rtol=0, atol=tol)


def _outputs_and_grads(model, variables, left, right, grads=True):
  """Training-mode outputs and the parameter gradient of a fixed projection of them, in
  float64: a small random PSMNet amplifies float32 rounding (its costs reach 1e6 and its
  gradients differ by tens of percent between two exact float32 formulations), while in
  float64 the two implementations agree to 1e-11."""
  with jax.enable_x64(True):
    variables = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), variables)
    left, right = jnp.asarray(left, jnp.float64), jnp.asarray(right, jnp.float64)

    def loss(params):
      out, _ = model.apply({**variables, "params": params}, left, right, train=True,
                           mutable=["batch_stats"])
      leaves = jax.tree.leaves(out)
      return sum(jnp.sum(o * jnp.cos(jnp.arange(o.size).reshape(o.shape))) for o in leaves), out

    if not grads:
      return jax.tree.map(np.asarray, jax.jit(loss)(variables["params"])[1])
    (_, out), g = jax.jit(jax.value_and_grad(loss, has_aux=True))(variables["params"])
    return jax.tree.map(np.asarray, (out, g))


# PSMNet's parameter gradients are compared kernel by kernel (tests/test_conv3d.py: every fast
# 3D kernel's VJP against lax's), not through the whole network: its float64 gradient programs
# took 70 s of the suite's compile time on a Zen 3 and guard no wiring the outputs do not.
@pytest.mark.parametrize("name, kwargs, channels, grads", [
    ("psmnet", {"maxdisp": MAXDISP}, 3, False),
    ("unet-sl", {"t": 3, "depth": 2, "base_width": 4}, 1, True),
])
def test_lax_and_fast_models_in_one_process_agree(monkeypatch, name, kwargs, channels, grads):
  """Built with "lax" and "fast" in one process (no environment): the same parameter tree,
  equal training-mode outputs (and parameter gradients for the UNet), and really two
  programs: every convolution module got the model's choice, and the fast program has no 3D
  convolution but custom VJPs."""
  monkeypatch.delenv("SLJAX_CONV3D", raising=False)
  left, right = _pair(channels)
  lax_model = build_model(name, conv_impl="lax", in_channels=channels, **kwargs)
  fast_model = build_model(name, conv_impl="fast", in_channels=channels, **kwargs)
  assert (lax_model.conv_impl, fast_model.conv_impl) == ("lax", "fast")
  variables = jax.jit(lax_model.init, compiler_options=INIT_COMPILER_OPTIONS)(KEY, left, right)
  assert jax.tree.map(jnp.shape, jax.eval_shape(fast_model.init, KEY, left, right)) == \
      jax.tree.map(jnp.shape, variables)  # the same parameter tree

  want = _outputs_and_grads(lax_model, variables, left, right, grads)
  got = _outputs_and_grads(fast_model, variables, left, right, grads)
  _assert_trees_close(got, want, 1e-9)

  lax_ranks = _conv_ranks(lax_model, left, right, variables)
  fast_ranks = _conv_ranks(fast_model, left, right, variables)
  assert 3 not in fast_ranks
  assert (3 in lax_ranks) == name.startswith("psmnet")
  lax_seen = _impls_seen(lax_model, left, right)
  fast_seen = _impls_seen(fast_model, left, right)
  assert set(lax_seen) == {"lax"} and set(fast_seen) == {"fast"}
  assert len(lax_seen) == len(fast_seen)
  # The fast convolutions are custom VJPs, the lax ones plain: one per UNet Conv2D (PSMNet's
  # transposed ones hold a folded one, its 32 -> 1 classifiers are tap products).
  extra = (_custom_vjps(fast_model, left, right, variables)
           - _custom_vjps(lax_model, left, right, variables))
  assert extra == len(fast_seen) if name == "unet-sl" else extra > 0


def test_environment_is_only_the_default_read_when_built(monkeypatch):
  """$SLJAX_CONV3D=lax: an explicit "fast" still wins; with nothing explicit the environment
  decides when the model is built, and changing it afterwards changes nothing."""
  left, right = _pair()
  monkeypatch.setenv("SLJAX_CONV3D", "lax")
  explicit = build_model("psmnet", maxdisp=MAXDISP, conv_impl="fast")
  default = build_model("psmnet", maxdisp=MAXDISP)
  twin = PSMNetMTL(maxdisp=MAXDISP, t=2)  # direct construction: same rule
  unet = UNet(depth=1, base_width=2, in_channels=3)
  auto = build_model("psmnet", maxdisp=MAXDISP, conv_impl="auto")  # the backend's, not env
  assert (explicit.conv_impl, default.conv_impl, twin.conv_impl, unet.conv_impl) == (
      "fast", "lax", "lax", "lax")
  assert auto.conv_impl == {"cpu": "fast", "gpu": "gpu"}.get(jax.default_backend(), "lax")

  monkeypatch.setenv("SLJAX_CONV3D", "fast")  # too late for the models above
  assert set(_impls_seen(default, left, right)) == {"lax"}
  assert set(_impls_seen(twin, left, right)) == {"lax"}
  assert set(_impls_seen(unet, left, right)) == {"lax"}
  assert set(_impls_seen(explicit, left, right)) == {"fast"}
  variables = jax.eval_shape(default.init, KEY, left, right)  # traced, never compiled
  assert 3 in _conv_ranks(default, left, right, variables)
  assert 3 not in _conv_ranks(explicit, left, right, variables)
  # That the two programs compute the same function is the test above's job.

  monkeypatch.delenv("SLJAX_CONV3D")
  assert build_model("unet-disp").conv_impl == auto.conv_impl
  with pytest.raises(SljaxError, match="auto, lax, fast, gpu or gpu-phase"):  # a clear error
    build_model("psmnet", conv_impl="bogus")
