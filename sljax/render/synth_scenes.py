"""Random scene descriptions for the synthetic renderer (inside jit): the shapes, viewpoints and
textures of the objects and tissue domains, as small arrays drawn from PRNG keys.

`sample_objects` and `sample_tissue` take the shape key (shared by a group's views), the view
key and the renderer's `SynthConfig`, and return the description `sljax.render.synthetic` renders.
"""

import math
from typing import Any

import jax
import jax.numpy as jnp

from sljax.render.synth_config import SynthConfig


def _unit_rows(v: jax.Array) -> jax.Array:
  """Rows scaled to unit length (small parameter arrays)."""
  return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


def _rotation(key: jax.Array, n: int) -> jax.Array:
  """n uniformly random rotation matrices (columns = rotated axes)."""
  q = _unit_rows(jax.random.normal(key, (n, 4)))
  w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
  return jnp.stack([
      jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
      jnp.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
      jnp.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)


def axis_rotation(axis: int, angle: jax.Array) -> jax.Array:
  """Rotation by angle (radians) about a coordinate axis (right-handed)."""
  c, s = jnp.cos(angle), jnp.sin(angle)
  i, j = [(1, 2), (2, 0), (0, 1)][axis]
  m = jnp.eye(3)
  return m.at[i, i].set(c).at[j, j].set(c).at[i, j].set(-s).at[j, i].set(s)


def _support(centres, rots, axes, v):
  """Support function of each ellipsoid in direction v: max over the ellipsoid of p . v."""
  return centres @ v + jnp.linalg.norm(axes * jnp.einsum("kji,j->ki", rots, v), axis=-1)


def _waves(key, n: int, wavelength_lo: float, wavelength_hi: float):
  """Random 3D plane waves (wave vectors, phases) for smooth solid textures."""
  k1, k2, k3 = jax.random.split(key, 3)
  direction = _unit_rows(jax.random.normal(k1, (n, 3)))
  lam = jax.random.uniform(k2, (n,), minval=wavelength_lo, maxval=wavelength_hi)
  return direction * (2 * jnp.pi / lam)[:, None], jax.random.uniform(k3, (n,)) * 2 * jnp.pi


def solid_texture(p, waves):
  """Smooth zero-mean texture in about [-1, 1] at points p (3, N)."""
  k, phase = waves
  total = 0.0
  for j in range(k.shape[0]):  # written out: tiny reductions do not fuse on CPU
    total = total + jnp.sin(p[0] * k[j, 0] + p[1] * k[j, 1] + p[2] * k[j, 2] + phase[j])
  return total * (1.0 / math.sqrt(k.shape[0]))


def sample_objects(key_shape, key_view, cfg: SynthConfig) -> dict[str, Any]:
  """Podium, object (union of ellipsoids) and a viewpoint looking at the object's centre."""
  ks = jax.random.split(key_shape, 8)
  n = cfg.num_ellipsoids
  size = jax.random.uniform(ks[0], (), minval=cfg.object_size_m[0], maxval=cfg.object_size_m[1])
  s = 0.5 * size
  body = jnp.concatenate([jnp.ones(1), jax.random.uniform(ks[1], (2,), minval=0.55, maxval=0.9)])
  sat = jax.random.uniform(ks[2], (n - 1, 3), minval=0.22, maxval=0.55)
  axes = s * jnp.concatenate([body[None], sat], 0)
  rots = _rotation(ks[3], n)
  frames = rots / axes[:, None, :]  # (p - c) @ frames[k] lies in the unit ball
  u = _unit_rows(jax.random.normal(ks[4], (n - 1, 3)))
  r_body = 1.0 / jnp.linalg.norm(u @ frames[0], axis=-1)  # body surface along u
  depth = jax.random.uniform(ks[5], (n - 1,), minval=0.55, maxval=0.95)
  centres = jnp.concatenate([jnp.zeros((1, 3)), u * (r_body * depth)[:, None]], 0)
  # Rest on the podium: the lowest point sinks 2 mm into its top.
  low = -_support(centres, rots, axes, jnp.array([0.0, 0.0, -1.0])).max()
  centres = centres + jnp.array([0.0, 0.0, 1.0]) * (cfg.podium_height_m - 0.002 - low)
  hi = jnp.stack([_support(centres, rots, axes, e).max() for e in jnp.eye(3)])
  lo = jnp.stack([-_support(centres, rots, axes, -e).max() for e in jnp.eye(3)])
  aim = 0.5 * (lo + hi)
  r_obj = jnp.max(jnp.linalg.norm(centres - aim, axis=-1) + axes.max(-1))
  podium_r = jnp.clip(jax.random.uniform(ks[6], (), minval=0.5, maxval=0.9) * s, 0.012, 0.05)
  tex_scale = size * jax.random.uniform(ks[7], (), minval=0.5, maxval=1.2)

  kv = jax.random.split(key_view, 4)
  f, b = cfg.focal, cfg.baseline_m
  azimuth = jax.random.uniform(kv[0], (), maxval=2 * jnp.pi)
  elevation = jnp.deg2rad(jax.random.uniform(kv[1], (), minval=10.0, maxval=45.0))
  rho = jax.random.uniform(kv[2], (), minval=0.22, maxval=0.38) * cfg.size
  dist = jnp.maximum(f * s / rho, r_obj + f * b / (cfg.max_disparity_fraction * cfg.size))
  return dict(
      frames=frames, centres=centres, podium_r=podium_r, aim=aim, dist=dist,
      azimuth=azimuth, elevation=elevation, size=size,
      waves_obj=_waves(jax.random.fold_in(key_shape, 100), 4, tex_scale, 2.5 * tex_scale),
      waves_room=_waves(jax.random.fold_in(key_shape, 101), 4, 0.2, 0.6),
      waves_vessel=_waves(jax.random.fold_in(key_shape, 102), 3, 0.01, 0.02))


def sample_tissue(key_shape, key_view, cfg: SynthConfig) -> dict[str, Any]:
  """Overlapping flattened lobes on a table and a viewpoint from above."""
  ks = jax.random.split(key_shape, 8)
  n = cfg.num_ellipsoids
  f, b = cfg.focal, cfg.baseline_m
  kv = jax.random.split(key_view, 4)
  # The cluster is sized for a nominal 9.5 cm view; per-view distances vary around it.
  half = 0.095 * (cfg.size / 2) / f
  spread = jax.random.uniform(ks[0], (), minval=0.7, maxval=1.0) * half
  radius = spread * 0.6 * jnp.sqrt(jax.random.uniform(ks[1], (n,)))
  angle = jax.random.uniform(ks[2], (n,), maxval=2 * jnp.pi)
  axes_xy = spread * jax.random.uniform(ks[3], (n, 2), minval=0.35, maxval=0.6)
  axes_z = axes_xy.min(-1) * jax.random.uniform(ks[4], (n,), minval=0.3, maxval=0.6)
  axes = jnp.concatenate([axes_xy, axes_z[:, None]], -1)
  yaw = jax.random.uniform(ks[5], (n,), maxval=2 * jnp.pi)
  tilt = jnp.deg2rad(jax.random.uniform(ks[6], (n, 2), minval=-15.0, maxval=15.0))
  rots = jax.vmap(lambda a, bx, by: axis_rotation(2, a) @ axis_rotation(0, bx)
                  @ axis_rotation(1, by))(yaw, tilt[:, 0], tilt[:, 1])
  sink = jax.random.uniform(ks[7], (n,), minval=0.1, maxval=0.4) * axes_z
  centres = jnp.stack([radius * jnp.cos(angle), radius * jnp.sin(angle), -sink], -1)
  frames = rots / axes[:, None, :]
  top = _support(centres, rots, axes, jnp.array([0.0, 0.0, 1.0])).max()
  dist = jax.random.uniform(kv[0], (), minval=0.075, maxval=0.115)
  dist = jnp.maximum(dist, top + f * b / (cfg.max_disparity_fraction * cfg.size))
  aim = jnp.concatenate([jax.random.uniform(kv[1], (2,), minval=-0.2, maxval=0.2) * spread,
                         jnp.zeros(1)])
  return dict(
      frames=frames, centres=centres, podium_r=jnp.zeros(()), aim=aim, dist=dist,
      azimuth=jax.random.uniform(kv[2], (), maxval=2 * jnp.pi),
      elevation=jnp.deg2rad(jax.random.uniform(kv[3], (), minval=55.0, maxval=85.0)),
      size=2 * spread,
      waves_obj=_waves(jax.random.fold_in(key_shape, 100), 4, 0.02, 0.05),
      waves_room=_waves(jax.random.fold_in(key_shape, 101), 4, 0.05, 0.15),
      waves_vessel=_waves(jax.random.fold_in(key_shape, 102), 3, 0.012, 0.03))
