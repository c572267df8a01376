"""`sljax predict MODEL LEFT RIGHT --out DIR` (or MODEL PAIRS_DIR, or MODEL --video FILE
--layout L, or MODEL --video LEFT RIGHT): disparity, depth, points."""

from pathlib import Path

from sljax.depth import geometry, pairs, video
from sljax.errors import SljaxError


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
                  "--out/<pair name>/. A rectified pair (an OpenCV --calib) also gets calib.txt, "
                  "its rectified geometry. With --video: disparity.mp4 (colour-mapped) and, "
                  "with --frames, frames/NNNNNN/ per predicted frame with the files above less "
                  "the colour PNGs.")
  p.add_argument("model", metavar="MODEL",
                 help="a training workdir, its checkpoints folder, a converted PSMNet folder, "
                      "or 'sgbm'")
  p.add_argument("inputs", metavar="INPUT", nargs="*",
                 help="LEFT RIGHT (two image files) or PAIRS_DIR (one folder of pairs); none "
                      "with --video")
  p.add_argument("--out", required=True, help="output folder")
  p.add_argument("--calib", default=None, nargs="+", metavar="FILE",
                 help="a Middlebury calib.txt (any .txt: the views are rectified already), or "
                      "an OpenCV stereo calibration to rectify every pair and frame with "
                      "before inference (M1 D1 M2 D2 R T as cv2.stereoCalibrate returns them: "
                      "a FileStorage .yml/.yaml/.xml/.json or an .npz, or OpenCV's "
                      "intrinsics.yml extrinsics.yml together; as import-captures reads "
                      "them). Default: calib.txt beside LEFT or the video, in each scene "
                      "folder, or in PAIRS_DIR")
  p.add_argument("--unit", choices=tuple(pairs.UNITS_MM), default="mm",
                 help="length unit of an OpenCV calibration's T (default mm; depth is in mm)")
  v = p.add_argument_group("video")
  v.add_argument("--video", nargs="+", metavar="FILE", default=None,
                 help="a stereo video: one file holding both views (with --layout) or two "
                      "files, LEFT RIGHT (any format OpenCV reads)")
  v.add_argument("--layout", choices=video.LAYOUTS, default=None,
                 help="one video file: stacked (left view on top, as SCARED's) or "
                      "side-by-side (left view on the left)")
  v.add_argument("--every", type=int, default=1, metavar="N",
                 help="predict frames 0, N, 2N, ... (default 1: every frame)")
  v.add_argument("--batch", type=int, default=None, metavar="B",
                 help="frame pairs per network call (default 4)")
  v.add_argument("--frames", action="store_true",
                 help="also write each predicted frame's files into --out/frames/NNNNNN/")
  v.add_argument("--disp-range", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                 help="the colour map's disparity range in px (default: the 1st to 99th "
                      "percentile of the first batch's disparities)")
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
  """Finds the pairs (or the video), loads the model, predicts and prints one line per pair."""
  geometry.check_max_depth(args.max_depth, "--max-depth")
  if args.video is not None:
    return run_video(args)
  for flag, value in (("--layout", args.layout), ("--every", args.every != 1),
                      ("--frames", args.frames), ("--disp-range", args.disp_range),
                      ("--batch", args.batch)):
    if value:
      raise SljaxError(f"{flag} is for --video")
  found = pairs.find_pairs(args.inputs, args.calib, pairs.UNITS_MM[args.unit])
  out = Path(args.out)
  pairs.check_outputs(out, found, args.overwrite)  # before the (slow) model loading
  predictor = pairs.load_predictor(args.model, args.mode, args.maxdisp, args.search_range,
                                     args.num_disparities)
  summaries = pairs.predict_pairs(predictor, found, out, args.max_depth)
  for pair, s in zip(found, summaries):
    line = f"{pairs.output_dir(out, pair)}: disparity known on {s['known_disparity']:.1%}"
    if "points" in s:
      line += f", {s['points']} points"
      if s["png_zero_but_known"]:
        line += (f" ({s['png_zero_but_known']} known depths do not fit 16-bit mm and are 0 in "
                 "depth_mm.png)")
    else:
      line += ", no calibration: no depth or point cloud"
    print(line)
  return 0


def run_video(args) -> int:
  """Checks the video and outputs, loads the model, predicts the frames, prints one line."""
  if args.inputs:
    raise SljaxError(f"--video takes the video file(s); got INPUT {' '.join(args.inputs)} too")
  video.check_options(args.every, args.batch or 4, args.disp_range)
  source = video.open_video(args.video, args.layout)
  calib = video.find_calibration(source, args.calib, pairs.UNITS_MM[args.unit])
  video.check_outputs(args.out, args.frames, args.overwrite)  # all before the (slow) loading
  predictor = pairs.load_predictor(args.model, args.mode, args.maxdisp, args.search_range,
                                     args.num_disparities)
  s = video.predict_video(predictor, source, args.out, calib, args.every, args.batch or 4,
                          args.frames, args.max_depth,
                          tuple(args.disp_range) if args.disp_range else None, args.overwrite)
  line = (f"{s['video']}: {s['frames']} frames" + (f" (one in {args.every})" if args.every > 1
                                                    else "")
          + f", disparity known on {s['known_disparity']:.1%}, colours over "
          f"{s['disp_range'][0]:.3g}..{s['disp_range'][1]:.3g} px"
          + (", rectified" if s["rectified"] else ""))
  if s["frames_dir"] is not None:
    line += f"; per frame files in {s['frames_dir']}" + (
        "" if calib is not None else " (no calibration: no depth or point cloud)")
  print(line)
  return 0
