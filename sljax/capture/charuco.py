"""Stereo calibration from a folder pair of ChArUco board images (OpenCV's aruco module).

The i-th left image (ordered by the integer in its name, as capture frames are) and the i-th
right image show the board at the same moment. Each camera is calibrated on its own
(cv2.calibrateCamera on the ChArUco corners each image shows; distortion k1 k2 p1 p2, k3 fixed
at 0: a few board images fit k3 to their noise), then the pair
(cv2.stereoCalibrate on the corners both images of a pair show, intrinsics fixed). Lengths are
in the unit of the square size, so T comes out in it.
"""

import dataclasses
import re
import sys
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from sljax.capture import frames
from sljax.capture.rig import StereoCalibration, check_calibration
from sljax.errors import SljaxError, require

MIN_CORNERS = 6  # ChArUco corners an image must show to constrain a pose
MIN_VIEWS = 3    # image pairs a calibration needs


@dataclasses.dataclass(frozen=True)
class Board:
  """A ChArUco board: squares across and down, square and marker side (one length unit), and
  the ArUco dictionary's OpenCV name (e.g. DICT_5X5_100)."""
  squares: tuple[int, int]
  square: float
  marker: float
  dictionary: str = "DICT_5X5_100"

  def check(self) -> "Board":
    """self; SljaxError naming the bad value."""
    sx, sy = self.squares
    require(sx >= 2 and sy >= 2, f"--board {sx}x{sy}: at least 2 x 2 squares")
    require(0 < self.marker < self.square, f"--marker {self.marker:g}: must be positive and "
            f"smaller than the square ({self.square:g})")
    require(re.fullmatch(r"DICT_\w+", self.dictionary) is not None
            and hasattr(cv2.aruco, self.dictionary),
            f"--dictionary {self.dictionary}: not an OpenCV ArUco dictionary (e.g. DICT_4X4_50, "
            "DICT_5X5_100, DICT_6X6_250, DICT_APRILTAG_36h11)")
    need = sx * sy // 2
    size = int(re.search(r"_(\d+)$", self.dictionary).group(1)) if re.search(
        r"_(\d+)$", self.dictionary) else None
    require(size is None or size >= need, f"--dictionary {self.dictionary}: {size} markers, a "
            f"{sx}x{sy} board needs {need}")
    return self


def opencv_board(board: Board) -> "cv2.aruco.CharucoBoard":
  """The OpenCV board object of a Board."""
  dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
  return cv2.aruco.CharucoBoard(tuple(board.squares), float(board.square), float(board.marker),
                                dictionary)


def detect(image: np.ndarray, detector) -> tuple[np.ndarray, np.ndarray]:
  """(corners Nx2 float32, ids N) of the ChArUco corners an image shows (N may be 0)."""
  g = frames.grey(image)
  if g.dtype != np.uint8:  # the detector wants 8 bits
    g = cv2.convertScaleAbs(g, alpha=255.0 / max(int(g.max()), 1))
  corners, ids, _, _ = detector.detectBoard(g)
  if ids is None or corners is None:
    return np.zeros((0, 2), np.float32), np.zeros(0, np.int32)
  return corners.reshape(-1, 2).astype(np.float32), ids.ravel().astype(np.int32)


def _images(spec: str, what: str) -> list[Path]:
  return frames.numbered_frames(frames.list_frames(spec, what), what)


def calibrate_stereo(left: str, right: str, board: Board, progress: bool = True
                     ) -> tuple[StereoCalibration, dict[str, float]]:
  """(calibration, {rms_left, rms_right, rms_stereo, pairs}) from the two folders' images."""
  board.check()
  cb = opencv_board(board)
  detector = cv2.aruco.CharucoDetector(cb)
  chess = cb.getChessboardCorners().astype(np.float32)
  lefts, rights = _images(left, "--charuco LEFT_DIR"), _images(right, "--charuco RIGHT_DIR")
  require(len(lefts) == len(rights), f"--charuco: {len(lefts)} left images but {len(rights)} "
          "right images; the i-th left image pairs with the i-th right one")
  pairs = list(zip(lefts, rights))
  size = None
  per_camera = ([], []), ([], [])  # (object points, image points) per camera
  stereo = [], [], []
  for paths in tqdm(pairs, desc="charuco: detecting", unit="pair", file=sys.stderr,
                    disable=not progress or None, leave=False):
    found = []
    for cam, path in enumerate(paths):
      img = frames.read_frame(path)
      shape = (img.shape[1], img.shape[0])
      size = size or shape
      require(shape == size, f"{path}: size {shape[0]}x{shape[1]} differs from the first board "
              f"image's {size[0]}x{size[1]}")
      corners, ids = detect(img, detector)
      found.append((corners, ids))
      if ids.size >= MIN_CORNERS:
        per_camera[cam][0].append(chess[ids])
        per_camera[cam][1].append(corners)
    common, i0, i1 = np.intersect1d(found[0][1], found[1][1], return_indices=True)
    if common.size >= MIN_CORNERS:
      stereo[0].append(chess[common])
      stereo[1].append(found[0][0][i0])
      stereo[2].append(found[1][0][i1])
  for cam, name in enumerate(("left", "right")):
    require(len(per_camera[cam][0]) >= MIN_VIEWS,
            f"--charuco {(left, right)[cam]}: the board ({board.squares[0]}x{board.squares[1]} "
            f"squares, {board.dictionary}) was found in {len(per_camera[cam][0])} of "
            f"{len(pairs)} {name} images (at least {MIN_CORNERS} corners each); "
            f"{MIN_VIEWS} are needed: check --board and --dictionary")
  require(len(stereo[0]) >= MIN_VIEWS,
          f"--charuco: only {len(stereo[0])} image pairs show {MIN_CORNERS} or more of the same "
          f"corners in both views; {MIN_VIEWS} are needed")
  mono = []
  for cam in (0, 1):
    rms, m, d, _, _ = cv2.calibrateCamera(per_camera[cam][0], per_camera[cam][1], size, None,
                                          None, flags=cv2.CALIB_FIX_K3)
    mono.append((rms, m, d))
  rms, m1, d1, m2, d2, r, t, _, _ = cv2.stereoCalibrate(
      stereo[0], stereo[1], stereo[2], mono[0][1], mono[0][2], mono[1][1], mono[1][2], size,
      flags=cv2.CALIB_FIX_INTRINSIC)
  as64 = lambda a, *shape: np.asarray(a, np.float64).reshape(*shape)  # noqa: E731
  cal = StereoCalibration(m1=as64(m1, 3, 3), d1=as64(d1, 1, -1), m2=as64(m2, 3, 3),
                          d2=as64(d2, 1, -1), r=as64(r, 3, 3), t=as64(t, 3, 1), size=size,
                          where=f"ChArUco calibration of {left} + {right}")
  if not np.all(np.isfinite(np.concatenate([a.ravel() for a in cal.as_dict().values()]))):
    raise SljaxError("--charuco: the calibration did not converge (NaN values); more board "
                     "images at varied angles help")
  check_calibration(cal)
  return cal, {"rms_left": float(mono[0][0]), "rms_right": float(mono[1][0]),
               "rms_stereo": float(rms), "pairs": len(stereo[0])}
