"""What only an accelerator shows: sljax's networks on a GPU, beside PyTorch on the same GPU,
and whether the GPU's float32 arithmetic keeps the networks equal to the CPU's. Parts (--part):

1. agreement: PSMNet's forward (pad-mode evaluation, the same random weights and pair) on the
   accelerator against the CPU, at XLA's default float32 precision (NVIDIA: TF32 tensor cores
   for convolutions and matrix products since Ampere) and at `highest` (true float32). The
   reference test allows 1e-3 px; this says whether the default passes it on this GPU.
2. models: forward (eval) and forward + backward (the paper's loss) of psmnet, psmnet-mtl and
   unet-sl at 256x256, maxdisp 96, in ms and samples/s, at both precisions; beside them, with
   `--reference DIR` (a local checkout of JiaRenChang/PSMNet) and a CUDA build of torch, the
   reference PSMNet on the same device with TF32 off and on (the stacks of bench_nets for the
   others). Times: minimum of `--repeats` after a warm-up, each call synchronised; peak: the
   device's peak bytes in use after each model (jax memory_stats). Both frameworks share one
   process (JAX preallocates 75% of the GPU's memory in it): a quick look, not the comparison
   a user makes; that is `step`.
3. step: the whole training step, each framework and configuration in its own process (a
   child of this script), one after the other on the same device: forward, backward and an
   Adam update of every parameter, the loss smooth L1 on the three outputs weighted 0.5 / 0.7 /
   1.0 (the reference's main.py), random weights and inputs (disparities beyond maxdisp
   masked). sljax: the step train.py compiles (`sljax.train.step.make_train_step`: psmnet with
   each `--impls` convolution choice, and the twin psmnet-mtl with uncertainty weighting
   beside it), the compile cache (sljax.runtime.compile_cache) on as in training, in a folder fresh for the run
   unless `--cache DIR`, so the first child compiles cold; `--warm-start` runs the first sljax
   child again, which then loads its programs from the cache (the time to its first step is
   the warm start). The reference: JiaRenChang/PSMNet's `stackhourglass` from `--reference DIR`
   (needed: the device has no network) with `cudnn.benchmark = True` (its fastest setting;
   its main.py leaves it off), Adam as in its main.py. Precisions: fp32 is each side's default
   float32 (TF32 convolutions on NVIDIA), bf16 is sljax's `--precision bf16` against the
   reference under `torch.autocast(bfloat16)`. Shapes: `paper` (256x256, maxdisp 96, batch
   12) and `crop` (PSMNet's training crop: 256x512, maxdisp 192, batch 8), or HxWxMAXDISPxBATCH.
   Per child: the time from its launch to the end of its first step (imports, initialisation,
   compilation or cache loads, the step), then the mean of `--steps` steps after `--warmup`
   steps (the first included), synchronised at both ends; peak memory: jax's peak_bytes_in_use
   and torch.cuda.max_memory_allocated (on a CPU, the process's peak RSS). Ratios are sljax /
   reference at the same shape and precision. `--profile-top K` traces 3 more sljax steps and
   prints their top K device kernels (what remains after a fix). The parent never starts
   jax's backend, which would take GPU memory from the children. The reference side is skipped
   without --reference or torch.

Every figure is appended to benchmarks/results/<backend>-<device kind>.jsonl. On a CPU it
runs too (CPU against CPU), which is how it is checked before a GPU session:

  python benchmarks/bench_gpu.py --reference DIR
  python benchmarks/bench_gpu.py --size 64 --maxdisp 32 --models psmnet --repeats 1   # dry run
  python benchmarks/bench_gpu.py --part step --shapes paper,crop --precisions fp32,bf16 \
      --impls lax,gpu --warm-start --reference DIR                                 # on a GPU
  python benchmarks/bench_gpu.py --part step --shapes 256x256x16x2 --impls lax,gpu \
      --steps 2 --warmup 1 --warm-start --reference DIR                            # CPU dry run
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from common import (best_time, device_of_process, machine, record,  # first: puts this
                    run_child)                                        # checkout's sljax on the path
from bench_fullres import random_variables
from bench_nets import inputs, jax_time, reference_psmnet, torch_loss, torch_models
from profile_step import kernel_rows, traced
from sljax.losses.disparity import PSMNET_OUTPUT_WEIGHTS
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


# ------------------------------------------------------------------------ the training step
STEP_SHAPES = {"paper": (256, 256, 96, 12), "crop": (256, 512, 192, 8)}  # H, W, maxdisp, batch
TWIN_PATTERNS = 8  # the paper preset's patterns per view
STEP_LR = 1e-3  # the reference main.py's Adam (sljax's paper lr is 1e-4: the same step time)
PROFILE_STEPS = 3


def step_shape(text: str) -> tuple[int, int, int, int]:
  """(height, width, maxdisp, batch) of a STEP_SHAPES name or of HxWxMAXDISPxBATCH."""
  if text in STEP_SHAPES:
    return STEP_SHAPES[text]
  h, w, maxdisp, batch = (int(v) for v in text.split("x"))
  return h, w, maxdisp, batch


def step_inputs(h: int, w: int, maxdisp: int, batch: int, patterns: int | None = None) -> dict:
  """Random NHWC views in [0, 1), disparities in [0, 1.1 maxdisp) (those past maxdisp masked)
  and, for the twin, 0/1 patterns: the same arrays for every child."""
  rng = np.random.RandomState(0)
  out = {"left": rng.rand(batch, h, w, 3), "right": rng.rand(batch, h, w, 3),
         "disp": rng.rand(batch, h, w) * maxdisp * 1.1}
  if patterns:
    out["sl"] = (rng.rand(batch, h, w, patterns) > 0.5)
  return {k: v.astype(np.float32) for k, v in out.items()}


def timed_steps(run_step, sync, warmup: int, steps: int, t0: float, setup: float) -> dict:
  """Runs the first step (the time from the child's launch t0 to its end, and from the call;
  the setup before it: since `setup`, a perf_counter time), the rest of the warm-up, then
  `steps` timed steps: their mean, synchronised at both ends."""
  start = time.perf_counter()
  run_step()
  sync()
  first = {"first_step_s": time.time() - t0, "first_call_s": time.perf_counter() - start,
           "setup_s": start - setup}
  for _ in range(warmup - 1):
    run_step()
  sync()
  start = time.perf_counter()
  for _ in range(steps):
    run_step()
  sync()
  return dict(first, step_s=(time.perf_counter() - start) / steps, steps=steps, warmup=warmup)


def sljax_step_child(args) -> dict:
  """One sljax configuration: the compiled training step of sljax.train (as train.py builds
  it, compile cache on), on one fixed random batch."""
  from sljax.losses.weighting import step_weights
  from sljax.nets import registry
  from sljax.nets.model_config import ModelConfig, init_variables
  from sljax.runtime.compile_cache import enable_compile_cache
  from sljax.train import loop
  from sljax.train import state as st
  from sljax.train import step as stp

  cache = enable_compile_cache()  # as train.py: $SLJAX_COMPILE_CACHE, which the parent sets
  hits = []
  jax.monitoring.register_event_listener(
      lambda name, **kw: hits.append(name) if name.endswith("cache_hits") else None)
  h, w, maxdisp, batch = step_shape(args.shape)
  spec = registry.spec(args.net)
  patterns = TWIN_PATTERNS if "t" in spec.options else None
  start = time.perf_counter()
  config = ModelConfig(args.net, 3, maxdisp, patterns, (), args.impl, args.precision)
  mesh = stp.make_mesh()
  model, tx, step, _ = loop.compiled_steps(config, "smooth_l1", STEP_LR, None, mesh)
  state = [jax.device_put(st.create_state(init_variables(model, 0, h, w, 3), tx),
                          stp.shardings(mesh)[0])]
  data = stp.put_batch({k: v for k, v in step_inputs(h, w, maxdisp, batch, patterns).items()
                        if k in spec.parts}, mesh)
  weights = jnp.asarray(step_weights("unc" if spec.multi_task else "stl", []))
  metrics = []

  def run_step():  # the step donates its state: keep the new one
    state[0], m = step(state[0], data, weights)
    metrics[:] = [m]

  sync = lambda: jax.block_until_ready((state[0], metrics))
  # setup_s: the model's initialisation (its compile or cache load), state and batch
  out = timed_steps(run_step, sync, args.warmup, args.steps, args.t0, start)
  out.update(device_of_process(), impl=model.conv_impl, cache=str(cache), cache_hits=len(hits),
             loss=float(metrics[0]["loss"]))
  stats = jax.devices()[0].memory_stats() or {}
  if "peak_bytes_in_use" in stats:
    out.update(peak_gib=stats["peak_bytes_in_use"] / 2**30, peak_of="device peak_bytes_in_use")
  if args.profile_top:
    def profiled():
      for _ in range(PROFILE_STEPS):
        run_step()
      return state[0], metrics
    out["kernels"] = kernel_rows(traced(profiled), PROFILE_STEPS, args.profile_top)
  return out


def reference_step_child(args) -> dict:
  """The reference PSMNet's training step in PyTorch (Adam, the reference's loss and mask)."""
  import torch
  import torch.nn.functional as F
  cuda = torch.cuda.is_available()
  dev = torch.device("cuda" if cuda else "cpu")
  torch.backends.cudnn.benchmark = True
  h, w, maxdisp, batch = step_shape(args.shape)
  start = time.perf_counter()
  torch.manual_seed(0)
  model = reference_psmnet(args.reference, maxdisp, keep_cuda=cuda).to(dev).train()
  opt = torch.optim.Adam(model.parameters(), lr=STEP_LR, betas=(0.9, 0.999))
  arrays = step_inputs(h, w, maxdisp, batch)
  left, right = (torch.tensor(arrays[k].transpose(0, 3, 1, 2).copy(), device=dev)
                 for k in ("left", "right"))
  gt = torch.tensor(arrays["disp"], device=dev)
  mask = gt < maxdisp  # the reference's main.py
  losses = []

  def run_step():
    opt.zero_grad()
    with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=args.precision == "bf16"):
      outs = [torch.squeeze(o, 1) for o in model(left, right)]  # as its main.py
      loss = sum(wt * F.smooth_l1_loss(o[mask], gt[mask])
                 for wt, o in zip(PSMNET_OUTPUT_WEIGHTS, outs))
    loss.backward()
    opt.step()
    losses[:] = [loss]

  sync = torch.cuda.synchronize if cuda else (lambda: None)
  out = timed_steps(run_step, sync, args.warmup, args.steps, args.t0, start)
  out.update(impl="cudnn.benchmark" if cuda else "cpu", loss=losses[0].item(),
             torch=torch.__version__, device_kind=torch.cuda.get_device_name() if cuda else "cpu")
  if cuda:
    out.update(peak_gib=torch.cuda.max_memory_allocated() / 2**30,
               reserved_gib=torch.cuda.max_memory_reserved() / 2**30,
               peak_of="torch max_memory_allocated")
  return out


def step_children(args) -> list[tuple[str, str, str]]:
  """(side, net, conv impl) of each child of one configuration: the reference first (every
  ratio needs it), then psmnet per impl, then the twin."""
  out = [("reference", "psmnet", "-")] if args.reference else []
  out += [("sljax", "psmnet", impl) for impl in args.impls.split(",")]
  if args.twin != "none":
    out.append(("sljax", "psmnet-mtl", args.twin))
  return out


def step_label(side: str, net: str, impl: str, run: str) -> str:
  """A child's name in the table."""
  if side == "reference":
    return "reference (PyTorch)"
  return (f"sljax {net}{' unc' if net == 'psmnet-mtl' else ''} {impl}"
          + (" (second run: warm cache)" if run == "second" else ""))


def step_part(args) -> None:
  """Launches one child per framework and configuration; prints and records their rows."""
  t0 = time.time()
  env = dict(os.environ, PYTHONUNBUFFERED="1")
  cache = args.cache or tempfile.mkdtemp(prefix="sljax-step-cache-")  # fresh: cold first
  env["SLJAX_COMPILE_CACHE"] = cache
  env.pop("JAX_COMPILATION_CACHE_DIR", None)  # the folder sljax.runtime.compile_cache would defer to
  if args.reference:
    try:
      import torch  # noqa: F401  (only whether it is there; the child imports it again)
    except ImportError:
      print("no torch here: the reference side is skipped")
      args.reference = None
  print(f"Training step, each side in its own process: mean of {args.steps} steps after "
        f"{args.warmup} warm-up steps; first step: from the child's launch; compile cache "
        f"{cache}{'' if args.cache else ' (fresh: the first sljax child compiles cold)'}")
  print("| shape | precision | side | first step s | step s | samples/s | peak GiB | / reference |")
  print("| --- | --- | --- | ---: | ---: | ---: | ---: | ---: |", flush=True)
  where, warm_done, path, pending = None, not args.warm_start, None, []
  for shape in args.shapes.split(","):
    h, w, maxdisp, batch = step_shape(shape)
    for precision in args.precisions.split(","):
      rows, ref_s = [], None
      todo = [(c, "first") for c in step_children(args)]
      while todo:
        (side, net, impl), run = todo.pop(0)
        label = step_label(side, net, impl, run)
        left = None if args.deadline is None else args.deadline - (time.time() - t0)
        if left is not None and left < 10:
          print(f"| {shape} | {precision} | {label} | skipped: {args.deadline} s deadline |",
                flush=True)
          continue
        child = ["--child", side, "--net", net, "--impl", impl, "--shape", shape,
                 "--precision", precision, "--steps", str(args.steps), "--warmup",
                 str(args.warmup), "--t0", repr(time.time())]
        child += ["--reference", args.reference] if side == "reference" else []
        child += ["--profile-top", str(args.profile_top)] if side == "sljax" else []
        res, rss = run_child(__file__, child, env=env, timeout=left, check=False)
        row = {"table": "step", "shape": shape, "height": h, "width": w, "maxdisp": maxdisp,
               "batch": batch, "precision": precision, "side": side, "net": net, "run": run}
        if res is None:
          row.update(failed=True, impl=impl)
          print(f"| {shape} | {precision} | {label} | failed (see its output above) |",
                flush=True)
          rows.append(row)
          continue
        row.update({k: v for k, v in res.items()
                    if k not in ("backend", "device_kind", "machine")})
        if "peak_gib" not in row:
          row.update(peak_gib=rss / 1024, peak_of="process peak RSS")
        if side == "sljax":
          where = where or {k: res[k] for k in ("backend", "device_kind", "machine")}
          if not warm_done:  # the same child again: its programs come from the cache
            warm_done = True
            todo.insert(0, ((side, net, impl), "second"))
        if side == "reference":
          ref_s = row["step_s"]
        if ref_s and side == "sljax":
          row["ratio"] = row["step_s"] / ref_s
        label = step_label(side, net, row["impl"], run)  # "auto" resolved by the child
        if row.get("cache_hits"):
          label += f" [{row['cache_hits']} programs from the cache]"
        rows.append(row)
        ratio = f"{row['ratio']:.2f}x" if "ratio" in row else "-"
        print(f"| {shape} {w}x{h} d{maxdisp} b{batch} | {precision} | {label} | "
              f"{row['first_step_s']:.1f} | {row['step_s']:.3f} | {batch / row['step_s']:.3g} | "
              f"{row['peak_gib']:.2f} | {ratio} |", flush=True)
        for k in row.get("kernels", []):  # s per step, share of the kernels' time
          what = "kernel" if k["where"] == "device" else "XLA op (host time)"
          print(f"|  |  | {what}, {100 * k['share']:.0f}%: {k['kernel'][:80]} |  | "
                f"{k['ms_per_call'] / 1e3:.4f} |  |  |  |", flush=True)
      pending.append(rows)  # recorded once a child has said where it ran: a run cut short
      while where and pending:  # keeps what it measured
        path = record("bench_gpu", pending.pop(0), quiet=True, where=where, cache=cache)
  if pending:  # no sljax child ran: this process may now start jax's backend
    where = device_of_process()
    for rows in pending:
      path = record("bench_gpu", rows, quiet=True, where=where, cache=cache)
  if where:
    print(f"\nsljax children ran on: {where['machine']}")
  if path:
    print(f"recorded in {os.path.relpath(path)}; {time.time() - t0:.0f} s in all")


def child_main(args) -> None:
  """A step child: prints its result as one JSON line (the last line of its output)."""
  import json
  result = (reference_step_child if args.child == "reference" else sljax_step_child)(args)
  print(json.dumps(result))


def agreement_part(args, torch) -> None:
  """PSMNet's forward on this device against the CPU's, at each precision."""
  rows = check_agreement(args.size, args.maxdisp)
  record("bench_gpu", rows, torch, quiet=True)  # each part recorded as it ends: a call cut
  # short keeps what it measured
  print(f"\nPSMNet forward, {jax.default_backend()} vs CPU ({args.size}x{args.size}, maxdisp "
        f"{args.maxdisp}, random weights): the reference test allows 1e-3 px")
  print("| precision | max px | mean px | pixels over 1e-3 px |\n| --- | ---: | ---: | ---: |")
  for r in rows:
    print(f"| {r['precision']} | {r['max_px']:.2e} | {r['mean_px']:.2e} | "
          f"{r['over_1e-3_pct']:.2f}% |")


def models_part(args, torch, t0: float) -> None:
  """sljax's models and PyTorch's in this process: forward and forward + backward."""
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
  ap.add_argument("--part", default="agreement,models", help="agreement, models, step")
  step = ap.add_argument_group("step (--part step)")
  step.add_argument("--shapes", default="paper,crop",
                    help=f"{', '.join(STEP_SHAPES)} or HxWxMAXDISPxBATCH")
  step.add_argument("--precisions", default="fp32,bf16")
  step.add_argument("--impls", default="auto", help="psmnet's conv_impl per child (sljax.kernels)")
  step.add_argument("--twin", default="auto", help="conv_impl of the twin's child, or none")
  step.add_argument("--steps", type=int, default=20)
  step.add_argument("--warmup", type=int, default=4, help="steps before the timed ones (>= 1)")
  step.add_argument("--warm-start", action="store_true",
                    help="run the first sljax child twice: the second loads from the cache")
  step.add_argument("--cache", default=None,
                    help="compile cache folder (default: a fresh one), or off")
  step.add_argument("--profile-top", type=int, default=0, help="sljax: top kernels of 3 steps")
  step.add_argument("--deadline", type=float, default=None,
                    help="seconds: children that would start later are skipped")
  for name, kind in (("--child", str), ("--net", str), ("--impl", str), ("--shape", str),
                     ("--precision", str), ("--t0", float)):
    ap.add_argument(name, type=kind, default=None, help=argparse.SUPPRESS)
  args = ap.parse_args()
  if args.child:
    child_main(args)
    return
  parts = args.part.split(",")
  if "step" in parts:
    step_part(args)
  if not {"agreement", "models"} & set(parts):
    return
  torch = None
  try:
    import torch as torch_module
    if torch_module.cuda.is_available():
      torch = torch_module
  except ImportError:
    pass
  print(machine(torch))
  t0 = time.perf_counter()

  if "agreement" in parts:
    agreement_part(args, torch)
  if "models" in parts:
    models_part(args, torch, t0)


if __name__ == "__main__":
  main()
