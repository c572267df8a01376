import json

import numpy as np
import pytest

from sljax import cli
from sljax.data.scene import Scene, write_scene

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
  assert "/ 2 groups" in split and "/ 1 groups" in split
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


def test_info_empty_dataset(tmp_path, capsys):
  assert cli.main(["info", str(tmp_path)]) == 2
  err = capsys.readouterr().err
  assert len(err.strip().splitlines()) == 1 and str(tmp_path) in err and "empty dataset" in err
