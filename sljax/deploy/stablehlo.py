"""A deployable file: the inference function as serialised StableHLO (jax.export).

`export_model(predictor, (H, W))` traces, for inputs of exactly H x W pixels and any batch size
(a symbolic dimension), what `sljax.inference.Predictor` computes in its resolution mode, with
the trained variables baked in as constants:

- pad: the views are padded at the top and right per the model's `pad_rule`, the network runs
  and the outputs are cropped back;
- resize: the views are resized to the training size and the outputs back, with the same
  linear maps as the predictor (OpenCV's area / bilinear resampling, read off as per-axis
  matrices by resizing impulses, and checked to be separable), and disparities are multiplied
  by the width ratio;
- structured-light outputs: pattern probabilities; for unet-sl the disparity and confidence of
  the windowed correlation of its patterns (the shift-major JAX formulation of sljax.corr, which
  equals the predictor's row path for 0/1 patterns and may pick the other shift only at
  float32 near-ties), for psmnet-mtl the mean pattern certainty as confidence.

The artifact takes float32 BxHxWxC views in [0, 1] with the model's channel count (the
conversions the predictor does on the host, from uint8 / uint16 and between gray and RGB, are
the caller's) and returns a dict of float32 arrays. It is lowered for CPU and CUDA GPUs
(`PLATFORMS`, and for the maker's platform where that is another) wherever it is made, so an
artifact written on a GPU machine runs on a laptop and the reverse (one made for the maker's
platform alone failed there, seen on an H100). On an NVIDIA GPU it runs at XLA's default
precision, which lets convolutions use TF32 (docs/benchmarks/gpu.md). Loading it
needs only jax (and numpy for the data):

  exp = jax.export.deserialize(open("model.jax", "rb").read())
  out = exp.call(left, right)

A JSON sidecar (`sidecar_path`) records the input size, channels, mode, output names and shapes,
and how to scale inputs and outputs.
"""

import json
import os
from numbers import Integral
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import export as jex

from sljax import inference
from sljax.corr import correlation
from sljax.data.dataset import resize_image
from sljax.errors import SljaxError
from sljax.inference.inputs import resize_maps
from sljax.inference.programs import outputs
from sljax.io import files, sizes

FORMAT = "sljax-export"
PLATFORMS = ("cpu", "cuda")  # lowered for both wherever it is exported
SEPARABLE_TOLERANCE = 1e-5


def parse_size(text: str) -> tuple[int, int]:
  """'480x640' (height x width) -> (480, 640); SljaxError for anything else."""
  return sizes.parse_size(text, "--size", square=False)  # an artifact's shape is spelt out


def check_size(size: Any) -> tuple[int, int]:
  """(H, W) as positive ints; SljaxError naming `size` for anything else (an int, a string, an
  empty or fractional size), which jax.export would refuse with a traceback or trace silently."""
  if isinstance(size, (str, bytes, Integral)) or not hasattr(size, "__len__") or len(size) != 2:
    raise SljaxError(f"size must be (height, width) in pixels, e.g. (480, 640), got "
                     f"{inference.short_repr(size)}")
  if not all(isinstance(v, Integral) and not isinstance(v, (bool, np.bool_)) for v in size):
    raise SljaxError(f"size must be two integers (height, width), got {inference.short_repr(size)}")
  h, w = int(size[0]), int(size[1])
  if h <= 0 or w <= 0:
    raise SljaxError(f"size {h}x{w}: height and width must be positive")
  return h, w


def check_predictor(predictor: Any) -> None:
  """SljaxError unless predictor is a sljax.inference.Predictor (else an AttributeError deep in
  the tracing)."""
  if not isinstance(predictor, inference.Predictor):
    raise SljaxError("predictor must be a sljax.inference.Predictor (sljax.inference.load(RUN)), "
                     f"got {type(predictor).__name__} {inference.short_repr(predictor)}")


def sidecar_path(out: str | os.PathLike) -> Path:
  """The JSON sidecar beside the artifact: model.jax -> model.json (model -> model.json)."""
  out = Path(out)
  return out.with_suffix(".json") if out.suffix and out.suffix != ".json" else Path(f"{out}.json")


def _axis_matrices(resize: Callable[[np.ndarray], np.ndarray], h: int, w: int,
                   chunk: int = 4) -> tuple[np.ndarray, np.ndarray]:
  """(M_h, M_w) with resize(x)[..., c] = M_h @ x[..., c] @ M_w.T, read off impulse images.

  Row impulse i (ones along row i) comes back as column i of M_h in every output column
  (resampling weights sum to 1); likewise for columns. Channels carry `chunk` impulses at once
  (OpenCV's area resampling takes at most 4 channels).
  """
  def read(n: int, make, take) -> np.ndarray:
    cols = []
    for start in range(0, n, chunk):
      k = min(chunk, n - start)
      img = np.zeros((h, w, k), np.float32)
      for j in range(k):
        make(img, start + j, j)
      cols.append(take(resize(img)))
    return np.concatenate(cols, axis=1).astype(np.float32)

  def set_row(img, i, j):
    img[i, :, j] = 1.0

  def set_col(img, i, j):
    img[:, i, j] = 1.0
  mh = read(h, set_row, lambda r: r[:, 0, :])
  mw = read(w, set_col, lambda r: r[0, :, :])
  return mh, mw


def _checked_matrices(resize, h: int, w: int, what: str) -> tuple[np.ndarray, np.ndarray]:
  """_axis_matrices, verified on a random image (the resampling must be separable and linear)."""
  mh, mw = _axis_matrices(resize, h, w)
  x = np.random.default_rng(0).uniform(0, 1, (h, w, 1)).astype(np.float32)
  want = resize(x)[..., 0]
  got = mh @ x[..., 0] @ mw.T
  err = float(np.abs(got - want).max())
  if err > SEPARABLE_TOLERANCE:
    raise SljaxError(f"{what}: the resampling is not a separable linear map (error {err:.2g}); "
                     "export in pad mode instead")
  return mh, mw


def _resize_to(x, mh: np.ndarray, mw: np.ndarray):
  """BxHxW(xC) -> Bx h' x w' (xC) with fixed per-axis matrices."""
  if x.ndim == 3:
    return jnp.einsum("ph,bhw,qw->bpq", mh, x, mw)
  return jnp.einsum("ph,bhwc,qw->bpqc", mh, x, mw)


def inference_function(predictor, size: tuple[int, int]) -> Callable:
  """f(left, right) -> outputs dict for BxHxWxC float32 views of the given size (see above)."""
  check_predictor(predictor)
  h, w = check_size(size)
  model, variables, c = predictor.model, predictor.variables, predictor.channels
  variables = jax.tree_util.tree_map(jnp.asarray, variables)
  mode = predictor.mode
  if mode == "pad":
    rule = predictor.pad
    ph, pw = -h % rule.multiple, -w % rule.multiple
    fill = jnp.asarray(np.asarray(rule.fill, np.float32))
    net_hw = (h + ph, w + pw)
  else:
    net_hw = predictor.train_size
    in_h, in_w = _checked_matrices(lambda x: resize_image(x, net_hw), h, w, "input resize")
    out_h, out_w = _checked_matrices(
        lambda x: resize_maps(x[None], (h, w))[0], *net_hw, "output resize")
    scale = np.float32(w / net_hw[1])

  def prepare(x):
    if mode == "resize":
      return _resize_to(x, in_h, in_w)
    if not (ph or pw):
      return x
    # A pad and a select (not a scatter into a filled canvas): the same values, and operators
    # that ONNX takes with a dynamic batch (sljax.deploy).
    inside = np.zeros((1, h + ph, w + pw, 1), bool)
    inside[:, ph:, :w] = True
    return jnp.where(inside, jnp.pad(x, ((0, 0), (ph, 0), (0, pw), (0, 0))), fill)

  sl_u = predictor.options.search_range
  sl_window = predictor.options.window or correlation.PAPER_WINDOW

  def f(left, right):
    # The predictor's order: crop (pad mode), then correlate or score the patterns, then resize
    # back (resize mode).
    out = outputs(model, variables, prepare(left), prepare(right))
    if mode == "pad":
      out = {k: v[:, ph:, :w] for k, v in out.items()}
    if "patterns_right" in out:  # unet-sl: correlation of its predicted patterns
      ch, cw = out["patterns"].shape[1:3]
      u = correlation.default_max_disp(cw) if sl_u is None else sl_u
      block = correlation.choose_block(1, ch, cw, u)
      corr = jax.vmap(lambda a, b: correlation._single(
          a, b, u=u, window=sl_window, subpixel=False, normalized=False,
          lr_check=False, confidence=True, block=block))(out["patterns"], out["patterns_right"])
      out["disparity"], out["confidence"] = corr["disparity"], corr["confidence"]
    elif "patterns" in out:  # psmnet-mtl: mean pattern certainty |2p - 1|
      out["confidence"] = 1.0 - jnp.mean(1.0 - 2.0 * jnp.abs(out["patterns"] - 0.5), axis=-1)
    if mode == "resize":
      out = {k: _resize_to(v, out_h, out_w) for k, v in out.items()}
      out["disparity"] = out["disparity"] * scale
    return {k: v.astype(jnp.float32) for k, v in out.items()}
  return f


def export_model(predictor, size: tuple[int, int]):
  """jax.export.Exported of the predictor's inference at size (H, W), batch symbolic."""
  check_predictor(predictor)
  size = check_size(size)
  h, w = size
  c = predictor.channels
  spec = jax.ShapeDtypeStruct(jex.symbolic_shape(f"b, {h}, {w}, {c}"), np.float32)
  f = inference_function(predictor, size)
  try:
    here = jex.default_export_platform()  # ROCm or TPU: the maker's platform too
    return jex.export(jax.jit(f), platforms=tuple(dict.fromkeys(PLATFORMS + (here,))))(spec, spec)
  except SljaxError:
    raise
  except Exception as e:  # a model that cannot take this size: one line, not a JAX traceback
    raise SljaxError(f"{predictor.name}: cannot export at {h}x{w} in {predictor.mode} mode "
                     f"({type(e).__name__}: {str(e).splitlines()[0][:300]})") from None


def describe(predictor, size: tuple[int, int], source: str) -> dict[str, Any]:
  """The sidecar fields that any exported form shares: model, mode, input, scaling."""
  h, w = size
  info: dict[str, Any] = {
      "model": predictor.model_name,
      "model_kwargs": predictor.model_kwargs,
      "source": source,
      "mode": predictor.mode,
      "mode_detail": predictor.describe(),
      "input": {"names": ["left", "right"], "height": h, "width": w,
                "channels": predictor.channels, "dtype": "float32", "layout": "BxHxWxC",
                "batch": "any (symbolic)", "range": [0.0, 1.0]},
      "how_to_scale": {
          "inputs": "uint8 / 255, uint16 / 65535, float already in [0, 1]; RGB -> gray by "
                    "ITU-R BT.601 luma (0.299 R + 0.587 G + 0.114 B), gray -> RGB by "
                    "repetition, to the channel count above",
          "disparity": "pixels of the input size (left-referenced: left x matches right "
                       "x - d)",
          "depth": "Z_mm = f_px * baseline_mm / (disparity + doffs) with Middlebury calib.txt "
                   "keys (sljax.depth.geometry)",
          "patterns": "probability that the pattern is lit, per pattern (coarsest first)",
          "confidence": "in [0, 1], higher is surer",
      },
  }
  if predictor.mode == "pad":
    info["pad"] = {"multiple": predictor.pad.multiple, "fill": list(predictor.pad.fill),
                   "where": "top and right"}
  else:
    info["train_size"] = list(predictor.train_size)
  return info


def sidecar(predictor, exported, size: tuple[int, int], source: str) -> dict[str, Any]:
  """What a user needs to call the artifact, as a JSON-able dict."""
  outputs = {k: [None if not isinstance(d, int) else d for d in v.shape]
             for k, v in exported.out_tree.unflatten(exported.out_avals).items()}
  info: dict[str, Any] = {"format": FORMAT, **describe(predictor, size, source)}
  info.update({
      "outputs": outputs,
      "platforms": list(exported.platforms),
      "jax_version": jax.__version__,
      "load": ["import jax", "exp = jax.export.deserialize(open(PATH, 'rb').read())",
               "out = exp.call(left, right)"],
  })
  return info


def write_export(predictor, size: tuple[int, int], out: str | os.PathLike, source: str,
                 overwrite: bool = False) -> tuple[Path, Path]:
  """Exports and writes OUT (serialised artifact) and its JSON sidecar; returns both paths."""
  check_predictor(predictor)  # before anything is checked on disk
  size = check_size(size)
  out = Path(out)
  side = sidecar_path(out)
  files.refuse_existing([out, side], overwrite)
  exported = export_model(predictor, size)
  info = json.dumps(sidecar(predictor, exported, size, source), indent=2) + "\n"
  out.parent.mkdir(parents=True, exist_ok=True)
  # Both to temporary files first: a full disk leaves the earlier pair, never a truncated
  # artifact (the two renames follow each other, so only a kill between them can mix a pair).
  with files.replacing(out, side) as (out_tmp, side_tmp):
    out_tmp.write_bytes(exported.serialize())
    side_tmp.write_text(info, encoding="utf-8")
  return out, side
