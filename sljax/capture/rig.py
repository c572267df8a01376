"""A calibrated stereo rig: OpenCV stereo calibration files and the rectification every importer
uses.

Calibration: M1, D1, M2, D2, R, T as cv2.stereoCalibrate returns them (a point X in the left
camera's frame is R X + T in the right camera's; T in the unit of the calibration target). They
are read from an OpenCV FileStorage YAML or XML, from an .npz, from OpenCV's stereo_calib
sample's intrinsics.yml + extrinsics.yml pair (read together, the keys merged), or under the
names of OpenCV's structured-light sample (cam1_intrinsics, cam1_distorsion, cam2_...). A file
may state the image size it was made for (image_width and image_height, or image_size /
imageSize as [width, height]).

Rectification: cv2.stereoRectify with CALIB_ZERO_DISPARITY (equal principal points, so
doffs = 0) and alpha = 0 (the rectified views hold only valid pixels) at the captures' own size,
then cv2.initUndistortRectifyMap; the baseline is |T|.
"""

import dataclasses
import os
import re
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from sljax.data.camera import Calib
from sljax.errors import SljaxError
from sljax.io import files

RECTIFY_ALPHA = 0.0
CALIB_KEYS = ("M1", "D1", "M2", "D2", "R", "T")
# The names OpenCV's structured-light sample (pointcloud.cpp) gives the same matrices.
SL_SAMPLE_KEYS = {"M1": "cam1_intrinsics", "D1": "cam1_distorsion", "M2": "cam2_intrinsics",
                  "D2": "cam2_distorsion", "R": "R", "T": "T"}
DIST_COUNTS = (4, 5, 8, 12, 14)  # the distortion models OpenCV's rectification accepts
UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
_SIZE_PAIRS = (("image_width", "image_height"), ("width", "height"))
_SIZE_KEYS = ("image_size", "imageSize", "ImageSize", "size")


@dataclasses.dataclass(frozen=True)
class StereoCalibration:
  """An OpenCV stereo calibration (float64): X_right = r @ X_left + t, t in the target's unit."""
  m1: np.ndarray  # 3x3
  d1: np.ndarray  # 1xk
  m2: np.ndarray
  d2: np.ndarray
  r: np.ndarray   # 3x3
  t: np.ndarray   # 3x1
  size: tuple[int, int] | None = None  # (width, height) the file states, if any
  where: str = "calibration"           # the file(s) it came from, for error messages
  files: tuple[str, ...] = ()          # the files read (none when made in memory)

  def as_dict(self) -> dict[str, np.ndarray]:
    """{M1, D1, M2, D2, R, T} as OpenCV names them."""
    return {"M1": self.m1, "D1": self.d1, "M2": self.m2, "D2": self.d2, "R": self.r, "T": self.t}


def _needs(keys: Sequence[str] = CALIB_KEYS) -> str:
  return f"an OpenCV FileStorage YAML with the matrices {' '.join(keys)}"


def _node_matrix(node) -> np.ndarray | None:
  """A FileStorage node as a float64 array: an !!opencv-matrix, or a sequence of numbers;
  None for anything else (OpenCV asserts, a cv2.error, on a scalar or a cut-off entry)."""
  try:
    if node.empty():
      return None
    if node.isMap():
      if not _whole_matrix(node):  # OpenCV would overrun its buffer (heap damage, an abort)
        return None
      m = node.mat()
      return None if m is None else np.asarray(m, np.float64)
    if node.isSeq():
      values = [node.at(i).real() for i in range(node.size())]
      return np.asarray(values, np.float64) if values else None
  except (cv2.error, UnicodeDecodeError):  # the binding decodes strings (a dt) as UTF-8
    return None
  return None


_MATRIX_TYPE = re.compile(r"^([1-4]?)[ucswifdh]$")  # an !!opencv-matrix's dt: channels, depth


def _whole_matrix(node) -> bool:
  """Whether an !!opencv-matrix node holds integer rows and cols, a dt OpenCV knows and exactly
  rows x cols x channels numbers: OpenCV 5.0 writes the data into a Mat of rows x cols before it
  checks the count, so a matrix without cols or with too many values damages the heap."""
  rows, cols, dt, data = (node.getNode(k) for k in ("rows", "cols", "dt", "data"))
  if not (rows.isInt() and cols.isInt() and dt.isString() and data.isSeq()):
    return False
  kind = _MATRIX_TYPE.match(dt.string())
  if kind is None or rows.real() < 0 or cols.real() < 0:
    return False
  need = int(rows.real()) * int(cols.real()) * int(kind.group(1) or 1)
  return data.size() == need and all(
      data.at(i).isInt() or data.at(i).isReal() for i in range(data.size()))


def _node_number(node) -> float | None:
  try:
    return float(node.real()) if node.isReal() or node.isInt() else None
  except cv2.error:
    return None


def _open_storage(path: str, needs: str):
  """An open cv2.FileStorage; SljaxError for a missing, empty or unparsable file."""
  if not os.path.exists(path):
    raise SljaxError(f"{path}: missing")
  if os.path.getsize(path) == 0:  # OpenCV asserts on it (a SystemError from the binding)
    raise SljaxError(f"{path}: empty file (0 bytes); expected {needs}")
  try:
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
  except (cv2.error, SystemError) as e:  # the binding wraps parse errors in a SystemError
    cause = e if isinstance(e, cv2.error) else e.__context__
    where = re.search(r"in function '(.+)'", str(cause))  # OpenCV's line number and reason
    detail = f" OpenCV: {where.group(1)}" if where else ""
    raise SljaxError(f"{path}: not readable as {needs} (damaged or half-written?{detail})"
                     ) from None
  if not fs.isOpened():
    raise SljaxError(f"{path}: cannot open as OpenCV FileStorage")
  return fs


def _storage_entries(path: str) -> dict[str, np.ndarray]:
  """Every matrix and number at the top of a FileStorage file, as float64 arrays."""
  fs = _open_storage(path, _needs())
  try:
    root = fs.root()
    if not root.isMap():
      return {}
    out = {}
    try:
      keys = root.keys()
    except UnicodeDecodeError as e:  # the binding decodes key names as UTF-8
      raise SljaxError(f"{path}: a key name is not UTF-8 text (byte "
                       f"{e.object[e.start:e.start + 1]!r}); expected {_needs()}") from None
    for key in keys:
      node = fs.getNode(key)
      m = _node_matrix(node)
      if m is None:
        number = _node_number(node)
        m = None if number is None else np.asarray(number, np.float64)
      if m is not None:
        out[key] = m
    return out
  finally:
    fs.release()


def _file_entries(path: Path) -> dict[str, np.ndarray]:
  """The arrays of one calibration file (.npz or FileStorage .yml/.yaml/.xml/.json)."""
  if path.suffix.lower() == ".npz":
    if not path.exists():
      raise SljaxError(f"{path}: missing")
    return {k: np.asarray(v, np.float64) for k, v in
            files.read_npz(path, "a stereo calibration (M1 D1 M2 D2 R T)").items()
            if np.asarray(v).dtype.kind in "biuf"}
  return _storage_entries(os.fspath(path))


def _stated_size(entries: dict[str, np.ndarray], where: str) -> tuple[int, int] | None:
  """(width, height) a calibration states, or None."""
  for wk, hk in _SIZE_PAIRS:
    if wk in entries and hk in entries:
      return _size_values(entries[wk], entries[hk], where)
  for key in _SIZE_KEYS:
    if key in entries:
      v = entries[key].ravel()
      if v.size != 2:
        raise SljaxError(f"{where}: {key} has {v.size} values, expected 2 (width, height)")
      return _size_values(v[0], v[1], where)
  return None


def _size_values(w, h, where: str) -> tuple[int, int]:
  w, h = float(np.ravel(w)[0]), float(np.ravel(h)[0])
  if not (w.is_integer() and h.is_integer() and w > 0 and h > 0):
    raise SljaxError(f"{where}: the stated image size {w:g} x {h:g} is not two positive integers")
  return int(w), int(h)


def read_calibration(paths: str | os.PathLike | Sequence[str | os.PathLike]) -> StereoCalibration:
  """Reads M1 D1 M2 D2 R T (and a stated image size) from one file, or two read together
  (intrinsics.yml + extrinsics.yml); SljaxError naming the file and the problem."""
  if isinstance(paths, (str, os.PathLike)):
    paths = [paths]
  paths = [Path(p) for p in paths]
  if not 1 <= len(paths) <= 2:
    raise SljaxError(f"a stereo calibration is one file or two (intrinsics + extrinsics), got "
                     f"{len(paths)}")
  where = " + ".join(map(str, paths))
  entries: dict[str, np.ndarray] = {}
  for path in paths:
    for key, value in _file_entries(path).items():
      if key in entries and not np.array_equal(entries[key], value):
        raise SljaxError(f"{where}: both files give {key}, with different values")
      entries[key] = value
  names = SL_SAMPLE_KEYS if "M1" not in entries and "cam1_intrinsics" in entries else \
      {k: k for k in CALIB_KEYS}
  missing = [name for name in names.values() if name not in entries
             or entries[name].ndim == 0]
  if missing:
    hint = ("; intrinsics.yml holds only M1 D1 M2 D2: pass its extrinsics.yml too"
            if set(missing) <= {"R", "T"} and len(paths) == 1 else "")
    raise SljaxError(f"{where}: lacks the {'matrix' if len(missing) == 1 else 'matrices'} "
                     f"{' '.join(missing)} (absent, cut off or not an !!opencv-matrix; expected "
                     f"{_needs(list(names.values()))}){hint}")
  cal = {key: entries[name] for key, name in names.items()}
  expect = {"M1": 9, "M2": 9, "R": 9, "T": 3}
  for key, size in expect.items():
    if cal[key].size != size:
      raise SljaxError(f"{where}: {names[key]} has {cal[key].size} values, expected {size}")
  out = StereoCalibration(
      m1=cal["M1"].reshape(3, 3), d1=cal["D1"].reshape(1, -1), m2=cal["M2"].reshape(3, 3),
      d2=cal["D2"].reshape(1, -1), r=cal["R"].reshape(3, 3), t=cal["T"].reshape(3, 1),
      size=_stated_size(entries, where), where=where, files=tuple(map(str, paths)))
  check_calibration(out)
  return out


def check_calibration(cal: StereoCalibration) -> None:
  """SljaxError unless every value is finite, M1 and M2 have positive focal lengths, D1, D2 hold
  a distortion model OpenCV knows and R is a rotation."""
  # cv2.stereoRectify asserts on a bad distortion length or a NaN T (a traceback) and turns a
  # NaN or zero intrinsic into NaN matrices, which would be written to calib.txt as is.
  named = cal.as_dict()
  for key in CALIB_KEYS:
    if not np.all(np.isfinite(named[key])):
      raise SljaxError(f"{cal.where}: {key} holds NaN or infinite values")
  for key in ("M1", "M2"):
    fx, fy = named[key][0, 0], named[key][1, 1]
    if not (fx > 0 and fy > 0):
      raise SljaxError(f"{cal.where}: {key} has focal lengths fx = {fx:g}, fy = {fy:g}; both "
                       "must be positive")
  for key in ("D1", "D2"):
    if named[key].size not in DIST_COUNTS:
      raise SljaxError(f"{cal.where}: {key} has {named[key].size} values, expected 4, 5, 8, 12 "
                       "or 14 (OpenCV's distortion models: k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 "
                       "[tx ty]]]])")
  if abs(np.linalg.det(cal.r) - 1) > 1e-3 or not np.allclose(cal.r @ cal.r.T, np.eye(3),
                                                              atol=1e-3):
    raise SljaxError(f"{cal.where}: R is not a rotation matrix")


def check_rig(cal: StereoCalibration, swapped_hint: str) -> None:
  """SljaxError unless T puts the right camera to the right of the left one, along x."""
  t = cal.t.ravel()
  if abs(t[0]) <= abs(t[1]):
    raise SljaxError(f"{cal.where}: T = {t.tolist()} is not a horizontal stereo rig")
  # stereoRectify takes either order, but with T x > 0 the true disparity is negative and the
  # f*B/Z written as disp0 would have the wrong sign.
  if t[0] > 0:
    raise SljaxError(f"{cal.where}: T = {t.tolist()} puts the right camera to the left of the "
                     f"left one (T x > 0; a left-right rig has T x < 0): {swapped_hint}")


def check_size(cal: StereoCalibration, size: tuple[int, int], what: str) -> None:
  """SljaxError when the calibration states an image size other than (width, height)."""
  if cal.size is not None and tuple(cal.size) != tuple(size):
    raise SljaxError(f"{cal.where}: calibrated for {cal.size[0]}x{cal.size[1]} images, but "
                     f"{what} is {size[0]}x{size[1]} (resize the captures or recalibrate)")


def write_calibration(path: str | os.PathLike, cal: StereoCalibration,
                      extra: dict[str, float] | None = None) -> None:
  """Writes M1 D1 M2 D2 R T (and the size) as an OpenCV FileStorage YAML, whole."""
  path = Path(path)
  tmp = files.temp_path(path)
  fs = cv2.FileStorage(os.fspath(tmp), cv2.FILE_STORAGE_WRITE)
  try:
    for key, value in cal.as_dict().items():
      fs.write(key, np.asarray(value, np.float64))
    if cal.size is not None:
      fs.write("image_width", int(cal.size[0]))
      fs.write("image_height", int(cal.size[1]))
    for key, value in (extra or {}).items():
      fs.write(key, float(value))
  finally:
    fs.release()
  try:
    os.replace(tmp, path)
  finally:
    if tmp.exists():
      tmp.unlink()


@dataclasses.dataclass(frozen=True)
class Rectification:
  """cv2.stereoRectify's result for one image size: rotations r1, r2 (original -> rectified
  camera), projections p1, p2 (3x4), and the baseline |T| in the calibration's unit."""
  r1: np.ndarray
  r2: np.ndarray
  p1: np.ndarray
  p2: np.ndarray
  size: tuple[int, int]  # (width, height)
  baseline: float

  @property
  def focal(self) -> float:
    """Rectified focal length (px)."""
    return float(self.p1[0, 0])

  def meta(self) -> dict[str, list]:
    """R1, R2, P1, P2 as nested lists (meta.json)."""
    return {"R1": self.r1.tolist(), "R2": self.r2.tolist(), "P1": self.p1.tolist(),
            "P2": self.p2.tolist()}

  def calib(self, unit_mm: float, disparities: Sequence[np.ndarray] = (), scale: float = 1.0
            ) -> Calib:
    """calib.txt of the rectified pair (baseline in mm): cameras from p1, p2, ndisp the multiple
    of 16 above the largest known disparity, vmin/vmax their range; scale: the views were
    resized by this factor (area-averaged, pixel centres at (x + 0.5) scale - 0.5)."""
    known = np.concatenate([np.ravel(d[np.isfinite(d)]) for d in disparities] or [np.zeros(0)])
    vmin = float(np.floor(known.min())) if known.size else None
    vmax = float(np.ceil(known.max())) if known.size else None
    ndisp = 16 * (int(np.floor(known.max() / 16)) + 1) if known.size else 16
    cams = []
    for p in (self.p1, self.p2):
      cams.append(np.array([[p[0, 0] * scale, 0, (p[0, 2] + 0.5) * scale - 0.5],
                            [0, p[1, 1] * scale, (p[1, 2] + 0.5) * scale - 0.5],
                            [0, 0, 1]], np.float64))
    w, h = self.size
    return Calib(cam0=cams[0], cam1=cams[1], doffs=float(cams[1][0, 2] - cams[0][0, 2]),
                 baseline=self.baseline * unit_mm, width=scaled_length(w, scale),
                 height=scaled_length(h, scale), ndisp=ndisp, vmin=vmin, vmax=vmax)


def scaled_length(n: int, scale: float) -> int:
  """An image side after resizing by scale (at least one pixel)."""
  return max(1, int(round(n * scale)))


def rectify(cal: StereoCalibration, size: tuple[int, int]) -> Rectification:
  """The rectification of the calibrated pair at image size (width, height)."""
  r1, r2, p1, p2, _, _, _ = cv2.stereoRectify(
      cal.m1, cal.d1, cal.m2, cal.d2, tuple(int(v) for v in size), cal.r, cal.t,
      flags=cv2.CALIB_ZERO_DISPARITY, alpha=RECTIFY_ALPHA)
  return Rectification(r1=np.asarray(r1), r2=np.asarray(r2), p1=np.asarray(p1),
                       p2=np.asarray(p2), size=(int(size[0]), int(size[1])),
                       baseline=float(np.linalg.norm(cal.t)))


def rectify_maps(cal: StereoCalibration, rect: Rectification
                 ) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
  """((map_x, map_y) of the left view, of the right view): the original pixel each rectified
  pixel samples (float32, for cv2.remap)."""
  maps0 = cv2.initUndistortRectifyMap(cal.m1, cal.d1, rect.r1, rect.p1, rect.size, cv2.CV_32FC1)
  maps1 = cv2.initUndistortRectifyMap(cal.m2, cal.d2, rect.r2, rect.p2, rect.size, cv2.CV_32FC1)
  return maps0, maps1


def remap(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
  """One view resampled into the rectified frame (bilinear; black outside), its dtype kept."""
  return cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
