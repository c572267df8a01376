"""Equal random draws of an initialiser made once, vmapped over their keys.

A network's `init` draws each parameter from its own key: the twin draws 116 arrays of 19
shapes, and XLA compiles every draw (a threefry loop and its bit twiddling) as kernels of its
own, most of the initialiser's compile time. `batched_draws(fn)` traces `fn`, inlines its jit
calls, and runs the integer and key equations that are equal but for their inputs (the same
primitive, parameters and input types at the same depth) as one vmapped equation, so each shape
is drawn once per depth over a stack of keys. Floating-point equations run as traced, one
array at a time, so every value is bit for bit what `fn` gives (jax's random bits under vmap
are those of each key alone; tests/test_draws.py checks each network).
"""

from __future__ import annotations

import collections
import functools
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jcore

_CALLS = ("jit", "pjit")


class _Var:
  """A variable of the inlined equations (jaxpr variables are not shared across calls)."""
  __slots__ = ("aval",)

  def __init__(self, aval):
    self.aval = aval


class _Eqn:
  __slots__ = ("primitive", "params", "invars", "outvars", "effects")

  def __init__(self, primitive, params, invars, outvars, effects):
    self.primitive, self.params = primitive, params
    self.invars, self.outvars, self.effects = invars, outvars, effects


class _Lane:
  """Row `i` of a batched result, indexed only where an unbatched equation reads it."""
  __slots__ = ("batch", "i")

  def __init__(self, batch, i):
    self.batch, self.i = batch, i


def _inline(jaxpr, invars: Sequence[Any]) -> tuple[list[_Eqn], list[Any]]:
  """The equations of `jaxpr` with its jit calls inlined, over fresh variables (`invars`
  stand for its constants', then its inputs' variables)."""
  env = dict(zip(list(jaxpr.constvars) + list(jaxpr.invars), invars))
  sub = lambda a: a if isinstance(a, jcore.Literal) else env[a]
  eqns = []
  for eqn in jaxpr.eqns:
    ins = [sub(a) for a in eqn.invars]
    call = eqn.params.get("jaxpr") if eqn.primitive.name in _CALLS else None
    if call is not None and not call.consts:
      inner, outs = _inline(call.jaxpr, ins)
      eqns += inner
    else:
      outs = [_Var(v.aval) for v in eqn.outvars]
      eqns.append(_Eqn(eqn.primitive, eqn.params, ins, outs, eqn.effects))
    env.update(zip(eqn.outvars, outs))
  return eqns, [sub(a) for a in jaxpr.outvars]


def _live(eqns: list[_Eqn], outvars: list[Any]) -> list[_Eqn]:
  """The equations the outputs depend on (the initialiser's forward pass is dead)."""
  needed = {id(v) for v in outvars}
  kept = []
  for eqn in reversed(eqns):
    if eqn.effects or any(id(v) in needed for v in eqn.outvars):
      kept.append(eqn)
      needed.update(id(a) for a in eqn.invars if not isinstance(a, jcore.Literal))
  return kept[::-1]


def _levels(eqns: list[_Eqn]) -> list[list[_Eqn]]:
  """Equations by depth: one longer than the deepest equation each reads from."""
  depth: dict[int, int] = {}
  levels = collections.defaultdict(list)
  for eqn in eqns:
    d = 1 + max((depth.get(id(a), 0) for a in eqn.invars
                 if not isinstance(a, jcore.Literal)), default=0)
    depth.update((id(v), d) for v in eqn.outvars)
    levels[d].append(eqn)
  return [levels[d] for d in sorted(levels)]


def _batchable(eqn: _Eqn) -> bool:
  """Integer and key equations only: floating-point ones stay unbatched, so that XLA's
  fusions of them, and with it their rounding, are those of the plain program."""
  return not eqn.effects and all(
      not jnp.issubdtype(v.aval.dtype, jnp.inexact) for v in eqn.outvars)


def _signature(eqn: _Eqn) -> tuple:
  return (eqn.primitive, tuple(a.aval for a in eqn.invars),
          repr(sorted(eqn.params.items(), key=lambda kv: kv[0])))


def _same(inputs: list[Any]) -> bool:
  first = inputs[0]
  if isinstance(first, jcore.Literal):
    return all(isinstance(a, jcore.Literal) and np.asarray(a.val).dtype == np.asarray(
        first.val).dtype and np.array_equal(a.val, first.val) for a in inputs)
  return all(a is first for a in inputs)


def _bind(eqn: _Eqn, args: list[Any]) -> list[Any]:
  """The equation applied to `args`, as jax's own jaxpr evaluator binds it."""
  params = eqn.primitive.get_bind_params(eqn.params)
  subfuns = ()
  if isinstance(params, tuple):  # jax before 0.7: (subfuns, params)
    subfuns, params = params
  out = eqn.primitive.bind(*subfuns, *args, **params)
  return out if eqn.primitive.multiple_results else [out]


class _Env:
  def __init__(self):
    self.values: dict[int, Any] = {}

  def read(self, a):
    if isinstance(a, jcore.Literal):
      return a.val
    value = self.values[id(a)]
    return value.batch[value.i] if isinstance(value, _Lane) else value

  def stacked(self, inputs: list[Any]):
    """The inputs as one array along a new first axis, reusing a batch already in order."""
    if all(isinstance(a, jcore.Literal) for a in inputs):
      return jnp.asarray(np.stack([np.asarray(a.val, a.aval.dtype) for a in inputs]))
    lanes = [self.values.get(id(a)) for a in inputs]
    first = lanes[0]
    if (isinstance(first, _Lane) and first.batch.shape[0] == len(inputs)
        and all(isinstance(l, _Lane) and l.batch is first.batch and l.i == i
                for i, l in enumerate(lanes))):
      return first.batch
    return jnp.stack([self.read(a) for a in inputs])

  def bind(self, eqn: _Eqn) -> None:
    outs = _bind(eqn, [self.read(a) for a in eqn.invars])
    self.values.update(zip(map(id, eqn.outvars), outs))

  def bind_batched(self, group: list[_Eqn]) -> None:
    """Equal equations as one: shared inputs passed once, the others stacked and vmapped."""
    first = group[0]
    columns = [[eqn.invars[p] for eqn in group] for p in range(len(first.invars))]
    shared = {p: self.read(col[0]) for p, col in enumerate(columns) if _same(col)}
    varying = [p for p in range(len(columns)) if p not in shared]
    if not varying:  # the same computation repeated: once, its results shared
      self.bind(first)
      for eqn in group[1:]:
        for mine, theirs in zip(eqn.outvars, first.outvars):
          self.values[id(mine)] = self.values[id(theirs)]
      return

    def one(*xs):
      args = {**shared, **dict(zip(varying, xs))}
      return _bind(first, [args[p] for p in range(len(columns))])

    outs = jax.vmap(one)(*[self.stacked(columns[p]) for p in varying])
    for i, eqn in enumerate(group):
      for var, batch in zip(eqn.outvars, outs):
        self.values[id(var)] = _Lane(batch, i)


def _evaluate(eqns: list[_Eqn], invars: list[Any], outvars: list[Any], args: Sequence[Any]):
  env = _Env()
  env.values.update(zip(map(id, invars), args))
  for level in _levels(eqns):
    groups: dict[tuple, list[_Eqn]] = collections.defaultdict(list)
    for eqn in level:
      if _batchable(eqn):
        groups[_signature(eqn)].append(eqn)
      else:
        env.bind(eqn)
    for group in groups.values():
      if len(group) == 1:
        env.bind(group[0])
      else:
        env.bind_batched(group)
  return [env.read(v) for v in outvars]


def batched_draws(fn: Callable[..., Any]) -> Callable[..., Any]:
  """`fn` with its equal integer and key equations (random draws) run once per depth,
  vmapped; the same values bit for bit, for fewer kernels to compile."""
  @functools.wraps(fn)
  def run(*args):
    closed, shapes = jax.make_jaxpr(fn, return_shape=True)(*args)
    jaxpr = closed.jaxpr
    invars = [_Var(v.aval) for v in list(jaxpr.constvars) + list(jaxpr.invars)]
    eqns, outvars = _inline(jaxpr, invars)
    flat = list(closed.consts) + jax.tree.leaves(args)
    values = _evaluate(_live(eqns, outvars), invars, outvars, flat)
    return jax.tree.unflatten(jax.tree.structure(shapes), values)
  return run

