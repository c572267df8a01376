"""Inference you can import: `predict = load(checkpoint)` then `predict(left, right)` on any size.

Inputs: numpy images HxW, HxWx1 or HxWx3 (or batched BxHxWxC), uint8 (/255), uint16
(/65535) or float already in [0, 1]. They are converted to the channel count the model was
trained with (RGB -> gray by ITU-R BT.601 luma, gray -> RGB by repetition).

Resolution modes:
- "pad" (the PSMNet reference's test protocol, Test_img.py / submission.py of JiaRenChang/PSMNet):
  the reference normalises the image with the ImageNet mean and std and pads the normalised
  tensor with 0 at the TOP and RIGHT to the next multiple of 16. sljax normalises inside the
  model, so the [0, 1] pair is padded with the value the model's input normalisation maps to 0
  (`pad_rule`), at the top and right, and the outputs are cropped back (rows from the top pad
  on, columns up to the input width):
    * psmnet, psmnet-mtl (RGB): the ImageNet mean colour (0.485, 0.456, 0.406), multiple of 16
      (the reference's rule exactly).
    * psmnet, psmnet-mtl (gray): 0.449, the average of the three means, which the 1-channel
      normalisation (mean and std averaged over the channels) maps to 0; multiple of 16.
    * unet-sl, unet-disp: 0.5, which the UNet's input centring 2x - 1 maps to 0; multiple of
      2^depth, so every pooling level halves an even size and the UNet's own bottom/right edge
      padding never applies. unet-disp scales its sigmoid by the width it is given, the padded
      width here.
  Why the normalised zero: the first convolution pads its input with zeros in the normalised
  domain, so a pad region of normalised zeros is read exactly as the network's own border
  padding; black (0) would be a dark frame (about -2 after normalisation) that the reference
  never shows its network.
  Why top and right: left-referenced disparity matches x in the left view with x - d in the
  right view, so columns added on the right are never a match for an image pixel, while columns
  on the left would be. Other (unknown) models are padded with 0 to a multiple of 16.
- "resize" (the paper's evaluation): the pair is resized to the training size with the
  training loader's resampling (area when shrinking, bilinear when enlarging), the outputs are
  resized back bilinearly, and disparities are multiplied by input width / training width.

Outputs: dict with "disparity" (HxW float32, input pixels; BxHxW for batched input) and, for
structured-light models, "patterns" (left-view probabilities HxWxt), "patterns_right" (unet-sl)
and "confidence" (HxW in [0, 1], higher is surer: the correlation's peak-ratio confidence for
unet-sl, whose disparity is the windowed correlation of its predicted patterns, and the mean
pattern certainty |2p - 1| for psmnet-mtl).

Memory at full resolution: the twin (psmnet-mtl) holds two stacks of 3D activations; when its
cost volume is large (TWIN_SPLIT_BYTES) it runs as two programs, PSMNet on the disparity
path's variables and then its SL path alone, with the same outputs (`forward`).

The network runs in one jitted function shared by every predictor of an equal model (flax
modules compare by their fields), so jax keeps one compilation per model and model-input shape
(in resize mode that is always the training size) for the whole process: both resolution
modes, or several checkpoints of one configuration, reuse it. `Predictor.traces` counts the
traces of the predictor's model.
"""

import collections
import dataclasses
import functools
import os
from typing import Any

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from sljax import tune
from sljax.corr.correlation import sl_disparity
from sljax.corr.uncertainty import view_uncertainty
from sljax.data.dataset import resize_image
from sljax.data.scene import to_gray, unit_image
from sljax.errors import SljaxError
from sljax.sizes import as_size
from sljax.nets import build_model, registry
from sljax.nets.psmnet import PSMNet, normalization_zero
from sljax.nets.psmnet_mtl import PSMNetMTL, SLOnly, detach_sl
from sljax.nets.unet import INPUT_ZERO, UNet
from sljax.train.checkpoint import load_for_inference

PAD_MULTIPLE = 16  # PSMNet reference (and the default for models sljax does not know)
MODES = ("pad", "resize")


@dataclasses.dataclass(frozen=True)
class PadRule:
  """How pad mode pads a model's input: to a multiple of `multiple`, with `fill` per channel."""
  multiple: int
  fill: tuple[float, ...]

  def describe(self) -> str:
    """E.g. 'multiple of 16, filled with (0.485, 0.456, 0.406)'."""
    return (f"multiple of {self.multiple} (top/right), filled with "
            f"({', '.join(f'{v:.4g}' for v in self.fill)})")


def pad_rule(model, channels: int) -> PadRule:
  """The pad protocol for a model with `channels` input channels (see the module docstring)."""
  if isinstance(model, (PSMNet, PSMNetMTL)):
    return PadRule(PAD_MULTIPLE, tuple(float(v) for v in normalization_zero(channels)))
  if isinstance(model, UNet):
    return PadRule(2 ** model.depth, (INPUT_ZERO,) * channels)
  return PadRule(PAD_MULTIPLE, (0.0,) * channels)


def pad_pair(left: np.ndarray, right: np.ndarray, rule: PadRule
             ) -> tuple[np.ndarray, np.ndarray, int]:
  """Pads BxHxWxC views at the top and right per rule; returns them and the top pad."""
  _, h, w, c = left.shape
  ph, pw = -h % rule.multiple, -w % rule.multiple
  if not (ph or pw):
    return left, right, 0
  fill = np.asarray(rule.fill, np.float32).reshape(1, 1, 1, c)

  def pad(x):
    out = np.empty((x.shape[0], h + ph, w + pw, c), np.float32)
    out[...] = fill
    out[:, ph:, :w] = x
    return out
  return pad(left), pad(right), ph


def short_repr(value: Any) -> str:
  """repr of value cut to 60 characters, for messages."""
  r = repr(value)
  return r if len(r) <= 60 else r[:57] + "..."


def _as_batch(image: np.ndarray, what: str) -> tuple[np.ndarray, bool]:
  """HxW / HxWxC / BxHxWxC -> (BxHxWxC, batched)."""
  try:
    a = np.asarray(image)
  except ValueError:  # a ragged nested list
    a = np.empty((), object)
  if a.dtype.kind == "V" and jnp.issubdtype(a.dtype, jnp.floating):
    # bfloat16 (and other ml_dtypes floats) is numpy kind "V": an image, not a record array
    a = a.astype(np.float32)
  if a.dtype.kind in "OUSV":  # a path, None or a ragged list: say what it was, not "shape ()"
    raise SljaxError(f"{what}: expected an image array (numpy HxW, HxWxC or BxHxWxC), got "
                     f"{type(image).__name__} {short_repr(image)}")
  if a.ndim == 2:
    a, batched = a[None, :, :, None], False
  elif a.ndim == 3:
    if a.shape[2] not in (1, 3):
      raise SljaxError(f"{what}: a 3-D image must be HxWx1 or HxWx3 (1 or 3 channels), got "
                       f"shape {a.shape} (pass a batch of gray images as BxHxWx1)")
    a, batched = a[None], False
  elif a.ndim == 4:
    batched = True
  else:
    raise SljaxError(f"{what}: expected HxW, HxWxC or BxHxWxC, got shape {a.shape}")
  if a.shape[3] not in (1, 3):
    raise SljaxError(f"{what}: images need 1 or 3 channels, got {a.shape[3]} (shape {a.shape})")
  if 0 in a.shape:
    raise SljaxError(f"{what}: empty image of shape {a.shape}")
  return a, batched


def prepare_pair(left: np.ndarray, right: np.ndarray, channels: int | None = None,
                 name: str = "input") -> tuple[np.ndarray, np.ndarray, bool]:
  """Checks and converts a stereo pair to float32 BxHxWxC in [0, 1] (C = channels if given)."""
  lb, batched = _as_batch(left, f"{name}: left view")
  rb, batched_r = _as_batch(right, f"{name}: right view")
  if batched != batched_r or lb.shape[:3] != rb.shape[:3]:
    raise SljaxError(f"{name}: left and right views differ in size: {np.shape(left)} vs "
                     f"{np.shape(right)}")
  lf = unit_image(lb, f"{name}: left view")
  rf = unit_image(rb, f"{name}: right view")
  if channels is not None:
    lf, rf = convert_channels(lf, channels), convert_channels(rf, channels)
  elif lf.shape[3] != rf.shape[3]:  # one gray, one colour: promote the gray one
    lf, rf = convert_channels(lf, 3), convert_channels(rf, 3)
  return lf, rf, batched


def convert_channels(images: np.ndarray, channels: int) -> np.ndarray:
  """...xC float images -> ...x`channels` (gray <-> RGB)."""
  c = images.shape[-1]
  if c == channels:
    return images
  if channels == 1:
    return to_gray(images)
  if channels == 3:
    return np.repeat(images, 3, axis=-1)
  raise SljaxError(f"cannot convert {c}-channel images to {channels} channels")


def _resize_maps(maps: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
  """Bilinear (half-pixel centres) resize of BxHxW or BxHxWxC float maps."""
  if maps.shape[1:3] == tuple(hw):
    return maps
  out = []
  for m in maps:  # one cv2 call per image (cv2 handles up to 512 channels at once)
    r = cv2.resize(np.ascontiguousarray(m, dtype=np.float32), (hw[1], hw[0]),
                   interpolation=cv2.INTER_LINEAR)
    out.append(r.reshape(hw + m.shape[2:]))
  return np.stack(out)


def _tree_diff(expected: Any, got: Any, path: str = "") -> str | None:
  """First difference between two nested dicts of arrays (keys or shapes), or None."""
  if isinstance(expected, dict) or hasattr(expected, "items"):
    if not (isinstance(got, dict) or hasattr(got, "items")):
      return f"{path or '/'}: expected a collection, got an array"
    ek, gk = set(expected.keys()), set(got.keys())
    if ek != gk:
      missing, extra = sorted(ek - gk), sorted(gk - ek)
      return (f"{path or '/'}: missing {missing[:3]}" if missing else
              f"{path or '/'}: unexpected {extra[:3]}")
    for k in sorted(ek):
      d = _tree_diff(expected[k], got[k], f"{path}/{k}")
      if d:
        return d
    return None
  if hasattr(got, "items"):
    return f"{path}: expected an array, got a collection"
  es, gs = tuple(expected.shape), tuple(np.shape(got))
  return None if es == gs else f"{path}: expected shape {es}, got {gs}"


_TRACES: collections.Counter = collections.Counter()  # model -> traces (compilations)


def _forward(model, variables, left, right) -> dict:
  """Eval-mode outputs: float32 disparity and pattern probabilities (sigmoid of the logits)."""
  _TRACES[model] += 1  # runs only while tracing: counts compilations
  out = model.apply(variables, left, right, train=False)
  res = {}
  if "disparity" in out:
    res["disparity"] = out["disparity"].astype("float32")
  if "sl_logits" in out:
    res["patterns"] = jax.nn.sigmoid(out["sl_logits"])
  if "sl_logits_right" in out:
    res["patterns_right"] = jax.nn.sigmoid(out["sl_logits_right"])
  return res


@functools.cache
def _jitted_forward(ynn: bool = True):
  """`_forward` jitted with the model static, so equal models share compilations; `ynn`:
  XLA:CPU's YNNPACK fusions on or off (sljax.tune's forward choice)."""
  options = tune.KernelChoice(forward_ynn=ynn).compiler_options("forward")
  return jax.jit(_forward, static_argnums=0, compiler_options=options)


# The twin (psmnet-mtl) runs as two programs when its cost volume would exceed this many bytes:
# PSMNet on the disparity path's variables, then the SL path alone (`SLOnly`). Same values;
# the two 3D stacks are never alive together (1024x1280, maxdisp 192: peak 9.2 -> 6.2 GiB when
# measured before issue 13's blocked convolutions; 4.0 GiB since).
TWIN_SPLIT_BYTES = 256 * 2**20


def _twin_halves(model):
  """(PSMNet, SLOnly) with the twin's configuration."""
  kw = {"maxdisp": model.maxdisp, "in_channels": model.in_channels,
        "align_corners": model.align_corners, "conv_impl": model.conv_impl}
  return PSMNet(**kw), SLOnly(t=model.t, **kw)


def _sl_forward(model, variables, left, right):
  """Pattern probabilities of the twin's SL path alone (SLOnly)."""
  _TRACES[model] += 1
  return {"patterns": jax.nn.sigmoid(model.apply(variables, left, right, train=False))}


@functools.cache
def _jitted_sl_forward(ynn: bool = True):
  """`_sl_forward` jitted as `_jitted_forward` is."""
  options = tune.KernelChoice(forward_ynn=ynn).compiler_options("forward")
  return jax.jit(_sl_forward, static_argnums=0, compiler_options=options)


def twin_split_needed(model, shape: tuple[int, ...]) -> bool:
  """True for a psmnet-mtl whose cost volume for a BxHxWxC input exceeds TWIN_SPLIT_BYTES."""
  if not isinstance(model, PSMNetMTL):
    return False
  b, h, w = shape[0], shape[1], shape[2]
  return 4 * b * (model.maxdisp // 4) * (h // 4) * (w // 4) * 64 > TWIN_SPLIT_BYTES


def forward(model, variables, left, right, split: bool | None = None, ynn: bool = True) -> dict:
  """The model's eval outputs (disparity, pattern probabilities) for prepared inputs.

  split: run the twin as two programs (see TWIN_SPLIT_BYTES); None decides by size.
  ynn: XLA:CPU's YNNPACK fusions on or off (the forward choice of sljax.tune).
  """
  if split is None:
    split = twin_split_needed(model, np.shape(left))
  if not split:
    return _jitted_forward(ynn)(model, variables, left, right)
  plain, sl_only = _twin_halves(model)
  out = dict(_jitted_forward(ynn)(plain, detach_sl(variables), left, right))
  out.update(_jitted_sl_forward(ynn)(sl_only, variables, left, right))
  return out


@dataclasses.dataclass(frozen=True)
class ModelSpec:
  """What the predictor learnt about a model from an abstract run of it."""
  channels: int
  outputs: tuple[str, ...]

  @property
  def is_sl(self) -> bool:
    """True for models that predict structured-light patterns."""
    return "sl_logits" in self.outputs


@functools.lru_cache(maxsize=16)
def _abstract_run(model, c: int, h: int, w: int) -> tuple[Any, tuple[str, ...]]:
  """(variable shapes, output names) of the model on 1 x h x w x c inputs: traced once per
  equal model and shape in a process (tracing a PSMNet takes seconds; an experiment grid loads
  many checkpoints of one model)."""
  x = jax.ShapeDtypeStruct((1, h, w, c), jnp.float32)
  shapes = jax.eval_shape(lambda a, b: model.init(jax.random.PRNGKey(0), a, b, train=False),
                          x, x)
  out = jax.eval_shape(lambda v, a, b: model.apply(v, a, b, train=False), shapes, x, x)
  return shapes, tuple(sorted(out.keys()))


def _probe(model, variables, channels_first_guess: int, size: tuple[int, int],
           name: str, model_desc: str) -> ModelSpec:
  """Finds the input channel count the variables fit and the model's outputs (no compute)."""
  h, w = size
  diffs = []
  for c in (channels_first_guess, 4 - channels_first_guess):
    try:
      shapes, outputs = _abstract_run(model, c, h, w)
    except MemoryError as e:  # e.g. a huge maxdisp: not a mismatch of the checkpoint
      raise SljaxError(f"{name}: cannot build the model {model_desc}: out of memory "
                       f"({str(e).splitlines()[0][:200]})") from None
    except Exception as e:  # a model that cannot take this channel count at all
      diffs.append(f"{c} channels: {type(e).__name__}: {str(e).splitlines()[0][:200]}")
      continue
    # Every collection the model creates (params, batch_stats) must be in the variables.
    d = _tree_diff(dict(shapes), {k: variables[k] for k in shapes.keys() if k in variables})
    if d is None:
      return ModelSpec(channels=c, outputs=outputs)
    diffs.append(f"{c} channels: {d}")
  raise SljaxError(f"{name}: the checkpoint's variables do not match the model {model_desc} "
                   f"({'; '.join(diffs)})")


class Predictor:
  """predict(left, right) -> dict of numpy outputs; see the module docstring."""

  def __init__(self, model, variables, *, model_name: str, model_kwargs: dict | None = None,
               train_size: Any = None, mode: str = "pad", gray: bool | None = None,
               sl_max_disp: int | None = None, sl_window: int | None = None,
               name: str | None = None, split_twin: bool | None = None,
               kernels: "tune.KernelChoice" = tune.DEFAULT):
    if mode not in MODES:
      raise SljaxError(f"mode must be one of {MODES}, got {mode!r}")
    if not isinstance(kernels, tune.KernelChoice):  # else it fails only at the first call
      raise SljaxError(f"kernels must be a sljax.tune.KernelChoice, got {short_repr(kernels)}")
    try:
      hash(model)  # the shared compiled function takes the model as a static argument
    except TypeError:
      raise SljaxError(f"{model_name}: the model must be hashable (a flax module whose fields "
                       "are hashable)") from None
    self.model_name = model_name
    self.model_kwargs = dict(model_kwargs or {})
    self.mode = mode
    self.split_twin = split_twin  # psmnet-mtl in two programs: None = when large (forward)
    self.kernels = kernels  # compiler choices (sljax.tune); its forward one applies here
    self.train_size = as_size(train_size, "train_size")
    self.name = name or model_name
    self.sl_max_disp = sl_max_disp
    self.sl_window = sl_window
    if mode == "resize" and self.train_size is None:
      raise SljaxError(f"{self.name}: resize mode needs the training size, which the "
                       "checkpoint's config lacks; use --mode pad (full resolution)")
    self.variables = jax.tree_util.tree_map(jax.numpy.asarray, variables)  # on device once
    probe_size = self.train_size or (256, 256)
    guess = getattr(model, "in_channels", None) or (1 if gray else 3)
    desc = f"{model_name}({', '.join(f'{k}={v!r}' for k, v in self.model_kwargs.items())})"
    self.spec = _probe(model, variables, guess, probe_size, self.name, desc)
    self.channels = self.spec.channels
    self.model = model
    self.pad = pad_rule(model, self.channels)
    self.train_config: dict[str, Any] = {}  # set by load(): the run's training config

  @property
  def traces(self) -> int:
    """How often this predictor's model was traced (compiled) in this process."""
    return _TRACES[self.model]

  @property
  def is_sl(self) -> bool:
    """True when the model predicts structured-light patterns."""
    return self.spec.is_sl

  def describe(self) -> str:
    """One line naming the model and the resolution mode, for reports."""
    if self.mode == "resize":
      return (f"{self.model_name}: resized to the training size {self.train_size[0]}x"
              f"{self.train_size[1]} and back (bilinear, disparity scaled by the width ratio)")
    return f"{self.model_name}: full resolution, padded to a {self.pad.describe()}"

  def __call__(self, left: np.ndarray, right: np.ndarray,
               calib: Any = None) -> dict[str, np.ndarray]:
    """Predicts disparity (and patterns) for a pair; `calib` is accepted and unused."""
    del calib
    lf, rf, batched = prepare_pair(left, right, self.channels, self.name)
    b, h, w, _ = lf.shape
    if self.mode == "pad":
      lin, rin, ph = pad_pair(lf, rf, self.pad)
    else:
      th, tw = self.train_size
      lin = np.stack([resize_image(x, (th, tw)) for x in lf])
      rin = np.stack([resize_image(x, (th, tw)) for x in rf])
    raw = forward(self.model, self.variables, lin, rin, self.split_twin,
                  self.kernels.forward_ynn)
    out = {k: np.asarray(v, dtype=np.float32) for k, v in raw.items()}

    if self.mode == "pad":
      out = {k: v[:, ph:, :w] for k, v in out.items()}
    if "patterns_right" in out:  # unet-sl: disparity by correlating the predicted patterns
      window = {} if self.sl_window is None else {"window": self.sl_window}
      disp, _, conf = sl_disparity(out["patterns"], out["patterns_right"],
                                   max_disp=self.sl_max_disp, confidence=True, **window)
      out["disparity"], out["confidence"] = disp, conf
    elif "patterns" in out:  # mean |2p - 1| over patterns: 1 - sljax.corr's uncertainty
      out["confidence"] = 1.0 - view_uncertainty(out["patterns"])
    if self.mode == "resize":
      scale = w / out["disparity"].shape[2]
      out = {k: _resize_maps(v, (h, w)) for k, v in out.items()}
      out["disparity"] = out["disparity"] * np.float32(scale)
    out = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in out.items()}
    return out if batched else {k: v[0] for k, v in out.items()}


def make_predictor(model_name: str, model_kwargs: dict, variables: dict, train_size: Any = None,
                   mode: str = "pad", *, gray: bool | None = None, sl_max_disp: int | None = None,
                   sl_window: int | None = None, name: str | None = None,
                   kernels: "tune.KernelChoice" = tune.DEFAULT,
                   conv_impl: str | None = None) -> Predictor:
  """Predictor for a model built by sljax.nets.build_model(model_name, **model_kwargs)."""
  model = build_model(model_name, **dict(model_kwargs or {}), conv_impl=conv_impl)
  return Predictor(model, variables, model_name=model_name, model_kwargs=model_kwargs,
                   train_size=train_size, mode=mode, gray=gray, sl_max_disp=sl_max_disp,
                   sl_window=sl_window, name=name, kernels=kernels)


def load(checkpoint: str | os.PathLike, mode: str = "pad", maxdisp: int | None = None,
         tune_kernels: bool | None = None, kernels: tune.KernelChoice | None = None,
         conv_impl: str | None = None) -> Predictor:
  """Predictor from a training workdir, its checkpoints dir, or a converted PSMNet dir.

  maxdisp (optional) replaces the disparity range: the cost volume's depth for psmnet and
  psmnet-mtl (a multiple of 16; the weights do not depend on it), the correlation's search
  range u for unet-sl (in the pixels the network sees); unet-disp has none.
  tune_kernels: use this CPU's tuned compiler choice (sljax.tune; measured on first use and
  cached); None follows $SLJAX_TUNE (on unless 0), False keeps XLA's defaults. kernels, when
  given, is the choice itself (e.g. the one a run trained with) and nothing is tuned.
  conv_impl: the convolution kernels (sljax.kernels.IMPLS; None: $SLJAX_CONV3D's default).
  """
  if not isinstance(checkpoint, (str, os.PathLike)) or not os.fspath(checkpoint):
    raise SljaxError(f"checkpoint must be a folder path (a training workdir, its checkpoints "
                     f"folder or a converted PSMNet), got {short_repr(checkpoint)}")
  if mode not in MODES:  # before the (slow) checkpoint read
    raise SljaxError(f"mode must be one of {MODES}, got {mode!r}")
  if tune_kernels is not None and not isinstance(tune_kernels, (bool, np.bool_)):
    raise SljaxError(f"tune_kernels must be True, False or None, got {tune_kernels!r}")
  if kernels is not None and not isinstance(kernels, tune.KernelChoice):
    raise SljaxError("kernels must be a sljax.tune.KernelChoice or None, got "
                     f"{short_repr(kernels)}")
  path = os.fspath(checkpoint)
  model_name, model_kwargs, variables, config = load_for_inference(path)
  config = dict(config or {})
  sl_max_disp = None
  if maxdisp is not None:
    # bool is an int: True would silently become a range of 1 px
    if (not isinstance(maxdisp, (int, np.integer)) or isinstance(maxdisp, (bool, np.bool_))
        or maxdisp <= 0):
      raise SljaxError(f"maxdisp must be a positive integer, got {maxdisp!r}")
    spec = registry.spec(model_name)
    if "maxdisp" in spec.options:
      model_kwargs = dict(model_kwargs, maxdisp=int(maxdisp))
    elif "sl_logits_right" in spec.outputs:  # disparity by correlating both views' patterns
      sl_max_disp = int(maxdisp)
    else:
      raise SljaxError(f"{path}: maxdisp does not apply to {model_name} (it predicts disparity "
                       "directly, as a fraction of the image width)")
  predictor = make_predictor(model_name, model_kwargs, variables, train_size=config.get("size"),
                             mode=mode, gray=config.get("gray"), sl_max_disp=sl_max_disp,
                             sl_window=config.get("corr_window"), name=path,
                             kernels=kernels or tune.choice(tune_kernels), conv_impl=conv_impl)
  predictor.train_config = config
  return predictor
