"""`sljax train`: the same as `python train.py` (one parser, one runner: sljax.train.cli)."""

from __future__ import annotations

import argparse

from sljax.train import cli as train_cli


def register(subparsers) -> None:
  """Adds the `train` subcommand with every flag of train.py."""
  p = subparsers.add_parser("train",
      description=train_cli.DESCRIPTION)
  train_cli.add_arguments(p)
  p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
  """Trains; errors end with one line naming `sljax train`."""
  return train_cli.run(args, prog="sljax train")
