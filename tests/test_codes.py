import jax.numpy as jnp
import numpy as np
import pytest

from sljax.errors import SljaxError
from sljax.sl import codes


def _naive_bits(c: int, code: str, t: int) -> list[int]:
  """Independent per-column construction: string formatting, Gray by the reflection rule."""
  if code == "gray":
    # Reflected construction: the Gray list of t bits is 0+G(t-1) followed by 1+reversed(G(t-1)).
    table = [""]
    for _ in range(t):
      table = ["0" + g for g in table] + ["1" + g for g in reversed(table)]
    return [int(ch) for ch in table[c]]
  return [int(ch) for ch in format(c, f"0{t}b")]


@pytest.mark.parametrize("width,expected", [(1, 1), (2, 1), (3, 2), (256, 8), (257, 9), (720, 10),
                                            (1280, 11)])
def test_num_bits(width, expected):
  assert codes.num_bits(width) == expected


@pytest.mark.parametrize("xp", [np, jnp], ids=["numpy", "jax"])
@pytest.mark.parametrize("code", ["binary", "gray"])
@pytest.mark.parametrize("width", [256, 720, 1280])
def test_round_trip_every_column(width, code, xp):
  t = codes.num_bits(width)
  cols = xp.arange(width)
  bits = codes.encode(cols, code, t, xp=xp)
  assert bits.shape == (width, t) and bits.dtype == xp.uint8
  back = np.asarray(codes.decode(bits, code, xp=xp))
  np.testing.assert_array_equal(back, np.arange(width))
  # Distinct codes for every column.
  assert len({tuple(b) for b in np.asarray(bits).tolist()}) == width


@pytest.mark.parametrize("code", ["binary", "gray"])
@pytest.mark.parametrize("width", [256, 720])
def test_patterns_match_naive_construction(width, code):
  t = codes.num_bits(width)
  p = codes.patterns(code, width)
  assert p.shape == (t, width) and p.dtype == np.uint8
  naive = np.array([_naive_bits(c, code, t) for c in range(width)], dtype=np.uint8).T
  np.testing.assert_array_equal(p, naive)
  np.testing.assert_array_equal(codes.inverse(p), 1 - naive)


def test_binary_pattern_n_has_2_to_the_n_stripes():
  p = codes.patterns("binary", 256)
  assert p.shape == (8, 256)
  for k in range(8):
    n = k + 1
    stripes = 1 + np.count_nonzero(np.diff(p[k].astype(int)))
    assert stripes == 2 ** n
    assert p[k, 0] == 0  # dark first, as bit k of column 0


def test_gray_neighbours_differ_in_one_bit():
  for width in (256, 720):
    p = codes.patterns("gray", width).astype(int)
    changes = np.abs(np.diff(p, axis=1)).sum(axis=0)
    np.testing.assert_array_equal(changes, np.ones(width - 1))


def test_fewer_patterns_than_bits_are_the_coarsest():
  full = codes.patterns("gray", 1024)
  coarse = codes.patterns("gray", 1024, t=9)
  # The t coarsest Gray patterns of a wider code equal the Gray code of the stripe index.
  np.testing.assert_array_equal(coarse, full[:9])
  np.testing.assert_array_equal(codes.pattern_columns(1024, 9), np.arange(1024) // 2)


def test_encode_batched_shape_and_float_bits():
  cols = np.array([[0, 5], [200, 255]])
  bits = codes.encode(cols, "gray", 8)
  assert bits.shape == (2, 2, 8)
  np.testing.assert_array_equal(codes.decode(bits.astype(np.float32), "gray"), cols)


def test_bad_arguments():
  with pytest.raises(SljaxError, match="code"):
    codes.patterns("ternary", 256)
  with pytest.raises(SljaxError, match="t = 9"):
    codes.patterns("binary", 256, t=9)
  with pytest.raises(SljaxError, match="width"):
    codes.num_bits(0)
