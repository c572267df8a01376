"""Which convolution implementation runs: "lax" (XLA's own), "fast" (this package's CPU
kernels) or "gpu" / "gpu-phase" (XLA's convolutions, the transposed one in a form GPUs run
natively)."""

from __future__ import annotations

import os

import jax

IMPLS = ("auto", "lax", "fast", "gpu", "gpu-phase")
# XLA's convolutions: these differ only in the stride-s transposed 3D convolution (conv3d.py).
XLA_IMPLS = ("lax", "gpu", "gpu-phase")
GPU_BACKENDS = ("gpu", "cuda", "rocm")
# The default when nothing explicit is given; read by `conv_impl()` (models: when built).
ENV_IMPL = "SLJAX_CONV3D"


def conv_impl(impl: str | None = None) -> str:
  """The explicit choice, else $SLJAX_CONV3D, else "auto" (fast on CPU, gpu on GPU, else lax)."""
  choice = impl or os.environ.get(ENV_IMPL, "auto")
  if choice not in IMPLS:
    raise ValueError(f"conv impl must be {', '.join(IMPLS[:-1])} or {IMPLS[-1]}, got {choice!r}")
  if choice == "auto":
    return auto_impl(jax.default_backend())
  return choice


def auto_impl(backend: str) -> str:
  """What "auto" means on a backend: the exact CPU kernels on a CPU, the native transposed
  convolution on a GPU (its lax form's kernel gradient falls to a slow cuDNN kernel), else
  XLA's convolutions as written."""
  if backend == "cpu":
    return "fast"
  return "gpu" if backend in GPU_BACKENDS else "lax"


class ResolvesConvImpl:
  """Mixin for flax modules with a `conv_impl` field: resolved when the module is constructed.

  The field becomes "lax", "fast", "gpu" or "gpu-phase" (`conv_impl`: None takes
  $SLJAX_CONV3D, "auto" the backend's choice; anything else is a ValueError), so the
  environment is read once, where the model is built, not when it is traced: what runs is
  fixed by the model object (and part of its hash, so jit with the model static compiles each
  choice apart), and two models in one process can hold different choices.
  """

  def __post_init__(self):
    object.__setattr__(self, "conv_impl", conv_impl(self.conv_impl))
    super().__post_init__()
