"""Images in memory and on disk: float32 in [0, 1], HxWxC RGB; 8- or 16-bit PNGs.

The ground floor's image helpers, shared by the structured-light decoder, the datasets and
inference: reading (any OpenCV format, to float), checking arrays handed in by users, grey
conversion and PNG writing (whole, through sljax.io.files).
"""

import os
from typing import Any

import cv2
import numpy as np

from sljax.errors import SljaxError
from sljax.io import files
from sljax.io.headers import check_image_size

# ITU-R BT.601 luma, the weights OpenCV uses for RGB -> gray.
_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)


def to_gray(image: np.ndarray) -> np.ndarray:
  """HxWx3 RGB (or HxWx1) float image -> HxWx1 luma."""
  if image.shape[-1] == 1:
    return image
  return (image @ _LUMA)[..., None].astype(np.float32)


def decode(path: str | os.PathLike, want_hw: tuple[int, int] | None = None,
           against: str = "im0.png") -> np.ndarray:
  """An image file as OpenCV decodes it (IMREAD_UNCHANGED), its header's size checked first
  (sljax.io.headers: MAX_PIXELS, and want_hw, the size of `against`); SljaxError naming the file."""
  path = os.fspath(path)
  if not os.path.exists(path):
    raise SljaxError(f"{path}: missing")
  check_image_size(path, want_hw, against)  # before OpenCV allocates what the header claims
  try:
    raw = cv2.imread(path, cv2.IMREAD_UNCHANGED)
  except cv2.error as e:  # a format whose header is not read first, claiming too much
    raise SljaxError(f"{path}: not a readable image ({str(e).strip().splitlines()[-1]})") from None
  if raw is None:
    raise SljaxError(f"{path}: not a readable image")
  return raw


def read_image(path: str | os.PathLike, gray: bool | None = None,
               want_hw: tuple[int, int] | None = None, against: str = "im0.png") -> np.ndarray:
  """Reads an 8- or 16-bit PNG to float32 HxWxC in [0, 1] (RGB order; alpha dropped).

  gray=None keeps the file's channels (C = 1 or 3), True gives C = 1, False gives C = 3;
  want_hw: the (height, width) it must have, checked before decoding (decode).
  """
  path = os.fspath(path)
  img = image_to_float(decode(path, want_hw, against), path)
  if gray is True:
    img = to_gray(img)
  elif gray is False and img.shape[2] == 1:
    img = np.repeat(img, 3, axis=2)
  return np.ascontiguousarray(img)


def unit_image(image: Any, what: str, allow_nan: bool = False) -> np.ndarray:
  """An in-memory image as float32 in [0, 1]: uint8 / uint16 scaled, floats checked (finite, or
  NaN where allow_nan; within [0, 1] up to 0.01, then clipped); SljaxError naming `what`."""
  a = np.asarray(image)
  if a.dtype == np.uint8:
    return a.astype(np.float32) / np.float32(255.0)
  if a.dtype == np.uint16:
    return a.astype(np.float32) / np.float32(65535.0)
  if a.dtype.kind != "f":
    raise SljaxError(f"{what} must be uint8, uint16 or float in [0, 1], got "
                     f"{type(image).__name__} of dtype {a.dtype}")
  a = a.astype(np.float32)
  if np.isinf(a).any() or (not allow_nan and np.isnan(a).any()):
    raise SljaxError(f"{what} holds {'infinite' if allow_nan else 'NaN or infinite'} values")
  finite = a[np.isfinite(a)]
  # 0..255 held as floats, clipped to [0, 1], would be a white image (or a meaningless one).
  if finite.size and (finite.min() < -0.01 or finite.max() > 1.01):
    raise SljaxError(f"{what} must be scaled to [0, 1], got values in "
                     f"[{finite.min():g}, {finite.max():g}]")
  return np.clip(a, 0.0, 1.0)


TWELVE_BIT_MAX = 4095  # the largest value of 12-bit sensor data


def holds_12_bit(max_value: int, dtype: Any) -> bool:
  """Whether 16-bit samples whose largest value is max_value are 12-bit data (at most 4095):
  read as value / 65535 they would come out 16x darker than they are."""
  return np.dtype(dtype) == np.uint16 and int(max_value) <= TWELVE_BIT_MAX


def image_to_float(raw: np.ndarray, where: str = "image") -> np.ndarray:
  """An OpenCV-decoded 8/16-bit array (HxW or BGR(A)) -> float32 HxWxC RGB in [0, 1]."""
  if raw.dtype == np.uint8:
    scale = 255.0
  elif raw.dtype == np.uint16:
    scale = 65535.0
  else:
    raise SljaxError(f"{where}: expected an 8- or 16-bit image, got {raw.dtype}")
  if raw.ndim == 2:
    img = raw[..., None]
  elif raw.shape[2] == 1:
    img = raw
  elif raw.shape[2] in (3, 4):
    img = raw[..., 2::-1]  # BGR(A) -> RGB
  else:
    raise SljaxError(f"{where}: unsupported channel count {raw.shape[2]}")
  return img.astype(np.float32) / np.float32(scale)


def png_pixels(path: str | os.PathLike, image: Any, bit_depth: int = 8) -> np.ndarray:
  """The 8- or 16-bit pixels (BGR for OpenCV) that write_image stores for an image: float in
  [0, 1], uint8 or uint16; HxW, HxWx1 or HxWx3 RGB. SljaxError naming path otherwise."""
  path = os.fspath(path)
  if bit_depth not in (8, 16):
    raise SljaxError(f"{path}: bit depth must be 8 or 16, got {bit_depth}")
  img = unit_image(image, path)
  if img.ndim == 3 and img.shape[2] == 1:
    img = img[..., 0]
  if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
    raise SljaxError(f"{path}: cannot write an image of shape {img.shape}")
  q = np.round(img * (255 if bit_depth == 8 else 65535))
  q = q.astype(np.uint8 if bit_depth == 8 else np.uint16)
  return np.ascontiguousarray(q[..., ::-1]) if q.ndim == 3 else q  # RGB -> BGR


def write_image(path: str | os.PathLike, image: Any, bit_depth: int = 8) -> None:
  """Writes an image (float in [0, 1], uint8 or uint16; HxW, HxWx1 or HxWx3 RGB) as an 8- or
  16-bit PNG."""
  files.write_png(path, png_pixels(path, image, bit_depth))  # whole, or the earlier file kept
