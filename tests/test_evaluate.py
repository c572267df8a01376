import csv
import json
import math

import cv2
import numpy as np
import pytest

import jax.numpy as jnp

from sljax import cli, inference
from sljax.data.camera import Calib
from sljax.data.dataset import FolderSource
from sljax.data.pfm import read_pfm
from sljax.data.scene import Scene, write_scene
from sljax.evaluation import metrics
from sljax.evaluation.scoring import evaluate
from sljax.inference.sgbm import SGBMPredictor
from sljax.nets import ModelConfig
from toys import ToySL, registered, toy_spec


def textured_scene(name, seed, h=48, w=80, d_back=6, d_front=12, with_gt=True):
  """Background plane + a nearer square with random texture; exact GT, mask = the square."""
  rng = np.random.default_rng(seed)
  back = cv2.GaussianBlur(rng.uniform(0, 1, (h, w + 32)).astype(np.float32), (0, 0), 1.0)
  front = cv2.GaussianBlur(rng.uniform(0, 1, (h, w + 32)).astype(np.float32), (0, 0), 1.0)
  ys, xs = np.mgrid[0:h, 0:w]
  inside = lambda x: (ys >= h // 4) & (ys < 3 * h // 4) & (x >= w // 3) & (x < 2 * w // 3)
  left = np.where(inside(xs), front[ys, xs], back[ys, xs])
  right = np.where(inside(xs + d_front), front[ys, xs + d_front], back[ys, xs + d_back])
  gt = np.where(inside(xs), float(d_front), float(d_back)).astype(np.float32)
  gt[:2, :2] = np.inf  # some unknown ground truth
  k = np.array([[100.0, 0, w / 2], [0, 100.0, h / 2], [0, 0, 1]])
  calib = Calib(cam0=k, cam1=k, doffs=1.0, baseline=20.0, width=w, height=h, ndisp=24)
  return Scene(name=name, im0=left[..., None].astype(np.float32),
               im1=right[..., None].astype(np.float32), disp0=gt if with_gt else None,
               mask0=inside(xs) if with_gt else None, calib=calib)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
  root = tmp_path_factory.mktemp("data")
  for i in range(3):
    write_scene(root / "group" / f"s{i}", textured_scene(f"s{i}", seed=i))
  return root


@pytest.fixture(scope="module")
def sgbm_run(dataset, tmp_path_factory):
  out = tmp_path_factory.mktemp("eval") / "sgbm"
  rc = cli.main(["evaluate", "sgbm", str(dataset), "--out", str(out), "--save-predictions",
                 "--figures"])
  assert rc == 0
  return out


def test_report_files_parse_and_agree_with_metrics(dataset, sgbm_run):
  report = json.loads((sgbm_run / "metrics.json").read_text())
  assert report["model"] == "sgbm" and report["n_scenes"] == 3 and report["n_scenes_with_gt"] == 3
  # The pooled numbers equal the metrics of the saved predictions pooled independently.
  names = [f"group/s{i}" for i in range(3)]
  preds = [read_pfm(sgbm_run / "predictions" / f"{n}.pfm") for n in names]
  gts = [read_pfm(dataset / n / "disp0.pfm") for n in names]
  want = metrics.pooled_disparity_metrics(preds, gts)
  full = report["pooled"]["full"]
  for k in ("mae", "iqr", "bad_2", "d1", "n_pixels"):
    assert full[k] == pytest.approx(want[k], rel=1e-6)
  assert full["n_pixels"] == 3 * (48 * 80 - 4)
  assert "depth_mae_mm" in full and math.isfinite(full["depth_mae_mm"])
  # Seg: the square only, 24 x 27 pixels per scene.
  assert report["pooled"]["seg"]["n_pixels"] == 3 * 24 * 27
  with open(sgbm_run / "per_scene.csv", newline="") as f:
    rows = list(csv.DictReader(f))
  assert [r["scene"] for r in rows] == names
  for r, p, g in zip(rows, preds, gts):
    assert float(r["full_mae"]) == pytest.approx(metrics.disparity_metrics(p, g)["mae"], rel=1e-6)
  md = (sgbm_run / "metrics.md").read_text()
  assert "resolution mode" in md and "| Full |" in md and "| Seg |" in md
  assert "group/s2" in md
  assert len(list((sgbm_run / "figures" / "group").glob("*.png"))) == 3


def test_save_predictions_round_trip(dataset, tmp_path):
  source = FolderSource(dataset)
  predictor = SGBMPredictor()
  report = evaluate(predictor, source, [1], out_dir=tmp_path, save_predictions=True,
                    progress=False)
  scene = source[1]
  direct = predictor(scene.im0, scene.im1, calib=scene.calib)["disparity"]
  saved = read_pfm(tmp_path / "predictions" / "group" / "s1.pfm")
  np.testing.assert_array_equal(saved, direct)  # inf (no match) survives the round trip
  assert report["per_scene"][0]["full"]["mae"] == pytest.approx(
      metrics.disparity_metrics(direct, scene.disp0)["mae"])


def test_refuses_non_empty_out(dataset, sgbm_run, capsys):
  rc = cli.main(["evaluate", "sgbm", str(dataset), "--out", str(sgbm_run)])
  assert rc == 2 and "not empty" in capsys.readouterr().err
  rc = cli.main(["evaluate", str(dataset), "--model", "sgbm", "--out", str(sgbm_run),
                 "--overwrite", "--split", "test"])
  assert rc == 0
  assert json.loads((sgbm_run / "metrics.json").read_text())["n_scenes"] == 1


def test_dataset_without_ground_truth(tmp_path, capsys):
  root = tmp_path / "nogt"
  write_scene(root / "a", textured_scene("a", seed=5, with_gt=False))
  out = tmp_path / "out"
  rc = cli.main(["evaluate", "sgbm", str(root), "--out", str(out), "--save-predictions",
                 "--figures"])
  assert rc == 0
  report = json.loads((out / "metrics.json").read_text())
  assert report["n_scenes_with_gt"] == 0 and report["pooled"] == {}
  assert any("no metrics could be computed" in n for n in report["notes"])
  assert "no metrics could be computed" in (out / "metrics.md").read_text()
  assert (out / "predictions" / "a.pfm").exists() and (out / "figures" / "a.png").exists()


def test_image_pair_of_different_sizes_names_the_file(tmp_path, capsys):
  root = tmp_path / "bad"
  write_scene(root / "x", textured_scene("x", seed=6))
  cv2.imwrite(str(root / "x" / "im1.png"), np.zeros((48, 70), np.uint8))
  rc = cli.main(["evaluate", "sgbm", str(root), "--out", str(tmp_path / "o")])
  err = capsys.readouterr().err
  assert rc == 2 and "im1.png" in err


def test_calibration_of_another_image_size_names_the_file(tmp_path, capsys):
  # The depth metrics used to be computed with it; `sljax predict` already refused it.
  root = tmp_path / "bad"
  write_scene(root / "x", textured_scene("x", seed=6))
  calib = root / "x" / "calib.txt"
  calib.write_text(calib.read_text().replace("width=80", "width=160"))
  out = tmp_path / "o"
  rc = cli.main(["evaluate", "sgbm", str(root), "--out", str(out)])
  err = capsys.readouterr().err
  assert rc == 2 and err == (
      f"sljax evaluate: error: scene {root / 'x'}: calib.txt: calibration is for 160x48 images, "
      "the pair is 80x48 (depth would be wrong; give the calib.txt of these images)\n"), err
  assert not (out / "metrics.json").exists()


def test_missing_checkpoint_is_an_error(dataset, tmp_path, capsys):
  rc = cli.main(["evaluate", str(tmp_path / "nope"), str(dataset), "--out", str(tmp_path / "o")])
  assert rc == 2 and "nope" in capsys.readouterr().err
  # A folder that is no checkpoint (here the dataset itself) says what a checkpoint is.
  rc = cli.main(["evaluate", str(dataset), str(dataset), "--out", str(tmp_path / "o")])
  err = capsys.readouterr().err
  assert rc == 2 and str(dataset) in err and "not a checkpoint" in err and "workdir" in err


def test_sl_model_pattern_accuracy_and_figures(tmp_path):
  rng = np.random.default_rng(3)
  h, w, d = 32, 64, 4
  tex = (rng.uniform(size=(h, w + d, 3)) > 0.5).astype(np.float32)
  left, right = tex[:, :w], tex[:, d:]
  sl0, sl1 = left.copy(), right.copy()
  sl0[:4, :, 0] = 1.0 - sl0[:4, :, 0]  # 4 * 64 wrong labels in pattern 0
  sl0[4:6, :, 1] = np.nan  # 2 * 64 unknown
  gt = np.full((h, w), float(d), np.float32)
  write_scene(tmp_path / "d" / "a",
              Scene(name="a", im0=left, im1=right, disp0=gt, sl0=sl0, sl1=sl1))
  out = tmp_path / "out"
  with registered(toy_spec("toy-sl", ToySL, outputs=("sl_logits", "sl_logits_right"))):
    predictor = inference.Predictor(ModelConfig.of("toy-sl"), {"params": {"gain": jnp.ones(())}})
    report = evaluate(predictor, FolderSource(tmp_path / "d"), out_dir=out, figures=True,
                      progress=False)
  known = h * w * 3 - 2 * 64
  left_acc = report["pooled"]["patterns_left"]
  assert left_acc["pattern_n_pixels"] == known
  assert left_acc["pattern_acc"] == pytest.approx(100.0 * (known - 4 * 64) / known)
  assert report["pooled"]["patterns_right"]["pattern_acc"] == pytest.approx(100.0)
  # The disparity evaluated is the pattern correlation's: right in the interior.
  assert report["per_scene"][0]["full"]["bad_1"] < 50
  assert (out / "figures" / "a.png").exists()
  md = (out / "metrics.md").read_text()
  assert "Pattern accuracy (left view)" in md


UNET_KW = {"depth": 2, "base_width": 4, "in_channels": 1, "t": 3}


def _write_unet_sl_workdir(workdir, kwargs_in_config):
  """A training workdir (config.json + orbax checkpoint) of a tiny random unet-sl."""
  import jax

  from sljax.models import checkpoint as ckpt
  from sljax.nets import build_model
  model = build_model("unet-sl", **UNET_KW)
  x = jax.ShapeDtypeStruct((1, 32, 32, 1), jnp.float32)
  shapes = jax.eval_shape(lambda a, b: model.init(jax.random.PRNGKey(0), a, b, train=False), x, x)
  rng = np.random.default_rng(0)
  variables = jax.tree_util.tree_map_with_path(
      lambda p, l: jnp.asarray(rng.uniform(0.5, 1.5, l.shape) if "var" in str(p[-1])
                               else rng.normal(size=l.shape) / np.sqrt(np.prod(l.shape[:-1]) or 1),
                               jnp.float32), dict(shapes))
  workdir.mkdir(parents=True)
  config = {"model": "unet-sl", "strategy": "stl", "net": "unet-sl",
            "model_kwargs": kwargs_in_config, "size": [32, 32], "gray": True, "t": 3}
  (workdir / "config.json").write_text(json.dumps(config))
  manager = ckpt.make_manager(workdir / "checkpoints")
  ckpt.save(manager, 1, variables, {"step": 1}, val_mae=1.0)
  manager.wait_until_finished()
  manager.close()


def test_evaluate_checkpoint_from_cli(tmp_path, capsys):
  rng = np.random.default_rng(4)
  h, w, d = 24, 40, 3
  tex = (rng.uniform(size=(h, w + d, 3)) > 0.5).astype(np.float32)
  sl0 = tex[:, :w].copy()
  sl0[0, 0, 0] = np.nan
  write_scene(tmp_path / "d" / "a", Scene(name="a", im0=tex[:, :w], im1=tex[:, d:],
                                          disp0=np.full((h, w), float(d), np.float32),
                                          sl0=sl0, sl1=tex[:, d:]))
  _write_unet_sl_workdir(tmp_path / "run", UNET_KW)
  for mode in ("pad", "resize"):
    out = tmp_path / f"out_{mode}"
    rc = cli.main(["evaluate", str(tmp_path / "run"), str(tmp_path / "d"), "--out", str(out),
                   "--mode", mode, "--save-predictions"])
    assert rc == 0, capsys.readouterr().err
    report = json.loads((out / "metrics.json").read_text())
    assert report["model"] == "unet-sl" and report["mode"] == mode
    assert report["pooled"]["patterns_left"]["pattern_n_pixels"] == h * w * 3 - 1
    assert report["pooled"]["full"]["n_pixels"] == h * w
    assert read_pfm(out / "predictions" / "a.pfm").shape == (h, w)
    assert mode in (out / "metrics.md").read_text()
  # A checkpoint whose saved variables do not fit the model options in its config.
  _write_unet_sl_workdir(tmp_path / "bad", dict(UNET_KW, base_width=8))
  rc = cli.main(["evaluate", str(tmp_path / "bad"), str(tmp_path / "d"), "--out",
                 str(tmp_path / "o2")])
  err = capsys.readouterr().err
  assert rc == 2 and "bad" in err and "do not match" in err


def test_full_disk_keeps_the_earlier_report_file(sgbm_run, tmp_path, monkeypatch):
  """A disk that fills while writing per_scene.csv (--overwrite): the earlier per_scene.csv
  stays byte for byte, no temporary file remains, the error names the file."""
  import errno
  from pathlib import Path
  from sljax.evaluation import scoring as ev
  report = json.loads((sgbm_run / "metrics.json").read_text())
  out = tmp_path / "r"
  ev.write_report(report, out)
  before = {p.name: p.read_bytes() for p in out.iterdir()}
  assert sorted(before) == ["metrics.json", "metrics.md", "per_scene.csv"]
  real = Path.write_bytes

  def full(path, data):
    if path.suffix != ".csv":
      return real(path, data)
    real(path, data[:len(data) // 2])
    raise OSError(errno.ENOSPC, "No space left on device", str(path))
  monkeypatch.setattr(Path, "write_bytes", full)
  report["model"] = "another"
  with pytest.raises(OSError) as info:
    ev.write_report(report, out)
  assert info.value.filename == str(out / "per_scene.csv")
  after = {p.name: p.read_bytes() for p in out.iterdir()}
  assert sorted(after) == sorted(before) and after["per_scene.csv"] == before["per_scene.csv"]


def test_a_late_failure_leaves_out_as_it_was(dataset, tmp_path, capsys):
  """A view that passes the pre-flight but does not decode in the last scene: --out stays
  absent (no empty folder), and an earlier --out keeps its files byte for byte."""
  import shutil  # pylint: disable=import-outside-toplevel
  import toys  # pylint: disable=import-outside-toplevel
  data = tmp_path / "data"
  shutil.copytree(dataset, data)
  toys.break_deflate(data / "group" / "s2" / "im1.png")
  out = tmp_path / "a" / "out"
  assert cli.main(["evaluate", "sgbm", str(data), "--out", str(out), "--save-predictions",
                   "--figures"]) == 2
  assert "s2/im1.png: not a readable image" in capsys.readouterr().err
  assert not (tmp_path / "a").exists()
  old = tmp_path / "old"
  assert cli.main(["evaluate", "sgbm", str(dataset), "--out", str(old),
                   "--save-predictions"]) == 0
  before = toys.tree(old)
  assert cli.main(["evaluate", "sgbm", str(data), "--out", str(old), "--overwrite",
                   "--save-predictions", "--figures"]) == 2
  assert toys.tree(old) == before
