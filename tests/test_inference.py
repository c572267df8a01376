import cv2
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sljax import inference
from sljax.data.dataset import resize_image
from sljax.errors import SljaxError
from sljax.nets import psmnet
from sljax.nets import ModelConfig
from sljax.runtime import choices
from toys import ToySL, registered, toy_spec


class ToyDisp(nn.Module):
  """disparity = 10 * first channel of the left view + bias: every output pixel is traceable."""
  in_channels: int = 1
  conv_impl: str | None = None

  @nn.compact
  def __call__(self, left, right, train=False):
    bias = self.param("bias", nn.initializers.zeros, (left.shape[-1],))
    return {"disparity": 10.0 * left[..., 0] + bias[0] + 0.0 * right[..., 0]}


class Spy(ToyDisp):
  """Records the input shape it is traced with (SEEN)."""

  @nn.compact
  def __call__(self, left, right, train=False):
    SEEN["shape"] = left.shape
    return {"disparity": left[..., 0]}


SEEN: dict = {}


@pytest.fixture(scope="module", autouse=True)
def toy_networks():
  """The toy networks of this file, in the registry while it runs."""
  with registered(toy_spec("toy", ToyDisp), toy_spec("count", ToyCount), toy_spec("spy", Spy),
                  toy_spec("spy-psmnet", SpyPSMNet, pad="normalized-zero", gray=False),
                  toy_spec("toy-sl", ToySL, outputs=("sl_logits", "sl_logits_right"),
                           gray=False),
                  toy_spec("toy-mtl", ToyMTL, outputs=("disparity", "sl_logits"), gray=False)):
    yield


def _predictor(net, variables, channels=1, **options):
  return inference.Predictor(ModelConfig.of(net, in_channels=channels), variables,
                             inference.PredictOptions(**options))


def _toy(mode, channels=1, train_size=(32, 48)):
  variables = {"params": {"bias": jnp.array([0.5] * channels, jnp.float32)}}
  return _predictor("toy", variables, channels, train_size=train_size, mode=mode)


@pytest.fixture(scope="module")
def pad_predictor():
  return _toy("pad")


@pytest.fixture(scope="module")
def resize_predictor():
  return _toy("resize")


def _pair(h, w, seed=0, c=None):
  rng = np.random.default_rng(seed)
  shape = (h, w) if c is None else (h, w, c)
  return rng.uniform(0, 1, shape).astype(np.float32), rng.uniform(0, 1, shape).astype(np.float32)


def test_pad_mode_on_odd_size_crops_back_exactly(pad_predictor):
  left, right = _pair(37, 45)
  out = pad_predictor(left, right)
  assert out["disparity"].shape == (37, 45) and out["disparity"].dtype == np.float32
  # Every output pixel comes from the same input pixel: crop offset is right.
  np.testing.assert_allclose(out["disparity"], 10.0 * left + 0.5, rtol=1e-6)
  assert pad_predictor.channels == 1


def test_pad_mode_pads_top_and_right():
  """Networks whose registry entry pads with "zero": zeros above and right of the image, to a
  multiple of 16."""
  pred = _predictor("spy", {}, mode="pad")
  left, right = _pair(33, 40)
  pred(left, right)
  assert SEEN["shape"] == (1, 48, 48, 1)
  lf = np.pad(left, ((15, 0), (0, 8)))
  # Apply the model directly on our own padding: the predictor's crop gives the same map.
  np.testing.assert_array_equal(pred(left, right)["disparity"], lf[15:, :40])


class SpyPSMNet(psmnet.PSMNet):
  """Records the input it runs on (SEEN["left"])."""

  @nn.compact
  def __call__(self, left, right, train=False):
    jax.debug.callback(lambda x: SEEN.update(left=np.asarray(x)), left)
    return {"disparity": left[..., 0]}


@pytest.mark.parametrize("channels", [1, 3])
def test_psmnet_pad_value_is_the_normalised_zero(channels):
  """Gray and RGB PSMNets see the normalisation's zero in the pad (a spy subclass records it)."""
  pred = _predictor("spy-psmnet", {}, channels, mode="pad")
  left, right = _pair(30, 27, c=channels)
  pred(left, right)
  jax.effects_barrier()
  x = np.asarray(SEEN["left"])
  assert x.shape == (1, 32, 32, channels)
  np.testing.assert_array_equal(x[0, 2:, :27], left)
  pad = np.concatenate([x[0, :2].reshape(-1, channels), x[0, 2:, 27:].reshape(-1, channels)])
  mean = np.array([0.485, 0.456, 0.406], np.float32)
  want = mean if channels == 3 else mean.mean(keepdims=True)
  np.testing.assert_allclose(pad, np.broadcast_to(want, pad.shape), rtol=1e-6)
  # ...which the model's own input normalisation maps to 0.
  np.testing.assert_allclose(np.asarray(psmnet.normalize_images(pad)), 0.0, atol=1e-6)


def test_resize_mode_against_cv2(resize_predictor):
  left, right = _pair(50, 70, seed=1)
  out = resize_predictor(left, right)["disparity"]
  small = resize_image(left[..., None], (32, 48))[..., 0]  # the training loader's resampling
  net = 10.0 * small + 0.5
  want = cv2.resize(net, (70, 50), interpolation=cv2.INTER_LINEAR) * (70 / 48)
  assert out.shape == (50, 70)
  np.testing.assert_allclose(out, want, rtol=1e-5, atol=1e-5)


def test_inputs_uint8_uint16_rgb_and_batches(pad_predictor):
  left, right = _pair(20, 30, seed=2)
  base = pad_predictor(left, right)["disparity"]
  u8l, u8r = (np.round(left * 255).astype(np.uint8), np.round(right * 255).astype(np.uint8))
  np.testing.assert_allclose(pad_predictor(u8l, u8r)["disparity"],
                             10.0 * u8l / 255.0 + 0.5, rtol=1e-5)
  u16l = np.round(left * 65535).astype(np.uint16)
  np.testing.assert_allclose(pad_predictor(u16l, u16l)["disparity"], base, atol=1e-3)
  # An RGB view of a gray image converts back to the same gray (luma weights sum to 1).
  rgb = np.repeat(left[..., None], 3, axis=2)
  np.testing.assert_allclose(pad_predictor(rgb, rgb)["disparity"], base, atol=1e-5)
  # Batched == one at a time.
  l2, r2 = _pair(20, 30, seed=3)
  batch = pad_predictor(np.stack([left, l2])[..., None], np.stack([right, r2])[..., None])
  assert batch["disparity"].shape == (2, 20, 30)
  np.testing.assert_allclose(batch["disparity"][0], base, rtol=1e-6)
  np.testing.assert_allclose(batch["disparity"][1], pad_predictor(l2, r2)["disparity"], rtol=1e-6)


def test_rgb_model_gets_gray_input_repeated():
  pred = _toy("pad", channels=3)
  assert pred.channels == 3
  left, right = _pair(16, 16, seed=4)
  np.testing.assert_allclose(pred(left, right)["disparity"], 10.0 * left + 0.5, rtol=1e-6)


class ToyCount(ToyDisp):
  """ToyDisp under another name: a model no other test compiles, so its trace count starts at 0."""


def test_compiled_once_per_shape_and_shared_between_predictors():
  variables = {"params": {"bias": jnp.array([0.5], jnp.float32)}}
  p = _predictor("count", variables, mode="pad")
  assert p.traces == 0
  p(*_pair(21, 33, seed=5))
  p(*_pair(21, 33, seed=6))
  assert p.traces == 1
  p(*_pair(40, 33, seed=6))  # pads to another shape: one more trace
  assert p.traces == 2
  # Resize mode: the network always sees the training size (32x48, compiled above: 21x33 pads
  # to 32x48), and an equal model in another predictor reuses the compilation.
  r = _predictor("count", variables, mode="resize", train_size=(32, 48))
  r(*_pair(17, 19))
  r(*_pair(60, 90))
  assert r.traces == p.traces == 2
  left, right = _pair(17, 19)
  r(np.stack([left, left])[..., None], np.stack([right, right])[..., None])  # batch 2: new shape
  assert r.traces == 3


def test_a_command_keeps_the_programs_whole_and_the_next_one_loads_them(tmp_path, monkeypatch):
  """With compiled programs kept on disk (command lines), a new process (a fresh Programs)
  loads the forward program instead of tracing it, with the same outputs; another model
  (its fields) or other compiler options is another program."""
  from sljax.inference import programs
  from sljax.runtime import kept_programs
  variables = {"params": {"bias": jnp.array([0.25], jnp.float32)}}
  pair = _pair(21, 33, seed=7)
  expected = _predictor("toy", variables, mode="pad")(*pair)  # the plain jitted program
  monkeypatch.setenv(kept_programs.ENV, "on")
  jax.clear_caches()
  where = kept_programs.enable(tmp_path / "xla")
  try:
    entries = lambda: sorted(p.name for p in where.glob("sljax-program-inference-forward-*-cache"))
    for process in range(2):
      monkeypatch.setattr(programs, "PROGRAMS", programs.Programs())
      out = _predictor("toy", variables, mode="pad")(*pair)
      for k in expected:
        np.testing.assert_array_equal(out[k], expected[k])
      model = ModelConfig.of("toy", in_channels=1).build()
      assert programs.PROGRAMS.traces(model) == (1 if process == 0 else 0)  # loaded, not traced
      assert len(entries()) == 1
    off = _predictor("toy", variables, mode="pad", kernels=choices.KernelChoice(forward_ynn=False))
    np.testing.assert_allclose(off(*pair)["disparity"], expected["disparity"], rtol=1e-6)
    assert len(entries()) == 2 and programs.PROGRAMS.traces(model) == 1
    # Another field of the model, with the same variables and inputs: another program.
    other = inference.Predictor(ModelConfig.of("toy", in_channels=1, conv_impl="lax"), variables,
                                inference.PredictOptions(mode="pad"))
    np.testing.assert_array_equal(other(*pair)["disparity"], expected["disparity"])
    assert len(entries()) == 3
  finally:
    kept_programs.enable(None)


def test_bad_inputs(pad_predictor):
  left, right = _pair(20, 30)
  with pytest.raises(SljaxError, match="differ in size"):
    pad_predictor(left, right[:, :29])
  with pytest.raises(SljaxError, match="channels"):
    pad_predictor(np.zeros((20, 30, 2), np.float32), np.zeros((20, 30, 2), np.float32))
  with pytest.raises(SljaxError, match="channels"):
    pad_predictor(np.zeros((1, 20, 30, 4), np.float32), np.zeros((1, 20, 30, 4), np.float32))
  bad = left.copy()
  bad[3, 4] = np.nan
  with pytest.raises(SljaxError, match="NaN"):
    pad_predictor(bad, right)
  with pytest.raises(SljaxError, match=r"\[0, 1\]"):
    pad_predictor(left * 255, right * 255)
  with pytest.raises(SljaxError, match="int32"):
    pad_predictor(left.astype(np.int32), right.astype(np.int32))
  with pytest.raises(SljaxError, match="mode"):
    _toy("crop")
  with pytest.raises(SljaxError, match="training size"):
    _toy("resize", train_size=None)


def test_bfloat16_jax_views_are_float_images(pad_predictor):
  """jax bfloat16 is numpy kind "V" (ml_dtypes): read as a float image, not refused as 'not an
  image array'; the values are the bfloat16 ones, as a float32 copy of them gives."""
  left, right = _pair(20, 30, seed=12)
  bl, br = jnp.asarray(left, jnp.bfloat16), jnp.asarray(right, jnp.bfloat16)
  want = pad_predictor(np.asarray(bl, np.float32), np.asarray(br, np.float32))["disparity"]
  np.testing.assert_array_equal(pad_predictor(bl, br)["disparity"], want)
  with pytest.raises(SljaxError, match=r"left view must be scaled to \[0, 1\]"):
    pad_predictor(bl * 255, br * 255)  # still checked as any float image


def test_checkpoint_that_does_not_match_the_model():
  with pytest.raises(SljaxError, match="do not match.*bias"):
    _predictor("toy", {"params": {"bias": jnp.zeros((2,))}}, name="ckpt/x")
  with pytest.raises(SljaxError, match="ckpt/y.*do not match"):
    _predictor("toy", {"params": {"other": jnp.zeros((1,))}}, name="ckpt/y")


def test_sl_model_disparity_from_pattern_correlation():
  rng = np.random.default_rng(7)
  h, w, d = 24, 64, 5
  tex = (rng.uniform(size=(h, w + d, 3)) > 0.5).astype(np.float32)
  left, right = tex[:, :w], tex[:, d:]  # right[x - d] = tex[x] = left[x]
  pred = _predictor("toy-sl", {"params": {"gain": jnp.ones(())}}, 3, mode="pad")
  assert pred.is_sl and pred.channels == 3
  out = pred(left, right)
  assert set(out) == {"disparity", "patterns", "patterns_right", "confidence"}
  np.testing.assert_allclose(out["patterns"], left, atol=1e-6)
  assert out["confidence"].shape == (h, w)
  # Interior pixels (window fully inside, shift within the image) find the true shift.
  np.testing.assert_array_equal(out["disparity"][8:-8, 8 + d:-8], d)


# Real networks, tiny and randomly initialised.
UNET_KW = {"depth": 2, "base_width": 4, "in_channels": 1}


def random_variables(name, kwargs, seed, hw=(32, 48)):
  """Random variables of the right structure without running init (slow on a busy CPU)."""
  import jax
  from sljax.nets import build_model
  model = build_model(name, **kwargs)
  x = jax.ShapeDtypeStruct((1, *hw, kwargs["in_channels"]), jnp.float32)
  shapes = jax.eval_shape(lambda a, b: model.init(jax.random.PRNGKey(0), a, b, train=False), x, x)
  rng = np.random.default_rng(seed)

  def fill(path, leaf):
    key = str(path[-1])
    if "var" in key:
      return jnp.asarray(rng.uniform(0.5, 1.5, leaf.shape), jnp.float32)
    if "scale" in key:
      return jnp.asarray(1.0 + 0.1 * rng.normal(size=leaf.shape), jnp.float32)
    fan_in = max(1, int(np.prod(leaf.shape[:-1])))
    return jnp.asarray(rng.normal(size=leaf.shape) / np.sqrt(fan_in), jnp.float32)

  return jax.tree_util.tree_map_with_path(fill, dict(shapes))


@pytest.fixture(scope="module")
def unet_disp_vars():
  return random_variables("unet-disp", UNET_KW, 0)


@pytest.fixture(scope="module")
def unet_sl_vars():
  return random_variables("unet-sl", dict(UNET_KW, t=4), 1)


@pytest.mark.parametrize("mode", ["pad", "resize"])
def test_unet_disp_odd_sizes_and_batches(unet_disp_vars, mode):
  pred = inference.make_predictor("unet-disp", UNET_KW, unet_disp_vars, train_size=(32, 48),
                                  mode=mode)
  assert not pred.is_sl and pred.channels == 1
  rgb = np.random.default_rng(8).uniform(0, 1, (2, 37, 45, 3)).astype(np.float32)
  right = rgb[:, :, ::-1].copy()
  batch = pred(rgb, right)["disparity"]
  assert batch.shape == (2, 37, 45) and np.isfinite(batch).all()
  for i in range(2):
    np.testing.assert_allclose(pred(rgb[i], right[i])["disparity"], batch[i], rtol=1e-5, atol=1e-5)
  # The network's disparity = sigmoid * model-input width (padded to a multiple of 2^depth = 4
  # in pad mode), so it stays inside [0, width].
  width = 45 if mode == "resize" else 48
  assert batch.min() >= 0 and batch.max() <= width


def test_unet_sl_outputs(unet_sl_vars):
  pred = inference.make_predictor("unet-sl", dict(UNET_KW, t=4), unet_sl_vars,
                                  train_size=(32, 48), mode="resize")
  assert pred.is_sl
  left, right = _pair(33, 50, seed=9)
  out = pred(left, right)
  assert out["patterns"].shape == (33, 50, 4) and out["patterns_right"].shape == (33, 50, 4)
  assert ((out["patterns"] >= 0) & (out["patterns"] <= 1)).all()
  assert out["disparity"].shape == (33, 50) and out["confidence"].shape == (33, 50)
  # Correlation at the training size (u = 25% of 48 = 12 px), scaled back by 50 / 48.
  assert out["disparity"].max() <= 12 * 50 / 48 + 1e-4


def test_wrong_model_options_for_checkpoint(unet_disp_vars):
  with pytest.raises(SljaxError, match="ckpt.*do not match"):
    inference.make_predictor("unet-disp", dict(UNET_KW, base_width=8), unet_disp_vars,
                             name="ckpt")
  with pytest.raises(SljaxError, match="do not match"):
    inference.make_predictor("unet-sl", dict(UNET_KW, t=4), unet_disp_vars)


def test_load_checkpoint_round_trip(unet_sl_vars, tmp_path):
  import json

  from sljax.models import checkpoint as ckpt
  workdir = tmp_path / "run"
  workdir.mkdir()
  config = {"model": "unet-sl", "strategy": "stl", "net": "unet-sl",
            "model_kwargs": dict(UNET_KW, t=4), "size": [32, 48], "gray": True, "t": 4}
  (workdir / "config.json").write_text(json.dumps(config))
  manager = ckpt.make_manager(workdir / "checkpoints")
  ckpt.save(manager, 1, dict(unet_sl_vars), {"step": 1}, val_mae=1.0)
  manager.wait_until_finished()
  manager.close()
  left, right = _pair(40, 40, seed=10)
  direct = inference.make_predictor("unet-sl", dict(UNET_KW, t=4), unet_sl_vars,
                                    train_size=(32, 48), mode="resize")
  b = direct(left, right)
  for path in (workdir, workdir / "checkpoints"):
    loaded = inference.load(path, mode="resize")
    assert loaded.train_size == (32, 48) and loaded.model_name == "unet-sl"
    a = loaded(left, right)
    np.testing.assert_array_equal(a["patterns"], b["patterns"])
    np.testing.assert_array_equal(a["disparity"], b["disparity"])


class ToyMTL(nn.Module):
  """Like psmnet-mtl: a disparity and left-view pattern logits (logit = 4 * (image - 0.5))."""
  in_channels: int = 3
  conv_impl: str | None = None

  @nn.compact
  def __call__(self, left, right, train=False):
    gain = self.param("gain", nn.initializers.ones, ())
    return {"disparity": gain * left[..., 0], "sl_logits": 4.0 * gain * (left - 0.5)}


def test_mtl_style_model_confidence_is_mean_pattern_certainty():
  pred = _predictor("toy-mtl", {"params": {"gain": jnp.ones(())}}, 3, mode="pad")
  left, right = _pair(20, 24, seed=11, c=3)
  out = pred(left, right)
  assert set(out) == {"disparity", "patterns", "confidence"}
  p = 1.0 / (1.0 + np.exp(-4.0 * (left.astype(np.float64) - 0.5)))
  np.testing.assert_allclose(out["patterns"], p, rtol=1e-5)
  np.testing.assert_allclose(out["confidence"], np.abs(2 * p - 1).mean(axis=-1), atol=1e-5)


# PSMNet and the twin, tiny (32x32 model input, maxdisp 16) and randomly initialised; one
# compilation each, shared by the predictors of both modes.
PSM_KW = {"maxdisp": 16, "t": 3, "in_channels": 3}


@pytest.fixture(scope="module")
def mtl_predictor():
  variables = random_variables("psmnet-mtl", PSM_KW, 12, hw=(32, 32))
  return inference.make_predictor("psmnet-mtl", PSM_KW, variables, train_size=(32, 32),
                                  mode="pad")


def test_psmnet_mtl_pad_mode_odd_size(mtl_predictor):
  rng = np.random.default_rng(13)
  left = rng.integers(0, 256, (30, 27, 3), dtype=np.uint8)
  right = rng.integers(0, 256, (30, 27, 3), dtype=np.uint8)
  out = mtl_predictor(left, right)
  assert mtl_predictor.is_sl and mtl_predictor.channels == 3
  assert set(out) == {"disparity", "patterns", "confidence"}
  assert out["disparity"].shape == (30, 27) and out["patterns"].shape == (30, 27, 3)
  d = out["disparity"]
  assert np.isfinite(d).all() and d.min() >= 0 and d.max() <= 15  # soft-argmax over 0..15
  p = out["patterns"].astype(np.float64)
  assert ((p >= 0) & (p <= 1)).all()
  np.testing.assert_allclose(out["confidence"], np.abs(2 * p - 1).mean(axis=-1), atol=1e-6)


def test_psmnet_mtl_resize_mode_is_pad_at_training_size_resized_back(mtl_predictor):
  rng = np.random.default_rng(14)
  left, right = rng.uniform(0, 1, (2, 40, 36, 3)).astype(np.float32)
  resize = mtl_predictor.with_options(train_size=(32, 32), mode="resize")
  traces = mtl_predictor.traces
  out = resize(left, right)
  assert resize.traces == traces  # the same model at the same input shape: no recompilation
  # Reference: the network at the training size (32x32 needs no padding), outputs resized
  # back bilinearly by OpenCV, disparity scaled by the width ratio 36 / 32.
  small = mtl_predictor(resize_image(left, (32, 32)), resize_image(right, (32, 32)))
  back = lambda a: cv2.resize(a, (36, 40), interpolation=cv2.INTER_LINEAR)
  np.testing.assert_allclose(out["disparity"], back(small["disparity"]) * 36 / 32,
                             rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(out["patterns"], back(small["patterns"]), atol=1e-6)
  np.testing.assert_allclose(out["confidence"], back(small["confidence"]), atol=1e-6)


def test_detached_psmnet_predicts_the_twins_disparity(mtl_predictor):
  from sljax.nets import detach_sl
  plain = inference.make_predictor("psmnet", {"maxdisp": 16, "in_channels": 3},
                                   detach_sl(mtl_predictor.variables), mode="pad")
  assert not plain.is_sl
  rng = np.random.default_rng(13)
  left = rng.integers(0, 256, (30, 27, 3), dtype=np.uint8)
  right = rng.integers(0, 256, (30, 27, 3), dtype=np.uint8)
  out = plain(left, right)
  assert set(out) == {"disparity"}
  np.testing.assert_allclose(out["disparity"], mtl_predictor(left, right)["disparity"],
                             rtol=1e-5, atol=1e-5)


def test_psmnet_pad_mode_matches_reference_padding(mtl_predictor, monkeypatch):
  """Pad mode == the reference's protocol computed by hand: normalise with the ImageNet mean and
  std, zero-pad the normalised tensor at the top and right to a multiple of 16, run the model's
  layers on it (its own normalisation switched off) and crop."""
  import jax
  from sljax.nets import psmnet
  rng = np.random.default_rng(15)
  left = rng.integers(0, 256, (30, 27, 3), dtype=np.uint8)
  right = rng.integers(0, 256, (30, 27, 3), dtype=np.uint8)
  out = mtl_predictor(left, right)
  mean = np.array([0.485, 0.456, 0.406], np.float32)
  std = np.array([0.229, 0.224, 0.225], np.float32)
  norm = lambda im: (im.astype(np.float32) / np.float32(255) - mean) / std
  pad = lambda x: np.pad(x, ((2, 0), (0, 5), (0, 0)))[None]  # 30x27 -> 32x32
  monkeypatch.setattr(psmnet, "normalize_images", lambda x: x)
  model = mtl_predictor.model
  run = jax.jit(lambda v, a, b: model.apply(v, a, b, train=False))
  ref = run(mtl_predictor.variables, pad(norm(left)), pad(norm(right)))
  # Tolerances: two compilations of one float32 network (random weights) differ by ~1e-4.
  np.testing.assert_allclose(out["disparity"], np.asarray(ref["disparity"])[0, 2:, :27],
                             rtol=1e-4, atol=2e-4)
  p = 1.0 / (1.0 + np.exp(-np.asarray(ref["sl_logits"], np.float64)[0, 2:, :27]))
  np.testing.assert_allclose(out["patterns"], p, atol=5e-4)
  # The test tells the protocols apart: black padding of the image (the old rule) is far off.
  black = lambda im: norm(np.pad(im, ((2, 0), (0, 5), (0, 0))))[None]
  old = run(mtl_predictor.variables, black(left), black(right))
  assert np.abs(out["disparity"] - np.asarray(old["disparity"])[0, 2:, :27]).max() > 0.05


def test_unet_pad_mode_matches_reference_padding(unet_disp_vars):
  """UNets: pad the centred input (2x - 1) with 0 at the top and right to a multiple of 2^depth
  by hand, feed it through the inverse of the centring, run and crop."""
  import jax
  from sljax.nets import build_model
  pred = inference.make_predictor("unet-disp", UNET_KW, unet_disp_vars, mode="pad")
  assert pred.pad.multiple == 4 and pred.pad.fill == (0.5,)
  left, right = _pair(37, 45, seed=16)
  out = pred(left, right)["disparity"]
  centred = lambda im: 2.0 * im.astype(np.float64) - 1.0
  pad = lambda x: np.pad(x, ((3, 0), (0, 3)))[None, ..., None]  # 37x45 -> 40x48
  back = lambda z: ((z + 1.0) / 2.0).astype(np.float32)
  model = build_model("unet-disp", **UNET_KW)
  ref = jax.jit(lambda v, a, b: model.apply(v, a, b, train=False))(
      unet_disp_vars, back(pad(centred(left))), back(pad(centred(right))))
  np.testing.assert_allclose(out, np.asarray(ref["disparity"])[0, 3:, :45], rtol=1e-5, atol=1e-4)


def test_psmnet_mtl_export_round_trip(mtl_predictor, tmp_path):
  """The deployable file of the twin (pad mode) in a process that imports only jax and numpy."""
  from test_export import exported_outputs
  rng = np.random.default_rng(17)
  left = rng.uniform(0, 1, (2, 30, 27, 3)).astype(np.float32)
  right = rng.uniform(0, 1, (2, 30, 27, 3)).astype(np.float32)
  (out,), info = exported_outputs(tmp_path, mtl_predictor, (30, 27), [(left, right)])
  want = mtl_predictor(left, right)
  assert set(out) == set(want) == {"disparity", "patterns", "confidence"}
  np.testing.assert_allclose(out["disparity"], want["disparity"], rtol=1e-4, atol=2e-4)
  np.testing.assert_allclose(out["patterns"], want["patterns"], atol=5e-4)
  np.testing.assert_allclose(out["confidence"], want["confidence"], atol=5e-4)
  assert info["pad"]["multiple"] == 16 and info["pad"]["fill"] == pytest.approx([0.485, 0.456,
                                                                                   0.406])


def test_twin_in_two_programs_equals_one(mtl_predictor):
  """The memory-bounded path for large inputs (the twin as PSMNet + its SL path alone, two
  programs) gives the one-program outputs; large inputs choose it, small ones do not."""
  split = mtl_predictor.with_options(split_twin=True)
  rng = np.random.default_rng(18)
  left = rng.integers(0, 256, (2, 30, 27, 3), dtype=np.uint8)
  right = rng.integers(0, 256, (2, 30, 27, 3), dtype=np.uint8)
  one, two = mtl_predictor(left, right), split(left, right)
  assert set(one) == set(two) == {"disparity", "patterns", "confidence"}
  for k in one:
    np.testing.assert_allclose(two[k], one[k], rtol=1e-5, atol=1e-5)
  big = ModelConfig.of("psmnet-mtl", maxdisp=192, t=9)
  assert inference.twin_split_needed(big, (1, 1024, 1280, 3))
  assert not inference.twin_split_needed(big, (1, 256, 320, 3))
  assert not inference.twin_split_needed(ModelConfig.of("psmnet", maxdisp=192),
                                         (1, 1024, 1280, 3))
