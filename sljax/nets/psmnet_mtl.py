"""The multi-task twin of PSMNet: one cost volume, a disparity path and a structured-light path.

Layout (paper section 3.3: the stacked hourglass is duplicated right after the cost volume):

* `feature_extraction` + concatenation cost volume, shared.
* Disparity path: `dres0`..`dres4`, `classif1`..`classif3`, exactly PSMNet's modules and names,
  so `detach_sl(variables)` (drop the `sl` subtree) is a complete plain-PSMNet variable tree
  and `PSMNet` applied to it gives bit-identical disparities.
* Structured-light path, everything under `sl`: its own dres0, dres1 and three hourglasses
  (same structure and skip links as the disparity path), then the SL head below.

SL head (our design; the paper does not specify it). It must turn the final 4D volume
[B, D/4, H/4, W/4, 32] into t pattern logits of the left view at full resolution:

1. `head_convbn`: 3D conv-BN-ReLU 32->32 (as the first layer of a PSMNet classifier).
2. `head_attention`: 3D conv 32->1 gives one score per disparity; a softmax over disparity
   weights the 32 features into a 2D map [B, H/4, W/4, 32] (a learned soft selection of the
   matching disparity, so the head sees the features where the match is), and the same
   weights give the expected disparity (divided by D/4) as one extra channel, since the
   projected stripe at a pixel is a function of its depth.
3. Two x2 bilinear upsamplings, each followed by a 3x3 conv-BN-ReLU (33->32, 32->32).
4. `logits`: 1x1 conv 32->t with bias.

Parameters of the head: 27*32*32 + 64 + 27*32 + (9*33*32 + 64) + (9*32*32 + 64) + 33*t
= 47,424 + 33 t (47,688 for t = 8); the whole SL path adds 1,846,912 + 33 t (1,847,176 for
t = 8) to PSMNet's 5,224,768 (`sljax summary --model psmnet-mtl`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from sljax.errors import require
from sljax.kernels import Conv3D, ResolvesConvImpl
from sljax.nets.layers import ConvBN2D, ConvBN3D, conv_init, resize_linear
from sljax.nets.psmnet import (check_pair, disparity_outputs, extract_cost_volume,
                               stacked_hourglass)

SL_KEY = "sl"


class SLPath(ResolvesConvImpl, nn.Module):
  """Structured-light path: own stacked hourglass + head -> [B, H, W, t] left-view logits."""

  t: int = 8
  align_corners: bool = False
  conv_impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D

  @nn.compact
  def __call__(self, cost: jax.Array, height: int, width: int, train: bool) -> jax.Array:
    """Maps the shared cost volume [B, D/4, H/4, W/4, 64] to pattern logits."""
    impl = self.conv_impl
    _, _, out3 = stacked_hourglass(cost, train, impl)
    x = nn.relu(ConvBN3D(32, conv_impl=impl, name="head_convbn")(out3, train))
    score = Conv3D(1, (3, 3, 3), padding=1, use_bias=False, kernel_init=conv_init, impl=impl,
                   name="head_attention")(x)
    # Softmax over disparity in float32 whatever the computation dtype; [B, D, h, w, 1].
    weights = jax.nn.softmax(score.astype(jnp.float32), axis=1)
    feat = jnp.sum(weights * x, axis=1)
    num_d = x.shape[1]
    disp = jnp.arange(num_d, dtype=jnp.float32)[None, :, None, None, None]
    expected = jnp.sum(weights * disp, axis=1) / num_d
    x = jnp.concatenate([feat, expected], axis=-1).astype(x.dtype)
    for i, (h, w) in enumerate(((height // 2, width // 2), (height, width)), start=1):
      x = resize_linear(x, (w, h), (2, 1), self.align_corners)
      x = nn.relu(ConvBN2D(32, 3, 1, 1, conv_impl=impl, name=f"up{i}")(x, train))
    return nn.Conv(self.t, (1, 1), kernel_init=conv_init, name="logits")(x)


class PSMNetMTL(ResolvesConvImpl, nn.Module):
  """PSMNet + structured-light path; apply(variables, left, right, train) -> output dict.

  Returns PSMNet's outputs ("disparity", and "disparities" in training) plus "sl_logits"
  [B, H, W, t] (the left view's patterns, sigmoid for probabilities). `conv_impl` as PSMNet's.
  """

  maxdisp: int = 96
  t: int = 8
  in_channels: int = 3
  align_corners: bool = False
  conv_impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D

  @nn.compact
  def __call__(self, left: jax.Array, right: jax.Array, train: bool = False) -> dict:
    """Predicts disparity and left-view pattern logits of a [0, 1] image pair."""
    check_pair(left, right, self.in_channels, self.maxdisp)
    require(self.t > 0, f"t (number of patterns) must be positive, got {self.t}")
    h, w = left.shape[1], left.shape[2]
    impl = self.conv_impl
    cost = extract_cost_volume(left, right, self.maxdisp, train, self.align_corners, impl)
    outs = stacked_hourglass(cost, train, impl)
    out = disparity_outputs(outs, train, self.maxdisp, h, w, self.align_corners, impl)
    out["sl_logits"] = SLPath(self.t, self.align_corners, impl, name=SL_KEY)(cost, h, w, train)
    return out


class SLOnly(ResolvesConvImpl, nn.Module):
  """The twin's structured-light output alone: feature extraction, cost volume and SL path.

  Same fields and parameter names as PSMNetMTL, so it applies to the twin's variables (the
  disparity path's are not read): `PSMNet` on `detach_sl(variables)` plus this give the twin's
  two outputs in two separate runs, which never hold both 3D stacks at once
  (`sljax.inference` does so at large sizes).
  """

  maxdisp: int = 96
  t: int = 8
  in_channels: int = 3
  align_corners: bool = False
  conv_impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D

  @nn.compact
  def __call__(self, left: jax.Array, right: jax.Array, train: bool = False) -> jax.Array:
    """Left-view pattern logits [B, H, W, t]."""
    check_pair(left, right, self.in_channels, self.maxdisp)
    h, w = left.shape[1], left.shape[2]
    impl = self.conv_impl
    cost = extract_cost_volume(left, right, self.maxdisp, train, self.align_corners, impl)
    return SLPath(self.t, self.align_corners, impl, name=SL_KEY)(cost, h, w, train)


def detach_sl(variables: Mapping[str, Any]) -> dict[str, Any]:
  """Variables of the plain PSMNet from psmnet-mtl variables: every collection minus `sl`."""
  require(isinstance(variables, Mapping) and "params" in variables,
          "detach_sl expects a variables dict with a 'params' collection")
  require(SL_KEY in variables["params"],
          "these variables have no structured-light path ('sl'); are they psmnet-mtl's?")
  return {col: {k: v for k, v in tree.items() if k != SL_KEY}
          for col, tree in variables.items()}
