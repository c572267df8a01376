"""--profile: a jax.profiler trace of a few steps once they are compiled."""

import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax

from sljax.errors import SljaxError

PROFILE_STEPS = (2, 5)  # --profile traces these steps after the run's (re)start: compiled by then


def check_profile_dir(directory: str | None) -> None:
  """Creates the --profile folder and checks it takes a file, before anything trains (a trace
  that cannot be written otherwise fails a few steps into the run); SljaxError naming it."""
  if not directory:
    return
  try:
    Path(directory).mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryFile(dir=directory):
      pass
  except OSError as e:
    raise SljaxError(f"--profile {directory}: cannot write a trace there "
                     f"({e.strerror or e}); choose a writable folder") from None


class StepProfiler:
  """--profile: a jax.profiler trace of steps PROFILE_STEPS after the run's first step. The
  trace is a by-product: a failure to start or write it is a warning line, the run goes on."""

  def __init__(self, directory: str | None, first_step: int, log: Callable[[str], None]):
    self.directory, self.log, self.active = directory, log, False
    self.start, self.stop = (first_step + s for s in PROFILE_STEPS)

  def before(self, step: int) -> None:
    """Called before dispatching global step `step` (1-based)."""
    if self.directory and step == self.start + 1:
      try:
        jax.profiler.start_trace(self.directory)
        self.active = True
      except Exception as e:  # pylint: disable=broad-except
        self._warn("could not start the trace", e)

  def after(self, step: int, state: Any) -> None:
    """Called after dispatching step `step`: ends the trace once its steps have run."""
    if self.active and step == self.stop:
      jax.block_until_ready(state)
      if self.close():
        self.log(f"profile of steps {self.start + 1}-{self.stop} written to {self.directory}")

  def close(self) -> bool:
    """Ends an open trace; whether it was written."""
    if not self.active:
      return False
    self.active = False
    try:
      jax.profiler.stop_trace()
      return True
    except Exception as e:  # pylint: disable=broad-except
      self._warn("the trace was not written", e)
      return False

  def _warn(self, what: str, e: Exception) -> None:
    reason = (str(e).strip().splitlines() or [type(e).__name__])[0][:200]
    self.log(f"warning: --profile {self.directory}: {what} ({reason}); training goes on")
