"""Peak memory and time of full-resolution (pad-mode) inference: SCARED-sized frames on the CPU.

Usage: python benchmarks/bench_fullres.py [--size 1024x1280] [--maxdisp 192]
       [--models psmnet,psmnet-mtl] [--repeats 1] [--reference DIR]

Each model runs in its own subprocess (randomly initialised weights: memory and time do not
depend on their values) through `sljax.inference.Predictor` in pad mode on one RGB pair; the
parent reads the child's peak resident memory (ru_maxrss via os.wait4). Prints one row per model:
the first call (tracing + compilation + run), the best later call, and the peak memory.
With --reference DIR (a local checkout of JiaRenChang/PSMNet, never shipped or fetched) the
reference PSMNet's forward (PyTorch, eval mode, no grad) runs on the same pair in a subprocess
of its own in the same run, and psmnet's row gets its ratio: the sizes are multiples of 16, so
the reference needs no padding and both compute the same map.
"""

import argparse
import json
import os
import time

import numpy as np

from common import machine, record, run_child


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


def reference_child(directory: str, h: int, w: int, maxdisp: int, repeats: int) -> None:
  """The reference PSMNet's forward on the same pair; prints a JSON line with the timings."""
  import torch

  from bench_nets import reference_psmnet
  model = reference_psmnet(directory, maxdisp).eval()
  rng = np.random.default_rng(0)
  mean, std = np.array([0.485, 0.456, 0.406]), np.array([0.229, 0.224, 0.225])
  left, right = ((rng.integers(0, 256, (h, w, 3)) / 255.0 - mean) / std for _ in range(2))
  left, right = (torch.tensor(a.transpose(2, 0, 1)[None].astype(np.float32)) for a in (left, right))
  times = []
  with torch.no_grad():
    for _ in range(repeats + 1):
      t0 = time.perf_counter()
      out = model(left, right)
      times.append(time.perf_counter() - t0)
  assert tuple(out.shape[-2:]) == (h, w)
  print(json.dumps({"first_call_s": times[0], "later_call_s": min(times[1:]),
                    "outputs": ["disparity"]}))


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
  parser.add_argument("--reference", metavar="DIR", default=None,
                      help="local checkout of JiaRenChang/PSMNet: its forward beside psmnet's")
  parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
  args = parser.parse_args()
  h, w = (int(v) for v in args.size.lower().split("x"))
  if args.child == "reference":
    reference_child(args.reference, h, w, args.maxdisp, args.repeats)
    return
  if args.child:
    child(args.child, h, w, args.maxdisp, args.repeats)
    return
  print(machine())
  print(f"pad mode, {w}x{h} RGB pair, maxdisp {args.maxdisp}, batch 1")
  print(f"{'model':>11} {'first call s':>12} {'later call s':>12} {'peak RSS GiB':>12}")
  records = []
  names = args.models.split(",") + (["reference"] if args.reference else [])
  for name in names:
    extra = ["--reference", args.reference] if name == "reference" else []
    res, rss = run_child(__file__, ["--child", name, "--size", args.size, "--maxdisp", str(args.maxdisp),
                          "--repeats", str(args.repeats)] + extra)
    print(f"{name:>11} {res['first_call_s']:>12.1f} {res['later_call_s']:>12.1f} {rss / 1024:>12.2f}")
    records.append({"model": name, "height": h, "width": w, "maxdisp": args.maxdisp,
                    "first_call_s": res["first_call_s"], "later_call_s": res["later_call_s"],
                    "peak_rss_gib": rss / 1024})
  if args.reference:
    ref = records.pop()
    for r in records:
      if r["model"] == "psmnet":
        r.update(reference_s=ref["later_call_s"], reference_peak_rss_gib=ref["peak_rss_gib"])
        print(f"psmnet / reference: {r['later_call_s'] / ref['later_call_s']:.2f}x time, "
              f"{r['peak_rss_gib'] / ref['peak_rss_gib']:.2f}x peak memory")
  record("bench_fullres", records)


if __name__ == "__main__":
  main()
