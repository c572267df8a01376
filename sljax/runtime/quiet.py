"""Library chatter kept to errors, for every command line (sljax and train.py)."""

from absl import logging as absl_logging


def quiet_libraries() -> None:
  """Keeps library chatter (orbax logs each read-only checkpoint opening as a warning) to
  errors only."""
  absl_logging.set_verbosity(absl_logging.ERROR)
