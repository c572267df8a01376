"""Depth from stereo video: frames read with OpenCV, split into views, rectified, predicted in
batches; a colour-mapped disparity video and, on request, each frame's files as for pairs.

Inputs (`open_video`): one file holding both views, one above the other (layout "stacked": the
left view on top, as SCARED's keyframe videos) or side by side ("side-by-side": the left view
on the left); or two files, the left and the right view, of equal frame count and size. A
file is anything cv2.VideoCapture reads, an image sequence pattern (frames/%06d.png) included.
Calibration (sljax.depth.pairs.read_calibration): a Middlebury calib.txt means the views are
rectified already; an OpenCV stereo calibration rectifies every frame pair first, with the code
of sljax.depth.pairs (sljax.capture.rig's), so disparity, depth and points are in the rectified left
view.

Outputs in OUT: disparity.mp4 (MPEG-4 part 2, 'mp4v': what opencv-python-headless writes without
extra codecs; the turbo colour map over a fixed disparity range, unknown pixels black; an odd
width or height gets one black column or row, as the codec needs even sizes), one frame per
predicted frame at the source's frame rate / every; with frames=True, OUT/frames/NNNNNN/ per
predicted frame (NNNNNN its index in the video) with the files sljax.depth.pairs writes for a pair,
less the colour PNGs (the video shows them), and for rectified video OUT/frames/calib.txt (the
rectified geometry). Everything is written under temporary names and
renamed at the end: a failure or Ctrl-C part way leaves the earlier outputs (with overwrite) or
nothing.
"""

import dataclasses
import os
import shutil
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from sljax import inference
from sljax.data.camera import Calib, write_calib
from sljax.depth import geometry, pairs
from sljax.errors import SljaxError
from sljax.io import files
from sljax.io.images import image_to_float

# FFmpeg logs its own lines to stderr ("moov atom not found" for a damaged mp4): an unreadable
# video is one line of ours. Read at FFmpeg's first use; a user's own setting is kept.
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")

LAYOUTS = ("stacked", "side-by-side")
VIDEO_FILE = "disparity.mp4"
FRAMES_DIR = "frames"
FOURCC = "mp4v"
DEFAULT_FPS = 25.0  # when the source states none


@dataclasses.dataclass(frozen=True)
class VideoSource:
  """A stereo video: one file (with its layout) or two; frame count (0: unknown), rate, and the
  size (width, height) of one view."""
  paths: tuple[Path, ...]
  layout: str | None
  frames: int
  fps: float
  view_size: tuple[int, int]

  @property
  def name(self) -> str:
    """The file(s), for messages."""
    return " + ".join(map(str, self.paths))


def split_frame(frame: np.ndarray, layout: str) -> tuple[np.ndarray, np.ndarray]:
  """(left, right) views of a frame holding both: stacked = left on top, side-by-side = left
  on the left."""
  h, w = frame.shape[:2]
  if layout == "stacked":
    return frame[:h // 2], frame[h // 2:]
  if layout == "side-by-side":
    return frame[:, :w // 2], frame[:, w // 2:]
  raise SljaxError(f"layout must be one of {LAYOUTS}, got {layout!r}")


def _capture(path: Path) -> tuple[cv2.VideoCapture, np.ndarray]:
  """An open capture and its first frame; SljaxError for a missing or unreadable file (an image
  sequence pattern such as frames/%06d.png is not a file, and is read as a video)."""
  if not path.is_file() and "%" not in path.name:
    raise SljaxError(f"{path}: " + ("is a folder, not a video file" if path.is_dir()
                                    else "no such video file"))
  cap = cv2.VideoCapture(os.fspath(path))
  ok, frame = cap.read() if cap.isOpened() else (False, None)
  if not ok or frame is None:
    cap.release()
    raise SljaxError(f"{path}: not a readable video (OpenCV cannot open it or decode a frame)")
  return cap, frame


def _info(path: Path) -> tuple[int, float, tuple[int, int]]:
  """(frame count or 0, frame rate or 0, (width, height)) of a readable video."""
  cap, frame = _capture(path)
  try:
    count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    fps = float(cap.get(cv2.CAP_PROP_FPS))
  finally:
    cap.release()
  return max(count, 0), fps if np.isfinite(fps) and fps > 0 else 0.0, (frame.shape[1],
                                                                       frame.shape[0])


def open_video(paths: Sequence[str | os.PathLike], layout: str | None = None) -> VideoSource:
  """Checks a stereo video before anything is written (see the module docstring); SljaxError
  naming the file for an unreadable video, a frame the layout cannot split into two equal
  views, or two files of different frame counts or sizes."""
  paths = tuple(Path(p) for p in ([paths] if isinstance(paths, (str, os.PathLike)) else paths))
  if len(paths) == 1:
    if layout not in LAYOUTS:
      raise SljaxError(f"--video {paths[0]}: one file holds both views: give --layout "
                       f"{' or '.join(LAYOUTS)}" + (f" (got {layout!r})" if layout else ""))
    count, fps, (w, h) = _info(paths[0])
    if layout == "stacked" and h % 2:
      raise SljaxError(f"{paths[0]}: frames are {w}x{h}; an odd height cannot be split into "
                       "two stacked views of equal height (--layout stacked)")
    if layout == "side-by-side" and w % 2:
      raise SljaxError(f"{paths[0]}: frames are {w}x{h}; an odd width cannot be split into "
                       "two views side by side of equal width (--layout side-by-side)")
    size = (w, h // 2) if layout == "stacked" else (w // 2, h)
    return VideoSource(paths, layout, count, fps, size)
  if len(paths) != 2:
    raise SljaxError(f"--video: one file (both views, with --layout) or two (LEFT RIGHT), got "
                     f"{len(paths)}")
  if layout is not None:
    raise SljaxError("--layout is for one file holding both views; two files are LEFT RIGHT")
  (n0, fps, s0), (n1, _, s1) = _info(paths[0]), _info(paths[1])
  if s0 != s1:
    raise SljaxError(f"{paths[1]}: frames are {s1[0]}x{s1[1]}, those of {paths[0]} "
                     f"{s0[0]}x{s0[1]} (the two views must be of one size)")
  if n0 != n1:
    raise SljaxError(f"{paths[1]}: {n1} frames, {paths[0]} {n0} (the two views must have as "
                     "many frames)")
  return VideoSource(paths, None, n0, fps, s0)


def read_frames(source: VideoSource, every: int = 1
                ) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
  """(index, left, right) of frames 0, every, 2 every, ...: views as float32 HxWx3 RGB in
  [0, 1]; SljaxError when two files turn out to end at different frames."""
  caps = [cv2.VideoCapture(os.fspath(p)) for p in source.paths]
  try:
    index = 0
    while True:
      take = index % every == 0
      got = [(c.read() if take else (c.grab(), None)) for c in caps]
      ok = [g[0] for g in got]
      if not any(ok):
        return
      if not all(ok):
        ended = source.paths[ok.index(False)]
        raise SljaxError(f"{ended}: ends at frame {index}, the other file goes on (the two "
                         "views must have as many frames)")
      if take:
        frames = [image_to_float(g[1], f"{source.name} frame {index}") for g in got]
        if len(frames) == 1:
          left, right = split_frame(frames[0], source.layout)
        else:
          left, right = frames
        if (left.shape[1], left.shape[0]) != source.view_size or left.shape != right.shape:
          raise SljaxError(f"{source.name}: frame {index} is {left.shape[1]}x{left.shape[0]} "
                           f"per view, the first {source.view_size[0]}x{source.view_size[1]}")
        yield index, left, right
      index += 1
  finally:
    for c in caps:
      c.release()


_TURBO: np.ndarray | None = None


def colour_map(disp: np.ndarray, lo: float, hi: float) -> np.ndarray:
  """HxW disparity -> HxWx3 uint8 BGR (turbo over [lo, hi]; unknown black)."""
  global _TURBO
  if _TURBO is None:
    import matplotlib  # pylint: disable=import-outside-toplevel
    lut = matplotlib.colormaps["turbo"](np.linspace(0.0, 1.0, 256))[:, :3]
    _TURBO = np.rint(lut[:, ::-1] * 255).astype(np.uint8)  # RGB -> BGR
  d = np.asarray(disp, np.float64)
  known = np.isfinite(d)
  scale = 255.0 / (hi - lo) if hi > lo else 0.0
  idx = np.clip(np.rint((np.where(known, d, lo) - lo) * scale), 0, 255).astype(np.intp)
  out = _TURBO[idx]
  out[~known] = 0
  return out


def _even(image: np.ndarray) -> np.ndarray:
  """One black row / column added to an odd height / width (the codec needs even sizes)."""
  h, w = image.shape[:2]
  return cv2.copyMakeBorder(image, 0, h % 2, 0, w % 2, cv2.BORDER_CONSTANT, value=0)


def disparity_range(disps: np.ndarray) -> tuple[float, float]:
  """The colour range of the video: the 1st to 99th percentile of the known disparities (of the
  first batch); (0, 1) when none is known."""
  known = disps[np.isfinite(disps)]
  if not known.size:
    return 0.0, 1.0
  lo, hi = np.percentile(known, [1.0, 99.0])
  return float(lo), float(hi if hi > lo else lo + 1.0)


def check_outputs(out: str | os.PathLike, frames: bool, overwrite: bool) -> Path:
  """Refuses (one line) before any work when OUT is a file, or disparity.mp4 (or, with frames,
  OUT/frames) exists and overwrite is off."""
  out = files.check_output_folder(out, overwrite)
  files.refuse_existing([out / VIDEO_FILE], overwrite)
  if frames and (out / FRAMES_DIR).exists() and not overwrite:
    raise SljaxError(f"{out / FRAMES_DIR}: exists (pass --overwrite to replace it)")
  if frames and (out / FRAMES_DIR).is_file():
    raise SljaxError(f"{out / FRAMES_DIR}: is a file, not a folder")
  return out


def view_calibration(calib: Calib | pairs.StereoRig | None, source: VideoSource,
                     where: str = "calibration"
                     ) -> tuple[pairs.Rectifier | None, Calib | None]:
  """(rectifier or None, the calibration of the views the network sees) for a source;
  SljaxError when the calibration (`where`: its file, for the message) is for another size."""
  if isinstance(calib, pairs.StereoRig):
    rect = pairs.rectifier(calib, source.view_size, f"{source.name} (per view)")
    return rect, rect.calib
  if calib is not None:
    geometry.check_calib_size(calib, source.view_size[::-1], where)
  return None, calib


def find_calibration(source: VideoSource, paths: Sequence[str | os.PathLike] | None,
                     unit_mm: float = 1.0) -> Calib | pairs.StereoRig | None:
  """The calibration files given (sljax.depth.pairs.read_calibration), else calib.txt beside the
  (left) video when present, else None; SljaxError when it is for another view size."""
  if paths is None and (source.paths[0].parent / "calib.txt").is_file():
    paths = [source.paths[0].parent / "calib.txt"]
  calib = pairs.read_calibration(paths, unit_mm)
  view_calibration(calib, source, " + ".join(map(str, paths)) if paths else "calibration")
  return calib


def check_options(every: Any, batch: Any, disp_range: Any = None) -> None:
  """SljaxError unless every and batch are positive integers and disp_range None or LO < HI."""
  for value, what in ((every, "every"), (batch, "batch")):
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
      raise SljaxError(f"--{what} must be a positive integer, got {value!r}")
  if disp_range is not None and not (len(disp_range) == 2 and np.all(np.isfinite(disp_range))
                                     and disp_range[0] < disp_range[1]):
    raise SljaxError(f"--disp-range must be two numbers LO < HI, got {disp_range}")


def _padded(batch: list[np.ndarray], size: int, pad: bool) -> np.ndarray:
  """The batch stacked; with pad, the last view repeated up to `size` (one compiled shape)."""
  if pad and len(batch) < size:
    batch = batch + [batch[-1]] * (size - len(batch))
  return np.stack(batch)


def _batches(items: Iterator, size: int) -> Iterator[list]:
  """Lists of up to `size` consecutive items."""
  chunk = []
  for item in items:
    chunk.append(item)
    if len(chunk) == size:
      yield chunk
      chunk = []
  if chunk:
    yield chunk


def _video_writer(tmp: Path, final: Path, hw: tuple[int, int], fps: float) -> cv2.VideoWriter:
  """An open mp4v writer of frames hw (rounded up to even sizes) at tmp; SljaxError naming
  the final file when OpenCV cannot open one."""
  h, w = hw
  writer = cv2.VideoWriter(os.fspath(tmp), cv2.VideoWriter_fourcc(*FOURCC), fps,
                           (w + w % 2, h + h % 2))
  if not writer.isOpened():
    raise SljaxError(f"{final}: OpenCV cannot write an {FOURCC!r} mp4 here")
  return writer


def predict_video(predictor, source: VideoSource, out: str | os.PathLike,
                  calib: Calib | pairs.StereoRig | None = None, every: int = 1,
                  batch: int = 4, frames: bool = False, max_depth: float | None = None,
                  disp_range: tuple[float, float] | None = None, overwrite: bool = False,
                  progress: bool = True) -> dict[str, Any]:
  """Predicts every `every`-th frame pair of source in batches and writes the outputs (module
  docstring); returns a summary (frames, known share, colour range, seconds per stage)."""
  check_options(every, batch, disp_range)
  if not callable(predictor):
    raise SljaxError("predictor must be callable as predictor(left, right) (load_predictor or "
                     f"sljax.inference.load), got {type(predictor).__name__} "
                     f"{inference.short_repr(predictor)}")
  geometry.check_max_depth(max_depth)
  out = check_outputs(out, frames, overwrite)
  rect, view_calib = view_calibration(calib, source)
  created = [d for d in (out, *out.parents) if not d.exists()]
  out.mkdir(parents=True, exist_ok=True)
  tmp_video = files.temp_path(out / VIDEO_FILE)
  tmp_frames = files.temp_path(out / FRAMES_DIR)
  pad = isinstance(predictor, inference.Predictor)  # compiled per batch size
  total = -(-source.frames // every) if source.frames else None
  seconds = {"read": 0.0, "rectify": 0.0, "network": 0.0, "write": 0.0}
  pair = pairs.Pair("", source.paths[0], source.paths[-1], view_calib)
  writer, done, known = None, 0, []
  try:
    with tqdm(total=total, desc="predict video", unit="frame",
              disable=None if progress else True) as bar:
      chunks = _batches(read_frames(source, every), batch)
      while True:
        start = time.perf_counter()
        pending = next(chunks, None)
        seconds["read"] += time.perf_counter() - start
        if pending is None:
          break
        start = time.perf_counter()
        views = [rect(l, r) if rect else (l, r) for _, l, r in pending]
        seconds["rectify"] += time.perf_counter() - start
        start = time.perf_counter()
        try:
          res = predictor(_padded([v[0] for v in views], batch, pad),
                          _padded([v[1] for v in views], batch, pad), calib=view_calib)
        except SljaxError as e:
          raise SljaxError(f"{source.name}: {e}") from None
        seconds["network"] += time.perf_counter() - start
        start = time.perf_counter()
        disps = res["disparity"][:len(pending)]
        if disp_range is None:
          disp_range = disparity_range(disps)
        if writer is None:
          writer = _video_writer(tmp_video, out / VIDEO_FILE, disps.shape[1:],
                                 (source.fps or DEFAULT_FPS) / every)
        for i, (index, _, _) in enumerate(pending):
          writer.write(_even(colour_map(disps[i], *disp_range)))
          known.append(float(np.isfinite(disps[i]).mean()))
          if frames:
            pairs.write_outputs(
                tmp_frames / f"{index:06d}",
                dataclasses.replace(pair, name=f"{FRAMES_DIR}/{index:06d}"), views[i][0],
                {k: v[i] for k, v in res.items()}, max_depth, figures=False)
        seconds["write"] += time.perf_counter() - start
        done += len(pending)
        bar.update(len(pending))
    if writer is None:
      raise SljaxError(f"{source.name}: no frame to predict")
    writer.release()
    writer = None
    if frames and rect is not None:  # the rectified geometry every frame's depth used
      write_calib(tmp_frames / "calib.txt", view_calib)
    if not tmp_video.is_file() or tmp_video.stat().st_size == 0:
      raise SljaxError(f"{out / VIDEO_FILE}: OpenCV wrote nothing (a full disk?)")
    _move_into_place(tmp_frames if frames else None, out / FRAMES_DIR)
    os.replace(tmp_video, out / VIDEO_FILE)
  except BaseException:
    if writer is not None:
      writer.release()
    tmp_video.unlink(missing_ok=True)
    shutil.rmtree(tmp_frames, ignore_errors=True)
    for d in created:  # folders this call made, deepest first, when left empty
      try:
        d.rmdir()
      except OSError:
        break
    raise
  return {"frames": done, "known_disparity": float(np.mean(known)) if known else 0.0,
          "disp_range": disp_range, "seconds": seconds, "video": out / VIDEO_FILE,
          "frames_dir": out / FRAMES_DIR if frames else None, "rectified": rect is not None}


def _move_into_place(tmp: Path | None, final: Path) -> None:
  """Renames the finished frames folder into place, replacing an earlier one."""
  if tmp is None:
    return
  old = None
  if final.exists():
    old = final.with_name(f".{final.name}.old{os.getpid()}")
    os.replace(final, old)
  try:
    os.replace(tmp, final)
  except BaseException:
    if old is not None:
      os.replace(old, final)
    raise
  if old is not None:
    shutil.rmtree(old, ignore_errors=True)
