"""`sljax predict MODEL LEFT RIGHT --out DIR` (or MODEL PAIRS_DIR): disparity, depth, points."""

import argparse
from pathlib import Path

from sljax import geometry, predict


def register(subparsers) -> None:
  """Adds the `predict` subcommand."""
  p = subparsers.add_parser(
      "predict",
      description="Runs a trained model (a training workdir, its checkpoints folder or a "
                  "converted PSMNet folder) or the classical baseline 'sgbm' on a stereo pair "
                  "(LEFT RIGHT image files) or on every pair of PAIRS_DIR (scene folders with "
                  "im0.png/im1.png, or left/ and right/ image folders paired by file name). "
                  "Writes per pair disparity.pfm and disparity.png (colour, scale bar); with a "
                  "calibration (--calib, else calib.txt beside LEFT, in the scene folder or in "
                  "PAIRS_DIR) depth_mm.pfm (float mm, inf = unknown), depth_mm.png (16-bit mm, "
                  "0 = unknown; depths over 65535 mm are 0 there and kept in the PFM) and "
                  "cloud.ply (binary PLY, x y z in mm in the left camera frame, RGB from the "
                  "left view; Z = f*B/(d + doffs), X = (x - cx) Z/f, Y = (y - cy) Z/fy; unknown "
                  "and out-of-range pixels dropped); for structured-light models "
                  "confidence.pfm and confidence.png. One pair writes into --out, several into "
                  "--out/<pair name>/.")
  p.add_argument("model", metavar="MODEL",
                 help="a training workdir, its checkpoints folder, a converted PSMNet folder, "
                      "or 'sgbm'")
  p.add_argument("inputs", metavar="INPUT", nargs="+",
                 help="LEFT RIGHT (two image files) or PAIRS_DIR (one folder of pairs)")
  p.add_argument("--out", required=True, help="output folder")
  p.add_argument("--calib", default=None,
                 help="Middlebury calib.txt for every pair (default: calib.txt beside LEFT, in "
                      "each scene folder, or in PAIRS_DIR)")
  p.add_argument("--mode", choices=("pad", "resize"), default="pad",
                 help="pad (default): full resolution, padded as the PSMNet reference pads; "
                      "resize: at the training size and back, disparity scaled by the width "
                      "ratio")
  p.add_argument("--maxdisp", type=int, default=None,
                 help="psmnet/psmnet-mtl: the cost volume's depth (a multiple of 16; default: "
                      "the model's)")
  p.add_argument("--search-range", type=int, default=None, metavar="PX",
                 help="unet-sl: the correlation's search range (default: sljax.corr's)")
  p.add_argument("--num-disparities", type=int, default=None, metavar="N",
                 help="sgbm: numDisparities (default: calib ndisp, else 25%% of the width)")
  p.add_argument("--max-depth", type=float, default=None, metavar="MM",
                 help="depths beyond this many mm are unknown in every output")
  p.add_argument("--overwrite", action="store_true", help="replace existing output files")
  p.set_defaults(func=run)


def run(args) -> int:
  """Finds the pairs, loads the model, predicts and prints one line per pair."""
  geometry.check_max_depth(args.max_depth, "--max-depth")
  pairs = predict.find_pairs(args.inputs, args.calib)
  out = Path(args.out)
  predict.check_outputs(out, pairs, args.overwrite)  # before the (slow) model loading
  predictor = predict.load_predictor(args.model, args.mode, args.maxdisp, args.search_range,
                                     args.num_disparities)
  summaries = predict.predict_pairs(predictor, pairs, out, args.max_depth)
  for pair, s in zip(pairs, summaries):
    line = f"{predict.output_dir(out, pair)}: disparity known on {s['known_disparity']:.1%}"
    if "points" in s:
      line += f", {s['points']} points"
      if s["png_zero_but_known"]:
        line += (f" ({s['png_zero_but_known']} known depths do not fit 16-bit mm and are 0 in "
                 "depth_mm.png)")
    else:
      line += ", no calibration: no depth or point cloud"
    print(line)
  return 0
