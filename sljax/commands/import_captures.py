"""`sljax import-captures`: a real rig's structured-light capture -> one scene folder."""

import argparse
from pathlib import Path

from sljax.capture import captures, charuco, frames
from sljax.capture.rig import UNITS_MM, read_calibration
from sljax.errors import require
from sljax.sl.decode import DecodeConfig
from sljax.sl.stereo import MatchConfig

_DECODE, _MATCH = DecodeConfig(), MatchConfig()


def register(subparsers) -> None:
  """Adds the import-captures subcommand."""
  p = subparsers.add_parser(
      "import-captures",
      description="Rectifies one Gray-code capture of a stereo rig with a projector (one image "
      "per projected frame and camera), decodes and matches it, and writes the scene OUT_SCENE: "
      "im0/im1 (the ambient pair or the white frame), raw0/raw1 (white, black, column patterns "
      "and inverses), sl0/sl1 (every column bit, coarsest first), disp0/disp1 (left-right "
      "checked, inf unknown), calib.txt and meta.json. See docs/captures.md.")
  p.add_argument("left", metavar="LEFT", help="the left camera's frames: a folder or a glob "
                 "such as 'caps/pattern_cam1_im*.png' (.png .bmp .jpg .tif, 8/16-bit)")
  p.add_argument("right", metavar="RIGHT", help="the right camera's frames")
  p.add_argument("out", metavar="OUT_SCENE", help="the scene folder to write")
  cal = p.add_mutually_exclusive_group(required=True)
  cal.add_argument("--calib", nargs="+", metavar="FILE",
                   help="OpenCV stereo calibration (M1 D1 M2 D2 R T, as cv2.stereoCalibrate "
                   "returns them): a FileStorage .yml/.xml or an .npz; or OpenCV's "
                   "intrinsics.yml and extrinsics.yml together")
  cal.add_argument("--charuco", nargs=2, metavar=("LEFT_DIR", "RIGHT_DIR"),
                   help="calibrate from ChArUco board images (the i-th left image with the i-th "
                   "right one); needs --board, --square, --marker; writes the calibration as "
                   f"OUT_SCENE/{captures.CALIBRATION_FILE}")
  p.add_argument("--board", metavar="XxY", help="ChArUco board: squares across x down, e.g. 7x5")
  p.add_argument("--square", type=float, metavar="LENGTH",
                 help="ChArUco square side, in --unit")
  p.add_argument("--marker", type=float, metavar="LENGTH",
                 help="ChArUco marker side, in --unit")
  p.add_argument("--dictionary", default="DICT_5X5_100",
                 help="ChArUco ArUco dictionary (default DICT_5X5_100)")
  p.add_argument("--layout", choices=frames.LAYOUTS, default="opencv",
                 help="frame order: opencv (structured_light.GrayCodePattern: column bits and "
                 "inverses, row bits and inverses, white, black; by file number) or sljax "
                 "(white, black, p000..., i000...); default opencv")
  p.add_argument("--projector", metavar="WxH", help="projector resolution, e.g. 1920x1080 "
                 "(needed by the opencv layout)")
  p.add_argument("--code", choices=("gray", "binary"), default="gray",
                 help="the sljax layout's code (default gray; the opencv layout is Gray)")
  p.add_argument("--ambient", nargs=2, metavar=("LEFT.png", "RIGHT.png"),
                 help="a pair taken without projector light for im0/im1 (default: the white "
                 "frame)")
  p.add_argument("--scale", type=float, default=1.0,
                 help="downsize the scene by this factor (disparity and calibration follow)")
  p.add_argument("--unit", choices=tuple(UNITS_MM), default="mm",
                 help="length unit of the calibration's T (default mm; the baseline is "
                 "written in mm)")
  p.add_argument("--group", help="meta.json group (default: the scene folder's name)")
  p.add_argument("--shadow-threshold", type=float, default=_DECODE.shadow_threshold * 255,
                 metavar="LEVELS", help="white - black below this (8-bit grey levels) is "
                 f"projector shadow (default {_DECODE.shadow_threshold * 255:g})")
  p.add_argument("--bit-threshold", type=float, default=_DECODE.bit_threshold * 255,
                 metavar="LEVELS", help="|pattern - inverse| below this (8-bit grey levels) "
                 f"is an uncertain bit (default {_DECODE.bit_threshold * 255:g})")
  p.add_argument("--match-bits", type=int, default=None, metavar="N",
                 help="column bits to match, coarsest first (default: the most whose stripes "
                 "are at least --min-stripe pixels wide)")
  p.add_argument("--min-stripe", type=float, default=_MATCH.min_stripe_px, metavar="PX",
                 help=f"narrowest stripe matched by default (default {_MATCH.min_stripe_px:g})")
  p.add_argument("--lr-tolerance", type=float, default=_MATCH.lr_tolerance, metavar="PX",
                 help="left-right check tolerance (default "
                 f"{_MATCH.lr_tolerance:g})")
  p.add_argument("--row-tolerance", type=float, default=_MATCH.row_tolerance, metavar="ROWS",
                 help="projector rows the two pixels of a match may differ by (opencv layout; "
                 f"default {_MATCH.row_tolerance:g})")
  p.add_argument("--no-row-check", action="store_true",
                 help="do not decode the row bits to check matches")
  p.add_argument("--overwrite", action="store_true", help="replace files already in OUT_SCENE")
  p.set_defaults(func=run)


def _board(args: argparse.Namespace) -> charuco.Board:
  """The --board/--square/--marker/--dictionary options as a Board."""
  require(args.board and args.square and args.marker,
          "--charuco needs --board XxY, --square LENGTH and --marker LENGTH")
  sx, sy = frames.parse_projector(args.board)
  return charuco.Board((sx, sy), args.square, args.marker, args.dictionary).check()


def run(args: argparse.Namespace) -> int:
  """Imports the capture and prints what it found."""
  require(args.shadow_threshold >= 0 and args.bit_threshold >= 0,
          "--shadow-threshold and --bit-threshold must be >= 0")
  require(args.calib is None or len(args.calib) <= 2,
          "--calib takes one file, or intrinsics.yml and extrinsics.yml")
  config = captures.ImportConfig(
      layout=args.layout, code=args.code, unit=args.unit, scale=args.scale, group=args.group,
      projector=None if args.projector is None else frames.parse_projector(args.projector),
      decode=DecodeConfig(args.shadow_threshold / 255.0, args.bit_threshold / 255.0),
      match=MatchConfig(bits=args.match_bits, min_stripe_px=args.min_stripe,
                        lr_tolerance=args.lr_tolerance, row_tolerance=args.row_tolerance),
      row_check=not args.no_row_check)
  out = Path(args.out)
  if args.charuco:
    board = _board(args)
    captures.refuse_existing(out, True, args.overwrite)  # before the calibration's work
    calibration, fit = charuco.calibrate_stereo(args.charuco[0], args.charuco[1], board)
    print(f"ChArUco calibration from {fit['pairs']} image pairs: RMS reprojection error "
          f"{fit['rms_left']:.3f} px (left), {fit['rms_right']:.3f} px (right), "
          f"{fit['rms_stereo']:.3f} px (stereo)")
  else:
    calibration = read_calibration(args.calib)
  report = captures.import_captures(args.left, args.right, out, calibration, config,
                                    ambient=args.ambient, overwrite=args.overwrite,
                                    save_calibration=bool(args.charuco))
  w, h = report.size
  print(f"{out}: {w}x{h}, {report.bit_depth}-bit frames, im0/im1 from the {report.views} "
        f"frame{'s' if report.views == 'ambient' else ''}, {report.match_bits} column bits "
        "matched" + (f", {report.row_rejected} left matches refused by the row check"
                     if config.layout == "opencv" and config.row_check else ""))
  for view, share, rng, decoded in zip(("left", "right"), report.valid, report.ranges,
                                       report.decoded):
    span = f"{rng[0]:.2f}..{rng[1]:.2f} px" if rng else "none"
    print(f"  {view}: disparity on {share:.1%} of pixels ({span}); code decoded on "
          f"{decoded:.1%}")
  if any(report.implausible):
    print(f"  {report.implausible[0]} left and {report.implausible[1]} right matches below 0 or "
          "above the width left unknown")
  if args.charuco:
    print(f"  calibration written to {out / captures.CALIBRATION_FILE}")
  return 0
