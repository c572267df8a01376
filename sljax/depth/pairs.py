"""Depth from stereo pairs: find the pairs, run a predictor, write disparity, depth and points.

Inputs (`find_pairs`):
- LEFT RIGHT: two image files; calib.txt beside LEFT is used when present.
- a folder of scene folders (docs/format.md: any folder holding im0.png and im1.png); each
  scene's own calib.txt is used when present.
- a folder holding left/ and right/ image folders, paired by file name; PAIRS_DIR/calib.txt is
  used for every pair when present.
An explicit calibration file replaces all of these. A Middlebury calib.txt (any `.txt`) means the
views are already rectified. Any other calibration is an OpenCV stereo calibration (M1 D1 M2 D2
R T, the files and keys `sljax import-captures` reads; sljax.capture.rig): each pair is then
rectified with sljax.capture.rig's rectification before inference, and the outputs are in the
rectified left view, depth and points with the rectified geometry.

Outputs per pair (`OUTPUT_FILES`; into OUT for a single pair, OUT/<pair name>/ otherwise):
disparity.pfm (float32, inf = unknown) and disparity.png (colour map with a scale bar); with a
calibration, depth_mm.pfm (float32 mm, inf = unknown), depth_mm.png (16-bit mm, 0 = unknown or
over 65535 mm) and cloud.ply (binary PLY, x y z float mm in the left camera frame + red green
blue uchar from the left view; see sljax.depth.geometry); for structured-light models confidence.pfm
and confidence.png (in [0, 1], higher is surer); for a rectified pair calib.txt, the rectified
geometry the depth used.

Stereo video (frames read with OpenCV, predicted in batches): sljax.depth.video.
"""

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from sljax import inference
from sljax.depth import geometry
from sljax.inference.sgbm import SGBMConfig, SGBMPredictor
from sljax.io import files
from sljax.capture import rig  # the one import of the rig module (OpenCV calibrations, rectifying)
from sljax.data.camera import Calib, read_calib, write_calib
from sljax.data.dataset import find_scenes
from sljax.data.pfm import write_pfm
from sljax.errors import SljaxError, require
from sljax.io.images import read_image
from sljax.io.pictures import Panel, save_panels

UNITS_MM = rig.UNITS_MM  # an OpenCV calibration's T unit (--unit), as import-captures takes it
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".ppm", ".pgm")
OUTPUT_FILES = ("disparity.pfm", "disparity.png", "depth_mm.pfm", "depth_mm.png", "cloud.ply",
                "confidence.pfm", "confidence.png", "calib.txt")


@dataclasses.dataclass(frozen=True)
class StereoRig:
  """An OpenCV stereo calibration whose views are rectified before inference (T in mm x unit_mm)."""
  calibration: rig.StereoCalibration
  unit_mm: float = 1.0


@dataclasses.dataclass(frozen=True)
class Rectifier:
  """Rectifies views of one size (width, height) with sljax.capture.rig's maps; `calib` is the
  rectified pair's Middlebury calibration (baseline in mm, doffs 0)."""
  maps: tuple
  calib: Calib
  size: tuple[int, int]

  def __call__(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two views (HxWxC float32) in the rectified frame (bilinear, black outside)."""
    return _remap(left, self.maps[0]), _remap(right, self.maps[1])


def _remap(image: np.ndarray, maps) -> np.ndarray:
  out = rig.remap(np.ascontiguousarray(image, np.float32), maps)
  return out.reshape(out.shape[:2] + image.shape[2:])  # cv2 drops a single channel axis


def rectifier(stereo: StereoRig, size: tuple[int, int], what: str) -> Rectifier:
  """The rectification of `stereo` at view size (width, height); SljaxError when the calibration
  states another size (`what` names the views in the message)."""
  cal = stereo.calibration
  rig.check_size(cal, size, what)
  rect = rig.rectify(cal, size)
  calib = rect.calib(stereo.unit_mm)
  # No disparity is known here: ndisp (SGBM's range) as SGBM's default, 25% of the width.
  calib = dataclasses.replace(calib, ndisp=16 * -(-size[0] // 64))
  return Rectifier(rig.rectify_maps(cal, rect), calib, (int(size[0]), int(size[1])))


def read_calibration(paths: str | os.PathLike | list | None, unit_mm: float = 1.0
                     ) -> Calib | StereoRig | None:
  """A Middlebury calib.txt (one `.txt` file: views already rectified) or an OpenCV stereo
  calibration (one .yml/.yaml/.xml/.json/.npz file, or intrinsics + extrinsics) to rectify with;
  None for None. SljaxError naming the file and the problem."""
  if paths is None:
    return None
  paths = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
  if not 1 <= len(paths) <= 2:
    raise SljaxError(f"--calib: one calibration file or two (intrinsics.yml extrinsics.yml), "
                     f"got {len(paths)}")
  for p in paths:
    if Path(p).is_dir():  # `--calib FILE INPUT...` takes the inputs as calibration files
      raise SljaxError(f"--calib {p}: is a folder (--calib takes one or two files; give the "
                       "inputs before it)")
    if not Path(p).is_file():
      raise SljaxError(f"--calib {p}: no such file")
  if len(paths) == 1 and Path(paths[0]).suffix.lower() == ".txt":
    if unit_mm != 1.0:
      raise SljaxError(f"--calib {paths[0]}: a Middlebury calib.txt gives its baseline in mm; "
                       "--unit is for an OpenCV calibration's T")
    return read_calib(paths[0])
  cal = rig.read_calibration(paths)
  rig.check_rig(cal, "are the cameras of the calibration, or the left and right views, swapped?")
  return StereoRig(cal, float(unit_mm))


@dataclasses.dataclass(frozen=True)
class Pair:
  """One stereo pair to predict: image files, its calibration, and its output sub-folder;
  `stereo`, when set, rectifies the pair first and gives its calibration."""
  name: str  # "" for a single pair written straight into the output folder
  left: Path
  right: Path
  calib: Calib | None = None
  calib_path: Path | None = None
  stereo: StereoRig | None = None


def _image_files(folder: Path) -> dict[str, Path]:
  return {p.name: p for p in sorted(folder.iterdir())
          if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES}


def _read_calib(path: Path | None) -> Calib | None:
  return None if path is None else read_calib(path)


def find_pairs(inputs: list[str], calib: str | os.PathLike | list | None = None,
               unit_mm: float = 1.0) -> list[Pair]:
  """The pairs named by the command line's inputs (see the module docstring); calib: a
  calibration file or two for every pair (`read_calibration`), T in mm x unit_mm."""
  if isinstance(inputs, (str, os.PathLike)):  # else each character would count as a path
    raise SljaxError(f"inputs must be a list of paths, [LEFT, RIGHT] or [PAIRS_DIR], got the "
                     f"single path {os.fspath(inputs)!r}; pass [{os.fspath(inputs)!r}]")
  given = read_calibration(calib, unit_mm)
  explicit = None
  if calib is not None:
    explicit = Path(calib if isinstance(calib, (str, os.PathLike)) else list(calib)[0])
  if len(inputs) == 2:
    left, right = (Path(p) for p in inputs)
    for p, which in ((left, "LEFT"), (right, "RIGHT")):
      if not p.is_file():
        raise SljaxError(f"{which} {p}: no such image file" +
                         (" (a folder: give one PAIRS_DIR instead)" if p.is_dir() else ""))
    return [_pair("", left, right, explicit, given, left.parent / "calib.txt")]
  if len(inputs) != 1:
    raise SljaxError(f"expected LEFT RIGHT image files or one PAIRS_DIR (or --video FILE), got "
                     f"{len(inputs)} paths")
  root = Path(inputs[0])
  if not root.is_dir():
    raise SljaxError(f"PAIRS_DIR {root}: " + ("is a file; give LEFT and RIGHT image files"
                                              if root.is_file() else "no such folder"))
  if (root / "left").is_dir() or (root / "right").is_dir():
    return _folder_pairs(root, explicit, given)
  try:
    scenes = find_scenes(root)
  except SljaxError:
    raise SljaxError(f"PAIRS_DIR {root}: holds neither scene folders (im0.png, im1.png) nor "
                     "left/ and right/ image folders") from None
  pairs = []
  for scene in scenes:
    name = scene.relative_to(root).as_posix()
    name = root.resolve().name if name == "." else name
    if not (scene / "im1.png").is_file():
      raise SljaxError(f"scene {scene}: im1.png: missing")
    pairs.append(_pair(name, scene / "im0.png", scene / "im1.png", explicit, given,
                       scene / "calib.txt"))
  return pairs


def _pair(name: str, left: Path, right: Path, explicit: Path | None,
          given: Calib | StereoRig | None, own: Path) -> Pair:
  """A Pair with the explicit calibration, else its own calib.txt when present."""
  if explicit is not None:
    stereo = given if isinstance(given, StereoRig) else None
    return Pair(name, left, right, None if stereo else given, explicit, stereo)
  path = own if own.is_file() else None
  return Pair(name, left, right, _read_calib(path), path)


def _folder_pairs(root: Path, explicit: Path | None, given: Calib | StereoRig | None
                  ) -> list[Pair]:
  """left/<name> with right/<name>, every name in both folders."""
  for side in ("left", "right"):
    if not (root / side).is_dir():
      raise SljaxError(f"{root / side}: missing (left/ and right/ go together)")
  left, right = _image_files(root / "left"), _image_files(root / "right")
  if not left:
    raise SljaxError(f"{root / 'left'}: no images ({', '.join(IMAGE_SUFFIXES)})")
  only = sorted(set(left) ^ set(right))
  if only:
    side = "right" if only[0] in left else "left"
    raise SljaxError(f"{root / side / only[0]}: missing (every image in left/ needs one of the "
                     f"same name in right/ and back; {len(only)} unpaired)")
  return [_pair(Path(n).stem, left[n], right[n], explicit, given, root / "calib.txt")
          for n in left]


def output_dir(out: str | os.PathLike, pair: Pair) -> Path:
  """Where a pair's files go."""
  out = Path(out)
  return out / pair.name if pair.name else out


def check_outputs(out: Path, pairs: list[Pair], overwrite: bool) -> None:
  """Refuses (one line) when any output file of any pair exists and overwrite is off."""
  files.check_output_folder(out, overwrite)
  if not overwrite:
    files.refuse_existing([output_dir(out, p) / f for p in pairs for f in OUTPUT_FILES], False)


def load_predictor(model: str, mode: str = "pad", maxdisp: int | None = None,
                   search_range: int | None = None, num_disparities: int | None = None):
  """'sgbm' (OpenCV StereoSGBM) or a checkpoint / converted PSMNet folder; each range applies to
  its own kind (PSMNet's cost volume, unet-sl's correlation, SGBM's numDisparities)."""
  if model == "sgbm":
    require(maxdisp is None and search_range is None, "MODEL sgbm: its disparity range is "
            "--num-disparities (--maxdisp and --search-range are the networks')")
    return SGBMPredictor(SGBMConfig(num_disparities=num_disparities))
  require(num_disparities is None, f"MODEL {model}: --num-disparities is sgbm's range (a "
          "PSMNet's is --maxdisp, unet-sl's --search-range)")
  if not Path(model).exists():
    raise SljaxError(f"MODEL {model}: unknown model: no such checkpoint, training workdir or "
                     "converted PSMNet folder (or use 'sgbm')")
  return inference.load(model, mode=mode, maxdisp=maxdisp, search_range=search_range)


def read_pair(pair: Pair) -> tuple[np.ndarray, np.ndarray]:
  """The two views as float32 HxWxC in [0, 1]; SljaxError when they differ in size."""
  left, right = read_image(pair.left), read_image(pair.right)
  if left.shape[:2] != right.shape[:2]:
    raise SljaxError(f"{pair.right}: size {right.shape[1]}x{right.shape[0]} differs from "
                     f"{pair.left} ({left.shape[1]}x{left.shape[0]})")
  return left, right


def _colour_png(path: Path, values: np.ndarray, title: str, label: str, cmap: str,
                vmin: float | None = None, vmax: float | None = None) -> None:
  finite = values[np.isfinite(values)]
  if vmin is None:
    vmin = float(finite.min()) if finite.size else 0.0
  if vmax is None:
    vmax = float(finite.max()) if finite.size else 1.0
  vmax = vmax if vmax > vmin else vmin + 1.0
  h, w = values.shape
  save_panels(path, [Panel(title, values, cmap=cmap, vmin=vmin, vmax=vmax, label=label)],
              ncols=1, tile_inches=max(3.0, min(8.0, 6.0 * w / max(h, w))))


def write_outputs(folder: str | os.PathLike, pair: Pair, left: np.ndarray,
                  out: dict[str, np.ndarray], max_depth: float | None = None,
                  figures: bool = True) -> dict[str, Any]:
  """Writes one pair's files (see the module docstring; the colour PNGs only with figures);
  `left` is the view the disparity belongs to (rectified when pair.stereo is set). Returns a
  summary for the report."""
  folder = Path(folder)
  folder.mkdir(parents=True, exist_ok=True)
  label = pair.name or pair.left.name
  disp = out["disparity"]
  write_pfm(folder / "disparity.pfm", disp)
  if figures:
    _colour_png(folder / "disparity.png", disp, f"{label}: disparity", "px", "turbo")
  summary: dict[str, Any] = {"pair": label, "known_disparity": float(np.isfinite(disp).mean())}
  if "confidence" in out:
    write_pfm(folder / "confidence.pfm", out["confidence"])
    if figures:
      _colour_png(folder / "confidence.png", out["confidence"], f"{label}: confidence", "",
                  "viridis", 0.0, 1.0)
  if pair.stereo is not None and pair.calib is not None:  # the rectified geometry
    write_calib(folder / "calib.txt", pair.calib)
  if pair.calib is not None:
    depth = geometry.depth_mm(disp, pair.calib, max_depth)
    write_pfm(folder / "depth_mm.pfm", depth)
    png = geometry.depth_png16(depth)
    files.write_png(folder / "depth_mm.png", png)
    xyz, rgb = geometry.point_cloud(disp, pair.calib, left, max_depth)
    geometry.write_ply(folder / "cloud.ply", xyz, rgb,  # written whole
                       comment=f"sljax predict {label}: x y z in mm, left camera frame "
                               "(x right, y down, z forward)")
    summary.update(points=len(xyz),
                   png_zero_but_known=int((np.isfinite(depth) & (png == 0)).sum()))
  return summary


def predict_pairs(predictor, pairs: list[Pair], out: str | os.PathLike,
                  max_depth: float | None = None, progress: bool = True) -> list[dict[str, Any]]:
  """Runs the predictor on every pair (progress bar) and writes its files; returns summaries."""
  # Checked before the first (slow) prediction, not after it.
  if not callable(predictor):
    raise SljaxError("predictor must be callable as predictor(left, right) (load_predictor or "
                     f"sljax.inference.load), got {type(predictor).__name__} "
                     f"{inference.short_repr(predictor)}")
  geometry.check_max_depth(max_depth)
  # Written into a hidden folder and moved in once every pair is done: a failure or Ctrl-C
  # leaves out as it was (absent stays absent; its other and, with --overwrite, old files stay).
  with files.staged(out) as stage:  # a str works as it does on the command line
    return [_predict_pair(predictor, pair, stage, max_depth)
            for pair in tqdm(pairs, desc="predict", unit="pair",
                             disable=None if progress else True)]


def _predict_pair(predictor, pair: Pair, out: Path, max_depth: float | None) -> dict[str, Any]:
  """Predicts one pair and writes its files under out; returns its summary."""
  left, right = read_pair(pair)
  if pair.stereo is not None:  # rectified before inference; every output is in that frame
    rect = rectifier(pair.stereo, (left.shape[1], left.shape[0]), f"{pair.left}")
    left, right = rect(left, right)
    pair = dataclasses.replace(pair, calib=rect.calib)
  if pair.calib is not None:  # before the (slow) prediction
    geometry.check_calib_size(pair.calib, left.shape[:2], str(pair.calib_path))
  try:
    res = predictor(left, right, calib=pair.calib)
  except SljaxError as e:
    raise SljaxError(f"{pair.left}: {e}") from None
  return write_outputs(output_dir(out, pair), pair, left, res, max_depth)
