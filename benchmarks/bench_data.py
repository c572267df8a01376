"""Scene loading throughput: load_scene and iterate_batches on a temporary dataset (256x256).

Run: JAX_PLATFORMS=cpu python benchmarks/bench_data.py [--scenes 32] [--size 256]
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from common import record  # first: puts this checkout's sljax on the path

from sljax.data.dataset import FolderSource, iterate_batches
from sljax.data.scene import Scene, load_scene, write_scene


def _make(root: Path, n: int, size: int, t: int) -> None:
  """Writes n random scenes of size x size with t patterns per view, four per group."""
  rng = np.random.default_rng(0)
  for k in range(n):
    sl = rng.integers(0, 2, (size, size, t)).astype(np.float32)
    write_scene(root / f"s{k:03d}", Scene(
        name=str(k), im0=rng.uniform(size=(size, size, 3)).astype(np.float32),
        im1=rng.uniform(size=(size, size, 3)).astype(np.float32),
        disp0=rng.uniform(0, 64, (size, size)).astype(np.float32), sl0=sl, sl1=sl,
        meta={"group": f"g{k // 4}"}))


def main() -> None:
  """Prints a table of per-scene and per-batch times."""
  ap = argparse.ArgumentParser()
  ap.add_argument("--scenes", type=int, default=32)
  ap.add_argument("--size", type=int, default=256)
  ap.add_argument("--patterns", type=int, default=8)
  ap.add_argument("--batch", type=int, default=8)
  a = ap.parse_args()
  with tempfile.TemporaryDirectory() as tmp:
    root = Path(tmp)
    _make(root, a.scenes, a.size, a.patterns)
    src = FolderSource(root)
    rows = []
    t0 = time.perf_counter()
    for p in src.paths:
      load_scene(p)
    rows.append(("load_scene (all parts)", (time.perf_counter() - t0) / a.scenes * 1e3, "ms/scene"))
    half = a.size // 2
    for label, kw in [("batches native", {}), (f"batches resize {half}", {"size": half}),
                      (f"batches crop {half}", {"size": half, "mode": "crop"})]:
      t0 = time.perf_counter()
      nb = 0
      for b in iterate_batches(src, range(len(src)), a.batch, seed=0, epoch=0, **kw):
        nb += 1
      dt = time.perf_counter() - t0
      rows.append((f"{label} (B={a.batch})", dt / nb * 1e3, "ms/batch"))
    print(f"{a.scenes} scenes {a.size}x{a.size}, {a.patterns} patterns per view")
    print(f"{'what':34s} {'time':>9s}")
    for name, v, unit in rows:
      print(f"{name:34s} {v:9.1f} {unit}")
    native = rows[1][1]
    print(f"ratio resize/native {rows[2][1] / native:.2f}, crop/native {rows[3][1] / native:.2f}")
    record("bench_data", [{"what": name, "value": v, "unit": unit} for name, v, unit in rows],
           scenes=a.scenes, size=a.size, patterns=a.patterns)


if __name__ == "__main__":
  main()
