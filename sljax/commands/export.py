"""`sljax export MODEL OUT --size HxW`: the inference function as a jax.export artifact, or as
an ONNX model checked by ONNX Runtime when OUT ends in .onnx (sljax.deploy.onnx)."""

import argparse
from pathlib import Path

from sljax import inference
from sljax.deploy import stablehlo
from sljax.deploy import onnx as onnx_export
from sljax.errors import SljaxError


def register(subparsers) -> None:
  """Adds the `export` subcommand."""
  p = subparsers.add_parser(
      "export",
      description="Traces the inference of a trained model (a training workdir, its checkpoints "
                  "folder or a converted PSMNet folder) for left and right views of HEIGHTxWIDTH "
                  "pixels and any batch size, in pad or resize mode, with the weights baked in, "
                  "and writes it with jax.export (StableHLO) to OUT, plus a JSON sidecar beside "
                  "it (OUT with the suffix .json: input size, channels, mode, outputs, scaling). "
                  "Load and run it with jax alone: exp = jax.export.deserialize(open(OUT, "
                  "'rb').read()); out = exp.call(left, right), left and right float32 "
                  "BxHxWxC in [0, 1]. The artifact is lowered for CPU and CUDA GPU (and the platform it "
                  "is made on). An OUT ending in .onnx writes ONNX instead (opset 18, dynamic "
                  "batch; needs pip install -e \".[onnx]\") and OUT.json beside it; the export "
                  "is checked by ONNX Runtime against JAX on a rendered pair, and nothing is "
                  "written if they differ by more than 0.01 px.")
  p.add_argument("model", metavar="MODEL",
                 help="a training workdir, its checkpoints folder or a converted PSMNet folder")
  p.add_argument("out", metavar="OUT",
                 help="the file to write, e.g. psmnet_1024x1280.jax, or psmnet_1024x1280.onnx "
                      "for ONNX")
  p.add_argument("--size", required=True, metavar="HxW",
                 help="input height x width in pixels, e.g. 1024x1280")
  p.add_argument("--mode", choices=("pad", "resize"), default="pad",
                 help="pad (default): full resolution, padded as the PSMNet reference pads; "
                      "resize: at the training size and back (fixed in the artifact)")
  p.add_argument("--maxdisp", type=int, default=None,
                 help="psmnet/psmnet-mtl: the cost volume's depth (a multiple of 16; default: "
                      "the model's)")
  p.add_argument("--search-range", type=int, default=None, metavar="PX",
                 help="unet-sl: the correlation's search range (default: sljax.corr's)")
  p.add_argument("--overwrite", action="store_true", help="replace OUT and its sidecar")
  p.set_defaults(func=run)


def run(args) -> int:
  """Exports and prints what was written."""
  size = stablehlo.parse_size(args.size)
  if args.model == "sgbm":
    raise SljaxError("MODEL sgbm: the OpenCV baseline is not a JAX model; nothing to export")
  if not Path(args.model).exists():
    raise SljaxError(f"MODEL {args.model}: unknown model: no such checkpoint, training workdir "
                     "or converted PSMNet folder")
  onnx = Path(args.out).suffix.lower() == ".onnx"
  if onnx:
    onnx_export.require()  # before the (slow) loading
  out = Path(args.out)
  side = onnx_export.sidecar_path(out) if onnx else stablehlo.sidecar_path(out)
  for p in (out, side):  # before the (slow) loading and tracing
    if p.exists() and not args.overwrite:
      raise SljaxError(f"{p}: exists (pass --overwrite to replace it)")
  predictor = inference.load(args.model, mode=args.mode, maxdisp=args.maxdisp,
                             search_range=args.search_range)
  if onnx:
    out, side, _ = onnx_export.write_onnx(predictor, size, out, args.model,
                                          overwrite=args.overwrite, log=print)
  else:
    out, side = stablehlo.write_export(predictor, size, out, args.model, overwrite=args.overwrite)
  print(f"wrote {out} ({out.stat().st_size / 2**20:.2f} MiB, {predictor.describe()}) and {side}")
  return 0
