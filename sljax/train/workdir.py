"""The run directory's on-disk format, shared by training, inference and experiments.

    <workdir>/config.json     the resolved run (TrainConfig fields + what the data decided)
    <workdir>/metrics.jsonl   a row per training step
    <workdir>/epochs.jsonl    a row per epoch (losses, weights, validation, throughput)
    <workdir>/checkpoints/N/  orbax checkpoints (sljax.models.checkpoint)
    <workdir>/.sljax.lock     while a run holds the workdir (`held`; removed at its end)

Writes happen on the main process only; every process checks the directory first.
"""

import contextlib
import json
import shutil
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np
from jax.experimental import multihost_utils

from sljax.errors import SljaxError
from sljax.io import files
from sljax.models.checkpoint import CHECKPOINT_DIR, CONFIG_FILE
from sljax.models.failures import storage_guard
from sljax.models.load import read_config
from sljax.nets import registry
from sljax.train.config import PATH_FIELDS, TrainConfig, diff_configs, dumps
from sljax.train.tensorboard import TensorBoardWriter

METRICS_FILE = "metrics.jsonl"
EPOCHS_FILE = "epochs.jsonl"
VALIDATION_FILE = "validation.jsonl"  # --val-every-steps: a row per validation

__all__ = ["CHECKPOINT_DIR", "CONFIG_FILE", "EPOCHS_FILE", "METRICS_FILE", "VALIDATION_FILE",
           "MetricWriter",
           "check_config_kept", "clear_run", "default_workdir", "has_checkpoints", "held",
           "prepare_workdir", "read_config", "restart_logs", "sync", "write_config"]


def default_workdir(config: TrainConfig) -> Path:
  """runs/<model>-<strategy>-<seed> (single-task models: runs/<model>-<seed>)."""
  strategies = registry.spec(config.model).twin is not None
  name = (f"{config.model}-{config.strategy}-{config.seed}" if strategies
          else f"{config.model}-{config.seed}")
  return Path("runs") / name


def sync(name: str) -> None:
  """Waits for every process (multi-process runs), e.g. between workdir checks and writes."""
  if jax.process_count() > 1:
    multihost_utils.sync_global_devices(name)


@contextlib.contextmanager
def held(workdir: Path, what: str) -> Iterator[None]:
  """The workdir held for one run (sljax.io.files.exclusive on the main process): a second run
  there stops with one line naming the first, on every process of a multi-process run (the
  others would otherwise wait for the main one at the next sync until the coordinator gave
  up)."""
  if jax.process_count() == 1:
    with files.exclusive(workdir, what):
      yield
    return
  with contextlib.ExitStack() as stack:
    refusal = None
    if jax.process_index() == 0:
      try:
        stack.enter_context(files.exclusive(workdir, what))
      except SljaxError as e:
        refusal = e
    if int(multihost_utils.broadcast_one_to_all(np.int32(refusal is not None))):
      raise refusal or SljaxError(f"{workdir}: in use by another run (process 0 found it "
                                  "held and names it)")
    yield


def _relative_note(value: Any) -> str:
  """For a saved relative path: where it points from here (it was relative to the folder the
  run started in, which config.json does not record)."""
  if not isinstance(value, str) or Path(value).is_absolute():
    return ""
  here = Path(value).absolute()
  return (f" (a path relative to the folder the run started in: {here} from here"
          + ("" if here.exists() else ", which does not exist") + ")")


def accepted_paths(saved: dict[str, Any], new: dict[str, Any]) -> dict[str, str]:
  """{field: value to record} of the path fields where the saved value names the folder the new
  absolute value names: the same folder however spelled, or a relative path (written by runs
  before paths were recorded absolute) that does not exist from here (the run started in
  another folder; the data-derived fields n_train, n_val and t are still compared)."""
  out = {}
  for k in PATH_FIELDS:
    s, n = saved.get(k), new.get(k)
    if not (isinstance(s, str) and isinstance(n, str)) or s == n:
      continue
    if Path(s).resolve() == Path(n).resolve():
      # The same folder, spelled as the run typed it (relative, a trailing slash, a symlink):
      # the run's config.json keeps its own spelling.
      out[k] = s
    elif not Path(s).is_absolute() and not Path(s).exists():
      out[k] = n  # recorded absolute from now on, so a resume works from any folder
  return out


def has_checkpoints(workdir: Path) -> bool:
  """Whether workdir/checkpoints holds a step folder (damaged or not)."""
  ckpt_dir = workdir / CHECKPOINT_DIR
  return ckpt_dir.is_dir() and any(p.name.isdigit() for p in ckpt_dir.iterdir())


def check_config_kept(workdir: Path) -> None:
  """SljaxError when workdir has checkpoints but no config.json: a resume would load them into
  whatever the flags say, and a new run would write its own beside them (the one refusal)."""
  if has_checkpoints(workdir) and not (workdir / CONFIG_FILE).is_file():
    raise SljaxError(f"{workdir}: has checkpoints but no {CONFIG_FILE}, so the run they belong "
                     f"to is unknown; put its {CONFIG_FILE} back (to --resume it), or pass "
                     "--overwrite to start again")


def prepare_workdir(workdir: Path, config_json: dict[str, Any], resume: bool,
                    overwrite: bool) -> tuple[bool, dict[str, Any]]:
  """Checks the workdir against the run (every process, before any writes; nothing is
  deleted here: --overwrite clears the old run with clear_run once every check has passed);
  returns (whether there is a checkpoint to resume, the config.json to write)."""
  cfg_path = workdir / CONFIG_FILE
  has_ckpt = has_checkpoints(workdir)
  if not overwrite:
    check_config_kept(workdir)
  if cfg_path.exists() and not overwrite:
    saved = read_config(workdir)
    paths = accepted_paths(saved, config_json)
    diff = diff_configs(saved, dict(config_json, **{k: saved[k] for k in paths}))
    config_json = dict(config_json, **paths)
    if diff:
      detail = ", ".join(f"{k}: {saved.get(k)!r}"
                         f"{_relative_note(saved.get(k)) if k in PATH_FIELDS else ''}"
                         f" -> {config_json.get(k)!r}" for k in diff[:4])
      # A relative path that names a folder here may not be the run's: say where it points.
      notes = "".join(f"; its {k} {saved[k]!r} is{_relative_note(saved[k])}"
                      for k in PATH_FIELDS if k not in diff and _relative_note(saved.get(k)))
      raise SljaxError(f"{workdir}: holds another run ({detail}{notes}); choose another "
                       "--workdir or pass --overwrite to replace it")
    if not resume and (has_ckpt or (workdir / METRICS_FILE).exists()):
      raise SljaxError(f"{workdir}: holds this run already; pass --resume to continue it or "
                       "--overwrite to start again")
  sync("sljax-workdir-checked")
  return has_ckpt and resume and not overwrite, config_json


def clear_run(workdir: Path) -> None:
  """--overwrite: deletes the old run's checkpoints, logs and config.json (the main process),
  called only once the new run has passed its checks, so that a refused run loses nothing."""
  if jax.process_index() == 0:
    if (workdir / CHECKPOINT_DIR).exists():  # a failure here is one line, not a mixed run
      shutil.rmtree(workdir / CHECKPOINT_DIR)
    for name in (METRICS_FILE, EPOCHS_FILE, VALIDATION_FILE, CONFIG_FILE):
      (workdir / name).unlink(missing_ok=True)
  sync("sljax-workdir-cleared")  # no process may list checkpoints while they are deleted


def write_config(workdir: Path, config_json: dict[str, Any]) -> None:
  """Writes the resolved config.json (the main process; the only place it is written)."""
  if jax.process_index() == 0:
    with storage_guard(f"writing {CONFIG_FILE}", workdir / CHECKPOINT_DIR):
      workdir.mkdir(parents=True, exist_ok=True)
      files.write_text(workdir / CONFIG_FILE, dumps(config_json) + "\n")  # never half-written
  sync("sljax-workdir-ready")


def _truncate_jsonl(path: Path, keep: Callable[[dict[str, Any]], bool]) -> None:
  """Drops lines written after the checkpoint a run resumes from, and lines that are not a JSON
  object (a torn last line, or outside damage)."""
  if not path.exists():
    return
  try:
    data = path.read_bytes()
  except OSError as e:  # a folder in its place: resuming would end in a traceback
    raise SljaxError(f"{path}: cannot read the run's log ({e.strerror or e})") from None
  lines = []
  for raw in data.splitlines():
    try:  # line by line: damaged bytes drop their line, not the resume
      line = raw.decode("utf-8")
      rec = json.loads(line)
    except (UnicodeDecodeError, json.JSONDecodeError):
      continue
    if isinstance(rec, dict) and keep(rec):
      lines.append(line)
  files.write_text(path, "".join(l + "\n" for l in lines))  # a kill here keeps the old log


def restart_logs(workdir: Path, step: int, steps_per_epoch: int) -> None:
  """Drops the log lines after the checkpoint resumed from (all of them for a fresh start)."""
  if jax.process_index() != 0:
    return
  _truncate_jsonl(workdir / METRICS_FILE, lambda r: _at_most(r, "step", step))
  _truncate_jsonl(workdir / EPOCHS_FILE, lambda r: _at_most(r, "epoch", step // steps_per_epoch))
  _truncate_jsonl(workdir / VALIDATION_FILE, lambda r: _at_most(r, "step", step))


def _at_most(row: dict[str, Any], key: str, limit: int) -> bool:
  """Whether a log row is from before limit (a row without the key counts as 0); a row whose
  key is no number is damage, dropped like a torn line."""
  value = row.get(key, 0)
  return type(value) in (int, float) and value <= limit


class MetricWriter:
  """The run's JSON lines: metrics.jsonl (a row per step), epochs.jsonl (a row per epoch),
  validation.jsonl (a row per validation, when validating by steps), mirrored to TensorBoard
  event files with --tensorboard. Writes on the main process only; a full or read-only disk ends
  the run with one line (checkpoint.storage_guard)."""

  def __init__(self, workdir: Path, enabled: bool, tensorboard: bool = False,
               first_step: int = 0, by_steps: bool = False):
    self.checkpoints = workdir / CHECKPOINT_DIR
    names = (METRICS_FILE, EPOCHS_FILE) + (VALIDATION_FILE,) * by_steps
    with storage_guard("opening the run's logs", self.checkpoints):
      self.files = ({name: open(workdir / name, "a", encoding="utf-8")
                     for name in names} if enabled else {})
      self.tensorboard = TensorBoardWriter(workdir, first_step) if enabled and tensorboard \
          else None

  def write(self, name: str, rows: Sequence[dict[str, Any]]) -> None:
    """Appends rows to one of the files and flushes it."""
    with storage_guard(f"writing {name}", self.checkpoints):
      if name in self.files:
        self.files[name].write("".join(json.dumps(r) + "\n" for r in rows))
        self.files[name].flush()
      if self.tensorboard is not None:
        self.tensorboard.write(name, rows)

  def close(self) -> None:
    """Closes the files."""
    with storage_guard("closing the run's logs", self.checkpoints):
      for f in self.files.values():
        f.close()
      if self.tensorboard is not None:
        self.tensorboard.close()
