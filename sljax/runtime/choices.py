"""Compiler choices per CPU kind: a table of the kinds measured, and `sljax tune` to measure.

What is chosen. XLA:CPU can hand convolutions and their neighbours to YNNPACK fusions or
compile them itself ("off" keeps YNNPACK for reductions only, where XLA's own are ~10x
slower); which is faster depends on the CPU (AVX-512 or not, cache sizes), on the XLA version
and on the program: on an AVX-512 Zen 5 turning the fusions off made PSMNet's
forward 1.2x faster and its training step 5-30% slower, on an AVX2 Zen 3 the forward was
slower without them. So the choice is made per program kind: forward-only programs
(inference, validation, evaluation) and training steps. Both settings compute the same
function (only float rounding differs), and the choice is an explicit argument of the programs
that use it (`KernelChoice.compiler_options(kind)`, passed to `jax.jit`), never process state.
The fusions also decide the kernel gradients' block size (`sljax.kernels.grad_blocks`): XLA's
own convolutions want 1 Mi-value blocks, YNNPACK's the layers' 128 Ki, on every kind measured
(`BLOCKS_BY_FUSIONS`); `sljax tune` measures it too. The convolution kernels themselves are not
tuned: the folded kernels train 3x faster than `lax` on Zen 3 and were made because `lax` was
several times slower on Zen 5 (docs/benchmarks/cpu-kernels.md); they are chosen where the model
is built (its `conv_impl`, `sljax.kernels`).

Where a choice comes from. A run never measures: on a fresh 2-core Zen 3 the measurement
took 106 s, more than the compile it tunes, and measured beside other work it chose wrongly.
It takes, in order: this machine's own measurement (`sljax tune`), else `KNOWN`, the choice
`sljax tune` made on an idle machine of the same CPU kind (`sljax.runtime.machine.cpu_key`), else
`UNKNOWN` for kinds not measured yet (one line says so and how to measure). `SLJAX_TUNE=0`
(or `--ynn on`) keeps XLA's defaults. Off the CPU nothing is chosen.

How `sljax tune` measures (`sljax.runtime.measuring`). `measure` compiles PSMNet itself (128x128, maxdisp 48, batch 1: the
real mix of 2D and 3D convolutions) as a forward and as a training program, with the fusions
on and off, and times them in interleaved rounds; then `measure_blocks` times the 3D layers'
gradients at the shapes runs use (PSMNet's at 256x256 and the main job's) in each block size,
under the training fusions chosen: 52 s on a 2-core Intel Xeon, most of it compiling. The blocks
are measured at the runs' shapes because a block's size is relative to the planes it holds (at
128x128 a 1 Mi-value block is a whole volume); the fusions on the probe, which compiles 4x
faster. When the probe and a benchmark at the runs' shapes disagree, the runs' shapes are
trusted: `KNOWN` holds their verdict for machines not tuned, and the probe's rule changes until
it agrees (it disagreed on Zen 5 until RULE 5; since then every kind measured both ways agrees).
A setting replaces XLA's default only when it was faster in every round and by more
than `MARGIN` in the median round (two tunings on a busy Zen 3 once disagreed when one fastest
call decided); when the median says faster but a round disagrees, a fresh batch of rounds
decides (up to `RETRIES`). Load that lasts the whole measurement can turn the choice around
with every round agreeing: on a 2-core Zen 4 beside a training run every training round said
the fusions win (off/on 1.13-1.74), where idle every round said they lose (0.79-1.00). So
`tuned` also records the share of the usable cores' time other processes used meanwhile
(`sljax.runtime.machine.others_share`); above `BUSY` the choice is provisional: it serves only while
the machine stays busy. The winner is kept in a JSON file of measurements in the user's cache directory
(`$SLJAX_CACHE_DIR`, else `$XDG_CACHE_HOME/sljax`, else `~/.cache/sljax`), keyed by the CPU
kind and the jax and jaxlib versions.
"""

import dataclasses
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jaxlib

from sljax.io import files
from sljax.runtime import compile_cache, machine

ENV_TUNE = "SLJAX_TUNE"
# "off" keeps one kind of YNNPACK fusion: reductions. Without it XLA:CPU rewrites each large
# reduction (BatchNorm's statistics and their gradients) into a reduce-window of its own
# loop emitter, 9-14x slower than YNNPACK's (a [2, 24, 64, 64, C] -> [C] sum: 2.4 ms against
# 0.27 ms at C = 32 on Zen 5); PSMNet's training step took 3.26-3.55 s with against 3.53-3.81 s
# without (5 alternating rounds), and the main job's step compiled 1 s faster. Convolutions,
# dots and elementwise fusions stay XLA's (with elementwise fusions too the step took 5 s).
YNN_OFF = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_REDUCE"}
# The decision rule's version: choices measured under another rule are measured again (3: the
# load beside the measurement is recorded; older entries may have been measured on a busy machine;
# 4: the training probe runs with the kernel-gradient blocks of GRAD_BLOCKS; 5: "off" keeps
# YNNPACK's reductions; 6: the kernel gradients' block size is measured too).
RULE = 6
BUSY = 0.1  # other processes' share of the CPUs above which a measurement is provisional


# The choice per CPU kind (machine.cpu_key) measured on an idle machine of that kind, with
# where: a first run takes it instead of measuring (issue 49: on a fresh 2-core Zen 3 the
# measurement took 106 s of the 251 s before the first step). A kind not listed takes UNKNOWN:
# off on every kind measured so far; without the fusions programs also load about 3x faster
# (docs/benchmarks/first-run.md).
KNOWN = {
    "amd-epyc-f25-m1-avx2": ("off", "Zen 3, `sljax tune` idle, 2026-11-27"),
    "amd-epyc-f25-m17-avx2": ("off", "Zen 4 showing AVX2 only, `sljax tune` idle, 2026-11-27"),
    # issue 61: `sljax tune` chose the fusions off for both programs in 67 s.
    "amd-epyc-f25-m17-avx512": ("off", "Zen 4 with AVX-512, `sljax tune` idle, 2026-11-29"),
    # `sljax tune`'s probe (128x128, batch 1) kept the fusions in training (off/on 1.03-1.10),
    # but at the main job's preset the step without them was 5% faster (0.79-0.83 s against
    # 0.84-0.93 s) and loaded from the cache in 3.0 s against 9.6-10.0 s. Since RULE 5 (the
    # reductions kept) the probe chooses off for both as well (training off/on 0.81-0.86,
    # forward 0.67-0.80, idle, 2026-11-28): a measured entry no longer disagrees with this one.
    "amd-epyc-f26-m2-avx512": ("off", "Zen 5, the main job's step and start-up, 2026-11-27"),
    # forward off/on 0.80-0.89, training 0.84-0.97 by round, 39 s, idle.
    "intel-r-xeon-r-processor-f6-m167-avx512": ("off", "Intel Xeon family 6 model 167, "
                                                "`sljax tune` idle, 2026-11-29"),
}
UNKNOWN = "off"

# The kernel gradients' block size (sljax.kernels.grad_blocks) by the training programs' fusions,
# where `sljax tune` has not measured this machine. Which size is fastest depends on the library
# XLA hands the gradients' blocked convolutions to, i.e. on the fusions, and on every kind
# measured the same way (PSMNet's forward + backward at 256x256, maxdisp 96, batch 2):
# * fusions off (XLA's own convolutions) want 1 Mi values: Zen 5 3.58-3.59 s against 4.73-4.92 s
#   in 128 Ki; Zen 4 (issue 61, alternating, huge pages) 6.05-6.99 s against 9.55-11.61 s; the
#   Intel Xeon family 6 model 167 4.68 s against 6.61 s (4 Mi 4.92 s, 256 Ki 5.79 s);
# * fusions on (YNNPACK's convolutions) want the layers' 128 Ki: Zen 5 slower in 1 Mi; the Xeon
#   5.39 s against 7.06 s in 1 Mi (256 Ki 5.21 s, 3% faster, 64 Ki 5.73 s).
# (benchmarks/bench_blocks.py, 2026-11-29; docs/benchmarks/cpu-kernels.md.) Zen 3 and Zen 4's
# fusions-on step are not measured: they take this rule until `sljax tune` measures them.
BLOCKS_BY_FUSIONS = {True: 1 << 17, False: 1 << 20}
BLOCK_CANDIDATES = (1 << 17, 1 << 20)  # what `sljax tune` times at the runs' shapes

KINDS = ("forward", "train")  # the program kinds a choice is made for
NAMES = {(True, True): "on", (False, False): "off", (False, True): "forward-off",
         (True, False): "train-off"}  # (forward_ynn, train_ynn) -> the --ynn value


@dataclasses.dataclass(frozen=True)
class KernelChoice:
  """The compiler choices of forward-only and training programs; defaults are XLA's."""
  forward_ynn: bool = True           # XLA:CPU YNNPACK fusions in forward-only programs
  train_ynn: bool = True             # ... and in training steps

  @property
  def name(self) -> str:
    """'on', 'off', 'forward-off' or 'train-off' (the training option --ynn)."""
    return NAMES[(self.forward_ynn, self.train_ynn)]

  @classmethod
  def from_name(cls, name: str) -> "KernelChoice":
    """The choice a --ynn value names."""
    fwd, train = next(k for k, v in NAMES.items() if v == name)
    return cls(forward_ynn=fwd, train_ynn=train)

  def compiler_options(self, kind: str) -> dict[str, str] | None:
    """XLA compiler options for a 'forward' or 'train' program (None: XLA's defaults)."""
    ynn = {"forward": self.forward_ynn, "train": self.train_ynn}[kind]
    return None if ynn else dict(YNN_OFF)


DEFAULT = KernelChoice()


def enabled(flag: bool | None = None) -> bool:
  """Whether to tune: an explicit flag wins, else $SLJAX_TUNE (on unless 0/off/false/no)."""
  if flag is not None:
    return flag
  return os.environ.get(ENV_TUNE, "1").strip().lower() not in ("0", "off", "false", "no")


def measurements_path() -> Path:
  """The file of this user's measurements, in sljax's cache directory
  (sljax.runtime.compile_cache.user_cache_dir)."""
  return compile_cache.user_cache_dir() / "tune.json"


def measurement_key() -> str:
  """What a measurement depends on: the CPU kind and the jax / jaxlib versions."""
  return f"{machine.cpu_key()} jax-{jax.__version__} jaxlib-{jaxlib.__version__}"


def read_measurements(path: Path | None = None) -> dict:
  """The measurements by key ({} when absent or unreadable: `sljax tune` can measure again)."""
  path = path or measurements_path()
  # Not held to the compile cache's trust check (sljax.runtime.cache_trust): JSON runs no code,
  # and what a planted file can choose is only which of two settings XLA compiles with, both
  # the same function (speed and float rounding differ), read back through KernelChoice's fields.
  try:
    data = json.loads(path.read_text(encoding="utf-8"))
  except (OSError, ValueError):
    return {}
  return data if isinstance(data, dict) else {}


def write_measurement(key: str, choice: KernelChoice, table: list[dict], seconds: float,
                      path: Path | None = None, others: float | None = None,
                      blocks: dict | None = None) -> Path:
  """Stores one key's choice, its measurements, the share of the CPUs other processes used
  meanwhile (None: unknown) and the kernel gradients' measured blocks (`measure_blocks`; None:
  not measured) atomically: write, then rename."""
  path = path or measurements_path()
  data = read_measurements(path)
  data[key] = {"choice": dataclasses.asdict(choice), "rule": RULE, "table": table,
               "grad_blocks": blocks,
               "seconds": round(seconds, 1), "cpu": machine.cpu_description(),
               "others": None if others is None else round(others, 3),
               "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
  path.parent.mkdir(parents=True, exist_ok=True)
  files.write_text(path, json.dumps(data, indent=1))
  return path


def is_share(others: Any) -> bool:
  """Whether a recorded share of the CPUs is one (a number in [0, 1]; not None, which means
  unknown, nor what a hand edit made of it)."""
  return isinstance(others, (int, float)) and not isinstance(others, bool) and 0 <= others <= 1


def busy(others: Any) -> bool:
  """Whether a recorded share of the CPUs used by other processes makes a measurement
  provisional (unknown, where /proc/stat is absent, does not)."""
  return is_share(others) and others > BUSY


def measured_choice(path: Path | None = None) -> KernelChoice | None:
  """This machine's measured choice, or None: none measured, or a provisional one (measured on a
  busy machine) while the machine is quiet now."""
  entry = read_measurements(path).get(measurement_key())
  if not isinstance(entry, dict) or entry.get("rule") != RULE:
    return None
  found = entry_choice(entry)
  if found is None:
    return None
  if busy(entry.get("others")) and not busy(machine.others_now()):
    return None
  return found


def entry_choice(entry: Any) -> KernelChoice | None:
  """The choice a measurements entry holds, or None where it holds none that is readable (written
  by another version of this module, or edited by hand: NAMES knows booleans only)."""
  try:
    found = KernelChoice(**entry["choice"])
  except (KeyError, TypeError, AttributeError):
    return None
  return found if all(type(v) is bool for v in dataclasses.astuple(found)) else None


def known_choice(key: str | None = None) -> tuple[KernelChoice, str]:
  """(the choice for a CPU kind, where it comes from): the table of kinds measured idle, else
  `UNKNOWN`."""
  key = key or machine.cpu_key()
  if key in KNOWN:
    return KernelChoice.from_name(KNOWN[key][0]), f"measured on this CPU kind ({KNOWN[key][1]})"
  return KernelChoice.from_name(UNKNOWN), "the default for CPU kinds not measured yet"


def grad_blocks_for(kernels: "KernelChoice", path: Path | None = None) -> int | None:
  """The kernel gradients' block size for training programs compiled with `kernels` on this
  machine: what `sljax tune` measured here for that fusions' setting, else `BLOCKS_BY_FUSIONS`;
  None off the CPU (the fast kernels do not run there)."""
  if jax.default_backend() != "cpu":
    return None
  return measured_blocks(kernels.train_ynn, path) or BLOCKS_BY_FUSIONS[bool(kernels.train_ynn)]


def measured_blocks(train_ynn: bool, path: Path | None = None) -> int | None:
  """The block size `sljax tune` measured on this machine for training programs with the fusions
  `train_ynn`, or None (not measured, measured under another rule, or edited into nonsense)."""
  entry = read_measurements(path).get(measurement_key())
  if not isinstance(entry, dict) or entry.get("rule") != RULE:
    return None
  blocks = entry.get("grad_blocks")
  if not isinstance(blocks, dict) or blocks.get("train_ynn") is not bool(train_ynn):
    return None
  values = blocks.get("values")
  return values if type(values) is int and values in BLOCK_CANDIDATES else None


def choice(tune: bool | None = None, log: Callable[[str], None] = print) -> KernelChoice:
  """The kernel choice for this process, never measured here: XLA's defaults off the CPU or
  with tuning off; else this machine's `sljax tune` entry (a provisional one only while the
  machine is still busy), else the table of CPU kinds (`known_choice`)."""
  if jax.default_backend() != "cpu" or not enabled(tune):
    return DEFAULT
  found = measured_choice()
  if found is not None:
    return found
  best, where = known_choice()
  log(f"XLA's settings for this CPU: {describe(best)}, {where}; `sljax tune` measures this "
      "machine (about a minute) and its choice wins from then on")
  return best


def describe(c: KernelChoice) -> str:
  """One line: 'YNNPACK fusions off in forward programs, on in training (--ynn forward-off)'."""
  ynn = lambda on: "on" if on else "off"
  return (f"YNNPACK fusions {ynn(c.forward_ynn)} in forward programs, {ynn(c.train_ynn)} in "
          f"training (--ynn {c.name})")
