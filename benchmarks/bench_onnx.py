"""ONNX Runtime (CPU) against sljax (CPU) on PSMNet's forward, and the ONNX export's own time.

PSMNet (random weights: the speed does not depend on them) at HxW (default 256x512, maxdisp
192, pad mode, batch 1), exported with `sljax.deploy.onnx.write_onnx` (conversion and the
ONNX Runtime check, timed apart), then the forward timed in both: sljax's Predictor as
`sljax predict` runs it (the machine's default convolutions: "fast" on a CPU) and ONNX
Runtime's CPUExecutionProvider on the written file (its default graph optimisations and
threads). Times are the best of --repeats calls after one warm-up; the ratio is sljax / ONNX
Runtime (above 1: ONNX Runtime is faster). The machine and its load are printed and recorded
(benchmarks/results/); the machines are shared, so compare the ratio, measured side by side.

  python benchmarks/bench_onnx.py                      # 256x512, maxdisp 192
  python benchmarks/bench_onnx.py --size 64x128 --maxdisp 48 --repeats 2    # a dry run
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from common import best_time, machine, record  # first: puts this checkout's sljax on the path
from sljax import inference
from sljax.deploy import onnx as dx
from sljax.deploy.stablehlo import parse_size


def psmnet_predictor(maxdisp: int):
  """A PSMNet Predictor with random variables of the right structure (pad mode)."""
  import jax
  from sljax.nets import build_model
  kw = {"maxdisp": maxdisp, "in_channels": 3}
  model = build_model("psmnet", **kw)
  x = jax.ShapeDtypeStruct((1, 64, 64, 3), np.float32)
  shapes = jax.eval_shape(lambda a, b: model.init(jax.random.PRNGKey(0), a, b, train=False), x, x)
  rng = np.random.default_rng(0)

  def fill(s):
    return (rng.standard_normal(s.shape) * 0.05).astype(np.float32)
  variables = jax.tree_util.tree_map(fill, shapes)
  variables["batch_stats"] = jax.tree_util.tree_map(
      lambda v: np.abs(v) + 1.0 if v.ndim else v, variables["batch_stats"])
  return inference.make_predictor("psmnet", kw, variables, mode="pad")


def main() -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--size", default="256x512", help="HxW (default 256x512)")
  p.add_argument("--maxdisp", type=int, default=192)
  p.add_argument("--repeats", type=int, default=3)
  args = p.parse_args()
  h, w = parse_size(args.size)
  print(machine())
  print(f"load average before: {os.getloadavg()}")
  pred = psmnet_predictor(args.maxdisp)
  with tempfile.TemporaryDirectory() as tmp:
    out = Path(tmp) / "psmnet.onnx"
    start = time.perf_counter()
    _, _, report = dx.write_onnx(pred, (h, w), out, "bench_onnx", log=print)
    export_s = time.perf_counter() - start
    model = out.read_bytes()
  import onnxruntime as ort
  sess = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
  left, right = dx.check_pair((h, w), 3)
  feeds = {"left": left, "right": right}
  ort_s = best_time(lambda: sess.run(None, feeds), args.repeats)
  sljax_s = best_time(lambda: pred(left, right), args.repeats)
  rows = [
      {"what": "export (convert + check)", "seconds": round(export_s, 2),
       "convert_s": report["convert_seconds"], "max_abs_disparity": report["max_abs_disparity"],
       "onnx_mb": round(len(model) / 2**20, 1)},
      {"what": "forward sljax CPU", "seconds": round(sljax_s, 3)},
      {"what": "forward ONNX Runtime CPU", "seconds": round(ort_s, 3),
       "onnxruntime": ort.__version__},
  ]
  print(f"\nPSMNet {h}x{w}, maxdisp {args.maxdisp}, batch 1, pad mode, best of {args.repeats}")
  print(f"| what | seconds |\n|---|---|")
  for r in rows:
    print(f"| {r['what']} | {r['seconds']} |")
  print(f"convert {report['convert_seconds']} s of the export; ONNX file "
        f"{len(model) / 2**20:.1f} MiB; max |delta disparity| {report['max_abs_disparity']:.2g} px")
  print(f"ratio sljax / ONNX Runtime (forward): {sljax_s / ort_s:.2f}")
  print(f"load average after: {os.getloadavg()}")
  record("onnx", rows, size=f"{h}x{w}", maxdisp=args.maxdisp,
         ratio_sljax_over_ort=round(sljax_s / ort_s, 3))


if __name__ == "__main__":
  main()
