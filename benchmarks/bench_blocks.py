"""PSMNet's forward + backward as a library user writes it, in each kernel-gradient block size.

A plain `jax.jit(jax.grad(loss))` over `build_model("psmnet")` (no `grad_blocks` context, XLA's
default compiler options, i.e. YNNPACK's fusions on) against the same program with the kernel
gradients in blocks of 2**K values set explicitly, with the fusions on and off, and the reference
PSMNet (JiaRenChang/PSMNet) beside them: alternating rounds in one process, so that a burst of
load hits every setting alike. Prints the table of medians with each round's range, the ratios
to the reference, which block size the context-free program took, and records the rows.

  python benchmarks/bench_blocks.py --reference ~/src/PSMNet
  python benchmarks/bench_blocks.py --reference DIR --blocks 17,20 --ynn on,off --rounds 5
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from common import machine, record  # first: puts this checkout's sljax on the path
from bench_nets import inputs, jax_loss, reference_psmnet, torch_loss
from sljax import kernels
from sljax.nets import build_model
from sljax.runtime import choices
from sljax.runtime.hugepages import reexec

PAUSE = 0.5  # seconds before each timed call


def programs(size: int, maxdisp: int, batch: int, settings: list[tuple[str, int | None]]):
  """{(ynn, blocks): (gradient program, its arguments)}; blocks None: no context (the plain
  user's program)."""
  model = build_model("psmnet", maxdisp=maxdisp)
  left, right, gt = (jnp.asarray(a) for a in inputs(batch, size, maxdisp))
  variables = jax.jit(model.init)(jax.random.PRNGKey(0), left[:1], right[:1])

  def loss(params, l, r, g):
    out, _ = model.apply({**variables, "params": params}, l, r, train=True,
                         mutable=["batch_stats"])
    return jax_loss(out, g, maxdisp)

  out = {}
  for ynn, blocks in settings:
    options = None if ynn == "on" else dict(choices.YNN_OFF)
    if blocks is None:
      fn = jax.jit(jax.grad(loss), compiler_options=options)
    else:
      def fn_blocks(p, l, r, g, blocks=blocks):
        with kernels.grad_blocks(blocks):
          return jax.grad(loss)(p, l, r, g)
      fn = jax.jit(fn_blocks, compiler_options=options)
    args = (variables["params"], left, right, gt)
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile()
    print(f"compiled ynn {ynn}, blocks {label(blocks)} in {time.perf_counter() - t0:.0f} s",
          flush=True)
    out[(ynn, blocks)] = (compiled, args)
  return out


def label(blocks: int | None) -> str:
  """'2^20' or 'none (context-free)'."""
  return "none (context-free)" if blocks is None else f"2^{blocks.bit_length() - 1}"


def main() -> None:
  """Alternating rounds, then the table."""
  reexec()  # as sljax's commands run: malloc with huge pages (sljax/runtime/hugepages.py)
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--reference", metavar="DIR", required=True,
                  help="local checkout of JiaRenChang/PSMNet")
  ap.add_argument("--size", type=int, default=256)
  ap.add_argument("--maxdisp", type=int, default=96)
  ap.add_argument("--batch", type=int, default=2)
  ap.add_argument("--blocks", default="17,20", help="log2 block sizes to set explicitly")
  ap.add_argument("--ynn", default="on,off", help="YNNPACK fusion settings of the explicit ones")
  ap.add_argument("--rounds", type=int, default=5)
  args = ap.parse_args()
  import torch
  print(machine(torch))
  default = kernels.grad_block_values(kernels.BLOCK_VALUES)
  print(f"a program traced without a context takes kernel-gradient blocks of {default} values "
        f"({label(default)})")
  # The context-free program last: the first one compiled ran 1.3x slower than the identical
  # program compiled later, in the one run that had it first (2-core Xeon, cause not found).
  settings = [(y, 1 << int(b)) for y in args.ynn.split(",")
              for b in args.blocks.split(",")] + [("on", None)]
  progs = programs(args.size, args.maxdisp, args.batch, settings)
  ref = reference_psmnet(args.reference, args.maxdisp)
  ref.train()
  left, right, gt = inputs(args.batch, args.size, args.maxdisp)
  tl, tr = (torch.tensor(a.transpose(0, 3, 1, 2).copy()) for a in (left, right))
  tg = torch.tensor(gt)

  def torch_step():
    ref.zero_grad(set_to_none=True)
    torch_loss(ref(tl, tr), tg, args.maxdisp).backward()

  calls = {k: (lambda c=c, a=a: jax.block_until_ready(c(*a))) for k, (c, a) in progs.items()}
  calls["reference"] = torch_step
  for f in calls.values():
    f()  # warm-up
  samples = {k: [] for k in calls}
  keys = list(calls)
  for i in range(args.rounds):
    # Each round starts at another setting, and every call waits for the machine to settle:
    # PyTorch's OpenMP threads spin a while after a step, and whatever ran right after the
    # reference was 1.3x slower on a 2-core Xeon (the same program timed as two settings).
    for k in keys[i % len(keys):] + keys[:i % len(keys)]:
      time.sleep(PAUSE)
      t0 = time.perf_counter()
      calls[k]()
      samples[k].append(time.perf_counter() - t0)
  ref_s = samples.pop("reference")
  print(f"\nPSMNet forward + backward, {args.size}x{args.size}, maxdisp {args.maxdisp}, batch "
        f"{args.batch}: medians of {args.rounds} alternating rounds; reference "
        f"{np.median(ref_s):.2f} s")
  print("| YNNPACK fusions | kernel-gradient blocks | sljax s | vs reference (median) | by round |")
  print("| --- | --- | ---: | ---: | --- |")
  rows = []
  for (ynn, blocks), s in samples.items():
    ratios = [a / b for a, b in zip(s, ref_s)]
    print(f"| {ynn} | {label(blocks)} | {np.median(s):.2f} | {np.median(ratios):.2f}x | "
          f"{min(ratios):.2f}-{max(ratios):.2f}x |")
    rows.append({"table": "blocks", "model": "psmnet", "size": args.size,
                 "maxdisp": args.maxdisp, "batch": args.batch, "ynn": ynn,
                 "grad_blocks": blocks if blocks is not None else f"context-free ({default})",
                 "sljax_s": float(np.median(s)), "torch_s": float(np.median(ref_s)),
                 "ratio": float(np.median(ratios)), "ratios": [round(r, 3) for r in ratios]})
  record("bench_blocks", rows, torch)


if __name__ == "__main__":
  main()
