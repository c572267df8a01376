import struct

import numpy as np
import pytest

from sljax.data.pfm import read_pfm, write_pfm
from sljax.errors import SljaxError


def _hand_written_pfm(values: np.ndarray, little: bool) -> bytes:
  """A PFM built byte by byte from the format description, independent of write_pfm."""
  h, w = values.shape[:2]
  c = 3 if values.ndim == 3 else 1
  magic = b"PF" if c == 3 else b"Pf"
  header = magic + b"\n" + f"{w} {h}\n{-1.0 if little else 1.0}\n".encode()
  order = "<" if little else ">"
  body = b""
  for y in range(h - 1, -1, -1):  # bottom row first
    for x in range(w):
      samples = values[y, x] if c == 3 else [values[y, x]]
      for v in samples:
        body += struct.pack(order + "f", float(v))
  return header + body


def test_round_trip_keeps_inf(tmp_path):
  rng = np.random.default_rng(0)
  a = rng.uniform(-50, 300, (5, 7)).astype(np.float32)
  a[1, 2] = np.inf
  a[4, 0] = -np.inf
  write_pfm(tmp_path / "d.pfm", a)
  b = read_pfm(tmp_path / "d.pfm")
  assert b.dtype == np.float32 and b.shape == (5, 7)
  np.testing.assert_array_equal(a, b)


def test_round_trip_three_channels(tmp_path):
  a = np.arange(4 * 3 * 3, dtype=np.float32).reshape(4, 3, 3) / 7
  write_pfm(tmp_path / "c.pfm", a)
  np.testing.assert_array_equal(read_pfm(tmp_path / "c.pfm"), a)


def test_writer_matches_hand_written_bytes(tmp_path):
  a = np.array([[1.5, np.inf, -2.0], [0.25, 3.0, 1e6]], dtype=np.float32)
  write_pfm(tmp_path / "d.pfm", a)
  written = (tmp_path / "d.pfm").read_bytes()
  # The header text may differ in number formatting; the layout and samples must not.
  expected = _hand_written_pfm(a, little=True)
  assert written.split(b"\n", 3)[:2] == expected.split(b"\n", 3)[:2]
  assert float(written.split(b"\n", 3)[2]) < 0  # little-endian
  assert written.split(b"\n", 3)[3] == expected.split(b"\n", 3)[3]


@pytest.mark.parametrize("little", [True, False])
def test_reader_matches_hand_written_file(tmp_path, little):
  a = np.array([[1.5, np.inf, -2.0], [0.25, 3.0, 1e6]], dtype=np.float32)
  (tmp_path / "h.pfm").write_bytes(_hand_written_pfm(a, little))
  np.testing.assert_array_equal(read_pfm(tmp_path / "h.pfm"), a)
  c = np.stack([a, a + 1, -a], axis=-1)
  (tmp_path / "h3.pfm").write_bytes(_hand_written_pfm(c, little))
  np.testing.assert_array_equal(read_pfm(tmp_path / "h3.pfm"), c)


@pytest.mark.parametrize("content", [
    b"P6\n3 2\n255\n" + bytes(18),          # a PPM, not a PFM
    b"Pf\n3 two\n-1\n" + bytes(24),         # bad size
    b"Pf\n3 2\n-1\n" + bytes(8),            # truncated samples
    b"Pf\n3 2\n0\n" + bytes(24),            # zero scale
])
def test_bad_header_names_file(tmp_path, content):
  p = tmp_path / "broken.pfm"
  p.write_bytes(content)
  with pytest.raises(SljaxError, match="broken.pfm"):
    read_pfm(p)


def test_missing_file_names_file(tmp_path):
  with pytest.raises(SljaxError, match="nothere.pfm"):
    read_pfm(tmp_path / "nothere.pfm")


def test_crlf_header(tmp_path):
  a = np.array([[1.0, 2.0], [3.0, np.inf]], dtype=np.float32)
  body = b"".join(struct.pack("<f", v) for v in a[::-1].ravel())
  (tmp_path / "w.pfm").write_bytes(b"Pf\r\n2 2\r\n-1.000000\r\n" + body)
  np.testing.assert_array_equal(read_pfm(tmp_path / "w.pfm"), a)
