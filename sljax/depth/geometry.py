"""From disparity to depth maps and coloured point clouds (rectified stereo, Middlebury calib).

Depth (mm) of a left pixel with disparity d: Z = f * B / (d + doffs), f = cam0[0, 0] (pixels),
B = baseline (mm), doffs = cx1 - cx0 (`sljax.data.camera.depth_from_disparity`). The point of
pixel (x, y) in the left (cam0) camera frame, x right, y down, z forward, in mm:

  X = (x - cx) * Z / f,  Y = (y - cy) * Z / fy,  Z

with (cx, cy) = cam0's principal point and fy = cam0[1, 1] (equal to f in a rectified
calibration). A pixel is unknown when its disparity is not finite or d + doffs <= 0 (a point
at or behind infinity), or when Z exceeds max_depth; unknown pixels have no depth (inf in
float maps, 0 in 16-bit PNGs) and no point.

16-bit depth PNG: millimetres rounded to the nearest integer; 0 = unknown. A known depth that
does not fit (rounds to 0 or above 65535 mm) is also written 0; the float PFM keeps it.
"""

import os
from numbers import Real
from typing import Any

import numpy as np

from sljax.data.camera import Calib, check_calib, depth_from_disparity
from sljax.errors import SljaxError
from sljax.io import files
from sljax.io.images import unit_image

PNG16_MAX_MM = 65535


def check_calib_size(calib: Calib, shape: tuple[int, int], where: str) -> None:
  """SljaxError unless calib's width x height is the image size (H, W)."""
  check_calib(calib, where)
  h, w = shape
  if (calib.width, calib.height) != (w, h):
    raise SljaxError(f"{where}: calibration is for {calib.width}x{calib.height} images, the pair "
                     f"is {w}x{h} (depth would be wrong; give the calib.txt of these images)")


def check_max_depth(max_depth: Any, what: str = "max_depth") -> None:
  """SljaxError unless max_depth is None or a positive number of mm (0, a negative or NaN one
  would silently mark every pixel unknown; a string fails inside numpy)."""
  if max_depth is None:
    return
  if not isinstance(max_depth, Real) or isinstance(max_depth, (bool, np.bool_)):
    raise SljaxError(f"{what} must be a number of mm or None, got {max_depth!r}")
  if not max_depth > 0:
    raise SljaxError(f"{what} must be positive (mm), got {max_depth!r}")


def depth_mm(disp: np.ndarray, calib: Calib, max_depth: float | None = None) -> np.ndarray:
  """HxW float32 depth in mm; inf where unknown (see the module docstring) or beyond max_depth."""
  check_max_depth(max_depth)
  d = np.asarray(disp)
  if d.ndim != 2:
    raise SljaxError(f"depth: disparity must be HxW, got shape {d.shape}")
  check_calib_size(calib, d.shape, "depth")
  z = depth_from_disparity(d, calib)
  if max_depth is not None:
    z = np.where(z <= max_depth, z, np.float32(np.inf)).astype(np.float32)
  return z


def depth_png16(depth: np.ndarray) -> np.ndarray:
  """uint16 millimetres from a float depth map; 0 where unknown or not representable."""
  z = np.asarray(depth, dtype=np.float64)
  mm = np.zeros(z.shape, np.uint16)
  finite = np.isfinite(z)
  r = np.rint(np.where(finite, z, 0.0))
  ok = finite & (r >= 1) & (r <= PNG16_MAX_MM)
  mm[ok] = r[ok].astype(np.uint16)
  return mm


def point_cloud(disp: np.ndarray, calib: Calib, image: np.ndarray | None = None,
                max_depth: float | None = None) -> tuple[np.ndarray, np.ndarray]:
  """(xyz, rgb): Nx3 float32 points in mm (cam0 frame) and Nx3 uint8 colours, row-major order.

  image: the left view, HxW, HxWx1 or HxWx3 float in [0, 1] (grey when None).
  """
  d = np.asarray(disp)
  if d.ndim != 2:
    raise SljaxError(f"point cloud: disparity must be HxW, got shape {d.shape}")
  check_calib_size(calib, d.shape, "point cloud")
  z = depth_mm(d, calib, max_depth).astype(np.float64)
  known = np.isfinite(z)
  ys, xs = np.nonzero(known)
  zk = z[known]
  cam = np.asarray(calib.cam0, dtype=np.float64)
  f, fy, cx, cy = cam[0, 0], cam[1, 1], cam[0, 2], cam[1, 2]
  xyz = np.stack([(xs - cx) * zk / f, (ys - cy) * zk / fy, zk], axis=1).astype(np.float32)
  if image is None:
    rgb = np.full((len(zk), 3), 128, np.uint8)
  else:
    img = unit_image(image, "point cloud: image")
    if img.ndim == 2:
      img = img[..., None]
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4):
      raise SljaxError(f"point cloud: image must be HxW, HxWx1, HxWx3 or HxWx4, got shape "
                       f"{img.shape}")
    if img.shape[:2] != d.shape:
      raise SljaxError(f"point cloud: image {img.shape[:2]} and disparity {d.shape} differ")
    img = np.repeat(img, 3, axis=2) if img.shape[2] == 1 else img[..., :3]
    rgb = np.rint(np.clip(img[known], 0.0, 1.0) * 255.0).astype(np.uint8)
  return xyz, rgb


_PLY_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                       ("red", "u1"), ("green", "u1"), ("blue", "u1")])


def write_ply(path: str | os.PathLike, xyz: np.ndarray, rgb: np.ndarray,
              comment: str = "") -> None:
  """Binary little-endian PLY of coloured points (float x, y, z; uchar red, green, blue)."""
  xyz = np.asarray(xyz, dtype=np.float32)
  rgb = np.asarray(rgb)
  for name, a in (("xyz", xyz), ("rgb", rgb)):
    if a.ndim < 1 or a.shape[-1] != 3:
      raise SljaxError(f"{path}: {name} must be Nx3, got shape {a.shape}")
  xyz, rgb = xyz.reshape(-1, 3), rgb.reshape(-1, 3)
  # Colours in [0, 1] would truncate to 0 (black) and values over 255 wrap around.
  if rgb.size and not (rgb.dtype.kind in "biuf" and np.all((rgb >= 0) & (rgb <= 255))
                       and np.all(rgb == np.round(rgb))):
    raise SljaxError(f"{path}: rgb must hold integers 0..255 (uint8 colours), got {rgb.dtype} "
                     f"values in [{rgb.min()}, {rgb.max()}]")
  rgb = rgb.astype(np.uint8)
  if len(xyz) != len(rgb):
    raise SljaxError(f"{path}: {len(xyz)} points but {len(rgb)} colours")
  body = np.empty(len(xyz), _PLY_DTYPE)
  for i, k in enumerate("xyz"):
    body[k] = xyz[:, i]
  for i, k in enumerate(("red", "green", "blue")):
    body[k] = rgb[:, i]
  lines = ["ply", "format binary_little_endian 1.0"]
  lines += [f"comment {c}" for c in comment.splitlines() if c.strip()]
  lines += [f"element vertex {len(xyz)}", "property float x", "property float y",
            "property float z", "property uchar red", "property uchar green",
            "property uchar blue", "end_header"]
  # Whole or not at all: a full disk leaves the earlier file, never half of one.
  files.write_bytes(path, ("\n".join(lines) + "\n").encode("ascii") + body.tobytes())
