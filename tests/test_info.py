import json

import cv2
import numpy as np
import pytest

from sljax import cli
from sljax.data.camera import Calib, write_calib
from sljax.data.scene import Scene, load_scene, write_scene
from sljax.errors import SljaxError

H, W = 6, 10


def _scene(k, t=4):
  rng = np.random.default_rng(k)
  disp = rng.uniform(1 + k, 5 + k, (H, W)).astype(np.float32)
  disp[:2] = np.inf
  return Scene(name=str(k), im0=rng.uniform(size=(H, W, 3)).astype(np.float32),
               im1=rng.uniform(size=(H, W, 3)).astype(np.float32), disp0=disp,
               sl0=rng.integers(0, 2, (H, W, t)).astype(np.float32),
               sl1=rng.integers(0, 2, (H, W, t)).astype(np.float32),
               meta={"group": f"obj{k // 2}"})


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
  root = tmp_path_factory.mktemp("info")
  scenes = [_scene(k) for k in range(5)]
  for k, s in enumerate(scenes):
    write_scene(root / f"set/s{k}", s)
  (root / "dataset.json").write_text(json.dumps({"name": "toy", "code": "gray", "patterns": 4}))
  return root, scenes


def test_info_summary(dataset, capsys):
  root, scenes = dataset
  assert cli.main(["info", str(root)]) == 0
  out = capsys.readouterr().out
  assert "dataset toy: 5 scenes" in out
  assert f"{W}x{H} 8-bit RGB (5)" in out
  assert "disp0.pfm 5/5" in out and "sl1 5/5" in out and "mask0" not in out.split("scenes:")[0]
  assert "code gray; 4 patterns (5 scenes)" in out
  lo = min(float(np.min(s.disp0[np.isfinite(s.disp0)])) for s in scenes)
  hi = max(float(np.max(s.disp0[np.isfinite(s.disp0)])) for s in scenes)
  assert f"{lo:.2f}..{hi:.2f} px" in out
  # 3 groups (obj0, obj1, obj2): one group is held out; 2 or 1 scenes depending on which.
  split = next(l for l in out.splitlines() if l.startswith("split"))
  assert "/ 2 groups" in split and split.rstrip().endswith("/ 1 group")
  assert "set/s3" in out and "obj1" in out  # per-scene table


def test_info_summarises_many(dataset, capsys):
  root, _ = dataset
  assert cli.main(["info", str(root), "--rows", "2"]) == 0
  out = capsys.readouterr().out
  assert "first: set/s0, last: set/s4" in out and "set/s2" not in out


def test_info_reports_problems(tmp_path, capsys):
  write_scene(tmp_path / "a", _scene(0))
  bad = _scene(1)
  write_scene(tmp_path / "b", bad)
  for k in (2, 3):
    (tmp_path / "b" / "sl1" / f"00{k}.png").unlink()
  (tmp_path / "b" / "disp0.pfm").write_bytes(b"garbage")
  assert cli.main(["info", str(tmp_path)]) == 1
  out = capsys.readouterr().out
  assert "b: sl0 holds 4 patterns, sl1 holds 2" in out
  assert "disp0.pfm: not a PFM" in out
  flipped = _scene(2)
  flipped.disp1 = -np.nan_to_num(flipped.disp0, posinf=np.inf)  # written x_right - x_left
  write_scene(tmp_path / "c", flipped)
  assert cli.main(["info", str(tmp_path)]) == 1
  out = capsys.readouterr().out
  # The loader's own words (sljax.data.checks.disparity_problem), as --check and training say it.
  assert "c: disp1.pfm: 100% of its known disparities are negative;" in out, out
  assert "(is the sign flipped?)" in out
  assert "c: disp0.pfm" not in out


def test_info_flags_mixed_or_undeclared_pattern_counts(tmp_path, capsys):
  """Its help promises exit 1 on inconsistent scenes: a 5-pattern scene among 4-pattern ones,
  or scenes that disagree with dataset.json, are problems (training would fail on them)."""
  write_scene(tmp_path / "a", _scene(0))
  write_scene(tmp_path / "b", _scene(1, t=5))
  assert cli.main(["info", str(tmp_path)]) == 1
  assert "scenes hold different pattern counts: 4 (1 scene), 5 (1 scene)" in capsys.readouterr().out
  (tmp_path / "b").rename(tmp_path.parent / f"{tmp_path.name}-b")  # keep only 4-pattern scenes
  (tmp_path / "dataset.json").write_text(json.dumps({"patterns": 6}))
  assert cli.main(["info", str(tmp_path)]) == 1
  assert "dataset.json declares 6 patterns; the scenes hold 4 (1 scene)" in capsys.readouterr().out


def test_info_does_not_count_a_killed_writes_leftover(tmp_path, capsys):
  """A decode or make-data killed mid-write leaves sl0/.000.tmpPID.png: not a fifth pattern."""
  from sljax.io import files
  write_scene(tmp_path / "a", _scene(0))
  write_scene(tmp_path / "b", _scene(1))
  sl0 = tmp_path / "b" / "sl0"
  files.temp_path(sl0 / "000.png").write_bytes((sl0 / "000.png").read_bytes())
  assert cli.main(["info", str(tmp_path)]) == 0
  assert "4 patterns (2 scenes)" in capsys.readouterr().out


def test_info_empty_dataset(tmp_path, capsys):
  assert cli.main(["info", str(tmp_path)]) == 2
  err = capsys.readouterr().err
  assert len(err.strip().splitlines()) == 1 and str(tmp_path) in err and "empty dataset" in err


def _drop_im1(d):
  (d / "im1.png").unlink()


def _resize_im1(d):
  cv2.imwrite(str(d / "im1.png"), np.zeros((H, W + 3, 3), np.uint8))


def _bad_pfm_header(d):
  (d / "disp0.pfm").write_bytes(b"Pf\n10 six\n-1\n" + bytes(4 * H * W))


def _calib_without_ndisp(d):
  cam = np.array([[50.0, 0, 5], [0, 50, 3], [0, 0, 1]])
  write_calib(d / "calib.txt", Calib(cam0=cam, cam1=cam, doffs=0.0, baseline=10.0, width=W,
                                     height=H, ndisp=8))
  text = (d / "calib.txt").read_text()
  (d / "calib.txt").write_text("".join(l + "\n" for l in text.splitlines()
                                       if not l.startswith("ndisp")))


def _calib_binary(d):
  (d / "calib.txt").write_bytes(b"\xff\xfe\x00garbage\n")  # was a UnicodeDecodeError traceback


def _fewer_right_patterns(d):
  (d / "sl1" / "003.png").unlink()


# Issue 2, item 6: each bad input names the scene and the file, in the library and on the CLI.
@pytest.mark.parametrize("damage, file", [
    (_drop_im1, "im1.png"), (_resize_im1, "im1.png"), (_bad_pfm_header, "disp0.pfm"),
    (_calib_without_ndisp, "calib.txt"), (_calib_binary, "calib.txt"),
    (_fewer_right_patterns, "sl1"),
], ids=["missing file", "view sizes", "pfm header", "calib key", "calib binary",
        "pattern counts"])
def test_bad_input_names_scene_and_file(tmp_path, capsys, damage, file):
  root = tmp_path / "data"
  write_scene(root / "good", _scene(0))
  write_scene(root / "broken", _scene(1))
  damage(root / "broken")
  with pytest.raises(SljaxError, match=rf"broken.*{file}") as e:
    load_scene(root / "broken")
  assert "\n" not in str(e.value)
  assert cli.main(["info", str(root)]) == 1
  out, err = capsys.readouterr()
  problems = out.split("problems (1):\n")[1].splitlines()
  assert len(problems) == 1 and "broken" in problems[0] and file in problems[0]
  assert "Traceback" not in out + err


def test_info_notes_12_bit_data_in_16_bit_files(tmp_path, capsys):
  # A 12-bit camera's values written as they are: read as value / 65535 they come out dark.
  for k in range(2):
    write_scene(tmp_path / f"s{k}", _scene(k))
    for view in ("im0.png", "im1.png"):
      im = np.full((H, W, 3), 100, np.uint16)
      im[0, 0] = 4000 + k
      cv2.imwrite(str(tmp_path / f"s{k}" / view), im)
  assert cli.main(["info", str(tmp_path)]) == 0
  out = capsys.readouterr().out
  assert (f"note:    s0/im0.png is 16-bit with values up to 4000 (12-bit data?); sljax reads "
          "16-bit PNGs as value / 65535, so it looks 16x darker than white: scale the values to "
          "the 16-bit range when writing the scenes") in out
  im = np.full((H, W, 3), 100, np.uint16)
  im[0, 0] = 60000  # the 16-bit range used: no note
  cv2.imwrite(str(tmp_path / "s0" / "im0.png"), im)
  assert cli.main(["info", str(tmp_path)]) == 0
  assert "note:" not in capsys.readouterr().out
