"""Resuming a run: its checkpoints opened, the newest intact one restored, and what a user can
do when one is damaged.

A damaged checkpoint (its bytes differ from those written: sljax.models.digest) is never
passed over in silence, which would quietly repeat steps: it is refused with the earlier
checkpoints and how to resume from one, or, only when the user asks (--resume-skip-damaged),
moved aside to N.damaged with a line naming it.
"""

from collections.abc import Callable
from pathlib import Path

import jax

from sljax.errors import SljaxError, require
from sljax.models import checkpoint as ckpt
from sljax.train import state as st
from sljax.train.state import LoopState
from sljax.train.workdir import EPOCHS_FILE, METRICS_FILE


def restore_checkpoint(manager, state: st.TrainState, sharding, skip_damaged: bool = False,
                       log: Callable[[str], None] = print) -> tuple[st.TrainState, LoopState]:
  """The TrainState and LoopState of the newest checkpoint; a damaged one is refused, or with
  skip_damaged moved aside (to N.damaged, named in a line) for the newest intact earlier one."""
  checkpoints = Path(manager.directory)
  abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding),
                          state)
  skipped = []
  # Every step entry, not orbax's list: orbax passes over a file or an emptied folder in
  # silence, and resuming from the step before it would quietly repeat steps.
  for step in reversed(ckpt.step_entries(checkpoints)):
    try:
      state, loop = _restore_step(manager, step, abstract, log)
      break
    except ckpt.CheckpointUnreadable as e:
      if not e.damaged:  # a permission problem: deleting the checkpoint is not the remedy
        raise
      if not skip_damaged:
        raise SljaxError(f"{e}; {resume_advice(checkpoints, step)}") from None
      skipped.append((step, e))
  else:  # every step damaged, or the only one already moved aside by open_manager
    raise SljaxError(f"{skipped[-1][1] if skipped else checkpoints}: no intact checkpoint is "
                     "left; start again with --overwrite")
  for bad, e in skipped:
    _move_aside(checkpoints, bad, e, log)
  if skipped:
    manager.reload()  # orbax listed the moved steps when it opened the folder
  return state, loop


def open_manager(checkpoints: Path, keep: int, skip_damaged: bool, log: Callable[[str], None]):
  """The run's checkpoint manager; a step whose orbax metadata is damaged (orbax reads them all
  on opening) is refused with the resume advice, or with skip_damaged moved aside."""
  while True:
    try:
      return ckpt.make_manager(checkpoints, keep=keep)
    except ckpt.CheckpointUnreadable as e:
      if not skip_damaged:
        raise SljaxError(f"{e}; {resume_advice(checkpoints, e.step)}") from None
      _move_aside(checkpoints, e.step, e, log)


def _move_aside(checkpoints: Path, step: int, why: Exception, log: Callable[[str], None]) -> None:
  """--resume-skip-damaged: step N renamed N.damaged, kept for a look and out of orbax's way (a
  later save reuses N), by the first process only; said in a line."""
  aside = checkpoints / f"{step}.damaged"
  if jax.process_index() == 0:
    (checkpoints / str(step)).rename(aside)
  log(f"--resume-skip-damaged: skipped {why} (moved to {aside.name})")


def _restore_step(manager, step: int, abstract, log: Callable[[str], None]
                  ) -> tuple[st.TrainState, LoopState]:
  """The TrainState and LoopState of one step's checkpoint (CheckpointUnreadable if damaged)."""
  state, meta = ckpt.restore(manager, step, abstract, note=log)
  try:
    loop = LoopState.from_meta(meta)
  except (KeyError, TypeError, ValueError) as e:
    raise ckpt.unreadable(manager.directory, step, e) from None
  require(loop.step == int(state.step), f"{manager.directory}: checkpoint {step} is inconsistent")
  return state, loop


def resume_advice(checkpoints: Path, step: int) -> str:
  """What a user can do about a damaged latest checkpoint: never a silent fallback (it would
  quietly repeat steps), but the earlier checkpoints and how to resume from one."""
  earlier = [s for s in ckpt.step_entries(checkpoints)
             if s < step and (checkpoints / str(s)).is_dir()]
  if not earlier:
    return "no earlier checkpoint exists; start again with --overwrite"
  return (f"earlier checkpoints: steps {', '.join(map(str, earlier))}; delete the damaged folder "
          f"{checkpoints / str(step)} to resume from step {earlier[-1]}, or pass "
          "--resume-skip-damaged to move it aside and do so")


def fresh_start_note(workdir: Path) -> str | None:
  """The line for a --resume that finds config.json but no checkpoint (a run stopped before its
  first one): it starts from step 0 and replaces the rows written before; None for a new
  workdir (the experiment runner resumes every cell, new ones too)."""
  if not (workdir / ckpt.CONFIG_FILE).exists():
    return None
  rows = []
  for name in (METRICS_FILE, EPOCHS_FILE):
    n = len((workdir / name).read_text().splitlines()) if (workdir / name).exists() else 0
    rows += [f"{n} row(s) of {name}"] if n else []
  return (f"--resume: no checkpoint in {workdir / ckpt.CHECKPOINT_DIR} yet; starting from step 0"
          + (f" (replacing the {' and '.join(rows)} written without one)" if rows else ""))
