"""sljax.runtime.machine's reading of how busy other processes keep the CPUs (the tuner's guard against
measuring beside other work): hand-made /proc/stat lines, and a real busy process."""

import os
import subprocess
import sys
import time

import pytest

from sljax.runtime import machine

HZ = os.sysconf("SC_CLK_TCK")


def _stat(tmp_path, name, *cores):
  """A /proc/stat with one line per core of (user, system, idle, iowait, steal, guest) ticks,
  the all-cores line first as the kernel writes it (nice, irq, softirq 0)."""
  line = lambda n, u, sy, i, io, st, g: f"{n} {u} 0 {sy} {i} {io} 0 0 {st} {g} 0\n"
  sums = [sum(c[k] for c in cores) for k in range(6)]
  path = tmp_path / name
  path.write_text(line("cpu ", *sums) + "".join(line(f"cpu{i}", *c) for i, c in enumerate(cores))
                  + "intr 1 2\nctxt 3\n")
  return str(path)


def test_snapshot_reads_the_usable_cores_busy_and_this_process(tmp_path):
  stat = _stat(tmp_path, "s", (300, 100, 500, 50, 50, 40), (10, 0, 990, 0, 0, 0),
               (200, 0, 700, 100, 0, 0))
  total, busy, own = machine.cpu_snapshot(stat, cpus={0, 2})
  assert total == pytest.approx((1000 + 1000) / HZ)  # guest (inside user already) not again
  assert busy == pytest.approx((450 + 200) / HZ)  # idle and iowait are not busy; steal is
  t = os.times()
  assert own == pytest.approx(t.user + t.system, abs=0.5)
  assert machine.cpu_snapshot(stat, cpus={1})[:2] == pytest.approx((1000 / HZ, 10 / HZ))
  assert machine.cpu_snapshot(str(tmp_path / "absent")) is None
  for bad in ("", "intr 1 2 3\n", "cpu  1 2 3 4 5 6 7 8\n", "cpu0 1 2 x 4 5 6 7 8\n",
              "cpu0 1 2 3\n"):
    (tmp_path / "bad").write_text(bad)
    assert machine.cpu_snapshot(str(tmp_path / "bad"), cpus={0}) is None, bad


def test_others_share_by_hand():
  # 10 s of two cores: 20 CPU-seconds, 13 busy, 3 of them this process's -> 10 others'.
  assert machine.others_share((100.0, 40.0, 5.0), (120.0, 53.0, 8.0)) == pytest.approx(0.5)
  assert machine.others_share((100.0, 40.0, 5.0), (120.0, 43.0, 8.0)) == 0.0  # all ours
  # Clock ticks and process time are counted apart: slightly more "ours" than busy is 0, not
  # negative, and a share over 1 is 1.
  assert machine.others_share((100.0, 40.0, 5.0), (120.0, 43.0, 8.5)) == 0.0
  assert machine.others_share((100.0, 40.0, 5.0), (120.0, 61.0, 5.0)) == 1.0
  assert machine.others_share(None, (1.0, 1.0, 1.0)) is None
  assert machine.others_share((1.0, 1.0, 1.0), None) is None
  # A few ticks are no measurement (two snapshots a microsecond apart once read 100%).
  assert machine.others_share((1.0, 1.0, 1.0), (1.01, 1.01, 1.0)) is None


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
