"""`sljax train` is `python train.py`: the same flags, the same run, errors naming the command;
and `sljax` imports only the command it runs."""

import json
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np

from sljax import cli
from sljax.data.scene import Scene, write_scene
from sljax.models import load as trained
from sljax.train import cli as train_cli


def _options(parser):
  """option string -> (dest, default, choices) of every flag of a parser."""
  return {s: (a.dest, a.default, a.choices) for a in parser._actions  # pylint: disable=protected-access
          for s in a.option_strings if s not in ("-h", "--help")}


def test_same_flags_as_train_py():
  top = cli.build_parser(["train"])
  sub = next(a for a in top._actions if a.dest == "command").choices["train"]  # pylint: disable=protected-access
  assert _options(sub) == _options(train_cli.build_parser())
  assert len(_options(sub)) > 30


def _dataset(root: Path) -> Path:
  rng = np.random.default_rng(0)
  for i in range(8):
    im = rng.random((32, 32, 3)).astype(np.float32)
    pat = (rng.random((32, 32, 5)) > 0.5).astype(np.float32)
    write_scene(root / f"s{i:02d}", Scene(
        name=f"s{i}", im0=im, im1=np.roll(im, -2, axis=1),
        disp0=np.full((32, 32), 2.0, np.float32), sl0=pat, sl1=pat.copy(),
        meta={"group": f"g{i // 2}"}))
  return root


def test_sljax_train_runs_exactly_as_train_py(tmp_path):
  data = _dataset(tmp_path / "data")
  flags = ["--data", str(data), "--model", "unet-sl", "--unet-depth", "2", "--unet-width", "8",
           "--size", "32", "--batch-size", "2", "--epochs", "1", "--no-progress"]
  assert cli.main(["train", *flags, "--workdir", str(tmp_path / "a")]) == 0
  assert train_cli.main([*flags, "--workdir", str(tmp_path / "b")]) == 0
  rows = [[{k: v for k, v in json.loads(l).items() if k not in ("seconds", "samples_per_s", "time")}
           for l in (tmp_path / wd / "metrics.jsonl").read_text().splitlines()] for wd in "ab"]
  assert rows[0] == rows[1] and rows[0]
  (_, a, step_a), (_, b, step_b) = (trained.load_params(tmp_path / wd) for wd in "ab")
  leaves = [jax.tree_util.tree_leaves_with_path(v) for v in (a, b)]
  assert step_a == step_b and len(leaves[0]) == len(leaves[1]) > 10
  for (pa, xa), (pb, xb) in zip(*leaves):
    assert pa == pb
    np.testing.assert_array_equal(np.asarray(xa), np.asarray(xb))


def test_errors_name_sljax_train(tmp_path, capsys):
  assert cli.main(["train", "--data", str(tmp_path / "missing"), "--no-progress",
                   "--workdir", str(tmp_path / "w")]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and err[0].startswith("sljax train: error:") and "missing" in err[0]


def test_help_imports_no_command_module():
  code = ("import sys; from sljax import cli; cli.build_parser(['--help']); "
          "print(sorted(m for m in sys.modules if m.startswith(('sljax.commands.', 'jax'))))")
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
  assert out.stdout.strip() == "[]"


def test_library_never_imports_the_command_line():
  root = Path(__file__).resolve().parents[1] / "sljax"
  for path in root.rglob("*.py"):
    if path.parent.name == "commands" or path.name == "cli.py" and path.parent == root:
      continue
    text = path.read_text()
    for needle in ("from sljax.cli", "import sljax.cli", "from sljax import cli",
                   "from sljax.commands", "import sljax.commands", "from sljax import commands"):
      assert needle not in text, f"{path.relative_to(root.parent)} imports the command line"
