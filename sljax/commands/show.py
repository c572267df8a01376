"""`sljax show`: a contact sheet of one scene (views, disparity, patterns, mask)."""

import argparse
from pathlib import Path

import numpy as np

from sljax.data.dataset import find_scenes
from sljax.data.scene import load_scene, present_parts
from sljax.errors import require
from sljax.io import files, pictures
from sljax.io.pictures import Panel, save_panels


def register(subparsers) -> None:
  """Adds the show subcommand."""
  p = subparsers.add_parser(
      "show",
      description="Draws both views, the disparity (colour map with scale bar), a few projected "
      "patterns and the mask of a scene folder, or of scene --index of a dataset.")
  p.add_argument("path", metavar="SCENE_OR_DATASET", help="a scene folder or a dataset folder")
  p.add_argument("--out", required=True,
                 help="picture to write: .png, or .pdf, .svg, .jpg, ... by its extension")
  p.add_argument("--index", type=int, default=0, help="scene of a dataset to show (default 0)")
  p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
  p.set_defaults(func=run)


def _pattern_panels(sl, side: str):
  """A few patterns (coarsest, middle, finest); unknown drawn mid grey."""
  t = sl.shape[-1]
  picks = sorted({0, t // 2, t - 1})
  return [Panel(f"{side} pattern {k}", np.where(np.isnan(sl[..., k]), 0.5, sl[..., k]))
          for k in picks]


def run(args: argparse.Namespace) -> int:
  """Loads the scene and writes the picture."""
  files.refuse_existing([pictures.check_figure_path(args.out)], args.overwrite)  # before any reading
  path = Path(args.path)
  require(path.is_dir(), f"{path}: no such scene or dataset folder")
  if (path / "im0.png").exists():
    scene_dir = path
  else:
    scenes = find_scenes(path)
    require(0 <= args.index < len(scenes),
            f"{path}: --index {args.index} out of range (dataset has {len(scenes)} scenes)")
    scene_dir = scenes[args.index]
  scene = load_scene(scene_dir, parts={"im", "disp", "mask", "sl", "calib", "meta"} & _present(
      scene_dir))
  panels = [Panel("left view", scene.im0), Panel("right view", scene.im1)]
  if scene.disp0 is not None:
    finite = scene.disp0[np.isfinite(scene.disp0)]
    panels.append(Panel(f"disparity ({finite.size / scene.disp0.size:.0%} known)", scene.disp0,
                        cmap="turbo", label="px"))
  if scene.mask0 is not None:
    panels.append(Panel("mask", np.asarray(scene.mask0, np.float32)))
  if scene.sl0 is not None:
    panels += _pattern_panels(scene.sl0, "left")
  if scene.sl1 is not None:
    panels.append(_pattern_panels(scene.sl1, "right")[-1])
  save_panels(args.out, panels, ncols=4, title=str(scene_dir))
  print(f"wrote {args.out}")
  return 0


def _present(scene_dir) -> set:
  """Parts a scene folder holds (so that optional parts are not requested)."""
  return set(present_parts(scene_dir))
