"""The smoke plan end to end (`sljax experiment run table2 OUT --scale smoke`, 1 seed), once
per convolution implementation, each in a fresh process with an empty compile cache (cold, as a
new user meets it) and then again on the cache it left (warm).

Smoke's programs run for seconds, so compiling is most of its time: this measures what the
scale's `conv_impl` costs there. The issue's target: under 3 minutes cold on a 2-core CPU.

Run: JAX_PLATFORMS=cpu python benchmarks/bench_smoke.py [--impls lax fast] [--plan table2]
"""

import argparse
import dataclasses
import json
import sys
import tempfile
import time

from common import machine, record, run_child  # first: puts this checkout's sljax on the path


def child(plan_name: str, impl: str, out: str) -> None:
  """Runs the smoke plan with the scale's conv_impl replaced; prints one JSON line."""
  from sljax.experiment.design import plans
  from sljax.experiment.running import runner
  from sljax.runtime.compile_cache import enable_compile_cache
  enable_compile_cache()  # as `sljax experiment run` does: $SLJAX_COMPILE_CACHE is the folder
  plans.SCALES["smoke"] = dataclasses.replace(plans.SCALES["smoke"], conv_impl=impl)
  t0 = time.perf_counter()
  res = runner.run(plans.build_plan(plan_name, "smoke", 1), out, progress=False)
  print(json.dumps({"seconds": time.perf_counter() - t0, "trained": res["trained"]}))


def main() -> None:
  """Prints a table of cold and warm wall times per implementation and their ratios."""
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--impls", nargs="+", default=["lax", "fast"], choices=("lax", "fast"))
  p.add_argument("--plan", default="table2")
  p.add_argument("--child", nargs=3, metavar=("PLAN", "IMPL", "OUT"), help=argparse.SUPPRESS)
  a = p.parse_args()
  if a.child:
    return child(*a.child)
  import os
  print(machine())
  rows = []
  for impl in a.impls:
    with tempfile.TemporaryDirectory() as tmp:
      os.environ["SLJAX_COMPILE_CACHE"] = os.path.join(tmp, "cache")
      times = {}
      for kind in ("cold", "warm"):
        t0 = time.perf_counter()
        res, rss = run_child(__file__, ["--child", a.plan, impl, os.path.join(tmp, kind)])
        times[kind] = (res["seconds"], time.perf_counter() - t0, rss, res["trained"])
      rows.append({"impl": impl, **{f"{k}_plan_s": v[0] for k, v in times.items()},
                   **{f"{k}_process_s": v[1] for k, v in times.items()},
                   "peak_rss_mib": max(v[2] for v in times.values()),
                   "cells": times["cold"][3]})
  base = rows[0]["cold_process_s"]
  print(f"\n{a.plan} at the smoke scale, 1 seed (seconds; process = with Python and imports)")
  print(f"{'impl':6} {'cold plan':>10} {'cold proc':>10} {'warm plan':>10} {'warm proc':>10} "
        f"{'cells':>6} {'cold / ' + rows[0]['impl']:>12}")
  for r in rows:
    r["cold_ratio_to_first"] = r["cold_process_s"] / base
    print(f"{r['impl']:6} {r['cold_plan_s']:10.1f} {r['cold_process_s']:10.1f} "
          f"{r['warm_plan_s']:10.1f} {r['warm_process_s']:10.1f} {r['cells']:6d} "
          f"{r['cold_ratio_to_first']:12.2f}")
  record("bench_smoke", rows, plan=a.plan)


if __name__ == "__main__":
  sys.exit(main())
