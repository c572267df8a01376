"""sljax export: the artifact runs in a process that imports only jax and numpy, and agrees with
sljax.inference on the same pairs; the sidecar; bad input."""

import errno
import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from sljax import cli, inference
from sljax.deploy import stablehlo
from sljax.errors import SljaxError
from test_inference import UNET_KW, random_variables

RUNNER = r"""
import json, sys
import numpy as np
import jax
jobs = json.loads(sys.argv[1])
for job in jobs:
  with open(job["artifact"], "rb") as f:
    exp = jax.export.deserialize(bytearray(f.read()))
  z = np.load(job["inputs"])
  out = exp.call(z["left"], z["right"])
  np.savez(job["outputs"], **{k: np.asarray(v) for k, v in out.items()})
model_code = sorted({m.split(".")[0] for m in sys.modules} & {"sljax", "flax", "optax", "orbax"})
print(json.dumps({"model_code_imported": model_code}))
"""


def run_artifacts(jobs: list[dict]) -> None:
  """Runs each artifact on its inputs in a fresh process that imports only jax and numpy."""
  env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
  env["JAX_PLATFORMS"] = "cpu"
  proc = subprocess.run([sys.executable, "-c", RUNNER, json.dumps(jobs)], capture_output=True,
                        text=True, env=env, cwd="/", timeout=600)
  assert proc.returncode == 0, proc.stderr[-3000:]
  assert json.loads(proc.stdout.strip().splitlines()[-1]) == {"model_code_imported": []}


def exported_outputs(tmp_path, predictor, size, batches):
  """Exports at size, runs the artifact on each batch in a clean process; returns its outputs."""
  path, side = stablehlo.write_export(predictor, size, tmp_path / "model.jax", "test")
  jobs = []
  for i, (left, right) in enumerate(batches):
    np.savez(tmp_path / f"in{i}.npz", left=left, right=right)
    jobs.append({"artifact": str(path), "inputs": str(tmp_path / f"in{i}.npz"),
                 "outputs": str(tmp_path / f"out{i}.npz")})
  run_artifacts(jobs)
  return [dict(np.load(j["outputs"])) for j in jobs], json.loads(side.read_text())


def _batch(rng, b, h, w, c=1):
  left = rng.uniform(0, 1, (b, h, w, c)).astype(np.float32)
  return left, np.roll(left, -3, axis=2)


@pytest.fixture(scope="module")
def unet_disp_vars():
  return random_variables("unet-disp", UNET_KW, 0)


@pytest.mark.parametrize("mode", ["pad", "resize"])
def test_unet_disp_round_trip_any_batch(tmp_path, unet_disp_vars, mode):
  pred = inference.make_predictor("unet-disp", UNET_KW, unet_disp_vars, train_size=(32, 48),
                                  mode=mode)
  rng = np.random.default_rng(1)
  batches = [_batch(rng, 1, 37, 45), _batch(rng, 3, 37, 45)]  # the batch size is symbolic
  outs, info = exported_outputs(tmp_path, pred, (37, 45), batches)
  for (left, right), out in zip(batches, outs):
    want = pred(left, right)
    assert set(out) == set(want) == {"disparity"}
    assert out["disparity"].shape == want["disparity"].shape == (len(left), 37, 45)
    np.testing.assert_allclose(out["disparity"], want["disparity"], rtol=1e-5, atol=1e-4)
  assert info["mode"] == mode and info["input"]["height"] == 37 and info["input"]["width"] == 45
  assert info["input"]["channels"] == 1 and info["outputs"] == {"disparity": [None, 37, 45]}
  if mode == "pad":
    assert info["pad"] == {"multiple": 4, "fill": [0.5], "where": "top and right"}
  else:
    assert info["train_size"] == [32, 48]


def test_unet_sl_round_trip(tmp_path):
  kw = dict(UNET_KW, t=4)
  pred = inference.make_predictor("unet-sl", kw, random_variables("unet-sl", kw, 1), mode="pad")
  batches = [_batch(np.random.default_rng(2), 2, 33, 50)]
  (out,), info = exported_outputs(tmp_path, pred, (33, 50), batches)
  want = pred(*batches[0])
  assert set(out) == set(want) == {"disparity", "patterns", "patterns_right", "confidence"}
  np.testing.assert_allclose(out["patterns"], want["patterns"], atol=1e-5)
  np.testing.assert_allclose(out["patterns_right"], want["patterns_right"], atol=1e-5)
  # The artifact correlates with the shift-major formulation: the same shifts except where two
  # shifts' sums are float32 near-ties (these random patterns sit near 0.5: many near-ties).
  same = out["disparity"] == want["disparity"]
  assert same.mean() > 0.99
  np.testing.assert_allclose(out["confidence"][same], want["confidence"][same], atol=1e-3)
  assert info["outputs"]["patterns"] == [None, 33, 50, 4]


def test_export_cli_and_bad_inputs(tmp_path, capsys, unet_disp_vars):
  from test_predict import _converted_model
  model = _converted_model(tmp_path / "m", "unet-disp", UNET_KW)
  out = tmp_path / "art" / "unet.jax"
  assert cli.main(["export", str(model), str(out), "--size", "24x40"]) == 0
  assert "wrote" in capsys.readouterr().out
  info = json.loads((tmp_path / "art" / "unet.json").read_text())
  assert info["load"][1].startswith("exp = jax.export.deserialize")
  assert info["model"] == "unet-disp" and info["platforms"] == ["cpu", "cuda"]

  def one_error(argv, match):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("sljax export: error: ") and match in err[0], err
  one_error(["export", str(model), str(out), "--size", "24x40"], "exists (pass --overwrite")
  for bad in ("24", "24x", "0x40", "axb"):
    one_error(["export", str(model), str(tmp_path / "b.jax"), "--size", bad], "--size")
  one_error(["export", "sgbm", str(tmp_path / "b.jax"), "--size", "8x8"], "not a JAX model")
  one_error(["export", str(tmp_path / "nope"), str(tmp_path / "b.jax"), "--size", "8x8"],
            "unknown model")
  one_error(["export", str(tmp_path), str(tmp_path / "b.jax"), "--size", "8x8"],
            "not a checkpoint")
  one_error(["export", str(model), str(tmp_path / "b.jax"), "--size", "8x8", "--mode", "resize"],
            "training size")
  one_error(["export", str(model), str(tmp_path / "b.jax"), "--size", "8x8", "--maxdisp", "16"],
            "maxdisp is a PSMNet's cost volume depth; unet-disp has none")
  one_error(["export", str(model), str(tmp_path / "b.jax"), "--size", "8x8",
             "--search-range", "16"], "search_range is unet-sl's correlation range")
  assert not (tmp_path / "b.jax").exists()
  with pytest.raises(SljaxError, match="HEIGHTxWIDTH"):
    stablehlo.parse_size("1x2x3")


@pytest.mark.parametrize("size, message", [
    ("24x40", "size must be (height, width) in pixels"),  # else ValueError: too many values
    (24, "size must be (height, width) in pixels"),  # else TypeError: cannot unpack
    ((24, 40, 1), "size must be (height, width) in pixels"),
    ((24.0, 40), "size must be two integers"),  # else jax's symbolic-shape syntax error
    ((0, 40), "size 0x40: height and width must be positive"),  # else an artifact for no pixels
    ((-8, 40), "size -8x40: height and width must be positive"),
])
def test_export_names_a_bad_size_before_tracing(tmp_path, unet_disp_vars, size, message):
  pred = inference.make_predictor("unet-disp", UNET_KW, unet_disp_vars, mode="pad")
  for call in (lambda: stablehlo.export_model(pred, size),
               lambda: stablehlo.inference_function(pred, size),
               lambda: stablehlo.write_export(pred, size, tmp_path / "m.jax", "test")):
    with pytest.raises(SljaxError, match=re.escape(message)):
      call()
  assert not list(tmp_path.iterdir())


def test_export_names_a_predictor_that_is_not_one(tmp_path):
  for call in (stablehlo.export_model, stablehlo.inference_function):
    with pytest.raises(SljaxError, match="predictor must be a sljax.inference.Predictor .*got "
                                         "str 'runs/x'"):
      call("runs/x", (8, 8))  # a path instead of sljax.inference.load(path): no AttributeError
  with pytest.raises(SljaxError, match="predictor must be a sljax.inference.Predictor"):
    stablehlo.write_export("runs/x", (8, 8), tmp_path / "m.jax", "test")


def test_export_size_of_numpy_ints_writes_a_json_sidecar(tmp_path, unet_disp_vars):
  """np.int64 sizes (e.g. from an image's shape) are plain ints in the sidecar, which json
  refused before."""
  pred = inference.make_predictor("unet-disp", UNET_KW, unet_disp_vars, mode="pad")
  _, side = stablehlo.write_export(pred, (np.int64(8), np.int64(12)), tmp_path / "m.jax", "test")
  info = json.loads(side.read_text())
  assert (info["input"]["height"], info["input"]["width"]) == (8, 12)


@pytest.mark.parametrize("fail", ["artifact", "sidecar"])
def test_full_disk_keeps_the_earlier_export(tmp_path, unet_disp_vars, monkeypatch, fail):
  """--overwrite onto a disk that fills part-way: the earlier artifact and its sidecar stay
  byte for byte, no temporary file remains, and the error names the file being written."""
  pred = inference.make_predictor("unet-disp", UNET_KW, unet_disp_vars, mode="pad")
  out, side = stablehlo.write_export(pred, (8, 8), tmp_path / "model.jax", "first")
  before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
  assert sorted(before) == ["model.jax", "model.json"]
  exported = stablehlo.export_model(pred, (8, 8))
  monkeypatch.setattr(stablehlo, "export_model", lambda *args: exported)  # no second tracing

  def half_then_full(self, data, *args, **kwargs):
    with open(self, "w" if isinstance(data, str) else "wb") as f:
      f.write(data[:len(data) // 2])
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))
  method = "write_bytes" if fail == "artifact" else "write_text"
  monkeypatch.setattr(type(tmp_path), method, half_then_full)
  with pytest.raises(OSError) as info:
    stablehlo.write_export(pred, (8, 8), out, "second", overwrite=True)
  assert info.value.filename == str(out if fail == "artifact" else side)
  assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
