"""`sljax import-captures` on an unrectified rendered rig (sljax.render.synth_rig): the renderer's
rectified scene, warped into two real cameras (known rotations and lens distortion) with their
OpenCV calibration, captured in OpenCV's GrayCodePattern layout; the ground truth mapped into
the importer's own rectified frame in float64."""

import dataclasses
import json
import math
import shutil
import types
from pathlib import Path

import cv2
import numpy as np
import pytest

from sljax import cli
from sljax.capture import captures, charuco
from sljax.capture import rig as rigs
from sljax.capture.frames import bit_counts, frame_number, opencv_roles, projector_frames
from sljax.data import preflight
from sljax.data.camera import read_calib
from sljax.data.dataset import FolderSource, load_batch
from sljax.data.pfm import read_pfm
from sljax.data.scene import load_scene
from sljax.render import synth_rig as sr
from sljax.render.synthetic import SynthConfig, render_scene
from sljax.errors import SljaxError
from sljax.sl import codes
from sljax.sl.stereo import decode_views, match_views

RENDER = SynthConfig(size=256, domain="objects", t=9, raw_noise=0.0, raw_blur=0.0)
OVERSAMPLE = 2  # the rectified frames are 128 px, rendered at 256 and area-averaged
RIG = sr.RigConfig(size=(128, 96), projector=(160, 120))  # W, H not powers of two
DEGRADED = sr.Degradation(blur_px=1.0, global_light=0.3, offset=0.1, noise=0.01, saturated=0.03,
                          seed=1)
PROJ = "160x120"


@pytest.fixture(scope="module")
def rendered():
  """The rendered scene, the rig's calibration, the importer's rectification and the ground
  truth in it."""
  cfg = RENDER.resolved()
  scene = render_scene(0, 0, cfg, raw=True)
  k_rect = sr.rectified_intrinsics(cfg, OVERSAMPLE)
  cal = sr.calibration(RIG, k_rect, cfg.baseline_m * 1000.0)  # T in mm
  rect = rigs.rectify(cal, RIG.size)
  gt = sr.ground_truth(scene, cfg, RIG, rect, OVERSAMPLE)
  clean = sr.real_captures(scene, cfg, RIG, OVERSAMPLE)
  return types.SimpleNamespace(scene=scene, cfg=cfg, k_rect=k_rect, cal=cal, rect=rect, gt=gt,
                               clean=clean)


def _write(folder, frames, name="pattern_cam1_im{}.png", start=1, convert=lambda f: f):
  """Frames written as numbered files (numbers from start)."""
  folder.mkdir(parents=True, exist_ok=True)
  for i, f in enumerate(frames):
    assert cv2.imwrite(str(folder / name.format(i + start)), convert(f))
  return folder


@pytest.fixture(scope="module")
def capture(rendered, tmp_path_factory):
  """The clean capture in OpenCV's sample naming (1-based) and its calibration YAML."""
  root = tmp_path_factory.mktemp("capture")
  _write(root / "cam1", rendered.clean[0])
  _write(root / "cam2", rendered.clean[1], "pattern_cam2_im{}.png")
  rigs.write_calibration(root / "calib.yml", rendered.cal)
  return root


def _import(args, capsys=None):
  rc = cli.main(["import-captures", *map(str, args)])
  out = capsys.readouterr() if capsys is not None else None
  return rc, out


def _accuracy(scene_dir, gt):
  """Per view: (share of ground-truth pixels with a disparity, share of those within 1 px,
  within 0.5 px)."""
  out = []
  for view in (0, 1):
    est = read_pfm(scene_dir / f"disp{view}.pfm")
    known = np.isfinite(gt[view])
    valid = known & np.isfinite(est)
    err = np.abs(est[valid] - gt[view][valid])
    out.append((valid.sum() / known.sum(), (err <= 1).mean(), (err <= 0.5).mean()))
  return out


# --- the OpenCV layout -----------------------------------------------------------------------


def _opencv_generate(width, height):
  """A line-by-line port of OpenCV's GrayCodePattern_Impl::generate (structured_light module):
  the column images, then the row images, each followed by its inverse; 255 lit."""
  n = math.ceil(math.log(width) / math.log(2))
  m = math.ceil(math.log(height) / math.log(2))
  pattern = [np.zeros((height, width), np.uint8) for _ in range(2 * n + 2 * m)]
  for j in range(width):
    num, prev = j, j % 2
    for k in range(n):
      num //= 2
      rem = num % 2
      flag = 1 if (rem == 0 and prev == 1) or (rem == 1 and prev == 0) else 0
      pattern[2 * n - 2 * k - 2][:, j] = flag * 255
      pattern[2 * n - 2 * k - 1][:, j] = 0 if flag else 255
      prev = rem
  for i in range(height):
    num, prev = i, i % 2
    for k in range(m):
      num //= 2
      rem = num % 2
      flag = 1 if (rem == 0 and prev == 1) or (rem == 1 and prev == 0) else 0
      pattern[2 * m - 2 * k + 2 * n - 2][i, :] = flag * 255
      pattern[2 * m - 2 * k + 2 * n - 1][i, :] = 0 if flag else 255
      prev = rem
  return pattern


@pytest.mark.parametrize("projector", [(13, 6), (160, 120), (64, 32)])
def test_opencv_layout_is_sljax_gray_code(projector):
  """Column pair k of OpenCV's generator is sljax's Gray pattern k (coarsest first), row pair j
  the same code down the rows; 2n + 2m frames before white and black (46 for 1920x1080)."""
  w, h = projector
  frames = _opencv_generate(w, h)
  roles = opencv_roles(projector)
  n, m = bit_counts(projector)
  assert len(frames) + 2 == len(roles) == 2 * n + 2 * m + 2
  assert roles[-2:] == ["white", "black"]
  cols, rows = codes.patterns("gray", w), codes.patterns("gray", h)
  for frame, role in zip(frames, roles):
    bit = int(role[-3:])
    want = (cols[bit][None, :] if not role.startswith("r") else rows[bit][:, None])
    if role[-4] == "i":
      want = 1 - want
    np.testing.assert_array_equal(frame, np.broadcast_to(want * 255, (h, w)), err_msg=role)
  projected = list(projector_frames(projector))
  assert [r for r, _ in projected] == roles
  for (role, image), frame in zip(projected, frames + [np.full((h, w), 255), np.zeros((h, w))]):
    np.testing.assert_array_equal(image, frame, err_msg=role)
  assert len(opencv_roles((1920, 1080))) == 46
  assert opencv_roles((1920, 1080))[44:] == ["white", "black"]


def test_decoding_opencv_frames_gives_every_projector_column_and_row():
  """A camera that sees the projector's own image: every pixel decodes to its column and row
  (W, H not powers of two; codes beyond them are impossible)."""
  w, h = 150, 40
  frames = _opencv_generate(w, h) + [np.full((h, w), 255, np.uint8), np.zeros((h, w), np.uint8)]
  named = dict(zip(opencv_roles((w, h)), frames))
  cols = {k: v for k, v in named.items() if not k.startswith("r")}
  rows = {"white": named["white"], "black": named["black"],
          **{k[1:]: v for k, v in named.items() if k.startswith("r")}}
  dec = decode_views(cols, cols, "gray", projector=(w, h), rows=(rows, rows))
  np.testing.assert_array_equal(dec.left.column, np.broadcast_to(np.arange(w), (h, w)))
  np.testing.assert_array_equal(dec.rows[0], np.broadcast_to(np.arange(h)[:, None], (h, w)))
  match_views(dec)
  np.testing.assert_array_equal(dec.disp0, np.zeros((h, w)))  # one image twice: disparity 0


# --- the rig's geometry, in float64 ----------------------------------------------------------


def test_rig_geometry_agrees_with_opencv(rendered):
  """The warp, the calibration and the ground-truth mapping agree with OpenCV's own projection
  and triangulation: a real pixel's rectified point, projected by cv2.projectPoints with the
  rig's calibration, lands on that pixel in both cameras; a ground-truth match triangulated with
  the importer's P1, P2 is the rendered surface point."""
  cal, k, rect = rendered.cal, rendered.k_rect, rendered.rect
  q1, q2 = sr.rig_rotations(RIG)
  baseline = rendered.cfg.baseline_m * 1000.0
  for view in (0, 1):
    ur, vr = sr.real_to_rectified(RIG, k, view)
    sel = (slice(None, None, 7), slice(None, None, 5))
    ray = np.stack([(ur[sel] - k[0, 2]) / k[0, 0], (vr[sel] - k[1, 2]) / k[1, 1],
                    np.ones_like(ur[sel])], -1).reshape(-1, 3)
    x_rect = 300.0 * ray + np.array([baseline, 0, 0]) * view  # in the left rectified frame
    x_left = x_rect @ q1.T
    if view == 0:
      px, _ = cv2.projectPoints(x_left, np.zeros(3), np.zeros(3), cal.m1, cal.d1)
    else:
      px, _ = cv2.projectPoints(x_left, cv2.Rodrigues(cal.r)[0], cal.t, cal.m2, cal.d2)
    v, u = np.mgrid[0:RIG.size[1], 0:RIG.size[0]]
    want = np.stack([u[sel], v[sel]], -1).reshape(-1, 2)
    np.testing.assert_allclose(px.reshape(-1, 2), want, atol=1e-6)
  np.testing.assert_allclose(cal.r @ q1, q2, atol=1e-12)  # R = Q2 Q1^T
  # The float64 undistortion the warps use agrees with OpenCV's iteration.
  u, v = np.meshgrid(np.arange(0, 128, 3.0), np.arange(0, 96, 3.0))
  x, y = sr.undistort_normalised((u - cal.m1[0, 2]) / cal.m1[0, 0],
                                 (v - cal.m1[1, 2]) / cal.m1[1, 1], cal.d1)
  stop = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14)
  ideal = cv2.undistortPoints(np.stack([u.ravel(), v.ravel()], -1)[:, None], cal.m1, cal.d1,
                              criteria=stop)[:, 0]
  np.testing.assert_allclose(ideal, np.stack([x.ravel(), y.ravel()], -1), atol=1e-12)
  # Ground truth: triangulate (x, y) <-> (x - d, y) and compare with the rendered depth.
  gt0 = rendered.gt[0]
  ys, xs = np.nonzero(np.isfinite(gt0))
  pick = np.random.default_rng(0).choice(ys.size, 200, replace=False)
  ys, xs = ys[pick].astype(np.float64), xs[pick].astype(np.float64)
  pts = cv2.triangulatePoints(rect.p1, rect.p2, np.stack([xs, ys]),
                              np.stack([xs - gt0[ys.astype(int), xs.astype(int)], ys]))
  x_imp = (pts[:3] / pts[3]).T
  x_render = x_imp @ rect.r1 @ q1  # importer rectified -> real left -> rendered left camera
  kr = sr.rectified_intrinsics(rendered.cfg)  # the render's own resolution
  u = kr[0, 0] * x_render[:, 0] / x_render[:, 2] + kr[0, 2]
  v = kr[1, 1] * x_render[:, 1] / x_render[:, 2] + kr[1, 2]
  depth = rendered.scene.depth0 * 1000.0
  z = cv2.remap(depth.astype(np.float32), u.astype(np.float32)[None],
                v.astype(np.float32)[None], cv2.INTER_LINEAR)[0]
  np.testing.assert_allclose(x_render[:, 2], z, rtol=2e-3)


# --- accuracy, clean and degraded ------------------------------------------------------------


@pytest.mark.parametrize("degraded", [False, True], ids=["clean", "degraded"])
def test_import_is_accurate(rendered, tmp_path, capsys, degraded):
  """>= 95% of the pixels with ground truth get a disparity, >= 95% of those within 1 px,
  clean and with defocus, indirect light, noise and overexposure (the 0.5 px share is printed)."""
  frames = (sr.real_captures(rendered.scene, rendered.cfg, RIG, OVERSAMPLE, DEGRADED)
            if degraded else rendered.clean)
  if degraded:  # the degradation is real: blur, offset, noise and clipping all visible
    white = frames[0][-2].astype(float)
    assert (frames[0][-2] == 255).mean() > 0.02
    assert not np.array_equal(frames[0][-1], rendered.clean[0][-1])
    assert np.abs(white - rendered.clean[0][-2]).mean() > 5
  _write(tmp_path / "L", frames[0])
  _write(tmp_path / "R", frames[1], "pattern_cam2_im{}.png")
  rigs.write_calibration(tmp_path / "calib.yml", rendered.cal)
  rc, out = _import([tmp_path / "L", tmp_path / "R", tmp_path / "scene", "--calib",
                     tmp_path / "calib.yml", "--projector", PROJ], capsys)
  assert rc == 0, out.err
  assert "left: disparity on" in out.out and "right: disparity on" in out.out
  for view, (valid, within1, within05) in enumerate(_accuracy(tmp_path / "scene", rendered.gt)):
    print(f"{'degraded' if degraded else 'clean'} view {view}: valid {valid:.3f}, within 1 px "
          f"{within1:.4f}, within 0.5 px {within05:.3f}")
    assert valid >= 0.95 and within1 >= 0.95
    assert within05 >= 0.85  # sub-pixel stripe boundaries (0.8 without them)


def test_scene_holds_what_the_format_requires(rendered, capture, tmp_path):
  """calib.txt from the rectified projections (doffs 0, baseline |T| in mm, ndisp the multiple
  of 16 above the largest disparity), raw0/raw1 without row frames, sl0/sl1 every column bit,
  meta.json's provenance; sl0 is what sljax decode makes of raw0."""
  out = tmp_path / "scene"
  rc, _ = _import([capture / "cam1", capture / "cam2", out, "--calib", capture / "calib.yml",
                   "--projector", PROJ, "--unit", "cm"])
  assert rc == 0
  c = read_calib(out / "calib.txt")
  p1, p2 = rendered.rect.p1, rendered.rect.p2
  np.testing.assert_allclose(c.cam0, [[p1[0, 0], 0, p1[0, 2]], [0, p1[1, 1], p1[1, 2]], [0, 0, 1]])
  np.testing.assert_allclose(c.cam1, [[p2[0, 0], 0, p2[0, 2]], [0, p2[1, 1], p2[1, 2]], [0, 0, 1]])
  assert c.doffs == 0 and (c.width, c.height) == RIG.size
  np.testing.assert_allclose(c.baseline, 10 * np.linalg.norm(rendered.cal.t))  # cm -> mm
  d = [read_pfm(out / f"disp{v}.pfm") for v in (0, 1)]
  top = max(np.max(x[np.isfinite(x)]) for x in d)
  assert c.ndisp % 16 == 0 and c.ndisp - 16 <= top < c.ndisp
  n = bit_counts(RIG.projector)[0]
  assert sorted(p.name for p in (out / "raw0").iterdir()) == sorted(
      ["white.png", "black.png"] + [f"{k}{b:03d}.png" for k in "pi" for b in range(n)])
  meta = json.loads((out / "meta.json").read_text())
  assert meta["code"] == "gray" and meta["group"] == "scene" and meta["layout"] == "opencv"
  assert meta["projector"] == list(RIG.projector) and meta["views"] == "white"
  assert meta["frames"]["left"]["white"].endswith(f"pattern_cam1_im{2 * n + 2 * 7 + 1}.png")
  assert meta["frames"]["right"]["p000"].endswith("pattern_cam2_im1.png")
  np.testing.assert_allclose(meta["rectification"]["P2"], p2)
  scene = load_scene(out)
  assert scene.sl0.shape[-1] == n and scene.im0.shape == (96, 128, 1)
  dec = decode_views(scene.raw0, scene.raw1, "gray", projector=(RIG.projector[0], None))
  np.testing.assert_array_equal(np.isnan(dec.left.bits), np.isnan(scene.sl0))
  np.testing.assert_array_equal(np.nan_to_num(dec.left.bits, nan=7), np.nan_to_num(scene.sl0,
                                                                                    nan=7))
  # Disparity only where both views decoded (the left-right check): inf in one view only.
  ys, xs = np.nonzero(np.isfinite(d[0]))
  partner = np.rint(xs - d[0][ys, xs]).astype(int)
  assert np.isfinite(d[1][ys, partner]).all()


def test_scale_resizes_images_disparity_and_calibration(rendered, capture, tmp_path):
  """--scale 0.5: half-size views and patterns, disparity halved (against the ground truth
  resized the same way), focal halved, principal point on the resized pixel grid."""
  full, half = tmp_path / "full", tmp_path / "half"
  common = [capture / "cam1", capture / "cam2"]
  assert _import([*common, full, "--calib", capture / "calib.yml", "--projector", PROJ])[0] == 0
  assert _import([*common, half, "--calib", capture / "calib.yml", "--projector", PROJ,
                  "--scale", "0.5"])[0] == 0
  cf, ch = read_calib(full / "calib.txt"), read_calib(half / "calib.txt")
  assert (ch.width, ch.height) == (64, 48)
  np.testing.assert_allclose(ch.cam0[0, 0], cf.cam0[0, 0] / 2)
  np.testing.assert_allclose(ch.cam0[:2, 2], (cf.cam0[:2, 2] + 0.5) / 2 - 0.5)
  assert ch.baseline == cf.baseline
  gt = [captures.resize_disparity(g, (64, 48), 0.5) for g in rendered.gt]
  for valid, within1, _ in _accuracy(half, gt):
    assert valid >= 0.9 and within1 >= 0.95
  scene = load_scene(half)
  assert scene.sl0.shape == (48, 64, 8) and scene.raw0["white"].shape == (48, 64)


# --- file names, formats and layouts ---------------------------------------------------------


def _variant(rendered, tmp_path, convert, name, start, ext, use_glob):
  """The clean capture written with another naming, numbering and format; (LEFT, RIGHT)."""
  specs = []
  for cam, frames in zip(("a", "b"), rendered.clean):
    folder = _write(tmp_path / cam, frames, name + ext, start, convert)
    specs.append(str(folder / ("*" + ext)) if use_glob else str(folder))
  return specs


@pytest.mark.parametrize("name, start, ext, use_glob", [
    ("frame_{:03d}", 0, ".png", True),    # 0-based, zero-padded, a glob
    ("cap-7-{}", 1, ".bmp", False),       # another integer earlier in the name
    ("img{}", 5, ".tif", True),           # numbering from 5
])
def test_names_numbering_and_formats(rendered, tmp_path, name, start, ext, use_glob):
  left, right = _variant(rendered, tmp_path, lambda f: f, name, start, ext, use_glob)
  out = tmp_path / "s"
  rc, _ = _import([left, right, out, "--calib", tmp_path / "c.yml", "--projector", PROJ]
                  ) if rigs.write_calibration(tmp_path / "c.yml", rendered.cal) is None else (1, 0)
  assert rc == 0
  for valid, within1, _ in _accuracy(out, rendered.gt):
    assert valid >= 0.95 and within1 >= 0.95


@pytest.mark.parametrize("kind", ["colour8", "16bit", "12bit", "jpg"])
def test_bit_depths_colour_and_jpeg(rendered, capture, tmp_path, kind, capsys):
  """Colour frames decode on grey and keep colour in im0/im1; 16-bit frames stay 16-bit; 12-bit
  data in 16-bit files are scaled to the 16-bit range; JPEG's artefacts cost little."""
  tint = np.array([0.8, 1.0, 1.2])  # BGR gains: a colour image whose luma is the frame

  def convert(f):
    if kind == "colour8":
      luma = tint @ np.array([0.114, 0.587, 0.299])
      return np.clip(np.round(f[..., None] * tint / luma), 0, 255).astype(np.uint8)
    if kind == "16bit":
      return f.astype(np.uint16) * 257
    if kind == "12bit":
      return np.round(f.astype(np.float64) * 4095 / 255).astype(np.uint16)
    return f

  ext = ".jpg" if kind == "jpg" else ".png"
  left, right = _variant(rendered, tmp_path, convert, "f{}", 1, ext, False)
  out = tmp_path / "s"
  rc, got = _import([left, right, out, "--calib", capture / "calib.yml", "--projector", PROJ],
                    capsys)
  assert rc == 0, got.err
  scene = load_scene(out)
  raw = cv2.imread(str(out / "raw0" / "white.png"), cv2.IMREAD_UNCHANGED)
  if kind == "colour8":
    assert scene.im0.shape[-1] == 3 and raw.ndim == 2 and raw.dtype == np.uint8
    assert scene.im0[..., 0].mean() > scene.im0[..., 2].mean()  # BGR gains 0.8 / 1.2: red
  if kind in ("16bit", "12bit"):
    # The 16-bit range: the brightest 12-bit value here is about 1900, scaled about 30500.
    assert raw.dtype == np.uint16 and raw.max() > 4 * 4095
    assert f"{12 if kind == '12bit' else 16}-bit frames" in got.out
    assert json.loads((out / "meta.json").read_text())["bit_depth"] == (12 if kind == "12bit"
                                                                       else 16)
  least = 0.9 if kind == "jpg" else 0.95
  for valid, within1, _ in _accuracy(out, rendered.gt):
    assert valid >= least and within1 >= 0.95


def test_sljax_layout_and_ambient_pair(rendered, capture, tmp_path, capsys):
  """The sljax layout (white, black, pNNN, iNNN; any other order of files) and an ambient pair
  for im0/im1, recorded in meta.json."""
  roles = opencv_roles(RIG.projector)
  for cam, frames in zip(("l", "r"), rendered.clean):
    (tmp_path / cam).mkdir()
    for role, f in zip(roles, frames):
      if not role.startswith("r"):
        cv2.imwrite(str(tmp_path / cam / f"{role}.png"), f)
    cv2.imwrite(str(tmp_path / f"amb_{cam}.png"), np.full(RIG.size[::-1] + (3,), (40, 90, 200),
                                                        np.uint8))
  out = tmp_path / "s"
  rc, got = _import([tmp_path / "l", tmp_path / "r", out, "--calib", capture / "calib.yml",
                     "--layout", "sljax", "--ambient", tmp_path / "amb_l.png",
                     tmp_path / "amb_r.png"], capsys)
  assert rc == 0, got.err
  assert "from the ambient frames" in got.out and "row check" not in got.out
  meta = json.loads((out / "meta.json").read_text())
  assert meta["views"] == "ambient" and meta["layout"] == "sljax"
  assert meta["frames"]["ambient"] == ["../amb_l.png", "../amb_r.png"]  # from the scene folder
  im0 = load_scene(out).im0
  centre = im0[40:56, 50:78]  # inside the rectified view: the ambient colour, RGB order
  np.testing.assert_allclose(centre.mean(axis=(0, 1)), np.array([200, 90, 40]) / 255, atol=0.01)
  for valid, within1, _ in _accuracy(out, rendered.gt):
    assert valid >= 0.95 and within1 >= 0.95


# --- calibration files -----------------------------------------------------------------------


def _fs_write(path, entries):
  fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
  for key, value in entries.items():
    fs.write(key, value)
  fs.release()


def test_calibration_readers_round_trip(rendered, tmp_path):
  """YAML (written and read back), XML, .npz, OpenCV's intrinsics.yml + extrinsics.yml pair and
  the structured-light sample's key names all give the same matrices; a stated size is read."""
  cal = rendered.cal
  want = cal.as_dict()
  rigs.write_calibration(tmp_path / "a.yml", cal)
  _fs_write(tmp_path / "b.xml", want)
  np.savez(tmp_path / "c.npz", **want, image_size=np.array(RIG.size))
  _fs_write(tmp_path / "intrinsics.yml", {k: want[k] for k in ("M1", "D1", "M2", "D2")})
  _fs_write(tmp_path / "extrinsics.yml", {"R": want["R"], "T": want["T"], "R1": np.eye(3),
                                          "P1": np.eye(3, 4), "Q": np.eye(4)})
  _fs_write(tmp_path / "sl.yml", {"cam1_intrinsics": want["M1"], "cam1_distorsion": want["D1"],
                                  "cam2_intrinsics": want["M2"], "cam2_distorsion": want["D2"],
                                  "R": want["R"], "T": want["T"]})
  for paths, size in (([tmp_path / "a.yml"], RIG.size), ([tmp_path / "b.xml"], None),
                      ([tmp_path / "c.npz"], RIG.size),
                      ([tmp_path / "intrinsics.yml", tmp_path / "extrinsics.yml"], None),
                      ([tmp_path / "sl.yml"], None)):
    got = rigs.read_calibration(paths)
    assert got.size == (tuple(size) if size else None), paths
    for key, value in got.as_dict().items():
      np.testing.assert_array_equal(value, want[key].reshape(value.shape), err_msg=key)


@pytest.mark.parametrize("damage, why", [
    ("intrinsics only", "lacks the matrices R T (absent, cut off or not an !!opencv-matrix; "
                        "expected an OpenCV FileStorage YAML with the matrices M1 D1 M2 D2 R T); "
                        "intrinsics.yml holds only M1 D1 M2 D2: pass its extrinsics.yml too"),
    ("garbage", "not readable as an OpenCV FileStorage YAML"),
    ("not npz", "not an .npz archive of a stereo calibration"),
    ("not a rotation", "R is not a rotation matrix"),
    ("size", "calibrated for 640x480 images, but the frame "),
    ("swapped", "puts the right camera to the left of the left one (T x > 0; a left-right rig has "
                "T x < 0): are LEFT and RIGHT, or the cameras of the calibration, swapped?"),
])
def test_bad_calibrations_are_one_line_errors(rendered, capture, tmp_path, capsys, damage, why):
  want = rendered.cal.as_dict()
  path = tmp_path / ("c.npz" if damage == "not npz" else "c.yml")
  if damage == "intrinsics only":
    _fs_write(path, {k: want[k] for k in ("M1", "D1", "M2", "D2")})
  elif damage == "garbage":
    path.write_text("M1: [ {{{ :\n")
  elif damage == "not npz":
    path.write_bytes(b"hello")
  elif damage == "not a rotation":
    _fs_write(path, dict(want, R=want["R"] * 1.5))
  elif damage == "size":
    _fs_write(path, dict(want, image_width=640, image_height=480))
  else:
    _fs_write(path, dict(want, T=-want["T"]))
  rc, out = _import([capture / "cam1", capture / "cam2", tmp_path / "s", "--calib", path,
                     "--projector", PROJ], capsys)
  err = out.err.strip().splitlines()
  assert rc == 2 and len(err) == 1 and why in err[0], err
  assert err[0].startswith("sljax import-captures: error: ")
  assert not (tmp_path / "s").exists()


# --- errors and overwriting ------------------------------------------------------------------


def _copy_capture(capture, tmp_path):
  for cam in ("cam1", "cam2"):
    shutil.copytree(capture / cam, tmp_path / cam)
  return tmp_path / "cam1", tmp_path / "cam2"


@pytest.mark.parametrize("damage, why", [
    ("count", "LEFT: 31 frames, but the opencv layout of a 160x120 projector has 32 (16 column "
              "frames for 8 bits, 14 row frames for 7 bits, white, black)"),
    ("projector", "LEFT: 32 frames, but the opencv layout of a 300x120 projector has 34 (18 "
                  "column frames for 9 bits"),
    ("gap", "frame numbers jump from 4 (pattern_cam1_im4.png) to 6 (pattern_cam1_im6.png); frame "
            "5 is missing"),
    ("duplicate", "have the same frame number 3"),
    ("no number", "no frame number in the file name"),
    ("size", "size 64x48 differs from the first LEFT frame's 128x96"),
    ("depth", "16-bit, the other LEFT frames are 8-bit"),
    ("format", "not a frame format sljax reads"),
    ("no projector", "--projector WxH is needed by the opencv layout"),
    ("bad projector", "--projector '160*120': expected WIDTHxHEIGHT"),
    ("file", "a single file; give the folder of the frames or a glob"),
    ("ambient", "--ambient"),
    ("scale", "--scale 2: must be in (0, 1]"),
])
def test_bad_captures_are_one_line_errors(capture, tmp_path, capsys, damage, why):
  left, right = _copy_capture(capture, tmp_path)
  extra = ["--projector", PROJ]
  if damage == "count":
    (left / "pattern_cam1_im32.png").unlink()
  elif damage == "projector":
    extra = ["--projector", "300x120"]
  elif damage == "gap":
    (left / "pattern_cam1_im5.png").rename(left / "pattern_cam1_im33.png")
  elif damage == "duplicate":
    (left / "pattern_cam1_im32.png").rename(left / "pattern_cam1_im003.png")
  elif damage == "no number":
    (left / "pattern_cam1_im32.png").rename(left / "white.png")
  elif damage == "size":
    img = cv2.imread(str(left / "pattern_cam1_im7.png"))
    cv2.imwrite(str(left / "pattern_cam1_im7.png"), cv2.resize(img, (64, 48)))
  elif damage == "depth":
    img = cv2.imread(str(left / "pattern_cam1_im7.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(left / "pattern_cam1_im7.png"), img.astype(np.uint16) * 257)
  elif damage == "format":
    (left / "pattern_cam1_im32.png").rename(left / "pattern_cam1_im32.gif")
    left = left / "pattern_cam1_im*"
  elif damage == "no projector":
    extra = []
  elif damage == "bad projector":
    extra = ["--projector", "160*120"]
  elif damage == "file":
    left = left / "pattern_cam1_im1.png"
  elif damage == "ambient":
    extra += ["--ambient", tmp_path / "none.png", tmp_path / "none.png"]
  elif damage == "scale":
    extra += ["--scale", "2"]
  rc, out = _import([left, right, tmp_path / "s", "--calib", capture / "calib.yml", *extra],
                    capsys)
  err = out.err.strip().splitlines()
  assert rc == 2 and len(err) == 1 and why in err[0], err
  assert not (tmp_path / "s").exists()


def test_nothing_is_replaced_without_overwrite(capture, tmp_path, capsys):
  """A second import into the scene refuses before reading a frame and leaves every file as it
  was, even one of the scene's folders alone; --overwrite replaces them."""
  out = tmp_path / "s"
  args = [capture / "cam1", capture / "cam2", out, "--calib", capture / "calib.yml",
          "--projector", PROJ]
  assert _import(args)[0] == 0
  before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
  (out / "disp0.pfm").unlink()
  (out / "disp1.pfm").unlink()
  rc, got = _import(args + ["--bit-threshold", "20"], capsys)
  assert rc == 2 and "scene " in got.err and "exists (use --overwrite" in got.err
  assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == {
      p: b for p, b in before.items() if p.suffix != ".pfm"}
  for keep in ("im1.png", "disp1.pfm", "calib.txt", "meta.json", "sl1", "raw0"):  # one alone
    alone = tmp_path / f"only-{keep}"
    alone.mkdir()
    (out / "disp1.pfm").write_bytes(b"Pf\n1 1\n-1\n\0\0\0\0")
    copy = shutil.copytree if (out / keep).is_dir() else shutil.copy
    copy(out / keep, alone / keep)
    listing = sorted(alone.rglob("*"))
    rc, got = _import([*args[:2], alone, *args[3:]], capsys)
    assert rc == 2 and f"{alone}: {keep}" in got.err and sorted(alone.rglob("*")) == listing
  assert _import(args + ["--overwrite", "--bit-threshold", "20"])[0] == 0
  meta = json.loads((out / "meta.json").read_text())
  assert math.isclose(meta["decode"]["bit_threshold"], 20 / 255)
  assert (out / "disp0.pfm").exists() and (out / "raw0" / "p000.png").exists()


def test_sljax_layout_errors(capture, tmp_path, capsys):
  roles = opencv_roles(RIG.projector)
  left = tmp_path / "l"
  left.mkdir()
  for role, p in zip(roles, sorted(capture.glob("cam1/*.png"), key=frame_number)):
    if not role.startswith("r") and role != "p007":
      shutil.copy(p, left / f"{role}.png")
  base = [left, left, tmp_path / "s", "--calib", capture / "calib.yml", "--layout", "sljax"]
  rc, out = _import(base, capsys)
  assert rc == 2 and "LEFT: inverse i007 has no pattern p007" in out.err
  (left / "p006.png").rename(left / "p007.png")
  rc, out = _import(base, capsys)
  assert rc == 2 and "LEFT: missing pattern capture p006" in out.err
  shutil.copy(left / "p007.png", left / "p006.png")
  rc, out = _import(base + ["--projector", "300x10"], capsys)
  assert rc == 2 and "LEFT: 8 column patterns, but a 300-column projector has 9" in out.err
  right = tmp_path / "r"
  shutil.copytree(left, right)
  for p in right.glob("i*.png"):
    p.unlink()
  rc, out = _import([left, right, *base[2:]], capsys)
  assert rc == 2 and "RIGHT: its frames differ from LEFT's (i000, i001, i002, i003 in one " \
      "camera only)" in out.err
  shutil.copy(left / "p006.png", left / "extra.png")
  rc, out = _import(base, capsys)
  assert rc == 2 and "extra.png: not a frame name of the sljax layout" in out.err


# --- ChArUco ---------------------------------------------------------------------------------


BOARD = charuco.Board((7, 5), 30.0, 22.0, "DICT_5X5_100")


def _board_views(m, d, poses, size, supersample=2):
  """The board seen by a camera (intrinsics m, distortion d) at each pose (R_b, t_b: board
  frame -> camera, mm), rendered with lens distortion at supersample x and area-averaged."""
  px = 60  # board image pixels per square
  board_img = charuco.opencv_board(BOARD).generateImage((7 * px, 5 * px), marginSize=0)
  w, h = size
  u, v = np.meshgrid((np.arange(w * supersample) + 0.5) / supersample - 0.5,
                     (np.arange(h * supersample) + 0.5) / supersample - 0.5)
  stop = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
  ideal = cv2.undistortPoints(np.stack([u.ravel(), v.ravel()], -1)[:, None], m,
                              np.asarray(d, np.float64), criteria=stop)[:, 0]
  rays = np.stack([ideal[:, 0], ideal[:, 1], np.ones(len(ideal))])
  views = []
  for rb, tb in poses:
    hom = np.column_stack([rb[:, 0], rb[:, 1], tb])  # board (X, Y, 1) -> camera ray
    plane = np.linalg.inv(hom) @ rays
    bx = (plane[0] / plane[2]).reshape(u.shape) / BOARD.square * px - 0.5
    by = (plane[1] / plane[2]).reshape(u.shape) / BOARD.square * px - 0.5
    big = cv2.remap(board_img, bx.astype(np.float32), by.astype(np.float32), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=255)
    views.append(cv2.resize(big, size, interpolation=cv2.INTER_AREA))
  return views


def _board_poses(n, seed=0):
  rng = np.random.default_rng(seed)
  out = []
  for _ in range(n):
    rb = cv2.Rodrigues(np.deg2rad(rng.uniform(-35, 35, 3) * [1, 1, 0.3]))[0]
    centre = np.array([rng.uniform(-25, 25), rng.uniform(-15, 15), rng.uniform(430, 520)])
    out.append((rb, centre - rb @ np.array([105.0, 75.0, 0.0])))  # the board's centre there
  return out


def test_charuco_calibration_recovers_the_rig(tmp_path):
  """Board images drawn by OpenCV, seen through two distorted cameras: intrinsics, R and T."""
  size = (480, 360)
  m1 = np.array([[620.0, 0, 242.0], [0, 620.0, 178.5], [0, 0, 1]])
  m2 = np.array([[632.0, 0, 236.5], [0, 632.0, 183.0], [0, 0, 1]])
  d1, d2 = np.array([-0.1, 0.05, 0.0, 0.0, 0.0]), np.array([-0.08, 0.03, 0.0, 0.0, 0.0])
  r = cv2.Rodrigues(np.deg2rad([0.4, -1.5, 0.7]))[0]
  t = np.array([-60.0, 1.0, 1.5])
  poses = _board_poses(10)
  for folder, m, d, pose in (("L", m1, d1, lambda rb, tb: (rb, tb)),
                             ("R", m2, d2, lambda rb, tb: (r @ rb, r @ tb + t))):
    _write(tmp_path / folder, _board_views(m, d, [pose(*p) for p in poses], size), "b{}.png")
  cal, fit = charuco.calibrate_stereo(str(tmp_path / "L"), str(tmp_path / "R"), BOARD,
                                      progress=False)
  assert fit["pairs"] == 10 and fit["rms_stereo"] < 0.3 and cal.size == size
  np.testing.assert_allclose(np.diag(cal.m1)[:2], np.diag(m1)[:2], rtol=0.01)
  np.testing.assert_allclose(np.diag(cal.m2)[:2], np.diag(m2)[:2], rtol=0.01)
  np.testing.assert_allclose(cal.t.ravel(), t, atol=1.5)
  angle = np.rad2deg(np.linalg.norm(cv2.Rodrigues(cal.r @ r.T)[0]))
  assert angle < 0.5
  # No board in the images: a one-line error naming the board and the dictionary.
  other = charuco.Board((7, 5), 30.0, 22.0, "DICT_4X4_50")
  with pytest.raises(SljaxError, match=r"found in 0 of 10 left images.*check --board"):
    charuco.calibrate_stereo(str(tmp_path / "L"), str(tmp_path / "R"), other, progress=False)


def test_charuco_command_calibrates_imports_and_writes_the_yaml(rendered, tmp_path, capsys):
  """--charuco: board images from the rig's own cameras (the capture's size and lenses) give a
  calibration good enough for the import; the YAML used is written into the scene."""
  big = sr.RigConfig(size=(480, 360), focal_scale=(4.2, 4.35),
                     centre_offset_px=((6.0, -4.0), (-5.0, 5.0)),
                     distortion=((-0.1, 0.05, 0.0, 0.0, 0.0), (-0.08, 0.03, 0.0, 0.0, 0.0)),
                     projector=RIG.projector)
  cal = sr.calibration(big, rendered.k_rect, rendered.cfg.baseline_m * 1000.0)
  poses = _board_poses(10, seed=1)
  for folder, m, d, pose in (
      ("L", cal.m1, cal.d1.ravel(), lambda rb, tb: (rb, tb)),
      ("R", cal.m2, cal.d2.ravel(), lambda rb, tb: (cal.r @ rb, cal.r @ tb + cal.t.ravel()))):
    _write(tmp_path / folder, _board_views(m, d, [pose(*p) for p in poses], big.size), "b{}.png")
  frames = sr.real_captures(rendered.scene, rendered.cfg, big, OVERSAMPLE)
  _write(tmp_path / "cam1", frames[0])
  _write(tmp_path / "cam2", frames[1])
  out = tmp_path / "s"
  rc, got = _import([tmp_path / "cam1", tmp_path / "cam2", out, "--charuco", tmp_path / "L",
                     tmp_path / "R", "--board", "7x5", "--square", "30", "--marker", "22",
                     "--projector", PROJ], capsys)
  assert rc == 0, got.err
  assert "ChArUco calibration from 10 image pairs: RMS reprojection error" in got.out
  written = rigs.read_calibration(out / captures.CALIBRATION_FILE)
  assert written.size == big.size
  # A 12 mm baseline seen from 450 mm: T's x well, its z (a few views) within 2 mm.
  err = np.abs(written.t.ravel() - cal.t.ravel())
  assert err[0] < 0.3 and err[1] < 0.3 and err[2] < 2.0, (written.t.ravel(), cal.t.ravel())
  # the calibration used is the one saved in the scene, named relative to it
  assert json.loads((out / "meta.json").read_text())["calibration"] == captures.CALIBRATION_FILE
  assert min(np.isfinite(read_pfm(out / f"disp{v}.pfm")).mean() for v in (0, 1)) > 0.55
  rc, got = _import([tmp_path / "cam1", tmp_path / "cam2", out, "--charuco", tmp_path / "L",
                     tmp_path / "R", "--board", "7x5", "--square", "30", "--projector", PROJ],
                    capsys)
  assert rc == 2 and "--charuco needs --board XxY, --square LENGTH and --marker" in got.err


# --- end to end ------------------------------------------------------------------------------


def test_imported_scene_works_with_info_evaluate_predict_and_training_data(capture, tmp_path,
                                                                            capsys):
  """sljax info, the pre-flight check and the batches of training with --data, sljax evaluate
  and sljax predict (SGBM, no network) take an imported scene; dataset.json "patterns" 6 gives
  the 6 coarsest of its 8 patterns."""
  data = tmp_path / "data"
  for name in ("a", "b"):
    assert _import([capture / "cam1", capture / "cam2", data / name, "--calib",
                    capture / "calib.yml", "--projector", PROJ, "--group", name])[0] == 0
  capsys.readouterr()
  assert cli.main(["info", str(data)]) == 0
  out = capsys.readouterr().out
  assert "code gray; 8 patterns (2 scenes)" in out and "train 1 scene / 1 group" in out
  src = FolderSource(data)
  preflight.check(src, [([0, 1], {"im", "disp", "sl"})], progress=False, use_cache=False)
  batch = load_batch(src, [0, 1], size=(64, 64), parts=("left", "right", "disp", "sl"))
  assert batch["sl"].shape == (2, 64, 64, 8) and np.isfinite(batch["disp"]).mean() > 0.5
  assert cli.main(["evaluate", "sgbm", str(data), "--out", str(tmp_path / "eval")]) == 0
  assert (tmp_path / "eval" / "per_scene.csv").exists()
  assert cli.main(["predict", "sgbm", str(data / "a"), "--out", str(tmp_path / "pred"),
                   "--num-disparities", "32"]) == 0
  assert (tmp_path / "pred").is_dir()
  (data / "dataset.json").write_text(json.dumps({"patterns": 6}))
  src = FolderSource(data)
  full = load_scene(data / "a").sl0
  np.testing.assert_array_equal(np.nan_to_num(src[0].sl0, nan=9), np.nan_to_num(full[..., :6],
                                                                                nan=9))
  preflight.check(src, [([0, 1], {"im", "sl"})], progress=False, use_cache=False)
  assert cli.main(["info", str(data)]) == 0


# --- refusals: what the import will not write ------------------------------------------------

# Cameras alike (small rotations, one lens): swapped views still rectify onto common rows, so
# the swap shows as negative disparities rather than as rows that do not match.
TWIN = sr.RigConfig(size=(128, 96), projector=(160, 120),
                    rotation_deg=((0.3, -0.4, 0.2), (-0.2, 0.3, -0.1)), focal_scale=(1.12, 1.13),
                    centre_offset_px=((1.0, -0.5), (-0.5, 1.0)),
                    distortion=((-0.1, 0.02, 0.0, 0.0, 0.0), (-0.1, 0.02, 0.0, 0.0, 0.0)))


@pytest.fixture(scope="module")
def twin(rendered, tmp_path_factory):
  """The rendered scene captured by the twin rig, in both layouts, with its calibration."""
  root = tmp_path_factory.mktemp("twin")
  frames = sr.real_captures(rendered.scene, rendered.cfg, TWIN, OVERSAMPLE)
  roles = opencv_roles(TWIN.projector)
  for cam, view in zip(("cam1", "cam2"), frames):
    _write(root / "opencv" / cam, view)
    (root / "sljax" / cam).mkdir(parents=True)
    for role, f in zip(roles, view):
      if not role.startswith("r"):
        assert cv2.imwrite(str(root / "sljax" / cam / f"{role}.png"), f)
  rigs.write_calibration(root / "calib.yml",
                         sr.calibration(TWIN, rendered.k_rect, rendered.cfg.baseline_m * 1000))
  return root


def _layout_args(layout):
  return ["--projector", PROJ] if layout == "opencv" else ["--layout", "sljax"]


def _refused(args, capsys, out, why):
  """The import exits 2 with one line holding why, and out is as it was (absent, or the same
  files byte for byte)."""
  before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} if out.exists() else None
  rc, got = _import(args, capsys)
  err = got.err.strip().splitlines()
  assert rc == 2 and len(err) == 1 and why in err[0], err
  assert err[0].startswith("sljax import-captures: error: ") and "Nothing written" in err[0]
  print(err[0])
  if before is None:
    assert not out.exists()
  else:
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
  return err[0]


@pytest.mark.parametrize("layout", ["opencv", "sljax"])
def test_swapped_views_are_refused_by_their_negative_disparities(twin, tmp_path, capsys, layout):
  """The same capture imports with LEFT and RIGHT in order (no disparity negative) and is
  refused swapped, by the rule a scene's loader applies (more than half negative)."""
  cams, calib = twin / layout, twin / "calib.yml"
  ok = tmp_path / "ok"
  rc, got = _import([cams / "cam1", cams / "cam2", ok, "--calib", calib,
                     *_layout_args(layout)], capsys)
  assert rc == 0, got.err
  d = [read_pfm(ok / f"disp{v}.pfm") for v in (0, 1)]
  assert min(np.isfinite(x).mean() for x in d) > 0.5
  assert all((x[np.isfinite(x)] >= 0).all() for x in d)
  # With row frames the row check sees the swap too: the message leads with the swap.
  err = _refused([cams / "cam2", cams / "cam1", tmp_path / "s", "--calib", calib,
                  *_layout_args(layout)], capsys, tmp_path / "s",
                 f"LEFT {cams / 'cam2'} and RIGHT {cams / 'cam1'} look swapped: ")
  assert "% of the left view's matched disparities are negative" in err
  assert ("the row check refused" in err) == (layout == "opencv")
  # --overwrite over the correct scene: refused before a file is touched.
  _refused([cams / "cam2", cams / "cam1", ok, "--calib", calib, "--overwrite",
            *_layout_args(layout)], capsys, ok, "look swapped: ")


def test_the_swap_rule_is_the_loaders(twin, tmp_path, capsys, monkeypatch):
  """Import and load agree: with the swap refusal and the sign filter planted away, the import
  writes the swapped scene and load_scene refuses it as negative."""
  cams = twin / "sljax"
  monkeypatch.setattr(captures.refusals, "check_signs", lambda *a: None)
  monkeypatch.setattr(captures.refusals, "plausible", lambda d0, d1, *a: (d0, d1, (0, 0)))
  rc, got = _import([cams / "cam2", cams / "cam1", tmp_path / "s", "--calib",
                     twin / "calib.yml", "--layout", "sljax"], capsys)
  assert rc == 0, got.err
  with pytest.raises(SljaxError, match=r"disp0.pfm: (9\d|100)% of its known disparities are negative"):
    load_scene(tmp_path / "s")


def test_the_sign_filter_alone_writes_no_negative_disparity(twin, tmp_path, capsys, monkeypatch):
  """With the swap refusal planted away, what is written of the swapped capture holds no
  negative disparity, and calib.txt's vmin/vmax are the written range."""
  cams = twin / "sljax"
  monkeypatch.setattr(captures.refusals, "check_signs", lambda *a: None)
  rc, got = _import([cams / "cam2", cams / "cam1", tmp_path / "s", "--calib",
                     twin / "calib.yml", "--layout", "sljax"], capsys)
  assert rc == 0, got.err
  meta = json.loads((tmp_path / "s" / "meta.json").read_text())
  assert meta["implausible"]["left"] > 1000 and "below 0 or above the width" in got.out
  d = [read_pfm(tmp_path / "s" / f"disp{v}.pfm") for v in (0, 1)]
  known = np.concatenate([x[np.isfinite(x)] for x in d])
  assert known.size and (known >= 0).all() and (known <= 128).all()
  c = read_calib(tmp_path / "s" / "calib.txt")
  assert (c.vmin, c.vmax) == (np.floor(known.min()), np.ceil(known.max()))


def test_swapped_views_of_unlike_cameras_are_refused_by_the_row_check(capture, tmp_path,
                                                                        capsys):
  """The test rig's cameras differ (rotations of a degree, other lenses): swapped, their rows do
  not match, and the row check refuses most matches."""
  err = _refused([capture / "cam2", capture / "cam1", tmp_path / "s", "--calib",
                  capture / "calib.yml", "--projector", PROJ], capsys, tmp_path / "s",
                 " swapped")
  assert "the row check refused" in err


@pytest.mark.parametrize("other", ["rotation", "focal"])
def test_a_calibration_of_another_rig_is_refused_by_the_row_check(rendered, capture, tmp_path,
                                                                  capsys, other):
  """R tilted 2 degrees about the baseline, or the left focal length 20% longer: the rectified
  rows do not match and the row check refuses most matches."""
  cal = rendered.cal
  if other == "rotation":
    cal = dataclasses.replace(cal, r=sr.rotation((2.0, 0.0, 0.0)) @ cal.r)
  else:
    cal = dataclasses.replace(cal, m1=cal.m1 * np.array([[1.2, 1, 1], [1, 1.2, 1], [1, 1, 1]]))
  rigs.write_calibration(tmp_path / "other.yml", cal)
  err = _refused([capture / "cam1", capture / "cam2", tmp_path / "s", "--calib",
                  tmp_path / "other.yml", "--projector", PROJ], capsys, tmp_path / "s",
                 "the rectified rows of the two views do not match: the row check refused ")
  assert f"is the calibration ({tmp_path / 'other.yml'}) of another rig" in err
  share = int(err.split("refused ")[1].split("%")[0])
  assert 25 < share <= 100


def test_the_unit_of_t_gives_the_baseline_in_mm(rendered, capture, tmp_path):
  """--unit mm, cm, m: calib.txt's baseline is |T| times 1, 10, 1000 (the disparities alike)."""
  for unit, mm in (("mm", 1.0), ("cm", 10.0), ("m", 1000.0)):
    assert _import([capture / "cam1", capture / "cam2", tmp_path / unit, "--calib",
                    capture / "calib.yml", "--projector", PROJ, "--unit", unit])[0] == 0
    np.testing.assert_allclose(read_calib(tmp_path / unit / "calib.txt").baseline,
                               mm * np.linalg.norm(rendered.cal.t), rtol=1e-6)
    assert json.loads((tmp_path / unit / "meta.json").read_text())["unit"] == unit


def test_a_wrong_baseline_length_is_not_seen_and_only_scales_depth(rendered, capture, tmp_path):
  """T twice as long: the same disparities (rectification does not depend on |T|), calib.txt's
  baseline doubled, so depth = f B / d doubles: nothing in the images can tell."""
  rigs.write_calibration(tmp_path / "long.yml", dataclasses.replace(rendered.cal,
                                                                    t=rendered.cal.t * 2))
  for name, calib in (("a", capture / "calib.yml"), ("b", tmp_path / "long.yml")):
    assert _import([capture / "cam1", capture / "cam2", tmp_path / name, "--calib", calib,
                    "--projector", PROJ])[0] == 0
  for v in (0, 1):
    np.testing.assert_array_equal(read_pfm(tmp_path / "a" / f"disp{v}.pfm"),
                                  read_pfm(tmp_path / "b" / f"disp{v}.pfm"))
  ca, cb = read_calib(tmp_path / "a" / "calib.txt"), read_calib(tmp_path / "b" / "calib.txt")
  np.testing.assert_allclose(cb.baseline, 2 * ca.baseline)


@pytest.mark.parametrize("light", ["projector off", "saturated"])
@pytest.mark.parametrize("layout", ["opencv", "sljax"])
def test_a_capture_where_almost_nothing_decodes_is_refused(capture, twin, tmp_path, capsys,
                                                           light, layout):
  """Every frame the ambient (black) frame, or every frame saturated: the coarsest stripe
  decodes nowhere."""
  src = capture if layout == "opencv" else twin / "sljax"
  for cam in ("cam1", "cam2"):
    shutil.copytree(src / cam, tmp_path / cam)
    paths = sorted((tmp_path / cam).glob("*.png"))
    black = cv2.imread(str(next(p for p in paths if p.stem == "black") if layout == "sljax"
                           else max(paths, key=frame_number)), cv2.IMREAD_UNCHANGED)
    for p in paths:
      cv2.imwrite(str(p), black if light == "projector off" else np.full_like(black, 255))
  err = _refused([tmp_path / "cam1", tmp_path / "cam2", tmp_path / "s", "--calib",
                  capture / "calib.yml", *_layout_args(layout)], capsys, tmp_path / "s",
                 "the projector's coarsest stripe decodes on 0.0% of the pixels (under 5%): was "
                 "the projector off, or the exposure wrong")
  assert err.startswith(f"sljax import-captures: error: LEFT {tmp_path / 'cam1'}: ")


def test_meta_paths_are_relative_to_the_scene(capture, tmp_path):
  """meta.json names every frame and the calibration relative to the scene folder: they resolve
  from there, and the scene still points at them after the whole tree moves."""
  shutil.copytree(capture, tmp_path / "a" / "caps")
  caps, out = tmp_path / "a" / "caps", tmp_path / "a" / "data" / "s"
  assert _import([caps / "cam1", caps / "cam2", out, "--calib", caps / "calib.yml",
                  "--projector", PROJ])[0] == 0
  meta = json.loads((out / "meta.json").read_text())
  assert meta["calibration"] == "../../caps/calib.yml"
  paths = [*meta["frames"]["left"].values(), *meta["frames"]["right"].values()]
  assert len(paths) == 2 * len(opencv_roles(RIG.projector))
  assert not any(Path(p).is_absolute() for p in paths)
  assert meta["frames"]["left"]["p000"] == "../../caps/cam1/pattern_cam1_im1.png"
  shutil.move(tmp_path / "a", tmp_path / "b")
  moved = tmp_path / "b" / "data" / "s"
  assert all((moved / p).is_file() for p in paths + [meta["calibration"]])


def test_plausible_drops_what_no_rig_can_see_by_hand():
  """A 1x8 pair by hand: left disparities -2 and 9 (width 8) are unknown, their partners in
  the right view too; nothing else changes; nothing dropped returns the arrays as they are."""
  inf = np.inf
  d0 = np.array([[inf, inf, 1.0, 1.0, -2.0, inf, inf, inf]], np.float32)
  d1 = np.array([[inf, 1.0, 1.0, inf, inf, inf, -2.0, inf]], np.float32)
  # x = 2, 3 in the left see x = 1, 2 in the right; x = 4 (d -2) sees x = 6 (d -2).
  got0, got1, dropped = captures.refusals.plausible(d0, d1, 8, 1.0)
  np.testing.assert_array_equal(got0, [[inf, inf, 1.0, 1.0, inf, inf, inf, inf]])
  np.testing.assert_array_equal(got1, [[inf, 1.0, 1.0, inf, inf, inf, inf, inf]])
  assert dropped == (1, 1)
  far = np.full((1, 8), inf, np.float32)
  far[0, 0] = 9.0
  assert captures.refusals.plausible(far, np.full((1, 8), inf, np.float32), 8, 1.0)[2] == (1, 0)
  same = captures.refusals.plausible(got0, got1, 8, 1.0)
  assert same[0] is got0 and same[1] is got1 and same[2] == (0, 0)


@pytest.mark.parametrize("error", [OSError(28, "No space left on device"), KeyboardInterrupt()])
def test_a_failure_while_writing_leaves_the_scene_as_it_was(capture, tmp_path, capsys,
                                                            monkeypatch, error):
  """A full disk (or Ctrl-C) while the raw frames are written, after the views, disparities
  and patterns: OUT_SCENE stays absent, and with --overwrite keeps its files byte for byte."""
  import gc  # pylint: disable=import-outside-toplevel
  import toys  # pylint: disable=import-outside-toplevel
  from sljax.data import scene as scene_module  # pylint: disable=import-outside-toplevel
  out = tmp_path / "s"
  args = [capture / "cam1", capture / "cam2", out, "--calib", capture / "calib.yml",
          "--projector", PROJ]

  def failing(*a, **k):
    gc.collect()  # not inside jax's gc callback, which would report a Ctrl-C as ignored
    raise error

  with monkeypatch.context() as m:
    m.setattr(scene_module, "write_raw", failing)
    assert _import(args, capsys)[0] in (2, 130)
  assert not out.exists()
  assert _import(args)[0] == 0
  before = toys.tree(out)
  with monkeypatch.context() as m:
    m.setattr(scene_module, "write_raw", failing)
    assert _import(args + ["--overwrite", "--bit-threshold", "20"], capsys)[0] in (2, 130)
  assert toys.tree(out) == before
