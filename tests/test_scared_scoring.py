"""SCARED scoring (sljax.capture.scared through sljax evaluate) over several keyframes, one
excluded for coverage: the hand-computed mean.

The toolkit's rule (sljax.capture.scared): a keyframe whose ground truth covers under 10% of its
pixels is excluded; the others are scored by the mean absolute depth error over the pixels
both maps know, and the dataset's number is the mean over the scored keyframes (not over
their pooled pixels). The keyframes here are imported-style scene folders whose original
view is the rectified one (R1 = I, no distortion, M1 = cam0 with fx != fy and doffs != 0),
so a constant disparity d maps to the depth fx B / (d + doffs) at every pixel.
"""

import numpy as np
import pytest

from sljax.capture import scared
from sljax.data.camera import Calib
from sljax.data.dataset import FolderSource
from sljax.data.pfm import write_pfm
from sljax.data.scene import Scene, write_scene
from sljax.evaluation.scoring import evaluate

H, W = 20, 30
FX, FY, CX, CY, BASELINE, DOFFS = 80.0, 92.0, 14.5, 9.5, 50.0, 2.0
DISP = 8.0
PRED_DEPTH = FX * BASELINE / (DISP + DOFFS)  # 400 mm


def _keyframe(root, name, gt):
  cam = np.array([[FX, 0, CX], [0, FY, CY], [0, 0, 1]])
  calib = Calib(cam0=cam, cam1=cam + np.array([[0, 0, DOFFS], [0, 0, 0], [0, 0, 0]]),
                doffs=DOFFS, baseline=BASELINE, width=W, height=H, ndisp=16)
  meta = {"source": "SCARED", "group": name,
          "original": {"M1": cam.tolist(), "D1": [0.0] * 5, "R1": np.eye(3).tolist(),
                       "width": W, "height": H}}
  gray = np.full((H, W, 1), 0.5, np.float32)
  write_scene(root / name, Scene(name=name, im0=gray, im1=gray,
                                 disp0=np.full((H, W), DISP, np.float32), calib=calib, meta=meta))
  write_pfm(root / name / scared.ORIGINAL_DEPTH, gt.astype(np.float32))


def _gt(depths):
  """Ground truth known on the first len(depths) interior pixels (row-major), inf elsewhere."""
  gt = np.full((H, W), np.inf)
  inner = gt[2:-2, 2:-2].reshape(-1)  # away from the border, where remap reads outside
  inner[:len(depths)] = depths
  gt[2:-2, 2:-2] = inner.reshape(H - 4, W - 4)
  return gt


class Fixed:
  """A predictor of the constant disparity DISP."""
  model_name, mode, is_sl = "fixed", "full", False

  def describe(self):
    return "constant disparity"

  def __call__(self, left, right, calib=None):
    return {"disparity": np.full(left.shape[:2], DISP, np.float32)}


@pytest.fixture(scope="module")
def report(tmp_path_factory):
  root = tmp_path_factory.mktemp("scared")
  n = H * W
  # a: 30% coverage, error 10 mm everywhere. b: 9% (< 10%): excluded, though its error
  # (300 mm) would dominate. c: 15%, errors 20 and 30 mm on equal halves -> 25 mm.
  _keyframe(root, "a", _gt([PRED_DEPTH - 10.0] * int(0.30 * n)))
  _keyframe(root, "b", _gt([PRED_DEPTH + 300.0] * int(0.09 * n)))
  half = int(0.15 * n) // 2
  _keyframe(root, "c", _gt([PRED_DEPTH + 20.0] * half + [PRED_DEPTH - 30.0] * half))
  out = root.parent / "eval"
  rep = evaluate(Fixed(), FolderSource(root), out_dir=out, progress=False)
  rep["_md"] = (out / "metrics.md").read_text()
  return rep


def test_each_keyframe_scored_or_excluded(report):
  rows = {r["scene"]: r["scared"] for r in report["per_scene"]}
  assert set(rows) == {"a", "b", "c"}
  assert rows["a"]["depth_mae_mm"] == pytest.approx(10.0, abs=1e-3)
  assert rows["a"]["coverage"] == pytest.approx(0.30) and not rows["a"]["excluded"]
  assert rows["a"]["assessed"] == pytest.approx(0.30)
  assert rows["b"]["excluded"] and np.isnan(rows["b"]["depth_mae_mm"])
  assert rows["b"]["coverage"] == pytest.approx(0.09) and rows["b"]["assessed"] == 0.0
  assert rows["c"]["depth_mae_mm"] == pytest.approx(25.0, abs=1e-3)


def test_pooled_is_the_mean_over_scored_keyframes(report):
  pooled = report["pooled"]["scared"]
  assert pooled["keyframes"] == 2 and pooled["excluded"] == 1
  # (10 + 25) / 2; pooling the pixels instead would give (0.30 * 10 + 0.15 * 25) / 0.45 = 15.
  assert pooled["depth_mae_mm"] == pytest.approx(17.5, abs=1e-3)


def test_metrics_md_names_the_exclusion(report):
  text = report["_md"]
  assert "SCARED (scared_toolkit rules, original frame)" in text
  assert "excluded" in text and "17.5" in text
