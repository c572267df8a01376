"""jax2onnx's lowering of lax.conv_general_dilated, extended to every rank and layout.

jax2onnx (0.12 to 0.17) maps only the 1D/2D layouts NCHW / NHWC with OIHW / HWIO kernels and
stops at PSMNet's first 3D convolution (NDHWC x DHWIO: "Unsupported conv layouts"). This plugin,
registered through jax2onnx's own registry (`register`), replaces its lowering for real
convolutions of any rank: the dimension numbers are read as permutations, so the input goes to
ONNX's N,C,spatial layout by one Transpose (perm = lhs_spec), the kernel to O,I,spatial (perm =
rhs_spec) and the result back (the inverse of out_spec).

A convolution of the s-dilated input (lhs_dilation, flax's transposed convolution) becomes
ONNX ConvTranspose: the same map with the kernel flipped in space and in/out swapped, and ONNX's
pads k_eff - 1 - p per side (p: JAX's padding of the dilated input). Other cases (complex
inputs, batch groups) go to jax2onnx's own lowering.

The smallest case jax2onnx fails on (for an upstream report):
  jax2onnx.to_onnx(lambda x, k: jax.lax.conv_general_dilated(x, k, (1, 1, 1), "SAME",
      dimension_numbers=("NDHWC", "DHWIO", "NDHWC")), [(1, 4, 4, 4, 1), (3, 3, 3, 1, 1)])
  raises jax2onnx's "Unsupported conv layouts: lhs=(0, 4, 1, 2, 3), rhs=(4, 3, 0, 1, 2), ..."
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np


def _inverse(perm) -> list[int]:
  """The permutation undoing `perm`."""
  inv = [0] * len(perm)
  for i, p in enumerate(perm):
    inv[p] = i
  return inv


def _transpose_pads(padding, kernel_spatial, rhs_dilation) -> list[int] | None:
  """ONNX ConvTranspose pads (begins then ends) for JAX's padding of the dilated input, or None
  where one would be negative (no ConvTranspose form)."""
  eff = [(k - 1) * d + 1 for k, d in zip(kernel_spatial, rhs_dilation)]
  begins = [e - 1 - lo for e, (lo, _) in zip(eff, padding)]
  ends = [e - 1 - hi for e, (_, hi) in zip(eff, padding)]
  return None if min(begins + ends) < 0 else begins + ends


def jax_compat() -> None:
  """jax 0.10 spells an unbatched axis None and dropped `batching.not_mapped`, which jax2onnx
  0.12's batching rules still read (AttributeError under vmap); its 0.17 sets the same name."""
  from jax.interpreters import batching
  try:
    batching.not_mapped
  except AttributeError:
    batching.not_mapped = None


def register() -> None:
  """Installs the lowering in jax2onnx's plugin registry (idempotent; after its own plugins)."""
  jax_compat()
  import onnx_ir as ir
  from jax2onnx.plugins import plugin_system
  from jax2onnx.plugins._ir_shapes import _ensure_value_metadata, _stamp_type_and_shape
  from jax2onnx.plugins.jax.lax import conv as upstream

  name = jax.lax.conv_general_dilated_p.name
  plugin_system.import_all_plugins()  # else theirs would be imported later and win
  if getattr(plugin_system.PLUGIN_REGISTRY.get(name), "sljax", False):
    return

  def typed(ctx, value, dtype, shape):
    value.type = ir.TensorType(dtype)
    _stamp_type_and_shape(value, shape)
    _ensure_value_metadata(ctx, value)
    return value

  def transpose(ctx, value, perm, shape, dtype, hint):
    out = ctx.builder.Transpose(value, _outputs=[ctx.fresh_name(hint)], perm=list(perm))
    return typed(ctx, out, dtype, tuple(shape[i] for i in perm))

  class AnyRankConv(upstream.ConvGeneralDilatedPlugin):
    """conv_general_dilated of any rank and layout -> Transpose, Conv / ConvTranspose, Transpose."""
    sljax = True

    def lower(self, ctx: Any, eqn: Any) -> None:
      p = eqn.params
      lhs_var, rhs_var = eqn.invars[:2]
      out_var = eqn.outvars[0]
      dtype = np.dtype(out_var.aval.dtype)
      lhs_spec, rhs_spec, out_spec = (tuple(int(i) for i in s) for s in p["dimension_numbers"])
      nsp = len(lhs_spec) - 2
      lhs_dil = tuple(p.get("lhs_dilation") or (1,) * nsp)
      rhs_dil = tuple(p.get("rhs_dilation") or (1,) * nsp)
      strides = tuple(p.get("window_strides") or (1,) * nsp)
      padding = tuple(tuple(int(v) for v in pair) for pair in p["padding"])
      groups = int(p.get("feature_group_count", 1))
      transposed = any(d > 1 for d in lhs_dil)
      rhs_shape = tuple(rhs_var.aval.shape)
      kernel_spatial = [rhs_shape[i] for i in rhs_spec[2:]]
      pads = (_transpose_pads(padding, kernel_spatial, rhs_dil) if transposed else
              [lo for lo, _ in padding] + [hi for _, hi in padding])
      if (np.issubdtype(dtype, np.complexfloating) or p.get("batch_group_count", 1) != 1
          or pads is None or min(pads) < 0
          or (transposed and (groups != 1 or any(s != 1 for s in strides)))):
        return super().lower(ctx, eqn)
      ir_dtype = upstream._dtype_to_ir(dtype, ctx.builder.enable_double_precision)
      lhs = ctx.get_value_for_var(lhs_var, name_hint=ctx.fresh_name("conv_lhs"))
      rhs = ctx.get_value_for_var(rhs_var, name_hint=ctx.fresh_name("conv_rhs"))
      lhs = transpose(ctx, lhs, lhs_spec, tuple(lhs_var.aval.shape), ir_dtype, "conv_lhs_nc")
      rhs = transpose(ctx, rhs, rhs_spec, rhs_shape, ir_dtype, "conv_rhs_oi")
      oi_shape = tuple(rhs_shape[i] for i in rhs_spec)
      out_shape = tuple(out_var.aval.shape)
      nc_shape = tuple(out_shape[i] for i in out_spec)
      attrs = {"pads": pads, "dilations": list(rhs_dil)}
      if transposed:
        # ConvTranspose scatters with the kernel as given; the dilated-input conv correlates:
        # flip the taps in space, and ONNX's kernel is (in, out, spatial).
        rhs = upstream._flip_spatial_dims(ctx, rhs, oi_shape, "OI" + "S" * nsp, "conv_rhs_flip")
        rhs = transpose(ctx, rhs, [1, 0] + list(range(2, nsp + 2)), oi_shape, ir_dtype,
                        "conv_rhs_io")
        conv = ctx.builder.ConvTranspose(lhs, rhs, _outputs=[ctx.fresh_name("conv_t")],
                                         strides=list(lhs_dil), **attrs)
      else:
        conv = ctx.builder.Conv(lhs, rhs, _outputs=[ctx.fresh_name("conv")],
                                strides=list(strides), group=groups, **attrs)
      conv = typed(ctx, conv, ir_dtype, nc_shape)
      out = ctx.builder.Transpose(conv, _outputs=[ctx.fresh_name("conv_out")],
                                  perm=_inverse(out_spec))
      ctx.bind_value_for_var(out_var, typed(ctx, out, ir_dtype, out_shape))

  metadata = dict(getattr(plugin_system.PLUGIN_REGISTRY.get(name), "metadata", {}) or {})
  plugin_system.register_primitive(**dict(metadata, jaxpr_primitive=name))(AnyRankConv)
