"""Property-based campaign over the JSON records sljax reads back: a workdir's config.json and
JSON lines, checkpoint digests, an experiment's plan.json, claims, heartbeats and worker files,
done.json, diverged.json and evaluation records (plain and .xz), tune's measurements and the
kept programs' index (tests/fuzz_kit.py states the property). Each valid record is written by
sljax's own writer, then mutated."""

import json
import lzma
import tempfile
import types
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

import fuzz_kit as fk
from sljax.experiment import records
from sljax.experiment.running import claims, runner, status, workers
from sljax.models import checkpoint, digest, load
from sljax.runtime import choices, kept_programs
from sljax.train import config as train_config
from sljax.train import workdir

FOLDER = fk.FOLDER



def records_of(value) -> st.SearchStrategy[bytes]:
  """A JSON record mutated, or a folder in its place."""
  return fk.mutated_json(value) | st.just(FOLDER)


# ----------------------------------------------------------------------------- a workdir

CONFIG = json.loads(train_config.dumps(train_config.TrainConfig(
    data="scenes", epochs=2, batch_size=1).to_json()))


@fk.fuzz(150)
@given(records_of(CONFIG))
@example(fk.dumps({**CONFIG, "size": None}))  # was a TypeError from tuple(None)
@example(fk.dumps({**CONFIG, "epochs": "2"}))  # was a TypeError in validate, far from the file
def test_config_json(data):
  """A workdir's config.json as resume and loading read it: a config or one line naming it."""
  with tempfile.TemporaryDirectory() as d:
    path = Path(d) / load.CONFIG_FILE
    fk.place(path, data)

    def read():
      saved = load.read_config(d)
      return train_config.config_from_json(saved, str(path))
    fk.check(read, path, fk.allowance(path))


ROWS = [{"epoch": 1, "step": 4, "loss": 0.5, "val_mae": 2.5, "seconds": 1.0},
        {"epoch": 2, "step": 8, "loss": 0.4, "val_mae": 2.0, "seconds": 1.1}]


def jsonl(rows) -> st.SearchStrategy[bytes]:
  """JSON lines with one row mutated, or their text edited."""
  text = b"".join(fk.dumps(r) + b"\n" for r in rows)
  return st.one_of(
      st.tuples(st.integers(0, len(rows) - 1), fk.mutated_json(rows[0])).map(
          lambda k: b"".join((k[1] if i == k[0] else fk.dumps(r)) + b"\n"
                             for i, r in enumerate(rows))),
      fk.mutated_bytes(text), st.just(FOLDER))


@fk.fuzz(150)
@given(jsonl(ROWS))
@example(FOLDER)  # resume's truncation: was an IsADirectoryError
@example(b'{"epoch": "1", "val_mae": 2.5}\n')  # was a TypeError comparing "1" <= 1
@example(b'{"epoch":\n{"epoch": 2, "val_mae": 2.0}\n')  # curve: was a JSONDecodeError
@example(b'{"epoch": Infinity, "step": 4}\n')  # status: was an OverflowError in int()
def test_epochs_jsonl(data):
  """epochs.jsonl as the experiment's curves and status read it, and as resume truncates it
  (whole: the file is the old one or the new one, never half)."""
  with tempfile.TemporaryDirectory() as d:
    out = Path(d)
    wd = records.cell_dir(out, "c")
    path = wd / workdir.EPOCHS_FILE
    fk.place(path, data)
    bound = fk.allowance(path)
    fk.check(lambda: records.curve(out, "c"), path, bound)
    fk.check(lambda: status.last_epoch(wd), path, bound)
    before = path.read_bytes() if path.is_file() else None
    result = fk.check(lambda: workdir.restart_logs(wd, 4, 4), path, bound)
    if result is fk.REFUSED and before is not None:
      assert path.read_bytes() == before  # refused: left as it was
    assert not [p for p in wd.iterdir() if p.name.startswith(".")]  # no temporary left


@fk.fuzz(100)
@given(jsonl(ROWS))
@example(b'{"estep": 4, "val_mae": 2.5}\n')  # was a KeyError: 'step'
@example(b'null\n{"step": 8, "val_mae": 2.0}\n')  # was an AttributeError on None
def test_validation_jsonl(data):
  """validation.jsonl (validation by steps) as the experiment's curves read it."""
  with tempfile.TemporaryDirectory() as d:
    out = Path(d)
    path = records.cell_dir(out, "c") / workdir.VALIDATION_FILE
    fk.place(path, data)
    bound = fk.allowance(path)
    fk.check(lambda: records.curve(out, "c"), path, bound)
    fk.check(lambda: records.train_curve(out, "c"), path, bound)


def _step_folder(root: Path) -> Path:
  """A checkpoint step folder of two files and the digest sljax writes of them."""
  folder = root / "checkpoints" / "4"
  (folder / "state").mkdir(parents=True)
  (folder / "state" / "data").write_bytes(bytes(range(256)) * 4)
  (folder / "meta").write_text('{"step": 4}')
  digest.write_digest(folder)
  return folder


@fk.fuzz(100)
@given(st.sampled_from(["digest", "data", "meta"]), st.data())
def test_checkpoint_digest(which, draw):
  """A step folder with its digest or a file damaged: verified, or one line naming the step."""
  with tempfile.TemporaryDirectory() as d:
    folder = _step_folder(Path(d))
    name = {"digest": digest.DIGEST_FILE, "data": "state/data", "meta": "meta"}[which]
    path = folder / name
    valid = path.read_bytes()
    data = draw.draw(fk.mutated_json(json.loads(valid)) if which == "digest"
                     else fk.mutated_bytes(valid) | st.just(FOLDER))
    fk.place(path, data)
    ok = fk.check(lambda: checkpoint.verify(folder.parent, 4), folder, fk.allowance(folder))
    if ok is not fk.REFUSED and which != "digest":
      assert data == valid  # a changed file never passes its digest


# ----------------------------------------------------------------------------- an experiment

PLAN = {"format": records.FORMAT_VERSION,
        "plans": {"v2": {"scale": "cpu", "seeds": 2, "data": "d", "eval_data": []}},
        "cells": {"c": {"arm": "sl", "seed": 0}}}


@fk.fuzz(150)
@given(records_of(PLAN))
def test_plan_json(data):
  """OUT/plan.json: the record or one line naming it."""
  with tempfile.TemporaryDirectory() as d:
    path = Path(d) / records.PLAN_FILE
    fk.place(path, data)
    fk.check(lambda: records.read_record(Path(d)), path, fk.allowance(path))


def _identity() -> dict:
  """A claim record as a worker writes it."""
  return workers.Identity(token="t0", host="elsewhere", pid=12345, started="99", job="7_1",
                          lease=60.0, since=1.7e9).record()


CLAIM = {"kind": claims.CLAIM, **_identity()}


@fk.fuzz(150)
@given(records_of(CLAIM), fk.mutated_json({"token": "t0", "step": 12}) | st.just(FOLDER))
@example(FOLDER, FOLDER)  # was an IsADirectoryError
@example(fk.dumps({**CLAIM, "host": workers.host_name(), "pid": "x"}), b"{}")  # int(): ValueError
@example(fk.dumps({**CLAIM, "lease": None}), b"{}")  # was a TypeError in float()
def test_claims_and_beats(claim, beat):
  """A cell's claim and heartbeat as take-over, status and a worker's last words read them."""
  with tempfile.TemporaryDirectory() as d:
    out = Path(d)
    path = claims.claim_path(out, "c", 0)
    assert claims.create_exclusive(path, CLAIM)
    fk.place(path, claim)
    fk.place(claims.beat_path(path), beat)
    me = workers.Identity(token="me", host=workers.host_name(), pid=1, started=None, job="7_1",
                          lease=60.0, since=0.0)
    bound = fk.allowance(path.parent)

    def read():
      t = claims.top(out, "c")
      return (workers.gone(t, me, 1.8e9), workers.late(t, 1.8e9), workers.held_by(out, ["c"]),
              workers.late_holders(out, ["c"], 1.8e9))
    fk.check(read, path, bound)


@fk.fuzz(100)
@given(records_of({**_identity(), "log": "w.log"}))
@example(fk.dumps({**_identity(), "lease": None}))  # was a TypeError in float()
def test_worker_files(data):
  """OUT/workers/*.json as `experiment status` lists the live workers."""
  with tempfile.TemporaryDirectory() as d:
    path = Path(d) / workers.WORKERS_DIR / "w.json"
    fk.place(path, data)
    fk.check(lambda: workers.live_workers(Path(d)), path, fk.allowance(path))


DONE = {"step": 8, "epochs": 2, "last_val_mae": 2.0, "train_seconds": 3.5,
        "wall_seconds_last_call": 4.0, "machine": "cpu", "best_step": 4}


def _cell(name: str = "c", init_cell=None):
  """What the readers of a cell use of it (name, evaluation sets, budget)."""
  return types.SimpleNamespace(name=name, init_cell=init_cell, evals=(),
                               config=types.SimpleNamespace(epochs=2, steps=None))


@fk.fuzz(150)
@given(records_of(DONE))
@example(fk.dumps({k: v for k, v in DONE.items() if k != "step"}))  # was a KeyError: 'step'
@example(fk.dumps({k: v for k, v in DONE.items() if k != "best_step"}))  # named the folder only
@example(fk.dumps({**DONE, "train_seconds": "3.5"}))  # status: was a ValueError in float()
def test_done_json(data):
  """A cell's done.json as status and the checkpoint lookup read it."""
  with tempfile.TemporaryDirectory() as d:
    out = Path(d)
    path = records.cell_dir(out, "c") / records.DONE_FILE
    fk.place(path, data)
    bound = fk.allowance(path)
    fk.check(lambda: status.cell_state(out, _cell()), path, bound)
    for which in ("final", "best"):
      fk.check(lambda: records.final_checkpoint(out, "c", which), path, bound)


@fk.fuzz(100)
@given(records_of({"message": "loss is nan at step 3", "machine": "cpu"}))
def test_diverged_json(data):
  """A cell's diverged.json as the runner and status leave it and its fine-tunings out."""
  with tempfile.TemporaryDirectory() as d:
    out = Path(d)
    path = records.cell_dir(out, "c") / records.DIVERGED_FILE
    fk.place(path, data)
    plan = types.SimpleNamespace(cells=[_cell("c"), _cell("f", init_cell="c")])
    fk.check(lambda: runner.diverged(out, plan), path, fk.allowance(path))


REPORT = {"pooled": {"full": {"mae": 1.5, "bad2": 0.1, "n": 100}},
          "scenes": [{"name": "a", "mae": 1.5}], "checkpoint": "final"}


@st.composite
def eval_records(draw):
  """An evaluation record, compressed as write_eval writes it or plain as older folders hold it,
  mutated before or after compression."""
  compressed = draw(st.booleans())
  if compressed and draw(st.booleans()):  # the compressed bytes damaged
    return True, draw(fk.mutated_bytes(lzma.compress(fk.dumps(REPORT))))
  data = draw(fk.mutated_json(REPORT))
  return compressed, lzma.compress(data) if compressed else data


@fk.fuzz(150)
@given(eval_records())
@example((True, lzma.compress(fk.dumps(REPORT), preset=9)))  # a 64 MiB dictionary: refused
@example((True, lzma.compress(b" " * (8 << 20))))  # 8 MiB from 1 KiB: refused
def test_eval_records(record):
  """eval/SET.json(.xz): the report or one line naming the file."""
  compressed, data = record
  with tempfile.TemporaryDirectory() as d:
    out = Path(d)
    path = records.cell_dir(out, "c") / records.EVAL_DIR / ("s.json" + (".xz" * compressed))
    fk.place(path, data)
    # xz's decoder takes the dictionary its header claims, up to the reader's limit.
    bound = (fk.allowance(path, per_byte=fk.PER_BYTE * records.XZ_MAX_RATIO)
             + records.XZ_MEMLIMIT if compressed else fk.allowance(path))
    rep = fk.check(lambda: records.read_eval(out, "c", "s"), path, bound)
    if rep is not fk.REFUSED:
      assert isinstance(rep, dict)


# ----------------------------------------------------------------------------- runtime caches

@pytest.fixture(scope="module")
def measured(tmp_path_factory):
  """tune.json's bytes as write_measurement writes one measurement of this machine."""
  path = tmp_path_factory.mktemp("tune") / "tune.json"
  choices.write_measurement(choices.measurement_key(), choices.KernelChoice(),
                            [{"kind": "a", "seconds": 1.0}], 3.0, path, others=0.1)
  return json.loads(path.read_text())


def test_tune_json_edited_by_hand(measured, tmp_path):
  """Regressions of the campaign: an entry that is no object, or whose choice holds no booleans,
  is no measurement (was an AttributeError, and a KeyError naming the choice later)."""
  key = choices.measurement_key()
  for entry in (True, {**measured[key], "choice": {"forward_ynn": None, "train_ynn": True}}):
    path = tmp_path / "tune.json"
    path.write_text(json.dumps({key: entry}))
    assert choices.measured_choice(path) is None


@fk.fuzz(150)
@given(st.data())
def test_tune_json(measured, draw):
  """tune.json: a measured choice, or none (measure again); never an error."""
  data = draw.draw(records_of(measured))
  with fk.placed("tune.json", data) as path:
    got = fk.check(lambda: choices.measured_choice(path), path, fk.allowance(path))
    assert got is not fk.REFUSED  # a cache: unreadable means measure again
    if got is not None:
      assert isinstance(got, choices.KernelChoice)
      choices.describe(got)


@fk.fuzz(100)
@given(fk.mutated_json(["sig-a", "sig-b"]) | st.just(FOLDER))
def test_kept_program_index(data):
  """A kept program's index of signatures: the strings in it, or none (compile again)."""
  with tempfile.TemporaryDirectory() as d:
    where = Path(d)
    kept_programs._state.update(folder=where, root=where)
    try:
      path = kept_programs.index_path(where, "p", "desc")
      fk.place(path, data)
      got = fk.check(lambda: kept_programs.remembered("p", "desc"), path, fk.allowance(path))
      assert got is not fk.REFUSED and all(isinstance(s, str) for s in got)
    finally:
      kept_programs._state.update(folder=None, root=None)


@fk.fuzz(60)
@given(st.data())
def test_kept_program_entry(draw):
  """A kept program's entry on disk damaged: loaded intact, or None (compile again)."""
  import jax  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  entry = _entry(jax, jnp)
  data = draw.draw(fk.mutated_bytes(entry) | st.just(entry))
  with tempfile.TemporaryDirectory() as d:
    where = Path(d)
    kept_programs._state.update(folder=where, root=where)
    try:
      kept_programs._store(where).put("k", data)
      got = fk.check(lambda: kept_programs.load("p", "k", lambda line: None), where,
                     fk.allowance(where, per_byte=1024))
      assert got is not fk.REFUSED
      if data == entry:
        assert got is not None
      if got is not None:  # an equivalent header (JSON spacing) may load: the program is intact
        assert np.allclose(got(jnp.ones(3)), 2.0)
    finally:
      kept_programs._state.update(folder=None, root=None)


_ENTRY = {}


def _entry(jax, jnp) -> bytes:
  """A packed entry of a tiny compiled program (compiled once)."""
  if "k" not in _ENTRY:
    compiled = jax.jit(lambda x: x * 2).lower(jnp.ones(3)).compile()
    _ENTRY["k"] = kept_programs.pack("k", compiled)
  return _ENTRY["k"]
