"""`sljax import-captures` on a full-size capture: 2048x1500 cameras, a 1920x1080 projector, 46
frames per camera (OpenCV's GrayCodePattern layout), 8-bit PNGs.

Usage: JAX_PLATFORMS=cpu python benchmarks/bench_import.py [--repeats 1] [--keep DIR]
A synthetic capture (seeded: the renderer's scene 0 of seed 0, seen through the unrectified rig
of sljax.render.synth_rig with mild blur and noise) is written to a temporary folder, then
imported twice: in this process, stage by stage (read, rectify, decode, match, write; the
import's own timers), and as the command a user runs, in a fresh process (imports included).
The target: the command in at most 60 s on a 2-core CPU with nothing else running. The load
average is printed beside the figures (the machines are shared).
"""

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import ROOT, machine, record  # first: puts this checkout's sljax on the path

SIZE = (2048, 1500)
PROJECTOR = (1920, 1080)


def make_capture(folder: Path) -> dict:
  """Writes cam1/, cam2/ (pattern_camN_im1.png ... im46.png) and calib.yml; returns facts."""
  import cv2

  from sljax.capture import rig as rigs
  from sljax.render import synth_rig as sr
  from sljax.render.synthetic import SynthConfig, render_scene

  cfg = SynthConfig(size=2048, domain="tissue", t=8, raw_noise=0.0, raw_blur=0.0).resolved()
  start = time.perf_counter()
  scene = render_scene(0, 0, cfg, raw=True)
  rig = sr.RigConfig(size=SIZE, focal_scale=(1.04, 1.06),
                     centre_offset_px=((12.0, -8.0), (-9.0, 10.0)), projector=PROJECTOR)
  k_rect = sr.rectified_intrinsics(cfg)
  cal = sr.calibration(rig, k_rect, cfg.baseline_m * 1000.0)
  frames = sr.real_captures(scene, cfg, rig, how=sr.Degradation(blur_px=0.8, noise=0.005))
  for cam, views in (("cam1", frames[0]), ("cam2", frames[1])):
    (folder / cam).mkdir(parents=True)
    for i, f in enumerate(views):
      cv2.imwrite(str(folder / cam / f"pattern_{cam}_im{i + 1}.png"), f)
  rigs.write_calibration(folder / "calib.yml", cal)
  return {"frames": len(frames[0]), "generate_s": time.perf_counter() - start}


def main() -> None:
  """Generates the capture, times both imports and prints a table."""
  ap = argparse.ArgumentParser(description=__doc__)
  ap.add_argument("--repeats", type=int, default=1, help="imports of each kind (best kept)")
  ap.add_argument("--keep", help="generate the capture here (kept) instead of a temporary folder")
  args = ap.parse_args()

  from sljax.capture import captures
  from sljax.capture.rig import read_calibration

  with tempfile.TemporaryDirectory() as tmp:
    folder = Path(args.keep or tmp)
    if not (folder / "calib.yml").exists():
      facts = make_capture(folder)
      print(f"generated {facts['frames']} frames per camera in {facts['generate_s']:.0f} s")
    config = captures.ImportConfig(projector=PROJECTOR)
    stages, best = None, float("inf")
    cpu0 = time.process_time()
    for _ in range(args.repeats):
      start = time.perf_counter()
      report = captures.import_captures(folder / "cam1", folder / "cam2", folder / "scene",
                                        read_calibration(folder / "calib.yml"), config,
                                        overwrite=True, progress=False)
      wall = time.perf_counter() - start
      if wall < best:
        best, stages = wall, report
    cpu = (time.process_time() - cpu0) / args.repeats
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    command = [sys.executable, "-m", "sljax.cli", "import-captures", str(folder / "cam1"),
               str(folder / "cam2"), str(folder / "scene_cli"), "--calib",
               str(folder / "calib.yml"), "--projector", "x".join(map(str, PROJECTOR)),
               "--overwrite"]
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cli_best = float("inf")
    for _ in range(args.repeats):
      start = time.perf_counter()
      done = subprocess.run(command, env=env, capture_output=True, text=True)
      cli_best = min(cli_best, time.perf_counter() - start)
      if done.returncode:
        raise SystemExit(done.stderr)
    load = os.getloadavg()[0]
  print(machine())
  print(f"import-captures {SIZE[0]}x{SIZE[1]}, projector {PROJECTOR[0]}x{PROJECTOR[1]}, "
        f"46 frames per camera, 8-bit PNG; load average {load:.1f} on {os.cpu_count()} CPUs")
  print(f"{'stage':10s} {'s':>7s}")
  for stage, seconds in stages.seconds.items():
    print(f"{stage:10s} {seconds:7.2f}")
  print(f"{'total':10s} {best:7.2f}   (CPU {cpu:.1f} s, peak RSS {peak_mib:.0f} MiB)")
  print(f"{'command':10s} {cli_best:7.2f}   (fresh process, imports included; target <= 60 s "
        "idle)")
  print(f"valid share {stages.valid[0]:.1%} / {stages.valid[1]:.1%}, {stages.match_bits} "
        "column bits matched")
  print(done.stdout.strip())
  record("bench_import", [{"stage": k, "s": v} for k, v in stages.seconds.items()]
         + [{"stage": "total", "s": best}, {"stage": "command", "s": cli_best}],
         size=list(SIZE), projector=list(PROJECTOR), cpu_s=cpu, peak_rss_mib=peak_mib,
         load=load)


if __name__ == "__main__":
  main()
