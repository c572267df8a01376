"""Training state (params, batch_stats, opt_state, step) and its creation; LoopState, the
loop's bookkeeping saved beside it in each checkpoint."""

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

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
  so a resumed run follows it exactly).

  optax's own update, leaf by leaf. Issue 42 ran it on the raveled parameters (fewer operations
  to trace), but unraveling a flat vector into the twin's 339 leaves is 339 slices that XLA:CPU
  compiles one by one: the update and its application compiled in 8.6 s against 1.5 s leaf
  by leaf and ran in 51 ms against 9 ms, and the training step compiled 6-7 s faster with
  steps as fast (Zen 5, 2026-11-28; docs/benchmarks/first-run.md).
  """
  if drop_step is not None:
    lr = optax.piecewise_constant_schedule(lr, {int(drop_step): LR_DROP})
  return optax.adam(lr, b1=0.9, b2=0.999)


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
