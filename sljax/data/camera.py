"""Middlebury 2014 calib.txt: the camera model of a rectified stereo pair."""

import dataclasses
import os

import numpy as np

from sljax.errors import SljaxError
from sljax.io import files


@dataclasses.dataclass(frozen=True)
class Calib:
  """Rectified stereo calibration with Middlebury 2014 keys (baseline in mm)."""
  cam0: np.ndarray  # 3x3 intrinsics of the left camera
  cam1: np.ndarray  # 3x3 intrinsics of the right camera
  doffs: float      # x-difference of the principal points, cx1 - cx0 (pixels)
  baseline: float   # mm
  width: int
  height: int
  ndisp: int
  vmin: float | None = None
  vmax: float | None = None

  @property
  def focal(self) -> float:
    """Focal length of the left camera in pixels."""
    return float(self.cam0[0, 0])


_REQUIRED = ("cam0", "cam1", "doffs", "baseline", "width", "height", "ndisp")


def _parse_matrix(text: str, path: str, key: str) -> np.ndarray:
  """Parses Middlebury matrix syntax `[f 0 cx; 0 f cy; 0 0 1]` into a 3x3 float64 array."""
  body = text.strip()
  if not (body.startswith("[") and body.endswith("]")):
    raise SljaxError(f"{path}: key {key!r} must be a matrix like [f 0 cx; 0 f cy; 0 0 1], "
                     f"got {text.strip()!r}")
  try:
    rows = [[float(v) for v in row.replace(",", " ").split()]
            for row in body[1:-1].split(";")]
  except ValueError:
    raise SljaxError(f"{path}: key {key!r} holds a non-number: {text.strip()!r}") from None
  if len(rows) != 3 or any(len(r) != 3 for r in rows):
    raise SljaxError(f"{path}: key {key!r} must be a 3x3 matrix, got {text.strip()!r}")
  return np.array(rows, dtype=np.float64)


def _same_number(a: str, b: str) -> bool:
  """Whether two value texts are one number however written (176.252 and 176.2520)."""
  try:
    return float(a) == float(b)
  except ValueError:
    return False


def _format_number(value: float) -> str:
  """Writes integers without a decimal point and other numbers with full precision."""
  value = float(value)
  if value.is_integer() and abs(value) < 1e15:
    return str(int(value))
  return repr(value)


def _format_matrix(m: np.ndarray) -> str:
  return "[" + "; ".join(" ".join(_format_number(v) for v in row) for row in np.asarray(m)) + "]"


def read_calib(path: str | os.PathLike) -> Calib:
  """Reads a Middlebury 2014 calib.txt; unknown keys (isint, dyavg, dymax, ...) are ignored."""
  path = os.fspath(path)
  try:
    # utf-8-sig: a byte-order mark (Windows editors) would otherwise glue onto "cam0".
    with open(path, encoding="utf-8-sig") as f:
      lines = f.read().splitlines()
  except OSError as e:
    raise SljaxError(f"{path}: cannot read calibration ({e.strerror or e})") from None
  except UnicodeDecodeError as e:  # a binary or damaged file in calib.txt's place
    raise SljaxError(f"{path}: not a text calibration file (the byte at offset {e.start} is "
                     "not UTF-8 text; expected Middlebury 'key=value' lines)") from None
  values: dict[str, str] = {}
  first_line: dict[str, int] = {}
  for n, line in enumerate(lines, 1):
    if not line.strip() or line.lstrip().startswith("#"):
      continue
    key, sep, value = line.partition("=")
    if not sep:
      raise SljaxError(f"{path}: line {n} is not 'key=value': {line.strip()!r}")
    key, value = key.strip(), value.strip()
    if key in values and values[key].split() != value.split() and not _same_number(
        values[key], value):  # two files pasted together: which one is meant?
      raise SljaxError(f"{path}: line {n} gives {key!r} again with another value ({value!r}; "
                       f"line {first_line[key]}: {values[key]!r})")
    values[key] = value
    first_line.setdefault(key, n)
  missing = [k for k in _REQUIRED if k not in values]
  if missing:
    raise SljaxError(f"{path}: calibration lacks required key(s) {', '.join(missing)}")

  def number(key: str) -> float:
    try:
      return float(values[key])
    except ValueError:
      raise SljaxError(f"{path}: key {key!r} is not a number: {values[key]!r}") from None

  def integer(key: str) -> int:
    v = number(key)
    if not v.is_integer():
      raise SljaxError(f"{path}: key {key!r} must be an integer, got {values[key]!r}")
    return int(v)

  for key in ("width", "height", "ndisp"):
    if integer(key) <= 0:
      raise SljaxError(f"{path}: key {key!r} must be positive, got {values[key]!r}")
  vmin = number("vmin") if "vmin" in values else None
  vmax = number("vmax") if "vmax" in values else None
  if vmin is not None and vmax is not None and not vmin <= vmax:
    raise SljaxError(f"{path}: vmin={values['vmin']} is not at most vmax={values['vmax']} "
                     "(they are the smallest and largest disparity present)")
  calib = Calib(
      cam0=_parse_matrix(values["cam0"], path, "cam0"),
      cam1=_parse_matrix(values["cam1"], path, "cam1"),
      doffs=number("doffs"),
      baseline=number("baseline"),
      width=integer("width"),
      height=integer("height"),
      ndisp=integer("ndisp"),
      vmin=vmin,
      vmax=vmax)
  # Refused here, where every reader reads it (the loader, the pre-flight, info, predict), not
  # first by the depth code when a run or an evaluation is half done.
  problem = calib_problem(calib)
  if problem is not None:
    raise SljaxError(f"{path}: {problem}")
  return calib


def calib_text(calib: Calib, where: str = "calib") -> str:
  """calib.txt's text in Middlebury 2014 syntax (vmin/vmax only when set); SljaxError for
  intrinsics that are not 3x3 or for values that are not numbers."""
  try:
    cams = [np.asarray(m, dtype=np.float64) for m in (calib.cam0, calib.cam1)]
    if any(m.shape != (3, 3) for m in cams):
      raise ValueError(f"cam0 and cam1 must be 3x3, got {cams[0].shape} and {cams[1].shape}")
    lines = [f"cam0={_format_matrix(cams[0])}", f"cam1={_format_matrix(cams[1])}",
             f"doffs={_format_number(float(calib.doffs))}",
             f"baseline={_format_number(float(calib.baseline))}",
             f"width={int(calib.width)}", f"height={int(calib.height)}",
             f"ndisp={int(calib.ndisp)}"]
    lines += [f"{k}={_format_number(float(v))}" for k, v in
              (("vmin", calib.vmin), ("vmax", calib.vmax)) if v is not None]
  except (TypeError, ValueError, AttributeError) as e:
    raise SljaxError(f"{where}: cannot be written: {e}") from None
  return "\n".join(lines) + "\n"


def write_calib(path: str | os.PathLike, calib: Calib) -> None:
  """Writes calib.txt in Middlebury 2014 syntax (vmin/vmax only when set)."""
  files.write_text(path, calib_text(calib, os.fspath(path)))


def calib_problem(calib: Calib) -> str | None:
  """Why a calibration cannot give depth (a focal length or baseline not positive, a value not
  finite); None when it can."""
  fy = float(np.asarray(calib.cam0, dtype=np.float64)[1, 1])
  # A zero or negative f, fy or baseline gives zero, negative or infinite depths, not an error.
  if not all(np.isfinite(v) and v > 0 for v in (calib.focal, fy, calib.baseline)):
    return (f"calibration needs a positive focal length and baseline, got "
            f"f = {calib.focal:g}, fy = {fy:g}, baseline = {calib.baseline:g}")
  numbers = [*np.ravel(calib.cam0), *np.ravel(calib.cam1), calib.doffs,
             *(v for v in (calib.vmin, calib.vmax) if v is not None)]
  if not np.all(np.isfinite(np.asarray(numbers, dtype=np.float64))):  # NaN depths, silently
    return "calibration holds a value that is not a finite number (NaN or inf)"
  return None


def check_calib(calib: Calib, where: str) -> None:
  """SljaxError unless calib is a Calib with positive, finite focal lengths and baseline."""
  if not isinstance(calib, Calib):
    raise SljaxError(f"{where}: calib must be a sljax.data.camera.Calib (read_calib reads "
                     f"calib.txt), got {type(calib).__name__}")
  problem = calib_problem(calib)
  if problem is not None:
    raise SljaxError(f"{where}: {problem}")


def depth_from_disparity(disp: np.ndarray, calib: Calib, where: str = "depth") -> np.ndarray:
  """Depth in mm, Z = f * B / (d + doffs); unknown or non-positive d + doffs gives inf."""
  check_calib(calib, where)
  d = np.asarray(disp, dtype=np.float64) + calib.doffs
  valid = np.isfinite(d) & (d > 0)
  z = np.full(d.shape, np.inf, dtype=np.float64)
  z[valid] = calib.focal * calib.baseline / d[valid]
  return z.astype(np.float32)
