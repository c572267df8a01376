"""sljax.machine's reading of how busy other processes keep the CPUs (the tuner's guard against
measuring beside other work): hand-made /proc/stat lines, and a real busy process."""

import os
import subprocess
import sys
import time

import pytest

from sljax import machine

HZ = os.sysconf("SC_CLK_TCK")


def _stat(tmp_path, name, user, system, idle, iowait, steal):
  """A /proc/stat whose first line holds these ticks (nice, irq, softirq 0)."""
  path = tmp_path / name
  path.write_text(f"cpu  {user} 0 {system} {idle} {iowait} 0 0 {steal} 0 0\n"
                  f"cpu0 {user} 0 {system} {idle} {iowait} 0 0 {steal} 0 0\nintr 1\n")
  return str(path)


def test_snapshot_reads_all_cores_busy_and_this_process(tmp_path):
  total, busy, own = machine.cpu_snapshot(_stat(tmp_path, "s", 300, 100, 500, 50, 50))
  assert total == pytest.approx(1000 / HZ)
  assert busy == pytest.approx(450 / HZ)  # idle and iowait are not busy; steal is
  t = os.times()
  assert own == pytest.approx(t.user + t.system, abs=0.5)
  assert machine.cpu_snapshot(str(tmp_path / "absent")) is None
  (tmp_path / "bad").write_text("intr 1 2 3\n")
  assert machine.cpu_snapshot(str(tmp_path / "bad")) is None


def test_others_share_by_hand():
  # 10 s of two cores: 20 CPU-seconds, 13 busy, 3 of them this process's -> 10 others'.
  assert machine.others_share((100.0, 40.0, 5.0), (120.0, 53.0, 8.0)) == pytest.approx(0.5)
  assert machine.others_share((100.0, 40.0, 5.0), (120.0, 43.0, 8.0)) == 0.0  # all ours
  assert machine.others_share(None, (1.0, 1.0, 1.0)) is None
  assert machine.others_share((1.0, 1.0, 1.0), None) is None
  assert machine.others_share((1.0, 1.0, 1.0), (1.0, 1.0, 1.0)) is None  # no time passed


@pytest.mark.skipif(machine.cpu_snapshot() is None, reason="no /proc/stat here")
def test_a_busy_process_beside_is_seen():
  spin = "import time\nt = time.time()\nwhile time.time() - t < 2.5: pass\n"
  child = subprocess.Popen([sys.executable, "-c", spin])
  try:
    time.sleep(0.5)
    share = machine.others_now(1.5)
  finally:
    child.wait()
  assert share is not None and share * os.cpu_count() >= 0.5  # at least half a core elsewhere
