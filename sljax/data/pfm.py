"""Portable float maps (PFM) as used by Middlebury for disparities.

Layout: a text header `Pf` (one channel) or `PF` (three channels), then `width height`, then
a scale whose sign gives the byte order (negative = little-endian), each on its own line,
followed by raw float32 samples stored from the bottom row to the top row.
"""

import os
import re

import numpy as np

from sljax.errors import SljaxError
from sljax.io import files

_HEADER = re.compile(rb"\A(P[fF])\s+(\d+)\s+(\d+)\s+([-+0-9.eE]+)\s")


def read_pfm(path: str | os.PathLike) -> np.ndarray:
  """Reads a PFM file into float32, HxW or HxWx3, top row first; inf values are kept."""
  path = os.fspath(path)
  try:
    with open(path, "rb") as f:
      data = f.read()
  except OSError as e:
    raise SljaxError(f"{path}: cannot read PFM ({e.strerror or e})") from None
  # The header is three whitespace-separated text fields after the magic; one whitespace
  # byte ends the scale, and the samples start right after it.
  m = _HEADER.match(data[:256])
  if m is None:
    raise SljaxError(
        f"{path}: not a PFM file (expected header 'Pf' or 'PF', then 'width height', then scale)")
  magic, width, height, scale_text = m.groups()
  channels = 3 if magic == b"PF" else 1
  width, height = int(width), int(height)
  try:
    scale = float(scale_text)
  except ValueError:
    raise SljaxError(f"{path}: PFM scale {scale_text!r} is not a number") from None
  if width <= 0 or height <= 0 or scale == 0.0:
    raise SljaxError(f"{path}: PFM header has width={width} height={height} scale={scale}; "
                     "expected positive sizes and a non-zero scale")
  dtype = np.dtype("<f4" if scale < 0 else ">f4")
  count = width * height * channels
  start = m.end()
  if data[start - 1:start + 1] == b"\r\n":  # a CRLF line end after the scale
    start += 1
  body = data[start:]
  if len(body) < count * 4:
    raise SljaxError(f"{path}: PFM holds {len(body)} data bytes, the header "
                     f"({width}x{height}x{channels}) needs {count * 4}")
  values = np.frombuffer(body, dtype=dtype, count=count).astype(np.float32)
  shape = (height, width, 3) if channels == 3 else (height, width)
  return np.ascontiguousarray(values.reshape(shape)[::-1])


def write_pfm(path: str | os.PathLike, array: np.ndarray) -> None:
  """Writes HxW or HxWx3 values as a little-endian float32 PFM (rows bottom to top, inf kept)."""
  path = os.fspath(path)
  a = np.asarray(array)
  if a.ndim == 3 and a.shape[2] == 1:
    a = a[..., 0]
  if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
    raise SljaxError(f"{path}: PFM needs an HxW or HxWx3 array, got shape {a.shape}")
  magic = b"PF" if a.ndim == 3 else b"Pf"
  height, width = a.shape[:2]
  header = magic + b"\n" + f"{width} {height}\n-1\n".encode("ascii")
  body = np.ascontiguousarray(a[::-1], dtype="<f4").tobytes()
  files.write_bytes(path, header + body)  # whole or not at all (a full disk, --overwrite)
