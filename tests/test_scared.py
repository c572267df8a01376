import struct

import cv2
import numpy as np
import pytest

from sljax import cli
from sljax.capture.scared import import_scared
from sljax.data.camera import read_calib
from sljax.data.pfm import read_pfm
from sljax.data.scene import load_scene
from sljax.errors import SljaxError

H, W = 60, 80
M1 = np.array([[70.0, 0, 41.0], [0, 71.0, 29.0], [0, 0, 1]])
M2 = np.array([[72.0, 0, 38.5], [0, 72.5, 31.0], [0, 0, 1]])
R = cv2.Rodrigues(np.array([0.01, -0.03, 0.015]))[0]
T = np.array([-4.5, 0.15, 0.1])  # mm; right camera to the right, as in SCARED
# The plane n . X = c in the left camera frame (mm): slanted, about 60 mm away.
N_PLANE = np.array([0.15, -0.1, 1.0])
C_PLANE = 60.0
STRIP = (30, 36)  # original left columns with unknown depth (z == 0 and NaN)


def _write_float_tiff(path, a):
  """Minimal little-endian baseline TIFF of HxWx3 float32, channels stored in the given order."""
  a = np.ascontiguousarray(a, dtype="<f4")
  h, w, c = a.shape
  data = a.tobytes()
  ifd_off = 8 + len(data)
  extra = ifd_off + 2 + 11 * 12 + 4

  def entry(tag, typ, count, value):
    return struct.pack("<HHI", tag, typ, count) + value

  short = lambda v: struct.pack("<HH", v, 0)
  long = lambda v: struct.pack("<I", v)
  ifd = [entry(256, 4, 1, long(w)), entry(257, 4, 1, long(h)), entry(258, 3, 3, long(extra)),
         entry(259, 3, 1, short(1)), entry(262, 3, 1, short(2)), entry(273, 4, 1, long(8)),
         entry(277, 3, 1, short(c)), entry(278, 4, 1, long(h)), entry(279, 4, 1, long(len(data))),
         entry(284, 3, 1, short(1)), entry(339, 3, 3, long(extra + 6))]
  path.write_bytes(b"II*\x00" + long(ifd_off) + data + struct.pack("<H", 11) + b"".join(ifd)
                   + bytes(4) + struct.pack("<3H", 32, 32, 32) + struct.pack("<3H", 3, 3, 3))


def _matrix_yaml(name, m):
  m = np.atleast_2d(m)
  values = ", ".join(repr(float(v)) for v in m.ravel())
  return (f"{name}: !!opencv-matrix\n   rows: {m.shape[0]}\n   cols: {m.shape[1]}\n   dt: d\n"
          f"   data: [ {values} ]\n")


def _undistort(xd, yd, dist):
  """Ideal normalised coordinates whose Brown-Conrady distortion (k1 k2 p1 p2 k3) gives
  (xd, yd): a fixed-point iteration, converged to float64 precision for mild distortion."""
  k1, k2, p1, p2, k3 = dist
  x, y = xd.copy(), yd.copy()
  for _ in range(100):
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    x = (xd - (2 * p1 * x * y + p2 * (r2 + 2 * x * x))) / radial
    y = (yd - (p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)) / radial
  r2 = x * x + y * y
  radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
  resid = np.hypot(x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd,
                   y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - yd)
  assert resid.max() < 1e-12
  return np.stack([x, y], -1)


def _plane_points(k, dist=None, rays_in_left=np.eye(3), origin=np.zeros(3)):
  """Intersections of the pixel rays of intrinsics k and lens distortion dist (camera pose
  given in the left frame)."""
  u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
  rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(k).T
  if dist is not None:
    rays[..., :2] = _undistort(rays[..., 0], rays[..., 1], dist)
  rays = rays @ rays_in_left.T
  s = (C_PLANE - origin @ N_PLANE) / (rays @ N_PLANE)
  return origin + s[..., None] * rays


def _texture(p):
  """Smooth texture on the plane (a function of the 3D point)."""
  return 0.5 + 0.25 * np.sin(p[..., 0] * 0.9) + 0.2 * np.cos(p[..., 1] * 0.7 + p[..., 0] * 0.3)


# Barrel distortion of a wide endoscope lens (k1, k2, p1, p2, k3), or none.
DISTORTION = {"pinhole": (np.zeros(5), np.zeros(5)),
              "distorted": (np.array([-0.12, 0.03, 0.001, -0.0015, 0.0]),
                            np.array([-0.09, 0.02, -0.001, 0.001, 0.0]))}


@pytest.fixture(scope="module", params=list(DISTORTION))
def keyframe(tmp_path_factory, request):
  d1, d2 = DISTORTION[request.param]
  kf = tmp_path_factory.mktemp("scared") / "dataset_3" / "keyframe_2"
  kf.mkdir(parents=True)
  xyz = _plane_points(M1, d1)
  cv2.imwrite(str(kf / "Left_Image.png"), np.round(_texture(xyz) * 255).astype(np.uint8))
  # Right camera: X_right = R X_left + T, so in the left frame its centre is -R^T T and its
  # axes are the rows of R.
  right = _plane_points(M2, d2, rays_in_left=R.T, origin=-R.T @ T)
  gray = np.round(_texture(right) * 255).astype(np.uint8)
  cv2.imwrite(str(kf / "Right_Image.png"), np.stack([gray] * 3, -1))
  unknown = xyz.copy()
  unknown[:, STRIP[0]:STRIP[1] // 2 + 17, 2] = 0.0
  unknown[:, STRIP[1] // 2 + 17:STRIP[1]] = np.nan
  _write_float_tiff(kf / "left_depth_map.tiff", unknown.astype(np.float32))
  yaml = "%YAML:1.0\n---\n" + "".join(
      _matrix_yaml(n, m) for n, m in [("M1", M1), ("D1", d1), ("M2", M2), ("D2", d2),
                                      ("R", R), ("T", T[:, None])])
  (kf / "endoscope_calibration.yaml").write_text(yaml)
  out = kf.parent / "scene"
  import_scared(kf, out)
  return kf, out, xyz


def test_calib_consistent(keyframe):
  _, out, _ = keyframe
  c = read_calib(out / "calib.txt")
  assert (c.width, c.height) == (W, H)
  np.testing.assert_allclose(c.baseline, np.linalg.norm(T), rtol=1e-6)
  assert c.doffs == 0 and c.cam0[0, 2] == c.cam1[0, 2] and c.cam0[1, 2] == c.cam1[1, 2]
  assert c.cam0[0, 0] == c.cam1[0, 0] == c.cam0[1, 1]
  d = read_pfm(out / "disp0.pfm")
  assert c.vmin <= np.min(d[np.isfinite(d)]) and np.max(d[np.isfinite(d)]) <= c.vmax <= c.ndisp
  s = load_scene(out)
  assert s.meta["group"] == "dataset_3/keyframe_2"
  assert s.im0.shape == (H, W, 3)  # gray left, colour right: both become colour


def test_disparity_matches_plane(keyframe):
  _, out, _ = keyframe
  c = read_calib(out / "calib.txt")
  d = read_pfm(out / "disp0.pfm")
  f, cx, cy, b = c.focal, c.cam0[0, 2], c.cam0[1, 2], c.baseline
  # Reference: the rectified view is the left camera rotated by R1; intersect each rectified
  # pixel ray with the plane (float64).
  r1 = cv2.stereoRectify(M1, np.zeros(5), M2, np.zeros(5), (W, H), R, T[:, None],
                         flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)[0]
  u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
  rays = np.stack([(u - cx) / f, (v - cy) / f, np.ones_like(u)], -1)  # rectified frame
  n_rect = r1 @ N_PLANE
  z = C_PLANE / (rays @ n_rect)
  expected = f * b / z
  known = np.isfinite(d)
  assert known.mean() > 0.8
  err = np.abs(d - expected)[known]
  # Nearest-pixel splatting moves a point by at most half a pixel: the disparity error is
  # half a pixel times the disparity gradient, a few hundredths of a pixel here.
  assert np.mean(err < 0.02) > 0.99 and err.max() < 0.05
  # Independent of R1: reconstructed points lie on a plane at distance c/|n| from the centre.
  zr = f * b / d[known]
  pts = np.stack([(u[known] - cx) * zr / f, (v[known] - cy) * zr / f, zr], -1)
  a = np.c_[pts, -np.ones(len(pts))]
  normal = np.linalg.svd(a, full_matrices=False)[2][-1]
  dist = abs(normal[3]) / np.linalg.norm(normal[:3])
  np.testing.assert_allclose(dist, C_PLANE / np.linalg.norm(N_PLANE), rtol=2e-3)


def test_unknown_depth_stays_unknown(keyframe):
  _, out, xyz = keyframe
  c = read_calib(out / "calib.txt")
  d = read_pfm(out / "disp0.pfm")
  r1 = cv2.stereoRectify(M1, np.zeros(5), M2, np.zeros(5), (W, H), R, T[:, None],
                         flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)[0]
  core = xyz[:, STRIP[0] + 1:STRIP[1] - 1].reshape(-1, 3) @ r1.T
  u = np.rint(c.focal * core[:, 0] / core[:, 2] + c.cam0[0, 2]).astype(int)
  v = np.rint(c.focal * core[:, 1] / core[:, 2] + c.cam0[1, 2]).astype(int)
  ok = (u >= 0) & (u < W) & (v >= 0) & (v < H)
  assert ok.sum() > 50 and np.all(np.isinf(d[v[ok], u[ok]]))


def test_rectified_views_agree_under_disparity(keyframe):
  _, out, _ = keyframe
  s = load_scene(out, gray=True)
  d = s.disp0
  yy, xx = np.nonzero(np.isfinite(d))
  xr = xx - d[yy, xx]
  inner = (xr > 2) & (xr < W - 3) & (yy > 2) & (yy < H - 3) & (xx > 2) & (xx < W - 3)
  yy, xx, xr = yy[inner], xx[inner], xr[inner]
  x0 = np.floor(xr).astype(int)
  a = xr - x0
  right = (1 - a) * s.im1[yy, x0, 0] + a * s.im1[yy, x0 + 1, 0]
  diff = np.abs(right - s.im0[yy, xx, 0])
  assert len(diff) > 1000 and np.median(diff) < 0.02


def test_refuses_overwrite_and_cli(keyframe, capsys):
  kf, out, _ = keyframe
  with pytest.raises(SljaxError, match="exists"):
    import_scared(kf, out)
  assert cli.main(["import-scared", str(kf), str(out), "--overwrite"]) == 0
  assert "baseline" in capsys.readouterr().out


def test_missing_file(keyframe, tmp_path, capsys):
  kf, _, _ = keyframe
  broken = tmp_path / "kf"
  broken.mkdir()
  for name in ("Left_Image.png", "Right_Image.png", "endoscope_calibration.yaml"):
    (broken / name).write_bytes((kf / name).read_bytes())
  with pytest.raises(SljaxError, match=r"kf.*left_depth_map\.tiff: missing"):
    import_scared(broken, tmp_path / "o")
  assert cli.main(["import-scared", str(broken), str(tmp_path / "o")]) == 2
  err = capsys.readouterr().err
  assert "left_depth_map.tiff" in err and len(err.strip().splitlines()) == 1
  (broken / "left_depth_map.tiff").write_bytes((kf / "left_depth_map.tiff").read_bytes())
  (broken / "endoscope_calibration.yaml").write_text(
      (kf / "endoscope_calibration.yaml").read_text().split("T: ")[0])
  with pytest.raises(SljaxError, match=r"endoscope_calibration\.yaml.*T"):
    import_scared(broken, tmp_path / "o")


def _exact_rectified_disparity(c):
  """The plane's disparity at every rectified pixel, by ray-plane intersection (float64)."""
  f, cx, cy, b = c.focal, c.cam0[0, 2], c.cam0[1, 2], c.baseline
  r1 = cv2.stereoRectify(M1, np.zeros(5), M2, np.zeros(5), (W, H), R, T[:, None],
                         flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)[0]
  u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
  rays = np.stack([(u - cx) / f, (v - cy) / f, np.ones_like(u)], -1)
  z = C_PLANE / (rays @ (r1 @ N_PLANE))
  return (f * b / z).astype(np.float32)


def test_original_frame_mapping_recovers_the_plane(keyframe):
  """A rectified disparity mapped back to the original, distorted left view gives the depth of
  the plane seen through each original pixel (the fixture's own ray-plane intersection)."""
  from sljax.capture import scared
  _, out, xyz = keyframe
  s = load_scene(out)
  original = scared.read_original(s.meta, str(out))
  depth = scared.original_frame_depth(_exact_rectified_disparity(s.calib), s.calib, original)
  known = np.isfinite(depth)
  assert known.mean() > 0.7  # alpha = 0 crops the rectified view: the border has no prediction
  np.testing.assert_allclose(depth[known], xyz[..., 2][known], rtol=2e-4)
  gt = read_pfm(out / scared.ORIGINAL_DEPTH)
  np.testing.assert_array_equal(np.isinf(gt[:, STRIP[0]:STRIP[1]]), True)
  np.testing.assert_allclose(gt[np.isfinite(gt)], xyz[..., 2][np.isfinite(gt)], rtol=1e-6)


def test_keyframe_error_follows_the_toolkit():
  from sljax.capture import scared
  gt = np.full((10, 10), np.inf, np.float32)
  gt[:3, :3] = 50.0  # 9% coverage: excluded
  r = scared.keyframe_error(gt, np.full((10, 10), 40.0))
  assert r["excluded"] and np.isnan(r["depth_mae_mm"]) and r["coverage"] == pytest.approx(0.09)
  gt[:4, :3] = 50.0  # 12%: scored over the pixels both maps know (0 = unknown, as the toolkit)
  pred = np.full((10, 10), 40.0)
  pred[0, 0], pred[0, 1] = np.nan, 0.0
  pred[1, 0] = 53.0
  r = scared.keyframe_error(gt, pred)
  assert not r["excluded"] and r["assessed"] == pytest.approx(0.10)
  assert r["depth_mae_mm"] == pytest.approx((9 * 10.0 + 3.0) / 10)


def test_evaluate_scores_keyframes_in_the_original_frame(keyframe, tmp_path):
  """sljax evaluate on an imported keyframe: a prediction 5% off in disparity is 1/1.05 off in
  depth everywhere, so the keyframe's MAE is (1 - 1/1.05) times the mean assessed depth."""
  from sljax.capture import scared
  from sljax.data.dataset import FolderSource
  from sljax.evaluation.scoring import evaluate
  _, out, _ = keyframe
  calib = load_scene(out).calib
  pred = _exact_rectified_disparity(calib) * np.float32(1.05)

  class Fixed:
    model_name, mode, is_sl = "fixed", "full", False

    def describe(self):
      return "fixed disparity"

    def __call__(self, left, right, calib=None):
      return {"disparity": pred}

  report = evaluate(Fixed(), FolderSource(out), out_dir=tmp_path / "eval", progress=False)
  row = report["per_scene"][0]["scared"]
  gt = read_pfm(out / scared.ORIGINAL_DEPTH)
  mapped = scared.original_frame_depth(pred, calib, scared.read_original(
      load_scene(out).meta, ""))
  both = np.isfinite(gt) & np.isfinite(mapped)
  assert row["assessed"] == pytest.approx(both.mean()) and not row["excluded"]
  np.testing.assert_allclose(row["depth_mae_mm"], (1 - 1 / 1.05) * gt[both].mean(), rtol=1e-3)
  pooled = report["pooled"]["scared"]
  assert pooled["keyframes"] == 1 and pooled["excluded"] == 0
  assert pooled["depth_mae_mm"] == row["depth_mae_mm"]
  md = (tmp_path / "eval" / "metrics.md").read_text()
  assert "SCARED (scared_toolkit rules, original frame)" in md
  assert "scared_depth_mae_mm" in (tmp_path / "eval" / "per_scene.csv").read_text()


def _with_matrix(yaml, name, m):
  """The calibration YAML with matrix `name` replaced by m."""
  start = yaml.index(f"{name}: !!opencv-matrix")
  end = yaml.index("\n", yaml.index("data:", start)) + 1
  return yaml[:start] + _matrix_yaml(name, m) + yaml[end:]


def _copy_keyframe(kf, tmp_path):
  broken = tmp_path / "kf"
  broken.mkdir()
  for p in kf.iterdir():
    (broken / p.name).write_bytes(p.read_bytes())
  return broken


@pytest.mark.parametrize("damage, why", [
    ("garbage", "not readable as an OpenCV FileStorage YAML with the matrices M1 D1 M2 D2 R T "
                "(damaged or half-written? OpenCV: "),  # was SystemError from cv2.FileStorage
    ("empty", "empty file (0 bytes); expected an OpenCV FileStorage YAML"),  # SystemError
    ("half", "lacks the matrices R T (absent, cut off"),  # cv2.error (-215) !dt.empty()
    ("scalar", "lacks the matrix M1 (absent, cut off or not an !!opencv-matrix"),  # cv2.error
    ("short_d1", "D1 has 3 values, expected 4, 5, 8, 12 or 14"),  # cv2.error in stereoRectify
    ("nan_t", "T holds NaN or infinite values"),  # cv2.error (-215) nt > 0.0
    ("zero_focal", "M2 has focal lengths fx = 0, fy = 0; both must be positive"),  # NaN calib.txt
    ("swapped", "T = [4.5, -0.15, -0.1] puts the right camera to the left of the left one"),
])  # swapped: was imported with positive disparities where the true ones are negative
def test_damaged_calibration_is_one_line_error(keyframe, tmp_path, capsys, damage, why):
  kf, _, _ = keyframe
  broken = _copy_keyframe(kf, tmp_path)
  yaml = broken / "endoscope_calibration.yaml"
  good = yaml.read_text()
  yaml.write_text({"garbage": "garbage {{{ : :\n", "empty": "",
                   "half": good[:good.index("dt:", good.index("R: "))],  # R cut off
                   "scalar": good.replace("M1: !!opencv-matrix", "M1: 3\nM0: !!opencv-matrix"),
                   "short_d1": _with_matrix(good, "D1", np.zeros((1, 3))),
                   "nan_t": _with_matrix(good, "T", np.array([[1.0], [0], [0]])).replace(
                       "data: [ 1.0", "data: [ .nan"),  # OpenCV's spelling of NaN
                   "zero_focal": _with_matrix(good, "M2", np.zeros((3, 3))),
                   "swapped": _with_matrix(good, "T", -T[:, None]),
                   }[damage])
  assert cli.main(["import-scared", str(broken), str(tmp_path / "o")]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and err[0].startswith(f"sljax import-scared: error: {yaml}: {why}"), err
  assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("damage, why", [
    # An 8-bit picture of the depth: was read as x, y, z of 0..255 mm, imported as ground truth.
    ("uint8", "expected a 3-channel float TIFF of x, y, z (mm), got 3 channel(s) of uint8"),
    # Points in metres: was imported with disparities 1000x too large.
    ("metres", "median depth z = 0.06"),
])
def test_depth_map_that_is_no_point_map_in_mm(keyframe, tmp_path, capsys, damage, why):
  kf, _, xyz = keyframe
  broken = _copy_keyframe(kf, tmp_path)
  tiff = broken / "left_depth_map.tiff"
  if damage == "uint8":
    assert cv2.imwrite(str(tiff), np.full((H, W, 3), 60, np.uint8))
  else:
    _write_float_tiff(tiff, (xyz / 1000.0).astype(np.float32))
  assert cli.main(["import-scared", str(broken), str(tmp_path / "o")]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and err[0].startswith(f"sljax import-scared: error: {tiff}: {why}"), err
  if damage == "metres":
    assert "more than the image width (80 px); x, y, z must be in mm (metres?)" in err[0]
  assert not (tmp_path / "o").exists()
