"""`sljax export MODEL OUT.onnx`: the inference function as an ONNX model, checked by ONNX Runtime.

The function is the `.jax` artifact's (`sljax.deploy.stablehlo.inference_function`: padding or resizing,
disparity, pattern probabilities and confidence, unet-sl's correlation), traced with XLA's
plain convolutions (conv_impl "lax") whatever the machine's default, and converted by jax2onnx
(the optional extra `.[onnx]`) at opset OPSET with a symbolic batch. jax2onnx maps only 1D/2D
convolution layouts; `sljax.deploy.conv` extends its plugin for PSMNet's 3D and transposed
convolutions.

Every export is checked before anything is written: ONNX Runtime (CPU) runs the model on a
pair rendered at the export size by the built-in renderer, JAX runs the same traced function on
the CPU at "highest" matmul precision, and the largest |delta disparity| is reported. Over
TOLERANCE_PX (or a pattern / confidence over TOLERANCE_PROB) is an error and nothing is written.
unet-sl's correlation picks integer shifts, which float32 near-ties may tip either way: its
check counts the pixels whose shift differs (at most MAX_SHIFT_FLIPS of them) and requires the
others' disparity equal.

A sidecar OUT.json beside OUT (model.onnx -> model.onnx.json, never a `.jax` artifact's
model.json) holds the input and output names, layouts, shapes and scaling, and the check.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
from importlib import metadata
import json
import logging
import os
import time
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np

from sljax.deploy.stablehlo import check_predictor, check_size, describe, inference_function
from sljax.errors import SljaxError
from sljax.inference.inputs import convert_channels
from sljax.io import files
from sljax.render.synthetic import SynthConfig, render_scene

FORMAT = "sljax-onnx"
OPSET = 18  # >= 17 as asked; jax2onnx emits ReduceMean with axes as an input (18)
INSTALL = 'pip install -e ".[onnx]"  (or: pip install "sljax[onnx]")'
TOLERANCE_PX = 1e-2  # largest |delta disparity| the export accepts
TOLERANCE_PROB = 1e-3  # largest |delta| of patterns and confidence (probabilities)
MAX_SHIFT_FLIPS = 0.01  # unet-sl: the fraction of pixels whose integer shift may differ
CHECK_SEED = 0  # the rendered check pair: scene 0 of dataset seed 0
INPUT_NAMES = ("left", "right")


def require() -> None:
  """SljaxError (one line naming the install command) unless jax2onnx and onnxruntime import."""
  for name in ("onnx", "onnxruntime", "jax2onnx"):
    try:
      __import__(name)
    except ImportError:
      raise SljaxError(f"ONNX export needs the onnx extra ({name} is not installed): "
                       f"{INSTALL}") from None


def sidecar_path(out: str | os.PathLike) -> Path:
  """The ONNX sidecar: model.onnx -> model.onnx.json (a .jax artifact's is model.json)."""
  return Path(f"{os.fspath(out)}.json")


def export_form(predictor):
  """The predictor with XLA's plain convolutions (conv_impl "lax"), sharing its variables."""
  if predictor.config.conv_impl == "lax":
    return predictor
  other = predictor.with_options()
  other.config = dataclasses.replace(predictor.config, conv_impl="lax")
  other.model = other.config.build()
  return other


@dataclasses.dataclass(frozen=True)
class Traced:
  """An ONNX model (serialised) and the JAX function it was converted from."""
  model: bytes
  fn: Callable  # (left, right) -> tuple of outputs, in `names` order
  names: tuple[str, ...]
  shapes: dict[str, list]  # output name -> [None (any batch) or 1, ...]
  seconds: float
  dynamic_batch: bool


@contextlib.contextmanager
def _converter_settings():
  """jax2onnx as the export runs it: quiet, and without its quadratic transpose-pair pass.

  It logs a warning per plugin it cannot import for this jax (and onnx_ir one per untyped
  constant), and 0.12 prints a line per 2D convolution: none of it is the user's business.
  Its graph pass `remove_redundant_transpose_pairs_ir` rescans the whole graph for every node
  it looks at (`_producer_node` builds a set of all nodes per call): on PSMNet (1435 nodes, 699
  of them Transposes around the convolutions) it took 721 of 770 s at 32x32 (cProfile, a busy
  2-core Zen 4). ONNX Runtime's own transpose optimizer cancels the same pairs when a session
  loads the model, so the export skips the pass (docs/deploy.md).
  """
  from jax2onnx.converter import ir_optimizations
  loggers = [logging.getLogger(n) for n in ("jax2onnx", "onnx_ir")]
  levels = [lg.level for lg in loggers]
  skipped = ir_optimizations.remove_redundant_transpose_pairs_ir
  for lg in loggers:
    lg.setLevel(logging.ERROR)
  ir_optimizations.remove_redundant_transpose_pairs_ir = lambda graph: None
  try:
    with contextlib.redirect_stdout(io.StringIO()):
      yield
  finally:
    ir_optimizations.remove_redundant_transpose_pairs_ir = skipped
    for lg, level in zip(loggers, levels):
      lg.setLevel(level)


def trace(predictor, size: tuple[int, int]) -> Traced:
  """The predictor's inference at size (H, W) as ONNX (batch symbolic), and its JAX function."""
  require()
  import jax2onnx

  from sljax.deploy import conv
  check_predictor(predictor)
  h, w = check_size(size)
  start = time.perf_counter()
  f = inference_function(export_form(predictor), (h, w))
  c = predictor.channels
  spec = jax.ShapeDtypeStruct((1, h, w, c), np.float32)
  shapes = jax.eval_shape(f, spec, spec)
  names = tuple(sorted(shapes))

  def fn(left, right):
    out = f(left, right)
    return tuple(out[k] for k in names)
  model_name = f"sljax_{predictor.model_name}".replace("-", "_")
  failures = []
  with _converter_settings():
    conv.register()
    # A dynamic batch where the operators allow one; else batch 1 (unet-sl: jax2onnx's batching
    # rule of a primitive in the correlation needs a constant batch).
    for batch in ("B", 1):
      try:
        proto = jax2onnx.to_onnx(fn, [(batch, h, w, c)] * 2, opset=OPSET, model_name=model_name,
                                 input_names=list(INPUT_NAMES), output_names=list(names))
        break
      except Exception as e:  # one line, not the converter's traceback
        failures.append(f"{type(e).__name__}: {str(e).splitlines()[0][:300] if str(e) else ''}")
    else:
      raise SljaxError(f"{predictor.name}: cannot convert to ONNX at {h}x{w} in "
                       f"{predictor.mode} mode ({failures[-1]})")
  if batch == "B":
    drop_traced_shapes(proto)
  return Traced(proto.SerializeToString(), fn, names,
                {k: [None if batch == "B" else batch, *v.shape[1:]] for k, v in shapes.items()},
                time.perf_counter() - start, batch == "B")


def drop_traced_shapes(proto) -> int:
  """Removes the intermediate tensors' shape annotations from a model with a symbolic batch;
  returns how many. The converter writes some with the trace's batch of 1 ('bcast_out_5':
  [1, 64]), and ONNX Runtime, finding [8, 64] at batch 8, warned "Error merging shape info" at
  every load: harmless (batch 4 equals 4 x batch 1 exactly) but read as a broken model. The
  annotations are optional; runtimes infer the shapes from the inputs."""
  n = len(proto.graph.value_info)
  del proto.graph.value_info[:]
  return n


def check_pair(size: tuple[int, int], channels: int) -> tuple[np.ndarray, np.ndarray]:
  """A 1xHxWxC float32 pair from the built-in renderer (a square scene, cropped top-left)."""
  h, w = size
  scene = render_scene(0, CHECK_SEED, SynthConfig(size=max(h, w, 32)))
  views = []
  for im in (scene.im0, scene.im1):
    im = np.asarray(im, np.float32)
    im = im[..., None] if im.ndim == 2 else im
    views.append(convert_channels(np.clip(im[:h, :w], 0, 1), channels)[None])
  return views[0], views[1]


def run_onnx(model: bytes, left: np.ndarray, right: np.ndarray) -> list[np.ndarray]:
  """The model's outputs from ONNX Runtime on the CPU."""
  import onnxruntime as ort
  options = ort.SessionOptions()
  options.log_severity_level = 3
  sess = ort.InferenceSession(model, options, providers=["CPUExecutionProvider"])
  return sess.run(None, {"left": left, "right": right})


def run_jax(fn: Callable, left: np.ndarray, right: np.ndarray) -> list[np.ndarray]:
  """fn run by JAX on the CPU with float32 matmuls and convolutions at "highest" precision."""
  cpu = jax.devices("cpu")[0]
  with jax.default_device(cpu), jax.default_matmul_precision("highest"):
    return [np.asarray(v) for v in jax.jit(fn)(left, right)]


def compare(names: tuple[str, ...], got: list[np.ndarray], want: list[np.ndarray],
            shifts: bool) -> dict[str, Any]:
  """Largest |delta| per output; shifts (unet-sl): disparity as integer shifts (module doc)."""
  report: dict[str, Any] = {}
  got, want = dict(zip(names, got)), dict(zip(names, want))
  same = np.ones(want["disparity"].shape, bool)
  if shifts:
    same = got["disparity"] == want["disparity"]
    report["shift_flips"] = int((~same).sum())
    report["pixels"] = int(same.size)
  for k in names:
    if got[k].shape != want[k].shape:
      raise SljaxError(f"ONNX Runtime's {k} has shape {got[k].shape}, JAX's {want[k].shape}")
    keep = same if got[k].shape[:3] == same.shape else np.ones(got[k].shape[:3], bool)
    delta = np.abs(got[k].astype(np.float64) - want[k])[keep]
    report[f"max_abs_{k}"] = float(delta.max()) if delta.size else 0.0
  return report


def verdict(report: dict[str, Any]) -> str | None:
  """Why the check fails (None: it passes)."""
  if report.get("shift_flips", 0) > MAX_SHIFT_FLIPS * report.get("pixels", 1):
    return (f"{report['shift_flips']} of {report['pixels']} pixels' correlation shifts differ "
            f"(more than {MAX_SHIFT_FLIPS:.0%})")
  if report["max_abs_disparity"] > TOLERANCE_PX:
    return (f"largest |delta disparity| {report['max_abs_disparity']:.3g} px is over "
            f"{TOLERANCE_PX:g} px")
  for k, v in report.items():
    if k.startswith("max_abs_") and k != "max_abs_disparity" and v > TOLERANCE_PROB:
      return f"largest |delta {k[8:]}| {v:.3g} is over {TOLERANCE_PROB:g}"
  return None


def check(traced: Traced, predictor, size: tuple[int, int]) -> dict[str, Any]:
  """ONNX Runtime against JAX on a rendered pair (module doc); the report of `compare`."""
  left, right = check_pair(size, predictor.channels)
  got = run_onnx(traced.model, left, right)
  want = run_jax(traced.fn, left, right)
  return compare(traced.names, got, want, shifts="patterns_right" in traced.names)


def sidecar(predictor, traced: Traced, size: tuple[int, int], source: str,
            report: dict[str, Any]) -> dict[str, Any]:
  """What an ONNX Runtime user needs, as a JSON-able dict."""
  import onnxruntime
  h, w = size
  info: dict[str, Any] = {"format": FORMAT, **describe(predictor, size, source)}
  info.update({
      "opset": OPSET,
      "input": {"names": list(INPUT_NAMES), "height": h, "width": w,
                "channels": predictor.channels,
                "channel_order": "gray" if predictor.channels == 1 else "RGB",
                "dtype": "float32", "layout": "BxHxWxC (NHWC)",
                "batch": "any (dynamic)" if traced.dynamic_batch else 1,
                "range": [0.0, 1.0]},
      "outputs": traced.shapes,
      "output_layouts": {k: "BxHxW" if len(v) == 3 else "BxHxWxP"
                         for k, v in traced.shapes.items()},
      "converter": {"jax2onnx": metadata.version("jax2onnx"), "jax": jax.__version__,
                    "conv_impl": "lax"},
      "check": dict(report, onnxruntime=onnxruntime.__version__,
                    pair=f"sljax.render.synthetic scene 0 of seed {CHECK_SEED}, top-left "
                         f"{h}x{w}", jax="CPU, matmul precision highest"),
      "load": ["import onnxruntime as ort",
               "sess = ort.InferenceSession(PATH, providers=['CPUExecutionProvider'])",
               "disparity = sess.run(['disparity'], {'left': left, 'right': right})[0]"],
  })
  return info


def write_onnx(predictor, size: tuple[int, int], out: str | os.PathLike, source: str,
               overwrite: bool = False, log: Callable[[str], None] = lambda s: None
               ) -> tuple[Path, Path, dict[str, Any]]:
  """Converts, checks and writes OUT (ONNX) and OUT.json; returns both paths and the check.

  A failed check raises SljaxError and writes nothing (the files at OUT stay as they were)."""
  require()
  check_predictor(predictor)
  size = check_size(size)
  out = Path(out)
  side = sidecar_path(out)
  files.refuse_existing([out, side], overwrite)
  log(f"tracing {predictor.describe()} at {size[0]}x{size[1]} and converting to ONNX ...")
  traced = trace(predictor, size)
  if not traced.dynamic_batch:
    log("the batch is fixed at 1 (an operator of this model needs a constant batch)")
  log(f"converted in {traced.seconds:.1f} s; checking with ONNX Runtime against JAX on a "
      "rendered pair ...")
  report = check(traced, predictor, size)
  report["convert_seconds"] = round(traced.seconds, 2)
  flips = (f", {report['shift_flips']} of {report['pixels']} pixels' shifts differ (float32 "
           "near-ties)" if "shift_flips" in report else "")
  log(f"largest |delta disparity| ONNX Runtime vs JAX: {report['max_abs_disparity']:.3g} px"
      + flips)
  failure = verdict(report)
  if failure:
    raise SljaxError(f"{out}: not written: ONNX Runtime disagrees with JAX: {failure}")
  info = json.dumps(sidecar(predictor, traced, size, source, report), indent=2) + "\n"
  out.parent.mkdir(parents=True, exist_ok=True)
  with files.replacing(out, side) as (out_tmp, side_tmp):
    out_tmp.write_bytes(traced.model)
    side_tmp.write_text(info, encoding="utf-8")
  return out, side, report
