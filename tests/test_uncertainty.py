"""sljax.corr.uncertainty and the `sljax uncertainty` command."""

import json

import numpy as np
import pytest

from sljax import cli
from sljax.corr import uncertainty as unc
from sljax.corr.correlation import sl_disparity
from sljax.data.scene import Scene, write_scene
from sljax.errors import SljaxError


def test_view_uncertainty_hand_computed():
  p = np.array([[[0.0, 1.0, 0.5, 0.25], [0.9, np.nan, np.nan, 0.1]]], np.float32)  # 1x2x4
  u = unc.view_uncertainty(p)
  np.testing.assert_allclose(u, [[(0 + 0 + 1 + 0.5) / 4, (0.2 + 0.2) / 2]], atol=1e-6)
  assert np.isnan(unc.view_uncertainty(np.full((1, 1, 3), np.nan)))[0, 0]
  both = unc.pattern_uncertainty(p, np.full_like(p, 0.5))
  np.testing.assert_allclose(both, 0.5 * (u + 1.0), atol=1e-6)
  with pytest.raises(SljaxError, match="HxWxt"):
    unc.view_uncertainty(np.zeros((3, 3)))


def test_spearman_averages_ties_hand_computed():
  # ranks x: 0, 1.5, 1.5, 3; y: 0, 2, 1, 3 -> r = 4.5 / sqrt(4.5 * 5)
  out = unc.analyse_uncertainty(np.array([1.0, 2, 2, 3]), np.array([1.0, 3, 2, 4]))
  assert out["n"] == 4
  assert out["spearman"] == pytest.approx(4.5 / np.sqrt(22.5), abs=1e-12)


def test_error_driven_by_uncertainty_correlates():
  rng = np.random.default_rng(0)
  u = rng.random((100, 120))
  error = 3.0 * u ** 2 + 0.2 * rng.random((100, 120))
  valid = rng.random((100, 120)) > 0.1
  error[~valid] = np.inf  # invalid pixels are excluded whatever they hold
  out = unc.analyse_uncertainty(u, error, valid)
  uu, ee = u[valid], error[valid]
  assert out["n"] == valid.sum()
  assert out["pearson"] == pytest.approx(np.corrcoef(uu, ee)[0, 1], abs=1e-9)
  slope, intercept = np.polyfit(uu, ee, 1)
  assert out["slope"] == pytest.approx(slope, rel=1e-9)
  assert out["intercept"] == pytest.approx(intercept, abs=1e-9)
  assert out["pearson"] > 0.9 and out["spearman"] > 0.95  # monotone: spearman near 1


def test_independent_error_does_not_correlate():
  rng = np.random.default_rng(1)
  out = unc.analyse_uncertainty(rng.random(40000), rng.exponential(size=40000))
  assert abs(out["pearson"]) < 0.03 and abs(out["spearman"]) < 0.03


def test_constant_input_gives_nan_not_crash():
  out = unc.analyse_uncertainty(np.ones(10), np.arange(10.0))
  assert np.isnan(out["pearson"]) and np.isnan(out["slope"]) and out["n"] == 10


def test_plots_write_pngs(tmp_path):
  rng = np.random.default_rng(2)
  u = rng.random((20, 30))
  e = u + 0.1 * rng.random((20, 30))
  stats = unc.plot_uncertainty_histogram(tmp_path / "h.png", u, e)
  assert stats["pearson"] > 0.9
  unc.plot_uncertainty_maps(tmp_path / "m.png", e, u, u)
  for name in ("h.png", "m.png"):
    assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _scene_and_pred(tmp_path, with_disparity):
  """A 12x24 scene with uniform disparity 2 whose right patterns are the left ones shifted."""
  rng = np.random.default_rng(3)
  h, w, t, d = 12, 24, 8, 2
  bits = (rng.random((h, w + d, t)) < 0.5).astype(np.float32)
  p_left = bits[:, d:]  # left x reads column x + d of the projector strip
  p_right = bits[:, :w]  # right x - d reads the same column
  # soften: uncertain (near 0.5) predictions on the right half
  p_left = np.where(np.arange(w)[None, :, None] < w // 2, 0.05 + 0.9 * p_left,
                    0.4 + 0.2 * p_left).astype(np.float32)
  p_right = (0.05 + 0.9 * p_right).astype(np.float32)
  disp0 = np.full((h, w), float(d), np.float32)
  disp0[:, :d] = np.inf
  im = np.zeros((h, w, 1), np.float32)
  write_scene(tmp_path / "scene", Scene(name="scene", im0=im, im1=im, disp0=disp0))
  arrays = {"p_left": p_left, "p_right": p_right}
  if with_disparity:
    arrays["disparity"] = np.where(np.arange(w)[None, :] < w // 2, 2.0, 5.0) * np.ones((h, 1))
  np.savez(tmp_path / "pred.npz", **arrays)
  return tmp_path / "pred.npz", tmp_path / "scene"


@pytest.mark.parametrize("with_disparity", [True, False])
def test_cli_writes_metrics_and_pictures(tmp_path, capsys, with_disparity):
  pred, scene = _scene_and_pred(tmp_path, with_disparity)
  out = tmp_path / "out"
  argv = ["uncertainty", "--pred", str(pred), "--gt", str(scene), "--out", str(out),
          "--window", "3", "--max-disp", "4"]
  assert cli.main(argv) == 0
  metrics = json.loads((out / "metrics.json").read_text())
  assert metrics["n"] == 12 * 22
  assert metrics["disparity_source"] == ("npz" if with_disparity else "correlation")
  if with_disparity:  # the uncertain half is exactly the wrong half
    assert metrics["pearson"] > 0.9 and metrics["mae"] == pytest.approx(3 * 12 / 22)
  else:  # the command passes --window and --max-disp on and scores where disp0 is known
    with np.load(pred) as z:
      disp, _ = sl_disparity(z["p_left"], z["p_right"], 4, 3)
    assert metrics["mae"] == pytest.approx(float(np.abs(disp[:, 2:] - 2.0).mean()))
  for name in ("uncertainty_hist.png", "uncertainty_maps.png"):
    assert (out / name).stat().st_size > 1000
  assert "pearson" in capsys.readouterr().out


def test_cli_bad_prediction_file_is_one_line_error(tmp_path, capsys):
  _, scene = _scene_and_pred(tmp_path, True)
  np.savez(tmp_path / "bad.npz", p_left=np.zeros((12, 24, 8)))
  argv = ["uncertainty", "--pred", str(tmp_path / "bad.npz"), "--gt", str(scene), "--out",
          str(tmp_path / "o")]
  assert cli.main(argv) == 2
  err = capsys.readouterr().err
  assert "p_right" in err and "bad.npz" in err


@pytest.mark.parametrize("key, scale, shift, why", [
    ("p_left", 10.0, -5.0, "got values in [-4.5, 4.5] (logits? apply a sigmoid first)"),
    ("p_right", 255.0, 0.0, "got values in [12.75, 242.25] (8-bit values? divide by 255 first)"),
])
def test_cli_probabilities_outside_unit_range_are_one_line_error(tmp_path, capsys, key, scale,
                                                                  shift, why):
  # Logits or 0..255 pixels were analysed as probabilities: uncertainties below 0, no error.
  pred, scene = _scene_and_pred(tmp_path, True)
  with np.load(pred) as z:
    arrays = dict(z)
  arrays[key] = arrays[key] * scale + shift
  arrays["p_left"][0, 0, 0] = np.nan  # an unknown pattern pixel stays allowed
  np.savez(tmp_path / "scaled.npz", **arrays)
  out = tmp_path / "o"
  argv = ["uncertainty", "--pred", str(tmp_path / "scaled.npz"), "--gt", str(scene), "--out",
          str(out)]
  assert cli.main(argv) == 2
  err = capsys.readouterr().err
  assert err == (f"sljax uncertainty: error: {tmp_path / 'scaled.npz'}: '{key}' must hold "
                 f"probabilities in [0, 1], {why}\n"), err
  assert not out.exists()


@pytest.mark.parametrize("flag, value", [("--window", "4"), ("--search-range", "-1")])
def test_cli_bad_option_is_one_line_error(tmp_path, capsys, flag, value):
  pred, scene = _scene_and_pred(tmp_path, False)
  argv = ["uncertainty", "--pred", str(pred), "--gt", str(scene), "--out", str(tmp_path / "o"),
          flag, value]
  assert cli.main(argv) == 2
  err = capsys.readouterr().err
  assert flag in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("content, why", [
    (b"", "empty file (0 bytes)"),  # numpy: EOFError
    ("npy", "a single .npy array"),  # numpy: an ndarray, then a TypeError
    (b"p_left p_right\n1 2 3\n", "not a zip archive"),  # numpy: "pickled data" ValueError
    ("truncated", "damaged or truncated: BadZipFile"),
])
def test_cli_unreadable_prediction_file_is_one_line_error(tmp_path, capsys, content, why):
  pred, scene = _scene_and_pred(tmp_path, True)
  bad = tmp_path / "bad.npz"
  if content == "npy":
    np.save(bad.with_suffix(".npy"), np.zeros((12, 24, 8)))
    bad = bad.with_suffix(".npy")
  elif content == "truncated":
    bad.write_bytes(pred.read_bytes()[:len(pred.read_bytes()) // 2])
  else:
    bad.write_bytes(content)
  argv = ["uncertainty", "--pred", str(bad), "--gt", str(scene), "--out", str(tmp_path / "o")]
  assert cli.main(argv) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and err[0].startswith(
      f"sljax uncertainty: error: {bad}: not an .npz archive of predictions ({why}"), err
  assert not (tmp_path / "o").exists()


def test_cli_existing_outputs_need_overwrite(tmp_path, capsys):
  """metrics.json and the pictures in an existing --out are replaced only with --overwrite;
  the refusal comes before the predictions are read."""
  pred, scene = _scene_and_pred(tmp_path, True)
  out = tmp_path / "out"
  out.mkdir()
  (out / "notes.txt").write_text("mine")
  argv = ["uncertainty", "--pred", str(pred), "--gt", str(scene), "--out", str(out)]
  assert cli.main(argv) == 0  # a folder holding other files is fine
  capsys.readouterr()
  before = {p.name: p.read_bytes() for p in out.iterdir()}
  assert sorted(before) == ["metrics.json", "notes.txt", "uncertainty_hist.png",
                            "uncertainty_maps.png"]
  for name in ("metrics.json", "uncertainty_hist.png", "uncertainty_maps.png"):
    keep = {name: before[name], "notes.txt": b"mine"}
    for p in out.iterdir():
      if p.name not in keep:
        p.unlink()
    (out / name).write_bytes(before[name])
    bad_pred = ["--pred", str(tmp_path / "missing.npz")]
    for args in (argv, argv[:1] + bad_pred + argv[3:]):  # refused before reading --pred
      assert cli.main(args) == 2
      err = capsys.readouterr().err.strip().splitlines()
      assert err == [f"sljax uncertainty: error: {out / name}: exists (pass --overwrite to "
                     "replace it)"]
    assert {p.name: p.read_bytes() for p in out.iterdir()} == keep
  assert cli.main(argv + ["--overwrite"]) == 0
  assert sorted(p.name for p in out.iterdir()) == sorted(before)
  (tmp_path / "file").write_text("x")
  assert cli.main(argv[:5] + ["--out", str(tmp_path / "file")]) == 2
  assert "exists and is not a folder" in capsys.readouterr().err
