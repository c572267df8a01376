"""The program `sljax tune` times: PSMNet at a small size, forward and training.

It lives beside the networks it builds, so that the compiler choices (sljax.runtime.choices,
on the ground floor) never import a network: the command passes it in.
"""

import jax
import jax.numpy as jnp
import numpy as np

from sljax.nets.model_config import build_model, init_variables


def workload(size: int = 128, maxdisp: int = 48, seed: int = 0):
  """PSMNet at a small size, as (forward, training) functions of (variables, left, right, gt)
  and their arguments: the real mix of 2D and 3D convolutions the choice is for."""
  model = build_model("psmnet", maxdisp=maxdisp)
  rng = np.random.default_rng(seed)
  left, right = (jnp.asarray(rng.random((1, size, size, 3), np.float32)) for _ in range(2))
  gt = jnp.asarray(rng.random((1, size, size), np.float32) * maxdisp)
  # The training loop's initialiser: compiled with its options, ~10x faster than XLA's default
  # for PSMNet's threefry initialisers (40 s of a Zen 3's time per tuning otherwise).
  variables = init_variables(model, seed, size, size, 3)

  def forward(variables, left, right, gt):
    return model.apply(variables, left, right, train=False)["disparity"]

  def loss(params, variables, left, right, gt):
    out, _ = model.apply({**variables, "params": params}, left, right, train=True,
                         mutable=["batch_stats"])
    return sum(jnp.mean((d - gt) ** 2) for d in out["disparities"])

  def train(variables, left, right, gt):
    return jax.grad(loss)(variables["params"], variables, left, right, gt)
  return {"forward": forward, "train": train}, (variables, left, right, gt)
