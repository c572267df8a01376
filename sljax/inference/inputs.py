"""What a predictor accepts: numpy images HxW, HxWx1 or HxWx3, or batched BxHxWxC; uint8 (/255),
uint16 (/65535) or float already in [0, 1]. They are checked and converted to float32
BxHxWxC with the channel count the model was trained with (RGB -> gray by ITU-R BT.601 luma,
gray -> RGB by repetition). Outputs are resized back with `resize_maps`."""

from typing import Any

import cv2
import jax.numpy as jnp
import numpy as np

from sljax.errors import SljaxError
from sljax.io.images import to_gray, unit_image


def short_repr(value: Any) -> str:
  """repr of value cut to 60 characters, for messages."""
  r = repr(value)
  return r if len(r) <= 60 else r[:57] + "..."


def as_batch(image: Any, what: str) -> tuple[np.ndarray, bool]:
  """HxW / HxWxC / BxHxWxC -> (BxHxWxC, batched); SljaxError naming `what` otherwise."""
  try:
    a = np.asarray(image)
  except ValueError:  # a ragged nested list
    a = np.empty((), object)
  if a.dtype.kind == "V" and jnp.issubdtype(a.dtype, jnp.floating):
    # bfloat16 (and other ml_dtypes floats) is numpy kind "V": an image, not a record array
    a = a.astype(np.float32)
  if a.dtype.kind in "OUSV":  # a path, None or a ragged list: say what it was, not "shape ()"
    raise SljaxError(f"{what}: expected an image array (numpy HxW, HxWxC or BxHxWxC), got "
                     f"{type(image).__name__} {short_repr(image)}")
  if a.ndim == 2:
    a, batched = a[None, :, :, None], False
  elif a.ndim == 3:
    if a.shape[2] not in (1, 3):
      raise SljaxError(f"{what}: a 3-D image must be HxWx1 or HxWx3 (1 or 3 channels), got "
                       f"shape {a.shape} (pass a batch of gray images as BxHxWx1)")
    a, batched = a[None], False
  elif a.ndim == 4:
    batched = True
  else:
    raise SljaxError(f"{what}: expected HxW, HxWxC or BxHxWxC, got shape {a.shape}")
  if a.shape[3] not in (1, 3):
    raise SljaxError(f"{what}: images need 1 or 3 channels, got {a.shape[3]} (shape {a.shape})")
  if 0 in a.shape:
    raise SljaxError(f"{what}: empty image of shape {a.shape}")
  return a, batched


def convert_channels(images: np.ndarray, channels: int) -> np.ndarray:
  """...xC float images -> ...x`channels` (gray <-> RGB)."""
  c = images.shape[-1]
  if c == channels:
    return images
  if channels == 1:
    return to_gray(images)
  if channels == 3:
    return np.repeat(images, 3, axis=-1)
  raise SljaxError(f"cannot convert {c}-channel images to {channels} channels")


def prepare_pair(left: Any, right: Any, channels: int | None = None,
                 name: str = "input") -> tuple[np.ndarray, np.ndarray, bool]:
  """Checks and converts a stereo pair to float32 BxHxWxC in [0, 1] (C = channels if given)."""
  lb, batched = as_batch(left, f"{name}: left view")
  rb, batched_r = as_batch(right, f"{name}: right view")
  if batched != batched_r or lb.shape[:3] != rb.shape[:3]:
    raise SljaxError(f"{name}: left and right views differ in size: {np.shape(left)} vs "
                     f"{np.shape(right)}")
  lf = unit_image(lb, f"{name}: left view")
  rf = unit_image(rb, f"{name}: right view")
  if channels is not None:
    lf, rf = convert_channels(lf, channels), convert_channels(rf, channels)
  elif lf.shape[3] != rf.shape[3]:  # one gray, one colour: promote the gray one
    lf, rf = convert_channels(lf, 3), convert_channels(rf, 3)
  return lf, rf, batched


def resize_maps(maps: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
  """Bilinear (half-pixel centres) resize of BxHxW or BxHxWxC float maps."""
  if maps.shape[1:3] == tuple(hw):
    return maps
  out = []
  for m in maps:  # one cv2 call per image (cv2 handles up to 512 channels at once)
    r = cv2.resize(np.ascontiguousarray(m, dtype=np.float32), (hw[1], hw[0]),
                   interpolation=cv2.INTER_LINEAR)
    out.append(r.reshape(hw + m.shape[2:]))
  return np.stack(out)
