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

from sljax.nets.registry import MODELS, NAMES, NETS, NetSpec, model_kwargs_for, spec

MODEL_NAMES = NAMES

_LAZY = {"PSMNet": "sljax.nets.psmnet", "PSMNetMTL": "sljax.nets.psmnet_mtl",
         "UNet": "sljax.nets.unet", "detach_sl": "sljax.nets.psmnet_mtl",
         "ModelConfig": "sljax.nets.model_config", "build_model": "sljax.nets.model_config"}

__all__ = ["MODELS", "MODEL_NAMES", "ModelConfig", "NETS", "NetSpec", "PSMNet", "PSMNetMTL", "UNet",
           "build_model", "detach_sl", "model_kwargs_for", "spec"]


def __getattr__(name: str) -> Any:
  if name in _LAZY:
    return getattr(importlib.import_module(_LAZY[name]), name)
  raise AttributeError(f"module 'sljax.nets' has no attribute {name!r}")
