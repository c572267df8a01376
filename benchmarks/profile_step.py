"""Where a network's training step (or forward) spends its time on this CPU: a jax.profiler
trace of one compiled call, its XLA operations' exclusive time grouped by kind.

The step is bench_nets' (the paper's loss, the tuned compiler choice of the program kind), so
the table explains bench_nets' ratios. Exclusive time: an operation's duration less that of
the operations nested in it on the same thread (XLA's loops contain the blocked convolutions);
the share is of all operations' time, summed over the threads that run them. `ynn_fusion` is
XLA handing a convolution (with what it fused to it) to its library kernels (YNNPACK).

  python benchmarks/profile_step.py                         # PSMNet, 256x256, batch 2, training
  python benchmarks/profile_step.py --model psmnet-mtl --forward
  python benchmarks/profile_step.py --batch 12 --kernels indexed,nchwToNhwc   # on a GPU

--kernels PATTERNS (a GPU): the device kernels whose names hold any of the comma-separated
patterns, each with its XLA operation and that operation's layer (its `op_name`: the flax
module path, and jvp/transpose for the gradients), dimension labels and shapes from the
compiled program: which convolution runs in cuDNN's sm80 `indexed` kernels and which brings
its `nchwToNhwc` layout conversions (issue 42).
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import re
import tempfile
from collections.abc import Callable
from pathlib import Path

import jax

from common import machine, record  # first: puts this checkout's sljax on the path
from sljax.runtime.hugepages import reexec
from bench_nets import jax_loss, inputs
from sljax import kernels
from sljax.nets import build_model
from sljax.runtime import choices

# Host-side spans, not XLA operations.
RUNTIME = ("$", "ThunkExecutor", "PjitFunction", "CommonPjRt", "SlinkyThreadPool",
           "AllocateOutputBuffers")


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


def traced(run: Callable[[], object], keep: Path | None = None) -> list[dict]:
  """The trace events of run() (its result waited for); the trace files are kept in `keep`
  when given, for a trace viewer."""
  with tempfile.TemporaryDirectory() as d:
    folder = Path(keep or d)
    jax.profiler.start_trace(str(folder), create_perfetto_trace=True)
    jax.block_until_ready(run())
    jax.profiler.stop_trace()
    path = sorted(folder.rglob("*.trace.json.gz"), key=lambda f: f.stat().st_mtime)[-1]
    data = json.loads(gzip.decompress(path.read_bytes()))
  return data["traceEvents"] if isinstance(data, dict) else data


def traced_call(fn, args, calls: int = 1, keep: Path | None = None) -> list[dict]:
  """The trace events of `calls` calls of a compiled function."""
  return traced(lambda: [fn(*args) for _ in range(calls)][-1], keep)


# Trace lines of an accelerator that summarise its kernels (XLA modules and operations, steps):
# counted once, through the kernels on the stream lines.
DERIVED_LINES = ("XLA Modules", "XLA Ops", "Async XLA Ops", "Steps", "TensorFlow", "Framework",
                 "Source", "Launch Stats")


def device_kernel_times(events: list[dict], by_op: bool = False
                        ) -> tuple[collections.Counter, dict[str, str]]:
  """Microseconds per kernel name on the accelerators' stream lines of a trace (an empty
  Counter on a CPU-only trace), and the XLA operations each kernel ran for where the trace
  names them (Counters of microseconds); by_op: per (kernel name, XLA operation) instead (one
  kernel can serve several operations)."""
  procs, threads = {}, {}
  for e in events:
    if e.get("ph") == "M" and e.get("name") in ("process_name", "thread_name"):
      table = procs if e["name"] == "process_name" else threads
      table[e["pid"] if e["name"] == "process_name" else (e["pid"], e.get("tid"))] = str(
          e.get("args", {}).get("name", ""))
  devices = {pid for pid, name in procs.items()
             if "/device:" in name and "/device:CPU" not in name.upper()}
  kernels, ops = collections.Counter(), {}
  for e in events:
    line = threads.get((e.get("pid"), e.get("tid")), "")
    if (e.get("ph") == "X" and "dur" in e and e.get("pid") in devices
        and not line.startswith(DERIVED_LINES)):
      op = (e.get("args") or {}).get("hlo_op")
      kernels[(e["name"], str(op or "")) if by_op else e["name"]] += e["dur"]
      if op:
        ops.setdefault(e["name"], collections.Counter())[str(op)] += e["dur"]
  return kernels, ops


def op_label(ops: collections.Counter | None) -> str:
  """The XLA operation a kernel spent most time in, and how many others it ran for."""
  if not ops:
    return ""
  (first, _), rest = ops.most_common(1)[0], len(ops) - 1
  return first + (f" (+{rest} more)" if rest else "")


def kernel_rows(events: list[dict], calls: int, top: int) -> list[dict]:
  """The `top` kernels of a trace of `calls` calls, ms per call and share of the device's
  kernel time; off an accelerator, XLA's operations by kind (exclusive host time) instead."""
  kernels, ops = device_kernel_times(events)
  where = "device"
  if not kernels:
    kernels, ops, where = by_kind(exclusive_times(events)), {}, "host"
  total = sum(kernels.values()) or 1.0
  return [{"kernel": name, "ms_per_call": us / 1e3 / calls, "share": us / total,
           "hlo_op": op_label(ops.get(name)), "where": where}
          for name, us in kernels.most_common(top)]


def main() -> None:
  reexec()  # as sljax's commands run: malloc with huge pages (sljax/runtime/hugepages.py)
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--model", default="psmnet")
  ap.add_argument("--size", type=int, default=256)
  ap.add_argument("--maxdisp", type=int, default=96)
  ap.add_argument("--batch", type=int, default=2)
  ap.add_argument("--forward", action="store_true", help="profile the forward (eval) program")
  ap.add_argument("--top", type=int, default=12)
  ap.add_argument("--kernels", default=None, metavar="PATTERNS",
                  help="device kernels naming any of these (comma-separated), with their layers")
  args = ap.parse_args()
  print(machine())
  kind = "forward" if args.forward else "train"
  choice = choices.choice()
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
    def grads(params, l, r, g):  # with the kernel gradients' blocks training takes here
      with kernels.grad_blocks(choices.grad_blocks_for(choice)):
        return jax.grad(loss)(params, l, r, g)
    fn = jax.jit(grads, compiler_options=options)
    call = (variables["params"], left, right, gt)
  jax.block_until_ready(fn(*call))  # compile and warm up
  if args.kernels:
    kernel_layers(fn, call, args)
    return
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


def hlo_ops(hlo_text: str) -> dict[str, dict[str, str]]:
  """Per instruction name of a compiled HLO module: its op_name metadata, dim_labels, the
  custom call's target and the instruction's text up to its operands (shapes)."""
  out = {}
  for line in hlo_text.splitlines():
    m = re.match(r"\s*(?:ROOT )?%?([\w.\-]+) = (.*)", line)
    if not m:
      continue
    meta = re.search(r'op_name="([^"]*)"', line)
    labels = re.search(r"dim_labels=([\w>\-]+)", line)
    target = re.search(r'custom_call_target="([^"]*)"', line)
    out[m.group(1)] = {"layer": meta.group(1) if meta else "",
                       "dim_labels": labels.group(1) if labels else "",
                       "target": target.group(1) if target else "",
                       "shape": m.group(2).split("(")[0][:120]}
  return out


def kernel_layers(fn, call, args, calls: int = 3) -> None:
  """Prints (and records) the device kernels matching args.kernels with their layers."""
  patterns = [p for p in args.kernels.split(",") if p]
  ops = hlo_ops(fn.lower(*call).compile().as_text())
  kernels, _ = device_kernel_times(traced_call(fn, call, calls), by_op=True)
  total = sum(kernels.values()) or 1.0
  print(f"\n{args.model} {'forward' if args.forward else 'train'}, {args.size}x{args.size}, "
        f"maxdisp {args.maxdisp}, batch {args.batch}: device kernels naming "
        f"{', '.join(patterns)} ({total / 1e3 / calls:.1f} ms of kernels a call)")
  print("| kernel | ms a call | share | XLA op | layer (op_name) | dim_labels | shape |\n"
        "| --- | ---: | ---: | --- | --- | --- | --- |")
  rows = []
  for (name, op), us in kernels.most_common():
    if not any(p in name for p in patterns):
      continue
    op = op.lstrip("%")
    info = ops.get(op, {})
    row = {"kernel": name, "ms_per_call": us / 1e3 / calls, "share": us / total, "hlo_op": op,
           **info}
    rows.append(row)
    print(f"| {name[:90]} | {row['ms_per_call']:.2f} | {100 * row['share']:.1f}% | {op} | "
          f"{info.get('layer', '?')} | {info.get('dim_labels', '')} | {info.get('shape', '')} |")
  if not kernels:
    print("(no device kernels in the trace: not on a GPU)")
  record("profile_step", rows, model=args.model, program="kernels", size=args.size,
         maxdisp=args.maxdisp, batch=args.batch, patterns=args.kernels)


if __name__ == "__main__":
  main()
