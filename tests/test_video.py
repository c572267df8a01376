"""sljax predict --video: layouts, --every, --frames, rectification with an OpenCV calibration
(for video and for pairs), and refusals that leave nothing behind.

References are independent of sljax.depth.video: frames are read back from the written video (the
codec is lossy) and split by numpy slicing, rectification is done by hand with
cv2.stereoRectify / initUndistortRectifyMap / remap, and each frame pair goes through the
pair path (the predictor called on one pair)."""

import cv2
import numpy as np
import pytest

from sljax import cli
from sljax.data.camera import read_calib, write_calib
from sljax.data.pfm import read_pfm
from sljax.depth import pairs, video
from sljax.errors import SljaxError
from sljax.io.images import image_to_float, write_image
from sljax.render.synthetic import SynthConfig, render_scene  # the renderer: one import line

from test_predict import _calib, _converted_model, read_ply

H, W, N = 64, 96, 10  # per view; frames
UNET = {"depth": 2, "base_width": 4, "in_channels": 3}
# A rig with distortion and a small rotation between the cameras; T in mm, right camera at -x.
M1 = np.array([[90.0, 0, 47.0], [0, 91.0, 31.5], [0, 0, 1]])
M2 = np.array([[92.0, 0, 49.0], [0, 92.5, 32.0], [0, 0, 1]])
D1 = np.array([[-0.08, 0.02, 0.001, -0.0005, 0.0]])
D2 = np.array([[-0.05, 0.01, -0.0008, 0.0004, 0.0]])
R = cv2.Rodrigues(np.array([0.01, -0.02, 0.005]))[0]
T = np.array([[-5.0], [0.1], [0.2]])


def _write_video(path, frames, fps=10.0):
  """frames: uint8 HxWx3 BGR, written as mp4v."""
  h, w = frames[0].shape[:2]
  writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
  assert writer.isOpened()
  for f in frames:
    writer.write(f)
  writer.release()
  return path


def _read_video(path):
  cap = cv2.VideoCapture(str(path))
  out = []
  while True:
    ok, f = cap.read()
    if not ok:
      return out
    out.append(f)


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
  """A 10-frame pan over a rendered scene, 64x96 per view, in the three layouts; the model."""
  root = tmp_path_factory.mktemp("clip")
  scene = render_scene(0, 0, SynthConfig(size=96, domain="objects", texture_amplitude=1.0))
  views = [np.rint(v[16:16 + H] * 255).astype(np.uint8)[..., ::-1] for v in (scene.im0,
                                                                              scene.im1)]
  lefts = [np.roll(views[0], 2 * i, axis=1) for i in range(N)]
  rights = [np.roll(views[1], 2 * i, axis=1) for i in range(N)]
  files = {
      "stacked": [_write_video(root / "stacked.mp4",
                               [np.concatenate([l, r], 0) for l, r in zip(lefts, rights)])],
      "side-by-side": [_write_video(root / "sbs.mp4",
                                    [np.concatenate([l, r], 1) for l, r in zip(lefts, rights)])],
      "two": [_write_video(root / "left.mp4", lefts), _write_video(root / "right.mp4", rights)],
  }
  model = _converted_model(root / "unet", "unet-disp", UNET, hw=(H, W))
  return {"root": root, "files": files, "model": model,
          "predictor": pairs.load_predictor(str(model))}


def _split_back(clip, layout):
  """(left, right) float views of every frame as decoded, split by numpy slicing."""
  if layout == "two":
    ls, rs = (_read_video(p) for p in clip["files"]["two"])
  else:
    frames = _read_video(clip["files"][layout][0])
    if layout == "stacked":
      ls, rs = [f[:H] for f in frames], [f[H:] for f in frames]
    else:
      ls, rs = [f[:, :W] for f in frames], [f[:, W:] for f in frames]
  assert len(ls) == len(rs) == N
  return [(image_to_float(l), image_to_float(r)) for l, r in zip(ls, rs)]


def _argv(clip, layout, out, *extra):
  paths = [str(p) for p in clip["files"][layout]]
  lay = [] if layout == "two" else ["--layout", layout]
  return ["predict", str(clip["model"]), "--video", *paths, *lay, "--out", str(out), *extra]


@pytest.mark.parametrize("layout", ["stacked", "side-by-side", "two"])
def test_layouts_equal_the_pair_path_on_the_split_frames(clip, tmp_path, capsys, layout):
  out = tmp_path / "out"
  assert cli.main(_argv(clip, layout, out, "--frames", "--batch", "4")) == 0
  assert "10 frames" in capsys.readouterr().out
  pairs = _split_back(clip, layout)
  assert sorted(p.name for p in (out / "frames").iterdir()) == [f"{i:06d}" for i in range(N)]
  disps = []
  for i, (l, r) in enumerate(pairs):
    want = clip["predictor"](l, r)["disparity"]  # one pair, unbatched
    got = read_pfm(out / "frames" / f"{i:06d}" / "disparity.pfm")
    np.testing.assert_allclose(got, want, atol=1e-4, rtol=1e-5)
    disps.append(got)
  # The video: a frame per predicted frame, the turbo colours of the disparity (lossy codec).
  back = _read_video(out / "disparity.mp4")
  assert len(back) == N and back[0].shape == (H, W, 3)
  import matplotlib
  first = np.stack(disps[:4])  # the first batch (--batch 4) sets the range
  lo, hi = np.percentile(first[np.isfinite(first)], [1, 99])
  rgb = matplotlib.colormaps["turbo"](np.clip((disps[3] - lo) / (hi - lo), 0, 1))[..., :3]
  mine = video.colour_map(disps[3], lo, hi)
  np.testing.assert_allclose(mine[..., ::-1] / 255.0, rgb, atol=0.04)  # a turbo LUT step
  # The codec subsamples colour: compare the frames' coarse content.
  blur = [cv2.GaussianBlur(x.astype(np.float32), (9, 9), 3) for x in (back[3], mine)]
  assert np.abs(blur[0] - blur[1]).mean() < 12
  assert not list(out.glob(".*"))  # no temporary left


def test_every_n_takes_frames_0_n_2n(clip, tmp_path):
  out = tmp_path / "out"
  assert cli.main(_argv(clip, "stacked", out, "--frames", "--every", "3")) == 0
  names = sorted(p.name for p in (out / "frames").iterdir())
  assert names == ["000000", "000003", "000006", "000009"]
  pairs = _split_back(clip, "stacked")
  for i in (0, 3, 6, 9):
    want = clip["predictor"](*pairs[i])["disparity"]
    np.testing.assert_allclose(read_pfm(out / "frames" / f"{i:06d}" / "disparity.pfm"), want,
                               atol=1e-4, rtol=1e-5)
  cap = cv2.VideoCapture(str(out / "disparity.mp4"))
  assert len(_read_video(out / "disparity.mp4")) == 4
  assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(10 / 3, rel=1e-3)


def test_calib_txt_beside_the_video_is_used_as_rectified(clip, tmp_path, capsys):
  folder = tmp_path / "rec"
  folder.mkdir()
  (folder / "v.mp4").write_bytes(clip["files"]["stacked"][0].read_bytes())
  write_calib(folder / "calib.txt", _calib(W, H))  # f 80, baseline 120 mm, doffs 2.5
  out = tmp_path / "out"
  assert cli.main(["predict", str(clip["model"]), "--video", str(folder / "v.mp4"), "--layout",
                   "stacked", "--every", "5", "--frames", "--out", str(out)]) == 0
  assert "rectified" not in capsys.readouterr().out
  pairs = _split_back(clip, "stacked")
  for i in (0, 5):
    got = read_pfm(out / "frames" / f"{i:06d}" / "disparity.pfm")
    np.testing.assert_allclose(got, clip["predictor"](*pairs[i])["disparity"], atol=1e-4,
                               rtol=1e-5)  # not rectified
    d = got.astype(np.float64) + 2.5
    depth = read_pfm(out / "frames" / f"{i:06d}" / "depth_mm.pfm")
    np.testing.assert_allclose(depth[d > 0], 80.0 * 120.0 / d[d > 0], rtol=1e-5)
  assert not (out / "frames" / "calib.txt").exists()
  write_calib(folder / "calib.txt", _calib(2 * W, H))
  assert "calib.txt: calibration is for 192x64 images, the pair is 96x64" in _one_error(
      capsys, ["predict", str(clip["model"]), "--video", str(folder / "v.mp4"), "--layout",
               "stacked", "--out", str(tmp_path / "o2")])
  assert not (tmp_path / "o2").exists()


def _write_opencv_calibration(path, size=None):
  fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
  for k, v in (("M1", M1), ("D1", D1), ("M2", M2), ("D2", D2), ("R", R), ("T", T)):
    fs.write(k, v)
  if size:
    fs.write("image_width", size[0])
    fs.write("image_height", size[1])
  fs.release()
  return path


def _by_hand(left, right, size=(W, H)):
  """Rectified views and (f, cx, cy, baseline) by OpenCV's calls, in float."""
  r1, r2, p1, p2, *_ = cv2.stereoRectify(M1, D1, M2, D2, size, R, T,
                                         flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
  views = []
  for img, m, d, rr, p in ((left, M1, D1, r1, p1), (right, M2, D2, r2, p2)):
    mx, my = cv2.initUndistortRectifyMap(m, d, rr, p, size, cv2.CV_32FC1)
    views.append(cv2.remap(np.ascontiguousarray(img, np.float32), mx, my, cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT))
  assert p2[0, 2] == p1[0, 2]  # zero disparity at infinity: doffs 0
  return views, (p1[0, 0], p1[0, 2], p1[1, 2], float(np.linalg.norm(T)))


def test_calib_rectifies_each_frame_as_opencv_by_hand(clip, tmp_path):
  cal = _write_opencv_calibration(tmp_path / "rig.yml", (W, H))
  out = tmp_path / "out"
  assert cli.main(_argv(clip, "side-by-side", out, "--frames", "--calib", str(cal),
                        "--every", "4")) == 0
  pairs = _split_back(clip, "side-by-side")
  for i in (0, 4, 8):
    (l, r), (f, cx, cy, b) = _by_hand(*pairs[i])
    want = clip["predictor"](l, r)["disparity"]
    folder = out / "frames" / f"{i:06d}"
    got = read_pfm(folder / "disparity.pfm")
    np.testing.assert_allclose(got, want, atol=1e-4, rtol=1e-5)
    unrect = clip["predictor"](*pairs[i])["disparity"]
    assert np.abs(unrect - want).max() > 0.05  # rectifying changed something
    depth = read_pfm(folder / "depth_mm.pfm").astype(np.float64)
    d64 = got.astype(np.float64)
    ok = np.isfinite(d64) & (d64 > 0)
    np.testing.assert_allclose(depth[ok], f * b / d64[ok], rtol=1e-5)
    xyz, _ = read_ply(folder / "cloud.ply")
    ys, xs = np.nonzero(ok & np.isfinite(depth))
    np.testing.assert_allclose(xyz[:, 0], (xs - cx) * depth[ys, xs] / f, rtol=1e-4, atol=1e-3)
  calib = read_calib(out / "frames" / "calib.txt")
  assert (calib.width, calib.height, calib.doffs) == (W, H, 0.0)
  assert calib.baseline == pytest.approx(np.linalg.norm(T))
  # --unit cm: T read in cm, depth in mm (x10).
  out_cm = tmp_path / "cm"
  assert cli.main(_argv(clip, "side-by-side", out_cm, "--frames", "--calib", str(cal),
                        "--every", "4", "--unit", "cm")) == 0
  np.testing.assert_allclose(read_pfm(out_cm / "frames/000004/depth_mm.pfm"),
                             10 * read_pfm(out / "frames/000004/depth_mm.pfm"), rtol=1e-6)


def test_calib_rectifies_a_pair_too(clip, tmp_path):
  cal = _write_opencv_calibration(tmp_path / "rig.npz")
  np.savez(cal, M1=M1, D1=D1, M2=M2, D2=D2, R=R, T=T)
  l8, r8 = (np.rint(v * 255).astype(np.uint8) for v in _split_back(clip, "two")[2])
  write_image(tmp_path / "l.png", l8)
  write_image(tmp_path / "r.png", r8)
  out = tmp_path / "out"
  assert cli.main(["predict", str(clip["model"]), str(tmp_path / "l.png"),
                   str(tmp_path / "r.png"), "--calib", str(cal), "--out", str(out)]) == 0
  (l, r), (f, _, _, b) = _by_hand(l8 / np.float32(255), r8 / np.float32(255))
  got = read_pfm(out / "disparity.pfm")
  np.testing.assert_allclose(got, clip["predictor"](l, r)["disparity"], atol=1e-4, rtol=1e-5)
  calib = read_calib(out / "calib.txt")
  assert calib.focal == pytest.approx(f) and calib.baseline == pytest.approx(b)
  assert (out / "cloud.ply").is_file() and (out / "depth_mm.pfm").is_file()


def _one_error(capsys, argv):
  assert cli.main(argv) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and err[0].startswith("sljax predict: error: "), err
  return err[0]


def test_bad_input_is_one_line_and_leaves_nothing(clip, tmp_path, capsys):
  out = tmp_path / "out"
  model = str(clip["model"])
  stacked = str(clip["files"]["stacked"][0])
  junk = tmp_path / "junk.mp4"
  junk.write_text("not a video")
  assert "junk.mp4: not a readable video" in _one_error(
      capsys, ["predict", model, "--video", str(junk), "--layout", "stacked", "--out", str(out)])
  assert "nope.mp4: no such video file" in _one_error(
      capsys, ["predict", model, "--video", "nope.mp4", "--layout", "stacked", "--out", str(out)])
  assert "give --layout stacked or side-by-side" in _one_error(
      capsys, ["predict", model, "--video", stacked, "--out", str(out)])
  # Odd sizes: an image sequence (the mp4 writer rounds sizes down to even).
  for i in range(3):
    cv2.imwrite(str(tmp_path / f"f_{i:02d}.png"), np.zeros((65, 97, 3), np.uint8))
  seq = str(tmp_path / "f_%02d.png")
  assert "an odd height cannot be split" in _one_error(
      capsys, ["predict", model, "--video", seq, "--layout", "stacked", "--out", str(out)])
  assert "an odd width cannot be split" in _one_error(
      capsys, ["predict", model, "--video", seq, "--layout", "side-by-side", "--out", str(out)])
  left, right = (str(p) for p in clip["files"]["two"])
  short = _write_video(tmp_path / "short.mp4", _read_video(right)[:7])
  assert "7 frames" in _one_error(
      capsys, ["predict", model, "--video", left, str(short), "--out", str(out)])
  small = _write_video(tmp_path / "small.mp4", [f[:32] for f in _read_video(right)])
  assert "frames are 96x32" in _one_error(
      capsys, ["predict", model, "--video", left, str(small), "--out", str(out)])
  assert "--layout is for one file" in _one_error(
      capsys, ["predict", model, "--video", left, right, "--layout", "stacked", "--out",
               str(out)])
  cal = _write_opencv_calibration(tmp_path / "rig.yml", (2 * W, H))
  assert "calibrated for 192x64 images" in _one_error(
      capsys, ["predict", model, "--video", stacked, "--layout", "stacked", "--calib", str(cal),
               "--out", str(out)])
  assert "--every must be a positive integer, got 0" in _one_error(
      capsys, ["predict", model, "--video", stacked, "--layout", "stacked", "--every", "0",
               "--out", str(out)])
  assert "--disp-range must be two numbers LO < HI" in _one_error(
      capsys, ["predict", model, "--video", stacked, "--layout", "stacked", "--disp-range", "5",
               "1", "--out", str(out)])
  assert "--calib " + str(tmp_path) + ": is a folder" in _one_error(
      capsys, ["predict", model, "--calib", str(cal), str(tmp_path), "--out", str(out)])
  txt = tmp_path / "calib.txt"
  txt.write_text("not read")
  assert "--unit is for an OpenCV calibration's T" in _one_error(
      capsys, ["predict", model, left, right, "--calib", str(txt), "--unit", "cm", "--out",
               str(out)])
  assert "--every is for --video" in _one_error(
      capsys, ["predict", model, left, right, "--every", "2", "--out", str(out)])
  assert not out.exists()


def test_a_failure_part_way_leaves_the_earlier_outputs(clip, tmp_path):
  out = tmp_path / "out"
  source = video.open_video(clip["files"]["stacked"], "stacked")
  traces = clip["predictor"].traces
  video.predict_video(clip["predictor"], source, out, frames=True, progress=False)
  # Batches 4, 4, 2: the last is padded to 4, so the network compiles for one batch shape.
  assert clip["predictor"].traces - traces <= 1
  before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
  calls = []

  def failing(left, right, calib=None):
    calls.append(len(left))
    if len(calls) == 2:
      raise KeyboardInterrupt
    return clip["predictor"](left, right)
  with pytest.raises(KeyboardInterrupt):
    video.predict_video(failing, source, out, frames=True, overwrite=True, progress=False)
  after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
  assert after == before  # nothing half-written, no temporary left
  fresh = tmp_path / "fresh" / "out"
  calls.clear()
  with pytest.raises(KeyboardInterrupt):
    video.predict_video(failing, source, fresh, frames=True, progress=False)
  assert not (tmp_path / "fresh").exists()
  with pytest.raises(SljaxError, match="exists"):
    video.predict_video(clip["predictor"], source, out, progress=False)
