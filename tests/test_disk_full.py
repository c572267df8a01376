"""A full disk, a read-only or unwritable workdir: the run ends with one line naming what failed
and the last good checkpoint, that checkpoint stays intact, and --resume then ends exactly as
the uninterrupted run (parameters, optimiser state, every logged row)."""

import errno
import os

import pytest
from orbax.checkpoint._src.path import atomicity

from sljax.errors import SljaxError
from sljax.models import checkpoint as ckpt
from sljax.models import failures
from sljax.train import cli as train_cli
from sljax.train import loop, workdir

from test_loop import _assert_same_run, _config, _final, tiny  # noqa: F401  (fixture)

QUIET = dict(log=lambda line: None, progress=False)
ENOSPC_TEXT = os.strerror(errno.ENOSPC)


def _fail_finalize(monkeypatch, step: int, exc: Exception) -> None:
  """Orbax's background finalisation of checkpoint `step` raises exc (its files are written
  under the tmp name, the rename into place never happens)."""
  finalize = atomicity.AtomicRenameTemporaryPath.finalize

  async def failing(self, *args, **kwargs):
    if self._final_path.name == str(step):
      raise exc
    return await finalize(self, *args, **kwargs)

  monkeypatch.setattr(atomicity.AtomicRenameTemporaryPath, "finalize", failing)


def _tensorstore_enospc(path) -> Exception:
  """What TensorStore raises on a full disk (seen on a full tmpfs), wrapped once more."""
  inner = ValueError(f'RESOURCE_EXHAUSTED: Error writing "float32/0" in OCDBT database at local '
                     f'file "{path}/ocdbt.process_0/": Failed writing: "{path}/d/0a1b": Failed '
                     f"to write 199819 bytes to file 4: {ENOSPC_TEXT} [os_error_code='28']")
  try:
    raise inner
  except ValueError as e:
    try:
      raise RuntimeError("Failed to run 4 Handler Commit operations") from e
    except RuntimeError as outer:
      return outer


@pytest.mark.parametrize("how", ["oserror", "tensorstore", "readonly"])
def test_failed_save_stops_with_one_line_and_resume_is_exact(how, tiny, monkeypatch, tmp_path):
  cfg = _config("epr", save_every=4)  # 6 steps per epoch: saves at 4, 6, 8, 12, 16, 18, ...
  loop.train(cfg, tmp_path / "full", **QUIET)
  wd = tmp_path / "run"
  ck = wd / ckpt.CHECKPOINT_DIR
  exc = {"oserror": OSError(errno.ENOSPC, ENOSPC_TEXT, str(ck / "16.orbax-checkpoint-tmp")),
         "tensorstore": _tensorstore_enospc(ck / "16.orbax-checkpoint-tmp/state"),
         "readonly": OSError(errno.EROFS, os.strerror(errno.EROFS), str(ck / "16"))}[how]
  with monkeypatch.context() as m:
    _fail_finalize(m, 16, exc)
    with pytest.raises(SljaxError) as info:
      loop.train(cfg, wd, **QUIET)
  msg = str(info.value)
  assert "\n" not in msg
  assert "checkpoint" in msg and os.strerror(exc.errno if how != "tensorstore" else 28) in msg
  assert f"the last good checkpoint is step 12 ({ck / '12'})" in msg and "--resume" in msg
  if how != "readonly":  # the failing save is named by its step
    assert msg.startswith("saving checkpoint 16 failed: "), msg
  # Nothing half-written is visible: checkpoint 16 never became a step; 12 restores.
  assert failures.last_good_step(ck) == 12 and _final(wd)[0] == 12
  result = loop.train(cfg, wd, resume=True, **QUIET)  # "space is back"
  assert result.step == 24
  _assert_same_run(tmp_path / "full", wd)


def test_full_disk_while_writing_metrics(tiny, monkeypatch, tmp_path):
  """metrics.jsonl hits a full disk mid-row: one line, and the torn row is dropped on resume."""
  cfg = _config("stl", save_every=4)
  loop.train(cfg, tmp_path / "full", **QUIET)
  init = workdir.MetricWriter.__init__

  class FullFile:
    def __init__(self, f):
      self.f = f

    def write(self, text):
      if '"step": 10,' in text:
        self.f.write(text[:7])  # a torn row, then the disk is full
        self.f.flush()
        raise OSError(errno.ENOSPC, ENOSPC_TEXT)
      return self.f.write(text)

    def __getattr__(self, name):
      return getattr(self.f, name)

  def full_disk_init(self, *args, **kwargs):
    init(self, *args, **kwargs)
    self.files[workdir.METRICS_FILE] = FullFile(self.files[workdir.METRICS_FILE])

  wd = tmp_path / "run"
  with monkeypatch.context() as m:
    m.setattr(workdir.MetricWriter, "__init__", full_disk_init)
    with pytest.raises(SljaxError, match=f"writing metrics.jsonl failed: {ENOSPC_TEXT}"):
      loop.train(cfg, wd, **QUIET)
  loop.train(cfg, wd, resume=True, **QUIET)
  _assert_same_run(tmp_path / "full", wd)


def test_read_only_workdir_from_the_start(tiny, monkeypatch, tmp_path):
  """The workdir cannot be created (read-only filesystem): one line, no checkpoint yet."""
  real_mkdir = type(tmp_path).mkdir

  def readonly_mkdir(self, *args, **kwargs):
    if self.name == "ro":
      raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(self))
    return real_mkdir(self, *args, **kwargs)

  monkeypatch.setattr(type(tmp_path), "mkdir", readonly_mkdir)
  with pytest.raises(SljaxError) as info:
    loop.train(_config("stl"), tmp_path / "ro", **QUIET)
  assert "Read-only file system" in str(info.value) and "no checkpoint was saved yet" in \
      str(info.value)


def test_cli_prints_one_line_without_traceback(tiny, monkeypatch, tmp_path, capfd):
  """train.py: rc 2 and one line; orbax's own error logs (a traceback per thread) are not
  shown for a failure that is reported."""
  _fail_finalize(monkeypatch, 6, OSError(errno.ENOSPC, ENOSPC_TEXT, str(tmp_path / "w")))
  rc = train_cli.main(["--preset", "quick", "--size", "32", "--maxdisp", "16", "--epochs", "2",
                       "--batch-size", "2", "--max-val", "2", "--workdir", str(tmp_path / "w"),
                       "--no-progress"])
  err = capfd.readouterr().err
  assert rc == 2
  assert "Traceback" not in err, err[-3000:]
  lines = [l for l in err.splitlines() if l.strip()]
  assert lines[-1].startswith("train.py: error: saving") and ENOSPC_TEXT in lines[-1], err


def test_storage_errno_finds_the_cause():
  """Direct OSErrors, chained ones, exception groups and TensorStore messages; other errors
  are not storage failures."""
  assert failures.storage_errno(OSError(errno.EACCES, "Permission denied", "/x")) == (errno.EACCES,
                                                                                  "/x")
  assert failures.storage_errno(_tensorstore_enospc("/w/c"))[0] == errno.ENOSPC
  assert failures.storage_errno(_tensorstore_enospc("/w/c"))[1] == "/w/c/d/0a1b"
  group = ExceptionGroup("many", [ValueError("x"), OSError(errno.EDQUOT, "quota")])
  assert failures.storage_errno(group)[0] == errno.EDQUOT
  assert failures.storage_errno(ValueError("shape mismatch")) is None
  assert failures.storage_errno(OSError(errno.ENOENT, "No such file")) is None


def test_resume_drops_damaged_log_lines(tmp_path):
  """Lines of metrics.jsonl / epochs.jsonl that are not a JSON object (a torn write, a list, a
  number, undecodable bytes) are dropped on resume, as are rows after the checkpoint; the rest is
  kept byte for byte."""
  good = [b'{"step": 1, "loss": 0.5}', b'{"step": 2, "loss": 0.25}']
  bad = [b"[1, 2]", b"3", b'"text"', b'{"step": 3, "lo\xff\xfess": 1}', b'{"step": 4, "lo']
  (tmp_path / workdir.METRICS_FILE).write_bytes(
      b"\n".join([good[0], bad[0], bad[1], good[1], bad[2], bad[3], b'{"step": 9}', bad[4]]))
  (tmp_path / workdir.EPOCHS_FILE).write_bytes(b'{"epoch": 1}\n[0]\n{"epoch": 5}\n')
  workdir.restart_logs(tmp_path, step=3, steps_per_epoch=2)
  assert (tmp_path / workdir.METRICS_FILE).read_bytes() == b"".join(g + b"\n" for g in good)
  assert (tmp_path / workdir.EPOCHS_FILE).read_text() == '{"epoch": 1}\n'
