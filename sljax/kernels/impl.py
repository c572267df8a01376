"""Which convolution implementation runs: "lax" (XLA's own) or "fast" (this package's)."""

from __future__ import annotations

import dataclasses
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


def impl_field() -> dataclasses.Field:
  """A model field whose default is `conv_impl()` when the model is constructed.

  So the environment is read once, where the model is built, not when it is traced: a
  compiled step cached for one model never silently runs the other implementation.
  """
  return dataclasses.field(default_factory=conv_impl)
