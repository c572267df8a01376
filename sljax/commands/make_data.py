"""`sljax make-data`: render a synthetic dataset (scene folders + dataset.json)."""

import argparse
import json
from pathlib import Path

from tqdm import tqdm

from sljax.data.scene import SEQUENCE_FOLDERS, write_scene
from sljax.errors import require
from sljax.io import files
from sljax.render.synthetic import SynthConfig, render_scene


def register(subparsers) -> None:
  """Adds the make-data subcommand."""
  p = subparsers.add_parser(
      "make-data",
      description="Renders N procedural scenes (rectified stereo views, ground-truth disparity, "
      "projected patterns, masks, optional raw captures) as scene folders under OUT. Scene i of "
      "seed S is always the same scene. All or nothing: the scenes are moved into OUT once "
      "every one is rendered, so a failure or Ctrl-C leaves OUT as it was.")
  p.add_argument("out", metavar="OUT", help="output folder (must be empty unless --overwrite)")
  p.add_argument("--n", type=int, default=100, help="number of scenes (default 100)")
  p.add_argument("--seed", type=int, default=0, help="dataset seed (default 0)")
  p.add_argument("--domain", choices=("objects", "tissue"), default="objects",
                 help="objects: podium + random object in a room (binary code); "
                 "tissue: folded soft tissue at close range (Gray code)")
  p.add_argument("--raw", action="store_true",
                 help="also write raw captures (white, black, patterns and inverses)")
  p.add_argument("--size", type=int, default=256, help="image width = height (default 256)")
  p.add_argument("--patterns", type=int, default=None,
                 help="number of stripe patterns t (projector of 2^t columns); "
                 "default 8 (objects) / 9 (tissue)")
  p.add_argument("--overwrite", action="store_true", help="write into a non-empty OUT")
  p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
  """Renders and writes the scenes with a progress bar."""
  out = Path(args.out)
  require(args.n >= 1, f"--n must be >= 1, got {args.n}")
  files.check_output_folder(out, args.overwrite, label="OUT", must_be_empty=True)
  cfg = SynthConfig(size=args.size, domain=args.domain, t=args.patterns).resolved()
  info = {"name": out.name or "synthetic", "code": cfg.code, "patterns": cfg.t,
          "generator": {"seed": args.seed, "n": args.n, "domain": cfg.domain, "size": cfg.size,
                        "raw": bool(args.raw)}}
  # Rendered into a hidden folder and moved in at the end: a failure or Ctrl-C part way leaves
  # OUT as it was (absent, empty, or with --overwrite its earlier scenes), never a partial set.
  with files.staged(out, whole=SEQUENCE_FOLDERS) as stage:
    files.write_text(stage / "dataset.json", json.dumps(info, indent=2) + "\n")
    for i in tqdm(range(args.n), desc="make-data", unit="scene"):
      scene = render_scene(i, args.seed, cfg, raw=args.raw)
      write_scene(stage / scene.name, scene, overwrite=args.overwrite)
  print(f"wrote {args.n} {cfg.domain} scenes ({cfg.size}x{cfg.size}, {cfg.code} code, "
        f"t={cfg.t}) to {out}")
  return 0
