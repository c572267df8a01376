"""The flat optimiser update (sljax.train.state.flat_update) and the step's flat helpers
against optax's leaf-by-leaf ones."""

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


def test_flat_adam_equals_optax_adam_over_steps_with_a_schedule():
  params = _tree(0)
  lr = optax.piecewise_constant_schedule(1e-2, {2: 0.1})
  ref_tx = optax.adam(lr, b1=0.9, b2=0.999)
  tx = st.flat_update(optax.adam(lr, b1=0.9, b2=0.999))
  ref_state, state = ref_tx.init(params), tx.init(params)
  ref_params = params
  for k in range(4):
    grads = _tree(10 + k)
    ref_up, ref_state = ref_tx.update(grads, ref_state, ref_params)
    up, state = jax.jit(tx.update)(grads, state, params)
    ref_params = optax.apply_updates(ref_params, ref_up)
    params = jax.jit(stp.apply_updates)(params, up)
  assert jax.tree.structure(state) == jax.tree.structure(ref_state)
  for got, want in zip(jax.tree.leaves((params, state)), jax.tree.leaves((ref_params, ref_state))):
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-6, atol=1e-7)
  assert float(jnp.abs(params["b"] - _tree(0)["b"]).max()) > 1e-3  # it did update


def test_make_optimizer_keeps_the_state_tree_of_optax_adam():
  params = _tree(1)
  got = jax.tree.structure(st.make_optimizer(1e-3, drop_step=5).init(params))
  want = optax.adam(optax.piecewise_constant_schedule(1e-3, {5: 0.1})).init(params)
  assert got == jax.tree.structure(want)


def test_mixed_dtypes_take_the_leaf_by_leaf_update():
  params = _tree(2, jnp.bfloat16)
  grads = _tree(3, jnp.bfloat16)
  tx = st.flat_update(optax.adam(1e-2))
  up, _ = tx.update(grads, tx.init(params), params)
  ref, _ = optax.adam(1e-2).update(grads, optax.adam(1e-2).init(params), params)
  assert all(a.dtype == b.dtype for a, b in zip(jax.tree.leaves(up), jax.tree.leaves(ref)))
  for a, b in zip(jax.tree.leaves(up), jax.tree.leaves(ref)):
    np.testing.assert_array_equal(np.asarray(a, np.float32), np.asarray(b, np.float32))
  new = stp.apply_updates(params, up)
  assert new["a"]["kernel"].dtype == jnp.bfloat16


def test_flat_norm_equals_the_float64_norm():
  tree = _tree(4)
  want = np.sqrt(sum(float(np.sum(np.asarray(x, np.float64) ** 2)) for x in jax.tree.leaves(tree)))
  np.testing.assert_allclose(float(stp.flat_norm(tree)), want, rtol=1e-6)
