"""Synthetic renderer throughput: scenes/s in memory (with and without raw captures), make-data.

Usage: JAX_PLATFORMS=cpu python benchmarks/bench_synthetic.py [--size 256] [--n 20] [--domain objects]
Prints wall-clock scenes/s and process CPU time per scene (all threads). On a shared machine the
CPU time is the figure to compare: 1000 / (CPU ms per scene) is the rate one otherwise idle core
sustains (the target, 20 scenes/s on a 2-core box, is <= 100 ms of CPU per scene).
"""

import argparse
import os
import tempfile
import time

from common import record  # first: puts this checkout's sljax on the path


def _rate(fn, n: int) -> tuple[float, float]:
  """(wall scenes/s, CPU ms per scene) of n calls fn(i), after one warm-up call (compilation)."""
  fn(0)
  w0, c0 = time.perf_counter(), time.process_time()
  for i in range(1, n + 1):
    fn(i)
  return n / (time.perf_counter() - w0), 1000.0 * (time.process_time() - c0) / n


def main() -> None:
  """Runs the three measurements and prints a table."""
  ap = argparse.ArgumentParser(description=__doc__)
  ap.add_argument("--size", type=int, default=256)
  ap.add_argument("--n", type=int, default=20)
  ap.add_argument("--domain", default="objects")
  args = ap.parse_args()

  from sljax.data.scene import write_scene
  from sljax.render.synthetic import SynthConfig, render_scene

  cfg = SynthConfig(size=args.size, domain=args.domain)
  rows = []
  t0 = time.perf_counter()
  render_scene(0, 0, cfg)
  compile_s = time.perf_counter() - t0
  rows.append(("in memory", *_rate(lambda i: render_scene(i, 0, cfg), args.n)))
  rows.append(("in memory + raw", *_rate(lambda i: render_scene(i, 0, cfg, raw=True), args.n)))
  with tempfile.TemporaryDirectory() as tmp:
    def write(i):
      scene = render_scene(i, 0, cfg, raw=True)
      write_scene(os.path.join(tmp, scene.name), scene, overwrite=True)
    rows.append(("make-data (raw, PNG/PFM)", *_rate(write, max(4, args.n // 4))))
  load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
  print(f"synthetic {args.domain} {args.size}x{args.size}, {os.cpu_count()} CPUs, load {load:.1f}, "
        f"first call (compile) {compile_s:.1f} s")
  print(f"{'path':26s} {'scenes/s (wall)':>16s} {'CPU ms/scene':>13s} {'scenes/s per core':>18s}"
        f" {'vs 20/s':>8s}")
  for name, wall, cpu_ms in rows:
    per_core = 1000.0 / cpu_ms  # what one idle core sustains, whatever the load on the box
    print(f"{name:26s} {wall:16.2f} {cpu_ms:13.1f} {per_core:18.1f} {per_core / 20:8.2f}")
  record("bench_synthetic", [{"path": name, "scenes_per_s_wall": wall, "cpu_ms_per_scene": cpu_ms}
                             for name, wall, cpu_ms in rows],
         domain=args.domain, size=args.size, compile_s=compile_s)


if __name__ == "__main__":
  main()
