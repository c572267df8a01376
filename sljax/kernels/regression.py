"""Soft-argmax regression over disparity planes upsampled by phases, its gradient written out."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

Phases = tuple[tuple[int, float, float], ...]


def _phase_planes(c: jax.Array, phases: Phases) -> list[jax.Array]:
  """Disparity planes f*i + r (in order) of edge-extended costs c [B, D + 2, H, W]."""
  d = c.shape[1] - 2
  return [w0 * c[:, 1 + s + i] + w1 * c[:, 2 + s + i] for i in range(d) for s, w0, w1 in phases]


def _regression_parts(c: jax.Array, phases: Phases):
  ups = _phase_planes(c, phases)
  top = functools.reduce(jnp.maximum, ups)
  exps = [jnp.exp(u - top) for u in ups]
  z = sum(exps)
  return sum(k * e for k, e in enumerate(exps)) / z, top + jnp.log(z)


@functools.partial(jax.custom_vjp, nondiff_argnums=(1,))
def phase_regression(c: jax.Array, phases: Phases) -> jax.Array:
  """sum_k k softmax(u)_k over the upsampled planes u_k of edge-extended costs c [B, D+2, H, W].

  Plane f*i + r is w0 * c[:, 1 + s + i] + w1 * c[:, 2 + s + i] for phase r = (s, w0, w1) of
  `sljax.nets.layers.linear_resize_phases`: the disparity regression of linearly upsampled
  costs without building the upsampled volume. Returns [B, H, W].
  """
  return _regression_parts(c, phases)[0]


def _regression_fwd(c, phases):
  pred, lse = _regression_parts(c, phases)
  return pred, (c, pred, lse)


def _regression_bwd(phases, res, g):
  # d pred / d u_k = p_k (k - pred) with p_k = exp(u_k - logsumexp); each plane of c collects
  # the interpolation weights of the (at most 2f) upsampled planes that read it. Written out
  # (autodiff's graph is 20x slower on XLA:CPU) and free of the maximum, which XLA would
  # otherwise recompute inside every plane's fusion. Saves the output and its log-sum-exp
  # beside the input, so it is not a `vjp_saving_inputs` VJP.
  c, pred, lse = res
  f = len(phases)
  terms = [[] for _ in range(c.shape[1])]
  for k, u in enumerate(_phase_planes(c, phases)):
    i, (s, w0, w1) = k // f, phases[k % f]
    gu = jnp.exp(u - lse) * (k - pred) * g
    terms[1 + s + i].append(w0 * gu)
    terms[2 + s + i].append(w1 * gu)
  zero = jnp.zeros_like(pred)
  return (jnp.stack([sum(t) if t else zero for t in terms], axis=1),)


phase_regression.defvjp(_regression_fwd, _regression_bwd)
