"""User-facing errors: one clear line, no traceback from the command line."""


class SljaxError(Exception):
  """Bad input or configuration; the message names the file or option and the problem."""


def require(condition: bool, message: str) -> None:
  """Raises SljaxError(message) unless condition holds."""
  if not condition:
    raise SljaxError(message)


def describe_os_error(e: OSError) -> str:
  """One line for a failed file operation (read-only or full disk, a file where a folder must
  be): the path and the system's reason, as the command line prints it instead of a traceback."""
  reason = e.strerror or str(e)
  if e.filename is None:
    return reason
  where = str(e.filename) + (f" -> {e.filename2}" if e.filename2 is not None else "")
  return f"{where}: {reason}"
