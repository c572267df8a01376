"""A process of tests/test_workers.py's race: it imports the claims alone (not jax), so that
four of them start in a second."""

import random
from pathlib import Path

from sljax.experiment.running import workers


def claim_all(out: str, cells: list[str], barrier, seed: int, results, rounds: int) -> None:
  """In each round, claims every cell it can of a fresh folder, all the processes starting at
  the barrier, each in its own order; puts (round, cells won) on results."""
  me = workers.identity(lease=60)
  for round_ in range(rounds):
    order = list(cells)
    random.Random(seed * 100 + round_).shuffle(order)
    folder = Path(out) / f"round{round_}"
    worker = workers.Worker(folder, me)
    worker.file.parent.mkdir(parents=True, exist_ok=True)
    worker.file.write_text("{}")
    barrier.wait()
    won = []
    for cell in order:
      worker.held = None  # one cell at a time: only the claims are under test here
      if worker.claim(cell):
        won.append(cell)
    results.put((round_, won))
