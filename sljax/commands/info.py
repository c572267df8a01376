"""`sljax info`: a summary of a dataset folder (scenes, sizes, files, disparities, splits)."""

import argparse
import collections
import os
import struct
from typing import Any
from pathlib import Path

import numpy as np
from tqdm import tqdm

from sljax.data import preflight
from sljax.data.camera import read_calib
from sljax.data.checks import disparity_problem
from sljax.data.dataset import FolderSource, split_indices
from sljax.data.pfm import read_pfm
from sljax.data.scene import present_parts
from sljax.errors import SljaxError
from sljax.io import files
from sljax.io.headers import pixel_problem
from sljax.io.images import decode, holds_12_bit

_FILES = ("im1.png", "disp0.pfm", "disp1.pfm", "mask0.png", "sl0", "sl1", "raw0", "raw1",
          "calib.txt", "meta.json")
_SHORT = {"im1.png": "im1", "disp0.pfm": "disp0", "disp1.pfm": "disp1", "mask0.png": "mask0",
          "sl0": "sl0", "sl1": "sl1", "raw0": "raw0", "raw1": "raw1", "calib.txt": "calib",
          "meta.json": "meta"}
_PNG_COLOUR = {0: "gray", 2: "RGB", 3: "palette", 4: "gray+alpha", 6: "RGBA"}


def register(subparsers) -> None:
  """Adds the info subcommand."""
  p = subparsers.add_parser(
      "info",
      description="Prints the scene count, image sizes, which files each scene holds, "
      "disparity ranges, pattern count and code, and the train/test split sizes. Exits with 1 "
      "when it finds inconsistent scenes (listed under 'problems').")
  p.add_argument("dataset", metavar="DATASET", help="a dataset folder (or one scene folder)")
  p.add_argument("--test-fraction", type=float, default=0.2,
                 help="fraction of groups held out for testing (default 0.2)")
  p.add_argument("--seed", type=int, default=0, help="split seed (default 0)")
  p.add_argument("--rows", type=int, default=20,
                 help="list every scene when there are at most this many (default 20)")
  p.add_argument("--check", action="store_true",
                 help="only check that every file of every scene is readable (the check "
                      "training runs before its first step: PNG structure, CRCs and image "
                      "data, PFM headers, sizes and values, calib.txt, meta.json, shapes); lists each bad scene "
                      "and exits with 2 when there is one")
  p.add_argument("--no-cache", action="store_true",
                 help="with --check: check every file again, ignoring the results cached for "
                      "files unchanged since the last check")
  p.set_defaults(func=run)


def png_header(path: Path) -> tuple[int, int, int, str]:
  """(width, height, bit depth, colour type) read from a PNG's IHDR chunk without decoding."""
  with open(path, "rb") as f:
    head = f.read(26)
  if len(head) < 26 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
    raise ValueError("not a PNG file")
  width, height, depth, colour = struct.unpack(">IIBB", head[16:26])
  return width, height, depth, _PNG_COLOUR.get(colour, f"type {colour}")


def _count(folder: Path, prefix: str = "") -> int:
  return sum(1 for p in folder.iterdir() if p.suffix == ".png" and p.name.startswith(prefix)
             and not files.is_temporary(p))  # a killed write's leftover is no pattern


def _scene_row(path: Path, problems: list[str], name: str, group: str) -> dict:
  """Facts about one scene folder, read cheaply (PNG headers, PFMs, file listings)."""
  row: dict = {"name": name, "group": group, "files": set(), "path": path}
  try:
    w, h, depth, colour = png_header(path / "im0.png")
  except (OSError, ValueError) as e:
    problems.append(f"{name}: im0.png: {e}")
    return row
  row["size"], row["kind"] = (w, h), f"{depth}-bit {colour}"
  if (problem := pixel_problem(w, h)) is not None:
    problems.append(f"{name}: im0.png: {problem}")
  for f in _FILES:
    if (path / f).exists():
      row["files"].add(f)
  if "im1.png" not in row["files"]:
    problems.append(f"{name}: im1.png missing")
  else:
    try:
      if png_header(path / "im1.png")[:2] != (w, h):
        problems.append(f"{name}: im1.png size differs from im0.png ({w}x{h})")
    except (OSError, ValueError) as e:
      problems.append(f"{name}: im1.png: {e}")
  for view in ("sl0", "sl1"):
    if view in row["files"]:
      row[view] = _count(path / view)
  if "sl0" in row and "sl1" in row and row["sl0"] != row["sl1"]:
    problems.append(f"{name}: sl0 holds {row['sl0']} patterns, sl1 holds {row['sl1']}")
  for view in ("raw0", "raw1"):
    if view in row["files"]:
      row[view] = _count(path / view, "p")
  for f in ("disp0.pfm", "disp1.pfm"):
    if f in row["files"]:
      try:
        d = read_pfm(path / f)
      except SljaxError as e:
        problems.append(str(e))
        continue
      problem = disparity_problem(d, (h, w))  # what loading and the pre-flight refuse
      if problem is not None:
        problems.append(f"{name}: {f}: {problem}")
      finite = d[np.isfinite(d)]
      row[f] = (float(finite.min()), float(finite.max()), finite.size / d.size) if finite.size \
          else None
  if "calib.txt" in row["files"]:
    try:
      c = read_calib(path / "calib.txt")
      if (c.width, c.height) != (w, h):
        problems.append(f"{name}: calib.txt says {c.width}x{c.height}, im0.png is {w}x{h}")
    except SljaxError as e:
      problems.append(str(e))
  return row


def check(src, use_cache: bool = True) -> int:
  """`sljax info --check`: the pre-flight check of every part of every scene; prints each bad
  scene's line and raises SljaxError when there is one."""
  jobs = [([i], list(present_parts(p))) for i, p in enumerate(src.paths)]
  # The whole dataset must hold a usable disparity somewhere, as a run's split must.
  with_disp = [i for (i,), parts in jobs if "disp" in parts]
  problems, counts = preflight.scan(src, jobs, use_cache=use_cache,
                                    disparity_sets=[with_disp] if with_disp else [])
  for line in problems:
    print(line)
  if problems:
    empty = sum(line.startswith(f"{src.root}: none of") for line in problems)
    bad = len(problems) - empty
    raise SljaxError(f"{src.root}: " + (f"{_plural(bad, 'bad scene')} of {counts['scenes']}"
                                        if bad else "no usable disparity"))
  print(f"{src.root}: all {_plural(counts['scenes'], 'scene')} readable "
        f"({counts['cached']} unchanged since the last check)")
  return 0


def _low_bit_note(rows: list[dict]) -> str | None:
  """A note when the first 16-bit view holds 12-bit (or fewer) values: sljax reads a 16-bit
  PNG as value / 65535, so such data come out 16x (or more) darker than they are."""
  row = next((r for r in rows if r["kind"].startswith("16-bit")), None)
  if row is None:
    return None
  try:
    image = decode(row["path"] / "im0.png")
  except SljaxError:  # listed under problems already, or found by --check
    return None
  if not holds_12_bit(image.max(), image.dtype):
    return None
  return (f"note:    {row['name']}/im0.png is 16-bit with values up to {int(image.max())} "
          "(12-bit data?); sljax reads 16-bit PNGs as value / 65535, so it looks "
          f"{65535 / max(int(image.max()), 1):.0f}x darker than white: scale the values to the "
          "16-bit range when writing the scenes")


def _plural(n: int, noun: str) -> str:
  """'1 scene', '2 scenes'."""
  return f"{n} {noun}{'' if n == 1 else 's'}"


def _disp_text(r) -> str:
  if r is None:
    return "no valid"
  return f"{r[0]:.1f}..{r[1]:.1f} ({r[2]:.0%})"


def _table(rows: list[list[str]]) -> str:
  widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
  return "\n".join("  " + "  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows)


def _pattern_problems(counts: list[int], declared: Any) -> list[str]:
  """The pre-flight check's pattern rule (preflight.expected_patterns), summarised: a mixed
  dataset would fail in its first training batch, later and less clearly."""
  expected = preflight.expected_patterns(declared, counts)
  if all(preflight.fits_patterns(t, expected, declared) for t in counts):
    return []
  found = ", ".join(f"{t} ({_plural(v, 'scene')})"
                    for t, v in sorted(collections.Counter(counts).items()))
  if declared is not None:
    return [f"dataset.json declares {declared} patterns; the scenes hold {found}"]
  return [f"scenes hold different pattern counts: {found}"]


def run(args: argparse.Namespace) -> int:
  """Prints the summary; returns 1 when problems were found."""
  src = FolderSource(args.dataset)
  if args.check:
    return check(src, use_cache=not args.no_cache)
  problems: list[str] = []
  rows = [_scene_row(p, problems, src.name(i), src.group(i))
          for i, p in enumerate(tqdm(src.paths, desc="reading scenes", unit="scene",
                                     disable=len(src) < 50, leave=False))]
  rows = [r for r in rows if "size" in r]
  n = len(src)
  title = src.info.get("name", Path(os.path.abspath(args.dataset)).name)
  print(f"dataset {title}: {_plural(n, 'scene')} in {args.dataset}")

  sizes = collections.Counter(f"{r['size'][0]}x{r['size'][1]} {r['kind']}" for r in rows)
  print("views:   " + ", ".join(f"{k} ({v})" for k, v in sizes.most_common()))
  note = _low_bit_note(rows)
  if note:
    print(note)

  counts = collections.Counter(f for r in rows for f in r["files"])
  print("files:   im0.png " + f"{len(rows)}/{n}, " +
        ", ".join(f"{f} {counts[f]}/{n}" for f in _FILES if counts[f]))

  problems += _pattern_problems([r["sl0"] for r in rows if "sl0" in r], src.info.get("patterns"))
  patterns = collections.Counter(r["sl0"] for r in rows if "sl0" in r)
  if patterns or src.num_patterns:
    found = ", ".join(f"{t} patterns ({_plural(v, 'scene')})" for t, v in sorted(patterns.items()))
    print(f"patterns: code {src.code or 'unknown'}; {found or f'{src.num_patterns} declared'}")
  raw = collections.Counter(r.get("raw0") for r in rows if "raw0" in r)
  if raw:
    print("raw:     " + ", ".join(f"{t} pattern captures ({_plural(v, 'scene')})"
                                   for t, v in sorted(raw.items())))

  for f in ("disp0.pfm", "disp1.pfm"):
    ranges = [r[f] for r in rows if r.get(f)]
    if ranges:
      lo, hi = min(r[0] for r in ranges), max(r[1] for r in ranges)
      known = sum(r[2] for r in ranges) / len(ranges)
      print(f"{f[:5]}:   {lo:.2f}..{hi:.2f} px over {_plural(len(ranges), 'scene')}, "
            f"{known:.0%} of pixels known on average")

  train, test = split_indices(src, test_fraction=args.test_fraction, seed=args.seed)
  groups = lambda idx: len({src.group(i) for i in idx})
  how = ("explicit (dataset.json)" if src.splits else
         f"by group hash, seed {args.seed}, {args.test_fraction:g} of groups for test")
  print(f"split:   {how}: train {_plural(len(train), 'scene')} / "
        f"{_plural(groups(train), 'group')}, test {_plural(len(test), 'scene')} / "
        f"{_plural(groups(test), 'group')}"
        + ("" if test or src.splits else " (a single group cannot be split: give scenes "
           "meta.json groups or dataset.json splits)"))

  if n <= args.rows:
    header = ["scene", "size", "group"] + [_SHORT[f] for f in _FILES] + ["disp0 px (known)"]
    table = [header]
    for r in rows:
      cells = []
      for f in _FILES:
        if f not in r["files"]:
          cells.append("-")
        elif f in ("sl0", "sl1", "raw0", "raw1"):
          cells.append(str(r.get(f, "")))
        else:
          cells.append("y")
      disp = _disp_text(r.get("disp0.pfm")) if "disp0.pfm" in r else "-"
      table.append([r["name"], f"{r['size'][0]}x{r['size'][1]}", r["group"]]
                   + cells + [disp])
    print("scenes:")
    print(_table(table))
  else:
    print(f"scenes:  {n} (list them with --rows {n}); "
          f"first: {src.name(0)}, last: {src.name(n - 1)}")

  if problems:
    print(f"problems ({len(problems)}):")
    for p in problems[:50]:
      print(f"  {p}")
    if len(problems) > 50:
      print(f"  ... and {len(problems) - 50} more")
    return 1
  return 0
