"""sljax.io.sizes: the one parser of image sizes, checked against hand-written cases."""

import argparse

import numpy as np
import pytest

from sljax.deploy import stablehlo
from sljax.errors import SljaxError
from sljax.io import sizes
from sljax.train.config import parse_size as flag_size


@pytest.mark.parametrize("value, want", [
    (None, None), (5, (5, 5)), (np.int64(7), (7, 7)), ((3, 4), (3, 4)), ([96, 128], (96, 128))])
def test_as_size_accepts(value, want):
  assert sizes.as_size(value) == want


@pytest.mark.parametrize("value", [0, -2, (0, 4), (4, -1), "ab", (1, 2, 3)])
def test_as_size_rejects_with_the_name(value):
  with pytest.raises(SljaxError, match="train_size"):
    sizes.as_size(value, "train_size")


@pytest.mark.parametrize("text, want", [("96x128", (96, 128)), ("96X128", (96, 128))])
def test_parse_size_every_entry_point(text, want):
  """The training flag, export's --size and the library agree on every spelling."""
  assert sizes.parse_size(text) == flag_size(text) == stablehlo.parse_size(text) == want


def test_square_sizes_where_allowed():
  """N means N x N for training; an export artifact's shape must be spelt out."""
  assert sizes.parse_size("256") == flag_size("256") == (256, 256)
  with pytest.raises(SljaxError, match="expected HEIGHTxWIDTH"):
    stablehlo.parse_size("256")


@pytest.mark.parametrize("text", ["1x2x3", "a", "", "0x3", "-1", "4x"])
def test_parse_size_rejects(text):
  with pytest.raises(SljaxError, match="--size"):
    sizes.parse_size(text)
  with pytest.raises(argparse.ArgumentTypeError):  # argparse prints it as a usage error
    flag_size(text)
