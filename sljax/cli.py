"""The `sljax` command line: a table of subcommands, each a module of sljax/commands.

Only the module of the command being run is imported (the listing of `sljax --help` comes
from the table), so a command pays only for its own imports; each module imports what it
needs at its top.
"""

import argparse
import importlib
import sys

from sljax.errors import run_command
from sljax.runtime.hugepages import reexec
from sljax.runtime.quiet import quiet_libraries

# subcommand -> (module in sljax.commands, one line for `sljax --help`)
COMMANDS = {
    "convert-psmnet": ("convert_psmnet", "convert an official PyTorch PSMNet checkpoint to sljax"),
    "decode": ("decode", "decode raw structured-light captures into pattern maps and disparity"),
    "evaluate": ("evaluate", "evaluate a checkpoint (or the SGBM baseline) on a dataset"),
    "experiment": ("experiment",
                     "run the grids behind the paper's tables, resumably, and report them"),
    "export": ("export", "write a deployable file (serialised StableHLO) of a trained model"),
    "import-captures": ("import_captures",
                        "rectify, decode and match a stereo rig's Gray-code capture into a scene"),
    "import-scared": ("import_scared", "convert a SCARED keyframe into a scene folder"),
    "info": ("info", "summarise a dataset folder"),
    "make-data": ("make_data", "render a synthetic stereo + structured-light dataset"),
    "plot-runs": ("plot_runs", "plot validation MAE against epoch for several training runs"),
    "predict": ("predict",
                  "predict disparity, depth (mm) and a coloured point cloud for stereo pairs"),
    "show": ("show", "write a contact sheet PNG of a scene"),
    "summary": ("summary", "parameter counts and output shapes of a network"),
    "train": ("train", "train a network (the same as python train.py)"),
    "tune": ("tune", "choose this CPU's faster XLA compiler settings by measurement (cached)"),
    "uncertainty": ("uncertainty", "correlate pattern uncertainty with disparity error"),
}


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
  """The parser: the command named in argv gets its module's full subparser (imported now),
  every other command a stub that only lists it."""
  parser = argparse.ArgumentParser(
      prog="sljax",
      description="Stereo disparity regularised by structured-light reconstruction.")
  sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
  chosen = next((a for a in argv or [] if not a.startswith("-")), None)
  for name, (module, text) in COMMANDS.items():
    if name == chosen:
      importlib.import_module(f"sljax.commands.{module}").register(sub)
    else:
      sub.add_parser(name, help=text, add_help=False)
  return parser


def main(argv: list[str] | None = None) -> int:
  """Entry point: runs a subcommand; bad input ends with one line on stderr and exit 2."""
  if argv is None:  # the command line itself: start again with huge pages where that helps
    reexec()
    argv = sys.argv[1:]
  if argv[:1] == ["train"]:  # as train.py: the last such launch's step loads while train imports
    from sljax.runtime.compile_cache import load_last_programs  # pylint: disable=import-outside-toplevel
    load_last_programs(argv[1:])
  args = build_parser(argv).parse_args(argv)
  quiet_libraries()
  # Imported here, at the command-line edge, so that `sljax --help` does not import jax.
  from sljax.runtime.compile_cache import enable_compile_cache  # pylint: disable=import-outside-toplevel
  enable_compile_cache(programs=True)
  code, result = run_command(f"sljax {args.command}", lambda: args.func(args),
                             quiet_broken_pipe=True)
  if code:
    return code
  return int(result or 0)


if __name__ == "__main__":
  sys.exit(main())
