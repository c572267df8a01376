"""The programs `sljax tune` times: PSMNet at a small size, forward and training; the 3D
layers' gradients at the runs' shapes.

It lives beside the networks it builds, so that the compiler choices (sljax.runtime.choices,
on the ground floor) never import a network: the command passes it in.
"""

import jax
import jax.numpy as jnp
import numpy as np

from sljax import kernels
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


# The 3D layers whose kernel gradients the block size decides, at the shapes runs use:
# (kind, batch, D, H, W, in channels, out channels, stride). PSMNet at 256x256, maxdisp 96 (its
# 1/4-resolution cost volume, batch 1 of the runs' 2: the blocks' shape is the same) and the main
# job's quick preset (64x64, maxdisp 32, batch 8).
GRADIENT_LAYERS = (
    ("conv", 1, 24, 64, 64, 64, 32, 1), ("conv", 1, 24, 64, 64, 32, 32, 1),
    ("conv", 1, 24, 64, 64, 32, 64, 2), ("conv", 1, 12, 32, 32, 64, 64, 1),
    ("convT", 1, 12, 32, 32, 64, 32, 2),
    ("conv", 8, 8, 16, 16, 32, 32, 1), ("conv", 8, 8, 16, 16, 32, 64, 2),
)


def gradient_workload(layers=GRADIENT_LAYERS, seed: int = 0):
  """The gradients (input and kernel) of `layers`, as a function of their inputs and kernels
  and those arguments: what the kernel gradients' block size (sljax.kernels.grad_blocks)
  changes, at the runs' shapes, compiled in seconds."""
  rng = np.random.default_rng(seed)
  args = tuple((jnp.asarray(rng.standard_normal((n, d, h, w, cin), np.float32)),
                jnp.asarray(rng.standard_normal((3, 3, 3, cin, cout), np.float32) * 0.05))
               for _, n, d, h, w, cin, cout, _ in layers)

  def loss(args):
    total = 0.0
    for (kind, *_, s), (x, k) in zip(layers, args):
      y = (kernels.conv3d(x, k, (s,) * 3, ((1, 1),) * 3) if kind == "conv" else
           kernels.conv_transpose3d(x, k, (s,) * 3, kernels.transpose_padding((3,) * 3, 1, 1)))
      total = total + jnp.sum(y * y)
    return total
  return jax.grad(loss), (args,)
