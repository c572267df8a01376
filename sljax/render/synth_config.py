"""The synthetic renderer's settings (`SynthConfig`) and the checks on what it is handed.

Below the renderer's stages (synth_scenes, synth_surface), which read the settings, and the
renderer (synthetic), which resolves and renders them.
"""

import dataclasses
import math
from typing import Any

import numpy as np

from sljax.errors import require
from sljax.sl import codes

DOMAINS = ("objects", "tissue")


def _is_int(v: Any) -> bool:
  """An integer that is not a bool (True would pass for 1)."""
  return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


def _is_real(v: Any) -> bool:
  """A real number that is not a bool."""
  return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(
      v, (bool, np.bool_))


def check_seed_index(seed: Any, index: Any) -> None:
  """Seeds and indices are uint32 in the renderer: outside that JAX fails with an overflow."""
  for name, v in (("seed", seed), ("index", index)):
    require(_is_int(v) and 0 <= v < 2**32,
            f"synthetic scene {name} must be an integer in 0..2^32-1, got {v!r}")


@dataclasses.dataclass(frozen=True)
class SynthConfig:
  """Renderer settings; None fields take the domain's default (see `resolved`)."""
  size: int = 256                      # image width = height (px)
  domain: str = "objects"              # "objects" (paper's virtual set) or "tissue"
  code: str | None = None              # binary (objects) / gray (tissue)
  t: int | None = None                 # patterns: 8 (binary) / 9 (gray); projector width 2^t
  focal_factor: float = 1.2            # f = focal_factor * size px (about 45 deg field of view)
  baseline_m: float | None = None      # 0.012 (objects) / 0.005 (tissue, laparoscope-like)
  projector_translation_m: tuple[float, float, float] = (0.02, 0.0, 0.02)  # in left-camera axes
  projector_rotation_deg: tuple[float, float, float] = (0.0, 1.5, 0.0)     # about x, y, z
  projector_fov_deg: float | None = None  # horizontal = vertical; 70 (objects) / 90 (tissue)
  views_per_object: int = 10           # views sharing one object (one group)
  object_size_m: tuple[float, float] = (0.03, 0.10)
  podium_height_m: float = 0.10
  num_ellipsoids: int | None = None    # 7 (objects) / 8 (tissue lobes)
  texture_amplitude: float | None = None  # 0.05 (objects: nearly textureless) / 1.0 (tissue)
  specular: float | None = None        # 0 (objects) / 0.25 (tissue); im0/im1 only
  ambient: float = 0.25                # im0/im1: ambient light
  light: float = 0.75                  # im0/im1: rig light (Lambertian)
  projector_power: float = 0.7         # raw: projector irradiance on a frontal surface
  raw_ambient: float = 0.08            # raw: ambient light
  min_contrast: float = 0.06           # patterns unknown where albedo x irradiance is below
  min_stripe_px: float = 1.0           # a pattern bit is unknown where its stripes are narrower
  image_noise: float = 0.002           # std of im0/im1 sensor noise
  raw_noise: float = 0.004             # std of raw capture sensor noise
  raw_blur: float = 0.4                # raw capture blur (Gaussian sigma, px)
  max_disparity_fraction: float = 0.22  # nearest surface disparity <= this * size

  def resolved(self) -> "SynthConfig":
    """A copy with every domain default filled in, validated."""
    require(self.domain in DOMAINS, f"unknown synthetic domain {self.domain!r}; "
            f"expected one of {DOMAINS}")
    require(_is_int(self.size) and self.size >= 16,
            f"synthetic image size must be an integer >= 16 px, got {self.size!r}")
    obj = self.domain == "objects"
    code = self.code or ("binary" if obj else "gray")
    require(code in codes.CODES, f"unknown code {code!r}; expected one of {codes.CODES}")
    t = self.t if self.t is not None else (8 if code == "binary" else 9)
    require(_is_int(t) and 1 <= t <= 12, f"number of patterns t must be an integer in 1..12, "
            f"got {t!r}")
    require(_is_int(self.views_per_object) and self.views_per_object >= 1,
            f"views_per_object must be an integer >= 1, got {self.views_per_object!r}")
    pick = lambda v, a, b: v if v is not None else (a if obj else b)  # noqa: E731
    resolved = dataclasses.replace(
        self, code=code, t=t, baseline_m=pick(self.baseline_m, 0.012, 0.005),
        num_ellipsoids=pick(self.num_ellipsoids, 7, 8),
        texture_amplitude=pick(self.texture_amplitude, 0.05, 1.0),
        specular=pick(self.specular, 0.0, 0.25),
        projector_fov_deg=pick(self.projector_fov_deg, 70.0, 90.0))
    resolved._check_values()
    return resolved

  def _check_values(self) -> None:
    """SljaxError naming the first field whose value would render garbage or fail in JAX."""
    def field(name: str, ok, expected: str) -> None:
      v = getattr(self, name)
      require(ok(v), f"SynthConfig.{name} must be {expected}, got {v!r}")

    def number(lo: float, hi: float = math.inf, lo_open: bool = False):
      def ok(v):
        if not _is_real(v) or not math.isfinite(v) or v > hi:
          return False
        return v > lo if lo_open else v >= lo
      return ok

    def vector(n: int):
      return lambda v: (isinstance(v, (tuple, list)) and len(v) == n
                        and all(_is_real(x) and math.isfinite(x) for x in v))

    # A zero/negative focal length or baseline gives NaN or negative disparities, a projector
    # field of view of 180 deg or more an infinite tan, zero lobes an empty shape.
    field("focal_factor", number(0, lo_open=True), "a positive number")
    field("baseline_m", number(0, lo_open=True), "a positive number (metres)")
    field("projector_fov_deg", lambda v: number(0, lo_open=True)(v) and v < 180,
          "in (0, 180) degrees")
    field("projector_translation_m", vector(3), "3 finite numbers (metres)")
    field("projector_rotation_deg", vector(3), "3 finite numbers (degrees)")
    field("object_size_m", lambda v: vector(2)(v) and 0 < v[0] <= v[1],
          "(min, max) metres with 0 < min <= max")
    field("num_ellipsoids", lambda v: _is_int(v) and v >= 1, "an integer >= 1")
    field("max_disparity_fraction", number(0, 1, lo_open=True), "in (0, 1]")
    for name in ("podium_height_m", "texture_amplitude", "specular", "ambient", "light",
                 "projector_power", "raw_ambient", "min_contrast", "min_stripe_px",
                 "image_noise", "raw_noise", "raw_blur"):
      field(name, number(0), "a finite number >= 0")

  @property
  def focal(self) -> float:
    """Focal length in pixels."""
    return self.focal_factor * self.size
