"""`sljax evaluate CHECKPOINT_OR_MODEL DATASET --out DIR`: metrics, reports and pictures."""

import argparse
from pathlib import Path

from sljax import inference
from sljax.data.dataset import FolderSource, split_indices
from sljax.errors import SljaxError
from sljax.evaluation.scoring import check_out_dir, evaluate, markdown_report
from sljax.inference.sgbm import SGBMConfig, SGBMPredictor


def register(subparsers) -> None:
  """Adds the `evaluate` subcommand."""
  p = subparsers.add_parser(
      "evaluate",
      description="Runs a trained model (a training workdir, its checkpoints folder or a "
                  "converted PSMNet folder) or the classical baseline 'sgbm' over every scene of "
                  "a dataset and writes metrics.json, metrics.md (Markdown tables) and "
                  "per_scene.csv: MAE (= EPE), IQR, RMS, A90, bad-0.5/1/2/3, D1, depth MAE/IQR "
                  "in mm when calib.txt exists, Seg metrics when mask0.png exists, and pattern "
                  "accuracy for structured-light models.",
      formatter_class=argparse.ArgumentDefaultsHelpFormatter)
  p.add_argument("source", metavar="CHECKPOINT_OR_MODEL",
                 help="a training workdir, its checkpoints folder, a converted PSMNet folder, "
                      "or 'sgbm' (with --model, this argument is the DATASET)")
  p.add_argument("dataset", metavar="DATASET", nargs="?",
                 help="dataset folder (scene format, e.g. Middlebury 2014 scenes)")
  p.add_argument("--model", default=None,
                 help="'sgbm' or a checkpoint path, instead of the first positional argument")
  p.add_argument("--out", required=True, help="output folder (must be empty or absent)")
  p.add_argument("--mode", choices=("resize", "pad"), default="resize",
                 help="resize: to the training size and back with disparity scaled by the width "
                      "ratio (the paper's protocol); pad: full resolution, padded at the top and "
                      "right as the PSMNet reference pads (see sljax.inference)")
  p.add_argument("--split", choices=("all", "test", "train"), default="all",
                 help="which scenes: all, or the dataset's group-level test/train split")
  p.add_argument("--test-fraction", type=float, default=None,
                 help="test fraction of the split when the dataset has no explicit splits "
                      "(default: the checkpoint's training config, else 0.2)")
  p.add_argument("--seed", type=int, default=None,
                 help="seed of the group-level split (default: the checkpoint's, else 0)")
  p.add_argument("--save-predictions", action="store_true",
                 help="write predicted disparities to OUT/predictions/<scene>.pfm")
  p.add_argument("--figures", action="store_true", help="write OUT/figures/<scene>.png")
  p.add_argument("--num-disparities", type=int, default=None,
                 help="SGBM only: disparity range (rounded up to 16); default calib ndisp, "
                      "else 25%% of the width")
  p.add_argument("--overwrite", action="store_true", help="write into a non-empty --out")
  p.set_defaults(func=run)


def run(args) -> int:
  """Runs the evaluation and prints the Markdown report."""
  if args.model is not None:
    if args.dataset is not None:
      raise SljaxError("with --model give only the DATASET folder as positional argument")
    model, dataset = args.model, args.source
  else:
    if args.dataset is None:
      raise SljaxError("expected CHECKPOINT_OR_MODEL DATASET (or DATASET with --model)")
    model, dataset = args.source, args.dataset

  if args.num_disparities is not None and model != "sgbm":
    raise SljaxError("--num-disparities applies to the sgbm baseline only")
  if not Path(dataset).is_dir():
    raise SljaxError(f"DATASET {dataset}: not a folder")
  source = FolderSource(dataset)
  out = check_out_dir(args.out, args.overwrite)  # before the (slow) model loading
  if model == "sgbm":
    predictor = SGBMPredictor(SGBMConfig(num_disparities=args.num_disparities))
    checkpoint = None
  else:
    if not Path(model).exists():
      raise SljaxError(f"CHECKPOINT_OR_MODEL {model}: no such checkpoint (or use 'sgbm')")
    predictor = inference.load(model, mode=args.mode)
    checkpoint = model
  # The held-out split of a run is reproduced from its config unless given explicitly.
  config = getattr(predictor, "train_config", {}) or {}
  if args.split == "all":
    indices = list(range(len(source)))
  else:
    fraction = args.test_fraction if args.test_fraction is not None else float(
        config.get("test_fraction", 0.2))
    seed = args.seed if args.seed is not None else int(config.get("seed", 0))
    train, test = split_indices(source, fraction, seed)
    indices = test if args.split == "test" else train
  report = evaluate(predictor, source, indices, out_dir=out,
                    save_predictions=args.save_predictions, figures=args.figures,
                    info={"checkpoint": checkpoint, "dataset": str(dataset), "split": args.split})
  print(markdown_report(report))
  print(f"wrote {out}/metrics.json, metrics.md, per_scene.csv")
  return 0
