"""Suite-wide settings: no per-CPU tuning (tests must not depend on timings; tests/test_tune.py
turns it on where it tests it), and JAX's persistent compilation cache in a folder of this
session's own (the suite compiles the same networks in many tests; the user's cache is never
touched), and float32 matrix products and convolutions at full float32 precision.

The tests check the arithmetic against float64 and naive references at float32 tolerances. On a
CPU 'highest' is what XLA computes anyway (bitwise the same outputs); on an NVIDIA GPU XLA's
default lets convolutions and products use TF32 (a 10-bit mantissa), which fails those
tolerances by design: 13 tests did on an H100 (docs/testing.md, "On a GPU"). How far TF32 moves the
networks is measured by benchmarks/bench_gpu.py, not asserted here.
SLJAX_TEST_PRECISION=default runs the suite at XLA's default instead.

On a GPU the suite also asks XLA for deterministic operations: a second program (a resumed run,
an exported file) is compiled again, and XLA:GPU picks convolution kernels by timing them at
each compilation and sums with atomics in some backward passes, so bitwise comparisons of two
runs fail by about 1e-5 relative without it (two of the four exact-resume tests on an H200; all
four passed with it, docs/testing.md).

On a CPU the suite compiles without XLA's LLVM backend optimisations (the options the training
loop already uses for initialisers): compiling dominates these tests (small inputs, many
networks), and the whole suite took about 0.8x the time on a Zen 3 (inference tests 0.76x,
training tests 0.88x, measured side by side). The HLO passes, YNNPACK fusions included, still
run; values change only by float rounding, which the tolerances and the bitwise comparisons of
two runs of one program do not see. SLJAX_TEST_XLA=default compiles as a user's run does
(on a GPU too: no deterministic operations).

The suite runs in two worker processes (pytest-xdist; `-n auto --maxprocesses=2 --dist loadfile`
in pyproject.toml; `pytest -n 0` runs in one). The workers share this session's compilation
cache folder (set here before they start; jax locks it with filelock), and on an accelerator
neither preallocates its memory."""

import atexit
import importlib.metadata
import os
import shutil
import tempfile

FAST_COMPILE = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
GPU_DETERMINISTIC = "--xla_gpu_deterministic_ops=true"


def _accelerators() -> set:
  """The accelerator kinds JAX may use here ('gpu', 'tpu'): its plugins installed, unless
  JAX_PLATFORMS=cpu."""
  if os.environ.get("JAX_PLATFORMS", "").strip().lower() == "cpu":
    return set()
  names = [str(d.metadata["Name"] or "").lower().replace("_", "-")
           for d in importlib.metadata.distributions()]
  return ({"gpu"} if any(n.startswith(("jax-cuda", "jax-rocm")) for n in names) else set()) | (
      {"tpu"} if any(n.startswith(("jax-tpu", "libtpu")) for n in names) else set())


ACCELERATORS = _accelerators()
if ACCELERATORS:  # the suite runs in two processes (pyproject addopts); by default each would take
  os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")  # 75% of the GPU up front
os.environ.setdefault("SLJAX_TUNE", "0")
# Whole compiled programs are kept only where a test turns it on (tests/test_kept_programs.py):
# a test that patches a traced function would otherwise be served another test's program.
os.environ["SLJAX_PROGRAM_CACHE"] = "off"  # even where a developer exported it on
if os.environ.get("SLJAX_TEST_PRECISION", "highest") != "default":  # inherited by subprocesses
  os.environ["JAX_DEFAULT_MATMUL_PRECISION"] = "highest"
if os.environ.get("SLJAX_TEST_XLA", "fast") != "default" and not ACCELERATORS:  # subprocesses too
  os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {FAST_COMPILE}".strip()
if os.environ.get("SLJAX_TEST_XLA", "fast") != "default" and "gpu" in ACCELERATORS:
  os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {GPU_DETERMINISTIC}".strip()
if "SLJAX_COMPILE_CACHE" not in os.environ:
  os.environ["SLJAX_COMPILE_CACHE"] = tempfile.mkdtemp(prefix="sljax-xla-")
  atexit.register(shutil.rmtree, os.environ["SLJAX_COMPILE_CACHE"], ignore_errors=True)

from sljax.runtime.compile_cache import enable_compile_cache  # noqa: E402  (after the settings above)

enable_compile_cache()


def pytest_xdist_auto_num_workers(config):
  """One worker on a TPU (libtpu lets a single process open the chip); else xdist's count."""
  return 1 if "tpu" in ACCELERATORS else None
