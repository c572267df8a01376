"""Bad input refused up front, with one verdict per file (issue 62, items 2 and 5).

Images are sized from their headers before anything decodes them (a PNG whose IHDR claims
60000x60000 is one line, never OpenCV's assertion), and decoded whole by `info --check` and the
training pre-flight (a zlib stream broken behind valid CRCs). The loader, the pre-flight and
`info` share one set of verdicts (sljax.data.checks, camera.read_calib): disparities of the
wrong sign, beyond the width or with nothing usable, and calibrations that give no depth are
refused by `info --check` in the words training, show and evaluate use. Every damaged input is
a real file written into tmp_path."""

import math
import struct
import time
import zlib

import cv2
import numpy as np
import pytest

from sljax import cli
from sljax.capture import frames
from sljax.data import preflight
from sljax.data.camera import Calib, read_calib, write_calib
from sljax.data.dataset import FolderSource
from sljax.data.pfm import write_pfm
from sljax.data.scene import Scene, load_scene, write_scene
from sljax.errors import SljaxError
from sljax.evaluation.scoring import evaluate
from sljax.inference.sgbm import SGBMPredictor
from sljax.io import headers
from sljax.io.images import read_image
from sljax.train import loop
from sljax.train.config import TrainConfig

import toys

H, W = 32, 32


@pytest.fixture(autouse=True)
def cache_dir(tmp_path, monkeypatch):
  monkeypatch.setenv("SLJAX_CACHE_DIR", str(tmp_path / "cache"))
  return tmp_path / "cache"


def _scene(k: int) -> Scene:
  rng = np.random.default_rng(k)
  return Scene(name=str(k), im0=rng.uniform(size=(H, W, 3)).astype(np.float32),
               im1=rng.uniform(size=(H, W, 3)).astype(np.float32),
               disp0=rng.uniform(1, 8, (H, W)).astype(np.float32),
               sl0=rng.integers(0, 2, (H, W, 4)).astype(np.float32),
               sl1=rng.integers(0, 2, (H, W, 4)).astype(np.float32), meta={"group": f"g{k}"})


def _dataset(root, n: int = 4):
  for k in range(n):
    write_scene(root / f"s{k}", _scene(k))
  return root


def _chunk(kind: bytes, body: bytes) -> bytes:
  return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _png(width: int, height: int, idat: bytes) -> bytes:
  """A PNG (8-bit RGB) of the given IHDR size and IDAT bytes, every CRC valid."""
  ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
  return (headers.PNG_SIGNATURE + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat)
          + _chunk(b"IEND", b""))


HUGE = _png(60000, 60000, zlib.compress(b"\0" * 64))  # 10.8 GB of pixels claimed, 100 bytes


def _broken_zlib(width: int, height: int) -> bytes:
  """A PNG whose image data is one stored deflate block with a wrong length check (NLEN), behind
  valid CRCs: only inflating the data finds it."""
  raw = b"".join(b"\0" + bytes(range(3 * width)) for _ in range(height))[:65535]
  block = b"\x01" + struct.pack("<HH", len(raw), len(raw))  # final stored block, NLEN broken
  return _png(width, height, b"\x78\x01" + block + raw + struct.pack(">I", zlib.adler32(raw)))


def _no_decoding(monkeypatch):
  """Any decode by OpenCV fails the test: the refusal must come from the header."""
  for name in ("imread", "imdecode"):
    monkeypatch.setattr(cv2, name, lambda *a, **k: pytest.fail("decoded before the size check"))


def _error_lines(err: str) -> list[str]:
  """stderr's lines, less a progress bar's (drawn and cleared with carriage returns)."""
  return [line for line in err.replace("\r", "\n").splitlines()
          if line.strip() and "scene/s]" not in line and "it/s]" not in line]


def _one_error_line(capsys, argv, command: str) -> str:
  assert cli.main(argv) == 2
  err = capsys.readouterr().err
  lines = _error_lines(err)
  assert "Traceback" not in err and len(lines) == 1, err
  assert lines[0].startswith(f"sljax {command}: error: "), err
  return lines[0]


# ----------------------------------------------------------------------------- item 2


def test_headers_give_opencvs_sizes(tmp_path):
  rng = np.random.default_rng(0)
  for shape, dtype in (((37, 53), np.uint8), ((21, 19, 3), np.uint16), ((5, 300, 4), np.uint8)):
    img = rng.integers(0, 255, shape).astype(dtype)
    for ext in (".png", ".jpg", ".bmp", ".tif"):
      path = tmp_path / f"a{ext}"
      assert cv2.imwrite(str(path), img)
      assert headers.image_size(path) == (shape[1], shape[0]), ext
      if ext == ".png":
        assert headers.png_check(path.read_bytes()) == (shape[1], shape[0], 8 * img.itemsize)
  cv2.imwrite(str(tmp_path / "g.pgm"), rng.integers(0, 255, (7, 9)).astype(np.uint8))
  assert headers.image_size(tmp_path / "g.pgm") == (9, 7)


def test_a_huge_header_is_refused_before_decoding(tmp_path, monkeypatch):
  path = tmp_path / "huge.png"
  path.write_bytes(HUGE)
  _no_decoding(monkeypatch)
  start = time.perf_counter()
  with pytest.raises(SljaxError) as e:
    read_image(path)
  assert time.perf_counter() - start < 1.0
  assert str(e.value) == (f"{path}: its header claims 60000x60000 pixels (3600 megapixels), "
                          "more than sljax reads (268 megapixels)")
  with pytest.raises(SljaxError, match="claims 60000x60000"):
    frames.read_frame(path)  # import-captures' reader
  with pytest.raises(ValueError, match="claims 60000x60000"):
    preflight.image_check(path)
  # A JPEG, TIFF or BMP header claiming as much is refused alike.
  jpeg = tmp_path / "huge.jpg"
  ok, buf = cv2.imencode(".jpg", np.zeros((8, 8), np.uint8))
  data = bytearray(buf.tobytes())
  sof = data.index(b"\xff\xc0")
  data[sof + 5:sof + 9] = struct.pack(">HH", 60000, 60000)
  jpeg.write_bytes(bytes(data))
  with pytest.raises(SljaxError, match="claims 60000x60000"):
    read_image(jpeg)


def test_a_view_of_another_size_is_refused_before_decoding(tmp_path, monkeypatch):
  root = _dataset(tmp_path / "data", 1)
  (root / "s0" / "im1.png").write_bytes(HUGE)
  real = cv2.imread
  monkeypatch.setattr(cv2, "imread", lambda p, *a: pytest.fail("decoded im1") if "im1" in str(p)
                      else real(p, *a))
  with pytest.raises(SljaxError, match=f"{root / 's0' / 'im1.png'}: its header claims"):
    load_scene(root / "s0")
  # Within the limit but not the scene's size: named against im0.png, still undecoded.
  (root / "s0" / "im1.png").write_bytes(_png(W + 1, H, zlib.compress(b"\0" * 10)))
  with pytest.raises(SljaxError, match=rf"im1.png: size {W + 1}x{H} differs from im0.png "):
    load_scene(root / "s0")


@pytest.mark.parametrize("command", ["info", "show", "predict", "evaluate"])
def test_every_command_names_the_huge_image(tmp_path, capsys, command):
  root = _dataset(tmp_path / "data", 2)
  victim = root / "s1" / ("im1.png" if command != "info" else "im0.png")
  victim.write_bytes(HUGE)
  argv = {"info": ["info", str(root), "--check"],
          "show": ["show", str(root / "s1"), "--out", str(tmp_path / "o.png")],
          "predict": ["predict", "sgbm", str(root / "s1" / "im0.png"), str(root / "s1" / "im1.png"),
                      "--out", str(tmp_path / "o")],
          "evaluate": ["evaluate", "sgbm", str(root), "--out", str(tmp_path / "o")]}[command]
  if command == "info":  # the bad scene on stdout, the count as the error line
    assert cli.main(argv) == 2
    out, err = capsys.readouterr()
    assert out.strip() == f"{victim}: its header claims 60000x60000 pixels (3600 megapixels), " \
                          "more than sljax reads (268 megapixels)"
    assert _error_lines(err) == [f"sljax info: error: {root}: 1 bad scene of 2"]
    return
  err = _one_error_line(capsys, argv, command)
  assert f"{victim}: its header claims 60000x60000 pixels" in err


def test_a_broken_zlib_stream_is_named_by_info_check_and_the_preflight(tmp_path, capsys):
  root = _dataset(tmp_path / "data")
  victim = root / "s2" / "im1.png"
  victim.write_bytes(_broken_zlib(W, H))
  assert cv2.imread(str(victim)) is None  # what the loader would meet, epochs in
  headers.png_chunks(victim.read_bytes())  # every chunk and CRC is intact
  assert cli.main(["info", str(root), "--check"]) == 2
  out, err = capsys.readouterr()
  assert out.strip() == (f"{victim}: corrupt: the image data does not inflate (Error -3 while "
                         "decompressing data: invalid stored block lengths) after 0 of "
                         f"{H * (1 + 3 * W)} bytes")
  assert _error_lines(err) == [f"sljax info: error: {root}: 1 bad scene of 4"]
  with pytest.raises(SljaxError, match=f"{victim}: corrupt: the image data does not inflate"):
    preflight.check(FolderSource(root), [(range(4), {"im"})], progress=False)
  # Too little data and an unknown row filter are named too.
  short = _png(W, H, zlib.compress(b"\0" * (1 + 3 * W)))
  with pytest.raises(ValueError, match=f"ends after {1 + 3 * W} of {H * (1 + 3 * W)} bytes"):
    headers.png_check(short)
  with pytest.raises(ValueError, match="row 1 has filter type 9"):
    headers.png_check(_png(W, H, zlib.compress(b"".join(
        bytes([9 if y == 1 else 0]) + b"\0" * 3 * W for y in range(H)))))


def test_training_names_a_broken_zlib_stream_before_its_first_step(tmp_path, monkeypatch):
  monkeypatch.setattr(loop, "compiled_steps", toys.tiny_steps)
  root = _dataset(tmp_path / "data", 6)
  victim = root / "s4" / "im0.png"
  victim.write_bytes(_broken_zlib(W, H))
  monkeypatch.setattr(loop, "create_train_state",
                      lambda *a: pytest.fail("training started before the data check"))
  cfg = TrainConfig(data=str(root), size=(32, 32), maxdisp=16, epochs=1, batch_size=2,
                    preset="quick")
  with pytest.raises(SljaxError, match=f"{victim}: corrupt: the image data does not inflate"):
    loop.train(cfg, tmp_path / "w", log=lambda line: None, progress=False)


# ----------------------------------------------------------------------------- item 5


def _check_line(capsys, root) -> str:
  """The one bad line `info --check` prints (exit 2)."""
  assert cli.main(["info", str(root), "--check", "--no-cache"]) == 2
  out, err = capsys.readouterr()
  assert "Traceback" not in err and len(_error_lines(err)) == 1, err
  return out.strip()


def test_wrong_sign_is_refused_by_check_as_training_refuses_it(tmp_path, capsys, monkeypatch):
  root = _dataset(tmp_path / "data", 6)
  victim = root / "s3" / "disp0.pfm"
  write_pfm(victim, -_scene(3).disp0)
  line = _check_line(capsys, root)
  assert line.startswith(f"{victim}: 100% of its known disparities are negative;")
  with pytest.raises(SljaxError) as loaded:
    load_scene(root / "s3")
  assert str(loaded.value).endswith(line.split(": ", 1)[1])  # the loader's words
  monkeypatch.setattr(loop, "compiled_steps", toys.tiny_steps)
  cfg = TrainConfig(data=str(root), size=(32, 32), maxdisp=16, epochs=1, batch_size=2,
                    preset="quick")
  with pytest.raises(SljaxError) as trained:
    loop.train(cfg, tmp_path / "w", log=lambda line: None, progress=False)
  assert str(trained.value).startswith(line)


@pytest.mark.parametrize("f, baseline", [(0.0, 100.0), (100.0, 0.0), (100.0, -5.0),
                                         (float("nan"), 100.0), (100.0, float("nan"))])
def test_a_calibration_without_depth_is_refused_by_check_show_and_evaluate(
    tmp_path, capsys, f, baseline):
  root = _dataset(tmp_path / "data", 2)
  cam = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
  victim = root / "s1" / "calib.txt"
  write_calib(victim, Calib(cam0=cam, cam1=cam, doffs=0.0, baseline=baseline, width=W,
                            height=H, ndisp=16))
  line = _check_line(capsys, root)
  assert line.startswith(f"{victim}: calibration needs a positive focal length and baseline")
  with pytest.raises(SljaxError) as loaded:
    load_scene(root / "s1")
  assert str(loaded.value) == line
  for command, argv in (("show", ["show", str(root / "s1"), "--out", str(tmp_path / "o.png")]),
                        ("evaluate", ["evaluate", "sgbm", str(root), "--out",
                                      str(tmp_path / "e")])):
    assert _one_error_line(capsys, argv, command).endswith(line)


def test_a_nan_doffs_is_refused(tmp_path):
  path = tmp_path / "calib.txt"
  path.write_text("cam0=[100 0 16; 0 100 16; 0 0 1]\ncam1=[100 0 16; 0 100 16; 0 0 1]\n"
                  "doffs=nan\nbaseline=100\nwidth=32\nheight=32\nndisp=16\n")
  with pytest.raises(SljaxError, match="not a finite number"):
    read_calib(path)


@pytest.mark.parametrize("value", [np.nan, 1e30])
def test_disparities_with_nothing_usable_are_refused(tmp_path, capsys, monkeypatch, value):
  root = _dataset(tmp_path / "data", 6)
  for k in range(6):
    write_pfm(root / f"s{k}" / "disp0.pfm", np.full((H, W), value, np.float32))
  if math.isnan(value):  # every value unknown: the dataset as a whole has nothing to learn
    assert cli.main(["info", str(root), "--check"]) == 2
    out, err = capsys.readouterr()
    assert out.strip() == (f"{root}: none of the 6 disparity map(s) holds a usable disparity "
                           "(all are unknown (inf or NaN) or out of range); training would learn "
                           "nothing from them and validation report no error")
    assert _error_lines(err) == [f"sljax info: error: {root}: no usable disparity"]
  else:  # every value beyond the width: each file is refused
    out = _check_line(capsys, root).splitlines()
    assert out[0] == (f"{root / 's0' / 'disp0.pfm'}: 100% of its known disparities are more "
                      f"than {W} px, the image's width (no match lies that far; unknown pixels "
                      "must be inf or NaN, not a large number)")
  monkeypatch.setattr(loop, "compiled_steps", toys.tiny_steps)
  monkeypatch.setattr(loop, "create_train_state",
                      lambda *a: pytest.fail("training started before the data check"))
  cfg = TrainConfig(data=str(root), size=(32, 32), maxdisp=16, epochs=1, batch_size=2,
                    preset="quick")
  with pytest.raises(SljaxError, match="usable disparity" if math.isnan(value) else
                     "more than 32 px, the image's width"):
    loop.train(cfg, tmp_path / "w", log=lambda line: None, progress=False)
  # One scene with usable disparities is enough: the rest are unknown, not wrong.
  write_scene(root / "s0", _scene(0), overwrite=True)
  if math.isnan(value):
    assert cli.main(["info", str(root), "--check"]) == 0


def test_evaluate_refuses_a_mean_error_no_disparity_can_have(tmp_path, capsys):
  root = tmp_path / "data"
  scene = _scene(0)
  scene.disp0[:4] = 1e30  # a few truth pixels: the file passes, the score would be 1e29 px
  write_scene(root / "s0", scene)
  err = _one_error_line(capsys, ["evaluate", "sgbm", str(root), "--out", str(tmp_path / "o")],
                        "evaluate")
  assert err.startswith(f"sljax evaluate: error: scene {root / 's0'}: the mean absolute error "
                        "would be ")
  assert f"disp0.pfm holds {4 * W} known disparities beyond the image's width" in err
  # A prediction that is nowhere finite: MAE NaN, named as the prediction's.
  write_scene(root / "s0", _scene(0), overwrite=True)
  blind = SGBMPredictor()
  nan_predictor = lambda left, right, calib=None: {
      "disparity": np.full(left.shape[:2], np.nan, np.float32)}
  for attr in ("model_name", "is_sl", "mode", "describe"):
    setattr(nan_predictor, attr, getattr(blind, attr))
  with pytest.raises(SljaxError, match=r"the mean absolute error would be nan px: the "
                     "prediction is not finite wherever the truth is known"):
    evaluate(nan_predictor, FolderSource(root), progress=False)
