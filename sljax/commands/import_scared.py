"""`sljax import-scared`: convert a SCARED keyframe into a rectified scene folder."""

import argparse

import numpy as np

from sljax.capture.scared import import_scared
from sljax.data.scene import load_scene


def register(subparsers) -> None:
  """Adds the import-scared subcommand."""
  p = subparsers.add_parser(
      "import-scared",
      description="Rectifies a SCARED keyframe (Left_Image.png, Right_Image.png, "
      "left_depth_map.tiff, endoscope_calibration.yaml) with OpenCV and writes a scene folder "
      "(im0.png, im1.png, disp0.pfm with the left ground-truth disparity, calib.txt, meta.json).")
  p.add_argument("keyframe_dir", metavar="KEYFRAME_DIR", help="a SCARED keyframe folder")
  p.add_argument("out_dir", metavar="OUT_DIR", help="the scene folder to write")
  p.add_argument("--overwrite", action="store_true", help="replace files already in OUT_DIR")
  p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
  """Runs the conversion and prints a one-line summary."""
  out = import_scared(args.keyframe_dir, args.out_dir, overwrite=args.overwrite)
  scene = load_scene(out, parts={"disp", "calib"})
  d = scene.disp0[np.isfinite(scene.disp0)]
  h, w = scene.shape
  rng = f"{d.min():.2f}..{d.max():.2f} px" if d.size else "none"
  print(f"{out}: {w}x{h}, baseline {scene.calib.baseline:.3f} mm, f {scene.calib.focal:.2f} px, "
        f"disparity known on {d.size / (h * w):.1%} of pixels ({rng})")
  return 0
