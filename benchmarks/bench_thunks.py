"""How loading a serialised XLA:CPU executable grows with its number of YNNPACK thunks.

A standalone reproduction (jax and numpy only; attachable to an upstream report): a jitted
function of N independent reductions (each a YNNPACK "reduce" fusion thunk, the kind sljax's
`--ynn off` keeps) or N independent 2D convolutions (YNNPACK convolution thunks under XLA's
default options), compiled, serialised with `jax.experimental.serialize_executable` and loaded
back. Prints compile, serialise and load seconds against N, with the fusions on and without any
YNNPACK fusion, the loaded program's first and a later run (YNNPACK's thunks set themselves up
in the first run, about 1 ms each, loaded or freshly compiled alike), and the growth exponent of
the load between the two largest N (1: linear, 2: quadratic). On a 2-core Intel Xeon (jaxlib 0.10.2) the reductions' load grew as N^1.9 and
took longer than their compile from N = 4096: `perf` puts the time in
`YnnFusionThunkFromProto` (a lookup of `HloInstruction::unique_id` over the whole module per
thunk) and in `BufferUse::ReadWriteSet::HasConflicts` (building the execution graph).

  python benchmarks/bench_thunks.py                       # reductions, N = 256 ... 4096
  python benchmarks/bench_thunks.py --ops conv --n 128,512,2048
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
from jax import lax
from jax.experimental import serialize_executable

NO_YNN = {"xla_cpu_experimental_ynn_fusion_type": ""}  # no YNNPACK fusion of any kind


def program(ops: str, n: int):
  """(f, args): N independent reductions or 2D convolutions of one input."""
  if ops == "reduce":
    x = jnp.ones((2, 32, 32, 32), jnp.float32)
    ks = [jnp.full((32,), i, jnp.float32) for i in range(n)]
    return (lambda x, ks: [jnp.sum(x * k, axis=(0, 1, 2)) for k in ks]), (x, ks)
  x = jnp.ones((1, 32, 32, 32), jnp.float32)
  ks = [jnp.full((3, 3, 32, 32), i, jnp.float32) for i in range(n)]
  conv = lambda x, k: lax.conv_general_dilated(x, k, (1, 1), "SAME",
                                               dimension_numbers=("NHWC", "HWIO", "NHWC"))
  return (lambda x, ks: [conv(x, k) for k in ks]), (x, ks)


def measure(ops: str, n: int, options: dict | None) -> dict:
  """Compile, serialise and load seconds (the load's best of 2), the executable's size and its
  YNNPACK fusion count."""
  f, args = program(ops, n)
  t0 = time.perf_counter()
  compiled = jax.jit(f, compiler_options=options).lower(*args).compile()
  compile_s = time.perf_counter() - t0
  thunks = compiled.as_text().count('"kind":"__ynn_fusion"')
  t0 = time.perf_counter()
  payload, in_tree, out_tree = serialize_executable.serialize(compiled)
  serialise_s = time.perf_counter() - t0
  loads = []
  for _ in range(2):
    t0 = time.perf_counter()
    loaded = serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
    loads.append(time.perf_counter() - t0)
  runs = []  # the loaded program's first run, then a later one
  for _ in range(2):
    t0 = time.perf_counter()
    jax.block_until_ready(loaded(*args))
    runs.append(time.perf_counter() - t0)
  return {"ops": ops, "n": n, "ynn": options is None, "ynn_thunks": thunks,
          "compile_s": compile_s, "serialise_s": serialise_s, "load_s": min(loads),
          "first_run_s": runs[0], "later_run_s": runs[1], "mbytes": len(payload) / 1e6}


def main() -> None:
  """The table, then the rows recorded where this runs inside sljax's checkout."""
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--ops", choices=("reduce", "conv"), default="reduce")
  ap.add_argument("--n", default="256,512,1024,2048,4096")
  ap.add_argument("--no-record", action="store_true")
  args = ap.parse_args()
  ns = [int(v) for v in args.n.split(",")]
  print(f"jax {jax.__version__}, backend {jax.default_backend()}, {args.ops} x N")
  print("| N | YNNPACK fusions | YNNPACK thunks | compile s | serialise s | load s | first run s "
        "| later run s | MB |")
  print("| ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
  rows = []
  for options in (None, NO_YNN):
    for n in ns:
      r = measure(args.ops, n, options)
      rows.append(r)
      print(f"| {n} | {'on' if r['ynn'] else 'none'} | {r['ynn_thunks']} | {r['compile_s']:.2f} | "
            f"{r['serialise_s']:.3f} | {r['load_s']:.3f} | {r['first_run_s']:.3f} | "
            f"{r['later_run_s']:.3f} | {r['mbytes']:.2f} |", flush=True)
  for ynn in (True, False):
    a, b = [r for r in rows if r["ynn"] == ynn][-2:] if len(ns) > 1 else (None, None)
    if a and a["load_s"] > 0:
      k = math.log(b["load_s"] / a["load_s"]) / math.log(b["n"] / a["n"])
      print(f"load grows as N^{k:.1f} between N = {a['n']} and {b['n']} with the fusions "
            f"{'on' if ynn else 'off (none)'}")
  if args.no_record:
    return
  sys.path.insert(0, str(Path(__file__).resolve().parent))
  try:
    from common import record  # sljax's records; absent where this file travels alone
  except ImportError:
    return
  record("bench_thunks", rows)


if __name__ == "__main__":
  main()
