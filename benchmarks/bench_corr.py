"""Speed of sljax.corr.sl_disparity (row path) beside the shift-major path it replaced.

Usage: python benchmarks/bench_corr.py [--quick] [--repeats N]

For each size one subprocess times both formulations side by side (interleaved, minimum over
repeats, wall and process CPU seconds) on random pattern probabilities and checks on random 0/1
patterns that they agree exactly; two more subprocesses run each formulation once alone so that
their peak resident memory (ru_maxrss via os.wait4) is measured separately. A naive NumPy loop
of the formula on a small crop gives the baseline in pixels per second.

Rows: "rows" is `sl_disparity` (plain cc: per-row matrix products + separable box filter on the
host CPU), "shifts" is the shift-major JAX formulation that `sl_disparity` used before
(`correlation._shift_major`, still used for normalised cc).
"""

import argparse
import json
import os
import time

import numpy as np

from common import machine, record, run_child

# (H, W, t, u): the paper's virtual set and a SCARED-sized frame.
SIZES = [(256, 256, 8, 64), (1024, 1280, 9, 320)]
WINDOW = 17


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


def _implementations():
  os.environ.setdefault("JAX_PLATFORMS", "cpu")
  from sljax.corr import correlation

  def rows(pl, pr, u):
    return correlation.sl_disparity(pl, pr, u, WINDOW)

  def shifts(pl, pr, u):
    d, p = correlation._shift_major(pl[None], pr[None], u, WINDOW)
    return d[0], p[0]
  return {"rows": rows, "shifts": shifts}


def child_time(h: int, w: int, t: int, u: int, repeats: int) -> None:
  """Times both formulations interleaved; checks exact agreement on 0/1 patterns; JSON line."""
  impls = _implementations()
  rng = np.random.default_rng(0)
  pl = rng.random((h, w, t), dtype=np.float32)
  pr = rng.random((h, w, t), dtype=np.float32)
  res = {name: {"seconds": float("inf"), "cpu_seconds": float("inf")} for name in impls}
  for name, f in impls.items():  # first calls compile (shifts) and warm the caches
    t0 = time.perf_counter()
    f(pl, pr, u)
    res[name]["first_call"] = time.perf_counter() - t0
  for _ in range(repeats):
    for name, f in impls.items():
      c0, t0 = time.process_time(), time.perf_counter()
      f(pl, pr, u)
      r = res[name]
      r["seconds"] = min(r["seconds"], time.perf_counter() - t0)
      r["cpu_seconds"] = min(r["cpu_seconds"], time.process_time() - c0)
  bl = (rng.random((h, w, t)) < 0.5).astype(np.float32)
  br = (rng.random((h, w, t)) < 0.5).astype(np.float32)
  (d1, p1), (d2, p2) = (f(bl, br, u) for f in impls.values())
  res["identical_on_binary"] = bool(np.array_equal(d1, d2) and np.array_equal(p1, p2))
  print(json.dumps(res))


def child_memory(h: int, w: int, t: int, u: int, name: str) -> None:
  """One call of one formulation (the parent reads this process's peak RSS)."""
  rng = np.random.default_rng(0)
  pl = rng.random((h, w, t), dtype=np.float32)
  pr = rng.random((h, w, t), dtype=np.float32)
  _implementations()[name](pl, pr, u)
  print(json.dumps({"ok": True}))


def main() -> None:
  """Prints the table."""
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--quick", action="store_true", help="only the 256x256 size")
  parser.add_argument("--repeats", type=int, default=3)
  parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
  parser.add_argument("--memory", default=None, help=argparse.SUPPRESS)
  args = parser.parse_args()
  if args.child:
    size = [int(v) for v in args.child.split(",")]
    if args.memory:
      child_memory(*size, args.memory)
    else:
      child_time(*size, args.repeats)
    return

  print(f"{machine()}\ntimes are minimums over {args.repeats} interleaved repeats")
  print(f"{'size':>10} {'t':>2} {'u':>4} {'rows s':>7} {'(cpu s)':>7} {'shifts s':>8} "
        f"{'(cpu s)':>7} {'shifts/rows':>11} {'rows px/s':>9} {'naive px/s':>10} "
        f"{'rows/naive':>10} {'peak MiB rows/shifts':>20} {'identical':>9}")
  records = []
  for h, w, t, u in (SIZES[:1] if args.quick else SIZES):
    size = f"{h},{w},{t},{u}"
    res, _ = run_child(__file__, ["--child", size, "--repeats", str(args.repeats)])
    mem = {name: run_child(__file__, ["--child", size, "--memory", name])[1] for name in ("rows", "shifts")}
    rows, shifts = res["rows"], res["shifts"]
    naive = naive_pixels_per_s(t, u)
    px = h * w / rows["seconds"]
    print(f"{w:>4}x{h:<5} {t:>2} {u:>4} {rows['seconds']:>7.3f} {rows['cpu_seconds']:>7.3f} "
          f"{shifts['seconds']:>8.3f} {shifts['cpu_seconds']:>7.3f} "
          f"{shifts['seconds'] / rows['seconds']:>11.1f} {px:>9.3g} {naive:>10.3g} "
          f"{px / naive:>10.0f} {mem['rows']:>9.0f}/{mem['shifts']:<10.0f} "
          f"{'yes' if res['identical_on_binary'] else 'NO':>9}")
    records.append({"height": h, "width": w, "t": t, "u": u, "rows_s": rows["seconds"],
                    "rows_cpu_s": rows["cpu_seconds"], "shifts_s": shifts["seconds"],
                    "shifts_cpu_s": shifts["cpu_seconds"], "naive_px_per_s": naive,
                    "rows_peak_mib": mem["rows"], "shifts_peak_mib": mem["shifts"],
                    "identical_on_binary": res["identical_on_binary"]})
  record("bench_corr", records)


if __name__ == "__main__":
  main()
