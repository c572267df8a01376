"""Moved: checkpoints are sljax.models.checkpoint, trained models sljax.models.load.

This name forwards the readers that scripts written before the move import; anything else
raises an AttributeError naming the new place.
"""

from sljax.models.load import load_for_inference, load_params, read_config  # noqa: F401


def __getattr__(name: str):
  raise AttributeError(f"sljax.train.checkpoint.{name} moved: checkpoints are "
                       "sljax.models.checkpoint, trained models sljax.models.load")
