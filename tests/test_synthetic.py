import gc
import json
import math

import numpy as np
import pytest

from sljax import cli
from sljax.errors import SljaxError
from sljax.io import files
from sljax.render import synth_geometry as geo
from sljax.render import synth_sensor
from sljax.render import synthetic as synth
from sljax.render.synthetic import SynthConfig, SyntheticSource, render_scene
from sljax.sl import codes
from sljax.sl.decode import decode_captures
from sljax.sl.match import disparity_from_codes

# 64 px views with a 2^t-column projector whose finest stripes stay wider than a pixel.
OBJ = SynthConfig(size=64, t=6)
TIS = SynthConfig(size=64, domain="tissue", t=7, specular=0.0)
SEED = 3


@pytest.fixture(scope="module")
def objects():
  return [render_scene(i, SEED, OBJ, raw=True) for i in (0, 1, 10, 11)]


@pytest.fixture(scope="module")
def tissue():
  return [render_scene(i, SEED, TIS, raw=True) for i in (0, 7)]


@pytest.fixture(scope="module")
def scenes(objects, tissue):
  return objects + tissue


def _sample_right(img, x):
  """Linear interpolation of rows of img (H, W[, C]) at float columns x (H, W)."""
  w = img.shape[1]
  x0 = np.clip(np.floor(x).astype(int), 0, w - 1)
  x1 = np.clip(x0 + 1, 0, w - 1)
  a = x - np.floor(x)
  rows = np.arange(img.shape[0])[:, None]
  if img.ndim == 3:
    a = a[..., None]
  return (1 - a) * img[rows, x0] + a * img[rows, x1], x0, x1


def _both_sides_visible(s):
  """Left pixels whose correspondence lies between two right pixels on the same surface."""
  h, w = s.disp0.shape
  x = np.arange(w)[None, :] - s.disp0
  ok = (~s.occ0) & (x >= 0) & (x <= w - 1)
  xr = np.clip(x, 0, w - 1)
  x0 = np.floor(xr).astype(int)
  x1 = np.minimum(x0 + 1, w - 1)
  rows = np.arange(h)[:, None]
  for xi in (x0, x1):  # both neighbours see the same surface (no depth edge in between)
    ok &= np.abs(s.disp1[rows, xi] - s.disp0) < 0.5
  return ok, x, x0, x1


# ----------------------------------------------------------------------------------------------
# Geometry primitives against brute-force float64 sampling along the rays.


def _brute_first(inside, o, d, t_max=2.0, n=4001):
  """First t in (0, t_max] where inside(o + t d) holds (float64), inf if none."""
  ts = np.linspace(0, t_max, n)[1:]
  pts = o[:, None, :] + ts[None, :, None] * d[:, None, :]
  hit = inside(pts)
  first = np.where(hit.any(1), ts[np.argmax(hit, 1)], np.inf)
  return first, ts[1] - ts[0]


def test_primitives_match_brute_force():
  rng = np.random.default_rng(0)
  n = 200
  o = np.stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), rng.uniform(0.05, 0.3, n)],
               1)
  o[:, 0] += np.sign(o[:, 0]) * 0.05  # every origin outside the podium (radius 0.04)
  target = rng.normal(0, 0.05, (n, 3)) + np.array([0, 0, 0.12])
  d = target - o
  # Ellipsoids (two, random frames) against |(p - c) A| <= 1.
  frames = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] / rng.uniform(0.02, 0.06, 3)
                     for _ in range(2)]).astype(np.float32)
  centres = rng.normal(0, 0.02, (2, 3)).astype(np.float32) + np.float32([0, 0, 0.12])

  def inside_ell(p):
    return np.any([np.linalg.norm((p - c) @ a, axis=-1) <= 1 for a, c in zip(frames, centres)], 0)

  # Rays from one origin (the renderer's layout).
  o1 = np.broadcast_to(o[0], o.shape)
  d1 = target - o1
  want, step = _brute_first(inside_ell, o1, d1)
  e0, _ = geo.ellipsoid_roots(o[0].astype(np.float32), geo.to_frames(
      d1.T.astype(np.float32), frames), frames, centres)
  e0 = np.asarray(e0)
  got = np.min(np.where(e0 > 0, e0, np.inf), 0)
  assert np.mean(np.isfinite(got) != np.isfinite(want)) < 0.02  # grazing rays within one step
  both = np.isfinite(got) & np.isfinite(want)
  assert both.sum() > 50
  assert np.all(got[both] <= want[both] + 1e-6) and np.all(want[both] - got[both] <= step + 1e-6)
  # Segment test agrees with the brute force on whether [0, 1) enters an ellipsoid.
  seg = np.asarray(geo.segments_hit_ellipsoids(
      o[0].astype(np.float32), geo.to_frames((d + o - o[0]).T.astype(np.float32), frames), frames, centres, 1e-4))
  want_seg, _ = _brute_first(inside_ell, np.broadcast_to(o[0], o.shape), d + o - o[0], 1.0)
  assert np.mean(seg == np.isfinite(want_seg)) > 0.98
  # Podium (cylinder radius 0.04, height 0.1).
  t_pod, normal = geo.ray_podium(o.T.astype(np.float32), d.T.astype(np.float32), 0.04, 0.1)
  want_pod, step = _brute_first(
      lambda p: (np.hypot(p[..., 0], p[..., 1]) <= 0.04) & (p[..., 2] >= 0) & (p[..., 2] <= 0.1),
      o, d)
  t_pod = np.asarray(t_pod)
  fin = np.isfinite(want_pod)
  assert fin.sum() > 20 and np.mean(np.isfinite(t_pod) == fin) > 0.98
  both = fin & np.isfinite(t_pod)
  assert np.all(t_pod[both] <= want_pod[both] + 1e-6)
  assert np.mean(want_pod[both] - t_pod[both] <= step + 1e-6) > 0.98


def test_normals_match_numeric_gradients():
  rng = np.random.default_rng(1)
  frames = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] / rng.uniform(0.02, 0.06, 3)
                     for _ in range(3)]).astype(np.float32)
  centres = rng.normal(0, 0.02, (3, 3)).astype(np.float32)
  k = rng.integers(0, 3, 50)
  p = (centres[k] + rng.normal(0, 0.03, (50, 3))).astype(np.float32)
  got = np.stack(geo.ellipsoid_normal(p.T, k, frames, centres), -1)

  def g(q):  # |(q - c) A|^2 in float64
    return np.sum(np.einsum("ni,nij->nj", q - centres[k], frames[k].astype(np.float64)) ** 2, -1)

  h = 1e-6
  num = np.stack([(g(p + h * e) - g(p - h * e)) / (2 * h) for e in np.eye(3)], -1)
  unit = lambda v: v / np.linalg.norm(v, axis=-1, keepdims=True)  # noqa: E731
  np.testing.assert_allclose(unit(got), unit(num), atol=1e-4)
  # Box: the inward normal of the exit wall; podium: radial side, top facing the ray.
  d = np.float32([[0.3, -0.9, 0.1], [-0.2, 0.1, 0.05], [0.1, 0.2, -1.0]]).T
  t, axis = geo.ray_box_exit(np.zeros((3, 1), np.float32), d, (-0.5, -0.5, 0.0), (0.5, 0.5, 1.0))
  np.testing.assert_array_equal(np.asarray(axis), [1, 0, 2])
  np.testing.assert_allclose(np.asarray(t), [0.5 / 0.9, 2.5, 0.0], atol=1e-6)
  n = np.stack(geo.box_normal(axis, d), -1)
  np.testing.assert_array_equal(n, [[0, 1, 0], [1, 0, 0], [0, 0, 1]])
  p_side = np.float32([[0.03, 0.04, 0.05]]).T
  n_side = np.stack(geo.podium_normal(p_side, np.array([False]), 0.05, d[:, :1]), -1)
  np.testing.assert_allclose(n_side, [[0.6, 0.8, 0.0]], atol=1e-6)
  n_top = np.stack(geo.podium_normal(p_side, np.array([True]), 0.05, d[:, 2:]), -1)
  np.testing.assert_allclose(n_top, [[0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------------------------
# Determinism and sources.


def test_same_seed_same_scene_different_seed_different(objects):
  again = render_scene(1, SEED, OBJ, raw=True)
  ref = objects[1]
  for name in ("im0", "im1", "disp0", "disp1", "sl0", "sl1", "mask0", "occ0"):
    np.testing.assert_array_equal(getattr(again, name), getattr(ref, name))
  for k in ref.raw0:
    np.testing.assert_array_equal(again.raw0[k], ref.raw0[k])
  src = SyntheticSource(20, SEED, OBJ, raw=True)
  np.testing.assert_array_equal(src[10].im0, objects[2].im0)  # independent of access order
  assert src.group(0) == src.group(1) == objects[0].group != src.group(10) == objects[2].group
  other = render_scene(1, SEED + 1, OBJ, raw=True)
  assert not np.allclose(other.disp0, ref.disp0)
  assert ref.meta["group"] == objects[0].meta["group"] and ref.meta["code"] == "binary"
  json.dumps(ref.meta)  # meta is JSON-serialisable


# ----------------------------------------------------------------------------------------------
# Physical consistency.


def test_disparity_matches_depth_and_range(scenes):
  for s in scenes:
    f, b = s.calib.focal, s.calib.baseline / 1000.0
    np.testing.assert_allclose(s.disp0, f * b / s.depth0, rtol=1e-5)
    np.testing.assert_allclose(s.disp1, f * b / s.depth1, rtol=1e-5)
    d = s.disp0[np.isfinite(s.disp0)]
    w = s.shape[1]
    assert d.size == s.disp0.size  # the room closes every scene
    assert np.mean((d >= 1) & (d <= w / 4)) >= 0.99, (s.name, d.min(), d.max())


def test_photometric_consistency(scenes):
  for s in scenes:
    ok, x, _, _ = _both_sides_visible(s)
    assert ok.mean() > 0.3
    warped, _, _ = _sample_right(s.im1, np.clip(x, 0, s.shape[1] - 1))
    mae = np.abs(warped - s.im0)[ok].mean()
    noise = SynthConfig().image_noise
    assert mae <= 1 / 255 + 2 * noise, (s.name, mae)


def test_pattern_consistency(scenes):
  for s in scenes:
    ok, _, x0, x1 = _both_sides_visible(s)
    rows = np.arange(s.shape[0])[:, None]
    a, b = s.sl1[rows, x0], s.sl1[rows, x1]
    known = ok[..., None] & np.isfinite(s.sl0) & np.isfinite(a) & np.isfinite(b)
    # The right view's pattern at x - d lies between its two neighbouring pixels' values.
    agree = (s.sl0 == a) | (s.sl0 == b)
    assert known.sum() > 1000
    assert agree[known].mean() >= 0.99, (s.name, agree[known].mean())


def test_code_matching_recovers_disparity(scenes):
  for s in scenes:
    code = s.meta["code"]
    cols = []
    for sl in (s.sl0, s.sl1):
      full = np.all(np.isfinite(sl), -1)
      c = codes.decode(np.nan_to_num(sl).astype(np.uint8), code).astype(np.float32)
      cols.append(np.where(full, c, np.nan))
    d0, _ = disparity_from_codes(cols[0], cols[1])
    both = np.isfinite(d0) & np.isfinite(s.disp0)
    assert both.sum() > 0.2 * s.disp0.size, (s.name, both.mean())
    err = np.abs(d0 - s.disp0)[both]
    assert np.mean(err <= 1.0) >= 0.95, (s.name, np.mean(err <= 1.0))


def test_raw_captures_decode_to_ground_truth(scenes):
  for s in scenes:
    for raw, sl in ((s.raw0, s.sl0), (s.raw1, s.sl1)):
      # 8-bit quantisation as on disk.
      raw8 = {k: np.round(v * 255) / 255 for k, v in raw.items()}
      dec = decode_captures(raw8, s.meta["code"])
      known = np.isfinite(sl)
      assert known.mean() > 0.3
      assert np.mean(dec.bits[known] == sl[known]) >= 0.99, s.name


def test_images_textured_and_coverage(scenes):
  for s in scenes:
    for im in (s.im0, s.im1):
      assert im.shape == s.shape + (3,) and 0 <= im.min() and im.max() <= 1
      assert im.std() > 0.03 and np.abs(np.diff(im, axis=1)).mean() > 1e-3
    assert 0.1 <= s.mask0.mean() <= 0.9, (s.name, s.mask0.mean())
    assert np.isnan(s.sl0).any() and np.isfinite(s.sl0).mean() > 0.3
    assert set(np.unique(s.sl0[np.isfinite(s.sl0)])) <= {0.0, 1.0}


def test_tissue_is_reddish(tissue):
  for s in tissue:
    rgb = s.im0[s.mask0].mean(0)
    assert rgb[0] > 1.5 * rgb[1] and rgb[0] > 1.5 * rgb[2]
    assert s.meta["code"] == "gray" and s.sl0.shape[-1] == 7


# ----------------------------------------------------------------------------------------------
# Command line.


def test_make_data_and_show(tmp_path, objects, capsys):
  out = tmp_path / "ds"
  args = ["make-data", str(out), "--n", "2", "--seed", str(SEED), "--size", "64",
          "--patterns", "6", "--raw"]
  assert cli.main(args) == 0
  info = json.loads((out / "dataset.json").read_text())
  assert info["code"] == "binary" and info["patterns"] == 6
  scene_dir = out / objects[0].name
  for f in ("im0.png", "im1.png", "disp0.pfm", "disp1.pfm", "mask0.png", "calib.txt", "meta.json",
            "sl0/000.png", "sl1/005.png", "raw0/white.png", "raw1/i005.png"):
    assert (scene_dir / f).exists(), f
  from sljax.data.dataset import FolderSource
  src = FolderSource(out)
  assert len(src) == 2 and src.group(0) == src.group(1) == objects[0].group
  back = src[0]
  np.testing.assert_allclose(back.disp0, objects[0].disp0)
  np.testing.assert_array_equal(np.isnan(back.sl0), np.isnan(objects[0].sl0))
  assert np.abs(back.im0 - objects[0].im0).max() <= 0.5 / 255 + 1e-6
  capsys.readouterr()
  assert cli.main(args) == 2  # refuses a non-empty folder
  assert "not empty" in capsys.readouterr().err
  assert cli.main(args + ["--overwrite"]) == 0
  png = tmp_path / "sheet.png"
  assert cli.main(["show", str(out), "--out", str(png), "--index", "1"]) == 0
  assert png.stat().st_size > 10000
  png2 = tmp_path / "scene.png"
  assert cli.main(["show", str(scene_dir), "--out", str(png2)]) == 0 and png2.exists()
  assert cli.main(["show", str(out), "--out", str(png), "--index", "5", "--overwrite"]) == 2
  assert "out of range" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------
# Sensor noise and raw-capture formation against NumPy references.


def _hash32_np(x):
  x = x.astype(np.uint64)
  x ^= x >> 16
  x = (x * 0x21F0AAAD) & 0xFFFFFFFF
  x ^= x >> 15
  x = (x * 0x735A2D97) & 0xFFFFFFFF
  return x ^ (x >> 15)


def test_noise_is_counter_hash_and_nearly_gaussian():
  import jax
  from math import erf, sqrt
  key = jax.random.PRNGKey(5)
  shape = (2, 3, 64, 64)
  z = np.asarray(synth_sensor.noise(key, shape))
  np.testing.assert_array_equal(z, np.asarray(synth_sensor.noise(key, shape)))  # deterministic
  # NumPy reference of the documented construction: hash(hash(i ^ k0) ^ k1), sum of its bytes.
  k0, k1 = (int(v) for v in np.asarray(jax.random.bits(key, (2,), np.uint32)))
  x = _hash32_np(_hash32_np(np.arange(z.size, dtype=np.uint64) ^ k0) ^ k1)
  total = sum((x >> s) & 255 for s in (0, 8, 16, 24)).astype(np.float64)
  want = (total - 510.0) / sqrt(4 * (256 ** 2 - 1) / 12)
  np.testing.assert_allclose(z.ravel(), want, atol=1e-5)
  assert abs(z.mean()) < 0.02 and abs(z.std() - 1) < 0.02 and np.abs(z).max() < 3.5
  flat = z.ravel()
  assert abs(np.corrcoef(flat[:-1], flat[1:])[0, 1]) < 0.02  # neighbours independent
  # Close to a standard normal: Kolmogorov-Smirnov distance against its CDF.
  s = np.sort(flat)
  cdf = 0.5 * (1 + np.vectorize(erf)(s / sqrt(2)))
  assert np.max(np.abs(cdf - np.arange(1, s.size + 1) / s.size)) < 0.015
  other = np.asarray(synth_sensor.noise(jax.random.PRNGKey(6), shape))
  assert abs(np.corrcoef(flat, other.ravel())[0, 1]) < 0.02


def _blur_np(img, sigma):
  """Naive separable Gaussian blur with edge replication (float64), radius ceil(3 sigma)."""
  r = max(1, int(np.ceil(3 * sigma)))
  w = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
  w /= w.sum()
  out = img.astype(np.float64)
  for axis in (-1, -2):
    pad = [(0, 0)] * out.ndim
    pad[axis] = (r, r)
    x = np.pad(out, pad, mode="edge")
    n = out.shape[axis]
    out = sum(w[i] * np.take(x, np.arange(i, i + n), axis=axis) for i in range(2 * r + 1))
  return out


def test_raw_captures_match_direct_formation():
  cfg = SynthConfig(size=24, t=5, raw_noise=0.0, raw_blur=0.7).resolved()
  rng = np.random.default_rng(2)
  col = rng.uniform(0, 32, (2, 24, 24)).astype(np.float32)
  col[rng.random(col.shape) < 0.2] = np.nan
  grey = rng.uniform(0.1, 0.9, col.shape).astype(np.float32)
  irr = np.where(np.isnan(col), 0, rng.uniform(0, 0.7, col.shape)).astype(np.float32)
  import jax
  rig = {"key_noise": jax.random.PRNGKey(0)}
  got = np.asarray(synth._stage_raw(rig, *synth._stage_raw_rows(col, grey, irr, cfg), cfg))
  # Direct formation of every capture, then blur each one.
  bits = codes.encode(np.nan_to_num(col).astype(int), "binary", 5).astype(np.float64)
  black = grey * cfg.raw_ambient
  white = black + grey * irr
  caps = [white, black] + [black + grey * irr * bits[..., k] for k in range(5)] + [
      black + grey * irr * (1 - bits[..., k]) for k in range(5)]
  want = np.clip(_blur_np(np.stack(caps, 1), cfg.raw_blur), 0, 1)
  assert got.shape == (2, 12, 24, 24)
  np.testing.assert_allclose(got, want, atol=1e-5)


def test_projector_pose_defaults_match_the_paper(objects):
  """proj_col0 is the column of a pinhole projector at [0.02, 0, 0.02] m in left-camera axes,
  rotated 1.5 deg about y (SPEC 6), recomputed here from depth0 in float64."""
  assert SynthConfig().projector_translation_m == (0.02, 0.0, 0.02)
  assert SynthConfig().projector_rotation_deg == (0.0, 1.5, 0.0)
  cfg = OBJ.resolved()
  for s in objects:
    h, w = s.depth0.shape
    c = (w - 1) / 2
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    z = s.depth0.astype(np.float64)
    pts = np.stack([(xs - c) * z / cfg.focal, (ys - c) * z / cfg.focal, z], -1)
    a = np.radians(1.5)
    rot_y = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    q = (pts - np.array([0.02, 0.0, 0.02])) @ rot_y  # rot_y^T (p - t), row vectors
    width_p = 2 ** cfg.t
    f_p = (width_p / 2) / math.tan(math.radians(cfg.projector_fov_deg) / 2)
    col = f_p * q[..., 0] / q[..., 2] + width_p / 2
    lit = np.isfinite(s.proj_col0)
    assert lit.mean() > 0.3
    np.testing.assert_allclose(s.proj_col0[lit], col[lit], atol=2e-3 * width_p)


def test_a_command_keeps_the_renderers_programs_and_the_next_one_loads_them(tmp_path,
                                                                            monkeypatch):
  """Where a command line keeps compiled programs, the renderer's stages are kept whole: a
  later process loads them (no tracing) and renders the same scenes bit for bit."""
  from sljax.render import synthetic
  from sljax.runtime import kept_programs
  cfg = SynthConfig(size=32, t=4, baseline_m=0.051)  # a configuration of this test's own
  plain = render_scene(3, SEED, cfg, raw=True)
  monkeypatch.setenv(kept_programs.ENV, "on")
  kept_programs.enable(tmp_path / "xla")
  try:
    synthetic._stage.cache_clear()
    kept = render_scene(3, SEED, cfg, raw=True)
    entries = sorted(p.name for p in (tmp_path / "xla").glob("sljax-program-render-*-cache"))
    assert len(entries) == 8, entries  # every stage, the raw captures' two included
    synthetic._stage.cache_clear()  # as a new process: programs found on disk
    loaded = render_scene(3, SEED, cfg, raw=True)
    assert {synthetic._stage(f, cfg.resolved()).origin for f in (
        synthetic._rig, synthetic._stage_surface, synthetic._stage_raw)} == {"loaded"}
  finally:
    kept_programs.enable(None)
    synthetic._stage.cache_clear()
  for scene in (kept, loaded):
    for k in ("im0", "im1", "disp0", "sl0", "depth0", "occ0"):
      np.testing.assert_array_equal(getattr(scene, k), getattr(plain, k), err_msg=k)
    assert scene.raw0.keys() == plain.raw0.keys()
    for k in plain.raw0:
      np.testing.assert_array_equal(scene.raw0[k], plain.raw0[k], err_msg=k)


@pytest.mark.parametrize("error", [SljaxError("scene 2: render failed"), KeyboardInterrupt()])
def test_make_data_is_all_or_nothing(tmp_path, capsys, monkeypatch, error):
  """A failure (or Ctrl-C) at the last scene: OUT stays absent, or with --overwrite keeps its
  earlier scenes byte for byte; a finished --overwrite with fewer patterns drops stale planes."""
  import toys  # pylint: disable=import-outside-toplevel
  from sljax.commands import make_data  # pylint: disable=import-outside-toplevel
  out = tmp_path / "ds"
  args = ["make-data", str(out), "--n", "3", "--size", "32", "--patterns", "5", "--raw"]

  def failing(i, *a, **k):
    if i == 2:
      gc.collect()  # not inside jax's gc callback, which would report a Ctrl-C as ignored
      raise error
    return render_scene(i, *a, **k)

  monkeypatch.setattr(make_data, "render_scene", failing)
  assert cli.main(args) in (2, 130)
  assert not out.exists()
  monkeypatch.setattr(make_data, "render_scene", render_scene)
  assert cli.main(args[:-3] + ["--patterns", "6", "--raw"]) == 0
  before = toys.tree(out)
  monkeypatch.setattr(make_data, "render_scene", failing)
  assert cli.main(args + ["--overwrite"]) in (2, 130)
  assert toys.tree(out) == before
  monkeypatch.setattr(make_data, "render_scene", render_scene)
  assert cli.main(args + ["--overwrite"]) == 0
  scene = sorted(p for p in out.iterdir() if p.is_dir())[0]
  assert sorted(p.name for p in (scene / "sl0").iterdir())[-1] == "004.png"
  assert not (scene / "raw0" / "p005.png").exists() and not any(
      files.is_temporary(p) for p in out.rglob("*"))
  capsys.readouterr()
