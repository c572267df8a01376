"""The verdicts on a scene's values that every reader shares: the loader (scene.load_scene),
the pre-flight check before training and `sljax info --check` (preflight.py), and `sljax info`.
One function per rule, so that what one of them refuses the others refuse with the same words.
A calibration's verdict is camera.calib_problem, applied by read_calib itself."""

import numpy as np


def negative_share(disparity: np.ndarray) -> float | None:
  """The share of a disparity map's known (finite) values that are negative, when it is more
  than half (a flipped sign: sljax reads x_left - x_right >= 0); None otherwise."""
  return _negative_share(disparity[np.isfinite(disparity)])


def _negative_share(known: np.ndarray) -> float | None:
  negative = np.count_nonzero(known < 0)
  return negative / known.size if negative * 2 > known.size else None


def usable_disparities(disparity: np.ndarray) -> int:
  """How many values of an HxW disparity map are known and possible: finite, 0 or more and at
  most the width (a match must lie inside the other view)."""
  d = disparity[np.isfinite(disparity)]
  return int(np.count_nonzero((d >= 0) & (d <= disparity.shape[1])))


def disparity_problem(disparity: np.ndarray, hw: tuple[int, int]) -> str | None:
  """Why a disparity map read for a scene of (height, width) hw is refused; None if it is not."""
  d = disparity
  if d.ndim != 2:
    return f"disparity must have one channel, got shape {d.shape}"
  if d.shape != tuple(hw):
    return f"size {d.shape[1]}x{d.shape[0]} differs from im0.png ({hw[1]}x{hw[0]})"
  known = d[np.isfinite(d)]  # once: the loader runs this on every map of every batch
  share = _negative_share(known)
  if share is not None:  # training would ignore them all, evaluation score them
    return (f"{share:.0%} of its known disparities are negative; disparities are x_left - "
            "x_right >= 0 in both views, unknown pixels inf or NaN (is the sign flipped?)")
  beyond = int(np.count_nonzero(known > d.shape[1]))
  # Mostly beyond: a large number marking unknown pixels, or a map of another scale. Training
  # ignores them, evaluation would score them as errors that large (1e30 px); the importer
  # makes such matches unknown (capture.refusals.plausible), by the same bound.
  if beyond * 2 > known.size:
    return (f"{beyond / known.size:.0%} of its known disparities are more than "
            f"{d.shape[1]} px, the image's width (no match lies that far; unknown pixels must "
            "be inf or NaN, not a large number)")
  return None


def no_usable_disparity(what: str, files: int) -> str:
  """The line for a set of scenes whose disparity maps hold nothing to train or score on."""
  return (f"{what}: none of the {files} disparity map(s) holds a usable disparity (all are "
          "unknown (inf or NaN) or out of range); training would learn nothing from them and "
          "validation report no error")
