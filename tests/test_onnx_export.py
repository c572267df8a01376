"""sljax export MODEL OUT.onnx: every network in both modes runs in ONNX Runtime as JAX runs the
same traced function (float32, CPU, highest precision), with any batch size; the 3D and
transposed convolutions of the conv plugin against lax; the check refuses and writes nothing;
the sidecar; a missing extra."""

import builtins
import json

import jax
import numpy as np
import pytest

pytest.importorskip("jax2onnx", reason='the onnx extra: pip install -e ".[test]"')
pytest.importorskip("onnxruntime", reason='the onnx extra: pip install -e ".[test]"')

from sljax import cli, inference  # noqa: E402
from sljax.deploy import onnx as dx  # noqa: E402
from sljax.errors import SljaxError  # noqa: E402
from test_inference import random_variables  # noqa: E402

KW = {
    "psmnet": {"maxdisp": 16, "in_channels": 3},
    "psmnet-mtl": {"maxdisp": 16, "t": 3, "in_channels": 3},
    "unet-sl": {"depth": 2, "base_width": 4, "in_channels": 1, "t": 4},
    "unet-disp": {"depth": 2, "base_width": 4, "in_channels": 1},
}
SIZE = (30, 44)  # not a multiple of any network's padding: pad mode pads and crops
TRAIN = (32, 48)


@pytest.fixture(scope="module")
def variables():
  return {name: random_variables(name, kw, 5, hw=(32, 32)) for name, kw in KW.items()}


def _random_pair(b, c, seed):
  rng = np.random.default_rng(seed)
  left = rng.uniform(0, 1, (b, *SIZE, c)).astype(np.float32)
  return left, np.roll(left, -3, axis=2)


OUTPUTS = {"psmnet": {"disparity"}, "unet-disp": {"disparity"},
           "psmnet-mtl": {"disparity", "patterns", "confidence"},
           "unet-sl": {"disparity", "patterns", "patterns_right", "confidence"}}


@pytest.mark.parametrize("mode", ["pad", "resize"])
@pytest.mark.parametrize("name", list(KW))
def test_onnx_runtime_equals_the_traced_function(variables, name, mode, capfd):
  pred = inference.make_predictor(name, KW[name], variables[name], train_size=TRAIN, mode=mode)
  traced = dx.trace(pred, SIZE)
  if traced.dynamic_batch:  # loads and runs at another batch without ONNX Runtime's warnings
    import onnxruntime as ort
    options = ort.SessionOptions()
    options.log_severity_level = 1  # info and up, as a user's session shows warnings
    capfd.readouterr()
    ort.InferenceSession(traced.model, options, providers=["CPUExecutionProvider"]).run(
        None, dict(zip(("left", "right"), _random_pair(3, pred.channels, 3))))
    assert "Error merging shape info" not in capfd.readouterr().err
  # A dynamic batch, except unet-sl (a constant batch for jax2onnx's rule in the correlation).
  assert traced.dynamic_batch == (name != "unet-sl")
  assert set(traced.names) == OUTPUTS[name]  # the .jax artifact's and the predictor's
  assert traced.shapes["disparity"] == [None if traced.dynamic_batch else 1, *SIZE]
  left, right = dx.check_pair(SIZE, pred.channels)
  if traced.dynamic_batch:  # the rendered pair and a random one, as a batch of 2
    more = _random_pair(1, pred.channels, 7)
    left, right = np.concatenate([left, more[0]]), np.concatenate([right, more[1]])
  got = dict(zip(traced.names, dx.run_onnx(traced.model, left, right)))
  want = dict(zip(traced.names, dx.run_jax(traced.fn, left, right)))
  assert got["disparity"].shape == (len(left), *SIZE)
  same = np.ones(want["disparity"].shape, bool)
  if name == "unet-sl":  # integer shifts: float32 near-ties may tip, the rest equal
    same = got["disparity"] == want["disparity"]
    assert same.mean() > 0.99
  else:
    # 1e-3 px, or float32's relative rounding over PSMNet's ~40 layers where the random
    # weights' soft argmin is steep (one pixel of psmnet's at 11.07 px differed by 1.15e-3).
    np.testing.assert_allclose(got["disparity"], want["disparity"], rtol=1e-4, atol=1e-3)
  for k in set(got) - {"disparity"}:
    keep = same if got[k].ndim == 3 else same[..., None].repeat(got[k].shape[-1], -1)
    # 1e-4, or float32's relative rounding (psmnet-mtl's random 2D stack: 1.4e-4 at p = 0.31)
    np.testing.assert_allclose(got[k][keep], want[k][keep], rtol=1e-3, atol=1e-4, err_msg=k)


@pytest.mark.parametrize("case", ["conv3d", "strided3d", "transposed3d", "transposed2d"])
def test_conv_plugin_matches_lax(case):
  """The plugin's Conv / ConvTranspose against lax.conv_general_dilated (float64 reference)."""
  import jax2onnx
  import onnxruntime as ort
  from sljax.deploy import conv
  dims3, dims2 = ("NDHWC", "DHWIO", "NDHWC"), ("NHWC", "HWIO", "NHWC")
  x3, k3 = (2, 4, 5, 6, 3), (3, 3, 3, 3, 2)
  fn, shapes = {
      "conv3d": (lambda x, k: jax.lax.conv_general_dilated(
          x, k, (1, 1, 1), ((1, 1),) * 3, dimension_numbers=dims3), (x3, k3)),
      "strided3d": (lambda x, k: jax.lax.conv_general_dilated(
          x, k, (2, 1, 2), ((1, 1), (0, 2), (1, 0)), dimension_numbers=dims3), (x3, k3)),
      "transposed3d": (lambda x, k: jax.lax.conv_general_dilated(  # PSMNet's hourglass
          x, k, (1, 1, 1), ((1, 2),) * 3, lhs_dilation=(2, 2, 2), dimension_numbers=dims3),
          (x3, k3)),
      "transposed2d": (lambda x, k: jax.lax.conv_general_dilated(
          x, k, (1, 1), ((1, 2), (0, 1)), lhs_dilation=(2, 3), dimension_numbers=dims2),
          ((2, 5, 6, 3), (3, 2, 3, 2))),
  }[case]
  rng = np.random.default_rng(0)
  args = [rng.standard_normal(s).astype(np.float32) for s in shapes]
  with dx._converter_settings():
    conv.register()
    model = jax2onnx.to_onnx(fn, [jax.ShapeDtypeStruct(s, np.float32) for s in shapes],
                             opset=dx.OPSET)
  ops = [n.op_type for n in model.graph.node]
  assert ("ConvTranspose" if "transposed" in case else "Conv") in ops
  sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
  got = sess.run(None, {i.name: a for i, a in zip(sess.get_inputs(), args)})[0]
  with jax.enable_x64():
    want = np.asarray(fn(*[a.astype(np.float64) for a in args]))
  assert got.shape == want.shape
  np.testing.assert_allclose(got, want, rtol=0, atol=1e-4)


def test_cli_writes_onnx_and_its_own_sidecar(tmp_path, capsys):
  """A converted PSMNet folder (what convert-psmnet writes; align_corners=True as for the
  PyTorch 0.3 checkpoints, the other upsampling path) to ONNX: the check's line, the sidecar
  beside it (not the .jax artifact's model.json), and the model runs from the file."""
  from test_predict import _converted_model
  model = _converted_model(tmp_path / "m", "psmnet", dict(KW["psmnet"], align_corners=True))
  out = tmp_path / "art" / "model.onnx"
  assert cli.main(["export", str(model), str(out), "--size", "24x40"]) == 0
  printed = capsys.readouterr().out
  assert "largest |delta disparity| ONNX Runtime vs JAX:" in printed and "wrote" in printed
  assert sorted(p.name for p in out.parent.iterdir()) == ["model.onnx", "model.onnx.json"]
  info = json.loads((out.parent / "model.onnx.json").read_text())
  assert info["format"] == "sljax-onnx" and info["opset"] >= 17
  assert info["converter"]["jax2onnx"] == "0.12.5" and info["input"]["batch"] == "any (dynamic)"
  assert info["input"]["names"] == ["left", "right"] and info["input"]["channels"] == 3
  assert info["input"]["channel_order"] == "RGB"
  assert info["outputs"] == {"disparity": [None, 24, 40]}
  assert info["check"]["max_abs_disparity"] <= dx.TOLERANCE_PX
  left, right = _random_pair(1, 3, 1)
  left, right = left[:, :24, :40], right[:, :24, :40]
  (disp,) = dx.run_onnx(out.read_bytes(), left, right)
  pred = inference.load(model, mode="pad")
  np.testing.assert_allclose(disp, pred(left, right)["disparity"], rtol=0, atol=1e-3)
  assert cli.main(["export", str(model), str(out), "--size", "24x40"]) == 2  # no overwrite
  assert "exists (pass --overwrite" in capsys.readouterr().err


def test_a_refused_export_writes_nothing(tmp_path, variables, monkeypatch):
  """ONNX Runtime off by more than the tolerance (planted): an error naming the difference,
  and no file (nor a temporary one) left behind; an earlier export stays as it was."""
  pred = inference.make_predictor("unet-disp", KW["unet-disp"], variables["unet-disp"])
  real = dx.run_onnx

  def off(model, left, right):
    return [v + np.float32(0.02) for v in real(model, left, right)]
  monkeypatch.setattr(dx, "run_onnx", off)
  with pytest.raises(SljaxError, match=r"not written: .*largest \|delta disparity\| 0.02"):
    dx.write_onnx(pred, (16, 24), tmp_path / "m.onnx", "test")
  assert list(tmp_path.iterdir()) == []
  (tmp_path / "m.onnx").write_bytes(b"earlier")
  with pytest.raises(SljaxError, match="not written"):
    dx.write_onnx(pred, (16, 24), tmp_path / "m.onnx", "test", overwrite=True)
  assert [p.name for p in tmp_path.iterdir()] == ["m.onnx"]
  assert (tmp_path / "m.onnx").read_bytes() == b"earlier"


def test_drop_traced_shapes_removes_every_intermediate_annotation():
  import onnx
  from onnx import TensorProto, helper
  x = helper.make_tensor_value_info("x", TensorProto.FLOAT, ["B", 64])
  y = helper.make_tensor_value_info("y", TensorProto.FLOAT, ["B", 64])
  traced_batch = helper.make_tensor_value_info("t", TensorProto.FLOAT, [1, 64])  # the trace's
  graph = helper.make_graph([helper.make_node("Relu", ["x"], ["t"]),
                             helper.make_node("Relu", ["t"], ["y"])], "g", [x], [y],
                            value_info=[traced_batch])
  model = helper.make_model(graph)
  assert dx.drop_traced_shapes(model) == 1
  assert len(model.graph.value_info) == 0
  assert [i.name for i in model.graph.input] == ["x"] and [o.name for o in model.graph.output] == ["y"]
  onnx.checker.check_model(model)


def test_verdict_counts_unet_sl_shift_flips():
  ok = {"max_abs_disparity": 0.0, "max_abs_confidence": 0.0, "shift_flips": 1, "pixels": 1000}
  assert dx.verdict(ok) is None
  assert "11 of 1000 pixels" in dx.verdict(dict(ok, shift_flips=11))
  assert "confidence" in dx.verdict(dict(ok, max_abs_confidence=2e-3))


def test_a_missing_extra_is_one_line(tmp_path, monkeypatch, capsys):
  real = builtins.__import__

  def no_jax2onnx(name, *args, **kwargs):
    if name.split(".")[0] == "jax2onnx":
      raise ImportError(f"No module named {name!r}", name=name)
    return real(name, *args, **kwargs)
  monkeypatch.setattr(builtins, "__import__", no_jax2onnx)
  with pytest.raises(SljaxError, match=r'jax2onnx is not installed\): pip install -e "\.\[onnx\]"'):
    dx.require()
  assert cli.main(["export", str(tmp_path), str(tmp_path / "m.onnx"), "--size", "8x8"]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and 'pip install -e ".[onnx]"' in err[0]
  assert not (tmp_path / "m.onnx").exists()
