"""Networks: PSMNet, its multi-task twin and the UNets, built by name from one table.

Every model is applied as `model.apply(variables, left, right, train=...)` (with
`mutable=["batch_stats"]` when training) on BxHxWxC images in [0, 1] and returns a dict:
"disparity" BxHxW (disparity models), "disparities" (PSMNets in training: the three
intermediate predictions), "sl_logits" BxHxWxt (left view; psmnet-mtl, unet-sl) and
"sl_logits_right" (unet-sl). What each network trains on and returns is in
`sljax.nets.registry.NETS`.

The model classes are imported on first use (module __getattr__), so that listing the
networks (command-line parsers) does not import flax.
"""

from __future__ import annotations

import importlib
from typing import Any

from sljax.errors import SljaxError
from sljax.nets.registry import COMMON_OPTIONS, MODELS, NAMES, NETS, NetSpec, spec

MODEL_NAMES = NAMES

_LAZY = {"PSMNet": "sljax.nets.psmnet", "PSMNetMTL": "sljax.nets.psmnet_mtl",
         "UNet": "sljax.nets.unet", "detach_sl": "sljax.nets.psmnet_mtl"}

__all__ = ["MODELS", "MODEL_NAMES", "NETS", "NetSpec", "PSMNet", "PSMNetMTL", "UNet",
           "build_model", "detach_sl", "model_kwargs_for", "spec"]


def __getattr__(name: str) -> Any:
  if name in _LAZY:
    return getattr(importlib.import_module(_LAZY[name]), name)
  raise AttributeError(f"module 'sljax.nets' has no attribute {name!r}")


def model_kwargs_for(name: str) -> tuple[str, ...]:
  """The keyword arguments build_model accepts for `name`."""
  return COMMON_OPTIONS + spec(name).options


def build_model(name: str, *, maxdisp: int = 96, t: int = 8, gray: bool = False,
                in_channels: int | None = None, **kwargs: Any):
  """Builds a model by name: "psmnet", "psmnet-mtl", "unet-sl" or "unet-disp".

  maxdisp (PSMNets; multiple of 16), t (patterns; psmnet-mtl, unet-sl), gray or in_channels
  (channels per view: 1 or 3) apply where relevant; align_corners (PSMNets) and depth,
  base_width (UNets) are model options; conv_impl ("auto" | "lax" | "fast", every network;
  left out: $SLJAX_CONV3D, else "auto") chooses the convolution kernels (sljax.kernels) and
  is resolved here, when the model is constructed. Unknown names or options raise SljaxError.
  """
  s = spec(name)
  unknown = sorted(set(kwargs) - set(s.options))
  if unknown:
    raise SljaxError(f"model {name!r} has no option(s) {', '.join(unknown)}; accepted: "
                     f"{', '.join(model_kwargs_for(name))}")
  if in_channels is None:
    in_channels = 1 if gray else 3
  if in_channels not in (1, 3) or (gray and in_channels != 1):
    raise SljaxError(f"in_channels must be 1 (gray) or 3 (RGB), got {in_channels} "
                     f"(gray={gray})")
  args = dict(s.fixed, in_channels=in_channels, **kwargs)
  if "maxdisp" in s.options:
    if maxdisp <= 0 or maxdisp % 16:
      raise SljaxError(f"maxdisp must be a positive multiple of 16 for {name}, got {maxdisp}")
    args["maxdisp"] = maxdisp
  if "t" in s.options:
    if t <= 0:
      raise SljaxError(f"t (number of patterns) must be positive, got {t}")
    args["t"] = t
  return s.build_class()(**args)
