"""The deterministic PSMNet weights and inputs behind tests/data/psmnet_reference.npz (NumPy only).

Used by tools/make_psmnet_fixture.py (which runs JiaRenChang/PSMNet's models/stackhourglass.py
on PyTorch with these weights and stores its outputs) and by tests/test_reference_psmnet.py
(which rebuilds the same weights, converts them with sljax.nets.convert and compares). No
weights are stored: they are a function of SEED and of the key order in psmnet_keys.txt.

Recipe, per tensor, in the order of tests/data/psmnet_keys.txt (the reference state_dict's
order), tensor i drawn from np.random.Generator(np.random.PCG64(SeedSequence([SEED, i]))) in
float64, then rounded to float32:

* Conv2d / Conv3d weight (out, in, *k): N(0, 1) * sqrt(2 / fan_in), fan_in = in * prod(k)
  (He scaling: every layer keeps its input's scale, so no part of the network is negligible).
* ConvTranspose3d weight (in, out, 3, 3, 3) of dres2-4 conv5 / conv6, stride 2: each output
  reads in * 27 / 8 inputs on average, so fan_in = in * 27 / 8.
* Classifier last layers classif1-3 .2.weight (32 -> 1): N(0, 1) * CLASSIFIER_GAIN /
  sqrt(fan_in), so the softmax over disparity stays soft: the mean peak probability is 0.06
  (train mode) to 0.26 (evaluation) over 32 planes, so the regression reads every plane rather
  than an argmax (the fixture records it per case).
* BatchNorm weight U(0.8, 1.2), bias U(-0.1, 0.1), running_mean U(-0.1, 0.1), running_var
  U(0.8, 1.25): close to identity in evaluation, but every channel differs, so a statistic
  or affine parameter read from the wrong layer or channel changes the output.
* Except the last BatchNorm of each residual branch (feature_extraction.layerN.M.conv2.1 and
  dres1.2.1): weight U(0.08, 0.12) and bias U(-0.02, 0.02). In evaluation mode BatchNorm
  does not renormalise, and the reference's blocks add their branch to an input that is not
  rectified, so with He-scaled branches the variance doubles per block (2^25 over the 25
  blocks); with these the features' scale grows about 6x through the network and the
  branches still contribute about a tenth of each block's output.

Inputs are U(0, 1) images from the same kind of generator seeded [SEED, 10_000 + case index].
`fingerprint` hashes the float32 bytes of weights and inputs; the fixture records it, so a
NumPy that changed its streams is reported as such rather than as a network mismatch.
"""

from __future__ import annotations

import dataclasses
import hashlib
import re
from pathlib import Path

import numpy as np

SEED = 21
KEYS_FILE = Path(__file__).parent / "data" / "psmnet_keys.txt"
FIXTURE_FILE = Path(__file__).parent / "data" / "psmnet_reference.npz"
CLASSIFIER_GAIN = 1.0
_TRANSPOSED = re.compile(r"^dres[234]\.conv[56]\.0\.weight$")
_CLASSIFIER_LAST = re.compile(r"^classif[123]\.2\.weight$")
_RESIDUAL_LAST_BN = re.compile(r"^(feature_extraction\.layer\d\.\d+\.conv2\.1|dres1\.2\.1)\.")


@dataclasses.dataclass(frozen=True)
class Case:
  """One reference run: a batch of inputs, the network's maxdisp and how it is run."""
  name: str
  batch: int
  height: int
  width: int
  maxdisp: int
  train: bool = False
  pad: bool = False  # the reference's Test_img.py protocol: pad the normalised input to x16
  row_step: int = 1  # the fixture keeps every row_step-th output row (all columns)

  @property
  def padded(self) -> tuple[int, int]:
    """The size the network sees (the input size rounded up to a multiple of 16 when padding)."""
    if not self.pad:
      return self.height, self.width
    return -(-self.height // 16) * 16, -(-self.width // 16) * 16


# Evaluation mode is pinned by "pad" (48x80 after padding) and "full". Small sizes (the 1/4-resolution map is smaller than the 64x64 SPP pool; see the fixture
# script for the one change this needs in the reference) plus one 256x256 case where every
# SPP pool has the reference's own kernel. "train" runs with batch statistics (batch 2: PyTorch
# refuses BatchNorm over the one value per channel of a global pool at batch 1).
CASES = (
    Case("train", 2, 48, 80, 32, train=True),
    Case("pad", 1, 45, 70, 32, pad=True),
    Case("full", 1, 256, 256, 16, row_step=8),
)


def reference_shapes() -> dict[str, tuple[int, ...]]:
  """Key -> shape of the reference state_dict, in its order (num_batches_tracked omitted)."""
  shapes = {}
  for line in KEYS_FILE.read_text().splitlines():
    if line and not line.startswith("#"):
      key, shape = line.split()
      shapes[key] = tuple(int(s) for s in shape.split("x"))
  return shapes


def _rng(*words: int) -> np.random.Generator:
  return np.random.Generator(np.random.PCG64(np.random.SeedSequence(list(words))))


def tensor(key: str, shape: tuple[int, ...], index: int, seed: int = SEED) -> np.ndarray:
  """Tensor `index` of the recipe (see the module docstring), float32, PyTorch layout."""
  rng = _rng(seed, index)
  leaf = key.rsplit(".", 1)[1]
  if len(shape) >= 4:  # convolution weights
    k = int(np.prod(shape[2:]))
    fan_in = shape[0] * k / 8 if _TRANSPOSED.match(key) else shape[1] * k
    gain = CLASSIFIER_GAIN if _CLASSIFIER_LAST.match(key) else np.sqrt(2.0)
    v = rng.standard_normal(shape) * gain / np.sqrt(fan_in)
  elif leaf == "weight":
    v = rng.uniform(0.08, 0.12, shape) if _RESIDUAL_LAST_BN.match(key) else rng.uniform(
        0.8, 1.2, shape)
  elif leaf == "bias":
    v = rng.uniform(-0.02, 0.02, shape) if _RESIDUAL_LAST_BN.match(key) else rng.uniform(
        -0.1, 0.1, shape)
  elif leaf == "running_mean":
    v = rng.uniform(-0.1, 0.1, shape)
  elif leaf == "running_var":
    v = rng.uniform(0.8, 1.25, shape)
  else:
    raise ValueError(f"no recipe for {key}")
  return v.astype(np.float32)


def state_dict(seed: int = SEED) -> dict[str, np.ndarray]:
  """The whole reference state_dict (PyTorch layout and names), in psmnet_keys.txt order."""
  return {k: tensor(k, s, i, seed) for i, (k, s) in enumerate(reference_shapes().items())}


def images(case: Case, seed: int = SEED) -> tuple[np.ndarray, np.ndarray]:
  """Left and right views of a case: BxHxWx3 float32 in [0, 1] (unpadded)."""
  rng = _rng(seed, 10_000 + CASES.index(case))
  shape = (case.batch, case.height, case.width, 3)
  return rng.random(shape).astype(np.float32), rng.random(shape).astype(np.float32)


def fingerprint(seed: int = SEED) -> str:
  """sha256 of the recipe's float32 weights (in key order) and every case's inputs."""
  h = hashlib.sha256()
  for k, v in state_dict(seed).items():
    h.update(k.encode())
    h.update(np.ascontiguousarray(v).tobytes())
  for case in CASES:
    for x in images(case, seed):
      h.update(x.tobytes())
  return h.hexdigest()
