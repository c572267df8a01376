"""One stereo scene in memory, as every scene source (folder, synthetic, SCARED) yields it."""

import dataclasses
from typing import Any

import numpy as np

from sljax.data.calib import Calib


@dataclasses.dataclass
class Scene:
  """A rectified stereo scene; parts a source lacks are None.

  Conventions: images float32 in [0, 1], HxWxC (C = 1 or 3); disparities float32 HxW,
  left-referenced, inf = unknown; patterns float32 HxWxt, 1 = lit, 0 = dark, NaN = unknown;
  raw captures float32 HxW in [0, 1] keyed 'white', 'black', 'p000'..., 'i000'....
  """
  name: str
  im0: np.ndarray
  im1: np.ndarray
  disp0: np.ndarray | None = None
  disp1: np.ndarray | None = None
  mask0: np.ndarray | None = None  # bool HxW, region of interest for "Seg" metrics
  sl0: np.ndarray | None = None
  sl1: np.ndarray | None = None
  raw0: dict[str, np.ndarray] | None = None
  raw1: dict[str, np.ndarray] | None = None
  calib: Calib | None = None
  meta: dict[str, Any] = dataclasses.field(default_factory=dict)

  @property
  def group(self) -> str:
    """Group id for group-level splits; a scene without one is its own group."""
    return str(self.meta.get("group", self.name))

  @property
  def shape(self) -> tuple[int, int]:
    """(height, width) of the views."""
    return self.im0.shape[:2]
