"""The house's floors (README, "A tour of the code"): every import of the sljax package runs
from a room to one on its own floor or below, never up. Read from the source with ast, nothing
imported, so a new module or import that breaks the order fails here with its file and line."""

import ast
import sys
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "sljax"
PAGE = ROOT.parent / "docs" / "architecture.md"

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


# The experiment room's stages, from the bottom (docs/architecture.md).
STAGES = ({"design"}, {"records"}, {"running"}, {"budget", "report"})
STAGE = {s: i for i, stages in enumerate(STAGES) for s in stages}
EXPERIMENT = ROOT / "experiment"


def _stage_imports(path: Path):
  """(line, stage) of every import of another experiment stage in a file of that room."""
  for node in ast.walk(ast.parse(path.read_text(), str(path))):
    if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
      parts = node.module.split(".")
      if parts[:2] == ["sljax", "experiment"]:
        yield from ((node.lineno, s) for s in ([parts[2]] if len(parts) > 2 else
                                              [a.name for a in node.names]))


@pytest.mark.parametrize("path", sorted(EXPERIMENT.rglob("*.py")),
                         ids=lambda p: str(p.relative_to(ROOT.parent)))
def test_the_experiment_stages_import_downwards(path):
  rel = path.relative_to(EXPERIMENT).parts
  here = rel[0] if len(rel) > 1 else path.stem
  if here == "__init__":
    return
  up = [f"{path.relative_to(ROOT.parent)}:{line} imports the {stage} stage"
        for line, stage in _stage_imports(path) if STAGE[stage] > STAGE[here]]
  assert not up, "\n".join(up)


# ----------------------------------------------------------------------------- the picture
# Left out of the drawing so that it can be read: arrows into the ground floor (every room
# imports errors and io) and out of the commands (they call every floor).
UNDRAWN_FROM, UNDRAWN_TO = {"commands", "cli"}, FLOORS[0][1]


def arrows() -> dict[str, set[str]]:
  """Room -> the other rooms it imports, as the source says today."""
  found = defaultdict(set)
  for path in FILES:
    here = _room(path)
    found[here].update(room for _, room in _imports(path) if room != here)
  return found


def drawing() -> str:
  """docs/architecture.md's picture (Mermaid): the floors top down, a box per room, an arrow per
  room that imports another (less UNDRAWN_FROM / UNDRAWN_TO)."""
  lines = ["flowchart TB"]
  for i, (name, rooms) in reversed(list(enumerate(FLOORS))):
    lines.append(f'  subgraph f{i}["{i + 1}. {name}"]')
    lines.extend(f"    {room}" for room in sorted(rooms))
    lines.append("  end")
  found = arrows()
  for room in sorted(found, key=lambda r: (-LEVEL[r], r)):
    if room not in UNDRAWN_FROM:
      lines.extend(f"  {room} --> {to}" for to in sorted(found[room] - UNDRAWN_TO,
                                                         key=lambda r: (-LEVEL[r], r)))
  return "\n".join(lines) + "\n"


def test_the_architecture_page_draws_todays_imports():
  """docs/architecture.md holds the picture drawn from today's imports (after a change of
  rooms or arrows, paste in what `python tests/test_imports.py` prints)."""
  page = PAGE.read_text(encoding="utf-8")
  assert "```mermaid\n" + drawing() + "```" in page, "run: python tests/test_imports.py"


def test_the_architecture_page_names_every_room_and_root_module():
  page = PAGE.read_text(encoding="utf-8")
  missing = [r for _, rooms in FLOORS for r in rooms if f"`{r}" not in page]
  missing += [m for m in ROOT_MODULES if m != "__init__" and f"`{m}.py`" not in page]
  assert not missing, f"docs/architecture.md says nothing of {missing}"


def test_a_training_run_starts_without_matplotlib():
  """train.py's imports leave matplotlib out (0.25 s of every start, for pictures a run never
  draws): it is imported where a figure is made (sljax.io.pictures.new_figure)."""
  import subprocess
  code = ("import sys, sljax.train.cli, sljax.train.loop; "
          "print(sorted(m for m in sys.modules if m.split('.')[0] == 'matplotlib'))")
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       cwd=ROOT.parent, check=True).stdout
  assert out.strip() == "[]", out


if __name__ == "__main__":
  sys.stdout.write(drawing())
