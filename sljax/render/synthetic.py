"""Procedural stereo + projector renderer: the built-in dataset (objects and tissue domains).

Geometry (world frame: metres, z up). A room [-0.5, 0.5]^2 x [0, 1] closes every scene.
- objects: a podium (cylinder, 10 cm high) carries one random object, a union of K random
  ellipsoids (a body and satellites on its surface: lobes, creases and self-occlusion) whose
  extent is U(3, 10) cm, seen from random viewpoints looking at its centre.
- tissue: a cluster of flattened, overlapping ellipsoidal lobes (folds between lobes) lying on a
  table (the room floor), seen from above at 7-12 cm.
Every surface is intersected in closed form, so depth, normals, projector shadows and occlusions
between the views are exact (float32 rounding only).

Rig. A rectified stereo pair (focal f = focal_factor * size px, principal point at the image
centre, baseline B; Z = f B / d, doffs = 0) and a projector rigidly attached to the left camera
(translation, rotation about the camera axes, square field of view) whose 2^t columns carry the
plain binary (t = 8) or Gray (t = 9) stripe code of sljax.sl.codes. A light fixed to the rig sits
at the projector's centre, so the light's cast shadows are exactly the projector shadows.

Distance choice. The paper (Blender) put the camera U(3, 10) cm from objects scaled U(3, 10) cm;
with our pinhole rig (45 deg field of view, B = 12 mm) the camera distance is instead chosen per
view so that the object's projected radius is U(0.22, 0.38) of the image width (coverage 10-90%)
and the nearest surface has a disparity <= max_disparity_fraction * width; the room walls
(<= 1.4 m) stay above 2.5 px. So >= 99% of disparities lie in [1, W/4].

Pixels: (x, y) = integer pixel centres, the ray of pixel x passes through x exactly. A left pixel x
with disparity d sees the point of right pixel x - d. Ground-truth patterns are the code bits of
the projector column that lights the pixel centre's surface point; they are unknown (NaN) where
the point is in projector shadow (including self-shadow), outside the projector's field of view,
or too weakly lit to be decoded (albedo x projector irradiance < min_contrast).

Raw captures (grey): black = albedo * raw_ambient, white = black + albedo * irradiance, pattern
k and its inverse in between; blurred (Gaussian raw_blur px) and with sensor noise. They are
matte: specular highlights only appear in im0/im1. Sensor noise (im0/im1 and raw) is a cheap
counter-based approximation of Gaussian noise (see synth_sensor.noise: a 32-bit integer hash of the
index and the scene's noise key, the sum of its four bytes standardised; bounded at +-3.45 sigma).

Determinism: scene i of seed s depends on (s, i) only: the shape (shared by the 10 views of a
group, group = i // views_per_object) uses fold_in(fold_in(PRNGKey(s), 0), group), the view
fold_in(fold_in(PRNGKey(s), 1), i) and the noise fold_in(fold_in(PRNGKey(s), 2), i). Each scene
is rendered on its own, so nothing depends on batch size or worker count.

Speed: both views are rendered together ((2, H, W) arrays) by a few jitted stages, compiled once
per configuration (the comment above _rig says why stages): about 14 ms of CPU per 256x256 scene,
29 ms with raw captures (benchmarks/bench_synthetic.py).
"""

import dataclasses
import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from sljax.data.camera import Calib
from sljax.data.scene import Scene
from sljax.errors import require
from sljax.render import synth_geometry as geo
from sljax.render import synth_scenes as scenes
from sljax.render import synth_sensor as sensor
from sljax.render import synth_surface as surface
from sljax.render.synth_config import SynthConfig, check_seed_index
from sljax.runtime import kept_programs

ROOM_LO = (-0.5, -0.5, 0.0)
ROOM_HI = (0.5, 0.5, 1.0)
_LUMA = (0.299, 0.587, 0.114)


@dataclasses.dataclass
class SyntheticScene(Scene):
  """A rendered Scene plus exact per-pixel extras (not part of the on-disk format).

  occ0: bool HxW, left pixels whose surface point the right camera cannot see (occluded or out
  of its frame); occ1 the same for the right view. depth0/depth1: Z in metres. proj_col0/1:
  continuous projector column lighting the pixel's point (NaN where the projector cannot).
  """
  occ0: np.ndarray | None = None
  occ1: np.ndarray | None = None
  depth0: np.ndarray | None = None
  depth1: np.ndarray | None = None
  proj_col0: np.ndarray | None = None
  proj_col1: np.ndarray | None = None


# ----------------------------------------------------------------------------------------------
# Rendering (inside jit); scene descriptions come from synth_scenes, what a hit looks like
# from synth_surface, noise and blur from synth_sensor.


def _stripe_columns(cfg: SynthConfig) -> np.ndarray:
  """Width in projector columns of the stripes of each pattern (coarsest first)."""
  t = cfg.t
  if cfg.code == "binary":
    return np.array([2 ** (t - 1 - k) for k in range(t)], np.float32)
  # Gray: the coarsest pattern has one edge; pattern k >= 1 has stripes 2^(t-k) columns wide.
  return np.array([2 ** (t - 1)] + [2 ** (t - k) for k in range(1, t)], np.float32)


def _column_rate(col):
  """Local projector column rate |grad col| (px^-1) of (..., H, W) columns (NaN: unlit).

  Uses the smaller one-sided difference along each image axis, so a depth edge next to the pixel
  does not count; a pattern whose stripes are narrower than min_stripe_px aliases (a real camera
  cannot resolve it) and is unknown.
  """
  def rate(axis):
    fwd = jnp.abs(jnp.diff(col, axis=axis, append=jnp.nan))
    bwd = jnp.abs(jnp.diff(col, axis=axis, prepend=jnp.nan))
    fwd = jnp.where(jnp.isnan(fwd), jnp.inf, fwd)
    bwd = jnp.where(jnp.isnan(bwd), jnp.inf, bwd)
    return jnp.minimum(fwd, bwd)
  return jnp.sqrt(rate(-1) ** 2 + rate(-2) ** 2)


# The renderer runs as a few jitted stages. The CPU backend has no multi-output fusion and drops
# optimisation barriers, so inside one jitted graph XLA fuses (recomputes) the whole intersection
# chain into each of its many consumers (10x slower); a stage boundary materialises its outputs
# once. Rays, hit points and other cheap per-pixel values are recomputed inside each stage.


def _rig(seed, index, cfg: SynthConfig) -> dict[str, Any]:
  """Scene description and rig pose of scene `index` of `seed` (small arrays)."""
  root = jax.random.PRNGKey(seed)
  group = index // cfg.views_per_object
  key_shape = jax.random.fold_in(jax.random.fold_in(root, 0), group)
  key_view = jax.random.fold_in(jax.random.fold_in(root, 1), index)
  key_noise = jax.random.fold_in(jax.random.fold_in(root, 2), index)
  sample = scenes.sample_objects if cfg.domain == "objects" else scenes.sample_tissue
  desc = sample(key_shape, key_view, cfg)
  cam_l, rot = surface.camera(desc, cfg)
  rot_p = rot @ scenes.axis_rotation(0, jnp.deg2rad(cfg.projector_rotation_deg[0])) \
      @ scenes.axis_rotation(1, jnp.deg2rad(cfg.projector_rotation_deg[1])) \
      @ scenes.axis_rotation(2, jnp.deg2rad(cfg.projector_rotation_deg[2]))
  return dict(desc=desc, cam_l=cam_l, cam_r=cam_l + cfg.baseline_m * rot[:, 0], rot=rot,
              rot_p=rot_p, proj=cam_l + rot @ jnp.array(cfg.projector_translation_m),
              key_noise=key_noise)


def _rays(rig, cfg: SynthConfig):
  """Both views at once: per-view values (2, 1, 1), per-pixel ones (1 or 2, H, W).

  Returns (origins, other cameras, pixel x, directions); the rectified views share directions
  (z in camera axes is 1, so t is the depth Z).
  """
  h = w = cfg.size
  c = (cfg.size - 1) / 2.0

  def as_views(a, b):
    return tuple(jnp.stack([a[i], b[i]]).reshape(2, 1, 1) for i in range(3))

  ys = jax.lax.broadcasted_iota(jnp.float32, (1, h, w), 1)
  xs = jax.lax.broadcasted_iota(jnp.float32, (1, h, w), 2)
  d = geo.matvec(rig["rot"], ((xs - c) / cfg.focal, (ys - c) / cfg.focal, 1.0))
  return as_views(rig["cam_l"], rig["cam_r"]), as_views(rig["cam_r"], rig["cam_l"]), xs, d


def _points(rig, t, cfg: SynthConfig):
  """First-hit points o + t d (component tuple of (2, H, W))."""
  o, _, _, d = _rays(rig, cfg)
  return tuple(oi + t * di for oi, di in zip(o, d))


def _stage_roots(rig, cfg: SynthConfig):
  """Entry parameters (K, 2, H, W) of every ray into every ellipsoid (inf: missed, behind)."""
  o, _, _, d = _rays(rig, cfg)
  frames, centres = rig["desc"]["frames"], rig["desc"]["centres"]
  d_local = geo.to_frames(d, frames)  # (K, 1, H, W): shared by both views
  o_local = geo.local_components(geo.origins_local(jnp.stack(o, -1)[:, 0, 0], frames, centres), 2)
  e0, _ = geo.unit_sphere_roots(o_local, d_local)
  return jnp.where(e0 > 0, e0, jnp.inf)


def _stage_first_hit(rig, e0, cfg: SynthConfig):
  """First hits: (t, facet id) of each pixel of both views, (2, H, W)."""
  o, _, _, d = _rays(rig, cfg)
  t_obj, k = geo.first_hit(e0)
  t_room, axis = geo.ray_box_exit(o, d, ROOM_LO, ROOM_HI)
  if cfg.domain == "objects":
    t_pod, top = geo.ray_podium(o, d, rig["desc"]["podium_r"], cfg.podium_height_m)
  else:
    t_pod, top = jnp.full_like(t_room, jnp.inf), False
  t = jnp.minimum(jnp.minimum(t_room, t_pod), t_obj)
  facet = jnp.where(t_obj <= t, surface.ELL + k,
                    jnp.where(t_pod <= t, jnp.where(top, surface.POD_TOP, surface.POD_SIDE), axis))
  return t, facet


def _stage_surface(rig, t, facet, cfg: SynthConfig):
  """Normals, shadow and occlusion tests and textures at the first hits."""
  _, other, _, d = _rays(rig, cfg)
  p = _points(rig, t, cfg)
  proj = tuple(rig["proj"][i] for i in range(3))
  # Segments to the projector (the rig light sits there, so its shadows are the projector's) and
  # to the other camera (exact occlusion between the views).
  return (surface.normal(p, d, facet, rig["desc"]), surface.blocked(proj, p, rig["desc"], cfg),
          surface.blocked(other, p, rig["desc"], cfg), surface.textures(p, facet, rig["desc"], cfg))


def _stage_shading(rig, t, facet, normal, blocked_p, blocked_o, tex, cfg: SynthConfig):
  """Per-pixel shading, projector column, pattern visibility and cross-view visibility."""
  o, other, xs, _ = _rays(rig, cfg)
  p = _points(rig, t, cfg)
  proj = tuple(rig["proj"][i] for i in range(3))
  width_p = 2 ** cfg.t
  tan_half = math.tan(math.radians(cfg.projector_fov_deg) / 2)
  f_p = (width_p / 2) / tan_half
  to_p = geo.normalize(tuple(pj - qi for pj, qi in zip(proj, p)))
  inv_n = jax.lax.rsqrt(jnp.maximum(geo.dot(normal, normal), 1e-30))
  cos_p = geo.dot(normal, to_p) * inv_n
  lit = (cos_p > 0) & ~blocked_p
  q = geo.matvec(rig["rot_p"].T, tuple(pi - qi for pi, qi in zip(p, proj)))
  qz = jnp.maximum(q[2], 1e-9)
  col = f_p * q[0] / qz + width_p / 2
  in_fov = (q[2] > 0) & (col >= 0) & (col < width_p) & (jnp.abs(q[1]) <= tan_half * qz)
  reach = lit & in_fov
  sign = jnp.array([-1.0, 1.0]).reshape(2, 1, 1)  # the other view's x = x + sign * disparity
  x_other = xs + sign * (cfg.baseline_m * cfg.focal / t)
  to_other = tuple(oi - pi for oi, pi in zip(other, p))
  seen = ((x_other > -0.5) & (x_other < cfg.size - 0.5) & (geo.dot(normal, to_other) > 0)
          & ~blocked_o)
  albedo = surface.albedo(facet, tex, cfg)
  grey = _LUMA[0] * albedo[0] + _LUMA[1] * albedo[1] + _LUMA[2] * albedo[2]
  irradiance = cfg.projector_power * jnp.maximum(cos_p, 0.0) * reach
  known = reach & (grey * irradiance >= cfg.min_contrast)
  shade = cfg.ambient + cfg.light * jnp.maximum(cos_p, 0.0) * lit
  spec = jnp.zeros(())
  if cfg.specular > 0:
    to_eye = geo.normalize([oi - pi for oi, pi in zip(o, p)])
    half_vec = geo.normalize([a + b for a, b in zip(to_p, to_eye)])
    spec = cfg.specular * lit * (jnp.maximum(geo.dot(normal, half_vec) * inv_n, 0.0) ** 40)
  return shade, spec, jnp.where(reach, col, jnp.nan), known, seen, grey, irradiance


def _code_bits_of(col, cfg: SynthConfig) -> list:
  """Code bits (int32 0/1, coarsest first) of the projector columns col (NaN: unlit -> 0)."""
  col_int = jnp.clip(jnp.floor(jnp.where(jnp.isnan(col), 0.0, col)), 0, 2 ** cfg.t - 1
                     ).astype(jnp.int32)
  c = col_int ^ (col_int >> 1) if cfg.code == "gray" else col_int
  return [(c >> (cfg.t - 1 - k)) & 1 for k in range(cfg.t)]


def _stage_outputs(rig, t, facet, tex, shade, spec, col, known, seen, cfg: SynthConfig):
  """Images with noise, disparities, patterns, masks (views stacked on axis 0)."""
  # Pattern bits of the integer projector column; stripes finer than the camera resolves are
  # unknown, as are unlit or too dark points.
  bits = _code_bits_of(col, cfg)
  rate = cfg.min_stripe_px * _column_rate(col)
  sl = jnp.stack([jnp.where(known & (float(wk) >= rate), b.astype(jnp.float32), jnp.nan)
                  for b, wk in zip(bits, _stripe_columns(cfg))], -1)
  image = jnp.stack([a * shade + spec for a in surface.albedo(facet, tex, cfg)], -1)
  noise_key = jax.random.fold_in(rig["key_noise"], 0)
  image = jnp.clip(image + cfg.image_noise * sensor.noise(noise_key, image.shape), 0, 1)
  desc = rig["desc"]
  return dict(im=image, disp=cfg.baseline_m * cfg.focal / t, depth=t, sl=sl,
              mask=facet >= (surface.ELL if cfg.domain == "tissue" else surface.POD_SIDE),
              occ=~seen,
              col=col, cam=rig["cam_l"], dist=desc["dist"], size=desc["size"],
              azimuth=desc["azimuth"], elevation=desc["elevation"])


def _stage_raw_rows(col, grey, irradiance, cfg: SynthConfig):
  """Raw captures before blur and noise, blurred along rows: (white, black) and signal x bits.

  Blurring is linear: blur(p_k) = blur(black) + blur(s b_k) and blur(i_k) = blur(white) -
  blur(s b_k), so t + 2 blurred images give all 2 t + 2 captures.
  """
  signal = grey * irradiance  # (2, H, W)
  black = grey * cfg.raw_ambient
  base = jnp.stack([black + signal, black], 1)  # white, black
  lit_bits = jnp.stack([signal * b for b in _code_bits_of(col, cfg)], 1)  # (2, t, H, W)
  if cfg.raw_blur > 0:
    w = sensor.blur_weights(cfg.raw_blur)
    base, lit_bits = sensor.blur_axis(base, w, -1), sensor.blur_axis(lit_bits, w, -1)
  return base, lit_bits


def _stage_raw(rig, base, lit_bits, cfg: SynthConfig):
  """Raw captures (2, 2 + 2 t, H, W) in raw_keys order: column blur, sensor noise, clipping."""
  if cfg.raw_blur > 0:
    w = sensor.blur_weights(cfg.raw_blur)
    base, lit_bits = sensor.blur_axis(base, w, -2), sensor.blur_axis(lit_bits, w, -2)
  stack = jnp.concatenate([base, base[:, 1:2] + lit_bits, base[:, 0:1] - lit_bits], 1)
  noise_key = jax.random.fold_in(rig["key_noise"], 1)
  return jnp.clip(stack + cfg.raw_noise * sensor.noise(noise_key, stack.shape), 0, 1)


@functools.lru_cache(maxsize=None)
def _stage(fn, cfg: SynthConfig):
  """fn jitted for one (resolved) configuration: compiled once per config and input shapes,
  and kept whole where a command line keeps programs (sljax.runtime.kept_programs: a later run neither
  traces nor lowers the renderer)."""
  return kept_programs.Program(jax.jit(functools.partial(fn, cfg=cfg)),
                             f"render-{fn.__name__.strip('_')}", repr(cfg)).prefetch()


def _render(seed, index, cfg: SynthConfig, raw: bool) -> dict[str, jax.Array]:
  """Renders scene `index` of `seed`: both views stacked on axis 0 (see render_scene)."""
  rig = _stage(_rig, cfg)(seed, index)
  t, facet = _stage(_stage_first_hit, cfg)(rig, _stage(_stage_roots, cfg)(rig))
  normal, blocked_p, blocked_o, tex = _stage(_stage_surface, cfg)(rig, t, facet)
  shade, spec, col, known, seen, grey, irradiance = _stage(_stage_shading, cfg)(
      rig, t, facet, normal, blocked_p, blocked_o, tex)
  out = _stage(_stage_outputs, cfg)(rig, t, facet, tex, shade, spec, col, known, seen)
  if raw:
    out["raw"] = _stage(_stage_raw, cfg)(rig, *_stage(_stage_raw_rows, cfg)(col, grey, irradiance))
  return out


def raw_keys(t: int) -> list[str]:
  """Raw capture names in the order the renderer stacks them."""
  return (["white", "black"] + [f"p{k:03d}" for k in range(t)]
          + [f"i{k:03d}" for k in range(t)])


def calib_for(cfg: SynthConfig, vmin: float | None = None, vmax: float | None = None) -> Calib:
  """The rig's Middlebury calibration (baseline in mm, doffs 0)."""
  cfg = cfg.resolved()
  c = (cfg.size - 1) / 2.0
  k = np.array([[cfg.focal, 0, c], [0, cfg.focal, c], [0, 0, 1]], np.float64)
  ndisp = max(cfg.size // 4, int(math.ceil(vmax or 0)) + 1)
  return Calib(cam0=k, cam1=k.copy(), doffs=0.0, baseline=cfg.baseline_m * 1000.0,
               width=cfg.size, height=cfg.size, ndisp=ndisp, vmin=vmin, vmax=vmax)


def render_scene(index: int, seed: int, config: SynthConfig = SynthConfig(), raw: bool = False
                 ) -> SyntheticScene:
  """Renders scene `index` of dataset `seed` (depends on (seed, index) only)."""
  require(isinstance(config, SynthConfig),
          f"config must be a SynthConfig, got {type(config).__name__}")
  cfg = config.resolved()
  check_seed_index(seed, index)
  out = jax.device_get(_render(jnp.uint32(seed), jnp.uint32(index), cfg, bool(raw)))
  for k in ("im", "disp", "depth", "sl", "mask", "occ", "col"):  # views stacked on axis 0
    out[f"{k}0"], out[f"{k}1"] = out[k][0], out[k][1]
  disp0 = np.asarray(out["disp0"], np.float32)
  group = int(index) // cfg.views_per_object
  meta = {
      "group": f"{cfg.domain}-s{int(seed)}-g{group:05d}", "domain": cfg.domain,
      "code": cfg.code, "patterns": cfg.t, "generator": "sljax.synthetic", "seed": int(seed),
      "index": int(index), "view": int(index) % cfg.views_per_object,
      "size_m": round(float(out["size"]), 5), "camera_distance_m": round(float(out["dist"]), 5),
      "azimuth_deg": round(math.degrees(float(out["azimuth"])), 3),
      "elevation_deg": round(math.degrees(float(out["elevation"])), 3),
      "focal_px": cfg.focal, "baseline_m": cfg.baseline_m,
      "projector_width": 2 ** cfg.t, "projector_fov_deg": cfg.projector_fov_deg,
      "projector_translation_m": list(cfg.projector_translation_m),
      "projector_rotation_deg": list(cfg.projector_rotation_deg),
      "texture_amplitude": cfg.texture_amplitude, "specular": cfg.specular,
  }
  scene = SyntheticScene(
      name=f"{cfg.domain}_s{int(seed)}_{int(index):06d}",
      im0=np.asarray(out["im0"], np.float32), im1=np.asarray(out["im1"], np.float32),
      disp0=disp0, disp1=np.asarray(out["disp1"], np.float32),
      mask0=np.asarray(out["mask0"], bool), sl0=np.asarray(out["sl0"], np.float32),
      sl1=np.asarray(out["sl1"], np.float32),
      calib=calib_for(cfg, float(disp0.min()), float(disp0.max())), meta=meta,
      occ0=np.asarray(out["occ0"], bool), occ1=np.asarray(out["occ1"], bool),
      depth0=np.asarray(out["depth0"], np.float32), depth1=np.asarray(out["depth1"], np.float32),
      proj_col0=np.asarray(out["col0"], np.float32), proj_col1=np.asarray(out["col1"], np.float32))
  if raw:
    stack = np.asarray(out["raw"], np.float32)
    names = raw_keys(cfg.t)
    scene.raw0 = {k: stack[0, i] for i, k in enumerate(names)}
    scene.raw1 = {k: stack[1, i] for i, k in enumerate(names)}
  return scene


class SyntheticSource:
  """An endless-on-demand source of rendered scenes: len(), src[i] -> Scene, group(i)."""

  def __init__(self, n: int, seed: int = 0, config: SynthConfig = SynthConfig(),
               raw: bool = False):
    require(int(n) >= 1, f"a synthetic source needs n >= 1 scenes, got {n}")
    require(isinstance(config, SynthConfig),
            f"config must be a SynthConfig, got {type(config).__name__}")
    check_seed_index(seed, int(n) - 1)  # every scene's index, before any rendering
    self.n = int(n)
    self.seed = int(seed)
    self.config = config.resolved()
    self.raw = bool(raw)

  def __len__(self) -> int:
    return self.n

  def _index(self, i: int) -> int:
    i = int(i)
    if i < 0:
      i += self.n
    if not 0 <= i < self.n:
      raise IndexError(f"synthetic scene index {i} out of range 0..{self.n - 1}")
    return i

  def __getitem__(self, i: int) -> SyntheticScene:
    return render_scene(self._index(i), self.seed, self.config, self.raw)

  def group(self, i: int) -> str:
    """Group id of scene i without rendering it."""
    g = self._index(i) // self.config.views_per_object
    return f"{self.config.domain}-s{self.seed}-g{g:05d}"

  def name(self, i: int) -> str:
    """Scene name of scene i."""
    return f"{self.config.domain}_s{self.seed}_{self._index(i):06d}"

  @property
  def code(self) -> str:
    """Structured-light code of the patterns."""
    return self.config.code

  @property
  def num_patterns(self) -> int:
    """Number of patterns t."""
    return self.config.t
