"""Peak memory and time of full-resolution (pad-mode) inference: SCARED-sized frames on the CPU.

Usage: python benchmarks/bench_fullres.py [--size 1024x1280] [--maxdisp 192]
       [--models psmnet,psmnet-mtl] [--repeats 1]

Each model runs in its own subprocess (randomly initialised weights: memory and time do not
depend on their values) through `sljax.inference.Predictor` in pad mode on one RGB pair; the
parent reads the child's peak resident memory (ru_maxrss via os.wait4). Prints one row per model:
the first call (tracing + compilation + run), the best later call, and the peak memory.
"""

import argparse
import json
import os
import time

import numpy as np

from common import machine, run_child


def random_variables(name: str, kwargs: dict, seed: int = 0) -> dict:
  """Variables of the right structure, filled with scaled normal values (BN stats positive)."""
  import jax
  import jax.numpy as jnp

  from sljax.nets import build_model
  model = build_model(name, **kwargs)
  x = jax.ShapeDtypeStruct((1, 64, 64, kwargs.get("in_channels", 3)), jnp.float32)
  shapes = jax.eval_shape(lambda a, b: model.init(jax.random.PRNGKey(0), a, b, train=False), x, x)
  rng = np.random.default_rng(seed)

  def fill(path, leaf):
    key = str(path[-1])
    if "var" in key:
      return np.asarray(rng.uniform(0.5, 1.5, leaf.shape), np.float32)
    if "scale" in key:
      return np.asarray(1.0 + 0.1 * rng.normal(size=leaf.shape), np.float32)
    fan_in = max(1, int(np.prod(leaf.shape[:-1])))
    return np.asarray(rng.normal(size=leaf.shape) / np.sqrt(fan_in), np.float32)
  return jax.tree_util.tree_map_with_path(fill, dict(shapes))


def child(name: str, h: int, w: int, maxdisp: int, repeats: int) -> None:
  """One model, pad mode, one pair; prints a JSON line with the timings."""
  os.environ.setdefault("JAX_PLATFORMS", "cpu")
  from sljax import inference

  kwargs = {"maxdisp": maxdisp, "in_channels": 3}
  if name == "psmnet-mtl":
    kwargs["t"] = 9
  pred = inference.make_predictor(name, kwargs, random_variables(name, kwargs), mode="pad")
  rng = np.random.default_rng(0)
  left = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
  right = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
  t0 = time.perf_counter()
  out = pred(left, right)
  first = time.perf_counter() - t0
  best = float("nan")
  for _ in range(repeats):
    t0 = time.perf_counter()
    pred(left, right)
    best = min(best, time.perf_counter() - t0) if best == best else time.perf_counter() - t0
  assert out["disparity"].shape == (h, w) and np.isfinite(out["disparity"]).all()
  print(json.dumps({"first_call_s": first, "later_call_s": best, "outputs": sorted(out)}))


def main() -> None:
  """Prints the table."""
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--size", default="1024x1280", help="HEIGHTxWIDTH")
  parser.add_argument("--maxdisp", type=int, default=192)
  parser.add_argument("--models", default="psmnet,psmnet-mtl")
  parser.add_argument("--repeats", type=int, default=1, help="later calls timed after the first")
  parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
  args = parser.parse_args()
  h, w = (int(v) for v in args.size.lower().split("x"))
  if args.child:
    child(args.child, h, w, args.maxdisp, args.repeats)
    return
  print(machine())
  print(f"pad mode, {w}x{h} RGB pair, maxdisp {args.maxdisp}, batch 1")
  print(f"{'model':>11} {'first call s':>12} {'later call s':>12} {'peak RSS GiB':>12}")
  for name in args.models.split(","):
    res, rss = run_child(__file__, ["--child", name, "--size", args.size, "--maxdisp", str(args.maxdisp),
                          "--repeats", str(args.repeats)])
    print(f"{name:>11} {res['first_call_s']:>12.1f} {res['later_call_s']:>12.1f} {rss / 1024:>12.2f}")


if __name__ == "__main__":
  main()
