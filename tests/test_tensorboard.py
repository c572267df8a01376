"""--tensorboard: the event files hold every logged scalar at its global step (read back by
parsing the TFRecord framing and Event protos here), a resume purges what follows its step,
and a missing tensorboardX is one clear line."""

import dataclasses
import json
import struct
import sys

import numpy as np
import pytest
import tensorboardX  # noqa: F401  (in the test extra: these tests run, never skip)

from sljax.errors import SljaxError
from sljax.train import loop
from sljax.train import tensorboard as tb
from sljax.train.config import validate
from sljax.train.workdir import EPOCHS_FILE, METRICS_FILE

from test_loop import _config, tiny  # noqa: F401  (fixture)

QUIET = dict(log=lambda line: None, progress=False)


def read_events(path):
  """Every Event in an event file, in order (TFRecord: u64 length, u32 CRC, data, u32 CRC;
  the payload is an Event protobuf)."""
  from tensorboardX.proto import event_pb2  # pylint: disable=import-outside-toplevel
  data, events, pos = path.read_bytes(), [], 0
  while pos < len(data):
    (n,) = struct.unpack("<Q", data[pos:pos + 8])
    events.append(event_pb2.Event.FromString(data[pos + 12:pos + 12 + n]))
    pos += 12 + n + 4
  assert pos == len(data), path  # no torn record
  return events


def event_files(workdir):
  """The run's event files, oldest first."""
  return sorted((workdir / tb.TB_DIR).glob("events.out.tfevents.*"))


def scalars(events):
  """{tag: {step: value}} of the scalar summaries."""
  out = {}
  for e in events:
    for v in e.summary.value:
      out.setdefault(v.tag, {})[e.step] = v.simple_value
  return out


def test_event_file_holds_the_run_scalars(tiny, tmp_path):
  cfg = _config("unc", tensorboard=True, epochs=2)
  loop.train(cfg, tmp_path / "w", **QUIET)
  (events,) = event_files(tmp_path / "w")
  got = scalars(read_events(events))
  rows = [json.loads(l) for l in (tmp_path / "w" / METRICS_FILE).read_text().splitlines()]
  epochs = [json.loads(l) for l in (tmp_path / "w" / EPOCHS_FILE).read_text().splitlines()]
  assert len(rows) == 12 and len(epochs) == 2
  for key in ("loss", "loss_sl", "loss_disp", "w_sl", "w_disp", "sigma_sl", "sigma_disp"):
    want = {r["step"]: r[key] for r in rows}
    assert set(got[f"train/{key}"]) == set(want), key
    np.testing.assert_allclose([got[f"train/{key}"][s] for s in want], list(want.values()),
                               rtol=1e-6)  # float32 in the event file
  for key, tag in (("val_mae", "val/mae"), ("samples_per_s", "perf/samples_per_s"),
                   ("loss_disp", "epoch/loss_disp"), ("w_sl", "epoch/w_sl")):
    want = {r["step"]: r[key] for r in epochs}
    np.testing.assert_allclose([got[tag][s] for s in want], list(want.values()), rtol=1e-6)


def test_resume_purges_the_events_after_its_step(tiny, tmp_path):
  """An interrupted run resumed from step 6 writes a purge marker at step 7, so TensorBoard
  drops the first attempt's events after 6; the resumed events cover 7.. again."""
  cfg = _config("stl", tensorboard=True, epochs=2, save_every=0)
  loop.train(cfg, tmp_path / "w", stop_after=9, **QUIET)  # checkpoint at 6, rows up to 9
  loop.train(cfg, tmp_path / "w", resume=True, **QUIET)
  files = event_files(tmp_path / "w")
  assert len(files) == 2
  from tensorboardX.proto import event_pb2  # pylint: disable=import-outside-toplevel
  starts = [[e.step for e in read_events(f) if e.HasField("session_log")
             and e.session_log.status == event_pb2.SessionLog.START] for f in files]
  assert starts == [[1], [7]]
  first, second = (scalars(read_events(f))["train/loss"] for f in files)
  assert sorted(first) == list(range(1, 10)) and sorted(second) == list(range(7, 13))


def test_missing_package_is_one_line(monkeypatch):
  monkeypatch.setitem(sys.modules, "tensorboardX", None)  # import fails
  with pytest.raises(SljaxError, match=r"--tensorboard needs the tensorboardX package"):
    validate(dataclasses.replace(_config("stl"), tensorboard=True))
  validate(_config("stl"))  # without the flag nothing is needed


def test_tags():
  assert tb.tag(METRICS_FILE, "loss_sl") == "train/loss_sl"
  assert tb.tag(EPOCHS_FILE, "val_mae") == "val/mae"
  assert tb.tag(EPOCHS_FILE, "samples_per_s") == "perf/samples_per_s"
  assert tb.tag(EPOCHS_FILE, "loss_disp") == "epoch/loss_disp"
