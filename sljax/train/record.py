"""Where a training run's results go: the step and epoch rows (metrics.jsonl, epochs.jsonl,
TensorBoard), the progress bar and the checkpoints, and the NaN check at each fetch."""

import dataclasses
import math
import time
from typing import Any

import jax
from tqdm import tqdm

from sljax.errors import SljaxError
from sljax.losses import weighting
from sljax.models import checkpoint as ckpt
from sljax.train import state as st
from sljax.train.setup import Setup
from sljax.train.state import LoopState
from sljax.train.workdir import EPOCHS_FILE, METRICS_FILE, VALIDATION_FILE, MetricWriter


class TrainingDiverged(SljaxError):
  """The loss became NaN or infinite."""


@dataclasses.dataclass(frozen=True)
class Recorder:
  """Where the loop's results go: the run's metric files, its checkpoints, the progress bar."""
  run: Setup
  writer: MetricWriter
  manager: Any
  bar: Any


def fetch_metrics(rec: Recorder, pending: list[tuple[int, Any]],
                  loop: LoopState) -> tuple[LoopState, dict[str, float]]:
  """Fetches the pending steps' metrics, checks them, logs a row per step and adds their
  losses to the epoch sums; returns the new LoopState and the last row."""
  config, spe = rec.run.config, rec.run.steps_per_epoch
  sigmas = weighting.TABLE[config.strategy].learns_sigmas
  rows = []
  for step, m in zip([s for s, _ in pending], jax.device_get([m for _, m in pending])):
    m = {k: float(v) for k, v in m.items() if sigmas or not k.startswith("sigma")}
    if not math.isfinite(m["loss"]):
      rec.writer.write(METRICS_FILE, rows)
      rec.manager.wait_until_finished()
      good = rec.manager.latest_step()
      raise TrainingDiverged(
          f"non-finite loss ({m['loss']}) at step {step} (epoch {(step - 1) // spe + 1}); "
          "stopped. " + (f"The last good checkpoint is step {good} in "
                         f"{rec.run.workdir / ckpt.CHECKPOINT_DIR}" if good is not None
                         else "No checkpoint was saved yet") + "; try a lower --lr")
    rows.append({"step": step, "epoch": (step - 1) // spe + 1, **m})
    loop = loop.add_step(m["loss_sl"], m["loss_disp"])
  rec.writer.write(METRICS_FILE, rows)
  ckpt.check(rec.manager)  # a failed background save ends the run now, not an epoch later
  rec.bar.set_postfix(epoch=rows[-1]["epoch"], loss=f"{rows[-1]['loss']:.4g}", refresh=False)
  rec.bar.update(len(rows))
  return loop, rows[-1]


def rate_after_first_step(bar: Any) -> None:
  """Called after the first step, before its metrics reach the bar: a tqdm bar's rate and
  time left then count the later steps only (the first one's compile is not a step's cost;
  on a CPU it made the first estimate 10 minutes for a run of 1.5). Elapsed stays wall time."""
  if isinstance(bar, tqdm) and not bar.disable:
    bar.last_print_n = bar.n + 1
    bar.last_print_t = getattr(bar, "_time", time.time)()


def save(rec: Recorder, state: st.TrainState, loop: LoopState, val: float | None = None) -> None:
  """Starts an async checkpoint of the state with the loop state as its metadata."""
  ckpt.save(rec.manager, loop.step, state, loop.to_meta(), val)


def _val_text(val: dict[str, float]) -> list[str]:
  text = []
  if val.get("val_mae") is not None:
    text.append(f"val MAE {val['val_mae']:.3f} px")
  if val.get("val_sl") is not None:
    text.append(f"val L_sl {val['val_sl']:.4f}")
  return text


def write_validation(rec: Recorder, loop: LoopState, val: dict[str, float]) -> None:
  """A validation by steps: its validation.jsonl row (with the mean training losses since the
  previous one; `loop` is the state before `validated` resets them) and its line."""
  spe = rec.run.steps_per_epoch
  loss_sl, loss_disp = loop.interval_means()
  row = {"step": loop.step, "epoch": loop.step / spe, "train_loss_sl": loss_sl,
         "train_loss_disp": loss_disp, "train_steps": loop.since_val[2], **val}
  rec.writer.write(VALIDATION_FILE, [row])
  needs_sl, needs_disp = rec.run.config.tasks
  text = ([f"L_sl {loss_sl:.4g}"] * needs_sl + [f"L_disp {loss_disp:.4g}"] * needs_disp
          + _val_text(val))
  rec.bar.write(f"step {loop.step}/{rec.run.total_steps}: {' '.join(text)}")


def write_epoch(rec: Recorder, loop: LoopState, last: dict[str, float], val: dict[str, float],
                seconds: float, samples: int) -> None:
  """The finished epoch's epochs.jsonl row and its line above the progress bar (none when
  validating by steps: the validation lines report, and a small set ends an epoch every step)."""
  config = rec.run.config
  epoch = len(loop.history)
  row = {"epoch": epoch, "step": loop.step, "loss_sl": loop.history[-1][0],
         "loss_disp": loop.history[-1][1], "w_sl": last["w_sl"], "w_disp": last["w_disp"],
         "samples_per_s": samples / max(seconds, 1e-9), "seconds": seconds}
  row.update({k: last[k] for k in ("sigma_sl", "sigma_disp") if k in last})
  row.update(val)
  rec.writer.write(EPOCHS_FILE, [row])
  needs_sl, needs_disp = config.tasks
  text = ([f"L_sl {row['loss_sl']:.4g}"] * needs_sl
          + [f"L_disp {row['loss_disp']:.4g}"] * needs_disp + _val_text(val))
  if config.val_every_steps is None:
    epochs = (f"{config.epochs}" if config.steps is None
              else f"{math.ceil(rec.run.total_steps / rec.run.steps_per_epoch)}")
    rec.bar.write(f"epoch {epoch}/{epochs}: {' '.join(text)} "
                  f"({row['samples_per_s']:.1f} samples/s)")
