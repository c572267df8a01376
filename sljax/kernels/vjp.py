"""The one way this package writes a custom VJP whose backward needs only the inputs."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax


def vjp_saving_inputs(forward: Callable, backward: Callable,
                      nondiff_argnums: Sequence[int] = ()) -> Callable:
  """forward(*args) with the hand-written backward(*nondiff_args, inputs, dy) as its VJP,
  jitted with the non-differentiable arguments static (they must be hashable).

  The residuals are the differentiable inputs (in order), so the backward recomputes what it
  needs from them instead of keeping the forward's intermediates alive. Jitted, a network's
  layers of one shape are traced and differentiated once, not once per layer: XLA inlines the
  calls, so the compiled program and its values are those of the plain function (issue 49:
  with the BatchNorms, the twin's step traced in 1.1 s against 2.4 s).
  """
  nondiff = tuple(nondiff_argnums)
  f = jax.custom_vjp(forward, nondiff_argnums=nondiff)

  def fwd(*args):
    return forward(*args), tuple(a for i, a in enumerate(args) if i not in nondiff)

  f.defvjp(fwd, backward)
  return jax.jit(f, static_argnums=nondiff)
