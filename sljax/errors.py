"""User-facing errors: one clear line, no traceback from the command line."""

import os
import sys
from collections.abc import Callable
from typing import Any


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


def run_command(prog: str, fn: Callable[[], Any],
                interrupted_note: Callable[[], str] = lambda: "",
                quiet_broken_pipe: bool = False) -> tuple[int, Any]:
  """(exit code, fn()'s result) for a command-line entry point (train.py and every `sljax`
  command): SljaxError or a failed file operation -> "PROG: error: ..." on stderr and 2;
  Ctrl-C -> "PROG: interrupted" + interrupted_note() and 130. quiet_broken_pipe: a reader that
  went away (`sljax info DATA | head`) ends the command quietly with 0, as other Unix tools
  (not for training, where it would pass an unfinished run off as done)."""
  try:
    return 0, fn()
  except SljaxError as e:
    print(f"{prog}: error: {e}", file=sys.stderr)
    return 2, None
  except BrokenPipeError as e:
    if not quiet_broken_pipe:
      print(f"{prog}: error: {describe_os_error(e)}", file=sys.stderr)
      return 2, None
    _silence_stdout()
    return 0, None
  except KeyboardInterrupt:
    print(f"{prog}: interrupted{interrupted_note()}", file=sys.stderr)
    return 130, None
  except OSError as e:  # a full or read-only disk, a file where a folder must be
    print(f"{prog}: error: {describe_os_error(e)}", file=sys.stderr)
    return 2, None


def _silence_stdout() -> None:
  """Points stdout at /dev/null, so that Python's flush at exit does not fail on the closed
  pipe again (a replaced stdout, as in a notebook, has no descriptor and is left alone)."""
  try:
    fd = sys.stdout.fileno()
  except (AttributeError, OSError, ValueError):  # io.UnsupportedOperation is both of the last
    return
  null = os.open(os.devnull, os.O_WRONLY)
  os.dup2(null, fd)
  os.close(null)
