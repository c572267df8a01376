"""The stride-2 transposed 3D convolution of PSMNet's hourglasses, in each of its forms: time
of the forward, of each gradient and of both, and (--profile) the device kernels each runs.

Issue 36 found 65% of PSMNet's GPU training step in one cuDNN fallback kernel
(`..._fprop_implicit_gemm_indexed_wo_smem_...`) coming from these layers. This measures, at
the layers' shapes, which program lands there and which form avoids it:

  lax           XLA's convolution of the 2-dilated input with flax's unflipped kernel, and
                JAX's gradients of it (the tests' reference).
  gpu-autodiff  gpu's forward (cuDNN's backward-data pattern: the kernel reversed in the
                program), differentiated by JAX: a fast forward, the lax form's gradients.
  gpu           that forward with a custom VJP: dL/dx the adjoint stride-2 convolution,
                dL/dkernel that convolution's weight gradient (`conv_impl="gpu"`).
  gpu-phase     the same VJP, the forward as the phase decomposition: one stride-1
                convolution with 8 x cout outputs, then a pixel shuffle (`conv_impl="gpu-phase"`).
  fast          the CPU kernels as they stand (folded 2D convolutions in loops).

Programs, each compiled alone: `fwd` (the output), `dx` (the output's gradient for the
input, from a fixed random output gradient), `dk` (for the kernel) and `both` (value and both
gradients: what a training step needs). XLA drops what a program does not return, so `dx`
and `dk` tell which gradient costs what. Times: the mean over a loop of calls (at least 0.2 s
of them, 3 to 50) after two warm-up calls (the first compiles and autotunes), synchronised
once at the end. Shapes: `paper` is the paper preset (256x256, maxdisp 96, batch 12), `crop`
PSMNet's training crop (256x512, maxdisp 192, batch 8); conv5 is 64 -> 64 from 1/16 to 1/8
resolution, conv6 64 -> 32 from 1/8 to 1/4. `--tiny` divides batch and spatial sizes for a
dry run on a CPU. With --profile PROGRAMS each of these programs is traced over 3 calls and
its top kernels (ms per call, share of kernel time, XLA operation) are printed; on a CPU the
XLA operations' host time by kind stands in. Every row is appended to benchmarks/results/ as
measured. Forms run in the order given: put the slow ones last, where a timeout cuts.

  python benchmarks/bench_convT.py --shapes paper --profile dk,both            # on a GPU
  python benchmarks/bench_convT.py --tiny --forms lax,gpu --profile dk,both    # CPU dry run
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from common import machine, record  # first: puts this checkout's sljax on the path
from profile_step import kernel_rows, traced_call
from sljax import kernels as c3
from sljax.kernels.conv3d import _backward_data_forward

STRIDES = (2, 2, 2)
PADDING = c3.transpose_padding((3, 3, 3), 1, 1)  # PyTorch ConvTranspose3d(3, 2, 1, 1)
# (name, batch, input D, H, W, cin, cout) per preset: the hourglasses' conv5 and conv6.
# conv6 first: the larger, and half the fallback's time at least.
SHAPES = {
    "paper": [("conv6", 12, 12, 32, 32, 64, 32), ("conv5", 12, 6, 16, 16, 64, 64)],
    "crop": [("conv6", 8, 24, 32, 64, 64, 32), ("conv5", 8, 12, 16, 32, 64, 64)],
}
PROGRAMS = ("fwd", "dx", "dk", "both")
PROFILE_CALLS = 3


def form(name: str):
  """f(x, kernel) of a form (the module docstring)."""
  if name == "gpu-autodiff":
    return lambda x, k: _backward_data_forward(x, k, STRIDES, PADDING)
  return lambda x, k: c3.conv_transpose3d(x, k, STRIDES, PADDING, impl=name)


def program(f, which: str):
  """The jitted program `which` of f: forward, one gradient, or value and both gradients."""
  loss = lambda x, k, w: jnp.sum(f(x, k) * w)
  if which == "fwd":
    return jax.jit(lambda x, k, w: f(x, k))
  if which == "both":
    return jax.jit(jax.value_and_grad(loss, (0, 1)))
  return jax.jit(jax.grad(loss, 0 if which == "dx" else 1))


def mean_time(fn, args, min_s: float = 0.2, max_calls: int = 50) -> tuple[float, int]:
  """(mean seconds a call, calls timed) over a loop after two warm-up calls."""
  for _ in range(2):
    jax.block_until_ready(fn(*args))
  t0 = time.perf_counter()
  jax.block_until_ready(fn(*args))
  one = time.perf_counter() - t0
  calls = int(min(max_calls, max(3, min_s / max(one, 1e-9))))
  t0 = time.perf_counter()
  for _ in range(calls):
    out = fn(*args)
  jax.block_until_ready(out)
  return (time.perf_counter() - t0) / calls, calls


def layer_inputs(shape, dtype, tiny: bool):
  """x, kernel and a fixed output gradient of one layer (random, the given dtype)."""
  _, batch, d, h, w, cin, cout = shape
  if tiny:
    batch, d, h, w = 1, max(1, d // 4), max(1, h // 4), max(1, w // 4)
  rng = np.random.RandomState(0)
  x = rng.randn(batch, d, h, w, cin)
  k = rng.randn(3, 3, 3, cin, cout) / np.sqrt(27 * cin / 8)
  y = rng.randn(batch, 2 * d, 2 * h, 2 * w, cout)
  return tuple(jnp.asarray(a, dtype) for a in (x, k, y))


def main() -> None:
  """Prints the timing table (and the kernel tables) and records every row."""
  ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                               formatter_class=argparse.RawDescriptionHelpFormatter)
  ap.add_argument("--shapes", default="paper", help="comma list of " + ", ".join(SHAPES))
  ap.add_argument("--forms", default="lax,gpu,gpu-phase,gpu-autodiff,fast")
  ap.add_argument("--programs", default=",".join(PROGRAMS))
  ap.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32",
                  help="float32 runs at XLA's default precision (TF32 convolutions on NVIDIA)")
  ap.add_argument("--tiny", action="store_true", help="batch 1, sizes / 4: a CPU dry run")
  ap.add_argument("--profile", default="",
                  help="comma list of programs to trace (e.g. dk,both): their top kernels")
  ap.add_argument("--top", type=int, default=4, help="kernels shown per profiled program")
  ap.add_argument("--trace-dir", type=Path, default=None,
                  help="keep each program's trace here (one folder a program)")
  args = ap.parse_args()
  forms, programs = args.forms.split(","), args.programs.split(",")
  print(machine())
  print(f"transposed 3D conv k3 s2 p1 op1, {args.dtype} (XLA's default precision), ms a call: "
        f"mean of a loop after 2 warm-up calls{'; tiny sizes' if args.tiny else ''}")
  print("| shape | layer | input | form | " + " | ".join(programs) + " | both / lax |")
  print("| --- | --- | --- | --- |" + " ---: |" * (len(programs) + 1), flush=True)
  profiles = []
  for preset in args.shapes.split(","):
    for shape in SHAPES[preset]:
      x, k, w = layer_inputs(shape, jnp.dtype(args.dtype), args.tiny)
      base, rows = None, []
      for name in forms:
        row = {"table": "convT", "shape": preset, "layer": shape[0], "form": name,
               "dtype": args.dtype, "tiny": args.tiny, "x": list(x.shape), "cout": k.shape[-1]}
        for which in programs:
          fn, call = program(form(name), which), (x, k, w)
          seconds, row[f"{which}_calls"] = mean_time(fn, call)
          row[f"{which}_ms"] = 1e3 * seconds
          if which in args.profile.split(","):
            keep = None
            if args.trace_dir:
              keep = args.trace_dir / f"{preset}-{shape[0]}-{name}-{which}"
              keep.mkdir(parents=True, exist_ok=True)
            kernels = kernel_rows(traced_call(fn, call, PROFILE_CALLS, keep), PROFILE_CALLS,
                                  args.top)
            profiles.append((f"{preset} {shape[0]} {name} {which}", kernels))
            row[f"{which}_kernels"] = kernels
        if name == "lax" and "both_ms" in row:
          base = row["both_ms"]
        if base and "both_ms" in row:
          row["both_over_lax"] = row["both_ms"] / base
        rows.append(row)
        ratio = f"{row['both_over_lax']:.2f}x" if "both_over_lax" in row else "-"
        print(f"| {preset} | {shape[0]} | {'x'.join(map(str, x.shape[1:4]))}x{x.shape[4]} b"
              f"{x.shape[0]} -> {k.shape[-1]} | {name} | "
              + " | ".join(f"{row[f'{p}_ms']:.2f}" for p in programs) + f" | {ratio} |",
              flush=True)
      path = record("bench_convT", rows, quiet=True)  # per layer: a run cut short keeps it
  for what, kernels in profiles:
    print(f"\n{what}: top kernels ({kernels[0]['where'] if kernels else 'none'}), ms a call, "
          "share of kernel time, XLA operation")
    for r in kernels:
      print(f"  {r['ms_per_call']:8.3f} ms {100 * r['share']:5.1f}%  {r['kernel'][:110]}"
            + (f"  [{r['hlo_op']}]" if r["hlo_op"] else ""))
  print(f"\nrecorded in {os.path.relpath(path)}")


if __name__ == "__main__":
  main()
