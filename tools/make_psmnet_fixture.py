"""Writes tests/data/psmnet_reference.npz: the reference PSMNet's outputs for the recipe weights.

Runs JiaRenChang/PSMNet's own models/stackhourglass.py on PyTorch (CPU) with the weights of
tests/reference_weights.py on that module's inputs (tests/reference_weights.CASES) and stores
what tests/test_reference_psmnet.py compares sljax with. Run it by hand when the recipe or the
cases change; CI only reads the stored file (and needs neither torch nor the reference).

  git clone https://github.com/JiaRenChang/PSMNet ~/src/PSMNet   # yourself; never fetched here
  pip install torch                                            # CPU is enough; not an sljax dependency
  python tools/make_psmnet_fixture.py ~/src/PSMNet

What runs, per case (eval, pad and the 256x256 "full" case in evaluation mode, "train" in
training mode with batch statistics):

* The images are normalised with the ImageNet mean and std (the reference's data loaders);
  the "pad" case then pads the normalised tensor with 0 at the top and right to a multiple of
  16 and crops the output back, exactly as the reference's Test_img.py.
* The network runs twice: in float32, as released, and in float64 (the reference allocates
  its cost volume with torch.FloatTensor; that constructor is pointed at DoubleTensor for the
  second run). The fixture stores the float64 outputs (rounded to float32) as the expected
  values and the float32 run's largest deviation from them, the reference's own rounding.
* One change to the model, and only where the reference cannot run at all: its SPP pools have
  fixed kernels 64, 32, 16, 8, and PyTorch refuses a kernel larger than the 1/4-resolution
  map, so for inputs under 256x256 each branch's AvgPool2d is replaced by one whose kernel is
  min(kernel, map size) per axis: sljax's documented rule (sljax/nets/psmnet.py, "SPP on other
  sizes"). The 256x256 case runs the reference untouched.
* "train" also stores every BatchNorm's running mean and variance after the forward pass
  (momentum 0.1, unbiased variance; the feature extractor runs twice, left then right), in the
  order of tests/data/psmnet_keys.txt.

Also stored: the reference's commit (git rev-parse HEAD in the checkout, or --commit), the
torch and NumPy versions, the recipe's seed and fingerprint, and the softmax's mean peak
probability per case (a check that the recipe keeps the disparity distribution soft).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
import reference_weights as rw  # noqa: E402  (the recipe shared with the test)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
SPP_POOLS = (64, 32, 16, 8)  # branch1..branch4 of the reference


def load_reference(directory: Path):
  """The reference's PSMNet class (models/stackhourglass.py), importable on a CPU."""
  import torch
  if not (directory / "models" / "stackhourglass.py").is_file():
    raise SystemExit(f"{directory}: no models/stackhourglass.py here; pass a checkout of "
                     "JiaRenChang/PSMNet")
  warnings.filterwarnings("ignore", message=".*upsample.*")  # deprecated, used by the reference
  torch.Tensor.cuda = lambda self, *a, **k: self  # the reference moves its buffers by hand
  sys.path.insert(0, str(directory))
  from models.stackhourglass import PSMNet  # pylint: disable=import-outside-toplevel
  return PSMNet


def reference_commit(directory: Path, given: str | None) -> str:
  """The checkout's HEAD commit (or the one given on the command line)."""
  if given:
    return given
  try:
    return subprocess.run(["git", "-C", str(directory), "rev-parse", "HEAD"], check=True,
                          capture_output=True, text=True).stdout.strip()
  except (OSError, subprocess.CalledProcessError):
    raise SystemExit(f"{directory} is not a git checkout; pass --commit HASH") from None


def build(psmnet_cls, case: rw.Case, dtype):
  """The reference model with the recipe's weights, pools adapted to small maps."""
  import torch
  model = psmnet_cls(case.maxdisp)
  sd = {k: torch.from_numpy(v) for k, v in rw.state_dict().items()}
  missing, unexpected = model.load_state_dict(sd, strict=False)
  assert not unexpected and all(k.endswith("num_batches_tracked") for k in missing), (
      missing, unexpected)
  h4, w4 = (-(-s // 4) for s in case.padded)
  fe = model.feature_extraction
  for i, k in enumerate(SPP_POOLS, start=1):
    kernel = (min(k, h4), min(k, w4))
    if kernel != (k, k):
      getattr(fe, f"branch{i}")[0] = torch.nn.AvgPool2d(kernel, stride=kernel)
  return model.to(dtype)


def normalised(x: np.ndarray, dtype):
  """BxHxWx3 [0, 1] -> normalised BxCxHxW tensor."""
  import torch
  x = (x - np.asarray(IMAGENET_MEAN, np.float32)) / np.asarray(IMAGENET_STD, np.float32)
  return torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2))).to(dtype)


def run_case(psmnet_cls, case: rw.Case, double: bool) -> dict[str, np.ndarray]:
  """The reference's outputs for one case (and its BN statistics and costs)."""
  import torch
  dtype = torch.float64 if double else torch.float32
  saved = torch.FloatTensor
  if double:
    torch.FloatTensor = torch.DoubleTensor  # the cost volume the reference allocates
  try:
    model = build(psmnet_cls, case, dtype)
    costs = {}
    for name in ("classif1", "classif2", "classif3"):
      getattr(model, name).register_forward_hook(
          lambda m, i, o, name=name: costs.__setitem__(name, o.detach()))
    left, right = (normalised(x, dtype) for x in rw.images(case))
    top = right_pad = 0
    if case.pad:
      (hp, wp), (h, w) = case.padded, (case.height, case.width)
      top, right_pad = hp - h, wp - w
      left, right = (torch.nn.functional.pad(x, (0, right_pad, top, 0)) for x in (left, right))
    out = {}
    if case.train:
      model.train()
      preds = model(left, right)
      out["disparities"] = np.stack([p.detach().numpy().reshape(case.batch, *case.padded)
                                     for p in preds])
      sd = model.state_dict()
      keys = rw.reference_shapes()
      out["running_mean"] = np.concatenate(
          [sd[k].numpy().ravel() for k in keys if k.endswith("running_mean")])
      out["running_var"] = np.concatenate(
          [sd[k].numpy().ravel() for k in keys if k.endswith("running_var")])
    else:
      model.eval()
      with torch.no_grad():
        pred = model(left, right).numpy().reshape(case.batch, *case.padded)
      out["disparity"] = pred[:, top:, :pred.shape[2] - right_pad]  # Test_img.py's crop
    # Softness: the mean over pixels of the largest softmax probability of the final costs.
    c = costs["classif1"] + costs["classif2"] + costs["classif3"]
    c = torch.nn.functional.interpolate(c, [case.maxdisp, *case.padded], mode="trilinear")
    out["peak"] = np.asarray(torch.softmax(c[:, 0], 1).max(1).values.mean().item())
  finally:
    torch.FloatTensor = saved
  return {k: np.asarray(v, np.float64) for k, v in out.items()}


def main(argv=None):
  """Command line: see the module docstring."""
  p = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
  p.add_argument("reference", type=Path, help="a checkout of JiaRenChang/PSMNet")
  p.add_argument("--out", type=Path, default=rw.FIXTURE_FILE)
  p.add_argument("--commit", help="the reference's commit, where the checkout has no .git")
  args = p.parse_args(argv)
  import torch
  torch.set_num_threads(1)
  torch.manual_seed(0)  # nothing random should run; this only pins it if something does
  directory = args.reference.expanduser().resolve()
  psmnet_cls = load_reference(directory)
  arrays, meta_cases = {}, {}
  for case in rw.CASES:
    ref64 = run_case(psmnet_cls, case, double=True)
    ref32 = run_case(psmnet_cls, case, double=False)
    for k, v in ref64.items():
      if k != "peak":
        if k.startswith("disparit"):
          v = v[..., ::case.row_step, :]
        arrays[f"{case.name}/{k}"] = v.astype(np.float32)
    f32_err = {k: float(np.abs(ref32[k] - v).max()) for k, v in ref64.items() if k != "peak"}
    meta_cases[case.name] = {"peak": float(ref64["peak"]), "float32_error": f32_err}
    print(f"{case.name}: peak probability {float(ref64['peak']):.3f}, float32 vs float64 "
          + ", ".join(f"{k} {e:.2e}" for k, e in f32_err.items()), flush=True)
  meta = {"reference": "https://github.com/JiaRenChang/PSMNet models/stackhourglass.py",
          "commit": reference_commit(directory, args.commit), "torch": torch.__version__,
          "numpy": np.__version__, "seed": rw.SEED, "fingerprint": rw.fingerprint(),
          "cases": meta_cases}
  arrays["meta"] = np.asarray(json.dumps(meta, sort_keys=True))
  args.out.parent.mkdir(parents=True, exist_ok=True)
  np.savez_compressed(args.out, **arrays)
  print(f"wrote {args.out} ({args.out.stat().st_size / 1024:.0f} KiB): {json.dumps(meta)}")


if __name__ == "__main__":
  main()
