"""Throughput of sljax.corr.sl_disparity beside a naive loop and the memory-bandwidth floor.

Usage: python benchmarks/bench_corr.py [--quick] [--repeats N]

Each size runs in its own subprocess, so its peak resident memory (ru_maxrss via os.wait4) is
measured alone. Prints one table: pixels/s of the jit correlation, of the naive NumPy loop (on a
crop, literal loops over pixels and shifts), and of the bandwidth floor (bytes the formulation
moves per pixel per shift / measured memcpy bandwidth), with the ratios.
"""

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

# (H, W, t, u): the paper's virtual set and a SCARED-sized frame.
SIZES = [(256, 256, 8, 64), (1024, 1280, 9, 320)]
WINDOW = 17


def bytes_per_pixel_shift(t: int, window: int = WINDOW) -> dict[str, float]:
  """Bytes per pixel per shift: 'fused' (each stage streams once), 'ops' (op by op)."""
  f = 4
  product = (2 * t + 1) * f  # read t left + t shifted right values, write the product map
  levels = int(np.log2(window))  # doubling levels per axis, each reads and writes a map
  extra = bin(window).count("1") - 1  # adds combining the levels
  box_axis = 2 * f + levels * 2 * f + extra * 3 * f  # pad copy, levels, final combination
  argmax = 3 * f  # maps read by max and argmax, running state update amortised
  return {"fused": product + 3 * f, "ops": product + 2 * box_axis + argmax}


def memcpy_bandwidth(nbytes: int = 256 * 2**20, repeats: int = 5) -> float:
  """Bytes/s moved by a large numpy copy (read + write counted)."""
  src = np.ones(nbytes // 4, np.float32)
  dst = np.empty_like(src)
  best = float("inf")
  for _ in range(repeats):
    t0 = time.perf_counter()
    np.copyto(dst, src)
    best = min(best, time.perf_counter() - t0)
  return 2 * nbytes / best


def naive_pixels_per_s(t: int, u: int, crop: int = 6, window: int = WINDOW) -> float:
  """Literal loop of the formula (per pixel, per shift, numpy window sum) on a crop x crop patch."""
  rng = np.random.default_rng(0)
  h = w = crop + u + window
  pl = rng.random((h, w, t))
  pr = rng.random((h, w, t))
  r = window // 2
  y0, x0 = r, u + r  # a crop whose windows and shifts stay inside the image
  t0 = time.perf_counter()
  disp = np.zeros((crop, crop), np.int32)
  for y in range(y0, y0 + crop):
    for x in range(x0, x0 + crop):
      left = pl[y - r:y + r + 1, x - r:x + r + 1]
      best, arg = -np.inf, 0
      for s in range(u + 1):
        c = float(np.sum(left * pr[y - r:y + r + 1, x - s - r:x - s + r + 1]))
        if c > best:
          best, arg = c, s
      disp[y - y0, x - x0] = arg
  return crop * crop / (time.perf_counter() - t0)


def child(h: int, w: int, t: int, u: int, repeats: int, block: int | None) -> None:
  """Times the jit correlation for one size; prints a JSON line."""
  os.environ.setdefault("JAX_PLATFORMS", "cpu")
  sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
  from sljax.corr import correlation

  rng = np.random.default_rng(0)
  pl = rng.random((h, w, t), dtype=np.float32)
  pr = rng.random((h, w, t), dtype=np.float32)
  t0 = time.perf_counter()
  correlation.sl_disparity(pl, pr, u, WINDOW, block=block)
  first = time.perf_counter() - t0
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    correlation.sl_disparity(pl, pr, u, WINDOW, block=block)
    times.append(time.perf_counter() - t0)
  used = block or correlation.choose_block(1, h, w, u, WINDOW)
  print(json.dumps({"seconds": float(np.median(times)), "compile_and_run": first, "block": used}))


def run_child(h, w, t, u, repeats, block=None) -> dict:
  """Runs child() in a fresh process; adds its peak RSS in MiB."""
  cmd = [sys.executable, os.path.abspath(__file__), "--child", f"{h},{w},{t},{u}",
         "--repeats", str(repeats)]
  if block:
    cmd += ["--block", str(block)]
  proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
  out = proc.stdout.read()
  _, status, usage = os.wait4(proc.pid, 0)
  proc.returncode = os.waitstatus_to_exitcode(status)
  if proc.returncode != 0:
    raise SystemExit(f"benchmark child for {h}x{w} failed with exit code {proc.returncode}")
  res = json.loads(out.strip().splitlines()[-1])
  res["peak_rss_mib"] = usage.ru_maxrss / 1024  # Linux reports KiB
  return res


def main() -> None:
  """Prints the table."""
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--quick", action="store_true", help="only the 256x256 size")
  parser.add_argument("--repeats", type=int, default=3)
  parser.add_argument("--blocks", default="", help="comma list: also time these block sizes at 256")
  parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
  parser.add_argument("--block", type=int, default=None, help=argparse.SUPPRESS)
  args = parser.parse_args()
  if args.child:
    child(*[int(v) for v in args.child.split(",")], args.repeats, args.block)
    return

  bandwidth = memcpy_bandwidth()
  print(f"memcpy bandwidth (numpy, read + write): {bandwidth / 1e9:.2f} GB/s; "
        f"CPU cores: {os.cpu_count()}")
  header = (f"{'size':>10} {'t':>2} {'u':>4} {'block':>5} {'jit px/s':>10} {'naive px/s':>10} "
            f"{'floor px/s (fused/ops)':>23} {'jit/naive':>9} {'jit/floor':>15} {'peak MiB':>8} "
            f"{'compile+run s':>13}")
  print(header)
  sizes = SIZES[:1] if args.quick else SIZES
  rows = [(s, None) for s in sizes]
  rows += [(SIZES[0], int(b)) for b in args.blocks.split(",") if b]
  for (h, w, t, u), block in rows:
    res = run_child(h, w, t, u, args.repeats, block)
    jit = h * w / res["seconds"]
    naive = naive_pixels_per_s(t, u)
    bpp = bytes_per_pixel_shift(t)
    floor_fused = bandwidth / (bpp["fused"] * (u + 1))
    floor_ops = bandwidth / (bpp["ops"] * (u + 1))
    print(f"{w:>4}x{h:<5} {t:>2} {u:>4} {res['block']:>5} {jit:>10.3g} {naive:>10.3g} "
          f"{floor_fused:>11.3g}/{floor_ops:<11.3g} {jit / naive:>9.0f} "
          f"{jit / floor_fused:>7.2f}/{jit / floor_ops:<7.2f} {res['peak_rss_mib']:>8.0f} "
          f"{res['compile_and_run']:>13.2f}")
  print("bytes per pixel per shift (t=8 / t=9): fused "
        f"{bytes_per_pixel_shift(8)['fused']}/{bytes_per_pixel_shift(9)['fused']}, op by op "
        f"{bytes_per_pixel_shift(8)['ops']}/{bytes_per_pixel_shift(9)['ops']}")


if __name__ == "__main__":
  main()
