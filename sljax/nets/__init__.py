"""Networks: PSMNet, its multi-task twin and the UNets, built by name.

Every model is applied as `model.apply(variables, left, right, train=...)` (with
`mutable=["batch_stats"]` when training) on BxHxWxC images in [0, 1] and returns a dict:
"disparity" BxHxW (disparity models), "disparities" (PSMNets in training: the three
intermediate predictions), "sl_logits" BxHxWxt (left view; psmnet-mtl, unet-sl) and
"sl_logits_right" (unet-sl).
"""

from __future__ import annotations

from typing import Any

import flax.linen as nn

from sljax.errors import SljaxError
from sljax.nets.psmnet import PSMNet
from sljax.nets.psmnet_mtl import PSMNetMTL, detach_sl
from sljax.nets.unet import UNet

MODEL_NAMES = ("psmnet", "psmnet-mtl", "unet-sl", "unet-disp")

# Accepted by every model (ignored where they do not apply, so one training config can
# carry them for any model) and the options specific to some models.
_COMMON = ("maxdisp", "t", "gray", "in_channels")
_SPECIFIC = {
    "psmnet": ("align_corners",),
    "psmnet-mtl": ("align_corners",),
    "unet-sl": ("depth", "base_width"),
    "unet-disp": ("depth", "base_width"),
}

__all__ = ["MODEL_NAMES", "PSMNet", "PSMNetMTL", "UNet", "build_model", "detach_sl",
           "model_kwargs_for"]


def model_kwargs_for(name: str) -> tuple[str, ...]:
  """The keyword arguments build_model accepts for `name`."""
  _check_name(name)
  return _COMMON + _SPECIFIC[name]


def _check_name(name: str) -> None:
  if name not in MODEL_NAMES:
    raise SljaxError(f"unknown model {name!r}; valid models: {', '.join(MODEL_NAMES)}")


def build_model(name: str, *, maxdisp: int = 96, t: int = 8, gray: bool = False,
                in_channels: int | None = None, **kwargs: Any) -> nn.Module:
  """Builds a model by name: "psmnet", "psmnet-mtl", "unet-sl" or "unet-disp".

  maxdisp (PSMNets; multiple of 16), t (patterns; psmnet-mtl, unet-sl), gray or in_channels
  (channels per view: 1 or 3) apply where relevant; align_corners (PSMNets) and depth,
  base_width (UNets) are model options. Unknown names or options raise SljaxError.
  """
  _check_name(name)
  unknown = sorted(set(kwargs) - set(_SPECIFIC[name]))
  if unknown:
    raise SljaxError(f"model {name!r} has no option(s) {', '.join(unknown)}; accepted: "
                     f"{', '.join(model_kwargs_for(name))}")
  if in_channels is None:
    in_channels = 1 if gray else 3
  if in_channels not in (1, 3) or (gray and in_channels != 1):
    raise SljaxError(f"in_channels must be 1 (gray) or 3 (RGB), got {in_channels} "
                     f"(gray={gray})")
  if name in ("psmnet", "psmnet-mtl") and (maxdisp <= 0 or maxdisp % 16):
    raise SljaxError(f"maxdisp must be a positive multiple of 16 for {name}, got {maxdisp}")
  if name in ("psmnet-mtl", "unet-sl") and t <= 0:
    raise SljaxError(f"t (number of patterns) must be positive, got {t}")
  if name == "psmnet":
    return PSMNet(maxdisp=maxdisp, in_channels=in_channels, **kwargs)
  if name == "psmnet-mtl":
    return PSMNetMTL(maxdisp=maxdisp, t=t, in_channels=in_channels, **kwargs)
  head = "sl" if name == "unet-sl" else "disp"
  return UNet(head=head, t=t, in_channels=in_channels, **kwargs)
