"""Data feeding for the loop: the scene source, a RAM cache of resized rows, batches built
ahead by background threads.

Batch k of epoch e is a function of (seed, e, k) only (the epoch's order is a permutation
drawn from (seed, e)), so the threads change when a batch is built, never what it holds.
"""

import collections
import concurrent.futures
import dataclasses
import functools
import itertools
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import jax
import numpy as np

from sljax.render import synthetic
from sljax.data.dataset import PART_FIELD, FolderSource, epoch_order, load_batch
from sljax.errors import require
from sljax.train import step as stp
from sljax.train.config import TrainConfig

PREFETCH = 3          # batches built ahead of the step that needs them
LOADER_THREADS = 2    # threads building them (decoding, resizing and rendering release the GIL)
CACHE_BYTES = 2 << 30  # a source whose resized rows fit in this is kept in RAM
_TARGET_TEXT = {"disp": "disparity (disp0.pfm)", "sl": "structured-light patterns (sl0/)",
                "sl_right": "right-view structured-light patterns (sl1/)"}


def open_source(config: TrainConfig):
  """The scene source: a scene-format folder or synthetic scenes rendered on the fly."""
  if config.data is not None:
    return FolderSource(config.data)
  synth = synthetic.SynthConfig(size=config.synth_size, domain=config.domain, t=config.synth_t)
  return synthetic.SyntheticSource(config.synth_n, seed=config.seed, config=synth)


def batch_parts(config: TrainConfig, validation: bool = False) -> tuple[str, ...]:
  """Batch keys to load; validation of an SL network also loads disparity when it exists."""
  parts = config.spec.parts
  if validation and "disp" not in parts:
    parts = parts + ("disp",)
  return parts


@dataclasses.dataclass(frozen=True)
class DataInfo:
  """What the first scene says about the data: patterns per view, input channels, disparity."""
  t: int | None
  channels: int
  has_disp: bool


def check_source(source, config: TrainConfig) -> DataInfo:
  """Checks the first scene has every target the network trains on (SljaxError naming it)."""
  where = config.data or "synthetic data"
  require(len(source) > 0, f"{where}: no scenes")
  scene = source[0]
  name = getattr(source, "name", None)
  label = name(0) if callable(name) else scene.name
  for part in config.spec.parts:
    if part in _TARGET_TEXT:
      require(getattr(scene, PART_FIELD[part][0]) is not None,
              f"{where}: scene {label} has no {_TARGET_TEXT[part]}, which model {config.net} "
              f"trains on")
  t = None if scene.sl0 is None else int(scene.sl0.shape[-1])
  return DataInfo(t, 1 if config.use_gray else 3, scene.disp0 is not None)


class RowCache:
  """Per-scene resized rows kept in RAM (small runs revisit every scene each epoch); safe to
  call from the loader threads (at worst two threads load one scene twice)."""

  def __init__(self, source, config: TrainConfig, parts: Sequence[str], enabled: bool):
    self.source, self.config, self.parts, self.enabled = source, config, tuple(parts), enabled
    self.rows: dict[int, dict[str, np.ndarray]] = {}

  def batch(self, indices: Sequence[int]) -> dict[str, np.ndarray]:
    """Stacked batch of the given scene indices (resized to config.size)."""
    load = functools.partial(load_batch, self.source, size=self.config.size,
                             gray=self.config.use_gray, parts=self.parts)
    if not self.enabled:
      return load(list(indices))
    missing = [i for i in indices if i not in self.rows]
    if missing:
      loaded = load(missing)
      for k, i in enumerate(missing):
        self.rows[i] = {p: loaded[p][k] for p in self.parts}
    return {p: np.stack([self.rows[i][p] for i in indices]) for p in self.parts}


def bytes_per_scene(config: TrainConfig, t: int | None) -> int:
  """Approximate RAM of one cached resized scene."""
  h, w = config.size
  c = 1 if config.use_gray else 3
  return 4 * h * w * (2 * c + 2 + 2 * (t or 0))


def row_caches(source, config: TrainConfig, info: DataInfo) -> tuple[RowCache, RowCache]:
  """(training rows, validation rows); cached when the whole source fits in CACHE_BYTES
  (training rows of a folder are not: its scenes are read once an epoch anyway)."""
  fits = len(source) * bytes_per_scene(config, info.t) < CACHE_BYTES
  return (RowCache(source, config, batch_parts(config), fits and config.data is None),
          RowCache(source, config, batch_parts(config, validation=info.has_disp), fits))


def prefetch(fn: Callable[[Any], Any], items: Iterator[Any], ahead: int = PREFETCH,
             threads: int = LOADER_THREADS) -> Iterator[Any]:
  """fn(item) for each item, in order, computed by background threads `ahead` items early."""
  items = iter(items)
  with concurrent.futures.ThreadPoolExecutor(threads, thread_name_prefix="sljax-data") as pool:
    queue = collections.deque(pool.submit(fn, x) for x in itertools.islice(items, ahead))
    try:
      while queue:
        result = queue.popleft().result()
        queue.extend(pool.submit(fn, x) for x in itertools.islice(items, 1))
        yield result
    finally:
      for future in queue:
        future.cancel()


def train_batches(rows: RowCache, train_idx: Sequence[int], config: TrainConfig,
                  steps_per_epoch: int, first_step: int, last_step: int,
                  mesh) -> Iterator[dict[str, jax.Array]]:
  """Device batches of the global steps first_step + 1, ..., last_step, built ahead."""
  b = config.batch_size
  mine = stp.process_rows(b)

  @functools.lru_cache(maxsize=2)
  def order(epoch: int) -> list[int]:
    return epoch_order(train_idx, config.seed, epoch)

  def build(step: int) -> dict[str, jax.Array]:
    epoch, k = divmod(step, steps_per_epoch)
    idx = order(epoch)[k * b:(k + 1) * b]
    return stp.put_batch(rows.batch(idx[mine]), mesh)

  return prefetch(build, range(first_step, last_step))
