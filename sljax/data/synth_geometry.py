"""Exact ray casting for the synthetic renderer: closed-form intersections only.

Vectors are stored component-major, shape (3, N) (or (3,) for one point): on CPU a minor axis of
size 3, and reductions over it, defeat fusion and vectorisation (10-100x slower). Rays are o, d
(d need not be unit length); every intersection returns the ray parameter t of the first hit
(inf when none), so a hit point is o + t * d. Scenes are built
from a room (box), a podium (cylinder) and unions of ellipsoids, all intersected in closed form,
so depth, normals, shadows and occlusions are exact up to float32 rounding.
"""

import jax
import jax.numpy as jnp

Array = jax.Array
INF = jnp.inf


def dot(a: Array, b: Array) -> Array:
  """Dot product over the leading (component) axis, written out."""
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def normalize(v: Array) -> Array:
  """Unit vectors along the leading (component) axis."""
  return v * jax.lax.rsqrt(jnp.maximum(dot(v, v), 1e-30))


def matvec(m: Array, v: Array) -> Array:
  """m @ v for a 3x3 m and component-major vectors v (3, N)."""
  return jnp.stack([m[i, 0] * v[0] + m[i, 1] * v[1] + m[i, 2] * v[2] for i in range(3)])


def first_hit(ts: Array) -> tuple[Array, Array]:
  """(min, argmin) over the leading axis of a small stack (K, N), written out."""
  best, index = ts[0], jnp.zeros(ts.shape[1:], jnp.int32)
  for k in range(1, ts.shape[0]):
    closer = ts[k] < best
    best = jnp.where(closer, ts[k], best)
    index = jnp.where(closer, k, index)
  return best, index


def select(index: Array, options: list[Array]) -> Array:
  """options[index] per element (options broadcastable against index)."""
  out = options[-1]
  for k in range(len(options) - 2, -1, -1):
    out = jnp.where(index == k, options[k], out)
  return out


def ray_box_exit(o: Array, d: Array, lo: tuple, hi: tuple) -> tuple[Array, Array]:
  """Exit parameter and inward normal of rays starting inside the axis-aligned box [lo, hi]."""
  t_axis = []
  for i in range(3):
    safe = jnp.where(jnp.abs(d[i]) < 1e-12, 1e-12, d[i])
    t_axis.append(jnp.where(safe > 0, (hi[i] - o[i]) / safe, (lo[i] - o[i]) / safe))
  t, axis = first_hit(jnp.stack(t_axis))  # the wall each ray leaves through
  sign = -jnp.sign(select(axis, [d[0], d[1], d[2]]))
  normal = jnp.stack([jnp.where(axis == i, sign, 0.0) for i in range(3)])
  return t, normal


def ray_podium(o: Array, d: Array, radius: Array, height: float, t_min: float = 0.0
               ) -> tuple[Array, Array]:
  """First hit after t_min with the vertical cylinder x^2 + y^2 <= r^2, 0 <= z <= height.

  Returns (t, outward normal); the floor disc is not part of it (it stands on the floor).
  """
  a = d[0] * d[0] + d[1] * d[1]
  b = o[0] * d[0] + o[1] * d[1]
  c = o[0] * o[0] + o[1] * o[1] - radius * radius
  disc = b * b - a * c
  s = jnp.sqrt(jnp.maximum(disc, 0.0))
  a_safe = jnp.where(a < 1e-20, 1e-20, a)
  cands = []
  for root in ((-b - s) / a_safe, (-b + s) / a_safe):
    z = o[2] + root * d[2]
    ok = (disc > 0) & (a > 1e-20) & (root > t_min) & (z >= 0) & (z <= height)
    cands.append(jnp.where(ok, root, INF))
  dz = jnp.where(jnp.abs(d[2]) < 1e-20, 1e-20, d[2])
  t_top = (height - o[2]) / dz
  px, py = o[0] + t_top * d[0], o[1] + t_top * d[1]
  on_top = (t_top > t_min) & (px * px + py * py <= radius * radius)
  cands.append(jnp.where(on_top, t_top, INF))
  t, k = first_hit(jnp.stack(cands))
  side = k < 2
  tt = jnp.where(jnp.isfinite(t), t, 0.0)
  # The side's normal is radial; the top disc faces up (a ray from below sees its underside).
  normal = jnp.stack([jnp.where(side, (o[0] + tt * d[0]) / radius, 0.0),
                      jnp.where(side, (o[1] + tt * d[1]) / radius, 0.0),
                      jnp.where(side, 0.0, jnp.sign(-dz))])
  return t, normal


def to_frames(v: Array, frames: Array) -> tuple[Array, Array, Array]:
  """Components of frames[k]^T v for all k: (3, N), (K, 3, 3) -> three (K, N) arrays."""
  return tuple(frames[:, 0, i, None] * v[0][None] + frames[:, 1, i, None] * v[1][None]
               + frames[:, 2, i, None] * v[2][None] for i in range(3))


def _origin_local(origin: Array, frames: Array, centres: Array) -> Array:
  """(origin - centres[k]) @ frames[k] for all k: (K, 3) (tiny)."""
  return jnp.einsum("kj,kji->ki", origin[None] - centres, frames)


def ellipsoid_roots(origin: Array, d_local: tuple, frames: Array, centres: Array
                    ) -> tuple[Array, Array]:
  """Both ray parameters (t0 <= t1) of rays from one origin through K ellipsoids; inf if missed.

  Ellipsoid k is {p : |(p - centres[k]) @ frames[k]| <= 1}; d_local = to_frames(d, frames) is
  shared by every origin that uses the same directions. Returns (K, N) arrays.
  """
  o_local = _origin_local(origin, frames, centres)
  x, y, z = d_local
  a = x * x + y * y + z * z
  b = x * o_local[:, 0, None] + y * o_local[:, 1, None] + z * o_local[:, 2, None]
  c = jnp.sum(o_local * o_local, -1)[:, None] - 1.0
  disc = b * b - a * c
  hit = disc > 0
  s = jnp.sqrt(jnp.where(hit, disc, 0.0))
  # Stable roots: q = -b - sign(b) s never cancels; the other root from t0 t1 = c / a.
  q = -b - jnp.where(b >= 0, s, -s)
  q = jnp.where(jnp.abs(q) < 1e-30, 1e-30, q)
  r0 = q / a
  r1 = c / q
  return (jnp.where(hit, jnp.minimum(r0, r1), INF), jnp.where(hit, jnp.maximum(r0, r1), -INF))


def segments_hit_ellipsoids(origin: Array, v_local: tuple, frames: Array, centres: Array,
                            eps: float) -> Array:
  """Whether segments origin + t v, t in (eps, 1 - eps), enter any ellipsoid (origin outside).

  v_local = to_frames(v, frames). With g(t) = |o + t v|^2 - 1 in ellipsoid coordinates
  (g(0) > 0), the segment meets the ellipsoid iff g(1 - eps) < 0 or g's minimum lies inside the
  segment and is negative: no square root or division needed. Returns (N,) bool.
  """
  o_local = _origin_local(origin, frames, centres)
  x, y, z = v_local
  a = x * x + y * y + z * z
  b = x * o_local[:, 0, None] + y * o_local[:, 1, None] + z * o_local[:, 2, None]
  c = jnp.sum(o_local * o_local, -1)[:, None] - 1.0
  e = 1.0 - eps
  end_inside = (a * e + 2.0 * b) * e + c < 0
  vertex_inside = (-b > eps * a) & (-b < e * a) & (b * b > a * c)
  hit = end_inside | vertex_inside
  out = hit[0]
  for k in range(1, hit.shape[0]):
    out = out | hit[k]
  return out


def ellipsoid_normal(p: Array, k: Array, frames: Array, centres: Array) -> Array:
  """Outward unit normal at points p (3, N) on ellipsoids k (N,): grad |(p - c) A|^2."""
  n = frames.shape[0]
  # Per-pixel coefficients by selection: gathers from a tiny table are slow on CPU.
  a = [[select(k, [frames[m, j, i] for m in range(n)]) for i in range(3)] for j in range(3)]
  v = [p[j] - select(k, [centres[m, j] for m in range(n)]) for j in range(3)]
  local = [v[0] * a[0][i] + v[1] * a[1][i] + v[2] * a[2][i] for i in range(3)]
  grad = [local[0] * a[j][0] + local[1] * a[j][1] + local[2] * a[j][2] for j in range(3)]
  return normalize(jnp.stack(grad))
