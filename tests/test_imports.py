"""The house's floors (README, "A tour of the code"): every import of the sljax package runs
from a room to one on its own floor or below, never up. Read from the source with ast, nothing
imported, so a new module or import that breaks the order fails here with its file and line."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "sljax"

# From the ground up; a room is a top-level module or package of sljax (docs/architecture.md).
FLOORS = (
    ("ground", {"errors", "io", "runtime", "kernels"}),
    ("structured light", {"sl"}),
    ("data", {"data"}),
    ("importers of real data", {"capture"}),
    ("renderer", {"render"}),
    ("networks, losses, correlation", {"nets", "losses", "corr"}),
    ("trained models", {"models"}),
    ("inference", {"inference"}),
    ("depth and deployment", {"depth", "deploy"}),
    ("evaluation", {"evaluation"}),
    ("training", {"train"}),
    ("experiments", {"experiment"}),
    ("commands", {"commands", "cli"}),
)
# The package root is the package's face: what a user imports first and the command line.
ROOT_MODULES = {"__init__", "cli", "errors"}
LEVEL = {room: i for i, (_, rooms) in enumerate(FLOORS) for room in rooms}


def _room(path: Path) -> str:
  parts = path.relative_to(ROOT).with_suffix("").parts
  return parts[0]


def _imports(path: Path):
  """(line, imported sljax room) of every import in a file (TYPE_CHECKING ones included)."""
  for node in ast.walk(ast.parse(path.read_text(), str(path))):
    names = []
    if isinstance(node, ast.Import):
      names = [a.name for a in node.names]
    elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
      names = [node.module] + [f"{node.module}.{a.name}" for a in node.names
                               if node.module == "sljax"]
    for name in names:
      parts = name.split(".")
      if parts[0] == "sljax" and len(parts) > 1:
        yield node.lineno, parts[1]


FILES = sorted(p for p in ROOT.rglob("*.py") if p.name != "__init__.py" or p.parent != ROOT)


def test_the_root_holds_only_the_packages_face():
  """A module added at the package root must be named here and in docs/architecture.md."""
  loose = {p.stem for p in ROOT.glob("*.py")}
  assert loose <= ROOT_MODULES, f"put {sorted(loose - ROOT_MODULES)} in a room (docs/architecture.md)"


def test_every_room_has_a_floor():
  rooms = {_room(p) for p in FILES}
  assert rooms <= set(LEVEL), f"rooms without a floor: {sorted(rooms - set(LEVEL))}"


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(ROOT.parent)))
def test_no_import_runs_up(path):
  here = _room(path)
  up = [f"{path.relative_to(ROOT.parent)}:{line} imports sljax.{room} "
        f"({FLOORS[LEVEL[room]][0]}) from {FLOORS[LEVEL[here]][0]}"
        for line, room in _imports(path) if LEVEL.get(room, -1) > LEVEL[here]]
  assert not up, "\n".join(up)


def test_the_check_sees_an_import_that_runs_up(tmp_path):
  """The reader finds `from sljax.train import ...` in a file of the data floor."""
  bad = tmp_path / "bad.py"
  bad.write_text("import os\nfrom sljax.train import loop\nfrom sljax import files\n")
  assert list(_imports(bad)) == [(2, "train"), (3, "files")]
