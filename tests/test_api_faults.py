"""The imported API on bad input: one SljaxError naming the argument and the problem (before
anything compiles), never a traceback from inside numpy or JAX, and nothing written by halves."""

import resource
import signal

import flax.linen as nn
import jax.numpy as jnp
import numpy as np
import pytest

from sljax import inference, sl
from sljax.corr import correlation
from sljax.data.camera import Calib, depth_from_disparity
from sljax.data.dataset import FolderSource
from sljax.data.dataset import iterate_batches
from sljax.data.scene import Scene, load_scene, write_scene
from sljax.depth import geometry
from sljax.errors import SljaxError
from sljax.evaluation.metrics import DisparityAccumulator
from sljax.nets import ModelConfig
from sljax.render import synthetic
from sljax.sl import codes
from toys import registered, toy_spec


class ToyDisp(nn.Module):
  """disparity = first channel of the left view (never compiled by these tests)."""
  in_channels: int = 1
  conv_impl: str | None = None

  @nn.compact
  def __call__(self, left, right, train=False):
    bias = self.param("bias", nn.initializers.zeros, (1,))
    return {"disparity": left[..., 0] + bias[0]}


def _toy(**kw):
  variables = {"params": {"bias": jnp.zeros((1,), jnp.float32)}}
  with registered(toy_spec("toy", ToyDisp)):
    return inference.Predictor(ModelConfig.of("toy"), variables,
                               inference.PredictOptions(mode="pad", **kw))


# ---- sljax.inference -------------------------------------------------------------------------


@pytest.mark.parametrize("checkpoint", [None, 5, ""])
def test_load_names_a_checkpoint_that_is_not_a_path(checkpoint):
  with pytest.raises(SljaxError, match="checkpoint must be a folder path"):
    inference.load(checkpoint)


def test_load_refuses_kernels_that_are_not_a_choice_before_reading_the_checkpoint():
  with pytest.raises(SljaxError, match="kernels must be a sljax.runtime.choices.KernelChoice"):
    inference.load("/nonexistent/run", kernels="fast")
  with pytest.raises(SljaxError, match="tune_kernels must be True, False or None"):
    inference.load("/nonexistent/run", tune_kernels="no")
  with pytest.raises(SljaxError, match="kernels must be a sljax.runtime.choices.KernelChoice"):
    _toy(kernels="fast")  # else an AttributeError at the first prediction


def test_load_refuses_maxdisp_true(monkeypatch):
  monkeypatch.setattr(inference.predictor, "load_for_inference",
                      lambda path: ("psmnet", {"maxdisp": 16}, {}, {}))
  with pytest.raises(SljaxError, match="maxdisp must be a positive integer, got True"):
    inference.load("run", maxdisp=True)


def test_a_model_too_large_to_build_is_not_called_a_checkpoint_mismatch(monkeypatch):
  def out_of_memory(*args):
    raise MemoryError("Unable to allocate 1.82 TiB")
  monkeypatch.setattr(inference.PROGRAMS, "variable_shapes", out_of_memory)
  with pytest.raises(SljaxError, match="cannot build the model .* out of memory") as e:
    _toy()
  assert "do not match" not in str(e.value)


@pytest.mark.parametrize("left", ["im0.png", None, [[0.1, 0.2], [0.3]]])
def test_predict_names_an_input_that_is_not_an_image_array(left):
  with pytest.raises(SljaxError, match="left view: expected an image array .* got (str|NoneType"
                                        "|list)"):
    _toy()(left, np.zeros((4, 4), np.float32))


# ---- sljax.depth.geometry --------------------------------------------------------------------------


def _calib(f=100.0, fy=None, baseline=10.0, width=8, height=6):
  cam = np.array([[f, 0, 4], [0, f if fy is None else fy, 3], [0, 0, 1]], np.float64)
  return Calib(cam0=cam, cam1=cam.copy(), doffs=0.0, baseline=baseline, width=width,
               height=height, ndisp=8)


DISP = np.full((6, 8), 4.0, np.float32)


@pytest.mark.parametrize("kw", [dict(f=0.0), dict(f=-100.0), dict(baseline=-10.0),
                                dict(baseline=float("nan"))])
def test_depth_refuses_a_calibration_without_positive_focal_length_and_baseline(kw):
  with pytest.raises(SljaxError, match="depth: calibration needs a positive focal length"):
    geometry.depth_mm(DISP, _calib(**kw))


def test_point_cloud_refuses_zero_fy():
  with pytest.raises(SljaxError, match=r"point cloud: .*fy = 0"):
    geometry.point_cloud(DISP, _calib(fy=0.0))


def test_depth_refuses_no_calibration_and_a_calibration_of_another_size():
  with pytest.raises(SljaxError, match=r"calib must be a sljax.data.camera.Calib .*got NoneType"):
    geometry.depth_mm(DISP, None)
  with pytest.raises(SljaxError, match="calibration is for 8x6 images, the pair is 4x3"):
    geometry.point_cloud(DISP[:3, :4], _calib())


def test_point_cloud_scales_8_bit_colours_and_refuses_two_channels():
  image = np.full((6, 8, 3), 100, np.uint8)
  _, rgb = geometry.point_cloud(DISP, _calib(), image)
  np.testing.assert_array_equal(rgb, 100)  # was 255: the uint8 values clipped to [0, 1]
  with pytest.raises(SljaxError, match="image must be HxW, HxWx1, HxWx3 or HxWx4"):
    geometry.point_cloud(DISP, _calib(), np.zeros((6, 8, 2), np.float32))


def test_write_ply_refuses_bad_shapes_and_float_colours(tmp_path):
  with pytest.raises(SljaxError, match=r"xyz must be Nx3, got shape \(4, 2\)"):
    geometry.write_ply(tmp_path / "a.ply", np.zeros((4, 2)), np.zeros((2, 3), np.uint8))
  with pytest.raises(SljaxError, match="rgb must hold integers 0..255"):
    geometry.write_ply(tmp_path / "a.ply", np.zeros((2, 3)), np.full((2, 3), 0.5))
  assert not (tmp_path / "a.ply").exists()


def test_write_ply_on_a_full_disk_keeps_the_earlier_file(tmp_path):
  path = tmp_path / "cloud.ply"
  geometry.write_ply(path, np.zeros((1, 3)), np.zeros((1, 3), np.uint8))
  before = path.read_bytes()
  old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
  soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
  resource.setrlimit(resource.RLIMIT_FSIZE, (4096, hard))  # writes past 4 KiB fail (EFBIG)
  try:
    with pytest.raises(OSError):
      geometry.write_ply(path, np.zeros((1000, 3)), np.zeros((1000, 3), np.uint8))
  finally:
    resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    signal.signal(signal.SIGXFSZ, old_handler)
  assert path.read_bytes() == before
  assert [p.name for p in tmp_path.iterdir()] == ["cloud.ply"]  # no temporary left


# ---- sljax.corr ------------------------------------------------------------------------------


P = np.ones((6, 8, 2), np.float32)


@pytest.mark.parametrize("bad", ["abc", [[1.0, 2.0], [3.0]], P.astype(complex)])
def test_sl_disparity_names_inputs_that_are_not_real_arrays(bad):
  with pytest.raises(SljaxError, match="sl_disparity: p_left must be a real-valued array"):
    correlation.sl_disparity(bad, P)


@pytest.mark.parametrize("normalized", [False, True])
@pytest.mark.parametrize("shape", [(0, 8, 2), (6, 8, 0)])
def test_cost_volume_refuses_an_empty_input(shape, normalized):
  p = np.ones(shape, np.float32)
  with pytest.raises(SljaxError, match="cost_volume: empty input of shape"):
    correlation.cost_volume(p, p, 2, 3, normalized=normalized)


def test_choose_block_and_default_max_disp_refuse_empty_sizes():
  with pytest.raises(SljaxError, match="choose_block: batch must be a positive integer, got 0"):
    correlation.choose_block(0, 8, 8, 4)
  with pytest.raises(SljaxError, match="image width must be >= 1, got -4"):
    correlation.default_max_disp(-4)


# ---- sljax.sl --------------------------------------------------------------------------------


def test_sl_decode_is_the_code_function_not_the_submodule():
  assert sl.decode is codes.decode
  assert sl.decode(np.array([[1, 0, 1]]), "binary")[0] == 5


@pytest.mark.parametrize("t", [40, 2.5])
def test_encode_refuses_more_patterns_than_int32_bits(t):
  with pytest.raises(SljaxError, match="number of patterns t must be an integer in 1..31"):
    sl.encode(np.arange(4), "binary", t)


def _raw(white=0.8, black=0.1, dtype=np.float32):
  w, b = np.full((2, 3), white, dtype), np.full((2, 3), black, dtype)
  return {"white": w, "black": b, "p000": w.copy(), "p001": b.copy()}


def test_decode_captures_refuses_bad_t_and_a_list():
  with pytest.raises(SljaxError, match="number of patterns t must be a positive integer, got 0"):
    sl.decode_captures(_raw(), "binary", t=0)
  with pytest.raises(SljaxError, match="raw captures must be a dict of HxW images"):
    sl.decode_captures(list(_raw().values()), "binary")


def test_decode_captures_reads_a_nan_capture_pixel_as_unknown():
  raw = _raw()
  raw["p001"][0, 0] = np.nan
  dec = sl.decode_captures(raw, "binary")
  assert np.isnan(dec.bits[0, 0, 1]) and np.isnan(dec.column[0, 0])
  assert dec.column[1, 1] == 2


def test_decode_captures_scales_8_bit_captures_and_refuses_unscaled_floats():
  dec = sl.decode_captures(_raw(12, 10, np.uint8), "binary")
  assert dec.shadow.all()  # 2 grey levels of contrast: below the 10-level shadow threshold
  with pytest.raises(SljaxError, match="capture 'white' must be scaled to"):
    sl.decode_captures(_raw(200.0, 20.0), "binary")


# ---- sljax.render.synthetic --------------------------------------------------------------------


@pytest.mark.parametrize("kw, message", [
    (dict(size=64.5), "size must be an integer >= 16"),
    (dict(t=8.5), "t must be an integer in 1..12"),
    (dict(views_per_object=2.5), "views_per_object must be an integer >= 1"),
    (dict(focal_factor=0.0), "focal_factor must be a positive number"),
    (dict(baseline_m=-0.01), "baseline_m must be a positive number"),
    (dict(projector_fov_deg=180.0), r"projector_fov_deg must be in \(0, 180\)"),
    (dict(num_ellipsoids=0), "num_ellipsoids must be an integer >= 1"),
    (dict(max_disparity_fraction=0.0), r"max_disparity_fraction must be in \(0, 1\]"),
    (dict(projector_translation_m=(0.1, 0.0)), "projector_translation_m must be 3 finite"),
    (dict(object_size_m=(0.1, 0.03)), "object_size_m must be .* 0 < min <= max"),
    (dict(image_noise=-0.1), "image_noise must be a finite number >= 0"),
])
def test_synth_config_names_a_bad_field(kw, message):
  with pytest.raises(SljaxError, match=message):
    synthetic.SynthConfig(**kw).resolved()


def test_synthetic_seed_outside_uint32_and_a_dict_config_are_refused():
  with pytest.raises(SljaxError, match="seed must be an integer in 0..2"):
    synthetic.SyntheticSource(2, seed=-1)
  with pytest.raises(SljaxError, match="seed must be an integer in 0..2"):
    synthetic.render_scene(0, 2**40, synthetic.SynthConfig(size=16))
  with pytest.raises(SljaxError, match="config must be a SynthConfig, got dict"):
    synthetic.render_scene(0, 0, {"size": 16})


# ---- sljax.data.scene: write_scene, one check before the first file ------------------------


def _scene(**kw):
  rng = np.random.default_rng(0)
  parts = {"name": "s", "im0": rng.random((8, 10, 3)).astype(np.float32),
           "im1": rng.random((8, 10, 3)).astype(np.float32)}
  return Scene(**{**parts, **kw})


def test_write_scene_scales_8_and_16_bit_views(tmp_path):
  """A uint8 view used to be read as floats and clipped to [0, 1]: a white image."""
  rng = np.random.default_rng(1)
  im8 = rng.integers(0, 256, (8, 10, 3), dtype=np.uint8)
  im16 = rng.integers(0, 65536, (8, 10), dtype=np.uint16)
  write_scene(tmp_path / "a", _scene(im0=im8, im1=im8))
  np.testing.assert_array_equal(load_scene(tmp_path / "a").im0, im8 / np.float32(255))
  write_scene(tmp_path / "b", _scene(im0=im16, im1=im16), bit_depth=16)
  np.testing.assert_array_equal(load_scene(tmp_path / "b").im0[..., 0], im16 / np.float32(65535))


CALIB = Calib(cam0=np.eye(3), cam1=np.eye(3), doffs=0.0, baseline=10.0, width=10, height=8,
              ndisp=4)


@pytest.mark.parametrize("kw, file, message", [
    ({"im0": np.full((8, 10, 3), 200.0, np.float32)}, "im0.png",
     r"must be scaled to \[0, 1\], got values in \[200, 200\]"),
    ({"im1": np.full((8, 10, 3), np.nan, np.float32)}, "im1.png", "holds NaN or infinite values"),
    ({"im0": None}, "im0", "must be an HxW or HxWxC image, got NoneType"),
    ({"raw0": {"white": np.full((8, 10), np.nan, np.float32)}}, "raw0/white.png", "NaN"),
    ({"meta": {"group": object()}}, "meta.json", "cannot be written: cannot store object"),
    ({"calib": Calib(cam0=np.eye(2), cam1=np.eye(3), doffs=0.0, baseline=1.0, width=10,
                     height=8, ndisp=4)}, "calib.txt", "cam0 and cam1 must be 3x3"),
])
def test_write_scene_refuses_bad_parts_before_writing_anything(tmp_path, kw, file, message):
  """Checked before the first file: a bad meta or calib used to leave the views written."""
  with pytest.raises(SljaxError, match=message) as e:
    write_scene(tmp_path / "s", _scene(**{"disp0": np.ones((8, 10), np.float32),
                                          "calib": CALIB, **kw}))
  assert file in str(e.value) and str(tmp_path / "s") in str(e.value)
  assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("baseline", [0.0, -10.0, float("nan")])
def test_depth_from_disparity_and_depth_metrics_refuse_a_bad_baseline(baseline):
  """Both used to return zero or negative depths, and the depth metrics averaged them."""
  bad = Calib(cam0=np.eye(3) * 100, cam1=np.eye(3) * 100, doffs=0.0, baseline=baseline,
              width=10, height=8, ndisp=4)
  with pytest.raises(SljaxError, match="depth: calibration needs a positive focal length"):
    depth_from_disparity(np.ones((8, 10)), bad)
  with pytest.raises(SljaxError, match="scene s7: depth metrics: calibration needs"):
    DisparityAccumulator().add(np.ones((8, 10)), np.ones((8, 10)), calib=bad, name="scene s7")


# ---- sljax.data: sources and batches ---------------------------------------------------------


@pytest.mark.parametrize("root", [None, ["a"], "", 3])
def test_folder_source_names_a_root_that_is_not_a_path(root):
  """Used to be a TypeError from pathlib ('' was the current folder)."""
  with pytest.raises(SljaxError, match="dataset folder must be a folder path"):
    FolderSource(root)


@pytest.mark.parametrize("indices, message", [
    ([0, 9], "scene index 9 is out of range for 3 scenes"),
    ([0, 1.5], "scene indices must be integers, got 1.5"),
    (["0"], "scene indices must be integers, got '0'"),
])
def test_iterate_batches_checks_the_indices_before_loading(indices, message):
  """A bad index used to fail inside the loader, after earlier batches were yielded."""
  source = synthetic.SyntheticSource(3, seed=0, config=synthetic.SynthConfig(size=16))
  with pytest.raises(SljaxError, match=message):
    next(iterate_batches(source, indices, 1, seed=0, epoch=0, shuffle=False))


