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
from jax.flatten_util import ravel_pytree
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from sljax.kernels import grad_blocks
from sljax.losses.disparity import disparity_loss, masked_mae
from sljax.losses.sl import sl_loss
from sljax.losses.weighting import UNCERTAINTY_KEY, combined_loss
from sljax.nets.model_config import COMPUTE_DTYPES, ModelConfig
from sljax.train.state import TrainState, net_params

__all__ = ["COMPUTE_DTYPES", "apply_model", "make_eval_step", "make_mesh", "make_train_step",
           "process_rows", "put_batch", "shardings", "task_losses"]


def make_mesh(devices: list[jax.Device] | None = None) -> Mesh:
  """1-D device mesh named 'data' over all (global) devices."""
  devices = jax.devices() if devices is None else devices
  return Mesh(np.asarray(devices), ("data",))


def shardings(mesh: Mesh) -> tuple[NamedSharding, NamedSharding]:
  """(replicated, batch-sharded along axis 0)."""
  return NamedSharding(mesh, P()), NamedSharding(mesh, P("data"))


def task_losses(outputs: dict[str, jax.Array], batch: dict[str, jax.Array], config: ModelConfig,
                disp_kind: str) -> tuple[jax.Array, jax.Array]:
  """(L_sl, L_disp) in float32 of a forward pass; a task the network lacks gives 0."""
  parts = config.spec.parts
  outputs = jax.tree.map(lambda x: x.astype(jnp.float32), outputs)
  zero = jnp.zeros((), jnp.float32)
  l_sl, l_disp = zero, zero
  if "sl" in parts:
    logits, targets = outputs["sl_logits"], batch["sl"]
    if "sl_right" in parts:
      # P_hat = [P_l; P_r] (paper 3.2): one loss over both views.
      logits = jnp.concatenate([logits, outputs["sl_logits_right"]], axis=-1)
      targets = jnp.concatenate([targets, batch["sl_right"]], axis=-1)
    l_sl = sl_loss(logits, targets)
  if "disp" in parts:
    preds = outputs.get("disparities") or (outputs["disparity"],)
    l_disp = disparity_loss(preds, batch["disp"], config.maxdisp, disp_kind)
  return l_sl, l_disp


def apply_model(model: nn.Module, params: dict[str, Any], batch_stats: dict[str, Any],
                batch: dict[str, jax.Array], train: bool, dtype: Any = jnp.float32):
  """model.apply on the batch's views computing in `dtype`: the parameters and images are cast
  (their float32 masters are what the optimiser updates); BatchNorm statistics stay float32."""
  def cast(x):
    return x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x
  variables = {"params": jax.tree.map(cast, net_params(params))}
  if batch_stats:
    variables["batch_stats"] = batch_stats
  left, right = cast(batch["left"]), cast(batch["right"])
  if train:
    return model.apply(variables, left, right, train=True, mutable=["batch_stats"])
  return model.apply(variables, left, right, train=False)


def make_train_step(model: nn.Module, config: ModelConfig, *, disp_loss: str,
                    tx: optax.GradientTransformation, mesh: Mesh,
                    compiler_options: dict[str, Any] | None = None,
                    grad_block_values: int | None = None
                    ) -> Callable[..., tuple[TrainState, dict[str, jax.Array]]]:
  """jit(step)(state, batch, weights) -> (new state, metrics); the state is donated.

  model: the module `config` describes (config.build(), or a stand-in with its outputs);
  config gives the tasks, disparity range and computation dtype. weights =
  weighting.step_weights(strategy, history). Metrics: loss (total), loss_sl, loss_disp,
  w_sl / w_disp (effective weights), sigma_sl / sigma_disp, grad_norm and the training batch's
  MAE for disparity networks. grad_block_values: the CPU kernels' gradient blocks
  (sljax.kernels.grad_blocks; sljax.runtime.choices.grad_blocks_for gives the one for the compiler
  options), None: those of a gradient traced without a context (context_free_blocks).
  """
  dtype, maxdisp = config.dtype, config.maxdisp

  def loss_fn(params, batch_stats, batch, weights):
    outputs, updates = apply_model(model, params, batch_stats, batch, True, dtype)
    l_sl, l_disp = task_losses(outputs, batch, config, disp_loss)
    u = params[UNCERTAINTY_KEY]
    total, eff = combined_loss(l_sl, l_disp, weights, u["log_sigma_sl"], u["log_sigma_disp"])
    aux = {"loss_sl": l_sl, "loss_disp": l_disp, "sigma_sl": jnp.exp(u["log_sigma_sl"]),
           "sigma_disp": jnp.exp(u["log_sigma_disp"])}
    aux["w_sl"], aux["w_disp"] = eff[0], eff[1]
    if "disparity" in outputs and "disp" in batch:
      s, n = masked_mae(outputs["disparity"].astype(jnp.float32), batch["disp"], maxdisp)
      aux["mae"] = s / jnp.maximum(n, 1.0)
    return total, (aux, updates.get("batch_stats", {}))

  def step(state: TrainState, batch: dict[str, jax.Array], weights: jax.Array):
    grad_fn = jax.value_and_grad(loss_fn, has_aux=True)
    with grad_blocks(grad_block_values):  # while traced: the gradients' kernels are traced here
      (total, (aux, new_stats)), grads = grad_fn(state.params, state.batch_stats, batch, weights)
    updates, opt_state = tx.update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    metrics = dict(aux, loss=total, grad_norm=flat_norm(grads))
    return TrainState(step=state.step + 1, params=params, batch_stats=new_stats,
                      opt_state=opt_state), metrics

  repl, data = shardings(mesh)
  return jax.jit(step, in_shardings=(repl, data, repl), out_shardings=(repl, repl),
                 donate_argnums=(0,), compiler_options=compiler_options)


def flat_norm(tree: Any) -> jax.Array:
  """The global L2 norm of a pytree's leaves (optax.tree.norm up to the order of summation)."""
  leaves = jax.tree.leaves(tree)
  if len({x.dtype for x in leaves}) != 1:
    return optax.tree.norm(tree)
  flat = ravel_pytree(tree)[0]
  return jnp.sqrt(jnp.sum(jnp.square(flat)))


def make_eval_step(model: nn.Module, config: ModelConfig, *, mesh: Mesh,
                   compiler_options: dict[str, Any] | None = None
                   ) -> Callable[..., dict[str, jax.Array]]:
  """jit(eval)(params, batch_stats, batch) -> the network's evaluation-mode outputs (float32):
  'disparity' (disparity networks), 'sl_logits' (+ 'sl_logits_right') (SL networks)."""
  keys, dtype = config.spec.outputs, config.dtype

  def evaluate(params, batch_stats, batch):
    outputs = apply_model(model, params, batch_stats, batch, False, dtype)
    return {k: outputs[k].astype(jnp.float32) for k in keys}

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
