"""Speed of sljax's networks on this machine beside PyTorch: the reference PSMNet or stacks.

Prints the machine (CPU model, ISA flags, cores, jax / jaxlib / torch versions) and two
tables: per-layer 3D convolution micro benchmarks (sljax fast path, plain
lax.conv_general_dilated, PyTorch) and whole models (UNet, PSMNet, the multi-task twin) at
SIZE x SIZE, maxdisp 96, forward (evaluation mode) and forward+backward (training mode, the
paper's loss), with sljax/PyTorch time ratios. Times are the minimum over --repeats runs
after one warm-up (compilation excluded).

With --reference DIR (a local checkout of JiaRenChang/PSMNet, which the project neither
ships nor fetches) PSMNet is compared with the reference model itself, at batch 2 by
default (the reference cannot train at batch 1 on 256x256: its 64x64 SPP pool leaves one
value per channel for BatchNorm). Without it, and for the other models, the PyTorch side is
a stack written here with the same shapes and layer types, labelled "stack".

PyTorch is imported only here (pip install "sljax[torch]").

  python benchmarks/bench_nets.py                 # everything
  python benchmarks/bench_nets.py --part micro    # layers only
  python benchmarks/bench_nets.py --part micro --ynn off --grad-blocks 20   # another blocking
  python benchmarks/bench_nets.py --part models --models psmnet --reference ~/src/PSMNet
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from common import best_time, machine, peak_gflops, record  # first: puts this checkout's sljax on the path
from sljax import kernels as c3
from sljax.losses.disparity import PSMNET_OUTPUT_WEIGHTS, disparity_loss
from sljax.nets import build_model
from sljax.runtime import choices
from sljax.runtime.hugepages import reexec


# ------------------------------------------------------------------------- PyTorch stacks
def torch_models():
  """PyTorch modules with the shapes of sljax's models (imported lazily)."""
  import torch
  from torch import nn
  import torch.nn.functional as F

  def cbn2(cin, cout, k=3, s=1, p=1, d=1):
    return nn.Sequential(nn.Conv2d(cin, cout, k, s, p, d, bias=False), nn.BatchNorm2d(cout))

  def cbn3(cin, cout, s=1):
    return nn.Sequential(nn.Conv3d(cin, cout, 3, s, 1, bias=False), nn.BatchNorm3d(cout))

  def up3(cin, cout):
    return nn.Sequential(nn.ConvTranspose3d(cin, cout, 3, 2, 1, 1, bias=False),
                         nn.BatchNorm3d(cout))

  class Res(nn.Module):
    def __init__(self, cin, cout, s, d):
      super().__init__()
      self.a, self.b = cbn2(cin, cout, 3, s, d, d), cbn2(cout, cout, 3, 1, d, d)
      self.skip = cbn2(cin, cout, 1, s, 0) if (s != 1 or cin != cout) else None

    def forward(self, x):
      y = self.b(F.relu(self.a(x)))
      return y + (self.skip(x) if self.skip is not None else x)

  class Features(nn.Module):
    def __init__(self, cin):
      super().__init__()
      self.stem = nn.Sequential(cbn2(cin, 32, s=2), nn.ReLU(), cbn2(32, 32), nn.ReLU(),
                                cbn2(32, 32), nn.ReLU())
      stages, c = [], 32
      for cout, n, s, d in ((32, 3, 1, 1), (64, 16, 2, 1), (128, 3, 1, 1), (128, 3, 1, 2)):
        stages.append(nn.Sequential(*[Res(c if i == 0 else cout, cout, s if i == 0 else 1, d)
                                      for i in range(n)]))
        c = cout
      self.stages = nn.ModuleList(stages)
      self.pools = (64, 32, 16, 8)
      self.branches = nn.ModuleList([nn.Sequential(cbn2(128, 32, 1, 1, 0), nn.ReLU())
                                     for _ in self.pools])
      for b in self.branches:
        b.is_spp_branch = True
      self.fuse = nn.Sequential(cbn2(320, 128), nn.ReLU(), nn.Conv2d(128, 32, 1, bias=False))

    def forward(self, x):
      x = self.stem(x)
      x = self.stages[0](x)
      raw = self.stages[1](x)
      skip = self.stages[3](self.stages[2](raw))
      size = skip.shape[2:]
      pyr = [F.interpolate(b(F.avg_pool2d(skip, min(k, size[0]))), size=size, mode="bilinear")
             for k, b in zip(self.pools, self.branches)]
      return self.fuse(torch.cat([raw, skip] + pyr[::-1], 1))

  class Hourglass(nn.Module):
    def __init__(self):
      super().__init__()
      self.c1, self.c2 = cbn3(32, 64, 2), cbn3(64, 64)
      self.c3, self.c4 = cbn3(64, 64, 2), cbn3(64, 64)
      self.c5, self.c6 = up3(64, 64), up3(64, 32)

    def forward(self, x, pre_in, post_in):
      pre = self.c2(F.relu(self.c1(x)))
      pre = F.relu(pre + post_in) if post_in is not None else F.relu(pre)
      y = F.relu(self.c4(F.relu(self.c3(pre))))
      post = F.relu(self.c5(y) + (pre_in if pre_in is not None else pre))
      return self.c6(post), pre, post

  class Stack(nn.Module):
    def __init__(self):
      super().__init__()
      self.d0 = nn.Sequential(cbn3(64, 32), nn.ReLU(), cbn3(32, 32), nn.ReLU())
      self.d1 = nn.Sequential(cbn3(32, 32), nn.ReLU(), cbn3(32, 32))
      self.hg = nn.ModuleList([Hourglass() for _ in range(3)])

    def forward(self, cost):
      c0 = self.d0(cost)
      c0 = self.d1(c0) + c0
      o1, p1, q1 = self.hg[0](c0, None, None)
      o1 = o1 + c0
      o2, _, q2 = self.hg[1](o1, p1, q1)
      o2 = o2 + c0
      o3, _, _ = self.hg[2](o2, p1, q2)
      return o1, o2, o3 + c0

  def head():
    return nn.Sequential(cbn3(32, 32), nn.ReLU(), nn.Conv3d(32, 1, 3, 1, 1, bias=False))

  def volume(fl, fr, nd):
    w = fl.shape[-1]
    right = torch.stack([F.pad(fr, (d, 0))[..., :w] for d in range(nd)], 2)
    mask = (torch.arange(w)[None, :] >= torch.arange(nd)[:, None]).to(fl.dtype)
    return torch.cat([fl.unsqueeze(2).expand_as(right) * mask[:, None], right], 1)

  class PSM(nn.Module):
    def __init__(self, maxdisp, t=None):
      super().__init__()
      self.maxdisp = maxdisp
      self.features = Features(3)
      self.stack = Stack()
      self.heads = nn.ModuleList([head() for _ in range(3)])
      self.t = t
      if t is not None:
        self.sl_stack, self.sl_cbn = Stack(), cbn3(32, 32)
        self.sl_att = nn.Conv3d(32, 1, 3, 1, 1, bias=False)
        self.sl_up = nn.ModuleList([nn.Sequential(cbn2(33, 32), nn.ReLU()),
                                    nn.Sequential(cbn2(32, 32), nn.ReLU())])
        self.sl_out = nn.Conv2d(32, t, 1)

    def regress(self, c, h, w):
      c = F.interpolate(c, [self.maxdisp, h, w], mode="trilinear")[:, 0]
      d = torch.arange(self.maxdisp, dtype=c.dtype)[None, :, None, None]
      return (F.softmax(c, 1) * d).sum(1)

    def forward(self, left, right):
      h, w = left.shape[2:]
      cost = volume(self.features(left), self.features(right), self.maxdisp // 4)
      outs = self.stack(cost)
      costs, acc = [], 0
      for o, hd in zip(outs, self.heads):
        acc = hd(o) + acc
        costs.append(acc)
      preds = ([self.regress(c, h, w) for c in costs] if self.training
               else [self.regress(costs[-1], h, w)])
      res = {"disparities": preds}
      if self.t is not None:
        x = F.relu(self.sl_cbn(self.sl_stack(cost)[2]))
        p = F.softmax(self.sl_att(x), 2)
        nd = x.shape[2]
        ex = (p * torch.arange(nd, dtype=x.dtype)[None, None, :, None, None]).sum(2) / nd
        x = torch.cat([(p * x).sum(2), ex], 1)
        for size, up in zip(((h // 2, w // 2), (h, w)), self.sl_up):
          x = up(F.interpolate(x, size=size, mode="bilinear"))
        res["sl"] = self.sl_out(x)
      return res

  class UNet(nn.Module):
    def __init__(self, out, depth=4, base=32):
      super().__init__()
      dc = lambda i, o: nn.Sequential(cbn2(i, o), nn.ReLU(), cbn2(o, o), nn.ReLU())
      widths = [base * 2 ** i for i in range(depth + 1)]
      self.down = nn.ModuleList([dc(6 if i == 0 else widths[i - 1], widths[i])
                                 for i in range(depth)])
      self.mid = dc(widths[-2], widths[-1])
      self.ups = nn.ModuleList([nn.ConvTranspose2d(widths[i + 1], widths[i], 2, 2)
                                for i in range(depth)])
      self.upc = nn.ModuleList([dc(2 * widths[i], widths[i]) for i in range(depth)])
      self.out = nn.Conv2d(base, out, 1)

    def forward(self, left, right):
      x = torch.cat([left, right], 1)
      skips = []
      for d in self.down:
        x = d(x)
        skips.append(x)
        x = F.max_pool2d(x, 2)
      x = self.mid(x)
      for i in reversed(range(len(self.ups))):
        x = self.upc[i](torch.cat([skips[i], self.ups[i](x)], 1))
      return {"out": self.out(x)}

  return torch, PSM, UNet


def reference_psmnet(directory: str, maxdisp: int, keep_cuda: bool = False):
  """JiaRenChang/PSMNet's stackhourglass model, imported from a local copy (on the CPU its
  `.cuda()` calls are made no-ops; keep_cuda keeps them, for a GPU)."""
  import torch
  path = Path(directory).expanduser()
  if not (path / "models" / "stackhourglass.py").is_file():
    raise SystemExit(f"{directory}: no models/stackhourglass.py here; --reference takes a "
                     "checkout of JiaRenChang/PSMNet")
  import warnings
  warnings.filterwarnings("ignore", message=".*upsample.*")  # deprecated, used by the reference
  if not keep_cuda:
    torch.Tensor.cuda = lambda self, *a, **k: self  # the reference moves its buffers by hand
  sys.path.insert(0, str(path))
  from models.stackhourglass import PSMNet
  return PSMNet(maxdisp)


def inputs(batch: int, size: int, maxdisp: int):
  """Random left, right (NHWC) and ground truth with some values beyond maxdisp (masked)."""
  rng = np.random.RandomState(0)
  left, right = (rng.rand(batch, size, size, 3).astype(np.float32) for _ in range(2))
  return left, right, (rng.rand(batch, size, size) * maxdisp * 1.1).astype(np.float32)


def torch_loss(out, gt, maxdisp):
  """The paper's loss (disparity_loss: weighted masked L2) plus the mean of other outputs."""
  if isinstance(out, (tuple, list)):  # the reference returns its three predictions
    out = {"disparities": list(out)}
  mask = (gt >= 0) & (gt < maxdisp)
  total = 0.0
  for w, p in zip(PSMNET_OUTPUT_WEIGHTS, out.get("disparities", [])):
    p = p.reshape(gt.shape)  # the reference's are [B, 1, H, W]
    total = total + w * (p[mask] - gt[mask]).pow(2).mean()
  for k, v in out.items():
    if k != "disparities":
      total = total + v.mean()
  return total


def torch_time(torch, model, batch, size, maxdisp, repeats, train):
  """PyTorch forward (eval, no grad) or forward+backward (train) time."""
  left, right, gt = inputs(batch, size, maxdisp)
  left, right = (torch.tensor(a.transpose(0, 3, 1, 2).copy()) for a in (left, right))
  gt = torch.tensor(gt)
  if not train:
    model.eval()

    def fwd():
      with torch.no_grad():
        model(left, right)
    return best_time(fwd, repeats)
  model.train()
  # PyTorch refuses batch statistics over one value (the 1x1 map of the 64x64 SPP pool at
  # batch 1); the stacks' tiny BN layers then run with running statistics (negligible time).
  for m in model.modules():
    if batch == 1 and getattr(m, "is_spp_branch", False):
      m.eval()

  def step():
    model.zero_grad(set_to_none=True)
    torch_loss(model(left, right), gt, maxdisp).backward()
  return best_time(step, repeats)


def jax_loss(out, gt, maxdisp):
  """torch_loss's twin: disparity_loss on the training outputs plus the mean of the others."""
  total = disparity_loss(out["disparities"], gt, maxdisp) if "disparities" in out else 0.0
  for k, v in out.items():
    if k == "disparities" or (k == "disparity" and "disparities" in out):
      continue
    for a in (v if isinstance(v, tuple) else (v,)):
      total = total + jnp.mean(a)
  return total


def jax_time(name, batch, size, maxdisp, repeats, train, impl=None, kernels=choices.DEFAULT):
  """sljax forward (eval) or forward+backward (train) time; impl: the model's conv_impl,
  kernels: the compiler choice (sljax.runtime.choices) of the program kind."""
  options = kernels.compiler_options("train" if train else "forward")
  model = build_model(name, maxdisp=maxdisp, conv_impl=impl)
  left, right, gt = (jnp.asarray(a) for a in inputs(batch, size, maxdisp))
  variables = jax.jit(model.init)(jax.random.PRNGKey(0), left[:1], right[:1])
  if not train:
    f = jax.jit(lambda v, l, r: model.apply(v, l, r, train=False), compiler_options=options)
    return best_time(lambda: jax.block_until_ready(f(variables, left, right)), repeats)

  def loss(params, l, r, g):
    out, _ = model.apply({**variables, "params": params}, l, r, train=True,
                         mutable=["batch_stats"])
    return jax_loss(out, g, maxdisp)

  def grads(params, l, r, g):  # the gradient blocks training takes with these options
    with c3.grad_blocks(choices.grad_blocks_for(kernels)):
      return jax.grad(loss)(params, l, r, g)
  g = jax.jit(grads, compiler_options=options)
  return best_time(lambda: jax.block_until_ready(g(variables["params"], left, right, gt)),
                   repeats)


# ------------------------------------------------------------------------- micro benchmarks
MICRO = [  # (label, kind, D, H, W, cin, cout, stride) at 256x256, maxdisp 96 (1/4 resolution)
    ("dres0 conv 64->32", "conv", 24, 64, 64, 64, 32, 1),
    ("conv 32->32", "conv", 24, 64, 64, 32, 32, 1),
    ("classifier 32->1", "conv", 24, 64, 64, 32, 1, 1),
    ("hg conv1 32->64 s2", "conv", 24, 64, 64, 32, 64, 2),
    ("hg conv2 64->64 (1/8)", "conv", 12, 32, 32, 64, 64, 1),
    ("hg conv3 64->64 s2", "conv", 12, 32, 32, 64, 64, 2),
    ("hg conv5 T 64->64", "convT", 6, 16, 16, 64, 64, 2),
    ("hg conv6 T 64->32", "convT", 12, 32, 32, 64, 32, 2),
]


def micro(repeats, with_lax, grad_blocks=None, options=None):
  """Per-layer table: fast / lax / torch, forward and forward+backward (ms); grad_blocks: the
  kernel gradients' blocks (None: the layers'), options: XLA's compiler options."""
  import torch
  import torch.nn.functional as F
  rows = []
  rng = np.random.RandomState(0)
  for label, kind, d, h, w, cin, cout, s in MICRO:
    x = jnp.asarray(rng.randn(1, d, h, w, cin).astype(np.float32))
    k = jnp.asarray(rng.randn(3, 3, 3, cin, cout).astype(np.float32) * 0.05)
    res = {}
    for impl in ("fast", "lax") if with_lax else ("fast",):
      if kind == "conv":
        f = lambda x, k, impl=impl: c3.conv3d(x, k, (s,) * 3, ((1, 1),) * 3, impl=impl)
      else:
        f = lambda x, k, impl=impl: c3.conv_transpose3d(
            x, k, (2, 2, 2), c3.transpose_padding((3, 3, 3), 1, 1), impl=impl)
      def grads(x, k, f=f):
        with c3.grad_blocks(grad_blocks):
          return jax.grad(lambda x, k: jnp.sum(f(x, k) ** 2), argnums=(0, 1))(x, k)
      fj, gj = jax.jit(f, compiler_options=options), jax.jit(grads, compiler_options=options)
      res[impl] = (best_time(lambda: jax.block_until_ready(fj(x, k)), repeats),
                   best_time(lambda: jax.block_until_ready(gj(x, k)), repeats))
    xt = torch.tensor(np.asarray(x).transpose(0, 4, 1, 2, 3).copy(), requires_grad=True)
    if kind == "conv":
      kt = torch.tensor(np.asarray(k).transpose(4, 3, 0, 1, 2).copy(), requires_grad=True)
      tf = lambda: F.conv3d(xt, kt, stride=s, padding=1)
    else:
      kt = torch.tensor(np.asarray(k).transpose(3, 4, 0, 1, 2).copy(), requires_grad=True)
      tf = lambda: F.conv_transpose3d(xt, kt, stride=2, padding=1, output_padding=1)

    def tfb():
      xt.grad = kt.grad = None
      (tf() ** 2).sum().backward()
    with torch.no_grad():
      t_f = best_time(tf, repeats)
    res["torch"] = (t_f, best_time(tfb, repeats))
    rows.append((label, res))
    print_micro_row(label, res, with_lax)
  peak, how = peak_gflops()
  print(f"\nachieved fp32 GFLOP/s (fwd, fwd+bwd; backward = 2 forwards' FLOPs) against the "
        f"nominal peak {peak:.0f} GFLOP/s ({how})")
  print("| layer | sljax fwd | sljax fwd+bwd | torch fwd | torch fwd+bwd | sljax share of peak |")
  print("| --- | ---: | ---: | ---: | ---: | ---: |")
  out = []
  for (label, r), spec in zip(rows, MICRO):
    flops = layer_flops(*spec[1:])
    g = [flops * m / t / 1e9 for m, t in ((1, r["fast"][0]), (3, r["fast"][1]),
                                          (1, r["torch"][0]), (3, r["torch"][1]))]
    print(f"| {label} | {g[0]:.0f} | {g[1]:.0f} | {g[2]:.0f} | {g[3]:.0f} | "
          f"{g[0] / peak:.0%} / {g[1] / peak:.0%} |")
    out.append({"table": "micro", "layer": label, "ynn": "off" if options else "on",
                "grad_blocks": grad_blocks, "fwd_s": r["fast"][0],
                "fwd_bwd_s": r["fast"][1], "torch_fwd_s": r["torch"][0],
                "torch_fwd_bwd_s": r["torch"][1], "gflop": flops / 1e9,
                "sljax_fwd_gflops": g[0], "sljax_fwd_bwd_gflops": g[1],
                "torch_fwd_gflops": g[2], "torch_fwd_bwd_gflops": g[3], "peak_gflops": peak})
  return out


def layer_flops(kind, d, h, w, cin, cout, s) -> float:
  """Multiply-adds x 2 of a 3x3x3 layer at batch 1: a convolution's output voxels, or a
  transposed convolution's input voxels (each scattered to 27 outputs), x 27 x cin x cout."""
  voxels = d * h * w if kind == "convT" else (d // s) * (h // s) * (w // s)
  return 2.0 * 27 * cin * cout * voxels


def print_micro_row(label, res, with_lax):
  """One line of the micro table."""
  tf, tb = res["torch"]
  cells = [f"{label:24s}"]
  for impl in ("fast", "lax") if with_lax else ("fast",):
    a, b = res[impl]
    cells.append(f"{impl} {a * 1e3:7.1f} {b * 1e3:7.1f} ({a / tf:4.2f}x {b / tb:4.2f}x)")
  cells.append(f"torch {tf * 1e3:7.1f} {tb * 1e3:7.1f}")
  print(" | ".join(cells), flush=True)


def main() -> None:
  """Runs the selected parts and prints the tables."""
  reexec()  # as sljax's commands run: malloc with huge pages (sljax/runtime/hugepages.py)
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--part", choices=("all", "micro", "models"), default="all")
  ap.add_argument("--models", default="unet-sl,psmnet,psmnet-mtl")
  ap.add_argument("--size", type=int, default=256)
  ap.add_argument("--maxdisp", type=int, default=96)
  ap.add_argument("--batch", type=int, default=None,
                  help="batch size of the model table (default: 2 with --reference, else 1)")
  ap.add_argument("--repeats", type=int, default=3)
  ap.add_argument("--reference", metavar="DIR", default=None,
                  help="local checkout of JiaRenChang/PSMNet: compare psmnet with it")
  ap.add_argument("--with-lax", action="store_true",
                  help="also time the plain lax 3D convolution (slow: minutes)")
  ap.add_argument("--ynn", choices=("on", "off"), default=None,
                  help="micro: XLA's YNNPACK fusions (default: XLA's, i.e. on)")
  ap.add_argument("--grad-blocks", type=int, default=None, metavar="LOG2",
                  help="micro: kernel gradients in blocks of 2**LOG2 values (default: the "
                       "layers' BLOCK_VALUES); the models take the table's (sljax.runtime.choices)")
  args = ap.parse_args()
  batch = args.batch or (2 if args.reference else 1)
  import torch
  print(machine(torch))
  print(f"conv3d auto -> {c3.conv_impl()}; times: minimum of {args.repeats} after a warm-up")
  # What training and inference use on this CPU (sljax tune; measured once and cached): a
  # program kind whose choice differs from XLA's default gets a "tuned" column too.
  kernels = choices.choice()
  print(f"this CPU's tuned compiler choice: --ynn {kernels.name}")
  records = []
  if args.part in ("all", "micro"):
    print(f"\n3D convolution layers, {args.size}x{args.size} maxdisp {args.maxdisp} shapes: "
          "fwd ms, fwd+bwd ms (ratio to torch)")
    records += micro(args.repeats, args.with_lax,
                     None if args.grad_blocks is None else 1 << args.grad_blocks,
                     choices.YNN_OFF if args.ynn == "off" else None)
  if args.part in ("all", "models"):
    torch_, PSM, UNet = torch_models()
    torch_.manual_seed(0)
    stacks = {"unet-sl": lambda: UNet(16), "unet-disp": lambda: UNet(1),
              "psmnet": lambda: PSM(args.maxdisp), "psmnet-mtl": lambda: PSM(args.maxdisp, 8)}
    print(f"\nModels at {args.size}x{args.size}, maxdisp {args.maxdisp}, batch {batch} "
          "(seconds; ratio = sljax / PyTorch)")
    print("sljax s: with this CPU's tuned compiler choice (records keep XLA's default too)")
    print("| model | mode | PyTorch side | sljax s | PyTorch s | ratio |"
          + (" lax s | ratio |" if args.with_lax else ""))
    print("| --- | --- | --- | ---: | ---: | ---: |" + (" ---: | ---: |" if args.with_lax else ""))
    for name in args.models.split(","):
      if name == "psmnet" and args.reference:
        side, tm = "reference", reference_psmnet(args.reference, args.maxdisp)
      else:
        side, tm = "stack", stacks[name]()
      for train in (False, True):
        mode = "fwd+bwd" if train else "fwd"
        kind = "train" if train else "forward"
        tj = jax_time(name, batch, args.size, args.maxdisp, args.repeats, train)
        tt = torch_time(torch_, tm, batch, args.size, args.maxdisp, args.repeats, train)
        row = {"table": "models", "model": name, "mode": mode, "torch_side": side,
               "size": args.size, "maxdisp": args.maxdisp, "batch": batch,
               "sljax_s": tj, "torch_s": tt, "ratio": tj / tt, "ynn": "on"}
        if kernels.compiler_options(kind) is not None:  # the tuned choice is what users get
          tu = jax_time(name, batch, args.size, args.maxdisp, args.repeats, train,
                        kernels=kernels)
          row.update(sljax_default_s=tj, ratio_default=tj / tt, sljax_s=tu, ratio=tu / tt,
                     ynn=kernels.name)
        line = (f"| {name} | {mode} | {side} | {row['sljax_s']:.2f} | {tt:.2f} | "
                f"{row['ratio']:.2f}x |")
        if args.with_lax and name.startswith("psmnet"):
          tl = jax_time(name, batch, args.size, args.maxdisp, max(1, args.repeats - 2), train,
                        "lax")
          line += f" {tl:.2f} | {tl / tt:.2f}x |"
          row["lax_s"] = tl
        print(line, flush=True)
        records.append(row)
  record("bench_nets", records, torch)


if __name__ == "__main__":
  main()
