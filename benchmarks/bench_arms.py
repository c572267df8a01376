"""The cost of a training step and of a validation per arm, at a plan's scale (issue 43).

docs/plan-v4.md sizes its test grid by the seconds its cells need: the pilot measured stl's
step (s) and an 80-scene validation (v) with a throwaway run; the grid's twins (unc, epr)
count at their measured ratio to stl. This benchmark measures that ratio: for each arm it runs
`sljax.train.loop.train` on the v4 pilot's first from-scratch cell's configuration (1/32 at
the cpu scale) with the arm's strategy swapped in (unc and epr train the twin), a few steps with
two validations on every validation scene, and reports the steady steps (the first epoch, which compiles, and the epochs
holding a validation are left out) and the second validation (the first compiles). Each arm
runs in its own process, one after the other, so the compile caches and threads of one never
help or slow another.

    python benchmarks/bench_arms.py                    # stl, unc, epr at the cpu scale
    python benchmarks/bench_arms.py --steps 30 --arms stl,unc

Name the CPU and load beside the figures; pause anything else running while it times.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
  sys.path.insert(0, ROOT)


def child(arm: str, scale: str, steps: int, workdir: str) -> None:
  """Times one arm; prints one JSON line."""
  from sljax.experiment.design import plans
  from sljax.train import loop

  plan = plans.build_plan(plans.V4_PILOT, scale, 1)
  cell = plan.cells_of(setting="scratch")[0]
  config = dataclasses.replace(cell.config, strategy=arm, steps=steps,
                               val_every_steps=steps // 2)
  val_times: list[float] = []
  validate = loop.validate_split

  def timed(*a, **k):
    t = time.perf_counter()
    out = validate(*a, **k)
    val_times.append(time.perf_counter() - t)
    return out

  loop.validate_split = timed
  loop.train(config, Path(workdir), overwrite=True, log=lambda *_: None, progress=False)
  rows = [json.loads(l) for l in (Path(workdir) / "epochs.jsonl").read_text().splitlines()]
  per_epoch = -(-config.steps // max(1, len(rows)))  # steps per full epoch
  first_val = (steps // 2) // per_epoch + 1          # the epoch holding the first validation
  steady = [r for r in rows if 2 <= r["epoch"] < first_val]
  if not steady:
    raise SystemExit(f"bench_arms: --steps {steps} leaves no epoch between the first (compiling) "
                     "and the first validation's; give more steps")
  sec = sum(r["seconds"] for r in steady) / (per_epoch * len(steady))
  print(json.dumps({"arm": arm, "sec_per_step": sec, "steady_steps": per_epoch * len(steady),
                    "validation_s": val_times[-1], "validations": len(val_times),
                    "first_epoch_s": rows[0]["seconds"]}))


def main() -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--arms", default="stl,unc,epr")
  p.add_argument("--scale", default="cpu")
  p.add_argument("--steps", type=int, default=30, help="steps per arm (validation at half)")
  p.add_argument("--child", help=argparse.SUPPRESS)
  p.add_argument("--workdir", help=argparse.SUPPRESS)
  a = p.parse_args()
  if a.child:
    child(a.child, a.scale, a.steps, a.workdir)
    return
  from benchmarks.common import machine, run_child
  print(f"# bench_arms: {a.scale} scale, the v4 pilot's first from-scratch cell per arm, "
        f"{a.steps} steps; "
        f"{machine()}; load {os.getloadavg()[0]:.2f}")
  results = []
  for arm in a.arms.split(","):
    with tempfile.TemporaryDirectory() as tmp:
      row, rss = run_child(__file__, ["--child", arm, "--scale", a.scale, "--steps",
                                      str(a.steps), "--workdir", tmp])
    results.append(dict(row, rss_mib=rss))
  base = results[0]
  print(f"\n| arm | s/step | steady steps | validation s | step ratio to {base['arm']} | "
        f"validation ratio |\n| --- | ---: | ---: | ---: | ---: | ---: |")
  for r in results:
    print(f"| {r['arm']} | {r['sec_per_step']:.3f} | {r['steady_steps']} | "
          f"{r['validation_s']:.2f} | {r['sec_per_step'] / base['sec_per_step']:.2f} | "
          f"{r['validation_s'] / base['validation_s']:.2f} |")
  print("\n" + json.dumps(results))


if __name__ == "__main__":
  main()
