"""--profile: a jax.profiler trace of a few steps once they are compiled."""

from collections.abc import Callable
from typing import Any

import jax

PROFILE_STEPS = (2, 5)  # --profile traces these steps after the run's (re)start: compiled by then


class StepProfiler:
  """--profile: a jax.profiler trace of steps PROFILE_STEPS after the run's first step."""

  def __init__(self, directory: str | None, first_step: int, log: Callable[[str], None]):
    self.directory, self.log, self.active = directory, log, False
    self.start, self.stop = (first_step + s for s in PROFILE_STEPS)

  def before(self, step: int) -> None:
    """Called before dispatching global step `step` (1-based)."""
    if self.directory and step == self.start + 1:
      jax.profiler.start_trace(self.directory)
      self.active = True

  def after(self, step: int, state: Any) -> None:
    """Called after dispatching step `step`: ends the trace once its steps have run."""
    if self.active and step == self.stop:
      jax.block_until_ready(state)
      self.close()
      self.log(f"profile of steps {self.start + 1}-{self.stop} written to {self.directory}")

  def close(self) -> None:
    """Ends an open trace."""
    if self.active:
      jax.profiler.stop_trace()
      self.active = False
