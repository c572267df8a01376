"""What only an accelerator shows: sljax's networks on a GPU, beside PyTorch on the same GPU,
and whether the GPU's float32 arithmetic keeps the networks equal to the CPU's.

1. Agreement: PSMNet's forward (pad-mode evaluation, the same random weights and pair) on the
   accelerator against the CPU, at XLA's default float32 precision (NVIDIA: TF32 tensor cores
   for convolutions and matrix products since Ampere) and at `highest` (true float32). The
   reference test allows 1e-3 px; this says whether the default passes it on this GPU.
2. Speed: forward (eval) and forward + backward (the paper's loss) of psmnet, psmnet-mtl and
   unet-sl at 256x256, maxdisp 96, in ms and samples/s, at both precisions; beside them, with
   `--reference DIR` (a local checkout of JiaRenChang/PSMNet) and a CUDA build of torch, the
   reference PSMNet on the same device with TF32 off and on (the stacks of bench_nets for the
   others). Times: minimum of `--repeats` after a warm-up, each call synchronised.
3. Memory: the device's peak bytes in use after each model (jax memory_stats).

Every figure is appended to benchmarks/results/<backend>-<device kind>.jsonl. On a CPU it
runs too (CPU against CPU), which is how it is checked before a GPU session:

  python benchmarks/bench_gpu.py --reference DIR
  python benchmarks/bench_gpu.py --size 64 --maxdisp 32 --models psmnet --repeats 1   # dry run
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from common import best_time, machine, record  # first: puts this checkout's sljax on the path
from bench_fullres import random_variables
from bench_nets import inputs, jax_time, reference_psmnet, torch_loss, torch_models
from sljax.nets import build_model

PRECISIONS = ("default", "highest")  # jax_default_matmul_precision: TF32 allowed, or not


def agreement(pred: np.ndarray, ref: np.ndarray) -> dict[str, float]:
  """Largest and mean absolute difference (px) of two disparity maps, and the share of pixels
  more than 1e-3 px apart (the reference test's tolerance)."""
  d = np.abs(np.asarray(pred, np.float64) - np.asarray(ref, np.float64))
  return {"max_px": float(d.max()), "mean_px": float(d.mean()),
          "over_1e-3_pct": float(100.0 * np.mean(d > 1e-3))}


def forward_on(device, model, variables, left, right, precision: str) -> np.ndarray:
  """The evaluation forward on one device at one matmul/conv precision."""
  put = lambda x: jax.device_put(x, device)
  with jax.default_matmul_precision(precision):
    f = jax.jit(lambda v, l, r: model.apply(v, l, r, train=False)["disparity"])
    return np.asarray(f(put(variables), put(left), put(right)))


def check_agreement(size: int, maxdisp: int) -> list[dict]:
  """PSMNet on the default device against the CPU, at each precision."""
  model = build_model("psmnet", maxdisp=maxdisp)
  variables = random_variables("psmnet", {"maxdisp": maxdisp})
  left, right, _ = inputs(1, size, maxdisp)
  cpu = forward_on(jax.devices("cpu")[0], model, variables, left, right, "highest")
  rows = []
  for precision in PRECISIONS:
    got = forward_on(jax.devices()[0], model, variables, left, right, precision)
    rows.append({"table": "agreement", "model": "psmnet", "size": size, "maxdisp": maxdisp,
                 "precision": precision, **agreement(got, cpu)})
  return rows


def peak_bytes() -> float | None:
  """The device's peak bytes in use so far (None where the backend does not report it)."""
  stats = jax.devices()[0].memory_stats() or {}
  return stats.get("peak_bytes_in_use")


def torch_cuda_time(torch, model, batch, size, maxdisp, repeats, train, tf32: bool) -> float:
  """PyTorch on the GPU: forward (eval, no grad) or forward + backward, synchronised."""
  torch.backends.cuda.matmul.allow_tf32 = tf32
  torch.backends.cudnn.allow_tf32 = tf32
  torch.backends.cudnn.benchmark = True
  left, right, gt = inputs(batch, size, maxdisp)
  dev = torch.device("cuda")
  left, right = (torch.tensor(a.transpose(0, 3, 1, 2).copy(), device=dev) for a in (left, right))
  gt = torch.tensor(gt, device=dev)
  model = model.to(dev)

  def call():
    if train:
      model.train()
      model.zero_grad(set_to_none=True)
      torch_loss(model(left, right), gt, maxdisp).backward()
    else:
      model.eval()
      with torch.no_grad():
        model(left, right)
    torch.cuda.synchronize()
  return best_time(call, repeats)


def main() -> None:
  ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                               formatter_class=argparse.RawDescriptionHelpFormatter)
  ap.add_argument("--models", default="psmnet,psmnet-mtl,unet-sl")
  ap.add_argument("--size", type=int, default=256)
  ap.add_argument("--maxdisp", type=int, default=96)
  ap.add_argument("--batch", type=int, default=4)
  ap.add_argument("--repeats", type=int, default=5)
  ap.add_argument("--reference", metavar="DIR", default=None,
                  help="local checkout of JiaRenChang/PSMNet: time it on the same GPU")
  args = ap.parse_args()
  torch = None
  try:
    import torch as torch_module
    if torch_module.cuda.is_available():
      torch = torch_module
  except ImportError:
    pass
  print(machine(torch))
  t0 = time.perf_counter()

  # ------------------------------------------------------------------------ agreement
  rows = check_agreement(args.size, args.maxdisp)
  record("bench_gpu", rows, torch, quiet=True)  # each part recorded as it ends: a call cut
  # short keeps what it measured
  print(f"\nPSMNet forward, {jax.default_backend()} vs CPU ({args.size}x{args.size}, maxdisp "
        f"{args.maxdisp}, random weights): the reference test allows 1e-3 px")
  print("| precision | max px | mean px | pixels over 1e-3 px |\n| --- | ---: | ---: | ---: |")
  for r in rows:
    print(f"| {r['precision']} | {r['max_px']:.2e} | {r['mean_px']:.2e} | "
          f"{r['over_1e-3_pct']:.2f}% |")

  # ------------------------------------------------------------------------ speed
  print(f"\nModels at {args.size}x{args.size}, maxdisp {args.maxdisp}, batch {args.batch}: ms a "
        "call (samples/s); torch: TF32 off / on")
  print("| model | mode | sljax default | sljax highest | torch fp32 | torch TF32 | peak GiB |")
  print("| --- | --- | ---: | ---: | ---: | ---: | ---: |")
  stacks = None
  for name in args.models.split(","):
    rows = []
    tm = None
    if torch is not None:
      if name == "psmnet" and args.reference:
        tm = reference_psmnet(args.reference, args.maxdisp, keep_cuda=True)
      else:
        stacks = stacks or torch_models()
        _, PSM, UNet = stacks
        tm = {"unet-sl": lambda: UNet(16), "unet-disp": lambda: UNet(1),
              "psmnet": lambda: PSM(args.maxdisp),
              "psmnet-mtl": lambda: PSM(args.maxdisp, 8)}[name]()
    for train in (False, True):
      row = {"table": "models", "model": name, "mode": "fwd+bwd" if train else "fwd",
             "size": args.size, "maxdisp": args.maxdisp, "batch": args.batch}
      for precision in PRECISIONS:
        with jax.default_matmul_precision(precision):
          row[f"sljax_{precision}_s"] = jax_time(name, args.batch, args.size, args.maxdisp,
                                                 args.repeats, train)
      if tm is not None:
        for tf32 in (False, True):
          row[f"torch_{'tf32' if tf32 else 'fp32'}_s"] = torch_cuda_time(
              torch, tm, args.batch, args.size, args.maxdisp, args.repeats, train, tf32)
        row["torch_side"] = "reference" if name == "psmnet" and args.reference else "stack"
      row["peak_gib"] = (peak_bytes() or float("nan")) / 2**30
      rows.append(row)
      cell = lambda k: (f"{row[k] * 1e3:.1f} ({args.batch / row[k]:.1f})" if k in row else "-")
      print(f"| {name} | {row['mode']} | {cell('sljax_default_s')} | {cell('sljax_highest_s')} | "
            f"{cell('torch_fp32_s')} | {cell('torch_tf32_s')} | {row['peak_gib']:.2f} |")
    path = record("bench_gpu", rows, torch, quiet=True)
  print(f"\n{time.perf_counter() - t0:.0f} s in all; recorded in {path}")


if __name__ == "__main__":
  main()
