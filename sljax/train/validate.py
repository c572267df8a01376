"""Validation of a training run: the held-out split scored as `sljax evaluate` scores it."""

from collections.abc import Callable, Sequence

import jax
import numpy as np
from jax.experimental import multihost_utils

from sljax.corr.correlation import sl_disparity
from sljax.evaluation.metrics import DisparityAccumulator
from sljax.losses.sl import sl_loss
from sljax.train import step as stp
from sljax.train.config import TrainConfig
from sljax.train.feed import RowCache, prefetch
from sljax.train.state import TrainState


def _gather(x: jax.Array) -> np.ndarray:
  """The whole array on this host (gathered from every process in multi-process runs)."""
  if jax.process_count() == 1:
    return np.asarray(jax.device_get(x))
  return np.asarray(multihost_utils.process_allgather(x, tiled=True))


def validate_split(state: TrainState, eval_step: Callable[..., dict[str, jax.Array]],
                   rows: RowCache, val_idx: Sequence[int], config: TrainConfig,
                   mesh) -> dict[str, float]:
  """Validation MAE (px, over valid GT) of the final disparity, and SL metrics for SL nets.

  For unet-sl the disparity comes from the predicted patterns by correlation (SPEC 2).
  """
  b = config.batch_size
  disp_metrics = DisparityAccumulator()  # the same metrics as `sljax evaluate`
  sl_sum, sl_n = 0.0, 0
  mine = stp.process_rows(b)

  def load(start: int) -> tuple[int, dict[str, np.ndarray]]:
    idx = list(val_idx[start:start + b])
    n_real = len(idx)
    idx = idx + [idx[-1]] * (b - n_real)  # pad to the sharded batch size; padding ignored below
    return n_real, rows.batch(idx)

  for n_real, host in prefetch(load, range(0, len(val_idx), b)):
    out = eval_step(state.params, state.batch_stats,
                    stp.put_batch({k: v[mine] for k, v in host.items()}, mesh))
    out = {k: _gather(v)[:n_real] for k, v in out.items()}
    if "sl_logits" in out:
      logits, targets = out["sl_logits"], host["sl"][:n_real]
      if "sl_logits_right" in out:
        logits = np.concatenate([logits, out["sl_logits_right"]], -1)
        targets = np.concatenate([targets, host["sl_right"][:n_real]], -1)
      sl_sum += float(sl_loss(logits, targets)) * n_real
      sl_n += n_real
    if "disp" in host:
      if "disparity" in out:
        pred = out["disparity"]
      else:  # unet-sl: disparity from the predicted patterns by correlation (SPEC 2)
        probs = [np.asarray(jax.nn.sigmoid(out[k])) for k in ("sl_logits", "sl_logits_right")]
        pred = sl_disparity(*probs, window=config.corr_window)[0]
      gt = host["disp"][:n_real]
      # Scored where the training loss is: finite ground truth in [0, maxdisp).
      disp_metrics.add(pred, gt, mask=(gt >= 0) & (gt < config.maxdisp), name="validation")
  res = {}
  if disp_metrics.n_pixels:
    m = disp_metrics.result()
    res["val_mae"] = m["mae"]
    res["val_bad_3"] = m["bad_3"]
  if sl_n:
    res["val_sl"] = sl_sum / sl_n
  return res
