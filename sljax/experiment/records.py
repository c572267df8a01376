"""An experiment folder on disk: where each record lives, and reading and writing them.

OUT/plan.json            the plans run here and the spec of every cell (see Cell.spec); a
                         plan calibrated here records its budgets (written once)
OUT/calibration-PLAN.json  the plateau rule applied to the plan's calibration cells, written
                         when the last of them is done (sljax.experiment.budget.calibrate)
OUT/claims/, workers/   which worker holds which cell (sljax.experiment.running.workers)
OUT/cells/NAME/          the cell's training workdir (config.json, checkpoints/, *.jsonl)
OUT/cells/NAME/train.log its training output
OUT/cells/NAME/done.json written once training finished: final step (and best step, where the
                         plan scores the best checkpoint), seconds, the CPU
OUT/cells/NAME/eval/SET.json.xz  the final (or best) checkpoint's evaluation report on that
                         set, pooled and per scene, compressed (older folders hold SET.json)
OUT/cells/NAME/eval/windows.json  v2 unet-sl: validation MAE per candidate correlation window
                         and the window chosen (the lowest; ties: the smaller)
OUT/cells/NAME/diverged.json  written when the cell's training loss went NaN or infinite: the
                         trainer's message and the CPU. The runner goes on without the cell and
                         without the cells fine-tuned from it; deleting the file trains it again

Every reader takes a record plain or compressed (NAME.xz beside where NAME would be): the
per-scene evaluation reports are written compressed, and the committed grids
(docs/results/) hold their training logs compressed too, so that a clone carries them.
"""

import json
import lzma
import math
from pathlib import Path
from typing import Any

from sljax.errors import SljaxError, require
from sljax.experiment.design.plans import (CALIBRATE, Plan, build_plan, calibration_plan,
                                          check_unique)
from sljax.io import files
from sljax.models import checkpoint as ckpt
from sljax.train.config import dumps
from sljax.train.workdir import EPOCHS_FILE, VALIDATION_FILE

PLAN_FILE = "plan.json"
CELLS_DIR = "cells"
DONE_FILE = "done.json"
EVAL_DIR = "eval"
WINDOWS_FILE = "windows.json"
LOG_FILE = "train.log"
DIVERGED_FILE = "diverged.json"
FORMAT_VERSION = 1
COMPRESSED = ".xz"  # lzma (xz): the standard library reads it, `xzcat` shows it
EVAL_SUFFIX = ".json" + COMPRESSED


def cell_dir(out: Path, name: str) -> Path:
  """The workdir of a cell."""
  return out / CELLS_DIR / name


def stored(path: Path) -> Path | None:
  """Where a record is: PATH, else its compressed copy PATH.xz (None: neither exists)."""
  for p in (path, path.with_name(path.name + COMPRESSED)):
    if p.exists():
      return p
  return None


def read_text(path: Path) -> str | None:
  """A record's text, from PATH or PATH.xz (None when neither exists); SljaxError naming the
  file when it cannot be read or decompressed."""
  found = stored(path)
  if found is None:
    return None
  try:
    data = found.read_bytes()
    if found.name.endswith(COMPRESSED):
      data = _decompress(data, found)
    return data.decode("utf-8")
  except (OSError, lzma.LZMAError, UnicodeDecodeError) as e:
    raise SljaxError(f"{found}: unreadable record ({e})") from None


# What decompressing a record may take: xz's decoder allocates the dictionary its header
# claims (8 MiB for the preset write_eval uses; a damaged header can claim 4 GiB), and a
# record's JSON compresses about 5 times, so 256 times its size is no record of sljax's.
XZ_MEMLIMIT = 64 << 20
XZ_MAX_RATIO = 256


def _decompress(data: bytes, path: Path) -> bytes:
  """An .xz record's bytes, within XZ_MEMLIMIT and XZ_MAX_RATIO (SljaxError naming path)."""
  d = lzma.LZMADecompressor(memlimit=XZ_MEMLIMIT)
  most = XZ_MAX_RATIO * len(data) + (1 << 20)
  out = d.decompress(data, max_length=most)
  if not d.eof:
    why = "is truncated" if d.needs_input else f"decompresses to more than {most} bytes"
    raise SljaxError(f"{path}: unreadable record (it {why})")
  return out


def read_json(path: Path) -> dict[str, Any] | None:
  """A JSON object record (PATH or PATH.xz), or None when absent."""
  text = read_text(path)
  if text is None:
    return None
  try:
    value = json.loads(text)
  except ValueError as e:
    raise SljaxError(f"{stored(path)}: not valid JSON ({e})") from None
  require(isinstance(value, dict), f"{stored(path)}: must hold a JSON object")
  return value


def read_lines(path: Path) -> list[dict[str, Any]]:
  """The rows of a JSON-lines record (PATH or PATH.xz; [] when absent); a last line without
  its line end (being written) is left out, any other that is not a JSON object is an
  SljaxError naming the file and line."""
  text = read_text(path) or ""
  lines = text.splitlines()
  rows = []
  for n, line in enumerate(lines, 1):
    if not line.strip():
      continue
    try:
      row = json.loads(line)
    except ValueError:
      row = None
    if not isinstance(row, dict):
      if n == len(lines) and not text.endswith("\n"):
        break
      raise SljaxError(f"{stored(path)}: line {n} is not a JSON object")
    rows.append(row)
  return rows


def _points(path: Path, rows: list[dict[str, Any]], x: str, y: str) -> list[tuple[int, float]]:
  """(row[x], row[y]) of the rows with a y; SljaxError naming the file for a row whose x is
  no integer or whose y is no number."""
  out = []
  for row in rows:
    if row.get(y) is None:
      continue
    if type(row.get(x)) is not int or type(row[y]) not in (int, float):
      raise SljaxError(f"{stored(path)}: a row has {x}={row.get(x)!r}, {y}={row[y]!r}; "
                       f"expected an integer and a number")
    out.append((row[x], row[y]))
  return out


def write_json(path: Path, obj: Any) -> None:
  """Writes whole (a killed runner never leaves half a file; sljax.io.files)."""
  files.write_text(path, dumps(obj) + "\n")


def eval_path(out: Path, name: str, set_name: str) -> Path:
  """Where a cell's evaluation report on a set is written (compressed: EVAL_SUFFIX)."""
  return cell_dir(out, name) / EVAL_DIR / f"{set_name}{EVAL_SUFFIX}"


def eval_record(out: Path, name: str, set_name: str) -> Path | None:
  """The file of a cell's evaluation report on a set, compressed or (older folders) plain; None
  when the set is not scored yet."""
  return stored(cell_dir(out, name) / EVAL_DIR / f"{set_name}.json")


def read_eval(out: Path, name: str, set_name: str) -> dict[str, Any] | None:
  """A cell's evaluation report on a set, or None when not scored yet."""
  return read_json(cell_dir(out, name) / EVAL_DIR / f"{set_name}.json")


def write_eval(out: Path, name: str, set_name: str, report: dict[str, Any]) -> Path:
  """Writes a cell's evaluation report on a set whole, compressed (its per-scene rows are most
  of an experiment folder: 0.63 MB of JSON a set at 500 scenes, 0.13 MB compressed)."""
  path = eval_path(out, name, set_name)
  path.parent.mkdir(parents=True, exist_ok=True)
  files.write_bytes(path, lzma.compress((dumps(report) + "\n").encode("utf-8")))
  return path


def plan_args(plan: Plan) -> dict[str, Any]:
  """What rebuilds the plan (build_plan's arguments), with the budgets its OUT's calibration
  gave where it has them."""
  args = {"scale": plan.scale.name, "seeds": len(plan.seeds), "data": plan.data,
          "eval_data": list(plan.eval_data)}
  if plan.budgets:  # only then: the records of plans with committed budgets stay as they were
    args["budgets"] = budget_rows(plan.budgets)
  return args


def budget_rows(budgets) -> list[list]:
  """((arm, phase), epochs) pairs as plan.json's [arm, phase, epochs] rows, sorted."""
  return sorted([arm, phase, int(epochs)] for (arm, phase), epochs in budgets)


def budget_pairs(rows) -> tuple[tuple[tuple[str, str], int], ...]:
  """plan.json's [arm, phase, epochs] rows as build_plan's ((arm, phase), epochs) pairs."""
  return tuple(sorted(((str(a), str(p)), int(e)) for a, p, e in rows))


def read_record(out: Path) -> dict[str, Any] | None:
  """OUT/plan.json as register writes it (plans by name with scale and seeds, cells by name), or
  None when absent; SljaxError naming the file for any other JSON object."""
  path = out / PLAN_FILE
  record = read_json(path)
  if record is None:
    return None
  by_plan, cells = record.get("plans"), record.get("cells")
  # Another program's plan.json (or an edited one) would otherwise end in a KeyError.
  ok = isinstance(by_plan, dict) and isinstance(cells, dict) and all(
      isinstance(a, dict) and isinstance(a.get("scale"), str) and type(a.get("seeds")) is int
      for a in by_plan.values())
  require(ok, f"{path}: not an sljax experiment record (expected {{\"plans\": {{PLAN: "
          f"{{\"scale\": ..., \"seeds\": N}}}}, \"cells\": {{...}}}}); use another OUT")
  return record


def register(out: Path, plan: Plan) -> dict[str, Any]:
  """Records the plan in OUT/plan.json; SljaxError when a cell's spec differs from the one
  already recorded there (a changed plan under an existing OUT)."""
  check_unique(plan)
  out.mkdir(parents=True, exist_ok=True)
  record = read_record(out) or {"version": FORMAT_VERSION, "plans": {}, "cells": {}}
  # Budgets first: a changed budget would also change its cells' specs, a vaguer message.
  _keep_budgets(out, plan.name, record["plans"].get(plan.name), plan_args(plan))
  for cell in plan.cells:
    old, new = record["cells"].get(cell.name), cell.spec()
    if old is not None and old != new:
      diff = _first_difference(old, new)
      raise SljaxError(f"{out}: cell {cell.name} was run with another configuration ({diff}); "
                       "use another OUT for the changed plan")
  previous = record["plans"].get(plan.name)
  if previous is not None and previous["scale"] != plan.scale.name:
    raise SljaxError(f"{out}: plan {plan.name} was run at scale {previous['scale']}, not "
                     f"{plan.scale.name}; use another OUT")
  args = plan_args(plan)
  _keep_budgets(out, plan.name, previous, args)
  if previous is not None:  # more seeds or evaluation folders extend a plan; fewer keep it
    args["seeds"] = max(args["seeds"], previous["seeds"])
    args["eval_data"] = sorted(set(args["eval_data"]) | set(previous.get("eval_data", [])))
  before = json.dumps(record, sort_keys=True)
  record["plans"][plan.name] = args
  record["cells"].update({c.name: c.spec() for c in plan.cells})
  if json.dumps(record, sort_keys=True) != before:  # written once: the workers of a grid agree
    write_json(out / PLAN_FILE, record)
  return record


def _keep_budgets(out: Path, name: str, previous: dict[str, Any] | None,
                  args: dict[str, Any]) -> None:
  """SljaxError when a plan recorded with its calibration's budgets comes with others; args
  keeps the recorded ones (budgets committed since win: the record stays)."""
  if previous is None or "budgets" not in previous:
    return
  require(args.get("budgets", previous["budgets"]) == previous["budgets"],
          f"{out}: plan {name} was registered with the budgets its calibration gave "
          f"({previous['budgets']}), not {args.get('budgets')}; budgets never change after "
          "results (use another OUT)")
  args["budgets"] = previous["budgets"]


def registered_plans(out: Path, seeds: int | None = None) -> list[Plan]:
  """The plans recorded in OUT/plan.json, rebuilt (with `seeds` seeds where more than were run,
  e.g. a grid's target while it runs seed by seed); SljaxError when OUT is not an experiment
  folder."""
  record = read_record(out)
  require(record is not None, f"{out}: no {PLAN_FILE} (not an experiment folder; run "
          "`sljax experiment run PLAN OUT` first)")
  require(seeds is None or seeds >= 1, f"--seeds {seeds}: at least 1")
  return [calibration_plan(name.removeprefix(CALIBRATE), args["scale"])
          if name.startswith(CALIBRATE) else
          build_plan(name, args["scale"], max(seeds or 0, args["seeds"]), args.get("data"),
                     tuple(args.get("eval_data", ())), budget_pairs(args.get("budgets", ())))
          for name, args in record["plans"].items()]


def _first_difference(old: Any, new: Any, path: str = "") -> str:
  if isinstance(old, dict) and isinstance(new, dict):
    for k in sorted(set(old) | set(new)):
      if old.get(k) != new.get(k):
        return _first_difference(old.get(k), new.get(k), f"{path}{k}.")
  return f"{path.rstrip('.')}: {old!r} -> {new!r}"


def curve(out: Path, name: str) -> list[tuple[int, float]]:
  """(epoch, validation MAE) of a cell's training log, or (step, ...) if it validated by steps."""
  if stored(cell_dir(out, name) / VALIDATION_FILE) is not None:
    return _points(cell_dir(out, name) / VALIDATION_FILE, step_curve(out, name), "step",
                   "val_mae")
  path = cell_dir(out, name) / EPOCHS_FILE
  return _points(path, read_lines(path), "epoch", "val_mae")


def train_curve(out: Path, name: str) -> list[tuple[int, float]]:
  """(step, mean training L_disp since the previous validation) of a cell validated by steps."""
  return _points(cell_dir(out, name) / VALIDATION_FILE, step_curve(out, name), "step",
                 "train_loss_disp")


def step_curve(out: Path, name: str) -> list[dict[str, Any]]:
  """The rows of a cell's validation.jsonl (validation by steps): step, validation MAE and the
  mean training losses since the previous validation."""
  return read_lines(cell_dir(out, name) / VALIDATION_FILE)


def read_done(out: Path, name: str) -> dict[str, Any] | None:
  """A cell's done.json (None: not finished); SljaxError naming it when its step, best step,
  seconds or machine are not of their types."""
  path = cell_dir(out, name) / DONE_FILE
  done = read_json(path)
  if done is None:
    return None
  step, best = done.get("step"), done.get("best_step")
  seconds = done.get("train_seconds")
  ok = (type(step) is int and step >= 0 and (best is None or (type(best) is int and best >= 0))
        and (seconds is None or (type(seconds) in (int, float) and math.isfinite(seconds)))
        and isinstance(done.get("machine"), (str, type(None))))
  require(ok, f"{stored(path)}: not a record of a finished cell (expected {{\"step\": N, "
          "\"train_seconds\": S, ...}); delete it to train the cell again")
  return done


def final_checkpoint(out: Path, name: str, which: str = "final") -> Path:
  """The checkpoint folder of a finished cell's last step, or of its best by validation MAE
  (which="best"; kept and recorded in done.json when the plan scores it)."""
  done = read_done(out, name)
  require(done is not None, f"{cell_dir(out, name)}: cell {name} has not finished training")
  if which == "best":
    require(done.get("best_step") is not None,
            f"{stored(cell_dir(out, name) / DONE_FILE)}: cell {name} kept no best checkpoint "
            "(it finished under a plan that scores the final one only)")
    return cell_dir(out, name) / ckpt.CHECKPOINT_DIR / str(done["best_step"])
  return cell_dir(out, name) / ckpt.CHECKPOINT_DIR / str(done["step"])
