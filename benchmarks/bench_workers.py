"""A smoke grid run by 1 and by 2 `sljax experiment run` workers on one OUT, side by side in
one run, and what a claim costs a cell (sljax.experiment.running.workers).

Each worker is its own process, as on a cluster; the grid's wall time runs from starting the
workers to the last one's exit. A warm-up grid fills the compile cache first, so both timings
read it (a cluster's workers share the cache folder too). The claim overhead: claiming a
free cell and releasing it (creating two claim files and a heartbeat, reading the top),
averaged over many cells in a folder beside OUT.

On a 2-core CPU two workers share the cores that one worker's XLA already uses, so about 1x is
the expected answer there: the gain comes with one device per worker.

Run: JAX_PLATFORMS=cpu python benchmarks/bench_workers.py [--plan table1] [--claims 500]
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import ROOT, machine, record  # first: puts this checkout's sljax on the path


def grid(plan: str, out: Path, workers: int) -> tuple[float, float]:
  """(wall seconds, CPU seconds of all of them) for `workers` worker processes to finish the
  smoke grid under out."""
  cmd = [sys.executable, "-m", "sljax.cli", "experiment", "run", plan, str(out), "--scale",
         "smoke", "--no-progress", "--lease", "6"]  # an idle worker looks every second
  env = dict(os.environ, PYTHONPATH=ROOT)
  t0 = time.perf_counter()
  procs = [subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL) for _ in range(workers)]
  codes, cpu = [], 0.0
  for proc in procs:
    _, status, usage = os.wait4(proc.pid, 0)
    codes.append(os.waitstatus_to_exitcode(status))
    cpu += usage.ru_utime + usage.ru_stime
  seconds = time.perf_counter() - t0
  if any(codes):
    raise SystemExit(f"a worker failed: exit codes {codes}")
  return seconds, cpu


def claim_cost(folder: Path, cells: int) -> float:
  """Mean seconds to claim a free cell and release it."""
  from sljax.experiment.running import workers
  with workers.Worker(folder, workers.identity(300.0)) as worker:
    t0 = time.perf_counter()
    for k in range(cells):
      assert worker.claim(f"cell-{k}")
      worker.release("finished")
    return (time.perf_counter() - t0) / cells


def main() -> None:
  """Prints the grid's wall time with 1 and 2 workers, their ratio, and the claim cost."""
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--plan", default="table1")
  p.add_argument("--claims", type=int, default=500, help="cells claimed for the overhead")
  a = p.parse_args()
  print(machine())
  print(f"load average before: {os.getloadavg()[0]:.2f} (1 min)")
  with tempfile.TemporaryDirectory() as tmp:
    tmp = Path(tmp)
    os.environ.setdefault("SLJAX_COMPILE_CACHE", str(tmp / "cache"))
    grid(a.plan, tmp / "warm-up", 1)
    seconds = {n: grid(a.plan, tmp / f"workers-{n}", n) for n in (1, 2)}
    per_claim = claim_cost(tmp / "claims", a.claims)
  load = os.getloadavg()[0]
  print(f"\n{a.plan} at the smoke scale, 1 seed, warm compile cache (seconds)")
  print(f"{'workers':>8} {'grid wall':>10} {'CPU, all':>9} {'1 worker / this':>16}")
  rows = []
  for n, (wall, cpu) in seconds.items():
    rows.append({"workers": n, "grid_s": wall, "cpu_s": cpu, "speedup": seconds[1][0] / wall})
    print(f"{n:8d} {wall:10.1f} {cpu:9.1f} {seconds[1][0] / wall:16.2f}")
  print(f"claim + release of a cell: {per_claim * 1e3:.2f} ms (mean of {a.claims})")
  print(f"load average after: {load:.2f} (1 min)")
  record("bench_workers", rows, plan=a.plan, claim_release_ms=per_claim * 1e3,
         claims=a.claims, loadavg_after=load)


if __name__ == "__main__":
  sys.exit(main())
