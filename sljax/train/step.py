"""The jitted, data-parallel training and evaluation steps for every model and strategy.

The batch is sharded along axis 0 over a 1-D mesh named 'data'; parameters and optimiser state
are replicated, so BatchNorm statistics and gradients are over the global batch (XLA inserts
the all-reduces). The strategy is an input array [w_sl, w_disp, unc] (weighting.step_weights)
and every state carries the unc log sigmas, so one compiled step serves all five strategies and
DWA's per-epoch weights never recompile.
"""

from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from sljax.errors import require
from sljax.losses.disparity import disparity_loss, masked_mae
from sljax.losses.sl import sl_loss
from sljax.losses.weighting import UNCERTAINTY_KEY, combined_loss
from sljax.train.state import TrainState, net_params

# Batch keys each network trains on.
BATCH_PARTS = {
    "psmnet": ("left", "right", "disp"),
    "psmnet-mtl": ("left", "right", "disp", "sl"),
    "unet-sl": ("left", "right", "sl", "sl_right"),
    "unet-disp": ("left", "right", "disp"),
}


def make_mesh(devices: list[jax.Device] | None = None) -> Mesh:
  """1-D device mesh named 'data' over all (global) devices."""
  devices = jax.devices() if devices is None else devices
  return Mesh(np.asarray(devices), ("data",))


def shardings(mesh: Mesh) -> tuple[NamedSharding, NamedSharding]:
  """(replicated, batch-sharded along axis 0)."""
  return NamedSharding(mesh, P()), NamedSharding(mesh, P("data"))


def task_losses(outputs: dict[str, jax.Array], batch: dict[str, jax.Array], net: str,
                maxdisp: float, disp_kind: str) -> tuple[jax.Array, jax.Array]:
  """(L_sl, L_disp) of a forward pass; a task the network lacks gives 0."""
  zero = jnp.zeros((), jnp.float32)
  l_sl, l_disp = zero, zero
  if "sl" in BATCH_PARTS[net]:
    logits, targets = outputs["sl_logits"], batch["sl"]
    if "sl_right" in BATCH_PARTS[net]:
      # P_hat = [P_l; P_r] (paper 3.2): one loss over both views.
      logits = jnp.concatenate([logits, outputs["sl_logits_right"]], axis=-1)
      targets = jnp.concatenate([targets, batch["sl_right"]], axis=-1)
    l_sl = sl_loss(logits, targets)
  if "disp" in BATCH_PARTS[net]:
    preds = outputs.get("disparities") or (outputs["disparity"],)
    l_disp = disparity_loss(preds, batch["disp"], maxdisp, disp_kind)
  return l_sl, l_disp


def make_train_step(model: nn.Module, *, net: str, maxdisp: float, disp_loss: str,
                    tx: optax.GradientTransformation, mesh: Mesh,
                    compiler_options: dict[str, Any] | None = None
                    ) -> Callable[..., tuple[TrainState, dict[str, jax.Array]]]:
  """jit(step)(state, batch, weights) -> (new state, metrics); the state is donated.

  weights = weighting.step_weights(strategy, history). Metrics: loss (total), loss_sl,
  loss_disp, w_sl / w_disp (effective weights), sigma_sl / sigma_disp, grad_norm and the
  training batch's MAE for disparity networks.
  """
  require(net in BATCH_PARTS, f"unknown network {net!r}")

  def loss_fn(params, batch_stats, batch, weights):
    variables = {"params": net_params(params)}
    if batch_stats:
      variables["batch_stats"] = batch_stats
    outputs, updates = model.apply(variables, batch["left"], batch["right"], train=True,
                                   mutable=["batch_stats"])
    l_sl, l_disp = task_losses(outputs, batch, net, maxdisp, disp_loss)
    u = params[UNCERTAINTY_KEY]
    total, eff = combined_loss(l_sl, l_disp, weights, u["log_sigma_sl"], u["log_sigma_disp"])
    aux = {"loss_sl": l_sl, "loss_disp": l_disp, "sigma_sl": jnp.exp(u["log_sigma_sl"]),
           "sigma_disp": jnp.exp(u["log_sigma_disp"])}
    aux["w_sl"], aux["w_disp"] = eff[0], eff[1]
    if "disparity" in outputs and "disp" in batch:
      s, n = masked_mae(outputs["disparity"], batch["disp"], maxdisp)
      aux["mae"] = s / jnp.maximum(n, 1.0)
    return total, (aux, updates.get("batch_stats", {}))

  def step(state: TrainState, batch: dict[str, jax.Array], weights: jax.Array):
    grad_fn = jax.value_and_grad(loss_fn, has_aux=True)
    (total, (aux, new_stats)), grads = grad_fn(state.params, state.batch_stats, batch, weights)
    updates, opt_state = tx.update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    metrics = dict(aux, loss=total, grad_norm=optax.tree.norm(grads))
    return TrainState(step=state.step + 1, params=params, batch_stats=new_stats,
                      opt_state=opt_state), metrics

  repl, data = shardings(mesh)
  return jax.jit(step, in_shardings=(repl, data, repl), out_shardings=(repl, repl),
                 donate_argnums=(0,), compiler_options=compiler_options)


def make_eval_step(model: nn.Module, *, net: str, mesh: Mesh,
                   compiler_options: dict[str, Any] | None = None
                   ) -> Callable[..., dict[str, jax.Array]]:
  """jit(eval)(params, batch_stats, batch) -> the evaluation-mode outputs that metrics need:
  'disparity' (disparity networks), 'sl_logits' (+ 'sl_logits_right') (SL networks)."""
  require(net in BATCH_PARTS, f"unknown network {net!r}")

  def evaluate(params, batch_stats, batch):
    variables = {"params": net_params(params)}
    if batch_stats:
      variables["batch_stats"] = batch_stats
    outputs = model.apply(variables, batch["left"], batch["right"], train=False)
    keys = ("disparity", "sl_logits", "sl_logits_right")
    return {k: outputs[k] for k in keys if k in outputs}

  repl, data = shardings(mesh)
  return jax.jit(evaluate, in_shardings=(repl, repl, data), compiler_options=compiler_options)


def put_batch(batch: dict[str, np.ndarray], mesh: Mesh) -> dict[str, jax.Array]:
  """Global batch arrays sharded over the mesh from this process's rows.

  Single process: the rows are the whole batch. Multi-process: each process passes its own
  contiguous slice of the global batch (see process_rows).
  """
  _, data = shardings(mesh)
  return {k: jax.make_array_from_process_local_data(data, np.ascontiguousarray(v))
          for k, v in batch.items()}


def process_rows(global_batch: int) -> slice:
  """This process's contiguous slice of a global batch (all rows on a single process)."""
  n = jax.process_count()
  per = global_batch // n
  i = jax.process_index()
  return slice(i * per, (i + 1) * per)
