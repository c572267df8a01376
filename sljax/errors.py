"""User-facing errors: one clear line, no traceback from the command line."""


class SljaxError(Exception):
  """Bad input or configuration; the message names the file or option and the problem."""


def require(condition: bool, message: str) -> None:
  """Raises SljaxError(message) unless condition holds."""
  if not condition:
    raise SljaxError(message)


def quiet_libraries() -> None:
  """Keeps library chatter (orbax logs each read-only checkpoint opening as a warning) to
  errors only, so what the user reads is sljax's own lines."""
  from absl import logging as absl_logging  # pylint: disable=import-outside-toplevel
  absl_logging.set_verbosity(absl_logging.ERROR)
