"""`sljax summary`: parameter counts per part and output shapes of a network."""

from __future__ import annotations

import argparse

from sljax.errors import require
from sljax.nets.registry import NAMES
from sljax.nets.summary import format_summary, param_summary


def register(subparsers) -> None:
  """Adds the `summary` subcommand."""
  p = subparsers.add_parser(
      "summary",
      description="Prints the parameter counts per part (features, cost aggregation, disparity "
                  "path, SL path, total) and the output shapes for an input size, without "
                  "running the network.")
  p.add_argument("--model", required=True, choices=NAMES, help="network name")
  p.add_argument("--size", nargs=2, type=int, default=(256, 256), metavar=("H", "W"),
                 help="input height and width (default 256 256)")
  p.add_argument("--maxdisp", type=int, default=96, help="PSMNet disparity range (default 96)")
  p.add_argument("--t", type=int, default=8, help="number of patterns (default 8)")
  p.add_argument("--gray", action="store_true", help="one channel per view instead of RGB")
  p.add_argument("--batch", type=int, default=1, help="batch size (default 1)")
  p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
  """Prints the summary table."""
  h, w = args.size
  require(h > 0 and w > 0, f"--size must be positive, got {h} {w}")
  require(args.batch > 0, f"--batch must be positive, got {args.batch}")
  s = param_summary(args.model, size=(h, w), batch=args.batch, maxdisp=args.maxdisp, t=args.t,
                    gray=args.gray)
  print(format_summary(s))
  return 0
