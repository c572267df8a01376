"""One stereo scene in memory, as every scene source (folder, synthetic, SCARED) yields it."""

import dataclasses
import json
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from sljax.data.camera import Calib, calib_text, read_calib
from sljax.data.checks import disparity_problem
from sljax.data.pfm import read_pfm, write_pfm
from sljax.errors import SljaxError
from sljax.io import files
from sljax.io.files import read_json_object
from sljax.io.images import decode, png_pixels, read_image


@dataclasses.dataclass
class Scene:
  """A rectified stereo scene; parts a source lacks are None.

  Conventions: images float32 in [0, 1], HxWxC (C = 1 or 3); disparities float32 HxW,
  left-referenced, inf = unknown; patterns float32 HxWxt, 1 = lit, 0 = dark, NaN = unknown;
  raw captures float32 HxW in [0, 1] keyed 'white', 'black', 'p000'..., 'i000'....
  """
  name: str
  im0: np.ndarray
  im1: np.ndarray
  disp0: np.ndarray | None = None
  disp1: np.ndarray | None = None
  mask0: np.ndarray | None = None  # bool HxW, region of interest for "Seg" metrics
  sl0: np.ndarray | None = None
  sl1: np.ndarray | None = None
  raw0: dict[str, np.ndarray] | None = None
  raw1: dict[str, np.ndarray] | None = None
  calib: Calib | None = None
  meta: dict[str, Any] = dataclasses.field(default_factory=dict)

  @property
  def group(self) -> str:
    """Group id for group-level splits; a scene without one is its own group."""
    return str(self.meta.get("group", self.name))

  @property
  def shape(self) -> tuple[int, int]:
    """(height, width) of the views."""
    return self.im0.shape[:2]


UNKNOWN_PATTERN = 128  # on-disk value of an unknown pattern pixel (0 = dark, 255 = lit)
PARTS = frozenset({"im", "disp", "mask", "sl", "raw", "calib", "meta"})
_PATTERN_FILE = re.compile(r"^(\d{3,})\.png$")
_RAW_FILE = re.compile(r"^(white|black|[pi]\d{3,})\.png$")
# Folders holding one numbered sequence, written whole by write_patterns / write_raw (a shorter
# new sequence drops the old one's extra planes): staged outputs replace them, never merge in.
SEQUENCE_FOLDERS = frozenset({"sl0", "sl1", "raw0", "raw1"})


def _fail(scene_dir: Path, file: str, problem: str) -> SljaxError:
  return SljaxError(f"scene {scene_dir}: {file}: {problem}")


def patterns_to_png(patterns: np.ndarray) -> np.ndarray:
  """Float patterns (1 lit, 0 dark, NaN unknown) -> uint8 0/255/UNKNOWN_PATTERN."""
  p = np.asarray(patterns, dtype=np.float32)
  out = np.where(p >= 0.5, 255, 0).astype(np.uint8)
  out[np.isnan(p)] = UNKNOWN_PATTERN
  return out


def patterns_from_png(values: np.ndarray) -> np.ndarray:
  """uint8 pattern pixels -> float32 1/0/NaN; exactly UNKNOWN_PATTERN is unknown, else > 127 lit."""
  v = np.asarray(values)
  out = (v > 127).astype(np.float32)
  out[v == UNKNOWN_PATTERN] = np.nan
  return out


def _numbered_files(folder: Path, pattern: re.Pattern) -> list[Path]:
  return sorted((p for p in folder.iterdir() if pattern.match(p.name)),
                key=lambda p: (len(p.name), p.name))


def read_patterns(folder: str | os.PathLike) -> np.ndarray:
  """Reads folder/000.png, 001.png, ... (coarsest first) into HxWxt float32, NaN unknown."""
  folder = Path(folder)
  if not folder.is_dir():
    raise SljaxError(f"{folder}: missing pattern folder")
  planes_found = _numbered_files(folder, _PATTERN_FILE)
  if not planes_found:
    raise SljaxError(f"{folder}: no pattern images 000.png, 001.png, ...")
  numbers = [int(_PATTERN_FILE.match(p.name).group(1)) for p in planes_found]
  if numbers != list(range(len(planes_found))):
    missing = sorted(set(range(max(numbers) + 1)) - set(numbers))
    raise SljaxError(f"{folder}: pattern images are not numbered "
                     f"000..{len(planes_found) - 1:03d} "
                     f"(missing {', '.join(f'{m:03d}.png' for m in missing[:5])})")
  planes = []
  for p in planes_found:
    # Sized from its header first: every plane has the first one's size.
    v = decode(p, planes[0].shape[:2] if planes else None, planes_found[0].name)
    if v.dtype != np.uint8:
      raise SljaxError(f"{p}: pattern images must be 8-bit (0 dark, 255 lit, 128 unknown)")
    if v.ndim == 3:
      v = v[..., 0]
    if planes and v.shape != planes[0].shape:
      raise SljaxError(f"{p}: size {v.shape[1]}x{v.shape[0]} differs from "
                       f"{planes_found[0].name} ({planes[0].shape[1]}x{planes[0].shape[0]})")
    planes.append(v)
  return patterns_from_png(np.stack(planes, axis=-1))


def write_patterns(folder: str | os.PathLike, patterns: np.ndarray,
                   overwrite: bool = False) -> None:
  """Writes HxWxt patterns as folder/000.png ... (0/255, UNKNOWN_PATTERN for NaN)."""
  folder = Path(folder)
  p = np.asarray(patterns)
  if p.ndim != 3:
    raise SljaxError(f"{folder}: patterns must be HxWxt, got shape {p.shape}")
  existing = _numbered_files(folder, _PATTERN_FILE) if folder.is_dir() else []
  if existing and not overwrite:
    raise SljaxError(f"{existing[0]}: exists (use --overwrite / overwrite=True to replace it)")
  folder.mkdir(parents=True, exist_ok=True)
  png = patterns_to_png(p)
  paths = [folder / f"{k:03d}.png" for k in range(png.shape[2])]
  # All planes or none: the old sequence is replaced only once every new plane is written.
  with files.replacing(*paths) as tmps:
    for k, tmp in enumerate(tmps):
      tmp.write_bytes(files.encode_png(png[..., k], paths[k]))
  for old in set(existing) - set(paths):  # a shorter sequence must not leave stale planes
    old.unlink()


def read_raw(folder: str | os.PathLike) -> dict[str, np.ndarray]:
  """Reads raw captures (white, black, p000..., i000...) as HxW float32 gray in [0, 1]."""
  folder = Path(folder)
  if not folder.is_dir():
    raise SljaxError(f"{folder}: missing raw capture folder")
  captures = _numbered_files(folder, _RAW_FILE)
  if not captures:
    raise SljaxError(f"{folder}: no raw captures (white.png, black.png, p000.png, ...)")
  out: dict[str, np.ndarray] = {}
  for p in captures:
    first = next(iter(out.items()), None)
    out[p.stem] = read_image(p, gray=True, want_hw=None if first is None else first[1].shape,
                             against="" if first is None else f"{first[0]}.png")[..., 0]
  return out


def write_raw(folder: str | os.PathLike, raw: dict[str, np.ndarray], bit_depth: int = 8,
              overwrite: bool = False) -> None:
  """Writes raw captures as gray PNGs named by their keys (white, black, p000, ...)."""
  folder = Path(folder)
  for key in raw:
    if not _RAW_FILE.match(f"{key}.png"):
      raise SljaxError(f"{folder}: raw capture key {key!r} is not white, black, pNNN or iNNN")
  existing = _numbered_files(folder, _RAW_FILE) if folder.is_dir() else []
  if existing and not overwrite:
    raise SljaxError(f"{existing[0]}: exists (use --overwrite / overwrite=True to replace it)")
  paths = [folder / f"{key}.png" for key in raw]
  pixels = [png_pixels(path, img, bit_depth) for path, img in zip(paths, raw.values())]
  folder.mkdir(parents=True, exist_ok=True)
  for path, q in zip(paths, pixels):  # each written whole; stale captures go last
    files.write_png(path, q)
  for old in set(existing) - set(paths):
    old.unlink()


def present_parts(path: str | os.PathLike) -> dict[str, list[str]]:
  """Which parts a scene folder holds: {part: [files or folders present]}, cheap (no decoding)."""
  path = Path(path)
  names = {
      "im": ["im0.png", "im1.png"], "disp": ["disp0.pfm", "disp1.pfm"], "mask": ["mask0.png"],
      "sl": ["sl0", "sl1"], "raw": ["raw0", "raw1"], "calib": ["calib.txt"], "meta": ["meta.json"],
  }
  out = {}
  for part, candidates in names.items():
    found = [f for f in candidates if (path / f).exists()]
    if found:
      out[part] = found
  return out


def _check_size(scene_dir: Path, file: str, array: np.ndarray, hw: tuple[int, int]) -> None:
  if tuple(array.shape[:2]) != tuple(hw):
    raise _fail(scene_dir, file, f"size {array.shape[1]}x{array.shape[0]} differs from "
                f"im0.png ({hw[1]}x{hw[0]})")


def load_scene(path: str | os.PathLike, gray: bool | None = None,
               parts: set[str] | None = None) -> Scene:
  """Loads a scene folder (a superset of a Middlebury 2014 scene) into a Scene.

  parts: subset of PARTS; None loads everything present. The views (im0/im1) are always
  loaded. An explicitly requested part whose left-view file (disp0.pfm, mask0.png, sl0/,
  raw0/, calib.txt, meta.json) is absent raises SljaxError; right-view files are loaded
  when present. gray: None keeps the file's channels, True -> HxWx1, False -> HxWx3.
  """
  scene_dir = Path(path)
  if not scene_dir.is_dir():
    raise SljaxError(f"scene {scene_dir}: not a folder")
  explicit = parts is not None
  parts = set(PARTS) if parts is None else set(parts)
  unknown = parts - PARTS
  if unknown:
    raise SljaxError(f"scene {scene_dir}: unknown part(s) {sorted(unknown)}; "
                     f"choose from {sorted(PARTS)}")

  def need(file: str) -> bool:
    """True when the file is there; raises when it was explicitly requested but absent."""
    if (scene_dir / file).exists():
      return True
    if explicit:
      raise _fail(scene_dir, file, "missing")
    return False

  for f in ("im0.png", "im1.png"):
    if not (scene_dir / f).exists():
      raise _fail(scene_dir, f, "missing")
  im0 = read_image(scene_dir / "im0.png", gray)
  hw = im0.shape[:2]
  im1 = read_image(scene_dir / "im1.png", gray, want_hw=hw)  # sized before it is decoded
  if im0.shape[2] != im1.shape[2]:  # one gray, one colour file: promote the gray one
    im0, im1 = (np.repeat(im, 3, axis=2) if im.shape[2] == 1 else im for im in (im0, im1))
  scene = Scene(name=scene_dir.name, im0=im0, im1=im1)

  if "disp" in parts:
    for i, f in enumerate(("disp0.pfm", "disp1.pfm")):
      if (need(f) if i == 0 else (scene_dir / f).exists()):
        d = read_pfm(scene_dir / f)
        problem = disparity_problem(d, hw)  # the pre-flight's and info's verdict too
        if problem is not None:
          raise _fail(scene_dir, f, problem)
        setattr(scene, f[:5], d)
  if "mask" in parts and need("mask0.png"):
    m = decode(scene_dir / "mask0.png", hw)
    scene.mask0 = m.reshape(m.shape[0], m.shape[1], -1).any(axis=2)
  if "sl" in parts:
    for i, f in enumerate(("sl0", "sl1")):
      if (need(f) if i == 0 else (scene_dir / f).exists()):
        p = read_patterns(scene_dir / f)
        _check_size(scene_dir, f, p, hw)
        setattr(scene, f, p)
    if scene.sl0 is not None and scene.sl1 is not None and scene.sl0.shape != scene.sl1.shape:
      raise _fail(scene_dir, "sl1", f"holds {scene.sl1.shape[2]} patterns, "
                  f"sl0 holds {scene.sl0.shape[2]}")
  if "raw" in parts:
    for i, f in enumerate(("raw0", "raw1")):
      if (need(f) if i == 0 else (scene_dir / f).exists()):
        raw = read_raw(scene_dir / f)
        _check_size(scene_dir, f, next(iter(raw.values())), hw)
        setattr(scene, f, raw)
    if scene.raw0 is not None and scene.raw1 is not None and set(scene.raw0) != set(scene.raw1):
      diff = sorted(set(scene.raw0) ^ set(scene.raw1))
      raise _fail(scene_dir, "raw1", f"captures differ from raw0 ({', '.join(diff[:5])})")
  if "calib" in parts and need("calib.txt"):
    scene.calib = read_calib(scene_dir / "calib.txt")
  if "meta" in parts and need("meta.json"):
    scene.meta = read_json_object(scene_dir / "meta.json", f"scene {scene_dir}: meta.json")
  return scene


def _json_default(value: Any) -> Any:
  if isinstance(value, np.generic):
    return value.item()
  if isinstance(value, np.ndarray):
    return value.tolist()
  if isinstance(value, Path):
    return str(value)
  raise TypeError(f"cannot store {type(value).__name__} in meta.json")


def write_scene(path: str | os.PathLike, scene: Scene, overwrite: bool = False,
                bit_depth: int = 8) -> None:
  """Writes the non-None parts of a scene as a scene folder (images as bit_depth-bit PNG).

  Nothing is written when any target file exists and overwrite is False.
  """
  scene_dir = Path(path)
  for name in ("im0", "im1"):
    if np.ndim(getattr(scene, name)) not in (2, 3):
      raise _fail(scene_dir, name, f"must be an HxW or HxWxC image, got "
                  f"{type(getattr(scene, name)).__name__} of shape {np.shape(getattr(scene, name))}")
  hw = tuple(np.shape(scene.im0)[:2])
  _check_size(scene_dir, "im1", np.asarray(scene.im1), hw)
  for name in ("disp0", "disp1", "mask0", "sl0", "sl1"):
    value = getattr(scene, name)
    if value is not None:
      _check_size(scene_dir, name, np.asarray(value), hw)
  if scene.sl0 is not None and scene.sl1 is not None and scene.sl0.shape != scene.sl1.shape:
    raise _fail(scene_dir, "sl1", f"holds {scene.sl1.shape[-1]} patterns, "
                f"sl0 holds {scene.sl0.shape[-1]}")

  targets = ["im0.png", "im1.png"]
  targets += [f for f, v in (("disp0.pfm", scene.disp0), ("disp1.pfm", scene.disp1),
                             ("mask0.png", scene.mask0), ("calib.txt", scene.calib),
                             ("meta.json", scene.meta or None)) if v is not None]
  if not overwrite:
    for f in targets:
      if (scene_dir / f).exists():
        raise _fail(scene_dir, f, "exists (use --overwrite / overwrite=True to replace it)")
    for folder, pattern in (("sl0", _PATTERN_FILE), ("sl1", _PATTERN_FILE),
                            ("raw0", _RAW_FILE), ("raw1", _RAW_FILE)):
      if getattr(scene, folder) is not None and (scene_dir / folder).is_dir():
        existing = _numbered_files(scene_dir / folder, pattern)
        if existing:
          raise _fail(scene_dir, f"{folder}/{existing[0].name}", "exists (use --overwrite / overwrite=True to replace it)")

  # Everything that can be refused is checked before the first file is written.
  views = [png_pixels(scene_dir / f"{v}.png", getattr(scene, v), bit_depth) for v in ("im0", "im1")]
  for folder in ("raw0", "raw1"):
    for key, capture in (getattr(scene, folder) or {}).items():
      png_pixels(scene_dir / folder / f"{key}.png", capture, bit_depth)
  calib = None if scene.calib is None else calib_text(scene.calib, str(scene_dir / "calib.txt"))
  meta = _meta_text(scene_dir, scene.meta) if scene.meta else None

  scene_dir.mkdir(parents=True, exist_ok=True)
  files.write_png(scene_dir / "im0.png", views[0])
  files.write_png(scene_dir / "im1.png", views[1])
  if scene.disp0 is not None:
    write_pfm(scene_dir / "disp0.pfm", scene.disp0)
  if scene.disp1 is not None:
    write_pfm(scene_dir / "disp1.pfm", scene.disp1)
  if scene.mask0 is not None:
    m = np.where(np.asarray(scene.mask0).reshape(hw) != 0, 255, 0).astype(np.uint8)
    files.write_png(scene_dir / "mask0.png", m)
  if scene.sl0 is not None:
    write_patterns(scene_dir / "sl0", scene.sl0, overwrite=True)
  if scene.sl1 is not None:
    write_patterns(scene_dir / "sl1", scene.sl1, overwrite=True)
  if scene.raw0 is not None:
    write_raw(scene_dir / "raw0", scene.raw0, bit_depth, overwrite=True)
  if scene.raw1 is not None:
    write_raw(scene_dir / "raw1", scene.raw1, bit_depth, overwrite=True)
  if calib is not None:
    files.write_text(scene_dir / "calib.txt", calib)
  if meta is not None:
    files.write_text(scene_dir / "meta.json", meta)


def _meta_text(scene_dir: Path, meta: dict[str, Any]) -> str:
  """meta.json's text; SljaxError naming the scene when a value has no JSON form."""
  try:
    return json.dumps(meta, indent=2, sort_keys=True, default=_json_default) + "\n"
  except (TypeError, ValueError) as e:
    raise _fail(scene_dir, "meta.json", f"cannot be written: {e}") from None
