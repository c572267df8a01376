"""Training-step cost per network and size: compile time, seconds per step and per sample, and
the extrapolated time per epoch of the quick and paper presets.

  JAX_PLATFORMS=cpu python benchmarks/bench_train.py --net psmnet-mtl --size 64 --maxdisp 32 --batch 8
  JAX_PLATFORMS=cpu python benchmarks/bench_train.py --preset paper --batch 1 --steps 2
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from sljax.losses.weighting import step_weights
from sljax.nets import build_model
from sljax.train import state as st
from sljax.train import step as stp
from sljax.train.config import PAPER, QUICK


def main() -> None:
  """Times one network's training step and prints a table row plus the epoch extrapolation."""
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--preset", choices=("quick", "paper"), default=None)
  p.add_argument("--net", default="psmnet-mtl",
                 choices=("psmnet", "psmnet-mtl", "unet-sl", "unet-disp"))
  p.add_argument("--size", type=int, default=None)
  p.add_argument("--maxdisp", type=int, default=None)
  p.add_argument("--batch", type=int, default=None)
  p.add_argument("--steps", type=int, default=3)
  p.add_argument("--t", type=int, default=8)
  args = p.parse_args()
  cfg = {"quick": QUICK, "paper": PAPER, None: QUICK}[args.preset]
  size = args.size or cfg.size[0]
  maxdisp = args.maxdisp or cfg.maxdisp
  batch = args.batch or cfg.batch_size
  c = 1 if args.net.startswith("unet") else 3
  kw = {"in_channels": c}
  if args.net.startswith("psmnet"):
    kw["maxdisp"] = maxdisp
  if args.net in ("psmnet-mtl", "unet-sl"):
    kw["t"] = args.t
  if args.net.startswith("unet"):
    kw.update(depth=cfg.unet_depth, base_width=cfg.unet_width)
  model = build_model(args.net, **kw)
  t0 = time.perf_counter()
  variables = st.init_variables(model, 0, size, size, c)
  t_init = time.perf_counter() - t0
  tx = st.make_optimizer(1e-4)
  mesh = stp.make_mesh()
  state = jax.device_put(st.create_state(variables, tx), stp.shardings(mesh)[0])
  step = stp.make_train_step(model, net=args.net, maxdisp=maxdisp, disp_loss="l2", tx=tx,
                             mesh=mesh)
  rng = np.random.default_rng(0)
  host = {"left": rng.random((batch, size, size, c), np.float32),
          "right": rng.random((batch, size, size, c), np.float32),
          "disp": rng.uniform(0, maxdisp, (batch, size, size)).astype(np.float32),
          "sl": (rng.random((batch, size, size, args.t)) > 0.5).astype(np.float32)}
  host["sl_right"] = host["sl"]
  b = stp.put_batch({k: host[k] for k in stp.BATCH_PARTS[args.net]}, mesh)
  w = jnp.asarray(step_weights("unc", []))
  t0 = time.perf_counter()
  state, m = step(state, b, w)
  jax.block_until_ready(m)
  t_first = time.perf_counter() - t0
  t0 = time.perf_counter()
  for _ in range(args.steps):
    state, m = step(state, b, w)
  jax.block_until_ready(m)
  per_step = (time.perf_counter() - t0) / args.steps
  per_sample = per_step / batch
  n_train = int(round(cfg.synth_n * (1 - cfg.test_fraction)))
  print(f"| net | size | maxdisp | batch | init s | compile+1st s | s/step | s/sample |")
  print(f"| {args.net} | {size} | {maxdisp} | {batch} | {t_init:.1f} | {t_first:.1f} | "
        f"{per_step:.3f} | {per_sample:.3f} |")
  print(f"{cfg.preset} preset ({n_train} training scenes of {cfg.synth_n}): ~"
        f"{per_sample * n_train / 60:.1f} min per epoch of training steps on "
        f"{jax.devices()[0].device_kind} (validation and data not included)")


if __name__ == "__main__":
  main()
