"""How `sljax tune` measures (sljax.runtime.choices says what is chosen and where a run finds
it): the fusions on PSMNet's probe in interleaved rounds, the kernel gradients' block size at
the runs' shapes, the decision rule, and the tables it prints."""

import time
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

from sljax.kernels import grad_blocks
from sljax.runtime import choices, machine
from sljax.runtime.choices import BLOCK_CANDIDATES, BLOCKS_BY_FUSIONS, KINDS, KernelChoice

MARGIN = 0.05  # a setting replaces XLA's default only when it is this much faster
RETRIES = 3  # fresh batches of rounds for a kind whose rounds disagreed

# () -> ({kind: f(*args)}, args): the programs a measurement times (sljax.nets.workload)
Workload = Callable[[], tuple[dict[str, Callable], tuple]]
# () -> (f, args): the kernel gradients the block size is measured on (the same module)
BlocksWorkload = Callable[[], tuple[Callable, tuple]]


def tuned(workload: Workload, repeats: int = 5, blocks_workload: BlocksWorkload | None = None
          ) -> tuple[KernelChoice, list[dict], float | None, dict | None]:
  """`measure`; the share of the CPUs other processes used meanwhile (None: unknown); and
  `measure_blocks` for the chosen training fusions where a `blocks_workload` is given (else
  None)."""
  before = machine.cpu_snapshot()
  best, table = measure(workload, repeats=repeats)
  blocks = None if blocks_workload is None else measure_blocks(blocks_workload, best.train_ynn)
  return best, table, machine.others_share(before, machine.cpu_snapshot()), blocks


def busy_note(others: float | None) -> str:
  """A sentence for a measurement taken beside other work, else ''."""
  if not choices.busy(others):
    return ""
  return (f"other processes used {others:.0%} of the CPUs while it measured, which can turn the "
          "choice around: it is provisional, serving runs only while the machine stays busy "
          "(then the CPU kind's table serves); `sljax tune` on an idle machine measures again")


def notes(table: list[dict], others: Any) -> list[str]:
  """Why a choice may not be what this machine would choose idle: rounds that disagreed, load
  beside the measurement."""
  return [n for n in (undecided_note(table), busy_note(others)) if n]


def _compiled(fns, args, kind: str, ynn: bool):
  """One program kind compiled with YNNPACK fusions on or off; training with the kernel
  gradients' blocks that training takes with that choice here (`grad_blocks_for`)."""
  kernels = KernelChoice(forward_ynn=ynn, train_ynn=ynn)
  blocks = choices.grad_blocks_for(kernels) if kind == "train" else None

  def program(*a):
    with grad_blocks(blocks):
      return fns[kind](*a)
  return jax.jit(program, compiler_options=kernels.compiler_options(kind)).lower(*args).compile()


def measure(workload: Workload | None = None, repeats: int = 5,
            clock: Callable[[], float] = time.perf_counter,
            timings: Callable[[str, bool], float] | None = None
            ) -> tuple[KernelChoice, list[dict]]:
  """Times each program kind of `workload()` with YNNPACK fusions on and off in `repeats`
  interleaved rounds, and a kind whose rounds disagreed again (up to `RETRIES` fresh batches);
  returns the choice and the table. `timings(kind, ynn) -> seconds` replaces one timed call
  (tests)."""
  keys = [(kind, ynn) for kind in KINDS for ynn in (True, False)]
  if timings is None:
    fns, args = workload()
    timed = _timer({k: _compiled(fns, args, *k) for k in keys}, args, clock)
    timings = lambda kind, ynn: timed((kind, ynn))
  samples = _rounds(timings, keys, repeats)
  batches = dict.fromkeys(KINDS, 1)
  for _ in range(RETRIES):
    # A burst of load that hits one setting of a round makes the rounds disagree; a fresh
    # batch decides instead of caching XLA's default for good (a busy Zen 4 once kept
    # fusions on in forward programs that run 1.4x faster without them).
    again = [kind for kind in KINDS if verdict(_ratios(samples, kind)) == "undecided"]
    if not again:
      break
    samples.update(_rounds(timings, [(kind, ynn) for kind in again for ynn in (True, False)],
                           repeats))
    for kind in again:
      batches[kind] += 1
  best = choose(samples)
  table = [{"kind": kind, "ynn": ynn, "seconds": round(float(np.median(samples[(kind, ynn)])), 5),
            "off_vs_on": [round(r, 3) for r in _ratios(samples, kind)],
            "batches": batches[kind], "verdict": verdict(_ratios(samples, kind))}
           for kind, ynn in keys]
  return best, table


def measure_blocks(workload: BlocksWorkload | None, train_ynn: bool, repeats: int = 3,
                   clock: Callable[[], float] = time.perf_counter,
                   timings: Callable[[int], float] | None = None) -> dict:
  """Times `workload()` (the 3D layers' gradients at the runs' shapes) in each of
  `BLOCK_CANDIDATES`, compiled with the training fusions `train_ynn`, in `repeats` interleaved
  rounds. The setting's default (`BLOCKS_BY_FUSIONS`) stays unless another size was faster in
  every round and by more than `MARGIN` in the median round (`verdict`). Returns
  {"train_ynn", "values" (the choice), "table"}; `timings(values) -> seconds` replaces one timed
  call (tests)."""
  default = BLOCKS_BY_FUSIONS[bool(train_ynn)]
  if timings is None:
    fn, args = workload()
    options = KernelChoice(train_ynn, train_ynn).compiler_options("train")

    def program(values):
      def blocked(*a):
        with grad_blocks(values):
          return fn(*a)
      return jax.jit(blocked, compiler_options=options).lower(*args).compile()
    timings = _timer({v: program(v) for v in BLOCK_CANDIDATES}, args, clock)
  samples = {v: [] for v in BLOCK_CANDIDATES}
  for _ in range(repeats):
    for v in BLOCK_CANDIDATES:
      samples[v].append(timings(v))
  ratios = {v: [a / b for a, b in zip(samples[v], samples[default])] for v in BLOCK_CANDIDATES}
  winners = [v for v in BLOCK_CANDIDATES if v != default and verdict(ratios[v]) == "off"]
  values = min(winners, key=lambda v: float(np.median(samples[v])), default=default)
  table = [{"values": v, "seconds": round(float(np.median(samples[v])), 5),
            "vs_default": [round(r, 3) for r in ratios[v]]} for v in BLOCK_CANDIDATES]
  return {"train_ynn": bool(train_ynn), "values": values, "table": table}


def format_blocks(blocks: Any) -> str:
  """The block measurement as a Markdown table ('' where there is none readable)."""
  if (not isinstance(blocks, dict) or not isinstance(blocks.get("table"), list)
      or type(blocks.get("values")) is not int):
    return ""
  rows = [r for r in blocks["table"] if isinstance(r, dict) and type(r.get("values")) is int
          and _positive_number(r.get("seconds"))]
  if not rows:
    return ""
  lines = [f"| kernel-gradient blocks (3D layers at the runs' shapes, training fusions "
           f"{'on' if blocks.get('train_ynn') else 'off'}) | ms | by round vs the default |",
           "| --- | ---: | --- |"]
  for r in rows:
    mark = " (chosen)" if r["values"] == blocks.get("values") else ""
    ratios = [x for x in r.get("vs_default") or [] if _positive_number(x)]
    spread = f"{min(ratios):.2f}-{max(ratios):.2f}" if ratios else ""
    lines.append(f"| {r['values'] >> 10} Ki values{mark} | {r['seconds'] * 1e3:.1f} | "
                 f"{spread} |")
  return "\n".join(lines)


def _timer(programs: dict, args: tuple, clock: Callable[[], float]) -> Callable[[Any], float]:
  """Runs each compiled program once (a first run sets things up: YNNPACK's thunks build their
  runtimes), then returns key -> seconds of one call of that program on `args`."""
  for p in programs.values():
    jax.block_until_ready(p(*args))

  def timed(key) -> float:
    t0 = clock()
    jax.block_until_ready(programs[key](*args))
    return clock() - t0
  return timed


def _rounds(timings: Callable[[str, bool], float], keys: list[tuple[str, bool]],
            repeats: int) -> dict[tuple[str, bool], list[float]]:
  """`repeats` rounds over `keys`, interleaved so that a burst of load hits every setting alike."""
  samples = {k: [] for k in keys}
  for _ in range(repeats):
    for k in keys:
      samples[k].append(timings(*k))
  return samples


def _ratios(samples: dict[tuple[str, bool], list[float]], kind: str) -> list[float]:
  """Per round, the time with the fusions off over the time with them on (< 1: off faster)."""
  return [off / on for off, on in zip(samples[(kind, False)], samples[(kind, True)])]


def verdict(ratios: list[float], margin: float = MARGIN) -> str:
  """'off' when off was faster in every round and by more than `margin` in the median round,
  'undecided' when the median round says off but another round disagrees, else 'on'."""
  if float(np.median(ratios)) >= 1.0 - margin:
    return "on"
  return "off" if max(ratios) < 1.0 else "undecided"


def choose(samples: dict[tuple[str, bool], list[float]],
           margin: float = MARGIN) -> KernelChoice:
  """Per kind, fusions off only on the verdict 'off': XLA's default stays unless the evidence
  is consistent, so the noise of a shared machine does not flip the choice from one tuning to
  the next."""
  off = lambda kind: verdict(_ratios(samples, kind), margin) == "off"
  return KernelChoice(forward_ynn=not off("forward"), train_ynn=not off("train"))


def undecided_note(table: list[dict]) -> str:
  """A sentence for a tuning whose rounds still disagreed after every retry, else ''."""
  kinds = sorted({str(r.get("kind")) for r in table
                  if isinstance(r, dict) and r.get("verdict") == "undecided"})
  if not kinds:
    return ""
  return (f"{' and '.join(kinds)}: the rounds disagreed in every batch, so XLA's default stays "
          "(a busy machine?); run `sljax tune` on an idle machine to measure again")


def _positive_number(x: Any) -> bool:
  return isinstance(x, (int, float)) and not isinstance(x, bool) and x > 0


def format_table(table: list[dict], best: KernelChoice) -> str:
  """The measurements as a Markdown table: each program's median time relative to the chosen
  setting, and with the fusions off the per-round off/on ratios' range. Rows that are no
  measurement (an entry written by hand: {"note": ...}) are shown as their note."""
  chosen = {"forward": best.forward_ynn, "train": best.train_ynn}
  # A row edited by hand into something that is no measurement is shown as itself, a note.
  rows = [r for r in table if isinstance(r, dict) and r.get("kind") in chosen
          and isinstance(r.get("ynn"), bool) and _positive_number(r.get("seconds"))]
  notes = [f"note: {r.get('note', r) if isinstance(r, dict) else r}" for r in table
           if not any(r is m for m in rows)]
  if not rows:
    return "\n".join(notes) or "no measurements recorded"
  ref = {r["kind"]: r["seconds"] for r in rows if r["ynn"] == chosen[r["kind"]]}
  lines = ["| program (PSMNet) | YNNPACK fusions | ms | vs chosen | off/on by round |",
           "| --- | --- | ---: | ---: | --- |"]
  for r in rows:
    mark = " (chosen)" if r["ynn"] == chosen[r["kind"]] else ""
    ratios = r.get("off_vs_on") or []
    spread = f"{min(ratios):.2f}-{max(ratios):.2f}" if ratios and not r["ynn"] else ""
    vs = f"{r['seconds'] / ref[r['kind']]:.2f}x" if r["kind"] in ref else "-"
    lines.append(f"| {r['kind']} | {'on' if r['ynn'] else 'off'} | {r['seconds'] * 1e3:.1f} | "
                 f"{vs}{mark} | {spread} |")
  for kind in KINDS:
    n = max((r.get("batches", 1) for r in rows if r["kind"] == kind), default=1)
    if n > 1:
      lines.append(f"\n{kind}: the first rounds disagreed, measured again ({n} batches; the "
                   "table shows the last)")
  return "\n".join(lines + (["", *notes] if notes else []))
