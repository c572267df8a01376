import subprocess
import sys

import pytest

from sljax import cli


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
