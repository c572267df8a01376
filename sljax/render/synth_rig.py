"""An unrectified stereo rig with a projector around the synthetic renderer's rectified scenes:
captures as a real rig takes them, with their calibration and ground truth.

The renderer (sljax.render.synthetic) renders a rectified pair: pinhole cameras K_r (focal f_r,
principal point at the centre), the right one at (B, 0, 0) in the left one's frame. Here each
real camera i is that rectified camera turned by a rotation Q_i (a point X in rectified camera
i's frame is Q_i X in real camera i's) and given its own intrinsics M_i and lens distortion D_i.
Then X_right = Q_2 (Q_1^T X_left - (B, 0, 0)), so the OpenCV calibration is R = Q_2 Q_1^T,
T = -Q_2 (B, 0, 0). A real camera's pixel sees the rectified pixel K_r Q_i^T undistort(M_i^-1
pixel); the captures are the rendered frames resampled there (cv2.remap).

Frames follow OpenCV's GrayCodePattern for a W x H projector (sljax.capture.frames): the
renderer's projector (2^t columns over a square field of view) lights the pixel's point at the
continuous projector coordinate (col, row), computed here in closed form from the depth and
checked against the renderer's own column; a W x H projector over the same field of view shows
column floor(col W / 2^t) and row floor(row H / 2^t). A frame is black + (white - black) x
stripe, white and black being the renderer's noise-free, unblurred raw captures (its projector
light and ambient light); frames are rendered at `oversample` times the rectified size and area
averaged, as a camera's pixels integrate light.

Ground truth in an importer's rectified frame (rotations R1, R2 and projections P1, P2 of its
own cv2.stereoRectify) follows each of its pixels' rays back into the render, reads the rendered
disparity there (bilinear, unknown at depth edges) and reprojects the point (float64).
Degradations (blur, indirect light, noise, saturation) act on the real camera's frames, as
they happen in the camera.
"""

import dataclasses
import math
from collections.abc import Iterator

import cv2
import numpy as np

from sljax.capture import frames
from sljax.capture.rig import StereoCalibration
from sljax.render.synthetic import SynthConfig, SyntheticScene


@dataclasses.dataclass(frozen=True)
class RigConfig:
  """The real cameras around the rendered rectified pair."""
  size: tuple[int, int] = (160, 120)  # real image (width, height)
  rotation_deg: tuple[tuple[float, float, float], ...] = ((0.9, -1.4, 0.6), (-0.7, 1.1, -0.5))
  focal_scale: tuple[float, float] = (1.12, 1.16)  # real focal / rectified focal (per camera)
  centre_offset_px: tuple[tuple[float, float], ...] = ((2.5, -1.5), (-1.5, 2.0))
  distortion: tuple[tuple[float, ...], ...] = ((-0.12, 0.03, 0.0012, -0.0008, 0.0),
                                               (-0.09, 0.02, -0.001, 0.0011, 0.0))
  projector: tuple[int, int] = (200, 150)  # (W, H) of the OpenCV GrayCodePattern


@dataclasses.dataclass(frozen=True)
class Degradation:
  """What a real capture adds, applied to every frame in the real camera (values in [0, 1])."""
  blur_px: float = 0.0        # Gaussian sigma (defocus)
  global_light: float = 0.0   # indirect light: share of each frame's low-passed projector light
  global_sigma: float = 0.15  # low-pass sigma, share of the image width
  offset: float = 0.0         # share of the low-passed white frame added to every frame
  noise: float = 0.0          # std of additive Gaussian noise
  saturated: float = 0.0      # share of the white frame's pixels overexposed (clipped at 1)
  seed: int = 0


def rotation(deg: tuple[float, float, float]) -> np.ndarray:
  """Rotation matrix of a rotation vector given in degrees."""
  return cv2.Rodrigues(np.deg2rad(np.asarray(deg, np.float64)))[0]


def rectified_intrinsics(cfg: SynthConfig, oversample: int = 1) -> np.ndarray:
  """K of the rendered rectified cameras at `cfg.size / oversample` pixels."""
  size = cfg.size / oversample
  f = cfg.focal_factor * size
  c = (size - 1) / 2.0
  return np.array([[f, 0, c], [0, f, c], [0, 0, 1]], np.float64)


def rig_rotations(rig: RigConfig) -> tuple[np.ndarray, np.ndarray]:
  """(Q_1, Q_2): rectified camera frame -> real camera frame."""
  return rotation(rig.rotation_deg[0]), rotation(rig.rotation_deg[1])


def real_intrinsics(rig: RigConfig, k_rect: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """(M_1, M_2) of the real cameras."""
  w, h = rig.size
  out = []
  for scale, (ox, oy) in zip(rig.focal_scale, rig.centre_offset_px):
    f = k_rect[0, 0] * scale
    out.append(np.array([[f, 0, (w - 1) / 2 + ox], [0, f, (h - 1) / 2 + oy], [0, 0, 1]]))
  return out[0], out[1]


def calibration(rig: RigConfig, k_rect: np.ndarray, baseline: float) -> StereoCalibration:
  """The OpenCV calibration of the rig (T in the unit of baseline)."""
  q1, q2 = rig_rotations(rig)
  m1, m2 = real_intrinsics(rig, k_rect)
  d1, d2 = (np.asarray(d, np.float64).reshape(1, -1) for d in rig.distortion)
  return StereoCalibration(m1=m1, d1=d1, m2=m2, d2=d2, r=q2 @ q1.T,
                           t=(-q2 @ np.array([baseline, 0.0, 0.0])).reshape(3, 1),
                           size=tuple(rig.size), where="synthetic rig")


def undistort_normalised(xd: np.ndarray, yd: np.ndarray, dist: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
  """Ideal normalised coordinates whose Brown-Conrady distortion (k1 k2 p1 p2 k3) is (xd, yd):
  a fixed-point iteration in float64, checked to have converged."""
  k1, k2, p1, p2, k3 = np.ravel(dist)[:5]
  x, y = xd.copy(), yd.copy()
  for _ in range(200):
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    x_new = (xd - (2 * p1 * x * y + p2 * (r2 + 2 * x * x))) / radial
    y_new = (yd - (p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)) / radial
    step = max(np.abs(x_new - x).max(initial=0), np.abs(y_new - y).max(initial=0))
    x, y = x_new, y_new
    if step < 1e-15:
      break
  r2 = x * x + y * y
  radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
  resid = np.hypot(x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd,
                   y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - yd)
  assert resid.max() < 1e-12, f"undistortion did not converge ({resid.max():g})"
  return x, y


def real_to_rectified(rig: RigConfig, k_rect: np.ndarray, view: int
                      ) -> tuple[np.ndarray, np.ndarray]:
  """Rectified (rendered) pixel coordinates (float64) seen by each pixel of real camera view."""
  q = rig_rotations(rig)[view]
  m = real_intrinsics(rig, k_rect)[view]
  w, h = rig.size
  u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
  xd, yd = (u - m[0, 2]) / m[0, 0], (v - m[1, 2]) / m[1, 1]
  x, y = undistort_normalised(xd, yd, np.asarray(rig.distortion[view], np.float64))
  ray = np.stack([x, y, np.ones_like(x)], -1) @ q  # Q^T applied to each row vector
  return (k_rect[0, 0] * ray[..., 0] / ray[..., 2] + k_rect[0, 2],
          k_rect[1, 1] * ray[..., 1] / ray[..., 2] + k_rect[1, 2])


def projector_coordinates(scene: SyntheticScene, cfg: SynthConfig
                          ) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
  """((col, row) of the left view, of the right view): the continuous coordinates, in the
  renderer's 2^t-column projector, of the projector pixel lighting each pixel's point (NaN where
  the renderer's projector does not reach it)."""
  cfg = cfg.resolved()
  size = cfg.size
  c = (size - 1) / 2.0
  width_p = 2 ** cfg.t
  f_p = (width_p / 2) / math.tan(math.radians(cfg.projector_fov_deg) / 2)
  ax, ay, az = np.deg2rad(cfg.projector_rotation_deg)
  rot_p = _axis(0, ax) @ _axis(1, ay) @ _axis(2, az)
  t_p = np.asarray(cfg.projector_translation_m, np.float64)
  ys, xs = np.mgrid[0:size, 0:size].astype(np.float64)
  out = []
  for view, (depth, col) in enumerate(((scene.depth0, scene.proj_col0),
                                       (scene.depth1, scene.proj_col1))):
    z = depth.astype(np.float64)
    p = np.stack([(xs - c) / cfg.focal * z + view * cfg.baseline_m, (ys - c) / cfg.focal * z, z],
                 -1)
    q = (p - t_p) @ rot_p  # rot_p^T (p - t_p) for row vectors
    lit = np.isfinite(col)
    out.append((np.where(lit, f_p * q[..., 0] / q[..., 2] + width_p / 2, np.nan),
                np.where(lit, f_p * q[..., 1] / q[..., 2] + width_p / 2, np.nan)))
  return tuple(out)


def _axis(axis: int, angle: float) -> np.ndarray:
  """Rotation about a coordinate axis (as sljax.render.synth_scenes.axis_rotation)."""
  c, s = math.cos(angle), math.sin(angle)
  i, j = [(1, 2), (2, 0), (0, 1)][axis]
  m = np.eye(3)
  m[i, i], m[j, j], m[i, j], m[j, i] = c, c, -s, s
  return m


def rectified_frames(scene: SyntheticScene, cfg: SynthConfig, projector: tuple[int, int],
                     view: int, oversample: int = 1) -> Iterator[np.ndarray]:
  """One view's frames in OpenCV's GrayCodePattern order (column bits and inverses, row bits
  and inverses, white, black), float32 in the rectified frame at cfg.size / oversample, one at
  a time (a 2048-pixel capture's 46 frames would not all fit in memory as floats)."""
  cfg = cfg.resolved()
  width_p = 2 ** cfg.t
  w_proj, h_proj = projector
  n, m = frames.bit_counts(projector)
  col, row = projector_coordinates(scene, cfg)[view]
  raw = (scene.raw0, scene.raw1)[view]
  black = raw["black"].astype(np.float32)
  lit = np.isfinite(col)
  signal = np.where(lit, np.maximum(raw["white"] - raw["black"], 0), 0).astype(np.float32)
  c_int = np.clip(np.floor(np.where(lit, col, 0) * w_proj / width_p), 0, w_proj - 1)
  r_int = np.clip(np.floor(np.where(lit, row, 0) * h_proj / width_p), 0, h_proj - 1)
  for value, bits in ((c_int.astype(np.int64), n), (r_int.astype(np.int64), m)):
    gray = value ^ (value >> 1)
    for k in range(bits):
      on = ((gray >> (bits - 1 - k)) & 1).astype(np.float32)
      for plane in (on, 1.0 - on):
        yield _downsample(black + signal * plane, oversample)
  yield _downsample(black + signal, oversample)
  yield _downsample(black, oversample)


def _downsample(image: np.ndarray, factor: int) -> np.ndarray:
  """Area average over factor x factor blocks."""
  if factor == 1:
    return image
  h, w = image.shape[:2]
  return image.reshape(h // factor, factor, w // factor, factor).mean(axis=(1, 3))


def warp_to_real(frame: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
  """A rectified frame resampled into a real camera (bilinear; black outside the render)."""
  return cv2.remap(frame.astype(np.float32), maps[0], maps[1], cv2.INTER_LINEAR,
                   borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)


class Camera:
  """What a real camera records of a frame (values in [0, 1]): blurred, plus indirect
  projector light (the frame's own projector light, low-passed, times global_light: about half
  the white frame's under a fine pattern and under its inverse alike, none under black), plus
  an offset (the low-passed white frame times `offset`, in every frame, black included), times
  an exposure gain that overexposes the share `saturated` of the white frame's pixels, plus
  noise, clipped to [0, 1]. Noise is drawn from (seed, view) in the order frames come."""

  def __init__(self, how: Degradation, view: int, white: np.ndarray, black: np.ndarray):
    self.how, self.black = how, black
    self.rng = np.random.default_rng([how.seed, view])
    self.offset = 0.0
    if how.offset > 0:
      self.offset = how.offset * cv2.GaussianBlur(white, (0, 0), how.global_sigma * white.shape[1],
                                                  borderType=cv2.BORDER_REFLECT)
    self.gain = 1.0
    if how.saturated > 0:  # the exposure that drives that share of the white frame to 1
      self.gain = 1.0 / max(float(np.quantile(self._light(white), 1.0 - how.saturated)), 1e-6)

  def _light(self, f: np.ndarray) -> np.ndarray:
    how = self.how
    g = cv2.GaussianBlur(f, (0, 0), how.blur_px) if how.blur_px > 0 else f
    if how.global_light > 0:
      sigma = how.global_sigma * f.shape[1]
      g = g + how.global_light * cv2.GaussianBlur(f - self.black, (0, 0), sigma,
                                                  borderType=cv2.BORDER_REFLECT)
    return g + self.offset

  def __call__(self, frame: np.ndarray) -> np.ndarray:
    g = self.gain * self._light(frame)
    if self.how.noise > 0:
      g = g + self.rng.normal(0.0, self.how.noise, g.shape)
    return np.clip(g, 0.0, 1.0).astype(np.float32)


def quantize(frame: np.ndarray, bits: int = 8) -> np.ndarray:
  """A frame in [0, 1] as uint8 (bits 8) or uint16 holding `bits`-bit values (12 or 16)."""
  top = 2 ** bits - 1
  return np.round(np.clip(frame, 0, 1) * top).astype(np.uint8 if bits == 8 else np.uint16)


def ground_truth(scene: SyntheticScene, cfg: SynthConfig, rig: RigConfig, rect,
                 oversample: int = 1, min_signal: float = 0.06, edge_px: float = 0.5
                 ) -> tuple[np.ndarray, np.ndarray]:
  """(disp0, disp1) in an importer's rectified frame (rect: sljax.capture.rig.Rectification of the
  rig's calibration), inf where unknown: where the rendered disparity is not smooth (its 2x2
  neighbours differ by more than edge_px rendered pixels), where the projector light is weaker
  than min_signal, where the renderer marks the point hidden from the other camera, and where
  the two views' ground truths do not confirm each other (within 1 px)."""
  cfg = cfg.resolved()
  k_r = rectified_intrinsics(cfg)  # the render's own resolution
  q = rig_rotations(rig)
  w, h = rect.size
  known_render = []
  for raw, col, occ in ((scene.raw0, scene.proj_col0, scene.occ0),
                        (scene.raw1, scene.proj_col1, scene.occ1)):
    known_render.append(np.isfinite(col) & ~occ & (raw["white"] - raw["black"] >= min_signal))
  disps = []
  for view, (r_imp, p_imp, disp, known) in enumerate((
      (rect.r1, rect.p1, scene.disp0, known_render[0]),
      (rect.r2, rect.p2, scene.disp1, known_render[1]))):
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    ray = np.stack([(u - p_imp[0, 2]) / p_imp[0, 0], (v - p_imp[1, 2]) / p_imp[1, 1],
                    np.ones_like(u)], -1)
    s = ray @ r_imp @ q[view]  # importer rectified -> real camera -> rendered camera
    ur = k_r[0, 0] * s[..., 0] / s[..., 2] + k_r[0, 2]
    vr = k_r[1, 1] * s[..., 1] / s[..., 2] + k_r[1, 2]
    d_r, ok = _bilinear(disp.astype(np.float64), known, ur, vr, edge_px)
    z = np.where(ok, k_r[0, 0] * cfg.baseline_m / np.where(ok, d_r, 1.0), np.nan)
    point = z[..., None] * s / s[..., 2:3]  # in the rendered camera's frame
    z_imp = (point @ q[view].T @ r_imp.T)[..., 2]
    d = np.where(ok & (z_imp > 0), rect.focal * cfg.baseline_m / z_imp, np.inf)
    disps.append(d)
  return _confirmed(disps[0], disps[1], 1.0, 1), _confirmed(disps[1], disps[0], -1.0, 1)


def _bilinear(values: np.ndarray, known: np.ndarray, x: np.ndarray, y: np.ndarray,
              edge: float) -> tuple[np.ndarray, np.ndarray]:
  """Bilinear samples of values at (x, y) and whether all four neighbours are known and within
  `edge` of each other."""
  h, w = values.shape
  x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
  inside = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h)
  xi, yi = np.clip(x0, 0, w - 2), np.clip(y0, 0, h - 2)
  corners = [values[yi + dy, xi + dx] for dy in (0, 1) for dx in (0, 1)]
  ok = inside & np.logical_and.reduce([known[yi + dy, xi + dx] for dy in (0, 1) for dx in (0, 1)])
  stack = np.stack(corners)
  ok &= np.all(np.isfinite(stack), 0) & (np.ptp(np.where(np.isfinite(stack), stack, 0), 0) <= edge)
  fx, fy = x - x0, y - y0
  val = (corners[0] * (1 - fx) * (1 - fy) + corners[1] * fx * (1 - fy)
         + corners[2] * (1 - fx) * fy + corners[3] * fx * fy)
  return np.where(ok, val, np.nan), ok


def _confirmed(d_a: np.ndarray, d_b: np.ndarray, sign: float, tol: float) -> np.ndarray:
  """d_a where view b's ground truth at the matched pixel (nearest) agrees within tol."""
  h, w = d_a.shape
  finite = np.isfinite(d_a)
  xb = np.rint(np.arange(w)[None, :] - sign * np.where(finite, d_a, 0)).astype(np.int64)
  inside = finite & (xb >= 0) & (xb < w)
  back = d_b[np.arange(h)[:, None], np.clip(xb, 0, w - 1)]
  ok = inside & np.isfinite(back)
  ok &= np.abs(np.where(ok, d_a, 0) - np.where(ok, back, 0)) <= tol
  return np.where(ok, d_a, np.inf).astype(np.float32)


def real_captures(scene: SyntheticScene, cfg: SynthConfig, rig: RigConfig,
                  oversample: int = 1, how: Degradation = Degradation(), bits: int = 8
                  ) -> tuple[list[np.ndarray], list[np.ndarray]]:
  """Both real cameras' frames in OpenCV's GrayCodePattern order, quantized to `bits`."""
  k_rect = rectified_intrinsics(cfg, oversample)
  out = []
  for view in (0, 1):
    maps = tuple(m.astype(np.float32) for m in real_to_rectified(rig, k_rect, view))
    raw = (scene.raw0, scene.raw1)[view]
    lit = np.isfinite((scene.proj_col0, scene.proj_col1)[view])
    black = raw["black"].astype(np.float32)
    white = black + np.where(lit, np.maximum(raw["white"] - black, 0), 0).astype(np.float32)
    camera = Camera(how, view, *(warp_to_real(_downsample(f, oversample), maps)
                                 for f in (white, black)))
    out.append([quantize(camera(warp_to_real(f, maps)), bits)
                for f in rectified_frames(scene, cfg, rig.projector, view, oversample)])
  return out[0], out[1]
