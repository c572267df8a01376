"""Frames per second of `sljax predict --video` on this CPU: a stacked stereo video (both views in
one 1280x1024 frame), rectified with an OpenCV calibration, a PSMNet in resize mode.

Usage: python benchmarks/bench_video.py [--frame 1280x1024] [--train-size 256x320]
       [--maxdisp 192] [--batch 4] [--frames 8] [--with-frames]

The PSMNet has random weights (its speed does not depend on their values). The video is
written first (mp4v, a textured pan, the right view shifted); the calibration has distortion and
a small rotation, so every frame pair is remapped. One short run of --batch frames compiles the
network; the timed run then predicts --frames frames through sljax.depth.video.predict_video (read,
split, rectify, resize, network, colour map, mp4) and prints frames/s with each stage's share.
--with-frames also writes each frame's PFM, depth and PLY.
"""

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from common import machine, record  # noqa: E402  (puts this checkout first on the path)
from bench_fullres import random_variables  # noqa: E402


def write_clip(path: Path, frames: int, w: int, h: int, shift: int = 24) -> None:
  """A stacked stereo video: a smooth random texture panning, the right view shifted."""
  rng = np.random.default_rng(0)
  tex = cv2.GaussianBlur(rng.uniform(0, 255, (h // 2, w + shift + 4 * frames, 3)).astype(
      np.float32), (0, 0), 2.0)
  tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
  writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 25.0, (w, h))
  for i in range(frames):
    x = 4 * i + shift
    writer.write(np.concatenate([tex[:, x:x + w], tex[:, x - shift:x - shift + w]], 0))
  writer.release()


def write_calibration(path: Path, w: int, h: int) -> None:
  """An OpenCV stereo calibration of views w x h with distortion and a small rotation."""
  f = 1.1 * w
  m1 = np.array([[f, 0, w / 2 - 3], [0, f, h / 2 + 2], [0, 0, 1]])
  m2 = np.array([[f * 1.01, 0, w / 2 + 4], [0, f * 1.01, h / 2 - 1], [0, 0, 1]])
  fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
  for key, value in (("M1", m1), ("D1", np.array([[-0.1, 0.03, 0.001, 0.0, 0.0]])),
                     ("M2", m2), ("D2", np.array([[-0.08, 0.02, 0.0, 0.001, 0.0]])),
                     ("R", cv2.Rodrigues(np.array([0.005, -0.01, 0.002]))[0]),
                     ("T", np.array([[-4.2], [0.05], [0.1]]))):
    fs.write(key, value)
  fs.write("image_width", w)
  fs.write("image_height", h)
  fs.release()


def main() -> None:
  """Prints the table."""
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--frame", default="1280x1024", help="WIDTHxHEIGHT of a frame (both views)")
  parser.add_argument("--train-size", default="256x320", help="HEIGHTxWIDTH the network runs at")
  parser.add_argument("--maxdisp", type=int, default=192)
  parser.add_argument("--batch", type=int, default=4)
  parser.add_argument("--frames", type=int, default=8, help="frames timed")
  parser.add_argument("--with-frames", action="store_true", help="also write per-frame files")
  args = parser.parse_args()
  fw, fh = (int(v) for v in args.frame.lower().split("x"))
  th, tw = (int(v) for v in args.train_size.lower().split("x"))

  from sljax import inference
  from sljax.depth import pairs, video
  kwargs = {"maxdisp": args.maxdisp, "in_channels": 3}
  predictor = inference.make_predictor("psmnet", kwargs, random_variables("psmnet", kwargs),
                                       mode="resize", train_size=(th, tw))
  print(machine())
  print(f"load average {os.getloadavg()[0]:.2f} (1 min) at the start")
  with tempfile.TemporaryDirectory() as tmp:
    tmp = Path(tmp)
    write_clip(tmp / "warm.mp4", args.batch, fw, fh)
    write_clip(tmp / "clip.mp4", args.frames, fw, fh)
    write_calibration(tmp / "rig.yml", fw, fh // 2)
    rig = pairs.read_calibration([tmp / "rig.yml"])
    t0 = time.perf_counter()
    video.predict_video(predictor, video.open_video([tmp / "warm.mp4"], "stacked"),
                        tmp / "warm", rig, batch=args.batch, progress=False)
    first = time.perf_counter() - t0
    source = video.open_video([tmp / "clip.mp4"], "stacked")
    t0 = time.perf_counter()
    s = video.predict_video(predictor, source, tmp / "out", rig, batch=args.batch,
                            frames=args.with_frames, progress=False)
    wall = time.perf_counter() - t0
  load = os.getloadavg()[0]
  n = s["frames"]
  print(f"{fw}x{fh} stacked mp4 ({fw}x{fh // 2} per view), rectified, psmnet maxdisp "
        f"{args.maxdisp} resized to {th}x{tw}, random weights, batch {args.batch}, "
        f"{'per-frame files written' if args.with_frames else 'video only'}")
  print(f"first run ({args.batch} frames, with compilation): {first:.1f} s")
  print(f"{'stage':>10} {'s/frame':>9} {'share':>7}")
  for stage, sec in s["seconds"].items():
    print(f"{stage:>10} {sec / n:>9.3f} {sec / wall:>7.1%}")
  print(f"{'total':>10} {wall / n:>9.3f}")
  print(f"\n{n / wall:.2f} frames/s ({n} frames in {wall:.1f} s); load average {load:.2f} "
        "(1 min) at the end")
  record("bench_video", [{"frame": [fw, fh], "train_size": [th, tw], "maxdisp": args.maxdisp,
                          "batch": args.batch, "frames": n, "with_frames": args.with_frames,
                          "wall_s": wall, "frames_per_s": n / wall, "first_run_s": first,
                          "stage_s": s["seconds"]}])


if __name__ == "__main__":
  main()
