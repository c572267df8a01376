"""Training state (params, batch_stats, opt_state, step) and its creation; LoopState, the
loop's bookkeeping saved beside it in each checkpoint."""

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct
from jax.flatten_util import ravel_pytree

from sljax.losses.weighting import UNCERTAINTY_KEY, init_uncertainty


class TrainState(struct.PyTreeNode):
  """Everything a step updates; a plain pytree so it can be donated, sharded and checkpointed."""
  step: jax.Array
  params: Any
  batch_stats: Any
  opt_state: Any


LR_DROP = 0.1  # the step decay's factor (the PSMNet reference's fine-tuning: 1e-3 -> 1e-4)


def make_optimizer(lr: float, drop_step: int | None = None) -> optax.GradientTransformation:
  """Adam (betas 0.9/0.999) with a fixed learning rate (paper: 1e-4), or one that drops to
  LR_DROP * lr from step drop_step on (a function of the step count in the optimiser state,
  so a resumed run follows it exactly)."""
  if drop_step is not None:
    lr = optax.piecewise_constant_schedule(lr, {int(drop_step): LR_DROP})
  return flat_update(optax.adam(lr, b1=0.9, b2=0.999))


def flat_update(tx: optax.GradientTransformation) -> optax.GradientTransformation:
  """tx with its update computed on one flat vector of all parameters; same state tree.

  An elementwise optimiser (Adam) applied leaf by leaf puts a dozen operations per parameter
  leaf into the training step: with PSMNet-MTL's hundreds of leaves 15% of the program that is
  traced, lowered and compiled before the first step, and as many small kernels at run time
  (issue 42). On the concatenated leaves it is a few operations, element for element the same
  arithmetic, so the values are equal. The state keeps tx's own tree (checkpoints unchanged):
  every parameter-shaped subtree of it is raveled for the update and unraveled after. Leaves
  of mixed dtypes (which raveling would cast) take tx's own leaf-by-leaf update.
  """

  def update(grads, state, params=None):
    leaves = jax.tree.leaves(grads)
    if params is None or len({x.dtype for x in leaves}) != 1:
      return tx.update(grads, state, params)
    treedef = jax.tree.structure(grads)
    flat_g, unravel = ravel_pytree(grads)

    def param_shaped(x):
      return jax.tree.structure(x) == treedef

    flat_state = jax.tree.map(lambda x: ravel_pytree(x)[0] if param_shaped(x) else x, state,
                              is_leaf=param_shaped)
    flat_updates, new_flat = tx.update(flat_g, flat_state, ravel_pytree(params)[0])
    new_state = jax.tree.map(lambda old, new: unravel(new) if param_shaped(old) else new, state,
                             new_flat, is_leaf=param_shaped)
    return unravel(flat_updates), new_state

  return optax.GradientTransformation(tx.init, update)


def net_params(params: dict[str, Any]) -> dict[str, Any]:
  """The network's parameters without the strategy's own (uncertainty log sigmas)."""
  return {k: v for k, v in params.items() if k != UNCERTAINTY_KEY}


def create_state(variables: dict[str, Any], tx: optax.GradientTransformation) -> TrainState:
  """Fresh state. The unc strategy's log sigmas always join the parameter tree (Adam leaves
  them at their initial value under the other strategies, whose gradient for them is 0)."""
  params = dict(variables["params"])
  params[UNCERTAINTY_KEY] = init_uncertainty()
  return TrainState(step=jnp.zeros((), jnp.int32), params=params,
                    batch_stats=dict(variables.get("batch_stats", {})), opt_state=tx.init(params))


@dataclasses.dataclass(frozen=True)
class LoopState:
  """The loop's bookkeeping beside the TrainState; each checkpoint's metadata.

  history: epoch-mean training (L_sl, L_disp) of the finished epochs (DWA reads it);
  partial: (sum L_sl, sum L_disp, steps) of the current epoch so far;
  since_val: the same sums since the last validation (--val-every-steps: each validation row's
  training loss, so that memorisation can be read beside the validation curve).
  """
  step: int = 0
  history: tuple[tuple[float, float], ...] = ()
  partial: tuple[float, float, int] = (0.0, 0.0, 0)
  best_val: float | None = None
  last_val: float | None = None
  since_val: tuple[float, float, int] = (0.0, 0.0, 0)

  def add_step(self, loss_sl: float, loss_disp: float) -> "LoopState":
    """After one step with these (unweighted) training losses."""
    s_sl, s_disp, n = self.partial
    v_sl, v_disp, m = self.since_val
    return dataclasses.replace(self, step=self.step + 1,
                               partial=(s_sl + loss_sl, s_disp + loss_disp, n + 1),
                               since_val=(v_sl + loss_sl, v_disp + loss_disp, m + 1))

  def interval_means(self) -> tuple[float, float]:
    """Mean training (L_sl, L_disp) over the steps since the last validation."""
    v_sl, v_disp, m = self.since_val
    return (v_sl / m, v_disp / m) if m else (math.nan, math.nan)

  def close_epoch(self) -> "LoopState":
    """The epoch's mean losses join the history; the partial sums restart."""
    s_sl, s_disp, n = self.partial
    return dataclasses.replace(self, history=self.history + ((s_sl / n, s_disp / n),),
                               partial=(0.0, 0.0, 0))

  def validated(self, val_mae: float | None) -> "LoopState":
    """After a validation that measured val_mae (None: nothing measured)."""
    best = self.best_val
    if val_mae is not None and (best is None or val_mae < best):
      best = val_mae
    return dataclasses.replace(self, last_val=val_mae, best_val=best, since_val=(0.0, 0.0, 0))

  def to_meta(self) -> dict[str, Any]:
    """JSON metadata saved with a checkpoint."""
    return {"step": self.step, "history": [list(e) for e in self.history],
            "partial": list(self.partial), "best_val": self.best_val, "last_val": self.last_val,
            "since_val": list(self.since_val)}

  @classmethod
  def from_meta(cls, meta: dict[str, Any]) -> "LoopState":
    """The LoopState saved by to_meta (runs saved before last_val or since_val existed: None,
    and empty sums)."""
    s_sl, s_disp, n = meta["partial"]
    v_sl, v_disp, m = meta.get("since_val", (0.0, 0.0, 0))
    return cls(step=int(meta["step"]),
               history=tuple((float(a), float(b)) for a, b in meta["history"]),
               partial=(float(s_sl), float(s_disp), int(n)), best_val=meta.get("best_val"),
               last_val=meta.get("last_val"), since_val=(float(v_sl), float(v_disp), int(m)))
