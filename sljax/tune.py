"""Kernel choices per CPU, made by measurement and cached: sljax's cuDNN benchmark mode.

What is chosen. On a CPU the hot operations of PSMNet and the twin (3D and 2D convolutions,
transposed 3D convolutions) have several exact implementations whose speed depends on the CPU
(cache sizes, AVX-512 or not) and on the XLA version: the folded / blocked CPU kernels or plain
`lax` convolutions (`conv_impl`), the size of the blocks of output planes of the folded kernels
(`block_values`), and whether XLA:CPU's YNNPACK fusions are on, separately for forward-only
programs (inference, validation, evaluation) and for training steps. Every candidate is one of
the implementations the tests compare with `lax` in value and gradient, so a choice changes
speed and float rounding, never the function computed.

How. `measure` times each candidate on PSMNet's own shapes at the paper's size (the 1/4
resolution cost-volume stack at 256x256, maxdisp 96, batch 2, and a 2D feature convolution),
forward and forward + backward, interleaved, the minimum of a few repeats: about a minute on a
2-core CPU. The winner is kept in a JSON cache in the user's cache directory
(`$SLJAX_CACHE_DIR`, else `$XDG_CACHE_HOME/sljax`, else `~/.cache/sljax`), keyed by the CPU
kind (`sljax.machine.cpu_key`) and the jax and jaxlib versions, so it is measured once per
machine kind and upgrade. `sljax tune` runs it and prints the table; `SLJAX_TUNE=0` (or
`--no-tune` on the commands that train or predict) uses the defaults. Off the CPU nothing is
measured: accelerators use `lax` convolutions and XLA's own autotuning.
"""

import dataclasses
import json
import os
import time
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import jaxlib
import numpy as np

from sljax import machine
from sljax.nets import conv3d as c3

ENV_TUNE = "SLJAX_TUNE"
ENV_CACHE = "SLJAX_CACHE_DIR"
YNN_OFF = {"xla_cpu_experimental_ynn_fusion_type": ""}
BLOCKS = (1 << 15, 1 << 17, 1 << 19)   # values per block of output planes: 128 KiB to 2 MiB


@dataclasses.dataclass(frozen=True)
class KernelChoice:
  """The kernels a program uses; the defaults are the untuned behaviour."""
  conv_impl: str = "auto"            # "fast" (folded CPU kernels), "lax", or "auto" (by platform)
  block_values: int = c3.BLOCK_VALUES
  forward_ynn: bool = True           # XLA:CPU YNNPACK fusions in forward-only programs
  train_ynn: bool = True             # ... and in training steps

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


def cache_path() -> Path:
  """The tuning cache file in the user's cache directory (overridable by $SLJAX_CACHE_DIR)."""
  root = os.environ.get(ENV_CACHE)
  if not root:
    root = os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"),
                        "sljax")
  return Path(root) / "tune.json"


def cache_key() -> str:
  """What a measurement depends on: the CPU kind and the jax / jaxlib versions."""
  return f"{machine.cpu_key()} jax-{jax.__version__} jaxlib-{jaxlib.__version__}"


def read_cache(path: Path | None = None) -> dict:
  """The cache's entries by key ({} when absent or unreadable: it is only a cache)."""
  path = path or cache_path()
  try:
    data = json.loads(path.read_text(encoding="utf-8"))
  except (OSError, ValueError):
    return {}
  return data if isinstance(data, dict) else {}


def write_cache(key: str, choice: KernelChoice, table: list[dict], seconds: float,
                path: Path | None = None) -> Path:
  """Stores one key's choice and its measurements (atomically: write, then rename)."""
  path = path or cache_path()
  data = read_cache(path)
  data[key] = {"choice": dataclasses.asdict(choice), "table": table,
               "seconds": round(seconds, 1), "cpu": machine.cpu_description(),
               "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
  path.parent.mkdir(parents=True, exist_ok=True)
  tmp = path.with_suffix(f".tmp{os.getpid()}")
  tmp.write_text(json.dumps(data, indent=1), encoding="utf-8")
  os.replace(tmp, path)
  return path


def cached_choice(path: Path | None = None) -> KernelChoice | None:
  """This machine's cached choice, or None."""
  entry = read_cache(path).get(cache_key())
  if not entry:
    return None
  try:
    return KernelChoice(**entry["choice"])
  except (KeyError, TypeError):
    return None  # written by another version of this module: measure again


def choice(tune: bool | None = None, log: Callable[[str], None] = print) -> KernelChoice:
  """The kernel choice for this process: defaults off the CPU or with tuning off; else the
  cached choice, measured first when this CPU kind and jax version have none."""
  if jax.default_backend() != "cpu" or not enabled(tune):
    return DEFAULT
  found = cached_choice()
  if found is not None:
    return found
  log(f"tuning the kernels for this CPU ({machine.cpu_description()}), once per CPU kind and "
      f"jax version; SLJAX_TUNE=0 skips it")
  t0 = time.perf_counter()
  best, table = measure()
  try:
    path = write_cache(cache_key(), best, table, time.perf_counter() - t0)
    log(f"tuned in {time.perf_counter() - t0:.0f} s: {describe(best)} (cached in {path})")
  except OSError as e:  # a read-only home must not stop a run: the choice holds for this process
    log(f"tuned in {time.perf_counter() - t0:.0f} s: {describe(best)} (not cached: {e})")
  return best


def describe(c: KernelChoice) -> str:
  """One line: 'fast convolutions, blocks of 128 Ki values, YNNPACK on/off (forward/train)'."""
  ynn = lambda on: "on" if on else "off"
  return (f"{c.conv_impl} convolutions, blocks of {c.block_values // 1024} Ki values, YNNPACK "
          f"fusions {ynn(c.forward_ynn)} in forward programs, {ynn(c.train_ynn)} in training")


# ----------------------------------------------------------------------------- measurement


def workload(batch: int = 2, depth: int = 24, size: int = 64, channels: int = 32, seed: int = 0):
  """PSMNet's hot shapes at 256x256, maxdisp 96: a 1/4-resolution cost-volume stack (3D conv,
  strided 3D conv, transposed 3D conv) and a 2D feature convolution; returns (fn, args)."""
  rng = np.random.default_rng(seed)
  r = lambda *s: jnp.asarray(rng.normal(size=s).astype(np.float32) / np.sqrt(np.prod(s[:-1])))
  x = jnp.asarray(rng.normal(size=(batch, depth, size, size, channels)).astype(np.float32))
  f = jnp.asarray(rng.normal(size=(batch, 2 * size, 2 * size, channels)).astype(np.float32))
  params = {"k1": r(3, 3, 3, channels, channels), "k2": r(3, 3, 3, channels, 2 * channels),
            "kt": r(3, 3, 3, 2 * channels, channels), "k2d": r(3, 3, channels, channels)}

  def fn(params, x, f, impl):
    y = jax.nn.relu(c3.conv3d(x, params["k1"], (1, 1, 1), ((1, 1),) * 3, impl=impl))
    z = jax.nn.relu(c3.conv3d(y, params["k2"], (2, 2, 2), ((1, 1),) * 3, impl=impl))
    u = c3.conv_transpose3d(z, params["kt"], (2, 2, 2), c3.transpose_padding((3, 3, 3), 1, 1),
                            impl=impl) + y
    g = c3.conv2d(f, params["k2d"], impl=impl)
    return jnp.sum(u ** 2) + jnp.sum(g ** 2)
  return fn, (params, x, f)


def _compiled(fn, args, impl: str, block: int, kind: str, ynn: bool):
  """The workload compiled as one program kind under one candidate."""
  body = (lambda p, x, f: fn(p, x, f, impl)) if kind == "forward" else \
      jax.grad(lambda p, x, f: fn(p, x, f, impl))
  options = None if ynn else dict(YNN_OFF)
  saved = c3.BLOCK_VALUES
  c3.BLOCK_VALUES = block  # read while tracing; restored before anything else traces
  try:
    return jax.jit(body, compiler_options=options).lower(*args).compile()
  finally:
    c3.BLOCK_VALUES = saved


def _time(compiled, args, repeats: int, clock: Callable[[], float]) -> list[float]:
  """Wall times of `repeats` calls after one warm-up."""
  jax.block_until_ready(compiled(*args))
  out = []
  for _ in range(repeats):
    t0 = clock()
    jax.block_until_ready(compiled(*args))
    out.append(clock() - t0)
  return out


PROBE = {"batch": 1, "depth": 12, "size": 32, "channels": 32}  # where lax is probed first
LAX_MARGIN = 1.5  # lax joins the full measurement only if the probe finds it this close


def candidates(with_lax: bool) -> list[tuple[str, int, bool]]:
  """(conv_impl, block_values, ynn) candidates: the fast kernels at each block size with
  YNNPACK fusions on and off, and the lax convolutions when they are in the running."""
  out = [("fast", b, ynn) for b in BLOCKS for ynn in (True, False)]
  return out + ([("lax", c3.BLOCK_VALUES, ynn) for ynn in (True, False)] if with_lax else [])


def lax_in_running(repeats: int, clock: Callable[[], float]) -> tuple[bool, float]:
  """Whether lax convolutions come within LAX_MARGIN of the fast ones on a small probe (forward
  + backward); returns (verdict, lax / fast). XLA:CPU's 3D convolution is many times slower on
  the CPUs measured so far, and timing it at full size would take minutes."""
  fn, args = workload(**PROBE)
  t = {}
  for impl in ("fast", "lax"):
    compiled = _compiled(fn, args, impl, c3.BLOCK_VALUES, "train", True)
    t[impl] = min(_time(compiled, args, repeats, clock))
  return t["lax"] / t["fast"] < LAX_MARGIN, t["lax"] / t["fast"]


def measure(repeats: int = 3, clock: Callable[[], float] = time.perf_counter,
            shapes: dict | None = None, timings: Callable | None = None
            ) -> tuple[KernelChoice, list[dict]]:
  """Times every candidate as a forward and as a training program; returns the choice and the
  table. `timings(impl, block, kind, ynn) -> seconds` replaces the measurement (tests)."""
  if timings is not None:
    keys = [(impl, block, ynn, kind) for impl, block, ynn in candidates(True)
            for kind in ("forward", "train")]
    times = {k: timings(k[0], k[1], k[3], k[2]) for k in keys}
  else:
    with_lax, _ = lax_in_running(repeats, clock)
    keys = [(impl, block, ynn, kind) for impl, block, ynn in candidates(with_lax)
            for kind in ("forward", "train")]
    fn, args = workload(**(shapes or {}))
    programs = {k: _compiled(fn, args, k[0], k[1], k[3], k[2]) for k in keys}
    samples = {k: [] for k in keys}
    for _ in range(repeats):  # interleaved, so that a burst of load hits every candidate alike
      for k in keys:
        samples[k] += _time(programs[k], args, 1, clock)
    times = {k: min(v) for k, v in samples.items()}
  best = choose(times)
  table = [{"conv_impl": i, "block_values": b, "ynn": y, "kind": k, "seconds": round(s, 5)}
           for (i, b, y, k), s in sorted(times.items(), key=lambda kv: (kv[0][3], kv[1]))]
  return best, table


MARGIN = 0.05  # a candidate replaces the default only when it is this much faster


def choose(times: dict[tuple[str, int, bool, str], float], margin: float = MARGIN) -> KernelChoice:
  """The choice from {(impl, block, ynn, kind): seconds}. conv_impl and block_values are one
  choice for both program kinds (a model is built once): the pair with the least forward plus
  training time, each kind at its better YNNPACK setting; then YNNPACK per kind for that pair.
  The default (fast kernels, default blocks, YNNPACK on) is kept unless a candidate is faster by
  more than `margin`, so that the noise of a shared machine does not move the choice."""
  default_pair = ("fast", DEFAULT.block_values)

  def best_ynn(impl, block, kind):
    on, off = times.get((impl, block, True, kind)), times.get((impl, block, False, kind))
    if on is None:
      return False
    return off is None or off >= on * (1 - margin)

  def cost(pair):
    return sum(times[(*pair, best_ynn(*pair, kind), kind)] for kind in ("forward", "train"))
  pairs = sorted({(i, b) for i, b, _, _ in times})
  impl, block = min(pairs, key=cost)
  if default_pair in pairs and cost((impl, block)) > cost(default_pair) * (1 - margin):
    impl, block = default_pair
  return KernelChoice(conv_impl=impl, block_values=block,
                      forward_ynn=best_ynn(impl, block, "forward"),
                      train_ynn=best_ynn(impl, block, "train"))


def format_table(table: list[dict], best: KernelChoice) -> str:
  """The measurements as a Markdown table, each kind's time relative to the chosen candidate."""
  def is_chosen(r):
    ynn = best.forward_ynn if r["kind"] == "forward" else best.train_ynn
    return (r["conv_impl"], r["block_values"], r["ynn"]) == (best.conv_impl, best.block_values, ynn)
  ref = {r["kind"]: r["seconds"] for r in table if is_chosen(r)}
  lines = ["| program | convolutions | block (Ki values) | YNNPACK | ms | vs chosen |",
           "| --- | --- | ---: | --- | ---: | ---: |"]
  for r in table:
    chosen = is_chosen(r)
    rel = r["seconds"] / ref[r["kind"]] if r["kind"] in ref else float("nan")
    lines.append(f"| {r['kind']} | {r['conv_impl']} | {r['block_values'] // 1024} | "
                 f"{'on' if r['ynn'] else 'off'} | {r['seconds'] * 1e3:.1f} | "
                 f"{rel:.2f}x{' (chosen)' if chosen else ''} |")
  return "\n".join(lines)
