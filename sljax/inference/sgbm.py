"""Classical baseline: OpenCV's semi-global block matching (StereoSGBM) as a predictor.

Parameters (fixed, the usual OpenCV recipe; cn = channels, bs = block size):
  minDisparity 0; numDisparities = calib ndisp (else the option, else 25% of the width) rounded
  up to a multiple of 16; blockSize 5; P1 = 8 * cn * bs^2; P2 = 32 * cn * bs^2;
  disp12MaxDiff 1; preFilterCap 63; uniquenessRatio 10; speckleWindowSize 100;
  speckleRange 2; mode MODE_SGBM_3WAY.
SGBM leaves the leftmost numDisparities columns unmatched; the pair is therefore padded on the
left by numDisparities columns (edge replication) and the padding cropped from the result, so
every pixel searches the whole range. Output disparity = SGBM's fixed-point value / 16; pixels
SGBM marks invalid (negative values) are inf, which the metrics count as invalid predictions.
"""

import dataclasses
import math
from typing import Any

import cv2
import numpy as np

from sljax.errors import SljaxError
from sljax.inference import prepare_pair


@dataclasses.dataclass(frozen=True)
class SGBMConfig:
  """StereoSGBM parameters (see the module docstring)."""
  num_disparities: int | None = None  # None: calib ndisp, else 25% of the width
  block_size: int = 5
  p1_factor: int = 8
  p2_factor: int = 32
  disp12_max_diff: int = 1
  pre_filter_cap: int = 63
  uniqueness_ratio: int = 10
  speckle_window_size: int = 100
  speckle_range: int = 2
  pad_left: bool = True


def round_up_16(n: float) -> int:
  """Smallest positive multiple of 16 that is >= n."""
  return max(16, int(math.ceil(n / 16.0)) * 16)


class SGBMPredictor:
  """predict(left, right, calib=None) -> {'disparity': HxW float32, inf = no match}."""

  model_name = "sgbm"
  is_sl = False
  mode = "full"

  def __init__(self, config: SGBMConfig = SGBMConfig(), name: str = "sgbm"):
    if config.num_disparities is not None and config.num_disparities <= 0:
      raise SljaxError(f"--num-disparities must be positive, got {config.num_disparities}")
    if config.block_size < 1 or config.block_size % 2 == 0:
      raise SljaxError(f"SGBM block size must be a positive odd number, got {config.block_size}")
    self.config = config
    self.name = name

  def describe(self) -> str:
    """One line for reports."""
    c = self.config
    nd = "calib ndisp" if c.num_disparities is None else str(round_up_16(c.num_disparities))
    return (f"OpenCV StereoSGBM at full resolution (numDisparities {nd} rounded up to 16, "
            f"blockSize {c.block_size}, P1 {c.p1_factor}*cn*bs^2, P2 {c.p2_factor}*cn*bs^2, "
            f"uniqueness {c.uniqueness_ratio}, speckle {c.speckle_window_size}/{c.speckle_range}, "
            "3-way)")

  def num_disparities(self, width: int, calib: Any = None) -> int:
    """The disparity range searched, a multiple of 16."""
    if self.config.num_disparities is not None:
      return round_up_16(self.config.num_disparities)
    if calib is not None and getattr(calib, "ndisp", None):
      return round_up_16(calib.ndisp)
    return round_up_16(0.25 * width)

  def _one(self, left: np.ndarray, right: np.ndarray, nd: int) -> np.ndarray:
    c = self.config
    cn = left.shape[2]
    to8 = lambda a: np.round(a * 255.0).astype(np.uint8)
    l8, r8 = to8(left), to8(right)
    pad = nd if c.pad_left else 0
    if pad:
      widths = ((0, 0), (pad, 0), (0, 0))
      l8, r8 = np.pad(l8, widths, mode="edge"), np.pad(r8, widths, mode="edge")
    if cn == 1:
      l8, r8 = l8[..., 0], r8[..., 0]
    matcher = cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=nd, blockSize=c.block_size,
        P1=c.p1_factor * cn * c.block_size ** 2, P2=c.p2_factor * cn * c.block_size ** 2,
        disp12MaxDiff=c.disp12_max_diff, preFilterCap=c.pre_filter_cap,
        uniquenessRatio=c.uniqueness_ratio, speckleWindowSize=c.speckle_window_size,
        speckleRange=c.speckle_range, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    raw = matcher.compute(np.ascontiguousarray(l8), np.ascontiguousarray(r8))[:, pad:]
    disp = raw.astype(np.float32) / 16.0
    disp[raw < 0] = np.inf  # SGBM writes (minDisparity - 1) * 16 where it found no match
    return disp

  def __call__(self, left: np.ndarray, right: np.ndarray,
               calib: Any = None) -> dict[str, np.ndarray]:
    """Disparity of a pair (or a batch: one SGBM run per pair)."""
    lf, rf, batched = prepare_pair(left, right, None, self.name)
    nd = self.num_disparities(lf.shape[2], calib)
    disp = np.stack([self._one(a, b, nd) for a, b in zip(lf, rf)])
    return {"disparity": disp if batched else disp[0]}
