"""benchmarks/profile_step.py's exclusive times against a hand-computed trace."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import profile_step  # noqa: E402  (after the path)


def span(name, ts, dur, tid=1):
  return {"ph": "X", "name": name, "ts": ts, "dur": dur, "pid": 1, "tid": tid}


def test_exclusive_times_by_hand():
  events = [span("while.3", 0, 100), span("ynn_fusion.1", 10, 20), span("add.7", 15, 5),
            span("ynn_fusion.2", 40, 20), span("ynn_fusion.1", 0, 50, tid=2),
            {"ph": "i", "name": "marker", "ts": 5}, span("ThunkExecutor::Execute", 0, 500, tid=3)]
  ex = profile_step.exclusive_times(events)
  # while: 100 - 20 - 20; the first fusion: 20 - 5 on thread 1, plus 50 on thread 2
  assert ex == {"while.3": 60, "ynn_fusion.1": 65, "add.7": 5, "ynn_fusion.2": 20,
                "ThunkExecutor::Execute": 500}
  assert profile_step.by_kind(ex) == {"while": 60, "ynn_fusion": 85, "add": 5}
