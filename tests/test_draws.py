"""`batched_draws`: an initialiser's equal random draws made once per shape, the values bit for
bit those of the plain function (the reference: the same function traced and compiled as is)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sljax.nets import build_model
from sljax.nets.draws import batched_draws
from sljax.nets.model_config import INIT_COMPILER_OPTIONS
from sljax.nets.registry import NAMES


def _draws(closed) -> list[tuple]:
  """The shapes of every random_bits equation, jit calls and vmaps included."""
  found = []
  for eqn in closed.jaxpr.eqns:
    if eqn.primitive.name == "random_bits":
      found.append(tuple(eqn.params["shape"]))
    for value in eqn.params.values():
      if isinstance(value, jax.extend.core.ClosedJaxpr):
        found += _draws(value)
  return found


def _assert_same_bits(a, b):
  assert jax.tree.structure(a) == jax.tree.structure(b)
  for (path, x), y in zip(jax.tree_util.tree_flatten_with_path(a)[0], jax.tree.leaves(b)):
    x, y = np.asarray(x), np.asarray(y)
    assert x.dtype == y.dtype and x.shape == y.shape, jax.tree_util.keystr(path)
    assert np.array_equal(x.view(np.uint8), y.view(np.uint8)), jax.tree_util.keystr(path)


def _toy(key):
  out = {f"a{i}": jax.random.normal(jax.random.fold_in(key, i), (4, 5)) for i in range(3)}
  out.update({f"b{i}": jax.random.uniform(jax.random.fold_in(key, 10 + i), (7,)) * 3.0 + 1.0
              for i in range(2)})
  out["same"] = [jax.random.bits(key, (3,)), jax.random.bits(key, (3,))]
  out["c"] = jax.random.normal(jax.random.fold_in(jax.random.fold_in(key, 1), 2), (4, 5))
  out["ones"] = jnp.ones(2) * 2
  out["ints"] = [jnp.arange(4) * 2, jnp.arange(4) * 3]  # integer equations on stacked literals
  # a custom-JVP function and a loop over a draw (bound as jax's evaluator binds them)
  out["relu"] = jax.nn.relu(jax.random.normal(jax.random.fold_in(key, 20), (4, 5)))
  out["loop"] = jax.lax.fori_loop(0, 3, lambda i, v: v * 0.5 + i, out["b0"])
  return out


def test_equal_draws_are_one_vmapped_draw_with_each_keys_values():
  key = jax.random.PRNGKey(5)
  plain = jax.jit(_toy)(key)
  batched = jax.jit(batched_draws(_toy))(key)
  _assert_same_bits(batched, plain)
  assert not np.array_equal(plain["a0"], plain["a1"])  # distinct keys, distinct values
  # a0-a2 and c: one draw of (4, 5) per depth (c's key is folded twice, so it is drawn a level
  # deeper); b0, b1 one of (7,); the two draws of one key one of (3,)
  assert sorted(_draws(jax.make_jaxpr(_toy)(key))) == sorted([(4, 5)] * 5 + [(7,)] * 2
                                                              + [(3,)] * 2)
  assert sorted(_draws(jax.make_jaxpr(batched_draws(_toy))(key))) == [(3,), (4, 5), (4, 5),
                                                                      (7,)]


@pytest.mark.parametrize("net", NAMES)
def test_every_network_initialises_bit_for_bit_as_its_plain_init(net):
  kwargs = {"maxdisp": 16} if net.startswith("psmnet") else {"depth": 2, "base_width": 8}
  model = build_model(net, **kwargs)
  x = jnp.zeros((1, 32, 32, 3), jnp.float32)
  init = lambda key: model.init(key, x, x, train=False)
  key = jax.random.PRNGKey(11)
  plain = jax.jit(init, compiler_options=INIT_COMPILER_OPTIONS)(key)
  batched = jax.jit(batched_draws(init), compiler_options=INIT_COMPILER_OPTIONS)(key)
  _assert_same_bits(batched, plain)
  draws = _draws(jax.make_jaxpr(init)(key))
  assert len(_draws(jax.make_jaxpr(batched_draws(init))(key))) == len(set(draws)) < len(draws)
