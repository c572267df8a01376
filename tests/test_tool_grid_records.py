"""tools/grid_records.py: copying finished cells' records from a running grid's folder into
the committed results, checked on a hand-made experiment folder."""

import json
import os
import sys
from pathlib import Path

from sljax.experiment import records
from sljax.experiment.design import plans
from sljax.experiment.running import runner

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import grid_records  # noqa: E402  (tools/ is on the path above)


def _cell(out, name, done=None, evals=("heldout",)):
  wd = records.cell_dir(out, name)
  (wd / records.EVAL_DIR).mkdir(parents=True)
  (wd / "checkpoints" / "8").mkdir(parents=True)
  for f in ("config.json", "epochs.jsonl", "train.log", "metrics.jsonl"):
    (wd / f).write_text(f"{name} {f}")
  if done is not None:
    records.write_json(wd / records.DONE_FILE, done)
  for e in evals:
    records.write_json(wd / records.EVAL_DIR / f"{e}.json", {"pooled": {}})


def test_copies_finished_cells_and_then_only_what_is_new(tmp_path, monkeypatch):
  monkeypatch.setattr(grid_records, "cpu_description", lambda: "CPU X")
  src, dst = tmp_path / "runs" / "g", tmp_path / "docs" / "g"
  records.register(src, plans.build_plan("table2", "smoke", 1))
  _cell(src, "psmnet-stl-objects-s0", {"step": 8, "machine": "CPU Y"})
  _cell(src, "psmnet-unc-objects-s0", {"step": 8})                    # no CPU recorded
  _cell(src, "psmnet-epr-objects-s0", {"step": 8}, evals=())          # trained, not scored
  _cell(src, "psmnet-cg_a-objects-s0")                                # training
  assert grid_records.copy_finished(src, dst) == ["psmnet-stl-objects-s0",
                                                  "psmnet-unc-objects-s0"]
  assert (dst / records.PLAN_FILE).read_bytes() == (src / records.PLAN_FILE).read_bytes()
  stl = records.cell_dir(dst, "psmnet-stl-objects-s0")
  assert sorted(os.listdir(stl)) == ["config.json", "done.json", "epochs.jsonl.xz", "eval",
                                     "train.log"]  # no checkpoints, no metrics.jsonl
  # The training log kept compressed, and read back as the cell wrote it.
  assert records.read_text(stl / "epochs.jsonl") == "psmnet-stl-objects-s0 epochs.jsonl"
  assert (stl / "train.log").read_text() == "psmnet-stl-objects-s0 train.log"
  assert json.loads((stl / "done.json").read_text())["machine"] == "CPU Y"  # kept
  for root in (src, dst):  # the CPU is named, in both folders
    done = json.loads((records.cell_dir(root, "psmnet-unc-objects-s0") / "done.json").read_text())
    assert done == {"step": 8, "machine": "CPU X"}
  assert not records.cell_dir(dst, "psmnet-epr-objects-s0").exists()
  assert grid_records.copy_finished(src, dst) == []  # nothing new
  # More scores of a copied cell (another plan's test set) come over alone.
  records.write_json(records.cell_dir(src, "psmnet-stl-objects-s0") / records.EVAL_DIR
                    / "test-tissue.json", {"pooled": {"full": {"mae": 1.0}}})
  (records.cell_dir(src, "psmnet-stl-objects-s0") / "train.log").write_text("changed")
  assert grid_records.copy_finished(src, dst) == ["psmnet-stl-objects-s0: eval/test-tissue.json"]
  assert json.loads((stl / "eval" / "test-tissue.json").read_text())["pooled"]["full"]["mae"] == 1
  assert (stl / "train.log").read_text() == "psmnet-stl-objects-s0 train.log"  # not recopied


def test_a_diverged_cell_comes_over_with_its_record_and_once(tmp_path):
  src, dst = tmp_path / "runs" / "g", tmp_path / "docs" / "g"
  plan = plans.build_plan("table2", "smoke", 1)
  records.register(src, plan)
  _cell(src, "psmnet-stl-objects-s0", evals=())
  records.write_json(records.cell_dir(src, "psmnet-stl-objects-s0") / records.DIVERGED_FILE,
                    {"message": "loss NaN at step 3"})
  assert grid_records.copy_finished(src, dst) == ["psmnet-stl-objects-s0: diverged"]
  d = records.cell_dir(dst, "psmnet-stl-objects-s0")
  assert sorted(os.listdir(d)) == ["config.json", "diverged.json", "epochs.jsonl.xz",
                                   "train.log"]
  assert runner.diverged(dst, plan)["psmnet-stl-objects-s0"] == "loss NaN at step 3"
  assert grid_records.copy_finished(src, dst) == []
