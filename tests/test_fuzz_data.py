"""Property-based campaign over the scene's readers: images, PFM, calib.txt, meta.json and
dataset.json (tests/fuzz_kit.py states the property). Each valid file is written by sljax's own
writers, then mutated."""

import functools
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import example, given
from hypothesis import strategies as st

import fuzz_kit as fk
from sljax.data import camera, dataset, pfm, scene
from sljax.io import images

FOLDER = fk.FOLDER



def _valid(write, name: str) -> bytes:
  """The bytes sljax's writer `write(path)` produces for a file called name."""
  with tempfile.TemporaryDirectory() as d:
    path = Path(d) / name
    write(path)
    return path.read_bytes()


@functools.cache
def valid_png(depth: int = 8, colour: bool = True) -> bytes:
  """A small image as write_image writes it."""
  rng = np.random.default_rng(depth + colour)
  shape = (12, 16, 3) if colour else (12, 16)
  return _valid(lambda p: images.write_image(p, rng.random(shape, dtype=np.float32), depth),
                "im0.png")


@functools.cache
def valid_pfm() -> bytes:
  """A small disparity map, inf (unknown) included, as write_pfm writes it."""
  d = np.random.default_rng(1).uniform(1, 30, (12, 16)).astype(np.float32)
  d[0, :3] = np.inf
  return _valid(lambda p: pfm.write_pfm(p, d), "disp0.pfm")


CALIB = camera.Calib(cam0=np.array([[500.0, 0, 8], [0, 500, 6], [0, 0, 1]]),
                     cam1=np.array([[500.0, 0, 9.5], [0, 500, 6], [0, 0, 1]]), doffs=1.5,
                     baseline=120.25, width=16, height=12, ndisp=64, vmin=2.0, vmax=40.0)


@functools.cache
def valid_calib() -> bytes:
  """calib.txt as write_calib writes it."""
  return _valid(lambda p: camera.write_calib(p, CALIB), "calib.txt")


def pngs() -> st.SearchStrategy[bytes]:
  """Mutated 8- and 16-bit, grey and colour PNGs."""
  return st.sampled_from([(8, True), (16, True), (8, False), (16, False)]).flatmap(
      lambda k: fk.mutated_png(valid_png(*k)))


@fk.fuzz(150)
@given(pngs() | st.just(FOLDER))
@example(fk.png_fix_crcs(valid_png()[:16] + (4000).to_bytes(4, "big") + (4000).to_bytes(4, "big")
                         + valid_png()[24:]))  # IHDR claims 4000x4000 in a few hundred bytes
@example(valid_png()[:33] + (0xFFFE0000).to_bytes(4, "big") + valid_png()[37:])  # IDAT claims
def test_image(data):  # 4 GiB: OpenCV took seconds over it (found by the deadline)
  """read_image of a damaged PNG: the right image or one line naming it."""
  with fk.placed("im0.png", data) as path:
    bound = fk.allowance(path, per_byte=fk.IMAGE_PER_BYTE)
    with fk.opencv_claims(bound):
      img = fk.check(lambda: images.read_image(path), path, bound)
    if img is not fk.REFUSED:
      assert img.dtype == np.float32 and img.ndim == 3 and img.shape[2] in (1, 3)
      assert np.isfinite(img).all() and img.min() >= 0 and img.max() <= 1


def pfms() -> st.SearchStrategy[bytes]:
  """Mutated PFMs: header lies (sizes, scale), byte edits."""
  return st.one_of(fk.text_lie(valid_pfm()[:20]).map(lambda h: h + valid_pfm()[20:]),
                   fk.mutated_bytes(valid_pfm()), st.just(FOLDER))


@fk.fuzz(200)
@given(pfms())
def test_pfm(data):
  """read_pfm: the header's array or one line naming the file."""
  with fk.placed("disp0.pfm", data) as path:
    out = fk.check(lambda: pfm.read_pfm(path), path, fk.allowance(path))
    if data == valid_pfm():
      assert out.shape == (12, 16)
    if out is not fk.REFUSED:
      assert out.dtype == np.float32 and out.ndim in (2, 3)


def calibs() -> st.SearchStrategy[bytes]:
  """Mutated calib.txt files: values lied about, bytes edited (non-UTF-8 among them)."""
  return st.one_of(fk.text_lie(valid_calib()), fk.text_lie(valid_calib()).flatmap(fk.text_lie),
                   fk.mutated_bytes(valid_calib()), st.just(FOLDER))


@fk.fuzz(200)
@given(calibs())
def test_calib(data):
  """read_calib: a Calib whose numbers are usable, or one line naming the file."""
  with fk.placed("calib.txt", data) as path:
    out = fk.check(lambda: camera.read_calib(path), path, fk.allowance(path))
    if out is not fk.REFUSED:
      assert camera.calib_problem(out) is None
      assert np.isfinite(out.cam0).all() and np.isfinite(out.cam1).all()


META = {"name": "a", "group": "g1", "code": "gray", "source": "synthetic", "patterns": 7}


def _scene(root: Path) -> Path:
  """A minimal valid scene under root (views, disparity, calib, meta) by write_scene."""
  rng = np.random.default_rng(0)
  s = scene.Scene(name="a", im0=rng.random((12, 16, 3), dtype=np.float32),
                  im1=rng.random((12, 16, 3), dtype=np.float32),
                  disp0=rng.uniform(1, 30, (12, 16)).astype(np.float32), calib=CALIB,
                  meta=dict(META))
  scene.write_scene(root / "a", s)
  return root / "a"


@fk.fuzz(150)
@given(fk.mutated_json(META) | st.just(FOLDER))
@example(fk.dumps({**META, "code": True}))  # was named by the dataset's folder, not meta.json
def test_meta(data):
  """load_scene's meta.json (and a dataset's view of it): the object or one line naming it."""
  with tempfile.TemporaryDirectory() as d:
    folder = _scene(Path(d))
    path = folder / "meta.json"
    fk.place(path, data)
    bound = fk.allowance(folder)
    out = fk.check(lambda: scene.load_scene(folder, parts={"meta"}), path, bound)
    if out is not fk.REFUSED:
      assert isinstance(out.meta, dict)
      str(out.group)
    src = fk.check(lambda: dataset.FolderSource(d), path, bound)
    if src is not fk.REFUSED:
      assert src.code in (None, "binary", "gray")
      fk.check(lambda: (src.name(0), src.group(0), src.meta(0)), path, bound)


DATASET = {"splits": {"train": ["a"], "test": []}, "patterns": 7, "code": "gray"}


@fk.fuzz(150)
@given(fk.mutated_json(DATASET) | st.just(FOLDER))
def test_dataset_json(data):
  """FolderSource's dataset.json: splits and patterns that hold, or one line naming it."""
  with tempfile.TemporaryDirectory() as d:
    _scene(Path(d))
    path = Path(d) / "dataset.json"
    fk.place(path, data)
    bound = fk.allowance(Path(d))
    src = fk.check(lambda: dataset.FolderSource(d), path, bound)
    if src is not fk.REFUSED:
      assert src.num_patterns is None or src.num_patterns > 0
      fk.check(lambda: dataset.split_indices(src), path, bound)
