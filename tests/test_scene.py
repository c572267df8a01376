import errno
import json
import os
import re
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from sljax.data.camera import Calib
from sljax.data.scene import UNKNOWN_PATTERN, Scene, load_scene, present_parts, write_scene
from sljax.errors import SljaxError
from sljax.io.images import read_image

H, W = 6, 8
CALIB_TXT = """cam0=[100 0 4; 0 100 3; 0 0 1]
cam1=[100 0 5; 0 100 3; 0 0 1]
doffs=1
baseline=50
width=8
height=6
ndisp=16
isint=0
vmin=1
vmax=9
dyavg=0.1
dymax=0.2
"""


def _pfm_bytes(a):
  """Little-endian Pf file built from the format description."""
  h, w = a.shape
  body = b"".join(struct.pack("<f", float(a[y, x])) for y in range(h - 1, -1, -1) for x in range(w))
  return f"Pf\n{w} {h}\n-1\n".encode() + body


@pytest.fixture
def middlebury(tmp_path):
  """A Middlebury 2014 shaped folder written with OpenCV and hand-made PFM bytes."""
  rng = np.random.default_rng(0)
  d = tmp_path / "Toy-perfect"
  d.mkdir()
  bgr0 = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
  bgr1 = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
  cv2.imwrite(str(d / "im0.png"), bgr0)
  cv2.imwrite(str(d / "im1.png"), bgr1)
  disp = rng.uniform(1, 9, (H, W)).astype(np.float32)
  disp[0, 0] = np.inf
  (d / "disp0.pfm").write_bytes(_pfm_bytes(disp))
  (d / "calib.txt").write_text(CALIB_TXT)
  return d, bgr0, bgr1, disp


def test_loads_middlebury_folder_unchanged(middlebury):
  d, bgr0, bgr1, disp = middlebury
  s = load_scene(d)
  assert s.name == "Toy-perfect" and s.shape == (H, W)
  assert s.im0.dtype == np.float32 and s.im0.shape == (H, W, 3)
  # RGB order, scaled by 1/255, computed independently of the loader.
  np.testing.assert_allclose(s.im0, bgr0[..., ::-1] / 255.0, atol=1e-7)
  np.testing.assert_allclose(s.im1, bgr1[..., ::-1] / 255.0, atol=1e-7)
  np.testing.assert_array_equal(s.disp0, disp)
  assert s.disp1 is None and s.sl0 is None and s.mask0 is None and s.meta == {}
  assert s.calib.focal == 100 and s.calib.doffs == 1 and s.calib.vmax == 9
  assert s.group == "Toy-perfect"
  assert set(present_parts(d)) == {"im", "disp", "calib"}


def test_gray_conversion(middlebury):
  d, bgr0, _, _ = middlebury
  g = load_scene(d, gray=True, parts={"im"})
  assert g.im0.shape == (H, W, 1)
  rgb = bgr0[..., ::-1].astype(np.float64) / 255
  expected = 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]
  np.testing.assert_allclose(g.im0[..., 0], expected, atol=1e-6)


def test_16bit_and_gray_files(tmp_path):
  rng = np.random.default_rng(1)
  a16 = rng.integers(0, 65536, (H, W), dtype=np.uint16)
  cv2.imwrite(str(tmp_path / "im0.png"), a16)
  cv2.imwrite(str(tmp_path / "im1.png"), a16)
  img = read_image(tmp_path / "im0.png")
  assert img.shape == (H, W, 1)
  np.testing.assert_allclose(img[..., 0], a16 / 65535.0, atol=1e-7)
  rgb = load_scene(tmp_path, gray=False).im0
  assert rgb.shape == (H, W, 3)
  np.testing.assert_array_equal(rgb[..., 0], rgb[..., 2])


def _full_scene():
  rng = np.random.default_rng(2)
  sl0 = rng.integers(0, 2, (H, W, 3)).astype(np.float32)
  sl0[1, 1, 0] = np.nan
  sl1 = rng.integers(0, 2, (H, W, 3)).astype(np.float32)
  disp = rng.uniform(0, 5, (H, W)).astype(np.float32)
  disp[2, 3] = np.inf
  cam = np.array([[100.0, 0, 4], [0, 100, 3], [0, 0, 1]])
  raw = {"white": rng.uniform(0, 1, (H, W)).astype(np.float32),
         "black": rng.uniform(0, 1, (H, W)).astype(np.float32),
         "p000": rng.uniform(0, 1, (H, W)).astype(np.float32),
         "i000": rng.uniform(0, 1, (H, W)).astype(np.float32)}
  return Scene(
      name="s", im0=rng.uniform(0, 1, (H, W, 3)).astype(np.float32),
      im1=rng.uniform(0, 1, (H, W, 3)).astype(np.float32), disp0=disp, disp1=disp + 1,
      mask0=rng.uniform(size=(H, W)) > 0.5, sl0=sl0, sl1=sl1, raw0=raw, raw1=dict(raw),
      calib=Calib(cam0=cam, cam1=cam, doffs=0.0, baseline=4.0, width=W, height=H, ndisp=8),
      meta={"group": "obj7", "code": "gray", "scale": np.float32(0.5)})


def test_write_load_round_trip(tmp_path):
  s = _full_scene()
  write_scene(tmp_path / "out", s)
  r = load_scene(tmp_path / "out")
  np.testing.assert_allclose(r.im0, np.round(s.im0 * 255) / 255, atol=1e-7)
  np.testing.assert_array_equal(r.disp0, s.disp0)
  np.testing.assert_array_equal(r.disp1, s.disp1)
  np.testing.assert_array_equal(r.mask0, s.mask0)
  np.testing.assert_array_equal(r.sl0, s.sl0)  # NaN positions compare equal
  np.testing.assert_array_equal(r.sl1, s.sl1)
  assert set(r.raw0) == {"white", "black", "p000", "i000"}
  np.testing.assert_allclose(r.raw1["p000"], np.round(s.raw0["p000"] * 255) / 255, atol=1e-7)
  assert r.meta == {"group": "obj7", "code": "gray", "scale": 0.5} and r.group == "obj7"
  np.testing.assert_array_equal(r.calib.cam0, s.calib.cam0)
  # On-disk pattern values follow the format: 0 / 255 / 128.
  p0 = cv2.imread(str(tmp_path / "out" / "sl0" / "000.png"), cv2.IMREAD_UNCHANGED)
  assert p0[1, 1] == UNKNOWN_PATTERN
  assert set(np.unique(p0)) <= {0, 255, UNKNOWN_PATTERN}
  assert sorted(p.name for p in (tmp_path / "out" / "sl0").iterdir()) == [
      "000.png", "001.png", "002.png"]


def test_write_16bit(tmp_path):
  s = _full_scene()
  write_scene(tmp_path / "o16", Scene(name="s", im0=s.im0, im1=s.im1), bit_depth=16)
  raw = cv2.imread(str(tmp_path / "o16" / "im0.png"), cv2.IMREAD_UNCHANGED)
  assert raw.dtype == np.uint16
  np.testing.assert_allclose(load_scene(tmp_path / "o16").im0, s.im0, atol=1 / 65535)


def test_refuses_overwrite_then_overwrites(tmp_path):
  s = _full_scene()
  write_scene(tmp_path / "o", s)
  with pytest.raises(SljaxError, match=r"o: im0\.png: exists"):
    write_scene(tmp_path / "o", s)
  s.sl0 = s.sl0[..., :2]
  s.sl1 = s.sl1[..., :2]
  write_scene(tmp_path / "o", s, overwrite=True)
  assert load_scene(tmp_path / "o", parts={"sl"}).sl0.shape == (H, W, 2)  # stale 002.png gone


def test_failed_overwrite_keeps_the_old_scene_files(tmp_path, monkeypatch):
  """A disk that fills part-way through a pattern folder (the second plane's write fails)
  leaves the old planes as they were and no temporaries: each file is replaced whole, a pattern
  sequence all at once or not at all (the other files, rewritten with the same content here,
  are replaced one by one)."""
  s = _full_scene()
  write_scene(tmp_path / "o", s)
  before = {str(p.relative_to(tmp_path)): p.read_bytes()
            for p in sorted((tmp_path / "o").rglob("*")) if p.is_file()}
  s.sl0, s.sl1 = 1.0 - s.sl0[..., :2], 1.0 - s.sl1[..., :2]
  planes = []
  real = Path.write_bytes

  def full_disk(path, data):
    if path.parent.name == "sl0":
      planes.append(path)
      if len(planes) == 2:
        real(path, data[:10])  # what a full disk leaves
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
    return real(path, data)

  monkeypatch.setattr(Path, "write_bytes", full_disk)
  with pytest.raises(OSError, match="No space left on device") as err:
    write_scene(tmp_path / "o", s, overwrite=True)
  assert err.value.filename == str(tmp_path / "o" / "sl0" / "001.png")  # the user's file
  after = {str(p.relative_to(tmp_path)): p.read_bytes()
           for p in sorted((tmp_path / "o").rglob("*")) if p.is_file()}
  assert after == before  # the names include any leftover temporary
  assert len(planes) == 2


def test_images_are_written_by_python_not_cv2_imwrite(tmp_path, monkeypatch):
  """cv2.imwrite ignores a failing close (a full disk can cut a small PNG short and still be
  called written): scene images must not go through it."""
  monkeypatch.setattr(cv2, "imwrite", lambda *a: pytest.fail("cv2.imwrite used"))
  write_scene(tmp_path / "o", _full_scene())
  back = load_scene(tmp_path / "o")
  assert back.sl0.shape == (H, W, 3) and back.mask0 is not None


def test_parts_subset(tmp_path):
  write_scene(tmp_path / "o", _full_scene())
  r = load_scene(tmp_path / "o", parts={"disp"})
  assert r.disp0 is not None and r.sl0 is None and r.calib is None and r.meta == {}


def test_missing_requested_file_names_scene_and_file(middlebury):
  d = middlebury[0]
  with pytest.raises(SljaxError, match=r"Toy-perfect.*sl0"):
    load_scene(d, parts={"sl"})
  with pytest.raises(SljaxError, match=r"Toy-perfect.*mask0\.png.*missing"):
    load_scene(d, parts={"im", "mask"})
  (d / "im1.png").unlink()
  with pytest.raises(SljaxError, match=r"Toy-perfect.*im1\.png.*missing"):
    load_scene(d)


def test_views_of_different_sizes(middlebury):
  d = middlebury[0]
  cv2.imwrite(str(d / "im1.png"), np.zeros((H, W + 2, 3), np.uint8))
  with pytest.raises(SljaxError, match=r"Toy-perfect.*im1\.png.*size"):
    load_scene(d)


def test_disparity_shape_mismatch(middlebury):
  d = middlebury[0]
  (d / "disp0.pfm").write_bytes(_pfm_bytes(np.ones((H - 1, W), np.float32)))
  with pytest.raises(SljaxError, match=r"Toy-perfect.*disp0\.pfm"):
    load_scene(d)


def test_mostly_negative_disparity_is_refused_a_few_are_kept(middlebury):
  # A flipped sign (x_right - x_left): training ignored every pixel, evaluation scored them.
  d, _, _, disp = middlebury
  flipped = -disp
  flipped[1, :2] = np.nan  # unknown pixels do not count
  (d / "disp1.pfm").write_bytes(_pfm_bytes(flipped))
  with pytest.raises(SljaxError, match=re.escape(
      f"scene {d}: disp1.pfm: 100% of its known disparities are negative; disparities are "
      "x_left - x_right >= 0 in both views, unknown pixels inf or NaN (is the sign flipped?)")):
    load_scene(d)
  few = disp.copy()
  few.flat[1:24] = -0.25  # 23 of the 47 known ((0, 0) is inf): noise near 0, not a flip
  (d / "disp1.pfm").write_bytes(_pfm_bytes(few))
  np.testing.assert_array_equal(load_scene(d).disp1, few)


def test_bad_pfm_header_in_scene(middlebury):
  d = middlebury[0]
  (d / "disp0.pfm").write_bytes(b"PX\n8 6\n-1\n" + bytes(4 * H * W))
  with pytest.raises(SljaxError, match=r"Toy-perfect.*disp0\.pfm"):
    load_scene(d)


def test_different_pattern_counts(tmp_path):
  s = _full_scene()
  write_scene(tmp_path / "o", s)
  (tmp_path / "o" / "sl1" / "002.png").unlink()
  with pytest.raises(SljaxError, match=r"o: sl1.*2 patterns.*3"):
    load_scene(tmp_path / "o")
  s.sl1 = s.sl1[..., :1]
  with pytest.raises(SljaxError, match="sl1"):
    write_scene(tmp_path / "p", s)


def test_bad_meta_json(middlebury):
  d = middlebury[0]
  (d / "meta.json").write_text("{not json")
  with pytest.raises(SljaxError, match=r"Toy-perfect.*meta\.json"):
    load_scene(d)
  (d / "meta.json").write_text(json.dumps({"group": 3}))
  assert load_scene(d).group == "3"
