"""The one table of per-network facts: what training, inference and evaluation need to know.

Each network is one `NetSpec` entry of `NETS`; adding a network means adding one entry (and
its module). The table imports nothing heavy, so command-line parsers can list the names; a
network's module is imported only when it is built.
"""

from __future__ import annotations

import dataclasses
import importlib
import numbers
from typing import Any

from sljax.errors import SljaxError

TASKS = ("sl", "disp")
# How pad-mode inference pads a network's input: "normalized-zero" (PSMNets: to a multiple of
# 16 with the value their input normalisation maps to 0), "unet" (to a multiple of 2^depth with
# the value the UNet's input centring maps to 0), "zero" (to a multiple of 16 with 0).
PAD_RULES = ("normalized-zero", "unet", "zero")


@dataclasses.dataclass(frozen=True)
class NetSpec:
  """Facts about one network (see NETS)."""
  name: str
  module: str                     # "package.module:Class"
  parts: tuple[str, ...]          # batch parts it trains on (sljax.data.dataset.BATCH_PARTS)
  tasks: tuple[str, ...]          # what it learns, a subset of TASKS in that order
  gray: bool                      # default input: one channel per view (else RGB)
  outputs: tuple[str, ...]        # evaluation-mode output keys
  options: tuple[str, ...]        # build options beyond in_channels
  fixed: tuple[tuple[str, Any], ...] = ()  # constructor arguments that define the network
  twin: str | None = None         # the multi-task twin trained by strategies other than stl
  single: str | None = None       # a twin's single-task network (its disparity path)
  sec_per_sample_64: float = 0.1  # rough CPU s per training sample at 64x64 (for estimates)
  pad: str = "zero"               # inference's pad protocol (PAD_RULES; sljax.inference.padding)

  @property
  def multi_task(self) -> bool:
    """True when the network learns both tasks (weighting strategies apply)."""
    return len(self.tasks) > 1

  def build_class(self):
    """The flax module class (imports its module)."""
    module, _, cls = self.module.partition(":")
    return getattr(importlib.import_module(module), cls)


NETS: dict[str, NetSpec] = {spec.name: spec for spec in (
    NetSpec("psmnet", "sljax.nets.psmnet:PSMNet", parts=("left", "right", "disp"),
            tasks=("disp",), gray=False, outputs=("disparity",),
            options=("maxdisp", "align_corners", "conv_impl"), twin="psmnet-mtl", sec_per_sample_64=0.11,
            pad="normalized-zero"),
    NetSpec("psmnet-mtl", "sljax.nets.psmnet_mtl:PSMNetMTL",
            parts=("left", "right", "disp", "sl"), tasks=("sl", "disp"), gray=False,
            outputs=("disparity", "sl_logits"), options=("maxdisp", "t", "align_corners", "conv_impl"),
            single="psmnet", sec_per_sample_64=0.18, pad="normalized-zero"),
    NetSpec("unet-sl", "sljax.nets.unet:UNet", parts=("left", "right", "sl", "sl_right"),
            tasks=("sl",), gray=True, outputs=("sl_logits", "sl_logits_right"),
            options=("t", "depth", "base_width", "conv_impl"), fixed=(("head", "sl"),),
            sec_per_sample_64=0.02, pad="unet"),
    NetSpec("unet-disp", "sljax.nets.unet:UNet", parts=("left", "right", "disp"),
            tasks=("disp",), gray=True, outputs=("disparity",),
            options=("depth", "base_width", "conv_impl"), fixed=(("head", "disp"),),
            sec_per_sample_64=0.02, pad="unet"),
)}
NAMES = tuple(NETS)
# What `train.py --model` chooses from: twins are reached through --strategy.
MODELS = tuple(name for name, spec in NETS.items() if spec.single is None)
# Options every network accepts (ignored where they do not apply, so one configuration can
# carry them for any network).
COMMON_OPTIONS = ("maxdisp", "t", "gray", "in_channels")


def check_maxdisp(maxdisp: Any, what: str) -> None:
  """The one rule on a disparity range: a positive multiple of 16 (PSMNet's cost volume is
  built at 1/4 resolution and its hourglasses halve it twice); SljaxError naming `what`."""
  if not isinstance(maxdisp, numbers.Integral) or isinstance(maxdisp, bool) or maxdisp <= 0 or maxdisp % 16:
    raise SljaxError(f"{what}: must be a positive multiple of 16")


def model_kwargs_for(name: str) -> tuple[str, ...]:
  """The keyword arguments build_model accepts for `name`."""
  return COMMON_OPTIONS + spec(name).options


def spec(name: str) -> NetSpec:
  """The table entry of a network; SljaxError listing the valid names."""
  if name not in NETS:
    raise SljaxError(f"unknown model {name!r}; valid models: {', '.join(NAMES)}")
  return NETS[name]


def trained_net(model: str, strategy: str) -> str:
  """The network a (model, strategy) pair trains: the twin for weighting strategies."""
  s = spec(model)
  return s.twin if s.twin is not None and strategy != "stl" else model
