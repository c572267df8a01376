"""Command line of training (`python train.py` and `sljax train`, one parser and one runner):
presets, one flag per TrainConfig field, clear errors."""

import argparse
import dataclasses
from pathlib import Path

import jax

from sljax.errors import SljaxError, run_command
from sljax.models import checkpoint as ckpt
from sljax.models import load as trained
from sljax.runtime.compile_cache import enable_compile_cache
from sljax.runtime.quiet import quiet_libraries
from sljax.train.config import FIELDS, PRESETS, TrainConfig, config_from_json, preset_config
from sljax.train.loop import train
from sljax.train.workdir import check_config_kept, default_workdir


def add_config_flags(parser: argparse.ArgumentParser) -> None:
  """One flag per TrainConfig field (help, parser and choices from the field); every flag
  defaults to None, meaning the preset's value."""
  for name, f in FIELDS.items():
    meta = f.metadata
    if not meta["flag"]:
      continue
    if meta["switch"]:
      group = parser.add_mutually_exclusive_group()
      for (flag, text), value in zip(meta["switch"], (True, False)):
        group.add_argument(flag, dest=name, action="store_const", const=value, default=None,
                           help=text)
      continue
    kw = {"choices": meta["choices"]} if meta["choices"] else {"type": meta["parse"]}
    parser.add_argument(f"--{name.replace('_', '-')}", dest=name, default=None,
                        help=meta["help"], **kw)


DESCRIPTION = ("Train PSMNet (stl), the PSMNet+SL twin (cg_a, cg_b, epr, unc) or the UNets. "
               "With no flags: the 'auto' preset (paper settings on an accelerator, a quick CPU "
               "run otherwise) on synthetic 'objects' scenes rendered on the fly. Flags left out "
               "take the preset's value.")


def build_parser(prog: str = "train.py") -> argparse.ArgumentParser:
  """The training argument parser (train.py's; `sljax train` adds the same arguments)."""
  p = argparse.ArgumentParser(prog=prog, description=DESCRIPTION)
  add_arguments(p)
  return p


def add_arguments(p: argparse.ArgumentParser) -> None:
  """Every training flag: one per TrainConfig field, then the run's own options."""
  add_config_flags(p)
  p.add_argument("--workdir", default=None,
                 help="run folder (default runs/<model>-<strategy>-<seed>)")
  start = p.add_mutually_exclusive_group()
  start.add_argument("--resume", action="store_true",
                     help="continue the run in --workdir from its last checkpoint (its saved "
                     "config is used; flags given must agree). Refused when --workdir holds no "
                     "run (no config.json); a run stopped before its first checkpoint starts "
                     "again from step 0, and says so")
  start.add_argument("--overwrite", action="store_true", help="replace a run in --workdir")
  # A run option, not a TrainConfig field: saved in config.json it would skip damaged
  # checkpoints on every later --resume, unasked.
  p.add_argument("--resume-skip-damaged", action="store_true",
                 help="with --resume: when the newest checkpoint is damaged (its bytes differ "
                 "from those written), move it aside to WORKDIR/checkpoints/N.damaged and "
                 "resume from the newest intact one, saying so; without it, a damaged "
                 "checkpoint stops the run with one line naming it")
  p.add_argument("--preset", choices=PRESETS, default="auto",
                 help="auto (default): paper with an accelerator, quick on CPU only; "
                 "paper: SPEC defaults (256x256, maxdisp 96, 120 epochs, Adam 1e-4); "
                 "quick: < 10 min on a 2-core CPU")
  p.add_argument("--distributed", action="store_true",
                 help="multi-host: call jax.distributed.initialize() first (cluster settings "
                 "from the environment, e.g. SLURM or JAX_COORDINATOR_ADDRESS/...)")
  p.add_argument("--stop-after", type=int, default=None,
                 help="stop after this global step (a clean interruption; --resume continues)")
  p.add_argument("--profile", default=None, metavar="DIR",
                 help="write a jax.profiler trace of a few steps after compilation to DIR")
  p.add_argument("--no-progress", action="store_true", help="no progress bar")


def resolve(args: argparse.Namespace, backend: str) -> tuple[TrainConfig, str, Path]:
  """(config, preset note, workdir): preset, or the saved config on --resume, then flags."""
  given = {k: getattr(args, k) for k, f in FIELDS.items()
           if f.metadata["flag"] and getattr(args, k) is not None}
  base = preset_config(args.preset, backend)
  note = ""
  if args.preset == "auto":
    note = (" (auto: no accelerator found)" if backend == "cpu"
            else f" (auto: {backend} accelerator found)")
  config = dataclasses.replace(base, **given)
  workdir = Path(args.workdir) if args.workdir else default_workdir(config)
  if args.resume:
    saved = config_from_json(saved_config(workdir), str(workdir / ckpt.CONFIG_FILE))
    config = dataclasses.replace(saved, **given)
    if "data" not in given:
      check_saved_data(workdir, config.data)
    note = " (resumed run)"
  return config, note, workdir


def saved_config(workdir: Path) -> dict:
  """The config.json of the run a --resume continues; SljaxError when there is none (a typo in
  --workdir must not start a new run, and checkpoints without their config cannot be loaded
  into the right model)."""
  check_config_kept(workdir)
  if not (workdir / ckpt.CONFIG_FILE).is_file():
    what = "does not exist" if not workdir.exists() else f"holds no run (no {ckpt.CONFIG_FILE})"
    raise SljaxError(f"--resume: {workdir} {what}; nothing to resume (check --workdir, or "
                     "leave out --resume to start a new run)")
  return trained.read_config(workdir)


def check_saved_data(workdir: Path, data: str | None) -> None:
  """A resumed run's saved --data must be found from here: runs before data paths were
  recorded absolute saved the path as typed, relative to the folder they started in."""
  if data is None or Path(data).exists():
    return
  if Path(data).is_absolute():
    raise SljaxError(f"{workdir}: the run's data {data!r} does not exist; pass --data with the "
                     "data folder's path")
  raise SljaxError(f"{workdir}: the run's data {data!r} was relative to the folder the run "
                   f"started in, and {Path(data).absolute()} does not exist from here; run from "
                   "that folder or pass --data with the data folder's path")


def _resume_hint(args: argparse.Namespace) -> str:
  """' (continue with --resume)' where the interrupted run left a config.json to resume (a run
  stopped before its checks passed wrote nothing, and --resume would refuse it)."""
  workdir = getattr(args, "workdir", None)
  if workdir is None or (Path(workdir) / ckpt.CONFIG_FILE).is_file():
    return " (continue with --resume)"
  return " before the run started; nothing was saved"


def main(argv: list[str] | None = None) -> int:
  """Entry point of train.py; SljaxError -> one line on stderr and exit code 2."""
  return run(build_parser().parse_args(argv))


def run(args: argparse.Namespace, prog: str = "train.py") -> int:
  """Trains as the parsed arguments say (train.py and `sljax train`); errors end with one line
  on stderr naming `prog` (errors.run_command)."""

  def start():
    if args.distributed:
      # Cross-process collectives on CPU need gloo (GPUs and TPUs bring their own).
      jax.config.update("jax_cpu_collectives_implementation", "gloo")
      jax.distributed.initialize()
    if args.resume_skip_damaged and not args.resume:
      raise SljaxError("--resume-skip-damaged: only with --resume (it says which checkpoint a "
                       "resume may skip)")
    quiet_libraries()
    enable_compile_cache(programs=True)
    config, note, workdir = resolve(args, jax.default_backend())
    return train(config, workdir, resume=args.resume, overwrite=args.overwrite,
                 stop_after=args.stop_after, preset_note=note, profile_dir=args.profile,
                 log=lambda line: print(line, flush=True),
                 progress=False if args.no_progress else None,
                 skip_damaged=args.resume_skip_damaged)

  code, result = run_command(prog, start, lambda: _resume_hint(args))
  if code or result is None:
    return code
  best = "n/a" if result.best_val is None else f"{result.best_val:.4f}"
  last = "n/a" if result.last_val is None else f"{result.last_val:.4f}"
  print(f"done: step {result.step}, {result.epochs_done} epochs; val MAE last {last}, best "
        f"{best}; workdir {result.workdir}")
  return 0
