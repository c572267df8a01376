"""Which convolution implementation runs: "lax" (XLA's own) or "fast" (this package's)."""

from __future__ import annotations

import os

import jax

IMPLS = ("auto", "lax", "fast")
# The default when nothing explicit is given; read by `conv_impl()` (models: when built).
ENV_IMPL = "SLJAX_CONV3D"


def conv_impl(impl: str | None = None) -> str:
  """'lax' or 'fast': the explicit choice, else $SLJAX_CONV3D, else "auto" (fast on CPU)."""
  choice = impl or os.environ.get(ENV_IMPL, "auto")
  if choice not in IMPLS:
    raise ValueError(f"conv impl must be auto, lax or fast, got {choice!r}")
  if choice == "auto":
    return "fast" if jax.default_backend() == "cpu" else "lax"
  return choice


class ResolvesConvImpl:
  """Mixin for flax modules with a `conv_impl` field: resolved when the module is constructed.

  The field becomes 'lax' or 'fast' (`conv_impl`: None takes $SLJAX_CONV3D, "auto" the
  backend's choice; anything else is a ValueError), so the environment is read once, where
  the model is built, not when it is traced: what runs is fixed by the model object (and
  part of its hash, so jit with the model static compiles each choice apart), and two models
  in one process can hold different choices.
  """

  def __post_init__(self):
    object.__setattr__(self, "conv_impl", conv_impl(self.conv_impl))
    super().__post_init__()
