"""`sljax decode DATASET`: raw structured-light captures -> sl0/, sl1/ and code disparity."""

import argparse
import contextlib
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from sljax.capture import refusals
from sljax.data import preflight
from sljax.data.dataset import FolderSource
from sljax.data.pfm import write_pfm
from sljax.data.scene import SEQUENCE_FOLDERS, write_patterns
from sljax.errors import SljaxError, require
from sljax.io import files
from sljax.io.images import read_image
from sljax.sl.decode import DecodeConfig, count_patterns
from sljax.sl.stereo import MatchConfig, decode_views, match_views

_DEFAULT_SHADOW = 10.0  # 8-bit grey levels; mirrors sljax.sl.decode.DecodeConfig
_DEFAULT_BIT = 6.0
_MATCH = MatchConfig()  # import-captures' defaults: the matching and its left-right tolerance


def register(subparsers) -> None:
  """Adds the `decode` subcommand."""
  p = subparsers.add_parser(
      "decode",
      description="For every scene below DATASET holding raw0/ and raw1/ (white, black, p000..., "
      "optional inverses i000...), classify each pattern bit, write sl0/ and sl1/ "
      "(0 dark, 255 lit, 128 unknown) and, where absent, disp0.pfm / disp1.pfm from matching "
      "equal codes along the rectified scanlines, left-right checked (inf = unknown; the same "
      "decoding, matching and filters as import-captures: a disparity below 0 or beyond the "
      "width is unknown, and a scene whose views look swapped gets no disparity and exit "
      "code 1). Existing disparity files are never replaced (they may be ground truth); "
      "delete them to recompute. All or nothing: every scene's outputs are moved in once "
      "all scenes are decoded, so a failure or Ctrl-C changes no scene.")
  p.add_argument("dataset", metavar="DATASET", help="dataset root (or one scene folder)")
  p.add_argument("--overwrite", action="store_true", help="replace existing sl0/ and sl1/")
  p.add_argument("--code", choices=("binary", "gray"), default=None,
                 help="projected code (default: meta.json or dataset.json 'code')")
  p.add_argument("--shadow-threshold", type=float, default=_DEFAULT_SHADOW, metavar="LEVELS",
                 help="white - black below this (8-bit grey levels) is shadow "
                 f"(default {_DEFAULT_SHADOW:g})")
  p.add_argument("--bit-threshold", type=float, default=_DEFAULT_BIT, metavar="LEVELS",
                 help="|pattern - inverse| (or |pattern - mean|) below this (8-bit grey levels) "
                 f"is an uncertain bit (default {_DEFAULT_BIT:g})")
  p.add_argument("--no-disparity", action="store_true",
                 help="only write the pattern maps, no disp0.pfm / disp1.pfm")
  p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
  """Decodes every scene with raw captures; returns 0 on success."""
  require(args.shadow_threshold >= 0 and args.bit_threshold >= 0,
          "--shadow-threshold and --bit-threshold must be >= 0")
  config = DecodeConfig(shadow_threshold=args.shadow_threshold / 255.0,
                        bit_threshold=args.bit_threshold / 255.0)
  src = FolderSource(args.dataset)
  todo = []
  for i, path in enumerate(src.paths):
    has = [(path / f"raw{cam}").is_dir() for cam in (0, 1)]
    if has[0] != has[1]:
      raise SljaxError(f"scene {path}: raw{has.index(False)}/: missing (raw{has.index(True)}/ "
                       "is present; both views' captures are needed)")
    if has[0]:
      todo.append(i)
  require(todo, f"{src.root}: no scene holds raw0/ and raw1/ (raw captures to decode)")

  # Check every scene before writing anything, so a refusal never leaves a partial run.
  codes = {}
  for i in todo:
    code = args.code or src.meta(i).get("code") or src.info.get("code")
    require(code in ("binary", "gray"),
            f"scene {src.paths[i]}: unknown code {code!r}: set 'code' in meta.json or "
            "dataset.json, or pass --code binary|gray")
    codes[i] = code
    # Capture names alone (cheap); decoding reads the pixels later.
    names = [{p.stem: None for p in (src.paths[i] / f"raw{cam}").glob("*.png")} for cam in (0, 1)]
    for cam, n in enumerate(names):
      for key in ("white", "black"):
        require(key in n, f"scene {src.paths[i]}: raw{cam}/{key}.png: missing")
    counts = [count_patterns(n, f"scene {src.paths[i]}: raw{cam}") for cam, n in enumerate(names)]
    differ = sorted(set(names[0]) ^ set(names[1]))
    require(not differ, f"scene {src.paths[i]}: raw0 holds {counts[0]} patterns, raw1 holds "
            f"{counts[1]} (captures in only one view: {', '.join(differ[:6])})")
  if not args.overwrite:
    for i in todo:
      for folder in ("sl0", "sl1"):
        existing = sorted((src.paths[i] / folder).glob("[0-9][0-9][0-9]*.png"))
        if existing:
          raise SljaxError(f"scene {src.paths[i]}: {folder}/{existing[0].name} exists "
                           "(use --overwrite to replace it)")
  _check_capture_files(src, todo)
  for i in todo:
    for cam in (0, 1):
      _check_contrast(src.paths[i] / f"raw{cam}", config.shadow_threshold)

  try:
    written_disp, kept_disp, coverage, disp_known, swaps = _decode_all(src, todo, codes, config,
                                                                       args)
  except SljaxError as e:
    raise SljaxError(f"{e}; nothing was decoded (no scene was changed)") from None

  print(f"decoded {len(todo)} scene(s) of {len(src)} below {src.root}: sl0/ and sl1/ written; "
        f"pixels with a decoded code: {np.mean(coverage):.1%} on average")
  if not args.no_disparity:
    known = (f" (left disparity known on {np.mean(disp_known):.1%} of pixels on average)"
             if disp_known else "")
    print(f"disparity files written: {written_disp}{known}; kept existing: {len(kept_disp)}"
          + (f" (e.g. {kept_disp[0]}; delete to recompute)" if kept_disp else ""))
  return 1 if swaps else 0


def _decode_all(src: FolderSource, todo: list[int], codes: dict[int, str],
                config: DecodeConfig, args: argparse.Namespace):
  """Decodes (and matches) every scene; all scenes' outputs are moved in together at the end.
  Returns the counts the summary prints."""
  written_disp, kept_disp, coverage, disp_known, swaps = 0, [], [], [], []
  # The checks above find damaged files, but some failures show only while decoding (codes
  # that do not decode, a full disk, Ctrl-C). So each scene's outputs are staged inside its
  # folder and moved in only once every scene has succeeded: a failure in the last scene
  # leaves the first ones as they were.
  with contextlib.ExitStack() as stack:
    for i in tqdm(todo, desc="decode", unit="scene", file=sys.stderr, disable=None):
      path = src.paths[i]
      stage = stack.enter_context(files.staged(path, whole=SEQUENCE_FOLDERS))
      scene = src.get(i, parts={"raw"})  # load_scene checks sizes and that raw0, raw1 agree
      # The projector's width (written by import-captures) makes codes beyond it unknown.
      width = (src.meta(i).get("projector") or [None])[0]
      dec = decode_views(scene.raw0, scene.raw1, codes[i], config, projector=(width, None),
                         where=(f"scene {path}: raw0", f"scene {path}: raw1"))
      for cam, d in enumerate((dec.left, dec.right)):
        write_patterns(stage / f"sl{cam}", d.bits, overwrite=args.overwrite)
      coverage.append(float(np.mean([np.isfinite(d.column).mean()
                                     for d in (dec.left, dec.right)])))
      if args.no_disparity:
        continue
      targets = [path / f"disp{cam}.pfm" for cam in (0, 1)]
      absent = [not p.exists() for p in targets]
      kept_disp += [str(p) for p, missing in zip(targets, absent) if not missing]
      if any(absent):
        match_views(dec, _MATCH)
        found = refusals.swapped(dec)
        if found is not None:  # the loader would refuse the scene: write no disparity for it
          swaps.append(path)  # said now: a later scene's error must not hide it
          tqdm.write(f"sljax decode: scene {path}: raw0 and raw1 look swapped ({found[1]:.0%} of "
                     f"the {found[0]} view's matched disparities are negative); no disparity "
                     "written for it: swap the two folders and rerun with --overwrite",
                     file=sys.stderr)
          continue
        *disps, _ = refusals.plausible(dec.disp0, dec.disp1, dec.disp0.shape[1],
                                       _MATCH.lr_tolerance)
        disp_known.append(float(np.isfinite(disps[0]).mean()))
        for p, missing, disp in zip(targets, absent, disps):
          if missing:
            write_pfm(stage / p.name, disp)
            written_disp += 1
  return written_disp, kept_disp, coverage, disp_known, swaps


def _check_capture_files(src: FolderSource, todo: list[int]) -> None:
  """SljaxError naming the first damaged capture or view, or one of another size, of any scene."""
  # The pre-flight check inflates every capture (headers, CRCs, the zlib stream), so that every
  # damaged file of every scene is named in one line before a scene is decoded, not the first
  # one found after minutes of decoding (the staging below keeps the folders as they were).
  problems, _ = preflight.scan(src, [(todo, {"raw"})], progress=False, use_cache=False)
  if problems:
    more = f" (and {len(problems) - 1} more bad scene(s))" if len(problems) > 1 else ""
    raise SljaxError(f"{problems[0]}{more}; nothing was decoded")


def _check_contrast(folder: Path, threshold: float) -> None:
  """SljaxError when no pixel of a view is brighter under white.png than under black.png by the
  shadow threshold (in [0, 1]): every bit would be unknown, and the all-unknown sl0/ and
  disp0.pfm written would be kept as if they were results."""
  white = read_image(folder / "white.png", gray=True)[..., 0]
  black = read_image(folder / "black.png", gray=True)[..., 0]
  if np.any(white - black >= threshold):  # as decode_captures tells shadow from lit
    return
  why = ("black.png is the brighter one: are the two swapped?"
         if np.any(black - white >= threshold) else "the projector off, or the same picture twice?")
  raise SljaxError(f"{folder}: white.png is nowhere brighter than black.png by "
                   f"{threshold * 255:g} grey levels (--shadow-threshold), so no pixel can be "
                   f"decoded; {why}")
