"""Depth and point clouds with fx != fy and doffs != 0: geometry, sljax predict's PLY, SCARED.

Every other test uses a square-pixel calibration (fx = fy) and SCARED imports always have
doffs = 0, so Y divided by fx instead of fy, or doffs dropped, passed them all. Expected
values here come from the pinhole formulas in float64 loops.
"""

import cv2
import numpy as np
import pytest

from sljax import cli
from sljax.capture import scared
from sljax.data.camera import Calib, write_calib
from sljax.data.pfm import read_pfm
from sljax.depth import geometry
from sljax.errors import SljaxError
from sljax.io.images import write_image

H, W = 24, 40
FX, FY, CX, CY, BASELINE, DOFFS = 80.0, 97.0, 18.5, 13.0, 120.0, 3.5


def _calib(width=W, height=H, fx=FX, fy=FY, doffs=DOFFS, cx=CX, cy=CY):
  cam0 = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
  cam1 = cam0 + np.array([[0, 0, doffs], [0, 0, 0], [0, 0, 0]])
  return Calib(cam0=cam0, cam1=cam1, doffs=doffs, baseline=BASELINE, width=width,
               height=height, ndisp=32)


def _points_loop(disp, max_depth=None):
  """Row-major points of known pixels: Z = fx B / (d + doffs), X = (x - cx) Z / fx, Y = (y - cy) Z / fy."""
  pts = []
  for y in range(disp.shape[0]):
    for x in range(disp.shape[1]):
      d = float(disp[y, x])
      if not np.isfinite(d) or d + DOFFS <= 0:
        continue
      z = FX * BASELINE / (d + DOFFS)
      if max_depth is None or z <= max_depth:
        pts.append(((x - CX) * z / FX, (y - CY) * z / FY, z))
  return np.array(pts, np.float64).reshape(-1, 3)


def _read_ply_xyz(path):
  data = path.read_bytes()
  end = data.index(b"end_header\n") + len(b"end_header\n")
  n = int(next(l for l in data[:end].decode().splitlines() if l.startswith("element vertex"))
          .split()[2])
  rec = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("c", "u1", 3)])
  v = np.frombuffer(data, rec, count=n, offset=end)
  return np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)


def test_point_cloud_with_non_square_pixels_and_doffs():
  rng = np.random.default_rng(3)
  disp = rng.uniform(0.5, 20.0, (H, W)).astype(np.float32)
  disp[2, 3] = -DOFFS  # at infinity: no point
  disp[4, :5] = 0.2  # far: beyond max_depth
  xyz, _ = geometry.point_cloud(disp, _calib(), None, max_depth=2500.0)
  want = _points_loop(disp, 2500.0)
  assert len(xyz) == len(want) == H * W - 6
  np.testing.assert_allclose(xyz, want, rtol=1e-6, atol=1e-4)
  # Depth uses doffs and fx only (the disparity is horizontal).
  z = geometry.depth_mm(disp, _calib())
  np.testing.assert_allclose(z[5:], FX * BASELINE / (disp[5:].astype(np.float64) + DOFFS),
                             rtol=1e-6)


def test_predict_ply_uses_fy_for_y(tmp_path):
  """sljax predict writes the cloud of its own disparity with the scene's fx, fy and doffs."""
  rng = np.random.default_rng(4)
  h, w, shift = 32, 64, 5
  tex = cv2.GaussianBlur(rng.uniform(0, 1, (h, w + shift)).astype(np.float32), (3, 3), 0.8)
  tex = (tex - tex.min()) / (tex.max() - tex.min())
  scene = tmp_path / "s"
  scene.mkdir()
  write_image(scene / "im0.png", np.stack([tex[:, :w]] * 3, -1))
  write_image(scene / "im1.png", np.stack([tex[:, shift:]] * 3, -1))
  write_calib(scene / "calib.txt", _calib(w, h))
  out = tmp_path / "out"
  assert cli.main(["predict", "sgbm", str(scene / "im0.png"), str(scene / "im1.png"),
                   "--out", str(out), "--num-disparities", "16"]) == 0
  disp = read_pfm(out / "disparity.pfm")
  want = _points_loop(disp)
  got = _read_ply_xyz(out / "cloud.ply")
  assert len(got) == len(want) > h * w // 2
  np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-4)


def test_scared_projection_into_the_rectified_view_uses_fy():
  """rectified_disparity puts each 3D point at (fx X / Z + cx, fy Y / Z + cy)."""
  rng = np.random.default_rng(5)
  z = rng.uniform(40.0, 90.0, (H, W))
  v, u = np.mgrid[0:H, 0:W].astype(np.float64)
  xyz = np.stack([(u - CX) * z / FX, (v - CY) * z / FY, z], -1).astype(np.float32)
  p1 = np.array([[FX, 0, CX, 0], [0, FY, CY, 0], [0, 0, 1, 0]])
  disp = scared.rectified_disparity(xyz, np.eye(3), p1, BASELINE, (H, W))
  np.testing.assert_allclose(disp, FX * BASELINE / xyz[..., 2].astype(np.float64), rtol=1e-5)


def _rot_x(a):
  c, s = np.cos(a), np.sin(a)
  return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def test_scared_original_frame_depth_with_fx_fy_and_doffs():
  """Original pixel -> ray (M1) -> rotated by R1 -> rectified pixel via cam0 (fx, fy); the
  disparity there (affine, so bilinear reads it exactly) gives Z_rect = fx B / (d + doffs),
  and the original depth is the z of R1^T (Z_rect * ray_rect), all in float64 here."""
  cx, cy = 31.5, 23.5
  calib = _calib(64, 48, cx=cx, cy=cy)
  m1 = np.array([[76.0, 0, 30.0], [0, 88.0, 25.5], [0, 0, 1]])
  r1 = _rot_x(0.06) @ np.array([[np.cos(0.05), 0, np.sin(0.05)], [0, 1, 0],
                                [-np.sin(0.05), 0, np.cos(0.05)]])
  h, w = 48, 64
  original = {"M1": m1, "D1": np.zeros((1, 5)), "R1": r1, "size": (h, w)}
  v, u = np.mgrid[0:h, 0:w].astype(np.float64)
  disp = (6.0 + 0.05 * u + 0.08 * v).astype(np.float32)
  got = scared.original_frame_depth(disp, calib, original).astype(np.float64)

  want = np.full((h, w), np.nan)
  for y in range(h):
    for x in range(w):
      ray = r1 @ np.linalg.solve(m1, [x, y, 1.0])
      ray = ray / ray[2]
      xr, yr = FX * ray[0] + cx, FY * ray[1] + cy
      if 0 <= xr <= w - 1 and 0 <= yr <= h - 1:
        z_rect = FX * BASELINE / (6.0 + 0.05 * xr + 0.08 * yr + DOFFS)
        want[y, x] = (r1.T @ (z_rect * ray))[2]
  inside = np.isfinite(want) & np.isfinite(got)
  assert inside.mean() > 0.6
  # cv2.remap samples at 1/32 pixel: |d error| <= 0.08 / 64 px.
  np.testing.assert_allclose(got[inside], want[inside], rtol=2e-4)


@pytest.mark.parametrize("fy", [FX, FY])
def test_point_cloud_y_scales_as_one_over_fy(fy):
  """Same disparity, fy doubled: X and Z unchanged, Y halved (a direct check of the axis)."""
  disp = np.full((H, W), 10.0, np.float32)
  a, _ = geometry.point_cloud(disp, _calib(fy=fy))
  b, _ = geometry.point_cloud(disp, _calib(fy=2 * fy))
  np.testing.assert_allclose(b[:, [0, 2]], a[:, [0, 2]], rtol=1e-7)
  np.testing.assert_allclose(2 * b[:, 1], a[:, 1], rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("baseline", [0.0, -120.0, float("nan")])
def test_calibration_without_a_positive_baseline_is_refused(baseline):
  calib = _calib()
  bad = Calib(cam0=calib.cam0, cam1=calib.cam1, doffs=DOFFS, baseline=baseline, width=W,
              height=H, ndisp=32)
  with pytest.raises(SljaxError, match="positive focal length and baseline"):
    geometry.check_calib_size(bad, (H, W), "calib.txt")
  geometry.check_calib_size(calib, (H, W), "calib.txt")  # the good one passes


def test_point_cloud_colours_from_gray_and_out_of_range_images():
  """An HxW gray image is repeated into r = g = b; values within rounding (0.01) of [0, 1] are
  clipped, a float image in 0..255 is refused (clipped, it used to be a white cloud)."""
  disp = np.full((2, 3), 10.0, np.float32)
  calib = _calib(3, 2)
  gray = np.array([[0.0, 0.5, 1.0], [1.004, -0.003, 0.25]], np.float32)
  _, rgb = geometry.point_cloud(disp, calib, gray)
  want = np.array([0, 128, 255, 255, 0, 64], np.uint8)
  np.testing.assert_array_equal(rgb, np.stack([want] * 3, 1))
  _, rgb3 = geometry.point_cloud(disp, calib, np.stack([gray, gray * 0, gray], -1))
  np.testing.assert_array_equal(rgb3[:, 1], 0)
  np.testing.assert_array_equal(rgb3[:, 0], want)
  with pytest.raises(SljaxError, match=r"point cloud: image must be scaled to \[0, 1\]"):
    geometry.point_cloud(disp, calib, gray * 255)


@pytest.mark.parametrize("focal", [0.0, -80.0, float("nan")])
def test_calibration_without_a_positive_focal_length_is_refused(focal):
  cam0 = np.array([[focal, 0, CX], [0, FY, CY], [0, 0, 1]])
  bad = Calib(cam0=cam0, cam1=cam0, doffs=DOFFS, baseline=BASELINE, width=W, height=H,
              ndisp=32)
  with pytest.raises(SljaxError, match="positive focal length and baseline"):
    geometry.check_calib_size(bad, (H, W), "calib.txt")


def test_point_cloud_colours_without_an_image_and_from_one_channel():
  disp = np.full((2, 3), 10.0, np.float32)
  calib = _calib(3, 2)
  _, rgb = geometry.point_cloud(disp, calib)
  np.testing.assert_array_equal(rgb, np.full((6, 3), 128, np.uint8))  # mid grey
  one = np.array([[[0.0], [1.0], [0.2]], [[0.4], [0.6], [0.8]]], np.float32)
  _, rgb = geometry.point_cloud(disp, calib, one)
  np.testing.assert_array_equal(rgb, np.repeat(np.rint(one.reshape(6, 1) * 255), 3, 1))
  with pytest.raises(SljaxError, match=r"image \(4, 3\) and disparity \(2, 3\) differ"):
    geometry.point_cloud(disp, calib, np.zeros((4, 3, 3), np.float32))
