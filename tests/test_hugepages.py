"""sljax.runtime.hugepages: when a command line starts again with glibc's huge-page tunable, that it
starts once with its arguments and interpreter flags, and that malloc then gets huge pages."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from sljax.runtime import hugepages

ROOT = Path(__file__).resolve().parents[1]
GLIBC = (2, 36)
USABLE = (sys.platform.startswith("linux") and hugepages.glibc_version() is not None
          and hugepages.glibc_version() >= hugepages.MIN_GLIBC)


@pytest.mark.parametrize("text, mode", [("always [madvise] never\n", "madvise"),
                                        ("[always] madvise never\n", "always"),
                                        ("always madvise [never]\n", "never"),
                                        ("garbled\n", "")])
def test_thp_mode_reads_the_bracketed_choice(tmp_path, text, mode):
  path = tmp_path / "enabled"
  path.write_text(text)
  assert hugepages.thp_mode(str(path)) == mode


def test_thp_mode_without_the_file_is_unknown(tmp_path):
  assert hugepages.thp_mode(str(tmp_path / "missing")) == ""


def test_restart_adds_the_tunable_to_the_environment():
  environ = {"PATH": "/bin", "GLIBC_TUNABLES": "glibc.malloc.arena_max=2"}
  env = hugepages.restart_environment(environ, "madvise", GLIBC)
  assert env == {"PATH": "/bin",
                 "GLIBC_TUNABLES": "glibc.malloc.arena_max=2:glibc.malloc.hugetlb=1"}
  assert environ["GLIBC_TUNABLES"] == "glibc.malloc.arena_max=2"  # the caller's is untouched
  assert hugepages.restart_environment({}, "madvise", GLIBC) == {
      "GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}


@pytest.mark.parametrize("environ, mode, glibc", [
    ({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"}, "madvise", GLIBC),  # the user's choice
    ({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}, "madvise", GLIBC),  # the second start
    ({"SLJAX_HUGEPAGES": "0"}, "madvise", GLIBC),
    ({}, "always", GLIBC), ({}, "never", GLIBC), ({}, "", GLIBC),
    ({}, "madvise", (2, 34)), ({}, "madvise", None)])
def test_no_restart_where_it_cannot_help_or_was_declined(environ, mode, glibc):
  assert hugepages.restart_environment(environ, mode, glibc) is None


def test_active_reads_the_tunable_among_others():
  assert hugepages.active({"GLIBC_TUNABLES": "glibc.malloc.arena_max=2:glibc.malloc.hugetlb=1"})
  assert not hugepages.active({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"})
  assert not hugepages.active({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=10"})
  assert not hugepages.active({})


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux")
def test_glibc_version_is_the_running_librarys():
  import ctypes
  libc = ctypes.CDLL(None)
  if not hasattr(libc, "gnu_get_libc_version"):  # musl and others
    assert hugepages.glibc_version() is None
    return
  libc.gnu_get_libc_version.restype = ctypes.c_char_p
  version = libc.gnu_get_libc_version().decode()  # asked of the library itself
  assert hugepages.glibc_version() == tuple(int(p) for p in version.split(".")[:2])


SET_BY_TEST = ("GLIBC_TUNABLES", "SLJAX_HUGEPAGES", "PYTHONOPTIMIZE")


def _child(tmp_path: Path, body: str, *flags: str, env: dict | None = None) -> list[str]:
  """Output lines of a child python (with `flags`) whose script pretends the kernel offers
  huge pages on request, then calls reexec() and runs `body`."""
  script = tmp_path / "child.py"
  script.write_text(textwrap.dedent(f"""\
      import os, sys
      sys.path.insert(0, {str(ROOT)!r})
      from sljax.runtime import hugepages
      hugepages.thp_mode = lambda path=None: "madvise"
      print("start", os.environ.get("GLIBC_TUNABLES"), sys.argv[1:], sys.flags.optimize,
            flush=True)
      hugepages.reexec()
      """) + textwrap.dedent(body))
  environ = {k: v for k, v in os.environ.items() if k not in SET_BY_TEST}
  out = subprocess.run([sys.executable, *flags, str(script), "a b", "--c"], capture_output=True,
                       text=True, env={**environ, **(env or {})}, check=True, timeout=60)
  return out.stdout.splitlines()


@pytest.mark.skipif(not USABLE, reason="needs Linux and glibc >= 2.35")
def test_reexec_starts_once_more_with_the_same_arguments_and_flags(tmp_path):
  lines = _child(tmp_path, 'print("pid", os.getpid(), os.environ["GLIBC_TUNABLES"])\n',
                 "-O")
  assert lines[:2] == ["start None ['a b', '--c'] 1",
                       "start glibc.malloc.hugetlb=1 ['a b', '--c'] 1"]
  assert lines[2].startswith("pid ") and lines[2].endswith(" glibc.malloc.hugetlb=1")
  assert len(lines) == 3


@pytest.mark.skipif(not USABLE, reason="needs Linux and glibc >= 2.35")
def test_reexec_declined_runs_on_in_the_same_process(tmp_path):
  lines = _child(tmp_path, 'print("on")\n', env={"SLJAX_HUGEPAGES": "0"})
  assert lines == ["start None ['a b', '--c'] 0", "on"]


# A 64 MiB malloc, touched, and how many of its KiB the kernel backs with huge pages.
HUGE_KIB = """
import ctypes
libc = ctypes.CDLL(None)
libc.malloc.restype = ctypes.c_void_p
def huge_kib():
  for line in open("/proc/self/smaps_rollup"):
    if line.startswith("AnonHugePages:"):
      return int(line.split()[1])
before = huge_kib()
p = libc.malloc(64 << 20)
ctypes.memset(p, 1, 64 << 20)
print("huge", huge_kib() - before)
"""


@pytest.mark.skipif(not USABLE or hugepages.thp_mode() != "madvise"
                    or not Path("/proc/self/smaps_rollup").exists(),
                    reason="needs glibc >= 2.35 and huge pages on request (madvise)")
def test_malloc_gets_huge_pages_after_the_restart_and_not_without(tmp_path):
  with_them = _child(tmp_path, HUGE_KIB)
  without = _child(tmp_path, HUGE_KIB, env={"SLJAX_HUGEPAGES": "0"})
  assert int(with_them[-1].split()[1]) >= 32 << 10, with_them  # at least half the block
  assert int(without[-1].split()[1]) == 0, without
