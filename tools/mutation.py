"""Mutation testing of the modules that results and depth maps depend on (cosmic-ray; not CI).

Each module is mutated in a scratch copy of the checkout (the working tree is never touched)
and every mutant is run against the FAST test files that cover that module (MODULES below),
so a mutant costs one pytest start plus those files. The report lists, per module, how many
mutants the tests killed and every survivor (file, line, operator, the diff); see
docs/testing.md for how to read it, the last report and the survivors judged equivalent.

  pip install cosmic-ray                            # tooling only, not an sljax dependency
  python tools/mutation.py --list                   # modules, their tests, mutant counts
  python tools/mutation.py geometry metrics         # run these modules (names from --list)
  python tools/mutation.py --all --budget-min 60    # everything, stop starting modules after 60 min
  python tools/mutation.py --report                 # the summary of what has run so far

Sessions live in --work (default $TMPDIR/sljax-mutation): a run interrupted or cut by
--timeout-min resumes where it stopped (cosmic-ray keeps the pending mutants in its sqlite
session); --fresh starts a module over (after changing the module itself). The scratch copy
is refreshed from the working tree (or --rev) at each run, so new tests count. Before and
after a change to the tests: run with --rev BASE into one --work, copy that folder, and run
--retest-survivors on the copy: a mutant the old tests killed stays killed when tests are only
added, so only the survivors need the new tests.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# module name -> (files to mutate, fast test files that cover them). JAX tests compile: keep
# each list to the tests that exercise the module directly.
MODULES: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "stats": (("sljax/experiment/report/stats.py",), ("tests/test_stats.py",)),
    "report": (("sljax/experiment/report/build.py",), ("tests/test_stats.py",)),
    "geometry": (("sljax/depth/geometry.py",), ("tests/test_geometry.py", "tests/test_predict.py")),
    "metrics": (("sljax/evaluation/metrics.py",), ("tests/test_metrics.py",)),
    "checkpoint": (("sljax/models/checkpoint.py", "sljax/models/load.py"),
                   ("tests/test_load.py", "tests/test_checkpoint.py")),
    "losses": (("sljax/losses/disparity.py", "sljax/losses/sl.py", "sljax/losses/weighting.py"),
               ("tests/test_losses.py", "tests/test_weighting.py")),
    "corr": (("sljax/corr/correlation.py", "sljax/corr/uncertainty.py"),
             ("tests/test_correlation.py", "tests/test_uncertainty.py")),
}
# Operators kept (cosmic-ray's core set makes every binary operator into 11 others, mostly
# bit operations that crash on floats and are killed trivially): the arithmetic inverse, the
# comparison boundary and negation, constants +-1, dropped negation, emptied loops,
# swapped boolean connectives and break/continue.
KEEP = ("ReplaceBinaryOperator_(Add_Sub|Sub_Add|Mul_Div|Div_Mul|FloorDiv_Div|Mod_FloorDiv|Pow_Mul)",
        "ReplaceComparisonOperator_(Lt_LtE|LtE_Lt|Gt_GtE|GtE_Gt|Eq_NotEq|NotEq_Eq|Is_IsNot|"
        "IsNot_Is|In_NotIn|NotIn_In)",
        "ReplaceUnaryOperator_Delete_(USub|Not)", "NumberReplacer", "AddNot",
        "ReplaceTrueWithFalse", "ReplaceFalseWithTrue", "ReplaceAndWithOr", "ReplaceOrWithAnd",
        "ZeroIterationForLoop", "ReplaceBreakWithContinue", "ReplaceContinueWithBreak")
EXCLUDE = "^(?!core/(" + "|".join(KEEP) + ")$)"
# one process: a mutant runs a few files, and two workers would cost more to start than they save
PYTEST = "python -m pytest -x -q -n 0 -p no:cacheprovider -p no:randomly"


def scratch_copy(work: Path, rev: str | None = None) -> Path:
  """A fresh copy of the working tree's tracked and untracked (not ignored) files, or of the
  commit rev (git archive: e.g. the tests before a change, for a "before" score)."""
  dest = work / "tree"
  if rev is not None:
    if dest.exists():
      shutil.rmtree(dest)
    dest.mkdir(parents=True)
    archive = subprocess.run(["git", "archive", rev], cwd=ROOT, check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest
  files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT,
                         check=True, capture_output=True).stdout.decode().split("\0")
  if dest.exists():
    shutil.rmtree(dest)
  for f in filter(None, files):
    src = ROOT / f
    if src.is_file():
      (dest / f).parent.mkdir(parents=True, exist_ok=True)
      shutil.copy2(src, dest / f)
  return dest


def config(tree: Path, path: str, tests: tuple[str, ...], timeout: float) -> str:
  """cosmic-ray's TOML configuration for one file of a module (the tests tree holds)."""
  existing = [t for t in tests if (tree / t).is_file()]
  return (f'[cosmic-ray]\nmodule-path = "{path}"\ntimeout = {timeout}\nexcluded-modules = []\n'
          f'test-command = "{PYTEST} {" ".join(existing)}"\n\n'
          '[cosmic-ray.distributor]\nname = "local"\n\n'
          f'[cosmic-ray.filters.operators-filter]\nexclude-operators = [{json.dumps(EXCLUDE)}]\n')


def sessions(work: Path, name: str) -> list[tuple[str, Path, Path]]:
  """(file, config path, session path) per file of a module."""
  out = []
  for path in MODULES[name][0]:
    stem = path.replace("/", "_").removesuffix(".py")
    out.append((path, work / f"{stem}.toml", work / f"{stem}.sqlite"))
  return out


HELD = "held back (not run)"  # pending mutants set aside by --retest-survivors


def forget_survivors(db: Path) -> int:
  """Marks a session's surviving mutants as not run (so exec tests them again) and holds its
  pending ones back, so that exec runs the survivors only; returns how many."""
  with sqlite3.connect(db) as con:
    con.execute("DELETE FROM work_results WHERE output = ?", (HELD,))
    con.execute("INSERT INTO work_results (worker_outcome, output, job_id) SELECT 'SKIPPED', ?, "
                "w.job_id FROM work_items w LEFT JOIN work_results r USING (job_id) "
                "WHERE r.job_id IS NULL", (HELD,))
    return con.execute("DELETE FROM work_results WHERE test_outcome = 'SURVIVED'").rowcount


def release_held(db: Path) -> None:
  """Returns the mutants forget_survivors held back to the pending set."""
  with sqlite3.connect(db) as con:
    con.execute("DELETE FROM work_results WHERE output = ?", (HELD,))


def run_module(name: str, work: Path, tree: Path, fresh: bool, timeout: float,
               deadline: float | None, retest: bool = False) -> None:
  """Initialises (once) and executes the module's sessions in the scratch tree."""
  env = dict(os.environ, PYTHONPATH=str(tree), JAX_PLATFORMS="cpu")
  for path, cfg, db in sessions(work, name):
    cfg.write_text(config(tree, path, MODULES[name][1], timeout))
    if fresh and db.exists():
      db.unlink()
    if retest and db.exists():
      print(f"{path}: testing {forget_survivors(db)} survivor(s) again", flush=True)
    if not db.exists():
      subprocess.run(["cosmic-ray", "init", str(cfg), str(db)], cwd=tree, env=env, check=True)
      subprocess.run(["cr-filter-operators", str(db), str(cfg)], cwd=tree, env=env, check=True)
    pristine = (tree / path).read_bytes()
    left = None if deadline is None else max(1.0, deadline - time.time())
    t0 = time.time()
    proc = subprocess.Popen(["cosmic-ray", "exec", str(cfg), str(db)], cwd=tree, env=env,
                            start_new_session=True)
    try:
      proc.wait(timeout=left)
    except subprocess.TimeoutExpired:
      os.killpg(proc.pid, signal.SIGTERM)  # cosmic-ray and the pytest it started
      proc.wait()
      print(f"{path}: stopped at the time limit; run again to resume", flush=True)
    finally:
      # A mutant left applied by an interrupted run must not leak into the next module.
      (tree / path).write_bytes(pristine)
      if retest:
        release_held(db)
    (work / f"{Path(db).stem}.seconds").write_text(
        str(time.time() - t0 + _seconds(work, Path(db).stem)))


def _seconds(work: Path, stem: str) -> float:
  f = work / f"{stem}.seconds"
  return float(f.read_text()) if f.exists() else 0.0


def summary(work: Path, names: list[str], diffs: bool = True) -> str:
  """Markdown: per module killed / survived / pending and the survivors' diffs."""
  rows = ["| module | mutants | killed | survived | timeout | incompetent | pending | score | "
          "time (contended) |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
  details = []
  for name in names:
    counts = dict.fromkeys(("total", "killed", "survived", "timeout", "incompetent",
                            "pending"), 0)
    seconds = 0.0
    for path, _, db in sessions(work, name):
      if not db.exists():
        continue
      seconds += _seconds(work, db.stem)
      dump = subprocess.run(["cosmic-ray", "dump", str(db)], check=True, capture_output=True,
                            text=True).stdout
      for line in filter(None, dump.splitlines()):
        job, result = json.loads(line)
        if result is not None and result.get("output") == HELD:
          result = None  # pending
        elif result is not None and result.get("worker_outcome") == "skipped":
          continue  # an operator outside KEEP
        counts["total"] += 1
        if result is None:
          counts["pending"] += 1
          continue
        outcome = result.get("test_outcome")
        if result.get("worker_outcome") == "timeout":
          counts["timeout"] += 1
        elif outcome == "killed":
          counts["killed"] += 1
        elif outcome == "incompetent":
          counts["incompetent"] += 1
        else:
          counts["survived"] += 1
          m = job["mutations"][0]
          details.append(f"- {name}: `{m['module_path']}` line {m['start_pos'][0]}, "
                         f"{m['operator_name']} #{m['occurrence']}"
                         + (f"\n\n```diff\n{result.get('diff', '').strip()}\n```\n" if diffs
                            else ""))
    done = counts["killed"] + counts["survived"] + counts["timeout"]
    score = f"{100 * (counts['killed'] + counts['timeout']) / done:.1f}%" if done else "-"
    rows.append(f"| {name} | {counts['total']} | {counts['killed']} | {counts['survived']} | "
                f"{counts['timeout']} | {counts['incompetent']} | {counts['pending']} | {score} | "
                f"{seconds / 60:.1f} min |")
  return "\n".join(rows) + ("\n\nSurvivors:\n\n" + "\n".join(details) if details else "")


def main(argv=None):
  """Command line: see the module docstring."""
  p = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
  p.add_argument("modules", nargs="*", help=f"of {', '.join(MODULES)}")
  p.add_argument("--all", action="store_true", help="every module, in the order above")
  p.add_argument("--list", action="store_true", help="modules, tests and mutant counts")
  p.add_argument("--report", action="store_true", help="summary of the sessions so far")
  p.add_argument("--fresh", action="store_true", help="discard the modules' earlier results")
  p.add_argument("--rev", help="mutate and test this commit instead of the working tree")
  p.add_argument("--retest-survivors", action="store_true",
                 help="test only the sessions' survivors again (after adding tests; killed "
                      "stay killed, pending stay pending)")
  p.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "sljax-mutation")
  p.add_argument("--timeout", type=float, default=120.0, help="seconds per mutant")
  p.add_argument("--budget-min", type=float, help="stop (resumably) after this many minutes")
  p.add_argument("--no-diffs", action="store_true", help="report without the survivors' diffs")
  args = p.parse_args(argv)
  names = list(MODULES) if args.all else args.modules
  unknown = sorted(set(names) - set(MODULES))
  if unknown:
    raise SystemExit(f"unknown module(s) {', '.join(unknown)}; known: {', '.join(MODULES)}")
  if shutil.which("cosmic-ray") is None:
    raise SystemExit("cosmic-ray is not installed: pip install cosmic-ray")
  args.work.mkdir(parents=True, exist_ok=True)
  if args.list:
    for name, (paths, tests) in MODULES.items():
      print(f"{name}: {', '.join(paths)} <- {', '.join(tests)}")
    return
  if not args.report:
    tree = scratch_copy(args.work, args.rev)
    deadline = None if args.budget_min is None else time.time() + 60 * args.budget_min
    for name in names:
      if deadline is not None and time.time() >= deadline:
        print(f"budget spent before {name}", flush=True)
        break
      run_module(name, args.work, tree, args.fresh, args.timeout, deadline,
                 args.retest_survivors)
  print(summary(args.work, names or list(MODULES), diffs=not args.no_diffs))


if __name__ == "__main__":
  sys.exit(main())
