"""What `sljax import-captures` will not write: a capture it cannot trust is refused with one
line naming the likely cause, before anything is written; the disparities it cannot trust are
made unknown.

Refused (the shares measured on the rendered captures of tests/test_captures.py; see
docs/captures.md):
- almost nothing decodes: the coarsest column bit, the easiest to decode, is known on under
  MIN_LIT of a view's pixels (the projector off, or the exposure far off: white - black under
  the shadow threshold everywhere, or both saturated). Correct captures: 73% and 88%; the
  projector off or every frame saturated: 0%.
- LEFT and RIGHT swapped: more than half of a view's matched disparities are negative, the rule
  sljax.data.checks.negative_share applies when a scene loads, so that an import never writes a
  scene the loader refuses. Correct captures: none negative; swapped, by cameras alike: 99%.
- rectified rows that do not match (the opencv layout's row frames, with the row check): the
  row check refuses more than MAX_ROW_REFUSED of the left matches it can judge: the
  calibration is of another rig (its rotation or focal lengths) or the views are swapped.
  Correct captures, clean or degraded: 0%; R tilted 2 degrees about the baseline: 100%; the
  left focal length 20% longer: 62%; swapped views: 100%. A wrong baseline LENGTH cannot be
  seen in the images (rectification does not depend on it: it scales depth, not disparity).

Unknown, never written: a disparity below 0 or above the rectified width (x_left - x_right
cannot be either), and then its partner in the other view (the left-right check again).
"""

import numpy as np

from sljax.data.checks import negative_share
from sljax.errors import SljaxError
from sljax.sl.match import lr_check_disparities
from sljax.sl.stereo import StereoDecoded

MIN_LIT = 0.05         # least share of a view's pixels where the coarsest column bit decodes
MAX_ROW_REFUSED = 0.25  # most share of the judged left matches the row check may refuse


def check_lit(decoded: StereoDecoded, where: tuple[str, str]) -> None:
  """SljaxError when a view's coarsest column bit decodes on under MIN_LIT of its pixels."""
  for view, name in zip((decoded.left, decoded.right), where):
    share = float(np.isfinite(view.bits[..., 0]).mean())
    if share < MIN_LIT:
      raise SljaxError(f"{name}: the projector's coarsest stripe decodes on {share:.1%} of the "
                       f"pixels (under {MIN_LIT:.0%}): was the projector off, or the exposure "
                       "wrong (white - black under --shadow-threshold, or both saturated)? "
                       "Nothing written")


def swapped(decoded: StereoDecoded) -> tuple[str, float] | None:
  """(view, share) of a view whose matched disparities are mostly negative, else None."""
  # The rule by which checks.negative_share refuses a scene on load: LEFT and RIGHT swapped.
  for view, d in zip(("left", "right"), (decoded.disp0, decoded.disp1)):
    share = negative_share(d)
    if share is not None:
      return view, share
  return None


def check_signs(decoded: StereoDecoded, where: tuple[str, str]) -> None:
  """SljaxError when the views look swapped (swapped())."""
  found = swapped(decoded)
  if found is not None:
    view, share = found
    raise SljaxError(f"{where[0]} and {where[1]} look swapped: {share:.0%} of the {view} "
                     "view's matched disparities are negative (x_left - x_right < 0); give "
                     "the left camera's frames first. Nothing written")


def check_rows(decoded: StereoDecoded, where: tuple[str, str], calibration: str) -> None:
  """SljaxError when the row check refused more than MAX_ROW_REFUSED of the left matches it
  judged: the rectified rows of the two views do not match. The likelier cause leads: a swap
  when most matched disparities are negative, else a calibration of another rig."""
  if decoded.rows is None or decoded.row_checked == 0:
    return
  share = decoded.row_rejected / decoded.row_checked
  if share <= MAX_ROW_REFUSED:
    return
  rows = (f"the row check refused {share:.0%} of {decoded.row_checked} matches (their pixels "
          f"see other projector rows; at most {MAX_ROW_REFUSED:.0%} may)")
  negative = negative_share(decoded.disp0)
  if negative is not None:
    raise SljaxError(f"{where[0]} and {where[1]} look swapped: {negative:.0%} of the left "
                     f"view's matched disparities are negative and {rows}; or the calibration "
                     f"({calibration}) is of another rig. Nothing written")
  raise SljaxError(f"the rectified rows of the two views do not match: {rows}: is the "
                   f"calibration ({calibration}) of another rig (rotation or focal lengths), or "
                   "are LEFT and RIGHT swapped? Nothing written")


def plausible(disp0: np.ndarray, disp1: np.ndarray, width: int, lr_tolerance: float
              ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
  """(disp0, disp1, pixels made unknown per view): disparities below 0 or above width become
  inf, then those whose partner in the other view did (the left-right check again)."""
  outside = [np.isfinite(d) & ((d < 0) | (d > width)) for d in (disp0, disp1)]
  if not any(o.any() for o in outside):  # nothing to drop: the matches stay as checked
    return disp0, disp1, (0, 0)
  known = [int(np.isfinite(d).sum()) for d in (disp0, disp1)]
  d0, d1 = lr_check_disparities(*(np.where(o, np.float32(np.inf), d).astype(np.float32)
                                  for o, d in zip(outside, (disp0, disp1))), lr_tolerance)
  return d0, d1, (known[0] - int(np.isfinite(d0).sum()), known[1] - int(np.isfinite(d1).sum()))
