"""Ctrl-C during training: stop after the current step, the way an interruption stops.

A KeyboardInterrupt raised wherever SIGINT happens to land is lost when that is inside a
callback Python cannot raise from (jax's `_xla_gc_callback`: "Exception ignored in ...
KeyboardInterrupt"), and training ran on to the end about 4 times in 10. So while the loop
runs, the first Ctrl-C only sets a flag that the loop checks after each step; a second one
raises KeyboardInterrupt at once (and if that one is lost too, the flag still stops the loop).
"""

import contextlib
import os
import signal
import threading
from collections.abc import Iterator

FIRST_NOTICE = b"\nCtrl-C: stopping after this step (Ctrl-C again to stop now)\n"


class Interrupt:
  """Whether a Ctrl-C asked the loop to stop."""

  def __init__(self):
    self.asked = False

  def handle(self, signum, frame) -> None:  # pylint: disable=unused-argument
    """The SIGINT handler: the first sets the flag, the next raises KeyboardInterrupt."""
    if self.asked:
      raise KeyboardInterrupt
    self.asked = True
    os.write(2, FIRST_NOTICE)  # not print: a handler may run in the middle of a print


@contextlib.contextmanager
def deferred_interrupt() -> Iterator[Interrupt]:
  """An Interrupt whose flag a Ctrl-C sets while the block runs (the main thread only: signal
  handlers can only be set there; elsewhere, or where SIGINT is ignored, the flag stays unset);
  KeyboardInterrupt on leaving if the flag was set and not acted on; restores the handler."""
  flag = Interrupt()
  if (threading.current_thread() is not threading.main_thread()
      or signal.getsignal(signal.SIGINT) is signal.SIG_IGN):
    # A background job (`cmd &` from a script) inherits SIGINT ignored: keep it ignored.
    yield flag
    return
  previous = signal.signal(signal.SIGINT, flag.handle)
  try:
    yield flag
    if flag.asked:  # a Ctrl-C during the block's own cleanup, after the last check
      raise KeyboardInterrupt
  finally:
    # None: a handler set outside Python, which cannot be put back; Python's default then.
    signal.signal(signal.SIGINT, signal.default_int_handler if previous is None else previous)
