"""A trained network as a function of a stereo pair: `Predictor`, built from a ModelConfig and
its variables, and `load`, which builds one from a training workdir or a converted PSMNet.

Resolution modes:
- "pad" (the PSMNet reference's test protocol; sljax.inference.padding): full resolution,
  padded at the top and right to the network's multiple, the outputs cropped back.
- "resize" (the paper's evaluation): the pair is resized to the training size with the
  training loader's resampling (area when shrinking, bilinear when enlarging), the outputs are
  resized back bilinearly, and disparities are multiplied by input width / training width.

Outputs: dict with "disparity" (HxW float32, input pixels; BxHxW for batched input) and, for
structured-light networks, "patterns" (left-view probabilities HxWxt), "patterns_right"
(unet-sl) and "confidence" (HxW in [0, 1], higher is surer: the correlation's peak-ratio
confidence for unet-sl, whose disparity is the windowed correlation of its predicted patterns,
and the mean pattern certainty |2p - 1| for psmnet-mtl).
"""

import dataclasses
import os
from typing import Any

import jax
import numpy as np

from sljax.corr.correlation import sl_disparity
from sljax.corr.uncertainty import view_uncertainty
from sljax.data.dataset import resize_image
from sljax.errors import SljaxError
from sljax.inference.inputs import prepare_pair, resize_maps, short_repr
from sljax.inference.padding import pad_pair, pad_rule
from sljax.inference.programs import PROGRAMS, forward
from sljax.io.sizes import as_size
from sljax.models.load import load_for_inference
from sljax.nets.model_config import ModelConfig
from sljax.runtime import choices

MODES = ("pad", "resize")


@dataclasses.dataclass(frozen=True)
class PredictOptions:
  """How a Predictor runs its network.

  mode: "pad" or "resize" (module docstring); train_size: (H, W) the network trained at
  (resize mode needs it); search_range: unet-sl's correlation search range in the pixels the
  network sees (None: sljax.corr's default); window: unet-sl's correlation window (None: the
  paper's 17); split_twin: psmnet-mtl as two programs (None: when large; programs.py);
  kernels: XLA's compiler choices (sljax.runtime.choices; its forward one applies); name: for messages.
  """
  mode: str = "pad"
  train_size: tuple[int, int] | None = None
  search_range: int | None = None
  window: int | None = None
  split_twin: bool | None = None
  kernels: choices.KernelChoice = choices.DEFAULT
  name: str | None = None

  def __post_init__(self):
    if self.mode not in MODES:
      raise SljaxError(f"mode must be one of {MODES}, got {self.mode!r}")
    if not isinstance(self.kernels, choices.KernelChoice):  # else it fails only at the first call
      raise SljaxError(f"kernels must be a sljax.runtime.choices.KernelChoice, got "
                       f"{short_repr(self.kernels)}")
    object.__setattr__(self, "train_size", as_size(self.train_size, "train_size"))


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


def check_variables(config: ModelConfig, model, variables: dict, size: tuple[int, int],
                    name: str) -> None:
  """SljaxError naming the first variable the network built from `config` lacks or shapes
  differently (a checkpoint of another network, width or channel count)."""
  try:
    shapes = PROGRAMS.variable_shapes(model, config.in_channels, *size)
  except MemoryError as e:  # e.g. a huge maxdisp: not a mismatch of the checkpoint
    raise SljaxError(f"{name}: cannot build the model {config.net}: out of memory "
                     f"({str(e).splitlines()[0][:200]})") from None
  # Every collection the network creates (params, batch_stats) must be in the variables.
  diff = _tree_diff(dict(shapes), {k: variables[k] for k in shapes.keys() if k in variables})
  if diff is not None:
    kwargs = ", ".join(f"{k}={v!r}" for k, v in config.saved_kwargs.items())
    raise SljaxError(f"{name}: the checkpoint's variables do not match the model "
                     f"{config.net}({kwargs}) ({diff})")


class Predictor:
  """predict(left, right) -> dict of numpy outputs; see the module docstring."""

  def __init__(self, config: ModelConfig, variables: dict,
               options: PredictOptions = PredictOptions()):
    if not isinstance(config, ModelConfig):
      raise SljaxError(f"Predictor needs a sljax.nets.ModelConfig, got {short_repr(config)}")
    self.config, self.options = config, options
    self.name = options.name or config.net
    if options.mode == "resize" and options.train_size is None:
      raise SljaxError(f"{self.name}: resize mode needs the training size, which the "
                       "checkpoint's config lacks; use --mode pad (full resolution)")
    self.model = config.build()
    self.variables = jax.tree_util.tree_map(jax.numpy.asarray, variables)  # on device once
    check_variables(config, self.model, self.variables, options.train_size or (256, 256),
                    self.name)
    self.pad = pad_rule(config, self.model)
    self.train_config: dict[str, Any] = {}  # set by load(): the run's training config

  def with_options(self, **changes: Any) -> "Predictor":
    """The same network and variables with some options changed (nothing recompiled)."""
    other = Predictor.__new__(Predictor)
    other.__dict__.update(self.__dict__)
    other.options = dataclasses.replace(self.options, **changes)
    other.name = other.options.name or self.config.net
    return other

  @property
  def mode(self) -> str:
    """"pad" or "resize"."""
    return self.options.mode

  @property
  def train_size(self) -> tuple[int, int] | None:
    """(H, W) the network trained at."""
    return self.options.train_size

  @property
  def channels(self) -> int:
    """Input channels per view."""
    return self.config.in_channels

  @property
  def model_name(self) -> str:
    """The registry name of the network."""
    return self.config.net

  @property
  def model_kwargs(self) -> dict[str, Any]:
    """The network's build options, as a checkpoint's config.json keeps them."""
    return self.config.saved_kwargs

  @property
  def is_sl(self) -> bool:
    """True when the network predicts structured-light patterns."""
    return "sl_logits" in self.config.spec.outputs

  @property
  def traces(self) -> int:
    """How often this predictor's network was traced (compiled) in this process."""
    return PROGRAMS.traces(self.model)

  def describe(self) -> str:
    """One line naming the network and the resolution mode, for reports."""
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
    raw = forward(self.config, self.model, self.variables, lin, rin, self.options.split_twin,
                  self.options.kernels.forward_ynn)
    out = {k: np.asarray(v, dtype=np.float32) for k, v in raw.items()}
    if self.mode == "pad":
      out = {k: v[:, ph:, :w] for k, v in out.items()}
    if "patterns_right" in out:  # unet-sl: disparity by correlating the predicted patterns
      window = {} if self.options.window is None else {"window": self.options.window}
      disp, _, conf = sl_disparity(out["patterns"], out["patterns_right"],
                                   max_disp=self.options.search_range, confidence=True,
                                   **window)
      out["disparity"], out["confidence"] = disp, conf
    elif "patterns" in out:  # mean |2p - 1| over patterns: 1 - sljax.corr's uncertainty
      out["confidence"] = 1.0 - view_uncertainty(out["patterns"])
    if self.mode == "resize":
      scale = w / out["disparity"].shape[2]
      out = {k: resize_maps(v, (h, w)) for k, v in out.items()}
      out["disparity"] = out["disparity"] * np.float32(scale)
    out = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in out.items()}
    return out if batched else {k: v[0] for k, v in out.items()}


def model_config(model_name: str, model_kwargs: dict, gray: bool | None = None,
                 conv_impl: str | None = None) -> ModelConfig:
  """The ModelConfig of saved build options (config.json's model_kwargs); checkpoints written
  before in_channels was saved take it from `gray`, else the network's default input."""
  kwargs = dict(model_kwargs or {})
  if "in_channels" not in kwargs and gray is not None:
    kwargs["in_channels"] = 1 if gray else 3
  return ModelConfig.of(model_name, **kwargs, conv_impl=conv_impl)


def make_predictor(model_name: str, model_kwargs: dict, variables: dict, *,
                   gray: bool | None = None, conv_impl: str | None = None,
                   **options: Any) -> Predictor:
  """Predictor for build_model(model_name, **model_kwargs); options are PredictOptions'."""
  return Predictor(model_config(model_name, model_kwargs, gray, conv_impl), variables,
                   PredictOptions(**options))


def _check_range(value: Any, what: str) -> None:
  """A positive integer (bool is an int: True would silently become a range of 1 px)."""
  if (not isinstance(value, (int, np.integer)) or isinstance(value, (bool, np.bool_))
      or value <= 0):
    raise SljaxError(f"{what} must be a positive integer, got {value!r}")


def load(checkpoint: str | os.PathLike, mode: str = "pad", maxdisp: int | None = None,
         tune_kernels: bool | None = None, kernels: choices.KernelChoice | None = None,
         conv_impl: str | None = None, search_range: int | None = None) -> Predictor:
  """Predictor from a training workdir, its checkpoints dir, or a converted PSMNet dir.

  maxdisp (PSMNets) replaces the cost volume's depth (a multiple of 16; the weights do not
  depend on it). search_range (unet-sl) is the correlation's search range in the pixels the
  network sees. tune_kernels: use this CPU's compiler choice (sljax.runtime.choices: `sljax tune`'s
  measurement, else its CPU kind's); None follows $SLJAX_TUNE (on unless 0), False keeps XLA's defaults.
  kernels, when given, is the choice itself (e.g. the one a run trained with) and nothing is
  tuned. conv_impl: the convolution kernels (sljax.kernels.IMPLS; None: $SLJAX_CONV3D's).
  """
  if not isinstance(checkpoint, (str, os.PathLike)) or not os.fspath(checkpoint):
    raise SljaxError(f"checkpoint must be a folder path (a training workdir, its checkpoints "
                     f"folder or a converted PSMNet), got {short_repr(checkpoint)}")
  if mode not in MODES:  # before the (slow) checkpoint read
    raise SljaxError(f"mode must be one of {MODES}, got {mode!r}")
  if tune_kernels is not None and not isinstance(tune_kernels, (bool, np.bool_)):
    raise SljaxError(f"tune_kernels must be True, False or None, got {tune_kernels!r}")
  if kernels is not None and not isinstance(kernels, choices.KernelChoice):
    raise SljaxError("kernels must be a sljax.runtime.choices.KernelChoice or None, got "
                     f"{short_repr(kernels)}")
  for value, what in ((maxdisp, "maxdisp"), (search_range, "search_range")):
    if value is not None:
      _check_range(value, what)
  path = os.fspath(checkpoint)
  model_name, model_kwargs, variables, saved = load_for_inference(path, fallback=True)
  saved = dict(saved or {})
  config = model_config(model_name, model_kwargs, saved.get("gray"), conv_impl)
  spec = config.spec
  if maxdisp is not None:
    if "maxdisp" not in spec.options:
      where = ("it matches its patterns by correlation: give search_range (predict: "
               "--search-range)" if "sl_logits_right" in spec.outputs else
               "it predicts disparity directly, as a fraction of the image width")
      raise SljaxError(f"{path}: maxdisp is a PSMNet's cost volume depth; {model_name} has "
                       f"none ({where})")
    config = dataclasses.replace(config, maxdisp=int(maxdisp))  # checked: registry's rule
  if search_range is not None and "sl_logits_right" not in spec.outputs:
    raise SljaxError(f"{path}: search_range is unet-sl's correlation range; {model_name} has "
                     "none" + (" (its cost volume depth is maxdisp)"
                               if "maxdisp" in spec.options else ""))
  options = PredictOptions(mode=mode, train_size=saved.get("size"),
                           search_range=search_range, window=saved.get("corr_window"),
                           kernels=kernels or choices.choice(tune_kernels), name=path)
  predictor = Predictor(config, variables, options)
  predictor.train_config = saved
  return predictor
