"""The accuracy cost of --precision bf16: the quick preset trained in float32 and in bfloat16,
same seed, same data, side by side in one run (validation MAE per epoch, final and best, and
seconds per epoch).

  python benchmarks/bench_precision.py                    # the main job's run: twin, epr
  python benchmarks/bench_precision.py --strategy stl --epochs 4

bfloat16 is for accelerators: XLA's CPU backend emulates it, so on a CPU it is slower than
float32 (the seconds column shows by how much); the accuracy columns are what this measures.
"""

import argparse
import dataclasses
import json
import tempfile
from pathlib import Path

from common import machine, record  # first: puts this checkout's sljax on the path
from sljax.train import loop
from sljax.train.config import QUICK
from sljax.train.workdir import EPOCHS_FILE


def main() -> None:
  """Trains both precisions and prints the table."""
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--strategy", default="epr")
  p.add_argument("--epochs", type=int, default=QUICK.epochs)
  p.add_argument("--seed", type=int, default=0)
  args = p.parse_args()
  runs = {}
  with tempfile.TemporaryDirectory() as tmp:
    for precision in ("fp32", "bf16"):
      config = dataclasses.replace(QUICK, strategy=args.strategy, epochs=args.epochs,
                                   seed=args.seed, precision=precision)
      wd = Path(tmp) / precision
      loop.train(config, wd, log=lambda line: None, progress=False)
      runs[precision] = [json.loads(l) for l in (wd / EPOCHS_FILE).read_text().splitlines()]
  print(f"\n{machine()}\nquick preset, psmnet-mtl/{args.strategy}, seed {args.seed}\n")
  print("| epoch | val MAE fp32 px | val MAE bf16 px | bf16 - fp32 | s/epoch fp32 | s/epoch bf16 |")
  print("| --- | --- | --- | --- | --- | --- |")
  for a, b in zip(runs["fp32"], runs["bf16"]):
    print(f"| {a['epoch']} | {a['val_mae']:.3f} | {b['val_mae']:.3f} | "
          f"{b['val_mae'] - a['val_mae']:+.3f} | {a['seconds']:.1f} | {b['seconds']:.1f} |")
  best = {k: min(r["val_mae"] for r in v) for k, v in runs.items()}
  print(f"\nfinal: fp32 {runs['fp32'][-1]['val_mae']:.3f} px, bf16 {runs['bf16'][-1]['val_mae']:.3f} "
        f"px; best: fp32 {best['fp32']:.3f} px, bf16 {best['bf16']:.3f} px")
  record("bench_precision", [{"epoch": a["epoch"], "val_mae_fp32": a["val_mae"],
                              "val_mae_bf16": b["val_mae"], "s_fp32": a["seconds"],
                              "s_bf16": b["seconds"]} for a, b in zip(runs["fp32"], runs["bf16"])],
         strategy=args.strategy, seed=args.seed)


if __name__ == "__main__":
  main()
