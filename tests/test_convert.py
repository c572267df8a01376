"""PyTorch PSMNet weight conversion: layouts against naive PyTorch semantics, key coverage, CLI."""

import json
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from sljax import cli
from sljax.errors import SljaxError
from sljax.nets import convert
from sljax.nets.layers import ConvBN2D, ConvBN3D
from sljax.nets.psmnet import ConvTransposeBN3D

KEYS_FILE = Path(__file__).parent / "data" / "psmnet_keys.txt"
EPS = 1e-5  # PyTorch BatchNorm default


def _reference_shapes() -> dict[str, tuple[int, ...]]:
  shapes = {}
  for line in KEYS_FILE.read_text().splitlines():
    if line and not line.startswith("#"):
      key, shape = line.split()
      shapes[key] = tuple(int(s) for s in shape.split("x"))
  return shapes


def _fake_state_dict(seed=0) -> dict[str, np.ndarray]:
  """Random tensors with the reference names and shapes ('module.' prefixed, as released)."""
  rng = np.random.RandomState(seed)
  sd = {}
  for key, shape in _reference_shapes().items():
    v = rng.randn(*shape).astype(np.float32) * 0.2
    if key.endswith("running_var"):
      v = rng.uniform(0.5, 1.5, shape).astype(np.float32)
    sd["module." + key] = v
  sd["module.dres0.0.1.num_batches_tracked"] = np.array(7)
  return sd


@pytest.fixture(scope="module")
def converted():
  sd = _fake_state_dict()
  return sd, convert.convert_state_dict(sd)


# Naive NumPy versions of PyTorch's layers (x is NDHWC / NHWC here, weights in PyTorch layout).
def _torch_conv(x, w, stride, pad):
  """Cross-correlation with zero padding: out[o] = sum_k x[s*o + k - p] w[k]."""
  nd = w.ndim - 2
  xp = np.pad(x, [(0, 0)] + [(pad, pad)] * nd + [(0, 0)])
  out_sz = [(xp.shape[1 + i] - w.shape[2 + i]) // stride + 1 for i in range(nd)]
  out = np.zeros([x.shape[0]] + out_sz + [w.shape[0]])
  for k in np.ndindex(*w.shape[2:]):
    sl = tuple(slice(k[i], k[i] + stride * (out_sz[i] - 1) + 1, stride) for i in range(nd))
    out += np.einsum("n...i,oi->n...o", xp[(slice(None),) + sl], w[(slice(None), slice(None)) + k])
  return out


def _torch_conv_transpose(x, w, stride, pad, out_pad):
  """Scatter: input i adds x[i] w[k] to output s*i + k - p; size (n-1)s - 2p + k + op."""
  nd = w.ndim - 2
  n_in = x.shape[1:1 + nd]
  full = np.zeros([x.shape[0]] + [(n_in[i] - 1) * stride + w.shape[2 + i] + out_pad
                                   for i in range(nd)] + [w.shape[1]])
  for k in np.ndindex(*w.shape[2:]):
    sl = tuple(slice(k[i], k[i] + stride * (n_in[i] - 1) + 1, stride) for i in range(nd))
    full[(slice(None),) + sl] += np.einsum("n...i,io->n...o", x, w[(slice(None), slice(None)) + k])
  crop = tuple(slice(pad, s - pad) if pad else slice(None) for s in full.shape[1:1 + nd])
  return full[(slice(None),) + crop]


def _torch_bn_eval(x, sd, prefix):
  g = lambda n: sd[f"module.{prefix}.{n}"]
  return (x - g("running_mean")) / np.sqrt(g("running_var") + EPS) * g("weight") + g("bias")


def _apply(module, variables, x):
  return np.asarray(jax.jit(lambda v, x: module.apply(v, x, train=False))(variables, x))


def _sub(variables, *path):
  out = {}
  for col in ("params", "batch_stats"):
    node = variables[col]
    for p in path:
      node = node[p]
    out[col] = node
  return out


def test_conv2d_bn_conversion(converted):
  sd, variables = converted
  x = np.random.RandomState(1).rand(1, 7, 8, 3).astype(np.float32)
  ours = _apply(ConvBN2D(32, 3, 2, 1), _sub(variables, "feature_extraction", "firstconv_0"), x)
  ref = _torch_bn_eval(_torch_conv(x, sd["module.feature_extraction.firstconv.0.0.weight"], 2, 1),
                       sd, "feature_extraction.firstconv.0.1")
  np.testing.assert_allclose(ours, ref, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("key,path,stride", [
    ("dres2.conv1.0", ("dres2", "conv1"), 2),     # 32 -> 64, stride 2
    ("dres0.0", ("dres0", "convbn_0"), 1),        # 64 -> 32
])
def test_conv3d_bn_conversion(converted, key, path, stride):
  sd, variables = converted
  cin = sd[f"module.{key}.0.weight"].shape[1]
  x = np.random.RandomState(2).randn(1, 4, 5, 6, cin).astype(np.float32)
  cout = sd[f"module.{key}.0.weight"].shape[0]
  ours = _apply(ConvBN3D(cout, strides=stride), _sub(variables, *path), x)
  ref = _torch_bn_eval(_torch_conv(x, sd[f"module.{key}.0.weight"], stride, 1), sd, f"{key}.1")
  np.testing.assert_allclose(ours, ref, rtol=1e-4, atol=1e-4)


def test_conv_transpose3d_bn_conversion(converted):
  sd, variables = converted
  x = np.random.RandomState(3).randn(1, 2, 3, 4, 64).astype(np.float32)
  ours = _apply(ConvTransposeBN3D(32), _sub(variables, "dres3", "conv6"), x)
  ref = _torch_bn_eval(_torch_conv_transpose(x, sd["module.dres3.conv6.0.weight"], 2, 1, 1),
                       sd, "dres3.conv6.1")
  assert ours.shape == (1, 4, 6, 8, 32)
  np.testing.assert_allclose(ours, ref, rtol=1e-4, atol=1e-4)


def test_every_reference_key_maps_and_every_param_is_covered(converted):
  sd, variables = converted
  template, transposed = convert.psmnet_template()
  flat = convert._flatten(variables)
  assert jax.tree.map(lambda a: tuple(a.shape), variables) == template
  # One flax array per reference tensor (num_batches_tracked dropped), nothing reused.
  assert len(flat) == len(_reference_shapes())
  assert sum(v.size for k, v in flat.items() if k[0] == "params") == 5_224_768
  assert len(transposed) == 6  # conv5 and conv6 of three hourglasses
  np.testing.assert_array_equal(
      variables["batch_stats"]["dres4"]["conv5"]["bn"]["var"],
      sd["module.dres4.conv5.1.running_var"])


def test_mismatched_state_dicts_are_errors(converted):
  sd, _ = converted
  missing = dict(sd)
  del missing["module.dres1.0.1.bias"]
  with pytest.raises(SljaxError, match=r"missing key\(s\): dres1\.0\.1\.bias"):
    convert.convert_state_dict(missing)
  extra = dict(sd, **{"module.dres9.0.weight": np.zeros(3)})
  with pytest.raises(SljaxError, match=r"unexpected key\(s\): dres9\.0\.weight"):
    convert.convert_state_dict(extra)
  wrong = dict(sd, **{"module.classif1.2.weight": np.zeros((2, 32, 3, 3, 3), np.float32)})
  with pytest.raises(SljaxError, match=r"classif1\.2\.weight"):
    convert.convert_state_dict(wrong)
  with pytest.raises(SljaxError, match="not a PSMNet"):
    convert.convert_state_dict({"fc.weight": np.zeros(3)})


def test_cli_round_trip(converted, tmp_path, capsys):
  sd, variables = converted
  np.savez(tmp_path / "sd.npz", **sd)
  out = tmp_path / "conv"
  assert cli.main(["convert-psmnet", str(tmp_path / "sd.npz"), str(out), "--maxdisp", "96"]) == 0
  assert "5,224,768" in capsys.readouterr().out
  name, kwargs, loaded = convert.load_converted(out)
  assert name == "psmnet" and kwargs == {"maxdisp": 96, "in_channels": 3}
  assert json.loads((out / "config.json").read_text())["model"] == "psmnet"
  a, b = convert._flatten(loaded), convert._flatten(variables)
  assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
  # Refuses to overwrite, accepts with --overwrite.
  assert cli.main(["convert-psmnet", str(tmp_path / "sd.npz"), str(out)]) == 2
  assert "--overwrite" in capsys.readouterr().err
  assert cli.main(["convert-psmnet", str(tmp_path / "sd.npz"), str(out), "--overwrite"]) == 0


def test_bad_inputs(tmp_path, monkeypatch, capsys):
  assert cli.main(["convert-psmnet", str(tmp_path / "none.tar"), str(tmp_path / "o")]) == 2
  assert "none.tar does not exist" in capsys.readouterr().err
  ckpt = tmp_path / "model.tar"
  ckpt.write_bytes(b"not a checkpoint")
  monkeypatch.setitem(sys.modules, "torch", None)  # as if PyTorch were not installed
  with pytest.raises(SljaxError, match=r"pip install \"sljax\[torch\]\""):
    convert.read_state_dict(ckpt)
  with pytest.raises(SljaxError, match="not a checkpoint.*converted PSMNet"):
    convert.load_converted(tmp_path)


@pytest.mark.parametrize("content, why", [
    (b"conv.weight 1 2 3\n", "not a zip archive"),  # numpy: "pickled (object) data" ValueError
    (b"", "empty file (0 bytes)"),
    (b"PK\x03\x04 half an archive", "damaged or truncated: BadZipFile"),
])
def test_unreadable_npz_is_one_line_error(tmp_path, capsys, content, why):
  fake = tmp_path / "fake.npz"
  fake.write_bytes(content)
  assert cli.main(["convert-psmnet", str(fake), str(tmp_path / "out")]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and err[0].startswith(
      f"sljax convert-psmnet: error: {fake}: not an .npz archive of a PyTorch state_dict "
      f"({why}"), err
  assert not (tmp_path / "out").exists()


def test_failed_save_keeps_the_earlier_conversion(tmp_path, monkeypatch):
  """A full disk while writing variables.npz (--overwrite): the earlier config.json and
  variables.npz stay byte for byte and no temporary file remains."""
  import errno
  out = convert.save_converted(tmp_path / "conv", {"params": {"w": np.ones(3)}}, {"maxdisp": 16})
  before = {p.name: p.read_bytes() for p in out.iterdir()}

  def full(path, **arrays):
    with open(path, "wb") as f:
      f.write(b"PK\x03\x04 half")
    raise OSError(errno.ENOSPC, "No space left on device", str(path))
  monkeypatch.setattr(np, "savez", full)
  with pytest.raises(OSError) as info:
    convert.save_converted(out, {"params": {"w": np.zeros(3)}}, {"maxdisp": 32}, overwrite=True)
  assert info.value.filename == str(out / "variables.npz")
  assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_invalid_config_json_is_named(tmp_path, capsys):
  """A workdir (or converted folder) whose config.json is not JSON: the JSON error, not 'not a
  checkpoint'."""
  for kind in ("workdir", "converted"):
    model = tmp_path / kind
    (model / ("checkpoints" if kind == "workdir" else "")).mkdir(parents=True, exist_ok=True)
    if kind == "converted":
      np.savez(model / "variables.npz", w=np.zeros(1))
    (model / "config.json").write_text("{not json")
    assert cli.main(["export", str(model), str(tmp_path / "a.jax"), "--size", "8x8"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{model / 'config.json'}: not valid JSON (" in err[0], err
  with pytest.raises(SljaxError, match="not valid JSON"):  # predict and evaluate load so too
    convert.load_converted(tmp_path / "converted")
