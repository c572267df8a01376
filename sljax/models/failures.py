"""What orbax and TensorStore raise, turned into one line, and the process-wide hooks that keep
their tracebacks off the terminal.

Storage failures (a full disk, a read-only or unwritable folder) arrive from anywhere in orbax
or TensorStore: an OSError, or TensorStore's ValueError carrying the OS error code, possibly
from a background thread at a later save or wait. `storage_failure` names what failed, where,
and the last good checkpoint. A checkpoint whose files do not restore raises anything from
KeyError to JSONDecodeError (RESTORE_ERRORS).

Process-wide hooks, installed once by the checkpoint functions that need them: a filter on
absl's logger (orbax logs each storage failure with a traceback per thread, and the caller
reports it in one line), a filter on asyncio's logger and an unraisable hook (when one array
of a restore fails, the other reads' failures surface later as "Task exception was never
retrieved" and "Event loop is closed"). Each drops only those records and passes everything
else on.
"""

import contextlib
import errno
import logging
import os
import re
import sys
from pathlib import Path
from typing import Any

from sljax.errors import SljaxError

# OS errors that mean "this storage does not take the write" (not a bug in the caller).
STORAGE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG)
_TS_CODE = re.compile(r"os_error_code='?(\d+)")  # TensorStore's errors carry the OS error code
_QUOTED_PATH = re.compile(r'"(/[^"]+)"')
SAVING = "saving a checkpoint"
_HINT = {errno.ENOSPC: "free some space", errno.EDQUOT: "free some space (disk quota)",
         errno.EFBIG: "free some space", errno.EROFS: "make it writable",
         errno.EACCES: "make it writable (permissions)",
         errno.EPERM: "make it writable (permissions)"}


def _causes(exc: BaseException):
  """exc, its causes and contexts, and the members of exception groups (each once)."""
  todo, seen = [exc], set()
  while todo:
    e = todo.pop(0)
    if e is None or id(e) in seen:
      continue
    seen.add(id(e))
    yield e
    todo += [e.__cause__, e.__context__, *getattr(e, "exceptions", ())]


def storage_errno(exc: BaseException) -> tuple[int, str | None] | None:
  """(errno, path or None) of a full-disk / read-only / permission failure inside exc (its
  chain, exception groups, or TensorStore's message), else None."""
  for e in _causes(exc):
    if isinstance(e, OSError) and e.errno in STORAGE_ERRNOS:
      return e.errno, e.filename and os.fspath(e.filename)
    text = str(e)
    m = _TS_CODE.search(text)
    codes = [int(m.group(1))] if m else [c for c in STORAGE_ERRNOS if os.strerror(c) in text]
    if codes and codes[0] in STORAGE_ERRNOS:
      paths = _QUOTED_PATH.findall(text)
      return codes[0], paths[-1] if paths else None
  return None


def last_good_step(directory: str | os.PathLike) -> int | None:
  """The step a --resume would restore: the latest finalised checkpoint (None: none)."""
  directory = Path(directory)
  steps = [int(p.name) for p in directory.iterdir() if p.name.isdigit() and p.is_dir()] \
      if directory.is_dir() else []
  return max(steps, default=None)


def storage_failure(exc: BaseException, what: str, checkpoints: str | os.PathLike
                    ) -> SljaxError | None:
  """The one-line SljaxError for a failed write (what: e.g. 'saving checkpoint 120'), or None
  when exc is not a storage failure."""
  found = storage_errno(exc)
  if found is None:
    return None
  code, path = found
  checkpoints = Path(checkpoints)
  step = re.search(r"/(\d+)\.orbax-checkpoint-tmp", path or "")
  if what.startswith("saving") and step:
    # Orbax reports a failed background save at the next save or wait: name the failed one.
    what = f"saving checkpoint {step.group(1)}"
  where = path or str(checkpoints)
  good = last_good_step(checkpoints)
  kept = (f"the last good checkpoint is step {good} ({checkpoints / str(good)}), intact"
          if good is not None else "no checkpoint was saved yet")
  again = "continue with --resume" if good is not None else "run again"
  return SljaxError(f"{what} failed: {os.strerror(code)} ({where}); stopped, {kept}; "
                    f"{_HINT[code]} and {again}")


@contextlib.contextmanager
def storage_guard(what: str, checkpoints: str | os.PathLike):
  """Turns a storage failure inside the block into storage_failure's SljaxError."""
  try:
    yield
  except SljaxError:
    raise
  except Exception as e:  # pylint: disable=broad-except
    failure = storage_failure(e, what, checkpoints)
    if failure is None:
      raise
    raise failure from None


# What orbax and TensorStore raise for damaged or missing files (TensorStore's DATA_LOSS,
# OUT_OF_RANGE and FAILED_PRECONDITION arrive as ValueError, a garbage JSON item as
# JSONDecodeError, a missing item as KeyError). Anything else (a device out of memory while
# the arrays are placed, a bug) is not the checkpoint's fault and keeps its own error.
RESTORE_ERRORS = (ValueError, KeyError, TypeError, EOFError, OSError)


class _QuietStorageFailures(logging.Filter):
  """Drops orbax's ERROR logs (with tracebacks, one per thread) of a storage failure: the same
  failure is raised to the caller, who reports it in one line."""

  def filter(self, record: logging.LogRecord) -> bool:
    exc = record.exc_info[1] if record.exc_info else None
    if exc is not None and storage_errno(exc) is not None:
      return False
    try:
      message = record.getMessage()
    except Exception:  # pylint: disable=broad-except
      return True
    return not (record.levelno >= logging.ERROR and "orbax" in record.pathname
                and storage_errno(Exception(message)) is not None)


_QUIET = _QuietStorageFailures()


def _late_read_callback(unraisable: Any) -> bool:
  """Whether an unraisable exception is a TensorStore read finishing after orbax's event loop
  closed: when one array of a restore fails, orbax closes its loop while the reads of the
  others are in flight, and each one's completion prints a traceback (after our one line)."""
  exc, tb = unraisable.exc_value, unraisable.exc_traceback
  while tb is not None and tb.tb_next is not None:
    tb = tb.tb_next
  return (isinstance(exc, RuntimeError) and str(exc) == "Event loop is closed"
          and tb is not None and "asyncio" in tb.tb_frame.f_code.co_filename)


class _QuietLateReadFailures(logging.Filter):
  """Drops asyncio's 'Task exception was never retrieved' for an orbax read: orbax gathers the
  reads of a restore without return_exceptions, so when one array fails the restore raises
  (reported in one line) and the other reads' failures, unretrieved, are logged with a
  traceback when their tasks are collected, possibly long after (seen in CI on a busy Zen 3)."""

  def filter(self, record: logging.LogRecord) -> bool:
    exc = record.exc_info[1] if record.exc_info else None
    return not (isinstance(exc, RESTORE_ERRORS) and _raised_in_orbax(exc)
                and str(record.msg).startswith("Task exception was never retrieved"))


def _raised_in_orbax(exc: BaseException) -> bool:
  """Whether exc's traceback passes through orbax's checkpoint package."""
  tb = exc.__traceback__
  while tb is not None:
    if "orbax" in Path(tb.tb_frame.f_code.co_filename).parts:
      return True
    tb = tb.tb_next
  return False


_QUIET_LATE_READS = _QuietLateReadFailures()


def _drop_late_read_callbacks() -> None:
  """Installs (once) an unraisable hook that drops _late_read_callback's tracebacks only."""
  previous = sys.unraisablehook
  if getattr(previous, "sljax_drops_late_reads", False):
    return

  def hook(unraisable: Any) -> None:
    if not _late_read_callback(unraisable):
      previous(unraisable)
  hook.sljax_drops_late_reads = True
  sys.unraisablehook = hook


def quiet_storage_logs() -> None:
  """Installs (once) the absl filter that drops orbax's logs of a storage failure."""
  logging.getLogger("absl").addFilter(_QUIET)  # idempotent: a filter is added once


def quiet_late_reads() -> None:
  """Installs (once) the hooks that drop a failed restore's late read tracebacks."""
  _drop_late_read_callbacks()
  logging.getLogger("asyncio").addFilter(_QUIET_LATE_READS)
