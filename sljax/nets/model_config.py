"""A network's configuration, resolved and checked once; `build_model` and `init_variables` on top
of it.

A `ModelConfig` is what training, inference and the compiled steps share about a network: its
name, input channels, disparity range, pattern count, module options, convolution kernels and
computation precision. It is checked when made (one SljaxError naming the problem) and is
hashable, so it keys the compiled-step cache: two configs that differ in anything that changes
a compiled program (the kernels included) never share one.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from sljax.errors import SljaxError
from sljax.kernels.impl import conv_impl as resolve_conv_impl
from sljax.nets.draws import batched_draws
from sljax.nets.registry import NetSpec, check_maxdisp, model_kwargs_for, spec
from sljax.runtime import kept_programs

# Computation dtypes of --precision; parameters, optimiser state and losses stay float32.
COMPUTE_DTYPES = {"fp32": jnp.float32, "bf16": jnp.bfloat16}


@dataclasses.dataclass(frozen=True)
class ModelConfig:
  """One network and every option that defines it (see `of` for the defaults).

  maxdisp is the disparity range of the network (PSMNets: the cost volume) and of its
  disparity loss and validation mask (every network); t the patterns of SL networks (None for
  the others); options the module options beyond these (align_corners, depth, base_width);
  conv_impl 'lax', 'fast', 'gpu' or 'gpu-phase' (resolved here from None or an IMPLS name:
  sljax.kernels.impl.conv_impl; None takes $SLJAX_CONV3D); precision a COMPUTE_DTYPES key.
  """
  net: str
  in_channels: int = 3
  maxdisp: int = 96
  t: int | None = None
  options: tuple[tuple[str, Any], ...] = ()
  conv_impl: str | None = None
  precision: str = "fp32"

  def __post_init__(self):
    s = spec(self.net)
    unknown = sorted({k for k, _ in self.options} - set(s.options) | (
        {k for k, _ in self.options} & {"maxdisp", "t", "conv_impl"}))
    if unknown:
      raise SljaxError(f"model {self.net!r} has no option(s) {', '.join(unknown)} here; "
                       f"accepted: {', '.join(model_kwargs_for(self.net))}")
    if self.in_channels not in (1, 3):
      raise SljaxError(f"in_channels must be 1 (gray) or 3 (RGB), got {self.in_channels}")
    check_maxdisp(self.maxdisp, f"maxdisp {self.maxdisp} ({self.net})")
    if "t" in s.options and (self.t is None or self.t <= 0):
      raise SljaxError(f"t (number of patterns) must be positive, got {self.t}")
    if self.precision not in COMPUTE_DTYPES:
      raise SljaxError(f"precision must be one of {tuple(COMPUTE_DTYPES)}, got "
                       f"{self.precision!r}")
    object.__setattr__(self, "t", self.t if "t" in s.options else None)
    object.__setattr__(self, "options", tuple(sorted(self.options)))
    try:
      object.__setattr__(self, "conv_impl", resolve_conv_impl(self.conv_impl))
    except ValueError as e:
      raise SljaxError(str(e)) from None

  @classmethod
  def of(cls, name: str, *, maxdisp: int = 96, t: int = 8, gray: bool = False,
         in_channels: int | None = None, conv_impl: str | None = None,
         precision: str = "fp32", **options: Any) -> ModelConfig:
    """The config build_model(name, ...) builds (its keyword arguments and defaults);
    conv_impl None takes $SLJAX_CONV3D, else "auto"."""
    if in_channels is None:
      in_channels = 1 if gray else 3
    if gray and in_channels != 1:
      raise SljaxError(f"in_channels must be 1 (gray) or 3 (RGB), got {in_channels} "
                       f"(gray={gray})")
    return cls(name, in_channels, maxdisp, t, tuple(options.items()), conv_impl, precision)

  @property
  def spec(self) -> NetSpec:
    """The network's entry in sljax.nets.registry.NETS."""
    return spec(self.net)

  @property
  def dtype(self) -> Any:
    """The computation dtype of the steps."""
    return COMPUTE_DTYPES[self.precision]

  @property
  def saved_kwargs(self) -> dict[str, Any]:
    """The build options a checkpoint's config.json keeps as model_kwargs (the kernels and
    precision are the loading machine's choice, not part of the network)."""
    kw: dict[str, Any] = {"in_channels": self.in_channels}
    if "maxdisp" in self.spec.options:
      kw["maxdisp"] = self.maxdisp
    if self.t is not None:
      kw["t"] = self.t
    kw.update(self.options)
    return kw

  def build(self):
    """The flax module."""
    return self.spec.build_class()(**dict(self.spec.fixed), **self.saved_kwargs,
                                   conv_impl=self.conv_impl)


def build_model(name: str, **kwargs: Any):
  """Builds a model by name: "psmnet", "psmnet-mtl", "unet-sl" or "unet-disp".

  maxdisp (PSMNets; multiple of 16), t (patterns; psmnet-mtl, unet-sl), gray or in_channels
  (channels per view: 1 or 3) apply where relevant; align_corners (PSMNets) and depth,
  base_width (UNets) are model options; conv_impl (sljax.kernels.impl.IMPLS, every network;
  left out: $SLJAX_CONV3D, else "auto") chooses the convolution kernels (sljax.kernels) and
  is resolved here, when the model is constructed. Unknown names or options raise SljaxError.
  """
  kwargs.pop("precision", None)  # a step option, not a module one
  return ModelConfig.of(name, **kwargs).build()


# Initialisation runs once: compile it without XLA's backend optimisations (2-3x faster to
# compile on CPU). Always the same options, so initial values stay deterministic in the seed.
INIT_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0,
                         "xla_llvm_disable_expensive_passes": True}


def _host_device() -> jax.Device | None:
  """The host's CPU device, or None where jax runs without its CPU backend (JAX_PLATFORMS)."""
  try:
    return jax.local_devices(backend="cpu")[0]
  except RuntimeError:
    return None


def _default_device() -> jax.Device:
  """Where uncommitted arrays go: jax's default device setting, else the first device."""
  chosen = jax.config.jax_default_device
  if isinstance(chosen, str):  # a platform name
    return jax.devices(chosen)[0]
  return chosen or jax.devices()[0]


def variable_shapes(model: nn.Module, height: int, width: int, channels: int) -> dict[str, Any]:
  """`init_variables`' tree as shapes and dtypes, traced and never run (no compile)."""
  x = jax.ShapeDtypeStruct((1, height, width, channels), jnp.float32)
  return dict(jax.eval_shape(lambda a, b: model.init(jax.random.PRNGKey(0), a, b, train=False),
                             x, x))


@functools.lru_cache(maxsize=8)
def _init_fn(model: nn.Module, height: int, width: int, channels: int,
             device: jax.Device | None):
  x = jnp.zeros((1, height, width, channels), jnp.float32)

  @batched_draws
  def init(key):
    return model.init(key, x, x, train=False)

  return kept_programs.Program(jax.jit(init, compiler_options=INIT_COMPILER_OPTIONS),
                             "init", (repr(model), height, width, channels),
                             device=device).prefetch()


def init_variables(model: nn.Module, seed: int, height: int, width: int,
                   channels: int) -> dict[str, Any]:
  """Model variables from a batch-1 dummy input, deterministic in seed (compiled once per
  model and shape in a process), computed on the host's CPU and placed on the default device."""
  # The forward is dead code in init; what is left is the random values of every parameter,
  # about 1500 small fusions for the twin, which XLA:GPU compiles kernel by kernel: about 33 s
  # of the paper preset's start on an H200, 7.8 s on its host's CPU (docs/benchmarks/gpu.md,
  # "NVIDIA H200"). Drawn once per shape (`batched_draws`) XLA:CPU compiles it in half the time.
  host = _host_device()
  if host is None or host == _default_device():
    return dict(_init_fn(model, height, width, channels, None)(jax.random.PRNGKey(seed)))
  with jax.default_device(host):
    variables = _init_fn(model, height, width, channels, host)(jax.random.PRNGKey(seed))
    variables = jax.device_get(variables)
  return dict(jax.tree.map(jnp.asarray, variables))  # uncommitted, on the default device
