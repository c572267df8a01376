"""Middlebury 2014 calib.txt: the camera model of a rectified stereo pair."""

import dataclasses

import numpy as np


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
