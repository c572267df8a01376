"""`sljax convert-psmnet CKPT OUT`: official PyTorch PSMNet weights -> an sljax model directory."""

import argparse

import numpy as np

from sljax.nets import registry
from sljax.nets import convert


def register(subparsers) -> None:
  """Adds the convert-psmnet subcommand."""
  p = subparsers.add_parser(
      "convert-psmnet",
      description="Converts a PyTorch PSMNet (stacked hourglass) checkpoint (a dict with "
      "'state_dict', keys may carry 'module.') to OUT/config.json + OUT/variables.npz, "
      "loadable for inference or as --init-from. Reading .tar/.pth files needs PyTorch "
      "(pip install \"sljax[torch]\"); an .npz of the state_dict needs nothing.")
  p.add_argument("ckpt", metavar="CKPT", help="PyTorch checkpoint (.tar/.pth) or .npz state_dict")
  p.add_argument("out", metavar="OUT", help="output directory")
  p.add_argument("--maxdisp", type=int, default=192,
                 help="maximum disparity stored in the model config (the released "
                 "checkpoints use 192; default %(default)s)")
  p.add_argument("--align-corners", action="store_true",
                 help="use PyTorch<0.4 align_corners=True interpolation (checkpoints "
                 "trained with old PyTorch)")
  p.add_argument("--overwrite", action="store_true", help="replace an existing conversion")
  p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
  """Converts and writes; prints a one-line summary."""
  registry.check_maxdisp(args.maxdisp, f"--maxdisp {args.maxdisp}")
  state_dict = convert.read_state_dict(args.ckpt)
  variables = convert.convert_state_dict(state_dict)
  in_channels = int(variables["params"]["feature_extraction"]["firstconv_0"]["conv"]["kernel"]
                    .shape[2])
  kwargs = {"maxdisp": args.maxdisp, "in_channels": in_channels}
  if args.align_corners:
    kwargs["align_corners"] = True
  out = convert.save_converted(args.out, variables, kwargs, overwrite=args.overwrite,
                               source=str(args.ckpt))
  n = sum(int(np.size(v)) for v in convert._flatten(variables["params"]).values())
  print(f"converted {args.ckpt}: PSMNet with {n:,} parameters -> {out}")
  return 0
