"""build_model: names, options, errors."""

import pytest

from sljax.errors import SljaxError
from sljax.nets import MODEL_NAMES, PSMNet, PSMNetMTL, UNet, build_model, model_kwargs_for


def test_builds_every_model():
  assert MODEL_NAMES == ("psmnet", "psmnet-mtl", "unet-sl", "unet-disp")
  m = build_model("psmnet", maxdisp=64, t=9, gray=True)  # t ignored by PSMNet
  assert isinstance(m, PSMNet) and m.maxdisp == 64 and m.in_channels == 1
  m = build_model("psmnet-mtl", t=9, align_corners=True)
  assert isinstance(m, PSMNetMTL) and m.t == 9 and m.in_channels == 3 and m.align_corners
  m = build_model("unet-sl", t=9, maxdisp=96, depth=3, base_width=16)
  assert isinstance(m, UNet) and (m.head, m.t, m.depth, m.base_width) == ("sl", 9, 3, 16)
  m = build_model("unet-disp", in_channels=1)
  assert isinstance(m, UNet) and m.head == "disp" and m.in_channels == 1


def test_unknown_model_lists_valid_names():
  with pytest.raises(SljaxError) as e:
    build_model("resnet")
  for name in MODEL_NAMES:
    assert name in str(e.value)


@pytest.mark.parametrize("name, kwargs, match", [
    ("psmnet", {"depth": 3}, "no option"),
    ("unet-sl", {"align_corners": True}, "no option"),
    ("psmnet", {"maxdisp": 100}, "multiple of 16"),
    ("psmnet-mtl", {"t": 0}, "positive"),
    ("unet-disp", {"in_channels": 2}, "in_channels"),
    ("unet-disp", {"gray": True, "in_channels": 3}, "in_channels"),
])
def test_bad_options(name, kwargs, match):
  with pytest.raises(SljaxError, match=match):
    build_model(name, **kwargs)


def test_model_kwargs_for():
  assert "depth" in model_kwargs_for("unet-sl") and "align_corners" in model_kwargs_for("psmnet")
  with pytest.raises(SljaxError):
    model_kwargs_for("nope")
