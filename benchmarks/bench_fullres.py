"""Peak memory and time of full-resolution (pad-mode) inference, on the CPU or a GPU.

Usage: python benchmarks/bench_fullres.py [--size 1024x1280[,1080x1920,...]] [--maxdisp 192]
       [--models psmnet,psmnet-mtl] [--repeats 1] [--reference DIR]

Each model runs in its own subprocess (randomly initialised weights: memory and time do not
depend on their values) through `sljax.inference.Predictor` in pad mode on one RGB pair, batch
1, on jax's default device. Prints one row per model and size: the first call (tracing +
compilation + run), the best later call, and the peak memory: on the CPU the child's peak
resident memory (ru_maxrss via os.wait4), on a GPU the device's peak bytes in use (the
allocator's, not the host's RSS). With --reference DIR (a local checkout of JiaRenChang/PSMNet,
never shipped or fetched) the reference PSMNet's forward (PyTorch, eval mode, no grad, on CUDA
when there is one, its peak `max_memory_allocated`) runs on the same pair in a subprocess of its
own, and psmnet's row gets its ratios. Both sides pad to a multiple of 16 as the reference's
Test_img.py does (at the top and the right: sljax's pad mode, and here the reference's input
with zeros after normalisation), then crop. A child that fails (out of memory) gives a row
saying so, and the sizes after it still run: the largest size that fits is in the table.
"""

import argparse
import json
import os
import time

import numpy as np

from common import cpu_description, record, run_child


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


def padded_16(h: int, w: int) -> tuple[int, int]:
  """(top pad, right pad) to the next multiples of 16, as the reference's Test_img.py."""
  return -h % 16, -w % 16


def reference_child(directory: str, h: int, w: int, maxdisp: int, repeats: int) -> None:
  """The reference PSMNet's forward on the same pair, padded to a multiple of 16 at the top
  and right with zeros after normalisation (Test_img.py) and cropped; one JSON line."""
  import torch

  from bench_nets import reference_psmnet
  cuda = torch.cuda.is_available()
  model = reference_psmnet(directory, maxdisp, keep_cuda=cuda).eval()
  dev = torch.device("cuda" if cuda else "cpu")
  model = model.to(dev)
  rng = np.random.default_rng(0)
  mean, std = np.array([0.485, 0.456, 0.406]), np.array([0.229, 0.224, 0.225])
  top, right_pad = padded_16(h, w)
  pairs = ((rng.integers(0, 256, (h, w, 3)) / 255.0 - mean) / std for _ in range(2))
  left, right = (torch.tensor(np.pad(a.transpose(2, 0, 1), ((0, 0), (top, 0), (0, right_pad)))
                              [None].astype(np.float32)).to(dev) for a in pairs)
  times = []
  with torch.no_grad():
    for _ in range(repeats + 1):
      t0 = time.perf_counter()
      out = model(left, right)
      out = out[..., top:, :w] if right_pad else out[..., top:, :]
      if cuda:
        torch.cuda.synchronize()
      times.append(time.perf_counter() - t0)
  assert tuple(out.shape[-2:]) == (h, w)
  peak = torch.cuda.max_memory_allocated() / 2**30 if cuda else None
  print(json.dumps({"first_call_s": times[0], "later_call_s": min(times[1:]),
                    "outputs": ["disparity"], "peak_device_gib": peak,
                    "device": torch.cuda.get_device_name() if cuda else "cpu"}))


def child(name: str, h: int, w: int, maxdisp: int, repeats: int) -> None:
  """One model, pad mode, one pair, jax's default device; prints a JSON line with the timings
  and, off the CPU, the device's peak memory."""
  import jax

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
  dev = jax.devices()[0]
  stats = dev.memory_stats() if jax.default_backend() != "cpu" else None
  peak = stats["peak_bytes_in_use"] / 2**30 if stats and "peak_bytes_in_use" in stats else None
  from common import device_of_process
  print(json.dumps({"first_call_s": first, "later_call_s": best, "outputs": sorted(out),
                    "peak_device_gib": peak, "where": device_of_process()}))


def main() -> None:
  """Prints the table."""
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--size", default="1024x1280",
                      help="HEIGHTxWIDTH, or several separated by commas")
  parser.add_argument("--maxdisp", type=int, default=192)
  parser.add_argument("--models", default="psmnet,psmnet-mtl")
  parser.add_argument("--repeats", type=int, default=1, help="later calls timed after the first")
  parser.add_argument("--reference", metavar="DIR", default=None,
                      help="local checkout of JiaRenChang/PSMNet: its forward beside psmnet's")
  parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
  args = parser.parse_args()
  if args.child:
    h, w = (int(v) for v in args.size.lower().split("x"))
    if args.child == "reference":
      reference_child(args.reference, h, w, args.maxdisp, args.repeats)
    else:
      child(args.child, h, w, args.maxdisp, args.repeats)
    return
  # No jax backend in this process: on a GPU it would hold memory the children need.
  print(cpu_description())
  print(f"pad mode, batch 1, maxdisp {args.maxdisp}; peak memory: the device's (GPU) or the "
        "process's RSS (CPU)")
  print(f"{'model':>11} {'size HxW':>10} {'first call s':>12} {'later call s':>12} "
        f"{'peak GiB':>9}  memory of")
  records, where = [], None
  names = args.models.split(",") + (["reference"] if args.reference else [])
  for size in args.size.split(","):
    h, w = (int(v) for v in size.lower().split("x"))
    rows = {}
    for name in names:
      extra = ["--reference", args.reference] if name == "reference" else []
      res, rss = run_child(__file__, ["--child", name, "--size", size, "--maxdisp",
                                      str(args.maxdisp), "--repeats", str(args.repeats)] + extra,
                           check=False)
      if res is None:
        print(f"{name:>11} {size:>10} failed (out of memory?)", flush=True)
        records.append({"model": name, "height": h, "width": w, "maxdisp": args.maxdisp,
                        "failed": True})
        continue
      where = res.get("where", where)
      gpu = res.get("peak_device_gib")
      peak, what = (gpu, "device") if gpu is not None else (rss / 1024, "RSS")
      print(f"{name:>11} {size:>10} {res['first_call_s']:>12.2f} {res['later_call_s']:>12.3f} "
            f"{peak:>9.2f}  {what}", flush=True)
      rows[name] = {"model": name, "height": h, "width": w, "maxdisp": args.maxdisp,
                    "first_call_s": res["first_call_s"], "later_call_s": res["later_call_s"],
                    "peak_rss_gib": rss / 1024, "peak_device_gib": gpu}
    ref = rows.pop("reference", None)
    if ref and "psmnet" in rows:
      r = rows["psmnet"]
      r.update(reference_s=ref["later_call_s"], reference_peak_rss_gib=ref["peak_rss_gib"],
               reference_peak_device_gib=ref["peak_device_gib"])
      mem = ("peak_device_gib" if r["peak_device_gib"] is not None
             and ref["peak_device_gib"] is not None else "peak_rss_gib")
      print(f"psmnet / reference at {size}: {r['later_call_s'] / ref['later_call_s']:.2f}x time, "
            f"{r[mem] / ref[mem]:.2f}x peak memory ({mem})",
            flush=True)
    records += list(rows.values())
  if where:
    print(f"sljax ran on: {where['machine']}")
  record("bench_fullres", records, where=where)


if __name__ == "__main__":
  main()
