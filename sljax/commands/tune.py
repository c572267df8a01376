"""`sljax tune`: measure this CPU's kernel choices now and print the table."""

from __future__ import annotations

import argparse
import time

from sljax.errors import require
from sljax.nets.workload import gradient_workload, workload
from sljax.runtime import choices, machine, measuring


def register(subparsers) -> None:
  """Adds the `tune` subcommand."""
  p = subparsers.add_parser(
      "tune",
      description="Compiles PSMNet as a forward-only and as a training program with XLA:CPU's "
                  "YNNPACK fusions on and off, times them, then times the 3D layers' gradients "
                  "at the runs' shapes in each kernel-gradient block size under the chosen "
                  "training fusions; prints the tables and keeps the choices for this CPU kind "
                  "and jax version, where training (--ynn auto), inference and gradients traced "
                  "without a context find them. Without it they take the choice measured on this CPU "
                  "kind before (sljax.runtime.choices.KNOWN) or the default for kinds not measured yet; "
                  "SLJAX_TUNE=0 or --ynn on keeps XLA's defaults.")
  p.add_argument("--show", action="store_true",
                 help="print the measured choice and its table without measuring")
  p.add_argument("--repeats", type=int, default=5,
                 help="interleaved timing rounds (default 5)")
  p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
  """Measures (or shows) and prints the table."""
  require(args.repeats > 0, f"--repeats must be positive, got {args.repeats}")
  key, path = choices.measurement_key(), choices.measurements_path()
  print(f"{machine.cpu_description()}\nmeasurements: {path} [{key}]")
  if args.show:
    entry = choices.read_measurements().get(key)
    if entry is None:
      best, where = choices.known_choice()
      print(f"not measured on this machine: runs take {choices.describe(best)}, {where}; "
            "`sljax tune` measures it")
      return 0
    best = choices.entry_choice(entry)
    require(best is not None, f"{path}: the entry for {key} has no readable choice; run "
            "`sljax tune` to measure again")
    table = entry.get("table") if isinstance(entry.get("table"), list) else []
    others = entry.get("others")
    print(f"measured {entry.get('time', '?')} in {entry.get('seconds', '?')} s"
          f"{_beside(others)}\n\n{measuring.format_table(table, best)}\n\n"
          f"{_blocks(entry.get('grad_blocks'))}choice: {choices.describe(best)}")
    _notes(table, others)
    return 0
  t0 = time.perf_counter()
  best, table, others, blocks = measuring.tuned(workload, args.repeats, gradient_workload)
  seconds = time.perf_counter() - t0
  print(f"measured in {seconds:.0f} s{_beside(others)}\n\n{measuring.format_table(table, best)}\n\n"
        f"{_blocks(blocks)}choice: {choices.describe(best)}")
  _notes(table, others)
  try:
    choices.write_measurement(key, best, table, seconds, others=others, blocks=blocks)
  except OSError as e:
    print(f"not kept ({path}: {e.strerror or e})")
  return 0


def _blocks(blocks) -> str:
  """The block measurement's table and its choice, then a blank line ('' where none)."""
  table = measuring.format_blocks(blocks)
  if not table:
    return ""
  return (f"{table}\n\nkernel-gradient blocks: {blocks['values'] >> 10} Ki values in training "
          f"programs with the fusions {'on' if blocks['train_ynn'] else 'off'}\n")


def _beside(others) -> str:
  """', other processes using N% of the CPUs meanwhile' where it was recorded."""
  if not choices.is_share(others):
    return ""
  return f", other processes using {others:.0%} of the CPUs meanwhile"


def _notes(table: list[dict], others) -> None:
  """Prints why a choice may not be this machine's when idle."""
  for note in measuring.notes(table, others):
    print(note)
