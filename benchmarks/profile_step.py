"""Where a network's training step (or forward) spends its time on this CPU: a jax.profiler
trace of one compiled call, its XLA operations' exclusive time grouped by kind.

The step is bench_nets' (the paper's loss, the tuned compiler choice of the program kind), so
the table explains bench_nets' ratios. Exclusive time: an operation's duration less that of
the operations nested in it on the same thread (XLA's loops contain the blocked convolutions);
the share is of all operations' time, summed over the threads that run them. `ynn_fusion` is
XLA handing a convolution (with what it fused to it) to its library kernels (YNNPACK).

  python benchmarks/profile_step.py                         # PSMNet, 256x256, batch 2, training
  python benchmarks/profile_step.py --model psmnet-mtl --forward
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import re
import tempfile
from pathlib import Path

import jax

from common import machine, record  # first: puts this checkout's sljax on the path
from bench_nets import jax_loss, inputs
from sljax import tune
from sljax.nets import build_model

RUNTIME = ("$", "ThunkExecutor", "PjitFunction")  # host-side spans, not XLA operations


def exclusive_times(events: list[dict]) -> collections.Counter:
  """Exclusive microseconds per event name: each span less its children on the same thread."""
  threads = collections.defaultdict(list)
  for e in events:
    if e.get("ph") == "X" and "dur" in e:
      threads[e.get("pid"), e.get("tid")].append(dict(e, child=0))
  out = collections.Counter()
  for spans in threads.values():
    spans.sort(key=lambda e: (e["ts"], -e["dur"]))
    stack: list[dict] = []
    for e in spans:
      while stack and e["ts"] >= stack[-1]["ts"] + stack[-1]["dur"]:
        stack.pop()
      if stack:
        stack[-1]["child"] += e["dur"]
      stack.append(e)
    for e in spans:
      out[e["name"]] += e["dur"] - e["child"]
  return out


def by_kind(exclusive: collections.Counter) -> collections.Counter:
  """Exclusive time per operation kind ('ynn_fusion.12' -> 'ynn_fusion'), runtime spans out."""
  kinds = collections.Counter()
  for name, us in exclusive.items():
    if not name.startswith(RUNTIME) and "block_until_ready" not in name and "trace" not in name:
      kinds[re.sub(r"\.\d+$", "", name)] += us
  return kinds


def traced_call(fn, args) -> list[dict]:
  """The trace events of one call of a compiled function."""
  with tempfile.TemporaryDirectory() as d:
    jax.profiler.start_trace(d, create_perfetto_trace=True)
    jax.block_until_ready(fn(*args))
    jax.profiler.stop_trace()
    path = sorted(Path(d).rglob("*.trace.json.gz"))[-1]
    data = json.loads(gzip.decompress(path.read_bytes()))
  return data["traceEvents"] if isinstance(data, dict) else data


def main() -> None:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--model", default="psmnet")
  ap.add_argument("--size", type=int, default=256)
  ap.add_argument("--maxdisp", type=int, default=96)
  ap.add_argument("--batch", type=int, default=2)
  ap.add_argument("--forward", action="store_true", help="profile the forward (eval) program")
  ap.add_argument("--top", type=int, default=12)
  args = ap.parse_args()
  print(machine())
  kind = "forward" if args.forward else "train"
  choice = tune.choice()
  model = build_model(args.model, maxdisp=args.maxdisp)
  left, right, gt = (jax.numpy.asarray(a) for a in inputs(args.batch, args.size, args.maxdisp))
  variables = jax.jit(model.init)(jax.random.PRNGKey(0), left[:1], right[:1])
  options = choice.compiler_options(kind)
  if args.forward:
    fn = jax.jit(lambda v, l, r: model.apply(v, l, r, train=False), compiler_options=options)
    call = (variables, left, right)
  else:
    def loss(params, l, r, g):
      out, _ = model.apply({**variables, "params": params}, l, r, train=True,
                           mutable=["batch_stats"])
      return jax_loss(out, g, args.maxdisp)
    fn = jax.jit(jax.grad(loss), compiler_options=options)
    call = (variables["params"], left, right, gt)
  jax.block_until_ready(fn(*call))  # compile and warm up
  kinds = by_kind(exclusive_times(traced_call(fn, call)))
  total = sum(kinds.values())
  print(f"\n{args.model} {kind}, {args.size}x{args.size}, maxdisp {args.maxdisp}, batch "
        f"{args.batch}, --ynn {choice.name}: exclusive time of XLA operations by kind "
        f"({total / 1e6:.2f} s over all threads)")
  print("| kind | ms | share |\n| --- | ---: | ---: |")
  rows = []
  for name, us in kinds.most_common(args.top):
    print(f"| {name} | {us / 1e3:.0f} | {100 * us / total:.1f}% |")
    rows.append({"kind": name, "ms": us / 1e3, "share": us / total})
  record("profile_step", rows, model=args.model, program=kind, size=args.size,
         maxdisp=args.maxdisp, batch=args.batch, ynn=choice.name)


if __name__ == "__main__":
  main()
