"""sljax predict and sljax.depth.geometry: depth maps, 16-bit PNGs and PLY point clouds read back."""

import json

import cv2
import numpy as np
import pytest

from sljax import cli
from sljax.data.camera import Calib, write_calib
from sljax.data.pfm import read_pfm
from sljax.depth import geometry, pairs
from sljax.errors import SljaxError
from sljax.io.images import write_image

H, W = 40, 64
F, CX, CY, FY, BASELINE, DOFFS = 80.0, 30.5, 21.0, 80.0, 120.0, 2.5


def _calib(width=W, height=H, doffs=DOFFS):
  cam = np.array([[F, 0, CX], [0, FY, CY], [0, 0, 1]])
  return Calib(cam0=cam, cam1=cam + np.array([[0, 0, doffs], [0, 0, 0], [0, 0, 0]]),
               doffs=doffs, baseline=BASELINE, width=width, height=height, ndisp=32)


def read_ply(path):
  """Independent PLY reader: parses the ASCII header, then the little-endian vertex records."""
  data = path.read_bytes()
  end = data.index(b"end_header\n") + len(b"end_header\n")
  header = data[:end].decode("ascii").splitlines()
  assert header[0] == "ply" and header[1] == "format binary_little_endian 1.0"
  count = next(int(line.split()[2]) for line in header if line.startswith("element vertex"))
  props = [tuple(line.split()[1:]) for line in header if line.startswith("property")]
  assert props == [("float", "x"), ("float", "y"), ("float", "z"), ("uchar", "red"),
                   ("uchar", "green"), ("uchar", "blue")]
  record = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"),
                     ("b", "u1")])
  assert len(data) - end == count * record.itemsize  # 15 bytes a point, nothing else
  v = np.frombuffer(data, record, count=count, offset=end)
  return np.stack([v["x"], v["y"], v["z"]], 1), np.stack([v["r"], v["g"], v["b"]], 1)


def expected_points(disp, calib, image, max_depth=None):
  """The formula in float64: Z = f B / (d + doffs), X = (x - cx) Z / f, Y = (y - cy) Z / fy."""
  rows = []
  for y in range(disp.shape[0]):
    for x in range(disp.shape[1]):
      d = float(disp[y, x])
      if not np.isfinite(d) or d + calib.doffs <= 0:
        continue
      z = calib.cam0[0, 0] * calib.baseline / (d + calib.doffs)
      if max_depth is not None and z > max_depth:
        continue
      rows.append(((x - calib.cam0[0, 2]) * z / calib.cam0[0, 0],
                   (y - calib.cam0[1, 2]) * z / calib.cam0[1, 1], z,
                   *np.rint(image[y, x] * 255)))
  a = np.array(rows, np.float64).reshape(-1, 6)
  return a[:, :3], a[:, 3:].astype(np.uint8)


def _disparity(rng):
  """Disparities with unknown pixels, d + doffs <= 0 (behind infinity) and far points."""
  d = rng.uniform(0.5, 30.0, (H, W)).astype(np.float32)
  d[3, :10] = np.inf
  d[5, 5] = np.nan
  d[7, 7:12] = -DOFFS  # at infinity: no depth
  d[8, 8] = -DOFFS - 1.0
  d[9, :20] = 0.05  # about 3.7 m: beyond --max-depth 3000 below
  return d


def test_point_cloud_and_depth_maps_match_the_formula(tmp_path):
  rng = np.random.default_rng(0)
  disp = _disparity(rng)
  image = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
  calib = _calib()
  for max_depth in (None, 3000.0):
    xyz, rgb = geometry.point_cloud(disp, calib, image, max_depth)
    want_xyz, want_rgb = expected_points(disp, calib, image, max_depth)
    assert len(xyz) == len(want_xyz) and xyz.dtype == np.float32
    np.testing.assert_allclose(xyz, want_xyz, rtol=2e-6, atol=1e-4)
    np.testing.assert_array_equal(rgb, want_rgb)
    geometry.write_ply(tmp_path / "c.ply", xyz, rgb, comment="test")
    back_xyz, back_rgb = read_ply(tmp_path / "c.ply")
    np.testing.assert_array_equal(back_xyz, xyz)
    np.testing.assert_array_equal(back_rgb, rgb)
  assert len(geometry.point_cloud(disp, calib, image, 3000.0)[0]) == len(xyz) < H * W - 30
  depth = geometry.depth_mm(disp, calib, 3000.0)
  png = geometry.depth_png16(depth)
  known = np.isfinite(depth)
  assert not known[3, :10].any() and not known[7, 7:12].any() and not known[9, :20].any()
  np.testing.assert_array_equal(png[known], np.rint(depth[known]).astype(np.uint16))
  assert (png[~known] == 0).all()


def test_png16_unknown_and_too_far():
  z = np.array([[np.inf, 0.3, 1.4], [65535.2, 65535.6, 70000.0]], np.float32)
  np.testing.assert_array_equal(geometry.depth_png16(z), [[0, 0, 1], [65535, 0, 0]])


def _scene(folder, shift=6, calib=True, size=(H, W)):
  """A Middlebury-format scene: a textured plane at disparity `shift` (right[x - d] = left[x])."""
  rng = np.random.default_rng(1)
  h, w = size
  tex = cv2.GaussianBlur(rng.uniform(0, 1, (h, w + shift)).astype(np.float32), (3, 3), 0.8)
  tex = (tex - tex.min()) / (tex.max() - tex.min())
  colour = np.stack([tex, 1 - tex, 0.5 * tex], -1)
  folder.mkdir(parents=True, exist_ok=True)
  write_image(folder / "im0.png", colour[:, :w])
  write_image(folder / "im1.png", colour[:, shift:])
  if calib:
    write_calib(folder / "calib.txt", _calib(w, h))
  return folder


def test_predict_writes_ply_that_agrees_with_its_disparity(tmp_path, capsys):
  scene = _scene(tmp_path / "data" / "s1")
  out = tmp_path / "out"
  assert cli.main(["predict", "sgbm", str(scene / "im0.png"), str(scene / "im1.png"),
                   "--out", str(out), "--num-disparities", "16"]) == 0
  assert "points" in capsys.readouterr().out
  names = {p.name for p in out.iterdir()}
  assert names == {"disparity.pfm", "disparity.png", "depth_mm.pfm", "depth_mm.png", "cloud.ply"}
  disp = read_pfm(out / "disparity.pfm")
  assert disp.shape == (H, W) and np.isfinite(disp).mean() > 0.5
  image = cv2.imread(str(scene / "im0.png"))[..., ::-1] / 255.0
  xyz, rgb = read_ply(out / "cloud.ply")
  want_xyz, want_rgb = expected_points(disp, _calib(), image)
  assert len(xyz) == len(want_xyz) > 0
  np.testing.assert_allclose(xyz, want_xyz, rtol=2e-6, atol=1e-4)
  np.testing.assert_array_equal(rgb, want_rgb)
  # The depth PFM and the 16-bit PNG agree (mm, rounded; 0 where the PFM is unknown).
  depth = read_pfm(out / "depth_mm.pfm")
  png = cv2.imread(str(out / "depth_mm.png"), cv2.IMREAD_UNCHANGED)
  assert png.dtype == np.uint16 and png.shape == (H, W)
  known = np.isfinite(depth)
  np.testing.assert_array_equal(png[known], np.rint(depth[known]).astype(np.uint16))
  assert (png[~known] == 0).all() and known.sum() == len(xyz)
  np.testing.assert_allclose(depth[known], F * BASELINE / (disp[known] + DOFFS), rtol=1e-6)
  colour = cv2.imread(str(out / "disparity.png"))
  assert colour.ndim == 3 and colour.std() > 10  # a picture, not a blank
  # Nothing is overwritten silently; --overwrite replaces.
  assert cli.main(["predict", "sgbm", str(scene / "im0.png"), str(scene / "im1.png"),
                   "--out", str(out)]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and "exists" in err[0] and "--overwrite" in err[0]
  limit = float(np.median(depth[known]))
  assert cli.main(["predict", "sgbm", str(scene / "im0.png"), str(scene / "im1.png"),
                   "--out", str(out), "--overwrite", "--max-depth", str(limit)]) == 0
  near = read_pfm(out / "depth_mm.pfm")
  np.testing.assert_array_equal(np.isfinite(near), known & (depth <= np.float32(limit)))
  assert len(read_ply(out / "cloud.ply")[0]) == np.isfinite(near).sum() < len(xyz)


def test_predict_folders_of_scenes_and_left_right(tmp_path, capsys):
  data = tmp_path / "data"
  _scene(data / "a" / "s1")
  _scene(data / "b", calib=False)
  out = tmp_path / "o1"
  assert cli.main(["predict", "sgbm", str(data), "--out", str(out)]) == 0
  lines = capsys.readouterr().out.strip().splitlines()
  assert len(lines) == 2 and "no calibration" in lines[1]
  assert (out / "a" / "s1" / "cloud.ply").exists() and not (out / "b" / "cloud.ply").exists()
  assert (out / "b" / "disparity.pfm").exists()
  # left/ and right/ folders paired by name, one calib.txt for all of them.
  pairs = tmp_path / "pairs"
  for name in ("f1", "f2"):
    s = _scene(tmp_path / "tmp" / name, calib=False)
    for side, f in (("left", "im0.png"), ("right", "im1.png")):
      (pairs / side).mkdir(parents=True, exist_ok=True)
      (pairs / side / f"{name}.png").write_bytes((s / f).read_bytes())
  write_calib(pairs / "calib.txt", _calib())
  out = tmp_path / "o2"
  assert cli.main(["predict", "sgbm", str(pairs), "--out", str(out)]) == 0
  assert sorted(p.name for p in out.iterdir()) == ["f1", "f2"]
  assert (out / "f2" / "cloud.ply").exists()


def _converted_model(folder, name, kwargs, hw=(32, 48)):
  """A randomly initialised network saved as a converted-model folder (config + variables)."""
  from test_inference import random_variables
  variables = random_variables(name, kwargs, 3, hw)
  flat = {}

  def walk(tree, prefix):
    for k, v in tree.items():
      if hasattr(v, "items"):
        walk(v, prefix + (k,))
      else:
        flat["/".join(prefix + (k,))] = np.asarray(v, np.float32)
  walk(variables, ())
  folder.mkdir(parents=True)
  np.savez(folder / "variables.npz", **flat)
  (folder / "config.json").write_text(json.dumps({"model": name, "model_kwargs": kwargs}))
  return folder


def test_predict_sl_model_writes_confidence(tmp_path):
  model = _converted_model(tmp_path / "unet", "unet-sl",
                           {"depth": 2, "base_width": 4, "in_channels": 1, "t": 4})
  scene = _scene(tmp_path / "s", size=(30, 50))
  out = tmp_path / "out"
  assert cli.main(["predict", str(model), str(scene / "im0.png"), str(scene / "im1.png"),
                   "--out", str(out), "--search-range", "12"]) == 0
  conf = read_pfm(out / "confidence.pfm")
  assert conf.shape == (30, 50) and (conf >= 0).all() and (conf <= 1).all()
  assert read_pfm(out / "disparity.pfm").max() <= 12  # the correlation's search range
  assert (out / "confidence.png").exists() and (out / "cloud.ply").exists()


def _one_error(capsys, argv):
  assert cli.main(argv) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and err[0].startswith("sljax predict: error: ")
  return err[0]


def test_predict_bad_inputs(tmp_path, capsys):
  scene = _scene(tmp_path / "s")
  left, right = str(scene / "im0.png"), str(scene / "im1.png")
  out = str(tmp_path / "out")
  base = ["predict", "sgbm"]
  assert "im9.png: no such image file" in _one_error(
      capsys, base + [str(scene / "im9.png"), right, "--out", out])
  small = tmp_path / "small.png"
  write_image(small, np.zeros((H, W - 4, 3)))
  assert "differs from" in _one_error(capsys, base + [left, str(small), "--out", out])
  bad_calib = tmp_path / "bad.txt"
  bad_calib.write_text("cam0=[80 0 30; 0 80 21; 0 0 1]\nbaseline=120\n")
  assert "lacks required key(s) cam1, doffs" in _one_error(
      capsys, base + [left, right, "--calib", str(bad_calib), "--out", out])
  other = tmp_path / "other.txt"
  write_calib(other, _calib(width=2 * W, height=2 * H))
  assert "calibration is for 128x80 images, the pair is 64x40" in _one_error(
      capsys, base + [left, right, "--calib", str(other), "--out", out])
  assert "--calib" in _one_error(capsys, base + [left, right, "--calib", "nope.txt", "--out", out])
  assert "unknown model" in _one_error(capsys, ["predict", "psmnet", left, right, "--out", out])
  (tmp_path / "empty_model").mkdir()
  assert "not a checkpoint" in _one_error(
      capsys, ["predict", str(tmp_path / "empty_model"), left, right, "--out", out])
  assert "neither scene folders" in _one_error(capsys, base + [str(tmp_path / "empty_model"),
                                                               "--out", out])
  assert "LEFT RIGHT" in _one_error(capsys, base + [left, right, left, "--out", out])
  pairs = tmp_path / "pairs"
  (pairs / "left").mkdir(parents=True)
  (pairs / "right").mkdir()
  write_image(pairs / "left" / "a.png", np.zeros((8, 8)))
  assert "right/a.png: missing" in _one_error(capsys, base + [str(pairs), "--out", out])
  # Each range belongs to one kind of model, and says which is the right one.
  assert "its disparity range is --num-disparities" in _one_error(
      capsys, base + [left, right, "--maxdisp", "16", "--out", out])
  assert "--max-depth must be positive (mm), got -1.0" in _one_error(
      capsys, base + [left, right, "--max-depth", "-1", "--out", out])
  psm = _converted_model(tmp_path / "psm", "psmnet", {"maxdisp": 16, "in_channels": 3},
                         hw=(32, 32))
  assert "multiple of 16" in _one_error(
      capsys, ["predict", str(psm), left, right, "--maxdisp", "20", "--out", out])
  assert "search_range is unet-sl's correlation range; psmnet has none" in _one_error(
      capsys, ["predict", str(psm), left, right, "--search-range", "20", "--out", out])
  assert "--num-disparities is sgbm's range" in _one_error(
      capsys, ["predict", str(psm), left, right, "--num-disparities", "16", "--out", out])
  assert not (tmp_path / "out").exists()  # no bad input left anything behind


def test_predict_pairs_from_python_takes_a_str_out_and_checks_its_arguments_first(tmp_path):
  scene = _scene(tmp_path / "s")
  found = pairs.find_pairs([str(scene / "im0.png"), str(scene / "im1.png")])
  sgbm = pairs.load_predictor("sgbm", num_disparities=16)
  out = tmp_path / "out"
  for bad in (0, -1.0, float("nan")):  # else every pixel silently unknown: an empty cloud
    with pytest.raises(SljaxError, match="max_depth must be positive"):
      pairs.predict_pairs(sgbm, found, str(out), max_depth=bad, progress=False)
  with pytest.raises(SljaxError, match="max_depth must be a number of mm or None, got '3000'"):
    pairs.predict_pairs(sgbm, found, str(out), max_depth="3000", progress=False)
  with pytest.raises(SljaxError, match="predictor must be callable .* got str 'sgbm'"):
    pairs.predict_pairs("sgbm", found, str(out), progress=False)
  assert not out.exists()  # refused before the first prediction
  # A str folder, as on the command line (an AttributeError on str.mkdir before).
  (summary,) = pairs.predict_pairs(sgbm, found, str(out), max_depth=3000.0, progress=False)
  assert summary["points"] > 0 and (out / "cloud.ply").is_file()


def test_geometry_refuses_a_max_depth_that_would_drop_every_point():
  disp = np.full((H, W), 10.0, np.float32)
  for bad in (0.0, -5, float("nan")):
    with pytest.raises(SljaxError, match="max_depth must be positive"):
      geometry.depth_mm(disp, _calib(), bad)
    with pytest.raises(SljaxError, match="max_depth must be positive"):
      geometry.point_cloud(disp, _calib(), None, bad)
  assert np.isfinite(geometry.depth_mm(disp, _calib(), float("inf"))).all()  # no limit


def test_find_pairs_names_a_single_path_given_instead_of_a_list(tmp_path):
  scene = _scene(tmp_path / "s")
  with pytest.raises(SljaxError, match="inputs must be a list of paths.*got the single path"):
    pairs.find_pairs(str(scene))  # was "got 15 paths" (one per character)
  assert len(pairs.find_pairs([scene])) == 1


def test_find_pairs_rejects_scene_without_right_view(tmp_path):
  scene = _scene(tmp_path / "d" / "s")
  (scene / "im1.png").unlink()
  with pytest.raises(SljaxError, match="im1.png: missing"):
    pairs.find_pairs([str(tmp_path / "d")])


@pytest.mark.parametrize("victim", ["cloud.ply", "disparity.pfm", "depth_mm.png"])
def test_full_disk_keeps_the_earlier_file(tmp_path, capsys, monkeypatch, victim):
  """--overwrite onto a disk that fills while writing one file: one line naming that file,
  exit 2; the earlier file stays byte for byte and no temporary file remains."""
  import errno
  scene = _scene(tmp_path / "data" / "s1")
  out = tmp_path / "out"
  argv = ["predict", "sgbm", str(scene / "im0.png"), str(scene / "im1.png"), "--out", str(out),
          "--num-disparities", "16"]
  assert cli.main(argv) == 0
  before = {p.name: p.read_bytes() for p in out.iterdir()}

  def full(path, *args, **kwargs):
    with open(path, "wb") as f:
      f.write(b"half")
    raise OSError(errno.ENOSPC, "No space left on device", str(path))
  from pathlib import Path
  real = Path.write_bytes  # what write_pfm's, write_png's and write_ply's temporaries use
  stem, suffix = victim.split(".")
  monkeypatch.setattr(Path, "write_bytes", lambda path, data: (
      full if stem in path.name and path.suffix == f".{suffix}" else real)(path, data))
  capsys.readouterr()
  assert cli.main(argv + ["--overwrite"]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert err == [f"sljax predict: error: {out / victim}: No space left on device"]
  after = {p.name: p.read_bytes() for p in out.iterdir()}
  assert set(after) == set(before) and after[victim] == before[victim]


def test_a_late_failure_leaves_out_as_it_was(tmp_path, capsys):
  """A folder of pairs whose last view does not decode (the pre-flight-proof damage): --out
  stays absent, and an existing --out keeps its earlier files byte for byte."""
  import toys  # pylint: disable=import-outside-toplevel
  data = tmp_path / "data"
  for name in ("a", "b", "c"):
    _scene(data / name)
  toys.break_deflate(data / "c" / "im1.png")
  out = tmp_path / "out"
  assert cli.main(["predict", "sgbm", str(data), "--out", str(out)]) == 2
  assert "c/im1.png: not a readable image" in capsys.readouterr().err
  assert not out.exists()
  assert cli.main(["predict", "sgbm", str(data / "a"), "--out", str(out)]) == 0
  (out / "notes.txt").write_text("mine")
  before = toys.tree(out)
  assert cli.main(["predict", "sgbm", str(data), "--out", str(out), "--overwrite"]) == 2
  assert toys.tree(out) == before
