"""Conversion of a SCARED keyframe into a rectified scene folder with ground-truth disparity,
and the SCARED error measured the way the challenge's toolkit measures it.

A SCARED keyframe holds the raw (unrectified, distorted) stereo pair, a per-pixel 3D point
map of the left view (x, y, z in mm, left camera frame) and the OpenCV stereo calibration.
We rectify with cv2.stereoRectify (alpha = 0: the rectified views hold only valid pixels,
CALIB_ZERO_DISPARITY: equal principal points, so doffs = 0) and project every 3D point into
the rectified left view, keeping the nearest point per pixel; pixels that no point lands on
take the point seen through them (the rectify map sampled back into the point map).

For scoring, the importer also keeps the original frame: `depth0_orig.pfm` (the ground-truth
depth z of the original left image, mm, inf = unknown) and meta.json "original" (M1, D1, R1
and the size). `original_frame_depth` maps a predicted rectified disparity back to that frame
(each original pixel's ray is followed into the rectified view, the disparity read there
bilinearly gives the point, which is rotated back by R1^T), and `keyframe_error` scores it as
the SCARED toolkit does (dimitrisPs/scared_toolkit, scaredtk/evaluation.py, depthmap_error):
coverage = share of the image's pixels with known ground truth; a frame under 10% coverage is
excluded (no error); otherwise the error is the mean absolute depth difference (mm) over the
pixels where both ground truth and prediction are known, and the share of such pixels is
reported as "assessed". The toolkit's disparity_to_original_depthmap.py maps predictions back
the other way round (points projected forward into the original view, holes interpolated);
following each original pixel's ray instead gives the same depth where the prediction is
smooth and leaves no holes to fill.
"""

import os
from pathlib import Path

import cv2
import numpy as np

from sljax.data.camera import Calib
from sljax.data.pfm import write_pfm
from sljax.io import files
from sljax.capture.rig import (RECTIFY_ALPHA, check_rig, read_calibration, rectify, rectify_maps,
                            remap)
from sljax.data.scene import Scene, write_scene
from sljax.errors import SljaxError
from sljax.io.headers import check_image_size
from sljax.io.images import decode, image_to_float

LEFT, RIGHT = "Left_Image.png", "Right_Image.png"
DEPTH, CALIB = "left_depth_map.tiff", "endoscope_calibration.yaml"
ORIGINAL_DEPTH = "depth0_orig.pfm"  # ground-truth depth of the original left view (scene file)
MIN_COVERAGE = 0.1  # scared_toolkit: frames with less known ground truth are not scored


def read_scared_calibration(path: str | os.PathLike) -> dict[str, np.ndarray]:
  """Reads M1 D1 M2 D2 R T (float64) from an OpenCV FileStorage YAML."""
  return read_calibration(path).as_dict()


def read_scared_points(path: str | os.PathLike) -> np.ndarray:
  """HxWx3 float32 (x, y, z) in mm; unknown points (NaN or z == 0) become NaN."""
  path = os.fspath(path)
  if not os.path.exists(path):
    raise SljaxError(f"{path}: missing")
  check_image_size(path)  # before OpenCV allocates what the header claims
  try:
    raw = cv2.imread(path, cv2.IMREAD_UNCHANGED)
  except cv2.error:  # a format whose header sljax does not read, claiming too much
    raw = None
  # An 8/16-bit image (a depth picture, not the point map) would pass as x, y, z of 0..255 mm.
  if raw is None or raw.ndim != 3 or raw.shape[2] != 3 or raw.dtype.kind != "f":
    found = ("unreadable" if raw is None else
             f"{raw.shape[2] if raw.ndim == 3 else 1} channel(s) of {raw.dtype}")
    raise SljaxError(f"{path}: expected a 3-channel float TIFF of x, y, z (mm), got {found}")
  # OpenCV returns a 3-channel TIFF in BGR order; the file stores x, y, z.
  xyz = raw[..., ::-1].astype(np.float32)
  bad = ~np.all(np.isfinite(xyz), axis=2) | (xyz[..., 2] <= 0)
  xyz[bad] = np.nan
  return xyz


def _read_view(path: Path) -> np.ndarray:
  """The raw 8/16-bit view as OpenCV decodes it (remapped before conversion to float)."""
  img = decode(path)  # sized from its header first
  if img.dtype not in (np.uint8, np.uint16):
    raise SljaxError(f"{path}: not an 8- or 16-bit image")
  return img


def rectified_disparity(xyz: np.ndarray, r1: np.ndarray, p1: np.ndarray, baseline: float,
                        shape: tuple[int, int],
                        lookup: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
  """Left disparity f*B/Z of 3D points in the rectified view (inf where unknown).

  Points (left camera frame) are rotated by r1, projected with p1 and rounded to the nearest
  pixel; where several land on a pixel the nearest wins. lookup = (map_x, map_y), the
  rectified -> original pixel maps, fills pixels that received no point.
  """
  h, w = shape
  f = float(p1[0, 0])
  pts = xyz.reshape(-1, 3).astype(np.float64)
  pts = pts[np.all(np.isfinite(pts), axis=1)]
  rect = pts @ np.asarray(r1, np.float64).T
  z = rect[:, 2]
  front = z > 0
  rect, z = rect[front], z[front]
  u = np.rint(f * rect[:, 0] / z + p1[0, 2]).astype(np.int64)
  v = np.rint(p1[1, 1] * rect[:, 1] / z + p1[1, 2]).astype(np.int64)
  inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
  zbuf = np.full(h * w, np.inf)
  np.minimum.at(zbuf, v[inside] * w + u[inside], z[inside])
  zbuf = zbuf.reshape(h, w)
  if lookup is not None:
    # The point seen through each rectified pixel: nearest sample of the original map.
    seen = np.stack([cv2.remap(xyz[..., c], lookup[0], lookup[1], cv2.INTER_NEAREST,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
                     for c in range(3)], axis=-1).astype(np.float64)
    z_seen = seen @ np.asarray(r1, np.float64)[2]
    hole = np.isinf(zbuf) & np.isfinite(z_seen) & (z_seen > 0)
    zbuf[hole] = z_seen[hole]
  disp = np.full((h, w), np.inf, np.float32)
  known = np.isfinite(zbuf)
  disp[known] = f * baseline / zbuf[known]
  return disp


def _check_depth_scale(known_disp: np.ndarray, xyz: np.ndarray, width: int, path: Path) -> None:
  """SljaxError when most known disparities exceed the image width, which no pair can show:
  depths in metres instead of mm make them 1000x too large."""
  if known_disp.size and np.median(known_disp) > width:
    z = float(np.nanmedian(xyz[..., 2]))
    raise SljaxError(f"{path}: median depth z = {z:.4g} gives a median disparity of "
                     f"{np.median(known_disp):.0f} px, more than the image width ({width} px); "
                     "x, y, z must be in mm (metres?)")


def import_scared(keyframe_dir: str | os.PathLike, out_dir: str | os.PathLike,
                  overwrite: bool = False) -> Path:
  """Converts one SCARED keyframe folder into a rectified scene folder; returns out_dir."""
  kf = files.require_folder(keyframe_dir, "keyframe folder")
  out = Path(out_dir)
  left, right = _read_view(kf / LEFT), _read_view(kf / RIGHT)
  h, w = left.shape[:2]
  if right.shape[:2] != (h, w):
    raise SljaxError(f"{kf / RIGHT}: size {right.shape[1]}x{right.shape[0]} differs from "
                     f"{LEFT} ({w}x{h})")
  xyz = read_scared_points(kf / DEPTH)
  if xyz.shape[:2] != (h, w):
    raise SljaxError(f"{kf / DEPTH}: size {xyz.shape[1]}x{xyz.shape[0]} differs from "
                     f"{LEFT} ({w}x{h})")
  cal = read_calibration(kf / CALIB)
  check_rig(cal, f"are {LEFT} and {RIGHT}, or the cameras of the calibration, swapped?")

  rect = rectify(cal, (w, h))
  maps0, maps1 = rectify_maps(cal, rect)
  im0, im1 = remap(left, maps0), remap(right, maps1)
  disp = rectified_disparity(xyz, rect.r1, rect.p1, rect.baseline, (h, w), lookup=maps0)

  finite = disp[np.isfinite(disp)]
  _check_depth_scale(finite, xyz, w, kf / DEPTH)
  calib = rect.calib(1.0, [disp])  # SCARED's calibrations are in mm
  group = f"{kf.resolve().parent.name}/{kf.resolve().name}"
  meta = {"group": group, "source": "SCARED", "keyframe": kf.resolve().name,
          "rectify_alpha": RECTIFY_ALPHA, "known_pixels": int(finite.size),
          "original": {"M1": cal.m1.tolist(), "D1": cal.d1.ravel().tolist(),
                       "R1": rect.r1.tolist(), "width": w, "height": h}}
  scene = Scene(name=out.name, im0=image_to_float(im0, str(kf / LEFT)),
                im1=image_to_float(im1, str(kf / RIGHT)), disp0=disp,
                calib=calib, meta=meta)
  if (out / ORIGINAL_DEPTH).exists() and not overwrite:
    raise SljaxError(f"scene {out}: {ORIGINAL_DEPTH}: exists (use --overwrite / "
                     "overwrite=True to replace it)")
  write_scene(out, scene, overwrite=overwrite, bit_depth=8 if left.dtype == np.uint8 else 16)
  write_pfm(out / ORIGINAL_DEPTH, np.where(np.isfinite(xyz[..., 2]), xyz[..., 2], np.inf))
  return out


def read_original(meta: dict, where: str) -> dict[str, np.ndarray]:
  """M1 (3x3), D1 (1xk), R1 (3x3) and (height, width) of the original view from meta.json."""
  try:
    o = meta["original"]
    out = {"M1": np.asarray(o["M1"], np.float64).reshape(3, 3),
           "D1": np.asarray(o["D1"], np.float64).reshape(1, -1),
           "R1": np.asarray(o["R1"], np.float64).reshape(3, 3),
           "size": (int(o["height"]), int(o["width"]))}
  except (KeyError, TypeError, ValueError):
    raise SljaxError(f"{where}: meta.json 'original' must hold M1, D1, R1, width and height "
                     "(re-import the keyframe with sljax import-scared)") from None
  return out


def original_frame_depth(disp: np.ndarray, calib: Calib, original: dict) -> np.ndarray:
  """Depth (mm, inf unknown) in the original, distorted left view from a rectified disparity.

  Original pixel (u, v) -> its ray (undistorted by M1, D1) -> rotated by R1 into the rectified
  camera -> the rectified pixel it passes (cam0 of calib); the disparity there (bilinear; any
  unknown neighbour makes it unknown) gives Z_rect = f B / (d + doffs) and the point
  Z_rect * ray; its z in the original camera frame is (R1^T point)_z.
  """
  h, w = original["size"]
  u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
  pix = np.stack([u.ravel(), v.ravel()], -1)[:, None, :]
  cam = np.asarray(calib.cam0, np.float64)
  rect = cv2.undistortPoints(pix, original["M1"], original["D1"], R=original["R1"], P=cam)
  xr = rect[:, 0, 0].reshape(h, w).astype(np.float32)
  yr = rect[:, 0, 1].reshape(h, w).astype(np.float32)
  d = np.asarray(disp, np.float32)
  # remap reads outside the rectified image as NaN; inf neighbours give inf or NaN: unknown.
  sampled = cv2.remap(d, xr, yr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                      borderValue=float("nan")).astype(np.float64)
  denom = sampled + calib.doffs
  known = np.isfinite(denom) & (denom > 0)
  z_rect = np.where(known, calib.focal * calib.baseline / np.where(known, denom, 1.0), np.inf)
  ray = np.stack([(xr - cam[0, 2]) / cam[0, 0], (yr - cam[1, 2]) / cam[1, 1],
                  np.ones_like(xr)], -1).astype(np.float64)
  z = np.where(known, z_rect * (ray @ original["R1"][:, 2]), np.inf)
  return z.astype(np.float32)


def keyframe_error(gt_depth: np.ndarray, pred_depth: np.ndarray) -> dict[str, float | bool]:
  """SCARED frame error (scared_toolkit depthmap_error): see the module docstring.

  Non-finite or zero depths are unknown in both maps. Returns depth_mae_mm (NaN when
  excluded), coverage and assessed (shares of all pixels) and excluded (coverage < 10%).
  """
  gt = np.asarray(gt_depth, np.float64)
  pred = np.asarray(pred_depth, np.float64)
  if gt.shape != pred.shape:
    raise SljaxError(f"SCARED error: ground truth {gt.shape} and prediction {pred.shape} differ")
  known_gt = np.isfinite(gt) & (gt != 0)
  both = known_gt & np.isfinite(pred) & (pred != 0)
  coverage = float(known_gt.mean())
  excluded = coverage < MIN_COVERAGE
  mae = float(np.abs(pred[both] - gt[both]).mean()) if both.any() and not excluded else float("nan")
  return {"depth_mae_mm": mae, "coverage": coverage,
          "assessed": 0.0 if excluded else float(both.mean()), "excluded": bool(excluded)}
