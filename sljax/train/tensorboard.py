"""--tensorboard: a run's curves as TensorBoard event files, written while it trains.

WORKDIR/tensorboard/ gets the rows of metrics.jsonl (train/*: losses, task weights, sigmas,
every step) and of epochs.jsonl (epoch/* means, val/* validation MAE, bad-3 and SL loss,
perf/* samples/s and seconds), all on the global step axis; watch them with
`tensorboard --logdir runs/`. Written with tensorboardX (protobuf only, no TensorFlow), an
optional dependency: pip install 'sljax[tensorboard]'.

A resumed run purges the events after the step it resumes from (as metrics.jsonl drops its
rows), so a curve never shows both the interrupted and the resumed run.
"""

import shutil
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from sljax.errors import SljaxError

TB_DIR = "tensorboard"
_AXES = ("step", "epoch")  # row keys that place a row, not curves


def summary_writer_class():
  """tensorboardX's SummaryWriter; SljaxError in one line when it is not installed."""
  try:
    from tensorboardX import SummaryWriter  # pylint: disable=import-outside-toplevel
  except ImportError:
    raise SljaxError("--tensorboard needs the tensorboardX package (no TensorFlow): "
                     "pip install 'sljax[tensorboard]' or pip install tensorboardX") from None
  return SummaryWriter


def tag(file: str, key: str) -> str:
  """The TensorBoard tag of a metrics.jsonl / epochs.jsonl / validation.jsonl column."""
  if file.startswith("metrics"):
    return f"train/{key}"
  if key.startswith("val_"):
    return f"val/{key[4:]}"
  if file.startswith("validation"):  # the training loss over the steps since the last one
    return f"interval/{key}"
  if key in ("samples_per_s", "seconds"):
    return f"perf/{key}"
  return f"epoch/{key}"


class TensorBoardWriter:
  """Mirrors the run's JSONL rows into event files (main process, --tensorboard only)."""

  def __init__(self, workdir: Path, first_step: int):
    writer_class = summary_writer_class()
    logdir = Path(workdir) / TB_DIR
    if first_step == 0:  # a fresh start: the curves of an earlier attempt go, as the JSONL rows
      shutil.rmtree(logdir, ignore_errors=True)
    # tensorboardX names a file by the second it opens: a resume within the same second would
    # reopen (and truncate) the interrupted attempt's file, so the nanoseconds go in the name.
    self.writer = writer_class(logdir=str(logdir), purge_step=first_step + 1, flush_secs=30,
                               filename_suffix=f".{time.time_ns() % 10**9:09d}")

  def write(self, file: str, rows: Sequence[dict[str, Any]]) -> None:
    """Adds each row's numeric columns as scalars at the row's global step."""
    for row in rows:
      for key, value in row.items():
        if key not in _AXES and isinstance(value, (int, float)):
          self.writer.add_scalar(tag(file, key), float(value), int(row["step"]))
    if not file.startswith("metrics"):
      self.writer.flush()  # an epoch ended: show it now

  def close(self) -> None:
    """Flushes and closes the event file."""
    self.writer.close()
