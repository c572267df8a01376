"""Training speed: the compiled step alone against the whole loop, side by side in one run.

Steps per second of
  (a) the compiled training step on one fixed device batch (no data, no logging);
  (b) the full loop (`sljax.train.loop.train`) on synthetic scenes rendered on the fly;
  (c) the full loop on a folder of 256x256 PNG scenes that this benchmark writes first;
and the ratios (b)/(a) and (c)/(a): the loop's overhead (data, logs, checkpoints) is hidden
when they are close to 1. Loop timings are the steady-state epochs (the first epoch, which
compiles, and validation are left out). Prints where it ran (CPU, devices, versions).

  python benchmarks/bench_train.py                          # quick preset, psmnet-mtl
  python benchmarks/bench_train.py --preset paper --batch 2 --steps 2
  python benchmarks/bench_train.py --net unet-sl --precision bf16
  python benchmarks/bench_train.py --preset paper --step-only --precision fp32,bf16
"""

import argparse
import concurrent.futures
import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from common import machine, record
from sljax.data.dataset import split_indices
from sljax.data.scene import write_scene
from sljax.losses.weighting import step_weights
from sljax.nets import registry
from sljax.nets.model_config import init_variables
from sljax.render.synthetic import SynthConfig, SyntheticSource
from sljax.runtime import choices
from sljax.runtime.hugepages import reexec
from sljax.train import loop
from sljax.train import state as st
from sljax.train import step as stp
from sljax.train.config import PAPER, QUICK, TrainConfig
from sljax.train.feed import RowCache, batch_parts, check_source, open_source
from sljax.train.setup import model_config
from sljax.train.workdir import EPOCHS_FILE


def config_for(args) -> TrainConfig:
  """The preset with the benchmark's network, batch and a training set of `steps` batches."""
  base = {"quick": QUICK, "paper": PAPER}[args.preset]
  spec = registry.spec(args.net)
  model = spec.single or args.net
  strategy = "unc" if spec.multi_task else "stl"
  b = args.batch or base.batch_size
  return dataclasses.replace(base, model=model, strategy=strategy, batch_size=b,
                             epochs=args.epochs, val_every=10**6, max_val=b, keep=1,
                             precision=args.precision)


def subset(config: TrainConfig, n_train: int, steps: int) -> TrainConfig:
  """Keeps `steps` batches of the training split (--fraction), so epochs are short."""
  return dataclasses.replace(config, fraction=f"{steps * config.batch_size}/{n_train}")


def compiled_step(config: TrainConfig):
  """The compiled step, a state and one fixed device batch for (a); compiles before returning."""
  source = open_source(config)
  info = check_source(source, config)
  mesh = stp.make_mesh()
  # The fusions a new run of this config trains with (--ynn auto: this CPU's choice), so that
  # (a) is the program the loop's (b) and (c) run.
  ynn = config.ynn if config.ynn != "auto" else choices.choice(log=lambda line: None).name
  model, tx, step, _ = loop.compiled_steps(model_config(config, info), config.disp_loss,
                                           config.lr, None, mesh, ynn)
  state = jax.device_put(st.create_state(init_variables(model, 0, *config.size,
                                                           info.channels), tx),
                         stp.shardings(mesh)[0])
  rows = RowCache(source, config, batch_parts(config), False)
  batch = stp.put_batch(rows.batch(list(range(config.batch_size))), mesh)
  w = jnp.asarray(step_weights(config.strategy, []))
  state, m = step(state, batch, w)  # compiles
  jax.block_until_ready(m)
  return step, state, batch, w


def time_compiled(prepared, steps: int):
  """Steps/s of a prepared step on its fixed batch, and the prepared step with the new state
  (the step donates its state)."""
  step, state, batch, w = prepared
  t0 = time.perf_counter()
  for _ in range(steps):
    state, m = step(state, batch, w)
  jax.block_until_ready((state, m))
  return steps / (time.perf_counter() - t0), (step, state, batch, w)


def time_step(config: TrainConfig, steps: int) -> float:
  """(a): steps/s of the compiled step on one fixed batch."""
  return time_compiled(compiled_step(config), steps)[0]


def time_precisions(config: TrainConfig, precisions, steps: int, rounds: int = 2) -> dict:
  """(a) for each precision, side by side: compiled together (threads overlap the compilers),
  then timed in alternation, the best of `rounds` each."""
  configs = [dataclasses.replace(config, precision=p) for p in precisions]
  t0 = time.perf_counter()

  def compile_one(c):  # says when each is compiled: a run cut short still tells how long it took
    prepared = compiled_step(c)
    print(f"{c.precision}: compiled, the first step run, {time.perf_counter() - t0:.0f} s after "
          f"the start", flush=True)
    return prepared
  with concurrent.futures.ThreadPoolExecutor(len(configs)) as pool:
    prepared = list(pool.map(compile_one, configs))
  best = dict.fromkeys(precisions, 0.0)
  for _ in range(rounds):
    for i, p in enumerate(precisions):
      sps, prepared[i] = time_compiled(prepared[i], steps)
      best[p] = max(best[p], sps)
  return best


def time_loop(config: TrainConfig, workdir: Path) -> float:
  """(b), (c): steps/s of the loop's steady-state epochs (epoch 1 compiles; no validation)."""
  loop.train(config, workdir, overwrite=True, log=lambda line: None, progress=False)
  recs = [json.loads(l) for l in (workdir / EPOCHS_FILE).read_text().splitlines()]
  steady = recs[1:]
  return recs[0]["step"] * len(steady) / sum(r["seconds"] for r in steady)


def write_folder(root: Path, n: int, size: int, seed: int = 0) -> Path:
  """n synthetic 'objects' scenes of size x size as PNG scene folders."""
  src = SyntheticSource(n, seed=seed, config=SynthConfig(size=size))
  for i in range(n):
    write_scene(root / src.name(i), src[i])
  return root


def main() -> None:
  """Prints the table."""
  reexec()  # as sljax's commands run: malloc with huge pages (sljax/runtime/hugepages.py)
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--preset", choices=("quick", "paper"), default="quick")
  p.add_argument("--net", default="psmnet-mtl", choices=registry.NAMES)
  p.add_argument("--batch", type=int, default=None, help="default: the preset's")
  p.add_argument("--steps", type=int, default=10, help="steps per epoch (and for (a))")
  p.add_argument("--epochs", type=int, default=3,
                 help="loop epochs (at least 2); the first is not timed")
  p.add_argument("--precision", default="fp32",
                 help="fp32 or bf16; 'fp32,bf16' times (a) of both side by side (--step-only)")
  p.add_argument("--step-only", action="store_true", help="only (a): no loop, no folder")
  p.add_argument("--folder-size", type=int, default=256, help="PNG scene size for (c)")
  args = p.parse_args()
  precisions = args.precision.split(",")
  if any(q not in ("fp32", "bf16") for q in precisions) or (len(precisions) > 1
                                                            and not args.step_only):
    p.error("--precision is fp32, bf16, or fp32,bf16 with --step-only")
  args.precision = precisions[0]
  config = config_for(args)
  n_train = len(split_indices(open_source(config), config.test_fraction, config.seed)[0])
  print(f"{machine()}")
  print(f"preset {config.preset}: {config.net}/{config.strategy}, {config.size[0]}x"
        f"{config.size[1]}, maxdisp {config.maxdisp}, batch {config.batch_size}, "
        f"{'/'.join(precisions)}, {args.steps} steps per epoch\n")
  print("| what | steps/s | samples/s | ratio to (a) |")
  print("| --- | --- | --- | --- |", flush=True)
  rows = []

  def add(name, sps, precision=config.precision):  # printed and recorded as measured
    rows.append((name, sps))
    print(f"| {name} | {sps:.3f} | {sps * config.batch_size:.2f} | {sps / rows[0][1]:.3f} |",
          flush=True)
    return record("bench_train", [{"what": name, "steps_per_s": sps,
                                   "samples_per_s": sps * config.batch_size,
                                   "ratio_to_a": sps / rows[0][1]}],
                  quiet=True, preset=config.preset, net=config.net, batch=config.batch_size,
                  precision=precision)
  if args.step_only:
    for q, sps in time_precisions(config, precisions, args.steps).items():
      path = add(f"(a) compiled step, fixed batch, {q}", sps, q)
    print(f"\nrecorded in {os.path.relpath(path)}")
    return
  add("(a) compiled step, fixed batch", time_step(config, args.steps))
  with tempfile.TemporaryDirectory() as tmp:
    tmp = Path(tmp)
    add("(b) loop, synthetic on the fly",
        time_loop(subset(config, n_train, args.steps), tmp / "b"))
    n_folder = int(np.ceil(args.steps * config.batch_size / 0.8 / 10) * 10) + 10
    folder = write_folder(tmp / "scenes", n_folder, args.folder_size)
    folder_cfg = dataclasses.replace(config, data=str(folder))
    n_folder_train = len(split_indices(open_source(folder_cfg), config.test_fraction,
                                       config.seed)[0])
    path = add(f"(c) loop, folder of {args.folder_size}x{args.folder_size} PNG scenes",
               time_loop(subset(folder_cfg, n_folder_train, args.steps), tmp / "c"))
  print(f"\nrecorded in {os.path.relpath(path)}")


if __name__ == "__main__":
  main()
