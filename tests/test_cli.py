import io
import subprocess
import sys

import pytest

from sljax import cli
from sljax.errors import SljaxError, run_command


def _subcommands():
  parser = cli.build_parser()
  action = next(a for a in parser._actions if a.dest == "command")
  return sorted(action.choices)


def test_top_level_help_lists_commands(capsys):
  with pytest.raises(SystemExit) as e:
    cli.main(["--help"])
  assert e.value.code == 0
  out = capsys.readouterr().out
  for name in _subcommands():
    assert name in out


@pytest.mark.parametrize("name", _subcommands())
def test_each_subcommand_has_help(name, capsys):
  with pytest.raises(SystemExit) as e:
    cli.main([name, "--help"])
  assert e.value.code == 0
  assert "usage" in capsys.readouterr().out


def test_console_script_module_runs():
  r = subprocess.run([sys.executable, "-m", "sljax.cli", "--help"], capture_output=True, text=True)
  assert r.returncode == 0 and "COMMAND" in r.stdout


def test_a_failed_file_operation_is_one_line_naming_the_path(tmp_path, capsys):
  """An OSError reaching the command line (here a file where the OUT folder must be; the same
  path serves read-only and full disks) prints the path and the reason, exit 2, no traceback."""
  blocker = tmp_path / "f"
  blocker.write_text("hi")
  assert cli.main(["experiment", "run", "table2", str(blocker), "--scale", "smoke",
                   "--no-progress"]) == 2
  err = capsys.readouterr().err
  assert err.startswith("sljax experiment: error: ") and str(blocker) in err
  assert "Traceback" not in err and len(err.strip().splitlines()) == 1
  assert blocker.read_text() == "hi"


def test_describe_os_error_names_both_paths():
  from sljax.errors import describe_os_error
  e = OSError(28, "No space left on device", "/disk/a.tmp", None, "/disk/a")
  assert describe_os_error(e) == "/disk/a.tmp -> /disk/a: No space left on device"
  assert describe_os_error(OSError("bare")) == "bare"


def _raise(e):
  raise e


@pytest.mark.parametrize("exc, code, line", [
    (None, 0, ""),
    (SljaxError("data: bad"), 2, "prog: error: data: bad"),
    (OSError(30, "Read-only file system", "/ro/x"), 2, "prog: error: /ro/x: Read-only file system"),
    (KeyboardInterrupt(), 130, "prog: interrupted (note)"),
])
def test_run_command_turns_each_failure_into_one_line_and_a_code(exc, code, line, capsys):
  """The one mapping from failures to exit codes that train.py and every sljax command use."""
  got = run_command("prog", (lambda: 7) if exc is None else (lambda: _raise(exc)),
                    lambda: " (note)")
  assert got == ((0, 7) if exc is None else (code, None))
  err = capsys.readouterr().err
  assert err == (line + "\n" if line else "")


@pytest.mark.parametrize("quiet, code, err", [
    (True, 0, ""),
    (False, 2, "prog: error: Broken pipe\n"),
])
def test_a_closed_pipe(quiet, code, err):
  """`sljax info DATA | head -1`: the reader goes away; the commands end quietly with 0, but
  training (quiet off) says so and exits 2, never passing an unfinished run off as done."""
  script = ("import sys; from sljax.errors import run_command\n"
            "def f():\n"
            "  for i in range(100000): print('line', i)\n"
            f"sys.exit(run_command('prog', f, quiet_broken_pipe={quiet})[0])\n")
  p = subprocess.run(f"set -o pipefail; {sys.executable} -c \"{script}\" | head -1",
                     shell=True, executable="/bin/bash", capture_output=True, text=True)
  assert (p.returncode, p.stdout, p.stderr) == (code, "line 0\n", err)


def test_a_closed_pipe_with_a_replaced_stdout(monkeypatch, capsys):
  """In a notebook stdout has no file descriptor: still no traceback."""
  monkeypatch.setattr(sys, "stdout", io.StringIO())
  assert run_command("prog", lambda: _raise(BrokenPipeError()), quiet_broken_pipe=True) == (
      0, None)
