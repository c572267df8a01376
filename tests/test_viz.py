import cv2
import numpy as np

from sljax import viz


def test_save_panels_writes_png_of_expected_layout(tmp_path):
  rng = np.random.default_rng(0)
  disp = rng.uniform(0, 10, (32, 40)).astype(np.float32)
  disp[:4] = np.inf
  panels = [viz.Panel("left", rng.uniform(size=(32, 40, 3))),
            viz.Panel("gray", rng.uniform(size=(32, 40, 1))),
            viz.Panel("disparity", disp, cmap="turbo", label="px")]
  out = tmp_path / "sub" / "fig.png"
  viz.save_panels(out, panels, ncols=2, title="t")
  img = cv2.imread(str(out))
  assert img is not None and img.shape[0] > 100 and img.shape[1] > 100
  # Two columns, two rows: wider than a single tile and not blank.
  assert img.std() > 10
