"""Property-based campaign over the readers of a real rig's files: OpenCV calibration YAML,
capture folders for `sljax import-captures`, and stereo video for `sljax predict --video`
(tests/fuzz_kit.py states the property). Each valid file is written by sljax's own writers (or,
for video, OpenCV's writer as the video tests do), then mutated."""

import functools
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
from hypothesis import example, given
from hypothesis import strategies as st

import fuzz_kit as fk
from sljax.capture import captures
from sljax.capture import rig as rigs
from sljax.depth import video
from sljax.io import images

FOLDER = fk.FOLDER
SIZE = (16, 12)  # (W, H) of the frames
CAL = rigs.StereoCalibration(
    m1=np.array([[20.0, 0, 8], [0, 20, 6], [0, 0, 1]]), d1=np.zeros((1, 5)),
    m2=np.array([[20.0, 0, 8], [0, 20, 6], [0, 0, 1]]), d2=np.zeros((1, 5)), r=np.eye(3),
    t=np.array([[-50.0], [0], [0]]), size=SIZE)



@functools.cache
def valid_yaml() -> bytes:
  """A calibration as write_calibration writes it (OpenCV FileStorage YAML)."""
  with tempfile.TemporaryDirectory() as d:
    rigs.write_calibration(Path(d) / "calib.yml", CAL)
    return (Path(d) / "calib.yml").read_bytes()


@fk.fuzz(200)
@given(st.one_of(fk.text_lie(valid_yaml()), fk.text_lie(valid_yaml()).flatmap(fk.text_lie),
                 fk.mutated_bytes(valid_yaml()), st.just(FOLDER)))
@example(valid_yaml().replace(b"M1:", b"\xcd1:"))  # was a UnicodeDecodeError from OpenCV's keys
@example(valid_yaml().replace(b"dt: d\n   data: [ 1.", b"dt:\x80d\n   data: [ 1."))  # and its dt
def test_calibration_yaml(data):
  """read_calibration: a checked calibration or one line naming the file."""
  with fk.placed("calib.yml", data) as path:
    cal = fk.check(lambda: rigs.read_calibration(path), path, fk.allowance(path))
    if cal is not fk.REFUSED:
      for m in (cal.m1, cal.m2, cal.r, cal.t, cal.d1, cal.d2):
        assert np.isfinite(m).all()


def test_a_matrix_without_cols_does_not_damage_the_heap(tmp_path):
  """Regression of the long campaign: M1 without `cols:` made OpenCV 5.0 write its 9 values into
  a Mat of 3 x 0 before its assertion, and a few reads later the process aborted (double free).
  The matrix is now checked first; 50 reads in a child process end with one line each."""
  path = tmp_path / "calib.yml"
  path.write_bytes(valid_yaml().replace(b"   rows: 3\n   cols: 3\n", b"   rows: 3\n", 1))
  code = ("import sys\nfrom sljax.capture import rig\nfrom sljax.errors import SljaxError\n"
          "for _ in range(50):\n  try:\n    rig.read_calibration(sys.argv[1])\n"
          "  except SljaxError as e:\n    said = str(e)\nprint(said)\n")
  done = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True,
                        cwd=Path(__file__).parent.parent, timeout=120, check=False)
  assert done.returncode == 0, done.stderr[-500:]
  assert "lacks the matrix M1" in done.stdout


ROLES = ("white", "black", "p000", "p001", "p002", "i000", "i001", "i002")


def _frame(role: str, shift: int) -> np.ndarray:
  """One frame of a 3-bit Gray code over 8 projector columns, 2 pixels each, seen by a camera
  whose pixel x sees projector pixel x + shift (white 0.9, black 0.1)."""
  c = np.clip((np.arange(SIZE[0]) + shift) // 2, 0, 7)
  if role in ("white", "black"):
    row = np.full(SIZE[0], 0.9 if role == "white" else 0.1)
  else:
    bit = ((c ^ (c >> 1)) >> (2 - int(role[1:]))) & 1
    row = 0.1 + 0.8 * (bit if role[0] == "p" else 1 - bit)
  return np.tile(row.astype(np.float32), (SIZE[1], 1))


def _frames(root: Path) -> tuple[Path, Path]:
  """LEFT and RIGHT capture folders in the sljax layout (white, black, 3 patterns and their
  inverses) as write_image writes them, of a plane at disparity 2: it imports."""
  for cam, shift in (("left", 0), ("right", 2)):
    (root / cam).mkdir()
    for role in ROLES:
      images.write_image(root / cam / f"{role}.png", _frame(role, shift))
  return root / "left", root / "right"


@st.composite
def capture_damage(draw):
  """(camera, frame or None for the folder, bytes or FOLDER): one place of a capture damaged."""
  cam = draw(st.sampled_from(["left", "right"]))
  if draw(st.integers(0, 9)) == 0:
    return cam, None, b"not a folder"  # a file where a camera's folder goes
  role = draw(st.sampled_from(ROLES))
  with tempfile.TemporaryDirectory() as d:
    images.write_image(Path(d) / "f.png", _frame(role, 0 if cam == "left" else 2))
    valid = (Path(d) / "f.png").read_bytes()
  return cam, role, draw(fk.mutated_png(valid) | st.just(FOLDER))


@fk.fuzz(40)
@given(capture_damage())
def test_capture_folders(damage):
  """import_captures over a damaged capture: a scene, or one line naming the damaged place
  (the frame, its camera's folder or the output) and no output folder."""
  cam, role, data = damage
  with tempfile.TemporaryDirectory() as d:
    left, right = _frames(Path(d))
    folder = Path(d) / cam
    path = folder if role is None else folder / f"{role}.png"
    if role is None:
      shutil.rmtree(folder)
      path.write_bytes(data)
    else:
      fk.place(path, data)
    out = Path(d) / "scene"
    config = captures.ImportConfig(layout="sljax", row_check=False)
    bound = fk.allowance(left, right, per_byte=fk.IMAGE_PER_BYTE)
    with fk.opencv_claims(bound):
      got = fk.check(lambda: captures.import_captures(left, right, out, CAL, config,
                                                      progress=False),
                     [path, "LEFT", "RIGHT", out], bound)
    if got is fk.REFUSED:
      assert not out.exists()  # nothing partial in the output place
    else:
      assert (out / "disp0.pfm").is_file() and (out / "meta.json").is_file()


@functools.cache
def valid_video() -> bytes:
  """A short side-by-side stereo video as OpenCV's mp4 writer writes it."""
  with tempfile.TemporaryDirectory() as d:
    path = Path(d) / "v.mp4"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (32, 16))
    rng = np.random.default_rng(0)
    for _ in range(3):
      w.write(rng.integers(0, 255, (16, 32, 3), dtype=np.uint8))
    w.release()
    return path.read_bytes()


@fk.fuzz(60)
@given(fk.mutated_bytes(valid_video(), max_edits=2) | st.just(FOLDER))
def test_video(data):
  """open_video and read_frames of a damaged video: frames of the stated size, or one line
  naming the file."""
  with fk.placed("v.mp4", data) as path:
    bound = fk.allowance(path, per_byte=fk.IMAGE_PER_BYTE)

    def read():
      source = video.open_video([path], "side-by-side")
      return source, list(video.read_frames(source))
    got = fk.check(read, path, bound)
    if got is not fk.REFUSED:
      source, frames = got
      for _, left, right in frames:
        assert left.shape == right.shape == (source.view_size[1], source.view_size[0], 3)
