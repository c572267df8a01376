"""The files of a capture: which image is which projected frame.

Frames. Each camera's frames are a folder or a glob of one image per projected frame (.png,
.bmp, .jpg, .tif; 8 or 16 bits; grey or colour, decoded on grey: BT.601 luma as OpenCV's
cvtColor). The opencv layout orders them by the last integer in the file name, the smallest
being frame 0 (so 0- and 1-based numbering both work); the sljax layout names them (white,
black, pNNN, iNNN). 16-bit files whose values all fit 12 bits are 12-bit data and are scaled to
the 16-bit range (the rule `sljax info` warns about).

Layouts. opencv: what OpenCV's structured_light.GrayCodePattern generates for a W x H projector,
in the order capture scripts save it: n = ceil(log2 W) column bits and m = ceil(log2 H) row bits;
frames 2k and 2k + 1 are column bit k and its inverse (k = 0..n-1, most significant first; lit
where the reflected Gray code g = c ^ (c >> 1) of the projector column c has that bit set),
frames 2n + 2j and 2n + 2j + 1 row bit j and its inverse, then the all-white and the all-black
frame. That is sljax's own Gray code (sljax.sl.codes: pattern k is bit n-1-k of the Gray code,
coarsest first), so column pair k becomes p{k:03d} / i{k:03d} unchanged. sljax: the project's
own names, patterns coarsest first.
"""

import glob
import os
import re
from collections.abc import Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np

from sljax.errors import SljaxError, require
from sljax.io import files
from sljax.io.images import decode
from sljax.sl import codes
from sljax.sl.decode import count_patterns

FRAME_EXTENSIONS = (".png", ".bmp", ".jpg", ".jpeg", ".tif", ".tiff")
LAYOUTS = ("opencv", "sljax")
_SLJAX_NAME = re.compile(r"^(white|black|[pi]\d{3})$")
_NUMBER = re.compile(r"\d+")
_GLOB = re.compile(r"[*?\[]")


def bit_counts(projector: tuple[int, int]) -> tuple[int, int]:
  """(n, m) = (ceil(log2 W), ceil(log2 H)): the column and row bits of a W x H projector."""
  w, h = projector
  require(w >= 2 and h >= 2, f"--projector {w}x{h}: width and height must be at least 2")
  return codes.num_bits(w), codes.num_bits(h)


def opencv_roles(projector: tuple[int, int]) -> list[str]:
  """The role of each frame of OpenCV's GrayCodePattern capture, in order: p000, i000, ...
  (column bits and inverses), rp000, ri000, ... (row bits), white, black."""
  n, m = bit_counts(projector)
  cols = [f"{kind}{k:03d}" for k in range(n) for kind in ("p", "i")]
  rows = [f"r{kind}{j:03d}" for j in range(m) for kind in ("p", "i")]
  return cols + rows + ["white", "black"]


def projector_frames(projector: tuple[int, int]) -> Iterator[tuple[str, np.ndarray]]:
  """(role, HxW uint8 image, 255 lit) of every frame to project for the opencv layout, in
  order: what OpenCV's GrayCodePattern.generate gives, then white and black."""
  w, h = projector
  n, m = bit_counts(projector)
  cols, rows = codes.patterns("gray", w), codes.patterns("gray", h)
  for k in range(n):
    lit = np.broadcast_to(cols[k][None, :] * np.uint8(255), (h, w))
    yield f"p{k:03d}", lit.copy()
    yield f"i{k:03d}", 255 - lit
  for j in range(m):
    lit = np.broadcast_to(rows[j][:, None] * np.uint8(255), (h, w))
    yield f"rp{j:03d}", lit.copy()
    yield f"ri{j:03d}", 255 - lit
  yield "white", np.full((h, w), 255, np.uint8)
  yield "black", np.zeros((h, w), np.uint8)


def parse_projector(text: str) -> tuple[int, int]:
  """'1920x1080' -> (1920, 1080); SljaxError otherwise."""
  m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", str(text))
  require(m is not None, f"--projector {text!r}: expected WIDTHxHEIGHT, e.g. 1920x1080")
  return int(m.group(1)), int(m.group(2))


def frame_number(path: Path) -> int | None:
  """The last integer in a file name's stem (pattern_cam1_im12.png -> 12), None without one."""
  found = _NUMBER.findall(path.stem)
  return int(found[-1]) if found else None


def list_frames(spec: str | os.PathLike, what: str) -> list[Path]:
  """The image files of a folder or a glob (unsorted); SljaxError when there are none."""
  text = os.fspath(spec)
  path = Path(text)
  if path.is_dir():
    found = [p for p in path.iterdir() if p.is_file() and not files.is_temporary(p)
             and p.suffix.lower() in FRAME_EXTENSIONS]
    require(found, f"{what} {text}: no frames ({', '.join(FRAME_EXTENSIONS)}) in the folder")
    return found
  if path.is_file():
    raise SljaxError(f"{what} {text}: a single file; give the folder of the frames or a glob "
                     "such as 'caps/pattern_cam1_im*.png'")
  if not _GLOB.search(text):
    raise SljaxError(f"{what} {text}: no such folder (give a folder or a glob of the frames)")
  found = [Path(p) for p in glob.glob(text) if Path(p).is_file()]
  require(found, f"{what} {text}: the glob matches no file")
  for p in found:
    require(p.suffix.lower() in FRAME_EXTENSIONS,
            f"{p}: not a frame format sljax reads ({', '.join(FRAME_EXTENSIONS)})")
  return found


def numbered_frames(paths: Sequence[Path], what: str) -> list[Path]:
  """Frames ordered by the integer in their names; SljaxError for a name without one, two
  frames of one number or a gap in the numbering."""
  numbered = {}
  for p in paths:
    k = frame_number(p)
    require(k is not None, f"{p}: no frame number in the file name ({what} frames are ordered by "
            "the integer in their names)")
    require(k not in numbered, f"{what}: {numbered.get(k)} and {p} have the same frame number {k}")
    numbered[k] = p
  order = sorted(numbered)
  for a, b in zip(order, order[1:]):
    require(b == a + 1, f"{what}: frame numbers jump from {a} ({numbered[a].name}) to {b} "
            f"({numbered[b].name}); frame {a + 1} is missing")
  return [numbered[k] for k in order]


def assign_roles(paths: Sequence[Path], layout: str, projector: tuple[int, int] | None,
                 what: str) -> dict[str, Path]:
  """{role: file} of one camera's frames in a layout (opencv or sljax) for a (W, H) projector;
  SljaxError when the frames do not fit them."""
  if layout == "opencv":
    require(projector is not None, "--projector WxH is needed by the opencv layout")
    roles = opencv_roles(projector)
    n, m = bit_counts(projector)
    w, h = projector
    require(len(paths) == len(roles),
            f"{what}: {len(paths)} frames, but the opencv layout of a {w}x{h} projector has "
            f"{len(roles)} ({2 * n} column frames for {n} bits, {2 * m} row frames for {m} bits, "
            "white, black)")
    return dict(zip(roles, numbered_frames(paths, what)))
  require(layout == "sljax", f"unknown layout {layout!r}; expected one of {LAYOUTS}")
  named: dict[str, Path] = {}
  for p in paths:
    require(_SLJAX_NAME.match(p.stem) is not None,
            f"{p}: not a frame name of the sljax layout (white, black, p000, p001, ..., i000, ...)")
    require(p.stem not in named, f"{what}: {named.get(p.stem)} and {p} are both frame {p.stem}")
    named[p.stem] = p
  for key in ("white", "black"):
    require(key in named, f"{what}: no {key} frame (the sljax layout names it {key}.png)")
  t = count_patterns(named, what)
  inverses = {int(k[1:]) for k in named if k[0] == "i"}
  if inverses:  # all or none: decoding compares every pattern with its inverse
    odd = sorted(inverses ^ set(range(t)))
    if odd:
      k = odd[0]
      raise SljaxError(f"{what}: " + (f"inverse i{k:03d} has no pattern p{k:03d}" if k in inverses
                                      else f"pattern p{k:03d} has no inverse i{k:03d}"))
  if projector is not None:
    n = bit_counts(projector)[0]
    require(t == n, f"{what}: {t} column patterns, but a {projector[0]}-column projector "
            f"has {n} (sljax layout)")
  return named


def read_frame(path: Path) -> np.ndarray:
  """A frame as OpenCV decodes it: uint8 or uint16, HxW or HxWx3 BGR (alpha dropped)."""
  img = decode(path)  # sized from its header first: a huge claim is one line, not cv2.error
  if img.dtype not in (np.uint8, np.uint16):
    raise SljaxError(f"{path}: {img.dtype} samples; frames must be 8- or 16-bit images")
  if img.ndim == 3 and img.shape[2] == 4:
    img = img[..., :3]
  if img.ndim == 3 and img.shape[2] == 1:
    img = img[..., 0]
  if img.ndim == 3 and img.shape[2] != 3:
    raise SljaxError(f"{path}: {img.shape[2]} channels; frames must be grey or colour")
  return img


def grey(frame: np.ndarray) -> np.ndarray:
  """Luma of a BGR frame (as cv2.cvtColor, BT.601), or the grey frame itself; dtype kept."""
  return cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame
