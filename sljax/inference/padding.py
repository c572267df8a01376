"""Pad mode's protocol: what a network's input is padded with, to which multiple, and where.

The PSMNet reference's test protocol (Test_img.py / submission.py of JiaRenChang/PSMNet)
normalises the image with the ImageNet mean and std and pads the normalised tensor with 0 at
the TOP and RIGHT to the next multiple of 16. sljax normalises inside the model, so the [0, 1]
pair is padded with the value the model's input normalisation maps to 0, at the top and right,
and the outputs are cropped back (rows from the top pad on, columns up to the input width).
Each network's rule is its registry entry's `pad` (sljax.nets.registry.PAD_RULES):
  * normalized-zero (psmnet, psmnet-mtl): the ImageNet mean colour (0.485, 0.456, 0.406) for
    RGB, 0.449 (the average of the three means, which the 1-channel normalisation maps to 0)
    for gray; multiple of 16 (the reference's rule exactly).
  * unet (unet-sl, unet-disp): 0.5, which the UNet's input centring 2x - 1 maps to 0; multiple
    of 2^depth, so every pooling level halves an even size and the UNet's own bottom/right
    edge padding never applies. unet-disp scales its sigmoid by the width it is given, the
    padded width here.
  * zero: 0, multiple of 16.
Why the normalised zero: the first convolution pads its input with zeros in the normalised
domain, so a pad region of normalised zeros is read exactly as the network's own border
padding; black (0) would be a dark frame (about -2 after normalisation) that the reference
never shows its network.
Why top and right: left-referenced disparity matches x in the left view with x - d in the right
view, so columns added on the right are never a match for an image pixel, while columns on the
left would be.
"""

import dataclasses

import numpy as np

from sljax.nets.model_config import ModelConfig
from sljax.nets.psmnet import normalization_zero
from sljax.nets.unet import INPUT_ZERO

PAD_MULTIPLE = 16  # the PSMNet reference's


@dataclasses.dataclass(frozen=True)
class PadRule:
  """How pad mode pads a model's input: to a multiple of `multiple`, with `fill` per channel."""
  multiple: int
  fill: tuple[float, ...]

  def describe(self) -> str:
    """E.g. 'multiple of 16, filled with (0.485, 0.456, 0.406)'."""
    return (f"multiple of {self.multiple} (top/right), filled with "
            f"({', '.join(f'{v:.4g}' for v in self.fill)})")


def pad_rule(config: ModelConfig, model) -> PadRule:
  """The pad protocol of a network (its registry entry's `pad`) built as `model`."""
  c = config.in_channels
  if config.spec.pad == "normalized-zero":
    return PadRule(PAD_MULTIPLE, tuple(float(v) for v in normalization_zero(c)))
  if config.spec.pad == "unet":
    return PadRule(2 ** model.depth, (INPUT_ZERO,) * c)
  return PadRule(PAD_MULTIPLE, (0.0,) * c)


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
