"""The optimiser (sljax.train.state.make_optimizer): Adam with the reference's betas whose
learning rate drops by LR_DROP at drop_step, against Adam's update written out in float64;
and the step's flat gradient norm against the float64 norm."""

import jax
import jax.numpy as jnp
import numpy as np
import optax

from sljax.train import state as st
from sljax.train import step as stp


def _tree(seed, dtype=jnp.float32):
  rng = np.random.default_rng(seed)
  return {"a": {"kernel": jnp.asarray(rng.normal(size=(3, 3, 2, 4)), dtype),
                "bias": jnp.asarray(rng.normal(size=(4,)), dtype)},
          "b": jnp.asarray(rng.normal(size=(5,)), jnp.float32),
          "unc": {"s": jnp.asarray(0.3, jnp.float32)}}


def test_adam_with_the_drop_equals_the_update_written_out_in_float64():
  """Four steps, the rate dropping 10x from step 2: m, v, bias correction and the update by
  hand in float64 (betas 0.9 / 0.999, eps 1e-8)."""
  lr, b1, b2, eps = 1e-2, 0.9, 0.999, 1e-8
  params = _tree(0)
  tx = st.make_optimizer(lr, drop_step=2)
  state = tx.init(params)
  ref = [np.asarray(x, np.float64) for x in jax.tree.leaves(params)]
  m = [np.zeros_like(x) for x in ref]
  v = [np.zeros_like(x) for x in ref]
  update = jax.jit(lambda g, s, p: tx.update(g, s, p))
  for k in range(4):
    grads = _tree(10 + k)
    up, state = update(grads, state, params)
    params = optax.apply_updates(params, up)
    rate = lr * (st.LR_DROP if k >= 2 else 1.0)
    for i, g in enumerate(jax.tree.leaves(grads)):
      g = np.asarray(g, np.float64)
      m[i] = b1 * m[i] + (1 - b1) * g
      v[i] = b2 * v[i] + (1 - b2) * g * g
      mhat, vhat = m[i] / (1 - b1 ** (k + 1)), v[i] / (1 - b2 ** (k + 1))
      ref[i] = ref[i] - rate * mhat / (np.sqrt(vhat) + eps)
  for got, want in zip(jax.tree.leaves(params), ref):
    np.testing.assert_allclose(np.asarray(got, np.float64), want, rtol=1e-5, atol=1e-6)
  assert float(jnp.abs(params["b"] - _tree(0)["b"]).max()) > 1e-3  # it did update


def test_make_optimizer_keeps_the_state_tree_of_optax_adam():
  """Checkpoints hold optax's Adam state: the tree the optimiser keeps."""
  params = _tree(1)
  got = jax.tree.structure(st.make_optimizer(1e-3, drop_step=5).init(params))
  want = optax.adam(optax.piecewise_constant_schedule(1e-3, {5: 0.1})).init(params)
  assert got == jax.tree.structure(want)
  assert jax.tree.structure(st.make_optimizer(1e-3).init(params)) == jax.tree.structure(
      optax.adam(1e-3).init(params))


def test_bfloat16_parameters_keep_their_dtype():
  params, grads = _tree(2, jnp.bfloat16), _tree(3, jnp.bfloat16)
  tx = st.make_optimizer(1e-2)
  up, _ = tx.update(grads, tx.init(params), params)
  new = optax.apply_updates(params, up)
  assert new["a"]["kernel"].dtype == jnp.bfloat16 and new["b"].dtype == jnp.float32


def test_flat_norm_equals_the_float64_norm():
  tree = _tree(4)
  want = np.sqrt(sum(float(np.sum(np.asarray(x, np.float64) ** 2)) for x in jax.tree.leaves(tree)))
  np.testing.assert_allclose(float(stp.flat_norm(tree)), want, rtol=1e-6)
