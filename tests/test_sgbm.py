import cv2
import numpy as np
import pytest

from sljax.data.camera import Calib
from sljax.errors import SljaxError
from sljax.evaluation import metrics
from sljax.inference.sgbm import SGBMConfig, SGBMPredictor, round_up_16


def textured_pair(h=64, w=96, seed=0, d_back=8, d_front=16):
  """A background plane at d_back and a square at d_front, random texture, exact occlusions."""
  rng = np.random.default_rng(seed)
  back = cv2.GaussianBlur(rng.uniform(0, 1, (h, w + 32)).astype(np.float32), (0, 0), 1.0)
  front = cv2.GaussianBlur(rng.uniform(0, 1, (h, w + 32)).astype(np.float32), (0, 0), 1.0)
  ys, xs = np.mgrid[0:h, 0:w]
  inside = lambda x: (ys >= h // 4) & (ys < 3 * h // 4) & (x >= 40) & (x < 72)
  left = np.where(inside(xs), front[ys, xs], back[ys, xs])
  # The right pixel x' sees the square where x' + d_front lies in it, else background x' + d_back.
  right = np.where(inside(xs + d_front), front[ys, xs + d_front], back[ys, xs + d_back])
  gt = np.where(inside(xs), float(d_front), float(d_back)).astype(np.float32)
  return left.astype(np.float32), right.astype(np.float32), gt


def _calib(ndisp):
  k = np.array([[100.0, 0, 48], [0, 100.0, 32], [0, 0, 1]])
  return Calib(cam0=k, cam1=k, doffs=0.0, baseline=10.0, width=96, height=64, ndisp=ndisp)


def test_round_up_16():
  assert [round_up_16(n) for n in (1, 16, 17, 70, 256)] == [16, 16, 32, 80, 256]


def test_num_disparities_sources():
  p = SGBMPredictor()
  assert p.num_disparities(96, _calib(70)) == 80
  assert p.num_disparities(200, None) == 64  # 25% of 200 = 50 -> 64
  assert SGBMPredictor(SGBMConfig(num_disparities=20)).num_disparities(96, _calib(70)) == 32


def test_sgbm_beats_constant_prediction():
  left, right, gt = textured_pair()
  out = SGBMPredictor()(left, right, calib=_calib(30))
  d = out["disparity"]
  assert d.shape == gt.shape and d.dtype == np.float32
  m = metrics.disparity_metrics(d, gt)
  const = metrics.disparity_metrics(np.full_like(gt, np.median(gt)), gt)
  assert np.isfinite(m["mae"]) and m["invalid_pred"] < 20
  assert m["mae"] < const["mae"] and m["bad_2"] < const["bad_2"]
  # Away from borders and occlusions SGBM recovers both planes.
  assert np.median(np.abs(d[20:44, 50:70] - 16)) < 0.5
  assert np.median(np.abs(d[5:12, 20:36] - 8)) < 0.5


def test_matches_direct_opencv_call_without_padding():
  left, right, _ = textured_pair(seed=1)
  out = SGBMPredictor(SGBMConfig(pad_left=False))(left, right, calib=_calib(30))["disparity"]
  l8 = np.round(left * 255).astype(np.uint8)
  r8 = np.round(right * 255).astype(np.uint8)
  sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=32, blockSize=5, P1=8 * 25,
                               P2=32 * 25, disp12MaxDiff=1, preFilterCap=63, uniquenessRatio=10,
                               speckleWindowSize=100, speckleRange=2,
                               mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
  raw = sgbm.compute(l8, r8).astype(np.float64)
  want = np.where(raw < 0, np.inf, raw / 16.0)
  np.testing.assert_array_equal(out, want.astype(np.float32))
  assert np.isinf(out[:, :32]).all()  # SGBM cannot match the leftmost numDisparities columns


def test_batched_and_rgb_and_uint8():
  left, right, _ = textured_pair(seed=2)
  single = SGBMPredictor()(left, right)["disparity"]
  batch = SGBMPredictor()(np.stack([left[..., None]] * 2), np.stack([right[..., None]] * 2))
  np.testing.assert_array_equal(batch["disparity"][1], single)
  rgb = SGBMPredictor()(np.round(np.repeat(left[..., None], 3, 2) * 255).astype(np.uint8),
                        np.round(np.repeat(right[..., None], 3, 2) * 255).astype(np.uint8))
  assert rgb["disparity"].shape == left.shape


def test_bad_inputs():
  left, right, _ = textured_pair()
  with pytest.raises(SljaxError, match="differ in size"):
    SGBMPredictor()(left, right[:, :90])
  with pytest.raises(SljaxError, match="positive"):
    SGBMPredictor(SGBMConfig(num_disparities=0))


def test_sgbm_row_on_synthetic_scenes_beats_constant_disparity(tmp_path):
  """Through `sljax evaluate sgbm` on rendered object scenes.

  The objects get full texture: the default virtual domain is nearly textureless (like the
  paper's), where block matching has nothing to match and a constant can do as well.
  """
  import json

  from sljax import cli
  from sljax.data.scene import write_scene
  from sljax.render.synthetic import SynthConfig, render_scene

  cfg = SynthConfig(size=96, domain="objects", texture_amplitude=1.0)
  scenes = [render_scene(i, 0, cfg) for i in range(3)]
  for i, s in enumerate(scenes):
    write_scene(tmp_path / "syn" / f"s{i}", s)
  rc = cli.main(["evaluate", "sgbm", str(tmp_path / "syn"), "--out", str(tmp_path / "out")])
  assert rc == 0
  full = json.loads((tmp_path / "out" / "metrics.json").read_text())["pooled"]["full"]
  gts = [s.disp0 for s in scenes]
  median = float(np.median(np.concatenate([g[np.isfinite(g)] for g in gts])))
  const = metrics.pooled_disparity_metrics([np.full_like(g, median) for g in gts], gts)
  assert np.isfinite(full["mae"]) and np.isfinite(full["depth_mae_mm"])
  assert full["mae"] < const["mae"] and full["bad_2"] < const["bad_2"]
