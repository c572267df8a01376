"""Suite-wide settings: no per-CPU tuning (tests must not depend on timings; tests/test_tune.py
turns it on where it tests it), and JAX's persistent compilation cache in a folder of this
session's own (the suite compiles the same networks in many tests; the user's cache is never
touched), and float32 matrix products and convolutions at full float32 precision.

The tests check the arithmetic against float64 and naive references at float32 tolerances. On a
CPU 'highest' is what XLA computes anyway (bitwise the same outputs); on an NVIDIA GPU XLA's
default lets convolutions and products use TF32 (a 10-bit mantissa), which fails those
tolerances by design: 13 tests did on an H100 (docs/testing.md, "On a GPU"). How far TF32 moves the
networks is measured by benchmarks/bench_gpu.py, not asserted here.
SLJAX_TEST_PRECISION=default runs the suite at XLA's default instead."""

import atexit
import os
import shutil
import tempfile

os.environ.setdefault("SLJAX_TUNE", "0")
if os.environ.get("SLJAX_TEST_PRECISION", "highest") != "default":  # inherited by subprocesses
  os.environ["JAX_DEFAULT_MATMUL_PRECISION"] = "highest"
if "SLJAX_COMPILE_CACHE" not in os.environ:
  os.environ["SLJAX_COMPILE_CACHE"] = tempfile.mkdtemp(prefix="sljax-xla-")
  atexit.register(shutil.rmtree, os.environ["SLJAX_COMPILE_CACHE"], ignore_errors=True)

from sljax.cache import enable_compile_cache  # noqa: E402  (after the settings above)

enable_compile_cache()
