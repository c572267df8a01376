"""Tiny stand-in models shared by the inference and evaluation tests."""

import flax.linen as nn


class ToySL(nn.Module):
  """Pattern logits = +-20 from the views themselves (t = channels), both views."""

  @nn.compact
  def __call__(self, left, right, train=False):
    gain = self.param("gain", nn.initializers.ones, ())
    return {"sl_logits": 20.0 * gain * (2.0 * left - 1.0),
            "sl_logits_right": 20.0 * gain * (2.0 * right - 1.0)}
