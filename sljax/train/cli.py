"""Command line of train.py: presets, flags that override them, clear errors."""

import argparse
import dataclasses
import sys
from pathlib import Path

from sljax.errors import SljaxError
from sljax.losses.disparity import DISP_LOSSES
from sljax.losses.weighting import STRATEGIES
from sljax.train.config import MODELS, PRESETS, TrainConfig

# CLI flag dest -> TrainConfig field, for the flags that override a preset.
_OVERRIDES = ("model", "strategy", "data", "fraction", "epochs", "batch_size", "lr", "size",
              "maxdisp", "seed", "disp_loss", "gray", "val_every", "save_every", "keep",
              "max_val", "init_from", "synth_n", "synth_size", "test_fraction", "unet_depth",
              "unet_width")


def parse_size(text: str) -> tuple[int, int]:
  """'256' -> (256, 256); '96x128' -> (96, 128) (height x width)."""
  try:
    parts = [int(p) for p in text.lower().split("x")]
  except ValueError:
    raise argparse.ArgumentTypeError(f"expected N or HEIGHTxWIDTH, got {text!r}") from None
  if len(parts) == 1:
    parts = parts * 2
  if len(parts) != 2:
    raise argparse.ArgumentTypeError(f"expected N or HEIGHTxWIDTH, got {text!r}")
  return parts[0], parts[1]


def build_parser() -> argparse.ArgumentParser:
  """The train.py argument parser; preset-overriding flags default to None (= preset value)."""
  p = argparse.ArgumentParser(
      prog="train.py",
      description="Train PSMNet (stl), the PSMNet+SL twin (cg_a, cg_b, epr, unc) or the UNets. "
      "With no flags: the 'auto' preset (paper settings on an accelerator, a quick CPU run "
      "otherwise) on synthetic 'objects' scenes rendered on the fly.")
  p.add_argument("--strategy", choices=STRATEGIES, default=None,
                 help="loss weighting (PSMNet): stl = plain PSMNet; cg_a/cg_b/epr/unc = the twin "
                 "with the SL path (default stl)")
  p.add_argument("--model", choices=MODELS, default=None, help="network (default psmnet)")
  p.add_argument("--data", default=None,
                 help="scene-format folder (default: synthetic 'objects' scenes on the fly)")
  p.add_argument("--fraction", default=None, help="fraction of the training split, e.g. 1/16")
  p.add_argument("--epochs", type=int, default=None)
  p.add_argument("--batch-size", type=int, default=None, help="global batch (all devices)")
  p.add_argument("--lr", type=float, default=None, help="Adam learning rate")
  p.add_argument("--size", type=parse_size, default=None,
                 help="training size N or HEIGHTxWIDTH (multiples of 16)")
  p.add_argument("--maxdisp", type=int, default=None, help="PSMNet disparity range (multiple of 16)")
  p.add_argument("--seed", type=int, default=None)
  p.add_argument("--disp-loss", choices=DISP_LOSSES, default=None,
                 help="l2 (paper, default) or smooth_l1 (reference PSMNet)")
  gray = p.add_mutually_exclusive_group()
  gray.add_argument("--gray", dest="gray", action="store_const", const=True, default=None,
                    help="grayscale inputs (default for the UNets)")
  gray.add_argument("--rgb", dest="gray", action="store_const", const=False,
                    help="RGB inputs (default for PSMNet)")
  p.add_argument("--val-every", type=int, default=None, help="epochs between validations")
  p.add_argument("--save-every", type=int, default=None,
                 help="also checkpoint every N steps (default: at each epoch end only)")
  p.add_argument("--keep", type=int, default=None,
                 help="checkpoints kept (the last N, plus the best by validation MAE)")
  p.add_argument("--max-val", type=int, default=None, help="cap on validation scenes")
  p.add_argument("--synth-n", type=int, default=None, help="synthetic scenes (train + val)")
  p.add_argument("--synth-size", type=int, default=None, help="synthetic render size")
  p.add_argument("--test-fraction", type=float, default=None, help="held-out group fraction")
  p.add_argument("--unet-depth", type=int, default=None, help="UNet levels (default 4)")
  p.add_argument("--unet-width", type=int, default=None,
                 help="UNet channels at the first level (default 32)")
  p.add_argument("--init-from", default=None,
                 help="start from a training workdir or a converted PSMNet (sljax.nets.convert)")
  p.add_argument("--workdir", default=None,
                 help="run folder (default runs/<model>-<strategy>-<seed>)")
  p.add_argument("--resume", action="store_true",
                 help="continue the run in --workdir from its last checkpoint (its saved "
                 "config is used; flags given must agree)")
  p.add_argument("--overwrite", action="store_true", help="replace a run in --workdir")
  p.add_argument("--preset", choices=PRESETS, default="auto",
                 help="auto (default): paper with an accelerator, quick on CPU only; "
                 "paper: SPEC defaults (256x256, maxdisp 96, 120 epochs, Adam 1e-4); "
                 "quick: < 10 min on a 2-core CPU")
  p.add_argument("--distributed", action="store_true",
                 help="multi-host: call jax.distributed.initialize() first (cluster settings "
                 "from the environment, e.g. SLURM or JAX_COORDINATOR_ADDRESS/...)")
  p.add_argument("--stop-after", type=int, default=None,
                 help="stop after this global step (a clean interruption; --resume continues)")
  p.add_argument("--no-progress", action="store_true", help="no progress bar")
  return p


def resolve(args: argparse.Namespace, backend: str) -> tuple[TrainConfig, str, Path]:
  """(config, preset note, workdir): preset, or the saved config on --resume, then flags."""
  # pylint: disable=import-outside-toplevel
  from sljax.train import checkpoint as ckpt
  from sljax.train.config import config_from_json, preset_config
  from sljax.train.loop import default_workdir
  given = {k: getattr(args, k) for k in _OVERRIDES if getattr(args, k) is not None}
  base = preset_config(args.preset, backend)
  note = ""
  if args.preset == "auto":
    note = (" (auto: no accelerator found)" if backend == "cpu"
            else f" (auto: {backend} accelerator found)")
  config = dataclasses.replace(base, **given)
  workdir = Path(args.workdir) if args.workdir else default_workdir(config)
  if args.resume and (workdir / ckpt.CONFIG_FILE).exists():
    saved = config_from_json(ckpt.read_config(workdir))
    config = dataclasses.replace(saved, **given)
    note = " (resumed run)"
  return config, note, workdir


def main(argv: list[str] | None = None) -> int:
  """Entry point of train.py; SljaxError -> one line on stderr and exit code 2."""
  args = build_parser().parse_args(argv)
  try:
    if args.distributed:
      import jax  # pylint: disable=import-outside-toplevel
      jax.distributed.initialize()
    import jax  # pylint: disable=import-outside-toplevel,reimported
    from absl import logging as absl_logging  # pylint: disable=import-outside-toplevel
    absl_logging.set_verbosity(absl_logging.ERROR)
    from sljax.train.loop import train  # pylint: disable=import-outside-toplevel
    config, note, workdir = resolve(args, jax.default_backend())
    result = train(config, workdir, resume=args.resume, overwrite=args.overwrite,
                   stop_after=args.stop_after, preset_note=note,
                   log=lambda line: print(line, flush=True),
                   progress=False if args.no_progress else None)
  except SljaxError as e:
    print(f"train.py: error: {e}", file=sys.stderr)
    return 2
  except KeyboardInterrupt:
    print("train.py: interrupted (continue with --resume)", file=sys.stderr)
    return 130
  best = "n/a" if result.best_val_mae is None else f"{result.best_val_mae:.4f}"
  last = "n/a" if result.last_val_mae is None else f"{result.last_val_mae:.4f}"
  print(f"done: step {result.step}, {result.epochs_done} epochs; val MAE last {last}, best "
        f"{best}; workdir {result.workdir}")
  return 0
