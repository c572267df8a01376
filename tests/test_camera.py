import re

import numpy as np
import pytest

from sljax.data.camera import Calib, depth_from_disparity, read_calib, write_calib
from sljax.errors import SljaxError

# A Middlebury 2014 calib.txt as distributed (Adirondack), with the extra keys it carries.
MIDDLEBURY = """cam0=[4161.221 0 1445.577; 0 4161.221 984.686; 0 0 1]
cam1=[4161.221 0 1654.636; 0 4161.221 984.686; 0 0 1]
doffs=209.059
baseline=176.252
width=2880
height=1988
ndisp=280
isint=0
vmin=33
vmax=218
dyavg=0.191
dymax=0.807
"""


def test_reads_middlebury_file(tmp_path):
  (tmp_path / "calib.txt").write_text(MIDDLEBURY)
  c = read_calib(tmp_path / "calib.txt")
  np.testing.assert_array_equal(
      c.cam0, [[4161.221, 0, 1445.577], [0, 4161.221, 984.686], [0, 0, 1]])
  assert c.cam1[0, 2] == 1654.636
  assert (c.doffs, c.baseline, c.width, c.height, c.ndisp) == (209.059, 176.252, 2880, 1988, 280)
  assert (c.vmin, c.vmax) == (33, 218)
  assert c.focal == 4161.221


def test_write_read_round_trip(tmp_path):
  cam = np.array([[512.5, 0, 128.25], [0, 512.5, 127.0], [0, 0, 1]])
  c = Calib(cam0=cam, cam1=cam.copy(), doffs=0.0, baseline=5.123456789, width=256, height=256,
            ndisp=64)
  write_calib(tmp_path / "calib.txt", c)
  text = (tmp_path / "calib.txt").read_text()
  assert "cam0=[512.5 0 128.25; 0 512.5 127; 0 0 1]" in text and "vmin" not in text
  r = read_calib(tmp_path / "calib.txt")
  np.testing.assert_array_equal(r.cam0, cam)
  assert r.baseline == c.baseline and r.ndisp == 64 and r.vmin is None
  c2 = Calib(cam0=cam, cam1=cam, doffs=3.5, baseline=1.0, width=2, height=3, ndisp=4,
             vmin=0.5, vmax=9.0)
  write_calib(tmp_path / "c2.txt", c2)
  r2 = read_calib(tmp_path / "c2.txt")
  assert (r2.doffs, r2.vmin, r2.vmax) == (3.5, 0.5, 9.0)


@pytest.mark.parametrize("key", ["cam0", "cam1", "doffs", "baseline", "width", "height", "ndisp"])
def test_missing_key_names_file_and_key(tmp_path, key):
  text = "\n".join(l for l in MIDDLEBURY.splitlines() if not l.startswith(key + "="))
  (tmp_path / "calib.txt").write_text(text)
  with pytest.raises(SljaxError, match=rf"calib\.txt.*{key}"):
    read_calib(tmp_path / "calib.txt")


def test_malformed_matrix(tmp_path):
  (tmp_path / "calib.txt").write_text(MIDDLEBURY.replace("0 0 1]\ncam1", "0 1]\ncam1", 1))
  with pytest.raises(SljaxError, match="cam0"):
    read_calib(tmp_path / "calib.txt")


def test_byte_order_mark_is_read(tmp_path):
  # Saved by a Windows editor: the mark glued onto "cam0" made it "lacks required key(s) cam0".
  (tmp_path / "calib.txt").write_bytes(b"\xef\xbb\xbf" + MIDDLEBURY.replace("\n", "\r\n").encode())
  c = read_calib(tmp_path / "calib.txt")
  assert c.focal == 4161.221 and c.ndisp == 280


@pytest.mark.parametrize("old, new, problem", [
    ("ndisp=280", "ndisp=0", "key 'ndisp' must be positive, got '0'"),  # was SGBM's fallback
    ("ndisp=280", "ndisp=-16", "key 'ndisp' must be positive, got '-16'"),
    ("width=2880", "width=0", "key 'width' must be positive, got '0'"),
    ("vmin=33", "vmin=300", "vmin=300 is not at most vmax=218"),
])
def test_out_of_range_value_names_file_and_key(tmp_path, old, new, problem):
  path = tmp_path / "calib.txt"
  path.write_text(MIDDLEBURY.replace(old, new))
  with pytest.raises(SljaxError, match=re.escape(f"{path}: {problem}")):
    read_calib(path)


def test_binary_file_names_file_and_problem(tmp_path):
  # A damaged or foreign file in calib.txt's place: one line, not a UnicodeDecodeError.
  path = tmp_path / "calib.txt"
  path.write_bytes(b"cam0=[1 0 0; 0 1 0; 0 0 1]\n\xff\xfe\x00garbage\n")
  with pytest.raises(SljaxError, match=re.escape(f"{path}: not a text calibration file (the byte "
                                                "at offset 27 is not UTF-8 text")):
    read_calib(path)


def test_depth_from_disparity_matches_float64_formula():
  cam = np.array([[4161.221, 0, 0], [0, 4161.221, 0], [0, 0, 1]])
  c = Calib(cam0=cam, cam1=cam, doffs=209.059, baseline=176.252, width=3, height=2, ndisp=280)
  d = np.array([[100.0, 33.5, np.inf], [np.nan, -209.059, -300.0]], dtype=np.float32)
  z = depth_from_disparity(d, c)
  assert z.dtype == np.float32
  np.testing.assert_allclose(z[0, :2], [4161.221 * 176.252 / (100 + 209.059),
                                        4161.221 * 176.252 / (33.5 + 209.059)], rtol=1e-6)
  assert np.all(np.isinf(z[0, 2])) and np.all(np.isinf(z[1]))


def test_a_key_given_twice_with_two_values_is_refused(tmp_path):
  # Two files pasted together: the last value used to win without a word.
  path = tmp_path / "calib.txt"
  path.write_text(MIDDLEBURY + "baseline=193.001\n")
  with pytest.raises(SljaxError, match=re.escape(
      f"{path}: line 13 gives 'baseline' again with another value ('193.001'; line 4: "
      "'176.252')")):
    read_calib(path)
  path.write_text(MIDDLEBURY + "baseline = 176.2520\n"  # the same value again is harmless
                  "cam1=[4161.221  0 1654.636;  0 4161.221 984.686; 0 0 1]\n")
  assert read_calib(path).baseline == 176.252
