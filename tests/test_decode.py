import gc
import json
import math

import cv2
import numpy as np
import pytest

from sljax import cli
from sljax.commands import decode
from sljax.data.pfm import read_pfm
from sljax.errors import SljaxError
from sljax.sl import codes
from sljax.sl.decode import DecodeConfig, column_from_bits, decode_captures
from sljax.sl.match import disparity_from_codes

import toys

H, W = 48, 256
T = 7                      # Gray code of a 128-column projector
F, BASE = 300.0, 50.0      # camera focal (px) and baseline
PX, FP, CP = -30.0, 116.0, 50.0  # projector x position, focal (px), principal column
BLOCKED = (60.0, 66.0)     # projector columns hidden by an occluder near the projector
NOISE = 0.008


def _truth_disparity(x, y):
  """Left-referenced disparity of the slanted plane, in closed form for each view."""
  return 20.0 + 0.05 * x + 0.02 * y


def _render(seed: int, inverses: bool = True):
  """Renders raw captures of a slanted plane for both cameras, plus the truth.

  Left pixel (x, y) has disparity d = 20 + 0.05 x + 0.02 y; the point it sees is lit by the
  projector column u = FP * ((x - cx) / F - PX * d / (F * BASE)) + CP (a pinhole projector
  beside the left camera, sharing its orientation). The right pixel xr sees the point of the
  left pixel xr + d, where d solves d = 20 + 0.05 (xr + d) + 0.02 y.
  """
  rng = np.random.default_rng(seed)
  ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
  cx = W / 2
  views = []
  for view in (0, 1):
    if view == 0:
      xl = xs
      d = _truth_disparity(xs, ys)
    else:
      d = (20.0 + 0.05 * xs + 0.02 * ys) / (1.0 - 0.05)
      xl = xs + d
    u = FP * ((xl - cx) / F - PX * d / (F * BASE)) + CP
    lit = (u >= 0) & (u < 2 ** T) & ~((u >= BLOCKED[0]) & (u < BLOCKED[1]))
    col = np.floor(u).astype(np.int64)
    bits = codes.encode(np.clip(col, 0, 2 ** T - 1), "gray", T).astype(np.float64)
    # Albedo is a property of the surface point, so it follows the left coordinate xl.
    albedo = 0.6 + 0.3 * np.sin(xl / 9.0) * np.cos(ys / 7.0)
    ambient = 0.04 * albedo
    light = 0.8 * albedo * lit
    noise = lambda: rng.normal(0.0, NOISE, (H, W))
    raw = {"white": ambient + light + noise(), "black": ambient + noise()}
    for k in range(T):
      raw[f"p{k:03d}"] = ambient + light * bits[..., k] + noise()
      if inverses:
        raw[f"i{k:03d}"] = ambient + light * (1 - bits[..., k]) + noise()
    raw = {k: np.clip(v, 0, 1).astype(np.float32) for k, v in raw.items()}
    # Truth disparity where the other camera sees the point and the projector lights it.
    other = xs - d if view == 0 else xs + d
    valid = lit & (other >= 0) & (other <= W - 1)
    views.append(dict(raw=raw, bits=bits, col=col, lit=lit, shadow_strip=(u >= BLOCKED[0]) &
                      (u < BLOCKED[1]), disp=np.where(valid, d, np.inf)))
  return views


def _abs_err(d, truth):
  """|d - truth|, inf wherever either is unknown."""
  both = np.isfinite(d) & np.isfinite(truth)
  return np.where(both, np.abs(np.where(both, d, 0) - np.where(both, truth, 0)), np.inf)


@pytest.fixture(scope="module")
def scene():
  return _render(seed=0)


@pytest.fixture(scope="module")
def decoded(scene):
  return [decode_captures(v["raw"], "gray") for v in scene]


def test_bits_agree_with_truth_on_lit_pixels(scene, decoded):
  for v, dec in zip(scene, decoded):
    assert dec.bits.shape == (H, W, T) and dec.bits.dtype == np.float32
    lit = v["lit"]
    agree = (dec.bits == v["bits"]).all(axis=-1)  # NaN never agrees
    assert agree[lit].mean() >= 0.995
    col_ok = dec.column == v["col"]
    assert col_ok[lit].mean() >= 0.995


def test_shadow_strip_is_unknown(scene, decoded):
  d0, d1 = disparity_from_codes(decoded[0].column, decoded[1].column)
  for v, dec, d in zip(scene, decoded, (d0, d1)):
    strip = v["shadow_strip"]
    assert strip.sum() > 5 * H  # a real strip, several pixels wide
    assert dec.shadow[strip].all()
    assert np.isnan(dec.bits[strip]).all()
    assert np.isnan(dec.column[strip]).all()
    assert np.isinf(d[strip]).all()


def test_disparity_from_codes_matches_truth(scene, decoded):
  d0, d1 = disparity_from_codes(decoded[0].column, decoded[1].column)
  for v, d in zip(scene, (d0, d1)):
    valid = np.isfinite(v["disp"])
    err = _abs_err(d, v["disp"])[valid]  # inf where the matcher gave up
    assert (err <= 1.0).mean() >= 0.95
    # Whatever the matcher does output is right.
    out = np.isfinite(d)
    assert (_abs_err(d, v["disp"])[out & valid] <= 1.0).mean() >= 0.99
    assert not (out & ~v["lit"]).any()


def test_decoding_without_inverses():
  scene = _render(seed=1, inverses=False)
  dec = decode_captures(scene[0]["raw"], "gray")
  lit = scene[0]["lit"]
  agree = (dec.bits == scene[0]["bits"]).all(axis=-1)
  assert agree[lit].mean() >= 0.99
  assert np.isnan(dec.column[scene[0]["shadow_strip"]]).all()


def test_thresholds_against_naive_loop():
  rng = np.random.default_rng(3)
  h, w, t = 5, 6, 3
  raw = {"white": rng.uniform(0.0, 1.0, (h, w)).astype(np.float32),
         "black": rng.uniform(0.0, 0.2, (h, w)).astype(np.float32)}
  for k in range(t):
    raw[f"p{k:03d}"] = rng.uniform(0, 1, (h, w)).astype(np.float32)
    raw[f"i{k:03d}"] = rng.uniform(0, 1, (h, w)).astype(np.float32)
  cfg = DecodeConfig(shadow_threshold=0.3, bit_threshold=0.1)
  dec = decode_captures(raw, "binary", config=cfg)
  for y in range(h):
    for x in range(w):
      shadow = raw["white"][y, x] - raw["black"][y, x] < 0.3
      assert dec.shadow[y, x] == shadow
      value, known = 0, not shadow
      for k in range(t):
        p, i = float(raw[f"p{k:03d}"][y, x]), float(raw[f"i{k:03d}"][y, x])
        unsure = abs(p - i) < 0.1
        assert dec.uncertain[y, x, k] == unsure
        if shadow or unsure:
          assert math.isnan(dec.bits[y, x, k])
          known = False
        else:
          assert dec.bits[y, x, k] == float(p > i)
          value = value * 2 + int(p > i)
      if known:
        assert dec.column[y, x] == value
      else:
        assert math.isnan(dec.column[y, x])


def test_bad_captures():
  raw = {"white": np.ones((4, 4), np.float32), "black": np.zeros((4, 4), np.float32),
         "p000": np.ones((4, 4), np.float32), "p002": np.ones((4, 4), np.float32)}
  with pytest.raises(SljaxError, match="p001"):
    decode_captures(raw, "gray", where="scene x/raw0")
  del raw["p002"]
  raw["i000"] = np.zeros((4, 4), np.float32)
  raw["p001"] = np.zeros((4, 4), np.float32)
  with pytest.raises(SljaxError, match="i001"):
    decode_captures(raw, "gray")
  del raw["black"]
  with pytest.raises(SljaxError, match="black"):
    decode_captures(raw, "gray")
  with pytest.raises(SljaxError, match="shape"):
    decode_captures({"white": np.ones((4, 4)), "black": np.ones((4, 5)), "p000": np.ones((4, 4))},
                    "gray")
  four = {"white": np.ones((4, 4)), "black": np.zeros((4, 4)),
          **{f"{c}{k:04d}": np.ones((4, 4)) for c in "pi" for k in range(5)}}
  with pytest.raises(SljaxError) as e:  # was the bare "no pattern captures"
    decode_captures(four, "gray", where="scene x/raw0")
  assert str(e.value) == ("scene x/raw0: no pattern captures (expected p000, p001, ...); found "
                          "p0000, p0001, p0002, ...: a capture's number takes exactly three "
                          "digits")
  with pytest.raises(SljaxError) as e:
    decode_captures({"white": np.ones((4, 4)), "black": np.zeros((4, 4))}, "gray", where="x")
  assert str(e.value) == "x: no pattern captures (expected p000, p001, ...)"
  with pytest.raises(SljaxError) as e:  # three digits, but inverses only
    decode_captures({"white": np.ones((4, 4)), "black": np.zeros((4, 4)), "i000": np.ones((4, 4)),
                     "i0001": np.ones((4, 4))}, "gray", where="x")
  assert str(e.value) == ("x: no pattern captures (expected p000, p001, ...); found i0001: a "
                          "capture's number takes exactly three digits")
  with pytest.raises(SljaxError) as e:
    decode_captures({"white": np.ones((4, 4)), "black": np.zeros((4, 4)), "i000": np.ones((4, 4))},
                    "gray", where="x")
  assert str(e.value) == ("x: no pattern captures (expected p000, p001, ...); only inverse "
                          "captures (i000, ...)")


# --- sljax decode -------------------------------------------------------------------------

def _write_png(path, image01):
  path.parent.mkdir(parents=True, exist_ok=True)
  assert cv2.imwrite(str(path), np.rint(np.clip(image01, 0, 1) * 255).astype(np.uint8))


def _write_scene_folder(root, name, views, meta=None):
  """A scene folder with raw captures, written by hand (FORMAT.md layout)."""
  d = root / name
  for cam, v in enumerate(views):
    _write_png(d / f"im{cam}.png", v["raw"]["black"] + 0.3)
    for key, img in v["raw"].items():
      _write_png(d / f"raw{cam}" / f"{key}.png", img)
  if meta is not None:
    (d / "meta.json").write_text(json.dumps(meta))
  return d


def _read_patterns(folder):
  files = sorted(folder.glob("*.png"))
  return np.stack([cv2.imread(str(f), cv2.IMREAD_UNCHANGED) for f in files], axis=-1)


def test_cli_decode_writes_refuses_then_overwrites(tmp_path, scene, capsys):
  root = tmp_path / "ds"
  sdir = _write_scene_folder(root, "a", scene, meta={"code": "gray", "group": "g"})
  assert cli.main(["decode", str(root)]) == 0
  for cam, v in enumerate(scene):
    sl = _read_patterns(sdir / f"sl{cam}")
    assert sl.shape == (H, W, T)
    assert set(np.unique(sl)) <= {0, 128, 255}
    lit = v["lit"]
    truth = (v["bits"] * 255).astype(np.uint8)
    assert (sl == truth).all(axis=-1)[lit].mean() >= 0.99  # 8-bit quantisation of the captures
    # 8-bit rounding adds to the noise: nearly all of the strip stays below the threshold.
    assert (sl[v["shadow_strip"]] == 128).all(axis=-1).mean() >= 0.99
    disp = read_pfm(sdir / f"disp{cam}.pfm")
    assert np.isinf(disp[v["shadow_strip"]]).all()
    assert (_abs_err(disp, v["disp"])[np.isfinite(v["disp"])] <= 1.0).mean() >= 0.95
  # A second run refuses to overwrite and names the file.
  assert cli.main(["decode", str(root)]) == 2
  err = capsys.readouterr().err
  assert "sl0" in err and "--overwrite" in err and len(err.strip().splitlines()) == 1
  # With --overwrite it runs again; an existing disparity is left alone.
  before = (sdir / "disp0.pfm").read_bytes()
  assert cli.main(["decode", str(root), "--overwrite", "--bit-threshold", "5"]) == 0
  assert (sdir / "disp0.pfm").read_bytes() == before


def _one_line_error(capsys, *needles):
  """The CLI printed exactly one line on stderr, holding every needle, and no traceback."""
  out, err = capsys.readouterr()
  assert len(err.strip().splitlines()) == 1 and "Traceback" not in out + err
  for n in needles:
    assert n in err, (n, err)


def test_cli_decode_errors(tmp_path, scene, capsys):
  root = tmp_path / "ds"
  # Another, valid scene sorted first: a refusal must not leave it half decoded.
  _write_scene_folder(root, "0ok", scene, meta={"code": "gray"})
  # No code anywhere.
  sdir = _write_scene_folder(root, "a", scene)
  assert cli.main(["decode", str(root)]) == 2
  _one_line_error(capsys, "code", "a")
  # Different pattern counts in the two views.
  (sdir / "raw1" / f"p{T - 1:03d}.png").unlink()
  (sdir / "raw1" / f"i{T - 1:03d}.png").unlink()
  assert cli.main(["decode", str(root), "--code", "gray"]) == 2
  _one_line_error(capsys, "raw0", "raw1", str(sdir))
  # A missing white capture.
  (sdir / "raw0" / "white.png").unlink()
  assert cli.main(["decode", str(root), "--code", "gray"]) == 2
  _one_line_error(capsys, str(sdir), "raw0/white.png", "missing")
  # One view's captures absent altogether.
  for f in (sdir / "raw1").iterdir():
    f.unlink()
  (sdir / "raw1").rmdir()
  assert cli.main(["decode", str(root), "--code", "gray"]) == 2
  _one_line_error(capsys, str(sdir), "raw1/", "missing")
  assert not (root / "0ok" / "sl0").exists() and not (root / "0ok" / "disp0.pfm").exists()


def test_cli_decode_checks_every_capture_before_writing(tmp_path, scene, capsys):
  """A capture of another size in a later scene: one line naming it, and the earlier scene is
  not written (it was, and a rerun after the fix refused it without --overwrite)."""
  root = tmp_path / "ds"
  _write_scene_folder(root, "0ok", scene, meta={"code": "gray"})
  sdir = _write_scene_folder(root, "b", scene, meta={"code": "gray"})
  bad = sdir / "raw1" / "p003.png"
  assert cv2.imwrite(str(bad), np.zeros((H, W - 1), np.uint8))
  assert cli.main(["decode", str(root)]) == 2
  _one_line_error(capsys, f"{bad}: size {W - 1}x{H} differs from im0.png ({W}x{H})",
                  "nothing was decoded")
  assert not (root / "0ok" / "sl0").exists() and not (root / "0ok" / "disp0.pfm").exists()


@pytest.mark.parametrize("damage, why", [
    ("swapped", "black.png is the brighter one: are the two swapped?"),
    ("same", "the projector off, or the same picture twice?"),
])
def test_cli_decode_refuses_captures_without_projector_contrast(tmp_path, scene, capsys,
                                                                damage, why):
  """white.png nowhere brighter than black.png: every pixel would be shadow, and the
  all-unknown sl0/ and disp0.pfm were written (and then kept as existing results)."""
  root = tmp_path / "ds"
  views = [dict(v, raw=dict(v["raw"])) for v in scene]
  raw = views[1]["raw"]
  raw["white"], raw["black"] = ((raw["black"], raw["white"]) if damage == "swapped"
                                else (raw["black"], raw["black"]))
  sdir = _write_scene_folder(root, "a", views, meta={"code": "gray"})
  assert cli.main(["decode", str(root)]) == 2
  _one_line_error(capsys, f"{sdir / 'raw1'}: white.png is nowhere brighter than black.png by 10 "
                  "grey levels (--shadow-threshold)", why)
  assert not (sdir / "sl0").exists() and not (sdir / "disp0.pfm").exists()


def test_cli_defaults_mirror_decode_config():
  from sljax.commands import decode as decode_cmd
  assert decode_cmd._DEFAULT_SHADOW / 255.0 == DecodeConfig().shadow_threshold
  assert decode_cmd._DEFAULT_BIT / 255.0 == DecodeConfig().bit_threshold


def test_column_from_bits_probabilities_and_nan(scene):
  v = scene[0]
  probs = np.where(v["bits"] > 0, 0.9, 0.2).astype(np.float32)
  col = column_from_bits(probs, "gray")
  np.testing.assert_array_equal(col, v["col"].astype(np.float32))
  probs[3, 4, 2] = np.nan
  col = column_from_bits(probs, "gray")
  assert np.isnan(col[3, 4]) and np.isfinite(np.delete(col.ravel(), 3 * W + 4)).all()


def test_cli_decode_applies_the_importers_filters(tmp_path, scene, capsys, monkeypatch):
  """As import-captures: a scene whose views look swapped gets pattern maps but no disparity,
  named on stderr, exit code 1, the other scenes decoded; a disparity below 0 or beyond the
  width is written unknown, and its partner in the other view too."""
  root = tmp_path / "ds"
  good = _write_scene_folder(root, "a", scene, meta={"code": "gray"})
  swapped = _write_scene_folder(root, "b", scene[::-1], meta={"code": "gray"})
  assert cli.main(["decode", str(root)]) == 1
  out, err = capsys.readouterr()
  assert err.count("\n") == 1 and f"scene {swapped}: raw0 and raw1 look swapped" in err
  assert "no disparity written" in err and "Traceback" not in err
  assert (swapped / "sl0").is_dir() and not (swapped / "disp0.pfm").exists()
  assert not (swapped / "disp1.pfm").exists() and (good / "disp0.pfm").exists()
  assert "disparity files written: 2" in out

  # Impossible matches planted into the matcher's output: a negative disparity at (3, 40) with a
  # consistent partner in the right view, and one beyond the width at (4, 50).
  from sljax.commands import decode as decode_cmd  # pylint: disable=import-outside-toplevel
  match = decode_cmd.match_views
  d = read_pfm(good / "disp0.pfm")[4, 50]
  partner = 50 - int(round(float(d)))  # the right pixel of the left pixel (4, 50)

  def planted(dec, *a, **k):
    match(dec, *a, **k)
    d0, d1 = dec.disp0.copy(), dec.disp1.copy()
    d0[3, 40], d1[3, 42] = -2.0, -2.0  # right pixel 42 = 40 - (-2)
    assert np.isfinite(d0[4, 50]) and np.isfinite(d1[4, partner])
    d0[4, 50] = W + 5.0                # its right partner was consistent until now
    dec.disp0, dec.disp1 = d0, d1
    return dec

  monkeypatch.setattr(decode_cmd, "match_views", planted)
  for f in ("disp0.pfm", "disp1.pfm"):
    (good / f).unlink()
  assert cli.main(["decode", str(root), "--overwrite"]) == 1
  capsys.readouterr()
  d0, d1 = read_pfm(good / "disp0.pfm"), read_pfm(good / "disp1.pfm")
  assert np.isinf(d0[3, 40]) and np.isinf(d1[3, 42]) and np.isinf(d0[4, 50])
  assert np.isinf(d1[4, partner])  # the left-right check again: its partner went too
  for d in (d0, d1):
    assert (np.isfinite(d) & ((d < 0) | (d > W))).sum() == 0
  assert np.isfinite(d0).mean() > 0.5  # the rest kept


def test_cli_decode_is_all_or_nothing(tmp_path, scene, capsys, monkeypatch):
  """A capture that fails only while the last scene decodes (its files pass every check):
  every scene stays as it was, byte for byte: none decoded (absent stays absent) and, with
  --overwrite, the earlier decoding of the others kept. A stream that does not inflate is
  named before anything is decoded."""
  from sljax.commands import decode as command  # pylint: disable=import-outside-toplevel
  real = command.decode_views

  def fails_in_2bad(raw0, raw1, code, config, projector, where):
    if "2bad" in where[0]:
      raise SljaxError(f"{where[1]}: the codes do not decode")
    return real(raw0, raw1, code, config, projector=projector, where=where)
  root = tmp_path / "ds"
  for name in ("0ok", "1ok"):
    _write_scene_folder(root, name, scene, meta={"code": "gray"})
  assert cli.main(["decode", str(root)]) == 0
  capsys.readouterr()
  _write_scene_folder(root, "2bad", scene, meta={"code": "gray"})
  monkeypatch.setattr(command, "decode_views", fails_in_2bad)
  before = toys.tree(root)
  assert cli.main(["decode", str(root), "--overwrite", "--bit-threshold", "5"]) == 2
  _one_line_error(capsys, "2bad: raw1: the codes do not decode", "nothing was decoded")
  assert toys.tree(root) == before
  fresh = tmp_path / "fresh"
  for name in ("0ok", "1ok", "2bad"):
    _write_scene_folder(fresh, name, scene, meta={"code": "gray"})
  before = toys.tree(fresh)
  assert cli.main(["decode", str(fresh)]) == 2
  capsys.readouterr()
  assert toys.tree(fresh) == before
  monkeypatch.undo()
  bad = fresh / "2bad" / "raw1" / "p003.png"
  toys.break_deflate(bad)  # caught by the checks before decoding (sljax.io.headers)
  before = toys.tree(fresh)
  assert cli.main(["decode", str(fresh)]) == 2
  _one_line_error(capsys, f"{bad}", "does not inflate")
  assert toys.tree(fresh) == before


def test_cli_decode_interrupted_leaves_nothing_partial(tmp_path, scene, capsys, monkeypatch):
  """Ctrl-C while the second scene's disparity is written: exit 130 and no scene changed."""
  root = tmp_path / "ds"
  for name in ("0", "1"):
    _write_scene_folder(root, name, scene, meta={"code": "gray"})
  before = toys.tree(root)
  calls, real = [], decode.write_pfm

  def write_pfm(path, disp):
    calls.append(path)
    if len(calls) == 3:  # the first scene's two files are staged by now
      gc.collect()  # not inside jax's gc callback, which would report it as ignored
      raise KeyboardInterrupt
    real(path, disp)

  monkeypatch.setattr(decode, "write_pfm", write_pfm)
  assert cli.main(["decode", str(root)]) == 130
  assert "interrupted" in capsys.readouterr().err
  assert toys.tree(root) == before and len(calls) == 3
