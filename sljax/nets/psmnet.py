"""PSMNet, stacked-hourglass variant (Chang & Chen, CVPR 2018), faithful to the public reference.

Layer for layer the reference's `models/stackhourglass.py` + `models/submodule.py`:

* Feature extraction: three 3x3 conv-BN-ReLU (3->32, stride 2 on the first), residual layers
  (3 x 32 ch; 16 x 64 ch stride 2, kept as the "raw" 1/4-resolution output; 3 x 128 ch;
  3 x 128 ch dilation 2), spatial pyramid pooling with average pools 64, 32, 16, 8 on the
  1/4-resolution map, and a 320->128 conv-BN-ReLU + 1x1 128->32 fusion.
* Concatenation cost volume [B, maxdisp/4, H/4, W/4, 64] (`cost_volume`).
* dres0, dres1 (residual), three hourglasses with the reference's skip links, including the
  third one reusing the *first* hourglass's `pre` (out3 = hg3(out2, pre1, post2)).
* Classifiers with cumulative costs, linear upsampling to [maxdisp, H, W], softmax over
  disparity, regression d = sum_d d p(d).

Decisions (the reference leaves these to the PyTorch version or to input sizes):

* Interpolation. The code calls `F.upsample(..., mode='trilinear'/'bilinear')` without
  `align_corners`; on PyTorch >= 0.4 (the repository now targets 1.6) that means
  align_corners=False, the default here. Checkpoints released for PyTorch 0.3 were trained
  with the old align_corners=True behaviour, so `align_corners=True` is available as an
  option (the reference README gives the same advice). `resize_linear` reproduces PyTorch's
  interpolation exactly in both modes.
* SPP on other sizes. The pools keep the reference's fixed kernels (stride = kernel, floor
  mode, so a remainder is dropped as in PyTorch). Where the 1/4-resolution map is smaller
  than a kernel, PyTorch would fail; here the kernel shrinks to the map size along that axis
  (a global average). For 256x256 input (64x64 map) this is exactly the reference.
* Sizes. H and W must be multiples of 16 and maxdisp a multiple of 16 (the hourglasses halve
  the 1/4-resolution volume twice); pad at inference (`sljax.inference` pads as the reference
  does: the normalised input with 0, at the top and right, to a multiple of 16).
* Inputs are images in [0, 1]; the ImageNet mean/std normalisation of the reference's data
  loader happens inside the model. Grayscale (1 channel) uses the mean of the three
  channels' statistics and a 1-channel first convolution.
* Initialisation as the reference: conv kernels N(0, sqrt(2 / (kernel volume * out ch))),
  BN scale 1 / bias 0. The reference does not re-initialise its ConvTranspose3d layers, so
  they keep PyTorch's default U(-b, b), b = 1 / sqrt(out ch * 27) (`conv_transpose_init`).
  (The reference's "zero the Linear biases" branch matches no layer.)

Parameter names follow the reference (see `reference_key`): top level `feature_extraction`,
`dres0`..`dres4`, `classif1`..`classif3`; 5,224,768 parameters for RGB input.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from sljax.errors import require
from sljax.kernels import Conv3D, ConvTranspose3D, ResolvesConvImpl, phase_regression
from sljax.nets.layers import (ConvBN2D, ConvBN3D, batch_norm, conv_init, conv_transpose_init,
                               linear_resize_matrix, linear_resize_phases, resize_linear)
from sljax.nets.registry import check_maxdisp

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
SPP_POOLS = (64, 32, 16, 8)  # branch1..branch4 of the reference


def normalize_images(x: jax.Array) -> jax.Array:
  """ImageNet mean/std normalisation of [0, 1] images (1 channel: the channel averages)."""
  c = x.shape[-1]
  require(c in (1, 3), f"PSMNet expects 1 or 3 image channels, got {c}")
  mean = np.asarray(IMAGENET_MEAN, np.float32)
  std = np.asarray(IMAGENET_STD, np.float32)
  if c == 1:
    mean, std = mean.mean(keepdims=True), std.mean(keepdims=True)
  return ((x - mean) / std).astype(x.dtype)


def normalization_zero(channels: int) -> np.ndarray:
  """The [0, 1] input that `normalize_images` maps to 0, per channel: the test-time pad value."""
  require(channels in (1, 3), f"PSMNet expects 1 or 3 image channels, got {channels}")
  mean = np.asarray(IMAGENET_MEAN, np.float32)
  return mean.mean(keepdims=True) if channels == 1 else mean


def cost_volume(left_feat: jax.Array, right_feat: jax.Array, num_disp: int) -> jax.Array:
  """Concatenation cost volume [B, num_disp, H, W, 2C] from [B, H, W, C] features.

  Entry (d, y, x) holds [left(y, x); right(y, x - d)] where x >= d and zeros elsewhere,
  exactly the reference's loop, built here with one gather and one mask.
  """
  w = left_feat.shape[2]
  d = jnp.arange(num_disp)[:, None]
  x = jnp.arange(w)[None, :]
  valid = (x >= d)  # [D, W]
  src = jnp.clip(x - d, 0, w - 1)
  right = jnp.take(right_feat, src, axis=2)  # [B, H, D, W, C]
  right = jnp.moveaxis(right, 2, 1)  # [B, D, H, W, C]
  left = jnp.broadcast_to(left_feat[:, None], right.shape)
  vol = jnp.concatenate([left, right], axis=-1)
  return jnp.where(valid[None, :, None, :, None], vol, 0.0).astype(left_feat.dtype)


def disparity_regression(cost: jax.Array) -> jax.Array:
  """Soft-argmax over axis 1 of [B, D, H, W] costs: sum_d d * softmax(cost)_d -> [B, H, W]."""
  prob = jax.nn.softmax(cost, axis=1)
  disp = jnp.arange(cost.shape[1], dtype=cost.dtype)
  return jnp.einsum("bdhw,d->bhw", prob, disp)


def regress_upsampled(cost: jax.Array, maxdisp: int, height: int, width: int,
                      align_corners: bool = False) -> jax.Array:
  """disparity_regression(upsample_cost(...)) without the [B, maxdisp, H, W] volume.

  The disparity axis is upsampled by phases (`linear_resize_phases`): every upsampled plane
  is two weighted planes of the [B, D/4, H, W] costs, so softmax and regression run on those
  directly, as sums over planes that XLA fuses into a few passes over a quarter of the data
  (forward and the written-out gradient). Equal to the composition to float rounding; falls
  back to it where the phases do not apply (align_corners=True, other factors).
  """
  phases = linear_resize_phases(cost.shape[1], maxdisp, align_corners)
  if phases is None:
    return disparity_regression(upsample_cost(cost, maxdisp, height, width, align_corners))
  # Height and width as one contraction: XLA keeps [B, D, H, W] in its natural layout (two
  # tensordots with moveaxis leave it transposed, which slows every plane's pass 1.7x).
  mh = jnp.asarray(linear_resize_matrix(cost.shape[2], height, align_corners), cost.dtype)
  mw = jnp.asarray(linear_resize_matrix(cost.shape[3], width, align_corners), cost.dtype)
  c = jnp.einsum("Hh,bdhw,Ww->bdHW", mh, cost, mw)
  c = jnp.concatenate([c[:, :1], c, c[:, -1:]], axis=1)  # edge extension along disparity
  return phase_regression(c, phases)


def upsample_cost(cost: jax.Array, maxdisp: int, height: int, width: int,
                  align_corners: bool = False) -> jax.Array:
  """Trilinear upsampling of [B, D/4, H/4, W/4] costs to [B, maxdisp, H, W]."""
  return resize_linear(cost, (width, height, maxdisp), (3, 2, 1), align_corners)


def spp_pool(x: jax.Array, kernel: int) -> jax.Array:
  """Average pool with stride = kernel (floor mode); the kernel shrinks to a smaller map."""
  kh, kw = min(kernel, x.shape[1]), min(kernel, x.shape[2])
  b, h, w, c = x.shape
  nh, nw = h // kh, w // kw
  # Non-overlapping windows are a reshape and a mean: XLA:CPU's reduce_window gradient for
  # these large windows costs far more than the whole pooling.
  x = x[:, :nh * kh, :nw * kw].reshape(b, nh, kh, nw, kw, c)
  return jnp.mean(x, axis=(2, 4))


class BasicBlock(ResolvesConvImpl, nn.Module):
  """Residual block: conv-BN-ReLU, conv-BN, add the (downsampled) input; no ReLU after."""

  features: int
  strides: int = 1
  dilation: int = 1
  downsample: bool = False
  conv_impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D
  views: int = 1  # BatchNorm's groups: the views of a pair stacked in the batch

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    """Applies the block to NHWC x."""
    # Reference: padding = dilation when dilated, else 1.
    pad, impl, g = self.dilation, self.conv_impl, self.views
    out = nn.relu(ConvBN2D(self.features, 3, self.strides, pad, self.dilation, impl, g,
                           name="conv1")(x, train))
    out = ConvBN2D(self.features, 3, 1, pad, self.dilation, impl, g, name="conv2")(out, train)
    if self.downsample:
      x = ConvBN2D(self.features, 1, self.strides, 0, conv_impl=impl, groups=g,
                   name="downsample")(x, train)
    return out + x


class FeatureExtraction(ResolvesConvImpl, nn.Module):
  """Shared 2D feature extractor with SPP: [B, H, W, C] -> [B, H/4, W/4, 32].

  views > 1: the batch is that many views stacked (left then right), whose BatchNorm
  statistics stay apart in training, as in as many separate calls (the reference's).
  """

  align_corners: bool = False
  conv_impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D
  views: int = 1

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    """Returns the 32-channel 1/4-resolution features."""
    impl, g = self.conv_impl, self.views
    x = nn.relu(ConvBN2D(32, 3, 2, 1, conv_impl=impl, groups=g, name="firstconv_0")(x, train))
    x = nn.relu(ConvBN2D(32, 3, 1, 1, conv_impl=impl, groups=g, name="firstconv_1")(x, train))
    x = nn.relu(ConvBN2D(32, 3, 1, 1, conv_impl=impl, groups=g, name="firstconv_2")(x, train))
    # (features, blocks, stride, dilation); downsample where stride or width changes.
    in_ch = 32
    raw = None
    for li, (feat, blocks, stride, dil) in enumerate(
        ((32, 3, 1, 1), (64, 16, 2, 1), (128, 3, 1, 1), (128, 3, 1, 2)), start=1):
      for bi in range(blocks):
        down = bi == 0 and (stride != 1 or in_ch != feat)
        x = BasicBlock(feat, stride if bi == 0 else 1, dil, down, impl, g,
                       name=f"layer{li}_{bi}")(x, train)
        in_ch = feat
      if li == 2:
        raw = x
    skip = x
    h, w = skip.shape[1], skip.shape[2]
    branches = []
    for bi, k in enumerate(SPP_POOLS, start=1):
      b = nn.relu(ConvBN2D(32, 1, 1, 0, conv_impl=impl, groups=g, name=f"branch{bi}")(
          spp_pool(skip, k), train))
      branches.append(resize_linear(b, (w, h), (2, 1), self.align_corners))
    # Reference order: raw, skip, branch4, branch3, branch2, branch1.
    x = jnp.concatenate([raw, skip] + branches[::-1], axis=-1)
    x = nn.relu(ConvBN2D(128, 3, 1, 1, conv_impl=impl, groups=g, name="lastconv_0")(x, train))
    return nn.Conv(32, (1, 1), use_bias=False, kernel_init=conv_init, name="lastconv_1")(x)


class Dres0(ResolvesConvImpl, nn.Module):
  """Two 3D conv-BN-ReLU: 64 -> 32 -> 32 on the cost volume."""

  conv_impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    """Applies the two layers."""
    x = nn.relu(ConvBN3D(32, conv_impl=self.conv_impl, name="convbn_0")(x, train))
    return nn.relu(ConvBN3D(32, conv_impl=self.conv_impl, name="convbn_1")(x, train))


class Dres1(ResolvesConvImpl, nn.Module):
  """3D conv-BN-ReLU then conv-BN (the caller adds the residual)."""

  conv_impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    """Applies the two layers."""
    x = nn.relu(ConvBN3D(32, conv_impl=self.conv_impl, name="convbn_0")(x, train))
    return ConvBN3D(32, conv_impl=self.conv_impl, name="convbn_1")(x, train)


class ConvTransposeBN3D(ResolvesConvImpl, nn.Module):
  """ConvTranspose3d(k=3, stride 2, padding 1, output_padding 1, no bias) + BN: doubles D, H, W."""

  features: int
  conv_impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    """Applies the transposed conv then BN."""
    x = ConvTranspose3D(self.features, (3, 3, 3), strides=2, padding=1, output_padding=1,
                        use_bias=False, kernel_init=conv_transpose_init, impl=self.conv_impl,
                        name="conv")(x)
    return batch_norm("bn")(x, use_running_average=not train)


class Hourglass(ResolvesConvImpl, nn.Module):
  """The reference's 3D hourglass: returns (out, pre, post) for the next one's skip links.

  pre = relu(conv2(conv1(x)) + postsqu) (relu without postsqu);
  post = relu(conv5(conv4(conv3(pre))) + presqu) (+ pre without presqu); out = conv6(post).
  """

  inplanes: int = 32
  conv_impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D

  @nn.compact
  def __call__(self, x: jax.Array, presqu: jax.Array | None, postsqu: jax.Array | None,
               train: bool) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Runs the hourglass on a 1/4-resolution volume."""
    c2, impl = self.inplanes * 2, self.conv_impl
    out = nn.relu(ConvBN3D(c2, strides=2, conv_impl=impl, name="conv1")(x, train))  # 1/8
    pre = ConvBN3D(c2, conv_impl=impl, name="conv2")(out, train)
    pre = nn.relu(pre + postsqu) if postsqu is not None else nn.relu(pre)
    out = nn.relu(ConvBN3D(c2, strides=2, conv_impl=impl, name="conv3")(pre, train))  # 1/16
    out = nn.relu(ConvBN3D(c2, conv_impl=impl, name="conv4")(out, train))
    up = ConvTransposeBN3D(c2, impl, name="conv5")(out, train)  # 1/8
    post = nn.relu(up + (presqu if presqu is not None else pre))
    out = ConvTransposeBN3D(self.inplanes, impl, name="conv6")(post, train)  # 1/4
    return out, pre, post


class Classifier(ResolvesConvImpl, nn.Module):
  """3D conv-BN-ReLU 32->32 then 3D conv 32->1 (no bias): one cost per disparity."""

  conv_impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    """Returns costs [B, D/4, H/4, W/4]."""
    x = nn.relu(ConvBN3D(32, conv_impl=self.conv_impl, name="convbn_0")(x, train))
    x = Conv3D(1, (3, 3, 3), padding=1, use_bias=False, kernel_init=conv_init,
               impl=self.conv_impl, name="conv_1")(x)
    return x[..., 0]


def stacked_hourglass(cost: jax.Array, train: bool, conv_impl: str
                      ) -> tuple[jax.Array, jax.Array, jax.Array]:
  """dres0, dres1 and the three hourglasses; submodules are created in the calling module.

  Must be called inside a compact method: it names its submodules dres0..dres4 there, which
  is what makes the twin's disparity path carry exactly PSMNet's parameter names.
  """
  cost0 = Dres0(conv_impl, name="dres0")(cost, train)
  cost0 = Dres1(conv_impl, name="dres1")(cost0, train) + cost0
  out1, pre1, post1 = Hourglass(conv_impl=conv_impl, name="dres2")(cost0, None, None, train)
  out1 = out1 + cost0
  out2, _, post2 = Hourglass(conv_impl=conv_impl, name="dres3")(out1, pre1, post1, train)
  out2 = out2 + cost0
  # The reference passes pre1 (not pre2) to the third hourglass; kept on purpose.
  out3, _, _ = Hourglass(conv_impl=conv_impl, name="dres4")(out2, pre1, post2, train)
  out3 = out3 + cost0
  return out1, out2, out3


def disparity_outputs(outs: tuple[jax.Array, jax.Array, jax.Array], train: bool, maxdisp: int,
                      height: int, width: int, align_corners: bool, conv_impl: str) -> dict:
  """Classifiers classif1..3 (cumulative costs), upsampling and regression -> output dict."""
  cost1 = Classifier(conv_impl, name="classif1")(outs[0], train)
  cost2 = Classifier(conv_impl, name="classif2")(outs[1], train) + cost1
  cost3 = Classifier(conv_impl, name="classif3")(outs[2], train) + cost2

  def regress(c):
    # Upsampling, softmax and regression in float32 whatever the computation dtype.
    return regress_upsampled(c.astype(jnp.float32), maxdisp, height, width, align_corners)

  pred3 = regress(cost3)
  if not train:
    return {"disparity": pred3}
  return {"disparity": pred3, "disparities": (regress(cost1), regress(cost2), pred3)}


def check_pair(left: jax.Array, right: jax.Array, in_channels: int, maxdisp: int,
               multiple: int = 16) -> None:
  """Validates a stereo batch for the PSMNets (SljaxError naming the problem)."""
  require(left.ndim == 4 and left.shape == right.shape,
          f"left and right must be BxHxWxC batches of the same shape, got {left.shape} and "
          f"{right.shape}")
  require(left.shape[-1] == in_channels,
          f"the model expects {in_channels} channel(s) per view, got {left.shape[-1]}")
  h, w = left.shape[1], left.shape[2]
  require(h % multiple == 0 and w % multiple == 0,
          f"image size {h}x{w} must be a multiple of {multiple} (pad the input)")
  check_maxdisp(maxdisp, f"maxdisp {maxdisp}")


def extract_cost_volume(left: jax.Array, right: jax.Array, maxdisp: int,
                        train: bool, align_corners: bool, conv_impl: str) -> jax.Array:
  """Normalises, runs the shared `feature_extraction` on each view and builds the volume."""
  # Training: one call on both views, BatchNorm statistics per view as in the reference's two
  # calls; half the operations to trace and compile (the main job's cold first step 20 s
  # against 22-23 s on Zen 5). Evaluation keeps two calls (running statistics: the same
  # values), which ONNX's symbolic batch needs (jax2onnx mis-sizes a slice of a stacked one).
  if not train:
    features = FeatureExtraction(align_corners, conv_impl, name="feature_extraction")
    return cost_volume(features(normalize_images(left), train),
                       features(normalize_images(right), train), maxdisp // 4)
  features = FeatureExtraction(align_corners, conv_impl, views=2, name="feature_extraction")
  f = features(normalize_images(jnp.concatenate([left, right])), train)
  return cost_volume(f[:left.shape[0]], f[left.shape[0]:], maxdisp // 4)


class PSMNet(ResolvesConvImpl, nn.Module):
  """PSMNet (stacked hourglass); apply(variables, left, right, train) -> output dict.

  Returns {"disparity": [B, H, W]} in evaluation and additionally {"disparities": (d1, d2, d3)}
  in training (then pass mutable=["batch_stats"]). `conv_impl` chooses the convolutions
  (`sljax.kernels`); left out, $SLJAX_CONV3D or "auto", read when the model is constructed.
  """

  maxdisp: int = 96
  in_channels: int = 3
  align_corners: bool = False
  conv_impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D

  @nn.compact
  def __call__(self, left: jax.Array, right: jax.Array, train: bool = False) -> dict:
    """Predicts the left-referenced disparity of a [0, 1] image pair."""
    check_pair(left, right, self.in_channels, self.maxdisp)
    impl = self.conv_impl
    cost = extract_cost_volume(left, right, self.maxdisp, train, self.align_corners, impl)
    outs = stacked_hourglass(cost, train, impl)
    return disparity_outputs(outs, train, self.maxdisp, left.shape[1], left.shape[2],
                             self.align_corners, impl)


def reference_key(path: tuple[str, ...]) -> str:
  """The reference PyTorch state_dict key of a flax variable path (params or batch_stats).

  E.g. ('feature_extraction', 'layer2_0', 'downsample', 'conv', 'kernel') ->
  'feature_extraction.layer2.0.downsample.0.weight'; BN 'scale'/'bias'/'mean'/'var' map to
  'weight'/'bias'/'running_mean'/'running_var'. Paths under the twin's 'sl' have no key.
  """
  leaf_names = {"kernel": "weight", "scale": "weight", "bias": "bias", "mean": "running_mean",
                "var": "running_var"}
  *mods, leaf = path
  require(leaf in leaf_names and mods and mods[0] != "sl", f"no reference key for {path}")
  leaf = leaf_names[leaf]
  inner = {"conv": "0", "bn": "1"}  # convbn = Sequential(conv, BN)
  parts: list[str] = []
  top = mods[0]
  rest = mods[1:]
  if top == "feature_extraction":
    parts.append(top)
    name = rest[0]
    base, _, idx = name.rpartition("_")
    if base.startswith("layer"):
      parts += [base, idx]
      blk = rest[1]  # conv1 / conv2 / downsample
      if blk == "conv1":
        parts += ["conv1", "0", inner[rest[2]]]
      else:
        parts += [blk, inner[rest[2]]]
    elif name.startswith("branch"):
      parts += [name, "1", inner[rest[1]]]
    elif base in ("firstconv", "lastconv"):
      parts += [base, str(2 * int(idx))]
      if len(rest) > 1:
        parts.append(inner[rest[1]])
    else:
      require(False, f"no reference key for {path}")
  elif top in ("dres0", "dres1", "classif1", "classif2", "classif3"):
    parts.append(top)
    _, _, idx = rest[0].rpartition("_")
    parts.append(str(2 * int(idx)))
    if len(rest) > 1:
      parts.append(inner[rest[1]])
  elif top in ("dres2", "dres3", "dres4"):
    parts += [top, rest[0]]
    if rest[0] in ("conv1", "conv3", "conv4"):
      parts.append("0")
    parts.append(inner[rest[1]])
  else:
    require(False, f"no reference key for {path}")
  return ".".join(parts + [leaf])
