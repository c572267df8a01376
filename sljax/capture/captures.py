"""A real rig's structured-light capture -> one scene folder: `sljax import-captures`.

Which file is which frame: sljax.capture.frames. What the import refuses: sljax.capture.refusals.

Pipeline (shared with import-scared and decode): the calibration's rectification
(sljax.capture.rig: cv2.stereoRectify, alpha 0, zero disparity), every frame resampled into it,
both views decoded and matched by sljax.sl.stereo (the row bits only check matches), the scene
written by sljax.data.scene.write_scene. With a scale, the views and raw frames are resized
(area averaging) after rectification, sl0/sl1 are decoded from the resized raw frames (so that
`sljax decode` on the scene gives the same patterns) and the disparity is measured at full
resolution and resized: a block's mean where all its pixels are known, times the scale.
"""

import dataclasses
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from sljax.capture import frames, refusals
from sljax.capture import rig as rigs
from sljax.data.scene import SEQUENCE_FOLDERS, Scene, write_scene
from sljax.errors import SljaxError, require
from sljax.io import files
from sljax.io.images import holds_12_bit, image_to_float
from sljax.sl.decode import DecodeConfig, count_patterns
from sljax.sl.stereo import MatchConfig, StereoDecoded, decode_views, match_views

CALIBRATION_FILE = "calibration.yml"  # written into the scene when the command calibrated

@dataclasses.dataclass(frozen=True)
class ImportConfig:
  """How a capture is read and decoded (the command's options)."""
  layout: str = "opencv"
  projector: tuple[int, int] | None = None  # (W, H); the opencv layout needs it
  code: str = "gray"                       # the sljax layout's code (opencv: always Gray)
  unit: str = "mm"                         # the calibration's length unit
  scale: float = 1.0                       # resize factor of the written scene
  group: str | None = None                 # meta.json group (default: the scene's name)
  decode: DecodeConfig = DecodeConfig()
  match: MatchConfig = MatchConfig()
  row_check: bool = True                   # use the row bits (opencv layout) to check matches


@dataclasses.dataclass(frozen=True)
class ImportReport:
  """What an import wrote and found."""
  out: Path
  size: tuple[int, int]                      # written (width, height)
  valid: tuple[float, float]                 # share of pixels with a disparity, per view
  ranges: tuple[tuple[float, float] | None, ...]  # disparity range per view
  decoded: tuple[float, float]               # share of pixels with a decoded column, per view
  row_rejected: int                          # left matches refused by the row check
  implausible: tuple[int, int]               # matches below 0 or above the width, per view
  match_bits: int                            # column bits the matching used
  bit_depth: int                             # 8, 12 or 16 bits of the frames
  views: str                                 # "ambient" or "white": what im0/im1 show
  seconds: dict[str, float]                  # time per stage


@dataclasses.dataclass
class _View:
  """One camera's rectified frames (grey, the frames' dtype) and its rectified colour view."""
  frames: dict[str, np.ndarray]
  colour: np.ndarray
  peak: int
  dtype: np.dtype


def _rectify_view(roles: dict[str, Path], keep: Sequence[str], colour_role: str | Path,
                  maps, size: tuple[int, int], what: str, bar, seconds: dict[str, float]
                  ) -> _View:
  """Reads and rectifies one camera's frames (those in keep) and its colour view."""
  rectified, peak, dtype, colour = {}, 0, None, None
  todo = [(role, roles[role]) for role in keep]
  if isinstance(colour_role, Path):
    todo.append(("", colour_role))
  for role, path in todo:
    start = time.perf_counter()
    img = frames.read_frame(path)
    h, w = img.shape[:2]
    require((w, h) == tuple(size), f"{path}: size {w}x{h} differs from the first {what} frame's "
            f"{size[0]}x{size[1]}")
    dtype = dtype or img.dtype
    require(img.dtype == dtype, f"{path}: {img.dtype.itemsize * 8}-bit, the other {what} frames "
            f"are {dtype.itemsize * 8}-bit")
    peak = max(peak, int(img.max()))
    g = frames.grey(img)
    seconds["read"] += time.perf_counter() - start
    start = time.perf_counter()
    if role:
      rectified[role] = rigs.remap(g, maps)
    if role == colour_role or not role:
      colour = rigs.remap(img, maps)
    seconds["rectify"] += time.perf_counter() - start
    bar.update(1)
  return _View(rectified, colour, peak, np.dtype(dtype))


def _to_16_bit(image: np.ndarray) -> np.ndarray:
  """12-bit values in a uint16 array scaled to the 16-bit range."""
  return np.round(image.astype(np.float32) * np.float32(65535.0 / 4095.0)).astype(np.uint16)


def _resize(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
  """Area-averaged resize to (width, height), dtype kept."""
  return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def resize_disparity(disp: np.ndarray, size: tuple[int, int], scale: float) -> np.ndarray:
  """A disparity map resized to (width, height): a new pixel's value is the area mean of the
  pixels it covers where all are known (else inf), times scale."""
  known = np.isfinite(disp)
  total = _resize(np.where(known, disp, 0.0).astype(np.float32), size)
  share = _resize(known.astype(np.float32), size)
  full = share > 1.0 - 1e-4
  return np.where(full, total / np.where(full, share, 1.0) * scale, np.inf).astype(np.float32)


def _targets(out: Path, with_calibration: bool) -> list[str]:
  """The files and folders an import writes into the scene."""
  names = ["im0.png", "im1.png", "disp0.pfm", "disp1.pfm", "calib.txt", "meta.json", "sl0", "sl1",
           "raw0", "raw1"]
  return names + ([CALIBRATION_FILE] if with_calibration else [])


def refuse_existing(out: Path, with_calibration: bool, overwrite: bool) -> None:
  """SljaxError naming the first file the import would replace, unless overwrite (checked
  before reading any frame)."""
  if out.exists() and not out.is_dir():
    raise SljaxError(f"{out}: exists and is not a folder")
  if overwrite or not out.is_dir():
    return
  for name in _targets(out, with_calibration):
    path = out / name
    if path.is_dir():
      inside = sorted(p.name for p in path.iterdir() if not files.is_temporary(p))
      if inside:
        raise SljaxError(f"scene {out}: {name}/{inside[0]}: exists (use --overwrite to replace it)")
    elif path.exists():
      raise SljaxError(f"scene {out}: {name}: exists (use --overwrite to replace it)")


def _share_and_range(d: np.ndarray) -> tuple[float, tuple[float, float] | None]:
  known = d[np.isfinite(d)]
  return float(known.size / d.size), (float(known.min()), float(known.max())) if known.size \
      else None


def _read_views(roles: list[dict[str, Path]], keep: list[str], ambient: list[Path] | None,
                calibration: rigs.StereoCalibration, progress: bool, seconds: dict[str, float]
                ) -> tuple[list[_View], rigs.Rectification, int]:
  """Both cameras' frames (the roles in keep) and colour views, rectified; 12-bit data scaled
  to the 16-bit range. Returns (views, rectification, bits of the frames: 8, 12 or 16)."""
  first = frames.read_frame(roles[0]["white"])
  size = (first.shape[1], first.shape[0])
  rigs.check_size(calibration, size, f"the frame {roles[0]['white']}")
  rect = rigs.rectify(calibration, size)
  maps = rigs.rectify_maps(calibration, rect)
  total = 2 * (len(keep) + (ambient is not None))
  with tqdm(total=total, desc="import-captures: frames", unit="frame", file=sys.stderr,
            disable=not progress or None, leave=False) as bar:
    views = [_rectify_view(roles[i], keep, "white" if ambient is None else ambient[i],
                           maps[i], size, what, bar, seconds)
             for i, what in enumerate(("LEFT", "RIGHT"))]
  require(views[0].dtype == views[1].dtype, f"RIGHT frames are {views[1].dtype.itemsize * 8}-bit, "
          f"LEFT frames {views[0].dtype.itemsize * 8}-bit")
  if not holds_12_bit(max(v.peak for v in views), views[0].dtype):
    return views, rect, views[0].dtype.itemsize * 8
  for v in views:
    v.frames = {k: _to_16_bit(f) for k, f in v.frames.items()}
    v.colour = _to_16_bit(v.colour)
  return views, rect, 12


def _timed(seconds: dict[str, float], stage: str, fn, *args, **kwargs):
  """fn(*args, **kwargs), its wall time added to seconds[stage]."""
  start = time.perf_counter()
  try:
    return fn(*args, **kwargs)
  finally:
    seconds[stage] += time.perf_counter() - start


def import_captures(left: str | os.PathLike, right: str | os.PathLike, out: str | os.PathLike,
                    calibration: rigs.StereoCalibration, config: ImportConfig = ImportConfig(),
                    *, ambient: tuple[str | os.PathLike, str | os.PathLike] | None = None,
                    overwrite: bool = False, save_calibration: bool = False,
                    progress: bool = True) -> ImportReport:
  """Rectifies, decodes and matches one capture and writes it as the scene folder out."""
  out = Path(out)
  require(config.unit in rigs.UNITS_MM, f"--unit {config.unit!r}: expected one of "
          f"{', '.join(rigs.UNITS_MM)}")
  require(np.isfinite(config.scale) and 0 < config.scale <= 1,
          f"--scale {config.scale:g}: must be in (0, 1] (it downsizes)")
  refuse_existing(out, save_calibration, overwrite)
  rigs.check_rig(calibration, "are LEFT and RIGHT, or the cameras of the calibration, swapped?")
  roles = [frames.assign_roles(frames.list_frames(spec, what), config.layout, config.projector,
                              what)
           for spec, what in ((left, "LEFT"), (right, "RIGHT"))]
  differ = sorted(set(roles[0]) ^ set(roles[1]))
  require(not differ, f"RIGHT: its frames differ from LEFT's ({', '.join(differ[:4])} in one "
          "camera only)")
  ambient_paths = None if ambient is None else [Path(p) for p in ambient]
  for p in ambient_paths or []:
    require(p.is_file(), f"--ambient {p}: {'is a folder' if p.exists() else 'missing'}")

  columns = [k for k in roles[0] if k[0] in "pi" or k in ("white", "black")]
  rows = [k for k in roles[0] if k.startswith("r")] if config.row_check else []
  seconds = {"read": 0.0, "rectify": 0.0, "decode": 0.0, "match": 0.0, "write": 0.0}
  views, rect, bits = _read_views(roles, columns + rows, ambient_paths, calibration, progress,
                                  seconds)
  raws = [{k: v.frames[k] for k in columns} for v in views]
  row_raws = None if not rows else [
      {"white": v.frames["white"], "black": v.frames["black"],
       **{k[1:]: v.frames[k] for k in rows}} for v in views]
  code = "gray" if config.layout == "opencv" else config.code
  projector = config.projector or (None, None)
  result = _timed(seconds, "decode", decode_views, raws[0], raws[1], code, config.decode,
                  projector=projector, rows=row_raws,
                  where=("LEFT (rectified)", "RIGHT (rectified)"))
  named = (f"LEFT {os.fspath(left)}", f"RIGHT {os.fspath(right)}")
  refusals.check_lit(result, named)
  _timed(seconds, "match", match_views, result, config.match)
  refusals.check_rows(result, named, calibration.where)
  refusals.check_signs(result, named)
  result.disp0, result.disp1, implausible = refusals.plausible(
      result.disp0, result.disp1, rect.size[0], config.match.lr_tolerance)

  size = (rigs.scaled_length(rect.size[0], config.scale),
          rigs.scaled_length(rect.size[1], config.scale))
  disp, ims = [result.disp0, result.disp1], [v.colour for v in views]
  patterns = [result.left.bits, result.right.bits]
  if config.scale != 1.0:
    disp = [resize_disparity(d, size, config.scale) for d in disp]
    ims = [_resize(im, size) for im in ims]
    raws = [{k: _resize(f, size) for k, f in raw.items()} for raw in raws]
    # The patterns of the written (resized) raw frames, as sljax decode would find them.
    small = _timed(seconds, "decode", decode_views, raws[0], raws[1], code, config.decode,
                   projector=projector)
    patterns = [small.left.bits, small.right.bits]

  shares = [_share_and_range(d) for d in disp]
  scene = Scene(name=out.name, im0=image_to_float(ims[0], str(out / "im0.png")),
                im1=image_to_float(ims[1], str(out / "im1.png")), disp0=disp[0], disp1=disp[1],
                sl0=patterns[0], sl1=patterns[1], raw0=raws[0], raw1=raws[1],
                calib=rect.calib(rigs.UNITS_MM[config.unit], disp, config.scale),
                meta=_meta(out, roles, ambient_paths, config, calibration, rect, bits, shares,
                           result, implausible, save_calibration))
  # The scene and its calibration are written into a hidden folder and moved in together: a
  # failure or Ctrl-C while writing leaves OUT_SCENE as it was (refuse_existing checked it).
  with files.staged(out, whole=SEQUENCE_FOLDERS) as stage:
    _timed(seconds, "write", write_scene, stage, scene, overwrite=overwrite,
           bit_depth=8 if bits == 8 else 16)
    if save_calibration:
      _timed(seconds, "write", rigs.write_calibration, stage / CALIBRATION_FILE, calibration)
  decoded = tuple(float(np.isfinite(v.column).mean()) for v in (result.left, result.right))
  return ImportReport(out=out, size=size, valid=(shares[0][0], shares[1][0]),
                      ranges=(shares[0][1], shares[1][1]), decoded=decoded,
                      row_rejected=result.row_rejected, implausible=implausible,
                      match_bits=result.bits, bit_depth=bits,
                      views="white" if ambient_paths is None else "ambient", seconds=seconds)


def _relative(path: Path, out: Path) -> str:
  """path as seen from the scene folder out (meta.json travels with the scene)."""
  return os.path.relpath(path.resolve(), out.resolve())


def _calibration_source(calibration: rigs.StereoCalibration, out: Path, saved: bool) -> str:
  """meta.json's "calibration": the file(s) read, relative to the scene, or the one saved in it."""
  if saved:
    return CALIBRATION_FILE
  if calibration.files:
    return " + ".join(_relative(Path(p), out) for p in calibration.files)
  return calibration.where


def _meta(out: Path, roles, ambient, config: ImportConfig, calibration, rect, bits: int,
          shares, result: StereoDecoded, implausible: tuple[int, int], saved: bool) -> dict:
  """meta.json of an imported capture (file paths relative to the scene folder)."""
  n = count_patterns({k: None for k in roles[0] if k[0] in "pi"}, "frames")
  meta = {
      "group": config.group or out.resolve().name, "code": "gray" if config.layout == "opencv"
      else config.code, "source": "import-captures", "layout": config.layout,
      "patterns": n, "views": "white" if ambient is None else "ambient",
      "frames": {view: {role: _relative(p, out) for role, p in r.items()}
                 for view, r in zip(("left", "right"), roles)},
      "bit_depth": bits, "calibration": _calibration_source(calibration, out, saved),
      "unit": config.unit,
      "rectification": {**rect.meta(), "alpha": rigs.RECTIFY_ALPHA, "width": rect.size[0],
                        "height": rect.size[1]},
      "scale": config.scale,
      "decode": dataclasses.asdict(config.decode), "match": dataclasses.asdict(config.match),
      "valid": {"left": shares[0][0], "right": shares[1][0]}, "match_bits": result.bits,
      "implausible": {"left": implausible[0], "right": implausible[1]},
  }
  if config.projector is not None:
    meta["projector"] = list(config.projector)
  if ambient is not None:
    meta["frames"]["ambient"] = [_relative(p, out) for p in ambient]
  if result.rows is not None:
    meta["row_check"] = {"row_tolerance": config.match.row_tolerance,
                         "rejected_left": result.row_rejected, "checked_left": result.row_checked}
  return meta
