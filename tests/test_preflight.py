"""The pre-flight data check: every file a run reads, checked before its first step (PNG chunk
structure and CRCs, PFM headers and sizes, calib.txt, shapes, pattern counts), cached by size
and mtime outside the dataset, and `sljax info --check`."""

import json
import zlib

import cv2
import numpy as np
import pytest

from sljax import cli
from sljax.data import preflight
from sljax.data.camera import Calib, write_calib
from sljax.data.dataset import FolderSource
from sljax.data.pfm import write_pfm
from sljax.data.scene import Scene, write_scene
from sljax.errors import SljaxError
from sljax.train import loop
from sljax.train.config import TrainConfig
from sljax.train.setup import setup
from sljax.train.workdir import METRICS_FILE

import toys

H, W = 32, 32


@pytest.fixture(autouse=True)
def cache_dir(tmp_path, monkeypatch):
  monkeypatch.setenv("SLJAX_CACHE_DIR", str(tmp_path / "cache"))
  return tmp_path / "cache"


def _scene(k: int, t: int = 4) -> Scene:
  rng = np.random.default_rng(k)
  disp = rng.uniform(1, 8, (H, W)).astype(np.float32)
  return Scene(name=str(k), im0=rng.uniform(size=(H, W, 3)).astype(np.float32),
               im1=rng.uniform(size=(H, W, 3)).astype(np.float32), disp0=disp,
               sl0=rng.integers(0, 2, (H, W, t)).astype(np.float32),
               sl1=rng.integers(0, 2, (H, W, t)).astype(np.float32),
               meta={"group": f"g{k}"})


def _dataset(root, n: int = 8):
  for k in range(n):
    write_scene(root / f"s{k}", _scene(k))
  return root


def _snapshot(root):
  return {p: (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*")}


def _png(img) -> bytes:
  ok, buf = cv2.imencode(".png", img)
  assert ok
  return buf.tobytes()


def test_png_check_against_opencv():
  """Intact PNGs give OpenCV's size and depth; truncation and a flipped byte inside the image
  data are caught (OpenCV cannot decode either, or decodes wrong pixels)."""
  rng = np.random.default_rng(0)
  for img, depth in ((rng.integers(0, 255, (H, W + 3, 3), dtype=np.uint8), 8),
                     (rng.integers(0, 65535, (H, W), dtype=np.uint16), 16)):
    data = _png(img)
    assert preflight.png_check(data) == (W + 3 if img.ndim == 3 else W, H, depth)
  data = _png(rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
  with pytest.raises(ValueError, match="truncated"):
    preflight.png_check(data[:len(data) // 2])
  idat = data.index(b"IDAT")
  flipped = bytearray(data)
  flipped[idat + 20] ^= 0x40
  with pytest.raises(ValueError, match="CRC"):
    preflight.png_check(bytes(flipped))
  with pytest.raises(ValueError, match="not a PNG"):
    preflight.png_check(b"GIF89a" + data[6:])
  # A CRC the check computes must be zlib's over the chunk type and data (the PNG spec).
  ihdr_len = int.from_bytes(data[8:12], "big")
  crc = int.from_bytes(data[16 + ihdr_len:20 + ihdr_len], "big")
  assert crc == zlib.crc32(data[12:16 + ihdr_len])


def test_pfm_check(tmp_path):
  write_pfm(tmp_path / "d.pfm", np.zeros((H, W), np.float32))
  assert preflight.pfm_check(tmp_path / "d.pfm") == (W, H, 1)
  data = (tmp_path / "d.pfm").read_bytes()
  (tmp_path / "t.pfm").write_bytes(data[:-5])
  with pytest.raises(ValueError, match="truncated"):
    preflight.pfm_check(tmp_path / "t.pfm")
  (tmp_path / "x.pfm").write_bytes(b"P5\n" + data[3:])
  with pytest.raises(ValueError, match="not a PFM"):
    preflight.pfm_check(tmp_path / "x.pfm")


@pytest.mark.parametrize("damage, where, problem", [
    ("truncate", "s3/im0.png", "truncated"),
    ("truncate", "s5/sl1/002.png", "truncated"),
    ("truncate", "s2/disp0.pfm", "truncated"),
    ("empty", "s1/im1.png", "empty file (0 bytes)"),  # cv2.imdecode asserted on it
    ("garbage", "s0/sl0/001.png", "not a readable image"),
    ("delete", "s6/disp0.pfm", "missing"),
    ("resize", "s1/im1.png", "differs from im0.png"),
    ("patterns", "s4", "holds 3 patterns"),
    ("calib", "s7/calib.txt", "calibration lacks"),
])
def test_bad_file_is_named(tmp_path, damage, where, problem):
  root = _dataset(tmp_path / "data")
  for k in range(8):
    write_calib(root / f"s{k}" / "calib.txt", Calib(cam0=np.eye(3), cam1=np.eye(3), doffs=0.0,
                                                    baseline=1.0, width=W, height=H, ndisp=16))
  path = root / where
  if damage == "truncate":
    path.write_bytes(path.read_bytes()[:-20])
  elif damage == "delete":
    path.unlink()
  elif damage in ("empty", "garbage"):
    path.write_bytes(b"" if damage == "empty" else b"not an image")
  elif damage == "resize":
    cv2.imwrite(str(path), np.zeros((H, W + 16, 3), np.uint8))
  elif damage == "patterns":
    for v in ("sl0", "sl1"):
      (path / v / "003.png").unlink()
  else:
    path.write_text("cam0=[1 0 0; 0 1 0; 0 0 1]\n")
  src = FolderSource(root)
  parts = {"im", "disp", "sl", "calib"}
  with pytest.raises(SljaxError) as info:
    preflight.check(src, [(range(8), parts)], progress=False)
  msg = str(info.value)
  assert "\n" not in msg and problem in msg
  assert str(root / (where if damage != "patterns" else where + "/sl0")) in msg
  # Parts a run does not read are not checked (a run without disparity targets).
  if where.endswith("disp0.pfm"):
    preflight.check(src, [(range(8), {"im", "sl"})], progress=False)


def test_scenes_disagreeing_with_dataset_json_are_named(tmp_path):
  """dataset.json's "patterns" sizes the experiment plans' networks: scenes holding another
  count are caught before training, even when they all agree with each other."""
  root = _dataset(tmp_path / "data", n=3)
  t = FolderSource(root)[0].sl0.shape[-1]
  (root / "dataset.json").write_text(json.dumps({"patterns": t + 1}))
  with pytest.raises(SljaxError) as info:
    preflight.check(FolderSource(root), [(range(3), {"im", "sl"})], progress=False)
  assert str(info.value) == (f"{root / 's0' / 'sl0'}: holds {t} patterns, "
                             f"{root / 'dataset.json'} declares {t + 1} (and 2 more bad "
                             "scene(s)); checked before training, nothing was run")
  (root / "dataset.json").write_text(json.dumps({"patterns": t}))
  preflight.check(FolderSource(root), [(range(3), {"im", "sl"})], progress=False)
  # A stray file beside the planes is not a pattern (the loader reads 000.png, 001.png, ...).
  (root / "dataset.json").unlink()
  (root / "s0" / "sl0" / "000_old.png").write_bytes((root / "s0" / "sl0" / "000.png").read_bytes())
  preflight.check(FolderSource(root), [(range(3), {"im", "sl"})], progress=False)
  # Without dataset.json, the first scene sets the count, and the message says so.
  for v in ("sl0", "sl1"):
    (root / "s2" / v / f"{t - 1:03d}.png").unlink()
  with pytest.raises(SljaxError, match=rf"s2/sl0: holds {t - 1} patterns, scene s0 holds {t};"
                     ) as info:
    preflight.check(FolderSource(root), [(range(3), {"im", "sl"})], progress=False)
  assert "dataset.json" not in str(info.value)


def test_cache_skips_unchanged_files_and_never_writes_the_dataset(tmp_path, cache_dir,
                                                                   monkeypatch):
  root = _dataset(tmp_path / "data")
  before = _snapshot(root)
  src = FolderSource(root)
  jobs = [(range(6), {"im", "sl"}), (range(6, 8), {"im", "sl", "disp"})]
  assert preflight.check(src, jobs, progress=False) == {"scenes": 8, "cached": 0}
  assert _snapshot(root) == before
  assert list(cache_dir.rglob("*.json")) == [preflight.cache_file(root)]
  reads = []
  real = preflight.image_check
  monkeypatch.setattr(preflight, "image_check", lambda p: reads.append(p) or real(p))
  assert preflight.check(src, jobs, progress=False) == {"scenes": 8, "cached": 8}
  assert reads == []  # nothing read a second time
  # A changed file (new size and mtime) is checked again; so is a scene asked for more parts.
  bad = root / "s2" / "im0.png"
  bad.write_bytes(bad.read_bytes()[:-20])
  with pytest.raises(SljaxError, match=f"{bad}: truncated"):
    preflight.check(src, jobs, progress=False)
  assert reads == [bad]  # only the changed scene, up to its bad file
  reads.clear()
  preflight.check(src, [(range(2), {"im", "sl"})], progress=False)
  assert reads == []
  preflight.check(src, [(range(2), {"im", "disp"})], progress=False)
  assert {p.parent.name for p in reads} == {"s0", "s1"}


def test_info_check(tmp_path, capsys):
  root = _dataset(tmp_path / "data", 4)
  assert cli.main(["info", str(root), "--check"]) == 0
  assert "all 4 scenes readable" in capsys.readouterr().out
  for k in (1, 3):
    p = root / f"s{k}" / "sl0" / "001.png"
    p.write_bytes(p.read_bytes()[:30])
  assert cli.main(["info", str(root), "--check"]) == 2
  out, err = capsys.readouterr()
  assert out.splitlines() == [f"{root / f's{k}' / 'sl0' / '001.png'}: truncated: chunk IHDR at "
                              "byte 8 needs 33 bytes, the file has 30" for k in (1, 3)]
  assert err.strip().splitlines()[-1] == f"sljax info: error: {root}: 2 bad scenes of 4"


def test_training_stops_before_its_first_step(tmp_path, monkeypatch):
  """A corrupt validation image ends `train` before anything is compiled or run."""
  monkeypatch.setattr(loop, "compiled_steps", toys.tiny_steps)
  root = _dataset(tmp_path / "data", 10)
  cfg = TrainConfig(data=str(root), size=(32, 32), maxdisp=16, epochs=1, batch_size=2,
                    preset="quick")
  run = setup(cfg, tmp_path / "probe", False, False, lambda line: None)
  victim = root / f"s{run.val_idx[-1]}" / "im0.png"
  victim.write_bytes(victim.read_bytes()[:-20])
  monkeypatch.setattr(loop, "create_train_state",
                      lambda *a: pytest.fail("training started before the data check"))
  with pytest.raises(SljaxError, match=f"{victim}: truncated"):
    loop.train(cfg, tmp_path / "w", log=lambda line: None, progress=False)
  assert not (tmp_path / "w" / METRICS_FILE).exists()


def test_a_bad_file_is_named_before_any_tuning_or_compiling(tmp_path, monkeypatch, capsys):
  """A 24-scene folder with one corrupt im0.png, on a CPU kind with empty tuning and pre-flight
  caches (the cache_dir fixture): `train` names the file and stops before it tunes XLA's
  settings (minutes on a new CPU kind) or compiles anything."""
  from sljax.runtime import choices, measuring
  monkeypatch.delenv("SLJAX_TUNE", raising=False)
  assert choices.enabled(None) and choices.measured_choice() is None  # a first run on this CPU kind
  tuned = []
  monkeypatch.setattr(measuring, "measure", lambda *a, **k: tuned.append(1) or pytest.fail("tuned"))
  monkeypatch.setattr(loop, "compiled_steps",
                      lambda *a, **k: pytest.fail("compiled before the data check"))
  root = _dataset(tmp_path / "data", 24)
  victim = root / "s17" / "im0.png"
  victim.write_bytes(victim.read_bytes()[:-20])
  assert cli.main(["train", "--data", str(root), "--size", "32", "--maxdisp", "16",
                   "--batch-size", "2", "--epochs", "1", "--ynn", "auto",
                   "--workdir", str(tmp_path / "w")]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert f"{victim}: truncated" in err[-1] and not tuned
  assert not (tmp_path / "w" / "config.json").exists()


def test_one_pattern_rule_for_info_and_the_preflight_check():
  """dataset.json's count where it declares one (0 included), else the first scene's; `sljax
  info` flags exactly the datasets the pre-flight check refuses."""
  from sljax.commands.info import _pattern_problems
  assert preflight.expected_patterns(None, [4, 6, 4]) == 4
  assert preflight.expected_patterns(6, [4]) == 6 and preflight.expected_patterns(0, [4]) == 0
  assert preflight.expected_patterns(None, []) is None
  for declared, counts in ((None, [4, 4]), (None, [4, 5]), (6, [6, 6]), (6, [6, 4]), (4, [])):
    refused = any(t != preflight.expected_patterns(declared, counts) for t in counts)
    assert bool(_pattern_problems(counts, declared)) == refused, (declared, counts)
