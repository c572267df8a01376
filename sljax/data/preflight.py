"""Pre-flight check of a scene folder: every file a run will read, checked before the first step.

A corrupt file found by the loader stops a run when the file is first read, which can be
hours in (validation scenes are first read at the end of epoch 1). The check reads each file
the run's scene parts need, whole, and passes its values through the loader's own verdicts
(sljax.data.checks, camera.read_calib), so that what it passes trains and what training would
refuse it refuses first:

- PNG: the chunk structure is walked and every chunk's CRC-32 verified (signature, IHDR first,
  IDAT present, IEND reached), the header's size checked (sljax.io.headers.MAX_PIXELS), then
  the image data inflated to the end (sljax.io.headers.png_check): truncation, flipped bytes
  (CRC) and a zlib stream written wrong behind correct CRCs are all named here. Other formats
  are sized from their headers, then decoded in full with OpenCV, as the loader reads them.
- PFM: the header parsed and the file's size compared with what the header needs, then the
  values read and judged (sljax.data.checks.disparity_problem: mostly negative or beyond the
  width). Every set of scenes whose disparities a run reads must hold at least one usable
  disparity (known, 0 to the width): all NaN or 1e30 would train on nothing.
- calib.txt, meta.json: parsed with the loader's own readers (they are small).
- Shapes: every view, disparity, pattern and mask of a scene has im0's size; sl1 holds as many
  patterns as sl0, and every scene as many as the first (the network's input is built for it),
  or at least as many as dataset.json's "patterns", of which the loader takes the coarsest.

Results are cached per dataset, keyed by each file's size and mtime (and the listing times of
the folders read), in the user's cache folder (SLJAX_CACHE_DIR, else XDG_CACHE_HOME/sljax,
else ~/.cache/sljax), never inside the dataset; a second run stats the files and reads none.
"""

import concurrent.futures
import hashlib
import json
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from sljax.data.camera import read_calib
from sljax.data.checks import disparity_problem, no_usable_disparity, usable_disparities
from sljax.data.dataset import FolderSource, PART_FIELD
from sljax.data.pfm import _HEADER as PFM_HEADER
from sljax.data.pfm import read_pfm
from sljax.data.scene import _PATTERN_FILE, _RAW_FILE, _numbered_files
from sljax.errors import SljaxError
from sljax.io import files
from sljax.io.files import read_json_object
from sljax.io.headers import PNG_SIGNATURE, image_size, pixel_problem, png_check
from sljax.runtime.compile_cache import user_cache_dir

CACHE_VERSION = 2  # 2: images decoded whole, disparities judged and counted ("usable")
THREADS = 4  # file reads and CRC-32 release the GIL
ALL_PARTS = ("im", "disp", "mask", "sl", "raw", "calib", "meta")


class BadFile(Exception):
  """A file that fails the check (path relative to the scene, problem)."""

  def __init__(self, file: str, problem: str):
    super().__init__(f"{file}: {problem}")
    self.file, self.problem = file, problem


def image_check(path: Path) -> tuple[int, int, int]:
  """(width, height, bit depth) of an image file the loader can read; ValueError otherwise."""
  data = path.read_bytes()
  if not data:  # cv2.imdecode asserts on an empty buffer (a cv2.error, not None)
    raise ValueError("empty file (0 bytes)")
  if data[:8] == PNG_SIGNATURE:
    return png_check(data)
  size = image_size(path)  # before OpenCV allocates what the header claims
  problem = None if size is None else pixel_problem(*size)
  if problem is not None:
    raise ValueError(problem)
  try:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
  except cv2.error:
    img = None
  if img is None:
    raise ValueError("not a readable image")
  return img.shape[1], img.shape[0], 8 * img.dtype.itemsize


def pfm_check(path: Path) -> tuple[int, int, int]:
  """(width, height, channels) of a PFM whose header parses and whose size fits it."""
  with open(path, "rb") as f:
    head = f.read(256)
  m = PFM_HEADER.match(head)
  if m is None:
    raise ValueError("not a PFM file (expected header 'Pf' or 'PF', then 'width height', "
                     "then scale)")
  magic, width, height, scale = m.groups()
  channels = 3 if magic == b"PF" else 1
  width, height = int(width), int(height)
  try:
    if width <= 0 or height <= 0 or float(scale) == 0.0:
      raise ValueError
  except ValueError:
    raise ValueError(f"PFM header has width={width} height={height} scale={scale!r}") from None
  start = m.end() + (head[m.end() - 1:m.end() + 1] == b"\r\n")
  need = start + width * height * channels * 4
  size = path.stat().st_size
  if size < need:
    raise ValueError(f"truncated: {size} bytes, the header ({width}x{height}x{channels}) needs "
                     f"{need}")
  return width, height, channels


# ----------------------------------------------------------------------------- one scene


def _stamp(path: Path) -> list[Any]:
  st = path.stat()
  return [st.st_size, st.st_mtime_ns]


class _Scene:
  """The check of one scene folder: the files read and their stamps (the cache key)."""

  def __init__(self, scene_dir: Path):
    self.dir = scene_dir
    self.stamps: dict[str, list[Any]] = {".": _stamp(scene_dir)}

  def exists(self, name: str) -> bool:
    return (self.dir / name).exists()

  def require(self, name: str) -> Path:
    path = self.dir / name
    if not path.exists():
      raise BadFile(name, "missing")
    self.stamps[name] = _stamp(path)
    return path

  def image(self, name: str, hw: tuple[int, int] | None = None, max_depth: int = 16,
            against: str = "im0.png") -> tuple[int, int]:
    """(height, width) of an image, checked against hw when given."""
    path = self.require(name)
    try:
      w, h, depth = image_check(path)
    except (OSError, ValueError) as e:
      raise BadFile(name, str(e)) from None
    if depth > max_depth:
      raise BadFile(name, f"{depth}-bit; must be at most {max_depth}-bit")
    self.same_size(name, (h, w), hw, against)
    return h, w

  def same_size(self, name: str, got: tuple[int, int], want: tuple[int, int] | None,
                against: str = "im0.png") -> None:
    if want is not None and tuple(got) != tuple(want):
      raise BadFile(name, f"size {got[1]}x{got[0]} differs from {against} ({want[1]}x{want[0]})")

  def numbered(self, folder: str, pattern, hw: tuple[int, int], max_depth: int) -> int:
    """How many numbered images a pattern/raw folder holds, each checked; their count."""
    path = self.require(folder)
    if not path.is_dir():
      raise BadFile(folder, "not a folder")
    images = _numbered_files(path, pattern)
    if not images:
      raise BadFile(folder, "no images")
    if pattern is _PATTERN_FILE:
      numbers = [int(pattern.match(p.name).group(1)) for p in images]
      if numbers != list(range(len(images))):
        raise BadFile(folder, f"pattern images are not numbered 000..{len(images) - 1:03d}")
    for p in images:
      self.image(f"{folder}/{p.name}", hw, max_depth)
    return len(images)


def check_scene(scene_dir: Path, parts: Iterable[str]) -> dict[str, Any]:
  """Checks the files of one scene that loading `parts` reads; returns {'hw', 't', 'stamps'}
  (BadFile naming the first bad file)."""
  parts = set(parts) | {"im"}
  s = _Scene(scene_dir)
  hw = s.image("im0.png")
  s.image("im1.png", hw)
  t = usable = None
  if "disp" in parts:
    for i, name in enumerate(("disp0.pfm", "disp1.pfm")):
      if i == 0 or s.exists(name):
        try:
          w, h, c = pfm_check(s.require(name))
          d = read_pfm(s.dir / name)
        except (OSError, ValueError) as e:
          raise BadFile(name, str(e)) from None
        except SljaxError as e:
          raise BadFile(name, str(e).split(": ", 1)[-1]) from None
        if c != 1:
          raise BadFile(name, "disparity must have one channel, the file holds 3")
        problem = disparity_problem(d, hw)  # the loader's verdict, word for word
        if problem is not None:
          raise BadFile(name, problem)
        if i == 0:
          usable = usable_disparities(d)
  if "mask" in parts:
    s.image("mask0.png", hw)
  if "sl" in parts:
    counts = [s.numbered(name, _PATTERN_FILE, hw, 8) for i, name in enumerate(("sl0", "sl1"))
              if i == 0 or s.exists(name)]
    if len(counts) == 2 and counts[0] != counts[1]:
      raise BadFile("sl1", f"holds {counts[1]} patterns, sl0 holds {counts[0]}")
    t = counts[0]
  if "raw" in parts:
    for i, name in enumerate(("raw0", "raw1")):
      if i == 0 or s.exists(name):
        s.numbered(name, _RAW_FILE, hw, 16)
  if "calib" in parts:
    try:
      read_calib(s.require("calib.txt"))
    except SljaxError as e:
      raise BadFile("calib.txt", str(e).split(": ", 1)[-1]) from None
  if "meta" in parts:
    try:
      read_json_object(s.require("meta.json"), "meta.json")
    except SljaxError as e:
      raise BadFile("meta.json", str(e).split(": ", 1)[-1]) from None
  return {"hw": list(hw), "t": t, "usable": usable, "stamps": s.stamps}


def _still_valid(scene_dir: Path, entry: dict[str, Any]) -> bool:
  """Whether every file (and folder listing) a cached check read is unchanged."""
  try:
    return all(_stamp(scene_dir / name) == stamp for name, stamp in entry["stamps"].items())
  except OSError:
    return False


# ----------------------------------------------------------------------------- the dataset


def cache_dir() -> Path:
  """Where check results are kept: the user's sljax cache folder (sljax.runtime.compile_cache)."""
  return user_cache_dir()


def cache_file(root: Path) -> Path:
  """The cache file of a dataset folder (one per resolved path)."""
  digest = hashlib.sha256(str(root.resolve()).encode("utf-8")).hexdigest()[:16]
  return cache_dir() / "preflight" / f"{digest}.json"


def _load_cache(path: Path, root: Path) -> dict[str, Any]:
  # Not held to the compile cache's trust check (sljax.runtime.cache_trust): JSON runs no code.
  # A planted entry can at most skip this check of a scene, and the loader still reads every
  # file with its own checks, so a bad file then fails there, later, with the loader's error.
  try:
    data = json.loads(path.read_text(encoding="utf-8"))
  except (OSError, ValueError):
    return {}
  if data.get("version") != CACHE_VERSION or data.get("root") != str(root.resolve()):
    return {}
  return data.get("scenes", {})


def _save_cache(path: Path, root: Path, scenes: dict[str, Any]) -> None:
  """Writes the cache atomically; a cache folder that cannot be written only costs speed."""
  try:
    path.parent.mkdir(parents=True, exist_ok=True)
    files.write_text(path, json.dumps({"version": CACHE_VERSION, "root": str(root.resolve()),
                                       "scenes": scenes}))
  except OSError:
    pass


def scan(source, jobs: Sequence[tuple[Iterable[int], Iterable[str]]], *,
         progress: bool = True, use_cache: bool = True,
         disparity_sets: Sequence[Iterable[int]] | None = None
         ) -> tuple[list[str], dict[str, int]]:
  """(one line per bad scene, then one per set of scenes without a usable disparity; {'scenes',
  'cached'}) for the scenes of a FolderSource: jobs = [(scene indices, scene-folder parts to
  read)]; disparity_sets: the sets of scenes that must each hold a usable disparity (default:
  each job that reads disparities)."""
  wanted: dict[int, set[str]] = {}
  for indices, parts in jobs:
    for i in indices:
      wanted.setdefault(int(i), set()).update(parts)
  root = Path(source.root)
  path = cache_file(root)
  cache = _load_cache(path, root) if use_cache else {}
  key = lambda i: f"{source.name(i)}|{','.join(sorted(wanted[i] | {'im'}))}"
  todo = [i for i in sorted(wanted)
          if not (key(i) in cache and _still_valid(source.paths[i], cache[key(i)]))]
  fresh = set(todo)
  results: dict[int, dict[str, Any]] = {i: cache[key(i)] for i in wanted if i not in fresh}
  problems: dict[int, str] = {}

  def one(i: int) -> tuple[int, dict[str, Any] | str]:
    try:
      return i, check_scene(source.paths[i], wanted[i])
    except BadFile as e:
      return i, f"{source.paths[i] / e.file}: {e.problem}"
    except OSError as e:  # e.g. a file unreadable for its permissions
      return i, f"{source.paths[i]}: {e.strerror or e}"

  with concurrent.futures.ThreadPoolExecutor(THREADS, thread_name_prefix="sljax-check") as pool:
    for i, res in tqdm(pool.map(one, todo), total=len(todo), desc="checking data",
                       unit="scene", disable=not progress or not todo, leave=False,
                       dynamic_ncols=True):
      if isinstance(res, str):
        problems[i] = res
      else:
        results[i] = res
  if use_cache and todo:
    cache.update({key(i): r for i, r in results.items()})
    _save_cache(path, root, cache)
  counted = [(i, r["t"]) for i, r in sorted(results.items()) if r.get("t") is not None]
  declared = getattr(source, "info", {}).get("patterns")  # not num_patterns: a glob of scene 0
  expected = expected_patterns(declared, [t for _, t in counted])
  whose = (f"{root / 'dataset.json'} declares" if declared is not None else
           f"scene {source.name(counted[0][0])} holds" if counted else "")
  for i, t in counted:
    if not fits_patterns(t, expected, declared):
      problems.setdefault(i, f"{source.paths[i] / 'sl0'}: holds {t} patterns, {whose} "
                             f"{expected}")
  if disparity_sets is None:
    disparity_sets = [indices for indices, parts in jobs if "disp" in parts]
  empty = [line for indices in disparity_sets
           if (line := _without_disparity(source, list(indices), results)) is not None]
  return ([problems[i] for i in sorted(problems)] + list(dict.fromkeys(empty)),
          {"scenes": len(wanted), "cached": len(wanted) - len(todo)})


def _without_disparity(source, indices: list[int], results: dict[int, dict[str, Any]]
                       ) -> str | None:
  """The line for a set of checked scenes whose disparity maps hold no usable value (all NaN,
  inf, negative or beyond the width: training would learn nothing from them); None otherwise
  (or when a scene of the set is bad already: its own line says why)."""
  counts = [results[int(i)].get("usable") for i in indices if int(i) in results]
  if len(counts) < len(indices) or not counts or any(c is None or c > 0 for c in counts):
    return None
  return no_usable_disparity(str(source.root), len(counts))


def fits_patterns(t: int, expected: int | None, declared: Any) -> bool:
  """Whether a scene holding t patterns gives a run its `expected` patterns: exactly, or, where
  dataset.json declares the count, t or more (FolderSource then takes the coarsest)."""
  return t == expected or (declared is not None and expected is not None and t >= expected)


def expected_patterns(declared: Any, counts: Sequence[int]) -> int | None:
  """The pattern count every scene must hold: dataset.json's "patterns" where it declares them,
  else the first scene's (one network and one batch take one count); None with neither."""
  if declared is not None:
    return int(declared)
  return counts[0] if counts else None


def check(source, jobs: Sequence[tuple[Iterable[int], Iterable[str]]], *,
          progress: bool = True, use_cache: bool = True) -> dict[str, int]:
  """scan, then SljaxError naming the first bad file (and how many more scenes are bad)."""
  problems, counts = scan(source, jobs, progress=progress, use_cache=use_cache)
  if problems:
    more = f" (and {len(problems) - 1} more bad scene(s))" if len(problems) > 1 else ""
    raise SljaxError(problems[0] + more + "; checked before training, nothing was run")
  return counts


def check_run(source, batches: Sequence[tuple[Iterable[int], Sequence[str]]], *,
              progress: bool = True) -> None:
  """The check before a run's first step: batches = [(scene indices, batch parts loaded for
  them)] (training, validation); nothing for sources that are not folders (in memory)."""
  if isinstance(source, FolderSource):
    check(source, [(idx, {PART_FIELD[p][1] for p in parts}) for idx, parts in batches],
          progress=progress)
