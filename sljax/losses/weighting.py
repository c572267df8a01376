"""Loss weighting strategies for the PSMNet twin (SPEC 4, paper eq. 5-8), as pure functions.

Task order everywhere is (sl, disp).
- stl:  plain PSMNet, disparity only: weights (0, 1).
- cg_a: 10 * L_sl + L_disp;  cg_b: 0.5 * L_sl + L_disp.
- epr:  Dynamic Weight Averaging, lambda_k = zeta1 * exp(zeta2 * w_k) / sum_i exp(zeta2 * w_i),
        w_k = L_k(e-1) / L_k(e-2) from epoch-mean training losses; weights 1 for the first two
        epochs; constant within an epoch (the loop computes them, the step takes them as input).
- unc:  lambda5 / (2 sigma_sl^2) * L_sl + 1 / (2 sigma_disp^2) * L_disp + log sigma_sl
        + log sigma_disp with lambda5 = 0.5 and learnable log sigmas, stored in the parameter tree
        as params['uncertainty'] = {'log_sigma_sl', 'log_sigma_disp'}, initialised to 0
        (sigma = 1, so the initial effective weights are 0.25 and 0.5).
"""

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np



@dataclasses.dataclass(frozen=True)
class Strategy:
  """One loss weighting: how its weights are set (see the module docstring)."""
  name: str
  weights: str                 # "constant" (sl_gain, 1), "dwa" or "uncertainty"
  sl_gain: float = 0.0         # the constant weight of L_sl ("constant" only)

  @property
  def multi_task(self) -> bool:
    """True when the twin's SL path trains too (every strategy but stl)."""
    return self.weights != "constant" or self.sl_gain > 0

  @property
  def learns_sigmas(self) -> bool:
    """True when the strategy has learnable log sigmas in the parameters (unc)."""
    return self.weights == "uncertainty"


# The one table of strategies; the order is the paper's.
TABLE = {s.name: s for s in (
    Strategy("stl", "constant"), Strategy("cg_a", "constant", 10.0),
    Strategy("cg_b", "constant", 0.5), Strategy("epr", "dwa"), Strategy("unc", "uncertainty"))}
STRATEGIES = tuple(TABLE)
SINGLE_TASK = "stl"  # plain PSMNet: the baseline every multi-task strategy is compared with
MULTI_TASK = tuple(name for name, s in TABLE.items() if s.multi_task)
DWA_ZETA1 = 2.0
DWA_ZETA2 = 2.0
UNC_SL_GAIN = 0.5
UNC_LOG_SIGMA_INIT = 0.0
UNCERTAINTY_KEY = "uncertainty"


def constant_weights(strategy: str) -> np.ndarray:
  """(w_sl, w_disp) of the fixed strategies stl, cg_a and cg_b."""
  s = TABLE.get(strategy)
  if s is None or s.weights != "constant":
    raise ValueError(f"strategy {strategy!r} has no constant weights")
  return np.array([s.sl_gain, 1.0], np.float32)


def dwa_weights(history: Sequence[Sequence[float]], zeta1: float = DWA_ZETA1,
                zeta2: float = DWA_ZETA2) -> np.ndarray:
  """DWA weights for the next epoch from the epoch-mean losses [(L_sl, L_disp), ...] so far."""
  if len(history) < 2:
    return np.ones(2, np.float32)
  prev = np.asarray(history[-1], np.float64)
  prev2 = np.asarray(history[-2], np.float64)
  w = prev / prev2
  e = np.exp(zeta2 * (w - w.max()))  # shift for overflow safety; softmax is shift-invariant
  return (zeta1 * e / e.sum()).astype(np.float32)


def epoch_weights(strategy: str, history: Sequence[Sequence[float]]) -> np.ndarray:
  """Task weights (w_sl, w_disp) fed to the step for the coming epoch of any strategy.

  For unc they are multipliers (1, 1) on top of the learned uncertainty weighting.
  """
  kind = TABLE[strategy].weights
  if kind == "dwa":
    return dwa_weights(history)
  if kind == "uncertainty":
    return np.ones(2, np.float32)
  return constant_weights(strategy)


def init_uncertainty(value: float = UNC_LOG_SIGMA_INIT) -> dict[str, jax.Array]:
  """Initial learnable log sigmas for the unc strategy."""
  return {"log_sigma_sl": jnp.asarray(value, jnp.float32),
          "log_sigma_disp": jnp.asarray(value, jnp.float32)}


def weighted_loss(l_sl: jax.Array, l_disp: jax.Array,
                  weights: jax.Array) -> tuple[jax.Array, jax.Array]:
  """(total, effective weights) of a fixed/DWA weighting: w_sl * L_sl + w_disp * L_disp."""
  return weights[0] * l_sl + weights[1] * l_disp, jnp.asarray(weights)


def uncertainty_factors(log_sigma_sl: jax.Array, log_sigma_disp: jax.Array,
                        sl_gain: float = UNC_SL_GAIN) -> tuple[jax.Array, jax.Array]:
  """Kendall's task factors (sl_gain / (2 sigma_sl^2), 1 / (2 sigma_disp^2)): written once."""
  return sl_gain * 0.5 * jnp.exp(-2.0 * log_sigma_sl), 0.5 * jnp.exp(-2.0 * log_sigma_disp)


def uncertainty_loss(l_sl: jax.Array, l_disp: jax.Array, log_sigma_sl: jax.Array,
                     log_sigma_disp: jax.Array,
                     sl_gain: float = UNC_SL_GAIN) -> tuple[jax.Array, jax.Array]:
  """(total, effective weights) of Kendall's uncertainty weighting with learnable log sigmas."""
  w_sl, w_disp = uncertainty_factors(log_sigma_sl, log_sigma_disp, sl_gain)
  total = w_sl * l_sl + w_disp * l_disp + log_sigma_sl + log_sigma_disp
  return total, jnp.stack([w_sl, w_disp])


def step_weights(strategy: str, history: Sequence[Sequence[float]]) -> np.ndarray:
  """The step's strategy input [w_sl, w_disp, unc]: one compiled step serves every strategy."""
  unc = 1.0 if TABLE[strategy].learns_sigmas else 0.0
  return np.array([*epoch_weights(strategy, history), unc], np.float32)


def combined_loss(l_sl: jax.Array, l_disp: jax.Array, weights: jax.Array,
                  log_sigma_sl: jax.Array, log_sigma_disp: jax.Array) -> tuple[jax.Array, jax.Array]:
  """(total, effective task weights) for a step_weights vector [w_sl, w_disp, unc].

  unc = 0: w_sl * L_sl + w_disp * L_disp, and the log sigmas get exactly zero gradient (Adam
  then leaves them unchanged). unc = 1: uncertainty_loss of (w_sl * L_sl, w_disp * L_disp).
  """
  unc = weights[2] > 0.5
  f_sl, f_disp = uncertainty_factors(log_sigma_sl, log_sigma_disp)
  u_sl, u_disp = jnp.where(unc, f_sl, 1.0), jnp.where(unc, f_disp, 1.0)
  eff = jnp.stack([weights[0] * u_sl, weights[1] * u_disp])
  total = eff[0] * l_sl + eff[1] * l_disp + jnp.where(unc, log_sigma_sl + log_sigma_disp, 0.0)
  return total, eff
