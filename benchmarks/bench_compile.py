"""Where the first training step's time goes: tracing, lowering, XLA's passes, the compile
cache, and which part of the network costs each (issue 42).

Part `run` times the main job (`python train.py --strategy epr`, its preset) as a user runs
it, each run a fresh process: first from an empty SLJAX_CACHE_DIR (cold: a fresh machine's
empty tuner and compile caches), then again from the cache that run filled (warm). Beside
train.py's own figure it gives the seconds from the process's launch to the end of the first
step (what a newcomer waits) and whether the step was loaded whole (sljax.runtime.kept_programs). The
figure is train.py's own "first step (...) N s" (from the first step call to its end); beside
it, from `jax.monitoring`'s
events during that call, the seconds spent tracing (jaxpr), lowering (StableHLO), in XLA's
compile (its passes and code generation) and loading from the persistent cache, and the rest
(the first batch, the step itself, dispatch). Programs compiled before the first step (the
initialisation) are listed apart.

Part `parts` compiles the pieces of the network alone (forward and backward of a sum of the
outputs, training mode), in one process with the compile cache off, and gives for each the
jaxpr equations, StableHLO operations and the seconds of each phase: which part costs what.

    python benchmarks/bench_compile.py                       # both parts, the quick preset
    python benchmarks/bench_compile.py --part run --runs 2   # cold, warm, cold, warm
    python benchmarks/bench_compile.py --train-args "--strategy epr --preset paper"  # a GPU

Timings on a shared machine are noisy: compare rows of one run, and name the CPU and load.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
  sys.path.insert(0, ROOT)

EVENTS = {"/jax/core/compile/jaxpr_trace_duration": "trace",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
          "/jax/core/compile/backend_compile_duration": "compile",
          "/jax/compilation_cache/cache_retrieval_time_sec": "cache_load"}
FIRST_STEP = re.compile(r"first step \([^)]*\) (\d+(?:\.\d+)?) s")


# ----------------------------------------------------------------------------- child: a run


def child_run(train_args: list[str]) -> None:
  """Runs train.py's main with monitoring listeners; prints one JSON line of the events."""
  import jax
  from jax import monitoring

  records = []
  t_start = time.perf_counter()

  def on_duration(event, duration, **kw):
    if event in EVENTS:
      records.append({"event": EVENTS[event], "s": duration, "fun": kw.get("fun_name", ""),
                      "end": time.perf_counter() - t_start})

  def on_event(event, **kw):
    if event.startswith("/jax/compilation_cache/cache_"):
      records.append({"event": event.rsplit("/", 1)[1], "s": 0.0, "fun": "",
                      "end": time.perf_counter() - t_start})

  monitoring.register_event_duration_secs_listener(on_duration)
  monitoring.register_event_listener(on_event)
  from sljax.runtime.compile_cache import load_last_programs
  load_last_programs(train_args)  # as train.py does, before the heavy imports
  from sljax.train import loop
  marks = {}
  original = loop.compiled_steps

  def timed_steps(*a, **kw):
    steps = original(*a, **kw)
    model, tx, train_step, eval_step = steps

    def first_timed(*args, **kwargs):
      t0 = time.perf_counter()
      out = jax.block_until_ready(train_step(*args, **kwargs))
      if "first_start" not in marks:
        marks["first_start"], marks["first_end"] = t0 - t_start, time.perf_counter() - t_start
        marks["first_end_epoch"] = time.time()
        marks["origin"] = getattr(train_step, "origin", None) or "jit"
      else:  # the later steps, each waited for: the step time a compile choice costs
        marks.setdefault("later", []).append(time.perf_counter() - t0)
      return out
    if hasattr(train_step, "ahead"):  # what the loop asks of a kept program
      first_timed.ahead, first_timed.prefetching = train_step.ahead, train_step.prefetching
    return model, tx, first_timed, eval_step

  loop.compiled_steps = timed_steps  # the bench's own hook: the loop calls the module's name
  from sljax.train import cli
  code = cli.main(train_args)
  from benchmarks.common import device_of_process
  print(json.dumps({"code": code, "records": records, **marks, "where": device_of_process(),
                    "total": time.perf_counter() - t_start}), flush=True)
  raise SystemExit(code)


def run_once(train_args: list[str], cache_dir: Path, workdir: Path, env_extra: dict) -> dict:
  """One train.py process (this file's child mode); its events and train.py's first-step line."""
  env = dict(os.environ, SLJAX_CACHE_DIR=str(cache_dir), PYTHONPATH=ROOT, **env_extra)
  env.pop("JAX_COMPILATION_CACHE_DIR", None)
  env.pop("SLJAX_COMPILE_CACHE", None)
  args = train_args + ["--workdir", str(workdir), "--overwrite"]
  launched = time.time()
  t0 = time.perf_counter()
  proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--child-run", "--",
                         *args], capture_output=True, text=True, env=env, cwd=ROOT)
  wall = time.perf_counter() - t0
  if proc.returncode != 0:
    sys.stderr.write(proc.stderr[-4000:])
    raise SystemExit(f"bench_compile: train.py {' '.join(args)} failed ({proc.returncode})")
  data = json.loads(proc.stdout.strip().splitlines()[-1])
  found = FIRST_STEP.findall(proc.stderr.replace("\r", "\n"))
  data["first_step_line"] = float(found[0]) if found else None
  data["wall"] = wall
  data["launch_to_first_end"] = data["first_end_epoch"] - launched
  return data


def program_name(fun: str) -> str:
  """A jitted function's name as the trace, lowering and compile events all give it."""
  return fun[4:-1] if fun.startswith("jit(") and fun.endswith(")") else fun


def phases(data: dict) -> dict:
  """Seconds of each phase inside the first step call, and the programs compiled before it."""
  start, end = data["first_start"], data["first_end"]
  inside = collections.Counter()
  before = collections.Counter()
  before_by_program = collections.Counter()
  hits = misses = 0
  for r in data["records"]:
    began = r["end"] - r["s"]
    if r["event"] == "cache_hits" and start <= r["end"] <= end:
      hits += 1
    elif r["event"] == "cache_misses" and start <= r["end"] <= end:
      misses += 1
    elif start <= began and r["end"] <= end + 1e-3:
      inside[r["event"]] += r["s"]
    elif r["end"] <= start:
      before[r["event"]] += r["s"]
      if r["event"] in ("trace", "lower", "compile"):
        before_by_program[program_name(r["fun"])] += r["s"]
  first = end - start
  xla = inside["compile"] - inside["cache_load"]
  other = first - inside["trace"] - inside["lower"] - inside["compile"]
  return {"first": first, "line": data["first_step_line"], "trace": inside["trace"],
          "lower": inside["lower"], "xla": xla, "cache_load": inside["cache_load"],
          "other": other, "hits": hits, "misses": misses,
          "before": before["trace"] + before["lower"] + before["compile"],
          "to_first_end": data["launch_to_first_end"], "wall": data["wall"],
          "origin": data.get("origin", "-"),
          "before_top": [[f, round(s, 2)] for f, s in before_by_program.most_common(4)],
          "later_step": min(data["later"]) if data.get("later") else None}


def part_run(args) -> list[dict]:
  """Cold and warm runs of the main job (args.runs pairs), one row each."""
  train_args = shlex.split(args.train_args) + ["--stop-after", str(1 + args.later_steps)]
  env_extra = {"SLJAX_TUNE": "0"} if args.tune_off else {}
  rows = []
  with tempfile.TemporaryDirectory(prefix="bench_compile_") as tmp:
    for i in range(args.runs):
      cache_dir = Path(tmp) / f"cache{i}"
      for kind in ("cold", "warm"):
        # One workdir for both: the warm run is the same command line again, as a user's is.
        data = run_once(train_args, cache_dir, Path(tmp) / f"run{i}", env_extra)
        rows.append(dict(kind=kind, **phases(data)))
        args.where = data["where"]
        print(format_run_row(rows[-1]), flush=True)
  for r in rows:  # which programs the start compiles before the step
    print(f"programs before the first step ({r['kind']}): "
          + (", ".join(f"{f} {s:.1f} s" for f, s in r["before_top"]) or "none"), flush=True)
  return rows


RUN_HEADER = ("| run | first step (train.py) s | first step call s | trace s | lower s | "
              "XLA compile s | cache load s | other s | cache hits / misses | step program | "
              "programs before it s | launch to first step end s | later step s (best) |\n"
              "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: "
              "| ---: |")


def format_run_row(r: dict) -> str:
  """One markdown row of a run."""
  line = "-" if r["line"] is None else f"{r['line']:.0f}"
  return (f"| {r['kind']} | {line} | {r['first']:.1f} | {r['trace']:.1f} | {r['lower']:.1f} | "
          f"{r['xla']:.1f} | {r['cache_load']:.2f} | {r['other']:.1f} | {r['hits']} / "
          f"{r['misses']} | {r.get('origin', '-')} | {r['before']:.1f} | {r['to_first_end']:.1f} | "
          f"{'-' if r['later_step'] is None else format(r['later_step'], '.2f')} |")


# ----------------------------------------------------------------------------- child: parts


def part_pieces(args) -> list[dict]:
  """Trace, lower and compile each piece of the network alone (cache off): one row each."""
  import flax.linen as nn
  import jax
  import jax.numpy as jnp

  from sljax.kernels.impl import conv_impl
  from sljax.nets.psmnet import (FeatureExtraction, cost_volume, disparity_outputs,
                                 stacked_hourglass)
  from sljax.nets.psmnet_mtl import SLPath

  jax.config.update("jax_enable_compilation_cache", False)
  impl = conv_impl(args.conv_impl)
  b, (h, w), d = args.batch, args.size, args.maxdisp

  class DisparityPath(nn.Module):
    @nn.compact
    def __call__(self, cost, train):
      outs = stacked_hourglass(cost, train, impl)
      return disparity_outputs(outs, train, d, h, w, False, impl)

  img = jnp.zeros((b, h, w, 3), jnp.float32)
  feat = jnp.zeros((b, h // 4, w // 4, 32), jnp.float32)
  cost = jnp.zeros((b, d // 4, h // 4, w // 4, 64), jnp.float32)
  pieces = [("feature extraction (both views in one batch, as the training step runs it)",
             FeatureExtraction(False, impl, views=2), (jnp.concatenate([img, img]),)),
            ("cost volume (gather)", None, (feat, feat)),
            ("disparity path: dres0-4 + classifiers + regression", DisparityPath(), (cost,)),
            ("SL path: second stacked hourglass + head", SLPath(8, False, impl), (cost, h, w))]
  rows = []
  for name, module, inputs in pieces:
    if module is None:
      def loss(params, *x):
        return jnp.sum(cost_volume(*x, d // 4) ** 2)
      params = {}
      static = ()
    else:
      variables = module.init(jax.random.PRNGKey(0), *inputs, train=False)
      params, stats = variables["params"], variables.get("batch_stats", {})
      static = inputs[1:] if isinstance(module, SLPath) else ()
      arrays = inputs[:1] if isinstance(module, SLPath) else inputs

      def loss(params, *x, module=module, stats=stats, static=static):
        out, _ = module.apply({"params": params, "batch_stats": stats}, *x, *static,
                              train=True, mutable=["batch_stats"])
        return sum(jnp.sum(jnp.square(leaf)) for leaf in jax.tree.leaves(out))
      inputs = arrays
    fn = jax.jit(jax.value_and_grad(loss))
    t0 = time.perf_counter()
    traced = fn.trace(params, *inputs)
    t1 = time.perf_counter()
    lowered = traced.lower()
    t2 = time.perf_counter()
    lowered.compile()
    t3 = time.perf_counter()
    eqns = count_eqns(traced.jaxpr.jaxpr)
    ops = sum(1 for line in lowered.as_text().splitlines() if " = " in line)
    rows.append({"piece": name, "eqns": eqns, "ops": ops, "trace": t1 - t0, "lower": t2 - t1,
                 "xla": t3 - t2})
    print(format_piece_row(rows[-1]), flush=True)
  return rows


def count_eqns(jaxpr) -> int:
  """Equations of a jaxpr and of every jaxpr inside it (loops, custom VJPs, calls)."""
  n = 0
  for eqn in jaxpr.eqns:
    n += 1
    for v in eqn.params.values():
      for sub in (v if isinstance(v, (list, tuple)) else (v,)):
        inner = getattr(sub, "jaxpr", None)
        if inner is not None and hasattr(inner, "eqns"):
          n += count_eqns(inner)
        elif hasattr(sub, "eqns"):
          n += count_eqns(sub)
  return n


PIECE_HEADER = ("| piece (forward + backward, training mode) | jaxpr eqns | StableHLO ops | "
                "trace s | lower s | XLA compile s |\n| --- | ---: | ---: | ---: | ---: | ---: |")


def format_piece_row(r: dict) -> str:
  """One markdown row of a piece."""
  return (f"| {r['piece']} | {r['eqns']} | {r['ops']} | {r['trace']:.1f} | {r['lower']:.1f} | "
          f"{r['xla']:.1f} |")


# ----------------------------------------------------------------------------- main


def main() -> None:
  """Parses the options, runs the parts, prints the tables and records them."""
  if "--child-run" in sys.argv:
    from sljax.runtime.hugepages import reexec  # pylint: disable=import-outside-toplevel
    reexec()  # as train.py starts (sljax/runtime/hugepages.py)
    child_run(sys.argv[sys.argv.index("--") + 1:])
    return
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--part", choices=("all", "run", "parts"), default="all")
  p.add_argument("--train-args", default="--strategy epr",
                 help="train.py's arguments for part run (default: the main job)")
  p.add_argument("--runs", type=int, default=1, help="cold/warm pairs of part run")
  p.add_argument("--later-steps", type=int, default=3,
                 help="part run: steps after the first, timed one by one (the best is shown)")
  p.add_argument("--tune-off", action="store_true",
                 help="SLJAX_TUNE=0 (XLA's defaults) instead of the CPU kind's choice")
  p.add_argument("--size", type=int, nargs=2, default=(64, 64), help="part parts: H W")
  p.add_argument("--maxdisp", type=int, default=32, help="part parts")
  p.add_argument("--batch", type=int, default=8, help="part parts")
  p.add_argument("--conv-impl", default=None, help="part parts (default: auto)")
  p.add_argument("--no-record", action="store_true", help="do not append to benchmarks/results")
  args = p.parse_args()
  from benchmarks.common import cpu_description
  # No jax backend in this process before the runs: on a GPU it would hold the children's memory.
  print(cpu_description())
  args.where = None
  print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} (1, 5 min)", flush=True)
  result = {}
  if args.part in ("all", "run"):
    print(f"\nFirst step of `python train.py {args.train_args}` "
          f"{'(SLJAX_TUNE=0) ' if args.tune_off else ''}from an empty SLJAX_CACHE_DIR (cold) and "
          "from the one it filled (warm):")
    print(RUN_HEADER, flush=True)
    result["run"] = part_run(args)
  if args.part in ("all", "parts"):
    print(f"\nThe network's pieces compiled alone ({args.size[0]}x{args.size[1]}, maxdisp "
          f"{args.maxdisp}, batch {args.batch}; compile cache off):")
    print(PIECE_HEADER, flush=True)
    result["parts"] = part_pieces(args)
  if args.where:
    print(f"\nruns on: {args.where['machine']}")
  if not args.no_record:
    from benchmarks.common import record
    rows = ([dict(table="run", **r) for r in result.get("run", [])]
            + [dict(table="parts", **r) for r in result.get("parts", [])])
    record("bench_compile", rows, where=args.where, train_args=args.train_args)


if __name__ == "__main__":
  main()
