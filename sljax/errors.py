"""User-facing errors: one clear line, no traceback from the command line."""


class SljaxError(Exception):
  """Bad input or configuration; the message names the file or option and the problem."""


def require(condition: bool, message: str) -> None:
  """Raises SljaxError(message) unless condition holds."""
  if not condition:
    raise SljaxError(message)
