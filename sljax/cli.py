"""The `sljax` command line: one subcommand per module in sljax/commands."""

import argparse
import importlib
import os
import pkgutil
import sys

from sljax import commands
from sljax.errors import SljaxError, quiet_libraries


def build_parser() -> argparse.ArgumentParser:
  """Builds the parser; every module in sljax.commands contributes one subcommand."""
  parser = argparse.ArgumentParser(
      prog="sljax",
      description="Stereo disparity regularised by structured-light reconstruction.")
  sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
  for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
    module = importlib.import_module(f"sljax.commands.{info.name}")
    module.register(sub)
  return parser


def main(argv: list[str] | None = None) -> int:
  """Entry point: runs a subcommand; bad input ends with one line on stderr and exit 2."""
  args = build_parser().parse_args(argv)
  quiet_libraries()
  try:
    result = args.func(args)
  except SljaxError as e:
    print(f"sljax {args.command}: error: {e}", file=sys.stderr)
    return 2
  except BrokenPipeError:
    # `sljax info DATA | head`: the reader went away; stop quietly like other Unix tools.
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0
  except KeyboardInterrupt:
    print(f"sljax {args.command}: interrupted", file=sys.stderr)
    return 130
  return int(result or 0)


if __name__ == "__main__":
  sys.exit(main())
