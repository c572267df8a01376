"""Exact ray casting for the synthetic renderer: closed-form intersections only.

Vectors are component tuples (x, y, z) of arrays (a (3, ...) array works too wherever a vector is
only read): on CPU a minor axis of size 3, stacks of components and reductions over them defeat
fusion and vectorisation, while separate component arrays fuse into plain elementwise loops.
Components broadcast, so one direction field (H, W) serves several origins (V, 1, 1). Rays are
o, d (d need not be unit length); every intersection returns the ray parameter t of the first hit
(inf when none), so a hit point is o + t * d. Scenes are built from a room (box), a podium
(cylinder) and unions of ellipsoids, all intersected in closed form, so depth, normals, shadows
and occlusions are exact up to float32 rounding.
"""

from collections.abc import Sequence

import jax
import jax.numpy as jnp

Array = jax.Array
Vec = Sequence[Array]
INF = jnp.inf


def dot(a: Vec, b: Vec) -> Array:
  """Dot product of component vectors, written out."""
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def normalize(v: Vec) -> tuple[Array, Array, Array]:
  """Unit vectors (component tuple)."""
  s = jax.lax.rsqrt(jnp.maximum(dot(v, v), 1e-30))
  return v[0] * s, v[1] * s, v[2] * s


def matvec(m: Array, v: Vec) -> tuple[Array, Array, Array]:
  """m @ v for a 3x3 m and component vectors v."""
  return tuple(m[i, 0] * v[0] + m[i, 1] * v[1] + m[i, 2] * v[2] for i in range(3))


def first_hit(ts: Sequence[Array]) -> tuple[Array, Array]:
  """(min, argmin) over the leading axis of a small stack (K, ...) or a list, written out."""
  best, index = ts[0], jnp.zeros(jnp.shape(ts[0]), jnp.int32)
  for k in range(1, len(ts)):
    closer = ts[k] < best
    best = jnp.where(closer, ts[k], best)
    index = jnp.where(closer, k, index)
  return best, index


def select(index: Array, options: Sequence) -> Array:
  """options[index] per element (options broadcastable against index)."""
  out = options[-1]
  for k in range(len(options) - 2, -1, -1):
    out = jnp.where(index == k, options[k], out)
  return out


def ray_box_exit(o: Vec, d: Vec, lo: tuple, hi: tuple) -> tuple[Array, Array]:
  """Exit parameter and exit axis (0, 1, 2) of rays starting inside the box [lo, hi]."""
  t_axis = []
  for i in range(3):
    safe = jnp.where(jnp.abs(d[i]) < 1e-12, 1e-12, d[i])
    t_axis.append(jnp.where(safe > 0, (hi[i] - o[i]) / safe, (lo[i] - o[i]) / safe))
  return first_hit(t_axis)  # the wall each ray leaves through


def box_normal(axis: Array, d: Vec) -> tuple[Array, Array, Array]:
  """Inward normal of the wall a ray with direction d leaves the box through (exit axis)."""
  return tuple(jnp.where(axis == i, -jnp.sign(d[i]), 0.0) for i in range(3))


def ray_podium(o: Vec, d: Vec, radius: Array, height: float, t_min: float = 0.0
               ) -> tuple[Array, Array]:
  """First hit after t_min with the vertical cylinder x^2 + y^2 <= r^2, 0 <= z <= height.

  Returns (t, whether the hit is on the top disc); the floor disc is not part of it (it stands
  on the floor).
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
  t, k = first_hit(cands)
  return t, k == 2


def podium_normal(p: Vec, top: Array, radius: Array, d: Vec) -> tuple[Array, Array, Array]:
  """Outward normal at podium hits p: radial on the side; the top disc faces the ray."""
  # A ray from below sees the top disc's underside.
  return (jnp.where(top, 0.0, p[0] / radius), jnp.where(top, 0.0, p[1] / radius),
          jnp.where(top, -jnp.sign(d[2]), 0.0))


def to_frames(v: Vec, frames: Array) -> tuple[Array, Array, Array]:
  """Components of frames[k]^T v for all k: (K, 3, 3) and (...) components -> (K, ...) each."""
  shape = (frames.shape[0],) + (1,) * jnp.ndim(v[0])
  f = lambda j, i: frames[:, j, i].reshape(shape)  # noqa: E731
  return tuple(f(0, i) * v[0] + f(1, i) * v[1] + f(2, i) * v[2] for i in range(3))


def origins_local(origins: Array, frames: Array, centres: Array) -> Array:
  """(origins[v] - centres[k]) @ frames[k]: (V, 3) or (3,) origins -> (K, V, 3) or (K, 3)."""
  if origins.ndim == 1:
    return origins_local(origins[None], frames, centres)[:, 0]
  return jnp.einsum("kvj,kji->kvi", origins[None] - centres[:, None], frames)


def local_components(o_local: Array, ndim: int) -> tuple[Array, Array, Array]:
  """Components of (K, [V,] 3) local origins shaped to broadcast against (K, ...) arrays."""
  return tuple(o_local[..., i].reshape(o_local.shape[:-1] + (1,) * ndim) for i in range(3))


def unit_sphere_roots(o: Vec, d: Vec) -> tuple[Array, Array]:
  """Both parameters (t0 <= t1) of rays o + t d through the unit sphere; (inf, -inf) if missed."""
  a = dot(d, d)
  b = dot(d, o)
  c = dot(o, o) - 1.0
  disc = b * b - a * c
  hit = disc > 0
  s = jnp.sqrt(jnp.where(hit, disc, 0.0))
  # Stable roots: q = -b - sign(b) s never cancels; the other root from t0 t1 = c / a.
  q = -b - jnp.where(b >= 0, s, -s)
  q = jnp.where(jnp.abs(q) < 1e-30, 1e-30, q)
  r0 = q / a
  r1 = c / q
  return jnp.where(hit, jnp.minimum(r0, r1), INF), jnp.where(hit, jnp.maximum(r0, r1), -INF)


def ellipsoid_roots(origin: Array, d_local: Vec, frames: Array, centres: Array
                    ) -> tuple[Array, Array]:
  """Both ray parameters (t0 <= t1) of rays from one origin through K ellipsoids; inf if missed.

  Ellipsoid k is {p : |(p - centres[k]) @ frames[k]| <= 1}; d_local = to_frames(d, frames) is
  shared by every origin that uses the same directions. Returns (K, N) arrays.
  """
  o = local_components(origins_local(origin, frames, centres), 1)
  return unit_sphere_roots(o, d_local)


def segments_enter_sphere(o: Vec, v: Vec, eps: float) -> Array:
  """Whether segments o + t v, t in (eps, 1 - eps), enter the unit sphere (o outside).

  With g(t) = |o + t v|^2 - 1 (g(0) > 0), the segment meets the sphere iff g(1 - eps) < 0 or
  g's minimum lies inside the segment and is negative: no square root or division needed.
  """
  a = dot(v, v)
  b = dot(v, o)
  c = dot(o, o) - 1.0
  e = 1.0 - eps
  end_inside = (a * e + 2.0 * b) * e + c < 0
  vertex_inside = (-b > eps * a) & (-b < e * a) & (b * b > a * c)
  return end_inside | vertex_inside


def any_leading(hit: Array) -> Array:
  """Logical or over the leading axis, written out."""
  out = hit[0]
  for k in range(1, hit.shape[0]):
    out = out | hit[k]
  return out


def segments_hit_ellipsoids(origin: Array, v_local: Vec, frames: Array, centres: Array,
                            eps: float) -> Array:
  """Whether segments origin + t v, t in (eps, 1 - eps), enter any ellipsoid (origin outside).

  v_local = to_frames(v, frames), (K, N) components. Returns (N,) bool.
  """
  o = local_components(origins_local(origin, frames, centres), 1)
  return any_leading(segments_enter_sphere(o, v_local, eps))


def ellipsoid_gradients(frames: Array, centres: Array) -> tuple[Array, Array]:
  """(M, m) with M_k = F_k F_k^T, m_k = M_k c_k: grad |(p - c_k) F_k|^2 / 2 = M_k p - m_k."""
  m = jnp.einsum("kij,klj->kil", frames, frames)
  return m, jnp.einsum("kij,kj->ki", m, centres)


def ellipsoid_normal(p: Vec, k: Array, frames: Array, centres: Array
                     ) -> tuple[Array, Array, Array]:
  """Outward (unnormalised) normal at points p on ellipsoids k: M_k p - m_k."""
  mat, off = ellipsoid_gradients(frames, centres)
  n = frames.shape[0]
  # Per-pixel coefficients by selection: gathers from a tiny table are slow on CPU.
  row = lambda i: [select(k, [mat[q, i, j] for q in range(n)]) for j in range(3)]  # noqa: E731
  return tuple(dot(row(i), p) - select(k, [off[q, i] for q in range(n)]) for i in range(3))
