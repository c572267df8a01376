"""What a first hit looks like, for the synthetic renderer (inside jit): the camera pose, the
surface normal of each facet, whether a segment is blocked (shadows, occlusion), and the
textures and albedo of the objects and tissue domains. `sljax.render.synthetic` calls these from
its rendering stages.
"""

import math

import jax.numpy as jnp

from sljax.render import synth_geometry as geo
from sljax.render import synth_scenes as scenes

from sljax.render.synth_config import SynthConfig

def camera(desc, cfg: SynthConfig):
  """Left camera centre and rotation (columns: x right, y down, z forward in world axes)."""
  el, az = desc["elevation"], desc["azimuth"]
  offset = jnp.stack([jnp.cos(el) * jnp.cos(az), jnp.cos(el) * jnp.sin(az), jnp.sin(el)])
  centre = desc["aim"] + desc["dist"] * offset
  z = -offset
  x = jnp.stack(geo.normalize(jnp.cross(z, jnp.array([0.0, 0.0, 1.0]))))
  y = jnp.cross(z, x)
  return centre, jnp.stack([x, y, z], axis=1)


# Facet ids of first hits: room walls by exit axis, podium side and top, then ellipsoid k.
POD_SIDE, POD_TOP, ELL = 3, 4, 5


def normal(p, d, facet, desc):
  """Outward normals (unit except on ellipsoids, where M_k p - m_k) at first hits p."""
  room = geo.box_normal(facet, d)
  pod = geo.podium_normal(p, facet == POD_TOP, desc["podium_r"], d)
  ell = geo.ellipsoid_normal(p, jnp.maximum(facet - ELL, 0), desc["frames"], desc["centres"])
  return tuple(jnp.where(facet >= ELL, e, jnp.where(facet >= POD_SIDE, q, r))
               for r, q, e in zip(room, pod, ell))


def blocked(origin, p, desc, cfg: SynthConfig, eps: float = 1e-4):
  """Whether the open segments origin -> p cross an object or the podium (room cannot)."""
  v = tuple(pi - oi for pi, oi in zip(p, origin))
  frames, centres = desc["frames"], desc["centres"]
  v_local = geo.to_frames(v, frames)
  # One origin (projector) or one per view: (K, 1 or V, 1, 1) components.
  o_local = geo.local_components(
      geo.origins_local(jnp.stack(origin, -1).reshape(-1, 3), frames, centres), 2)
  hit = geo.any_leading(geo.segments_enter_sphere(o_local, v_local, eps))
  if cfg.domain == "objects":
    t_pod, _ = geo.ray_podium(origin, v, desc["podium_r"], cfg.podium_height_m, t_min=eps)
    hit = hit | (t_pod < 1.0 - eps)
  return hit


def textures(p, facet, desc, cfg: SynthConfig):
  """Albedo inputs at points p: objects (grey,); tissue (mottle texture, vessel field)."""
  # One texture per point: the object's waves on the object, the room's elsewhere (same values
  # as evaluating both and selecting, half the sines).
  on_obj = facet >= ELL
  k_obj, ph_obj = desc["waves_obj"]
  k_room, ph_room = desc["waves_room"]
  total = 0.0
  for j in range(k_obj.shape[0]):
    arg = sum(p[i] * jnp.where(on_obj, k_obj[j, i], k_room[j, i]) for i in range(3))
    total = total + jnp.sin(arg + jnp.where(on_obj, ph_obj[j], ph_room[j]))
  tex = total * (1.0 / math.sqrt(k_obj.shape[0]))
  amp = cfg.texture_amplitude
  if cfg.domain == "objects":
    base = jnp.where(on_obj, 0.6, jnp.where(facet >= POD_SIDE, 0.7, 0.5))
    return (base * (1.0 + amp * tex),)
  vessel = jnp.exp(-(scenes.solid_texture(p, desc["waves_vessel"]) / 0.08) ** 2)
  return (tex, vessel)


def albedo(facet, tex, cfg: SynthConfig):
  """RGB albedo (component tuple) from the texture values of `textures`."""
  if cfg.domain == "objects":
    return tex * 3  # (grey,) -> (grey, grey, grey)
  # Tissue: reddish, mottled, with dark vessel lines along the zero sets of a smooth field.
  tex, vessel = tex
  amp = cfg.texture_amplitude
  on_obj = facet >= ELL
  mottle = 1.0 + 0.12 * amp * tex
  dark = min(max(0.55 * amp, 0.0), 1.0) * vessel
  tissue = [base * mottle * (1.0 - dark * v)
            for base, v in zip((0.75, 0.33, 0.28), (0.4, 0.8, 0.7))]
  table = [base * (1.0 + 0.1 * tex) for base in (0.22, 0.36, 0.38)]
  return tuple(jnp.where(on_obj, a, b) for a, b in zip(tissue, table))
