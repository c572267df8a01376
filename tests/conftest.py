"""Suite-wide settings: no per-CPU tuning (tests must not depend on timings; tests/test_tune.py
turns it on where it tests it), and JAX's persistent compilation cache in a folder of this
session's own (the suite compiles the same networks in many tests; the user's cache is never
touched)."""

import atexit
import os
import shutil
import tempfile

os.environ.setdefault("SLJAX_TUNE", "0")
if "SLJAX_COMPILE_CACHE" not in os.environ:
  os.environ["SLJAX_COMPILE_CACHE"] = tempfile.mkdtemp(prefix="sljax-xla-")
  atexit.register(shutil.rmtree, os.environ["SLJAX_COMPILE_CACHE"], ignore_errors=True)

from sljax.cache import enable_compile_cache  # noqa: E402  (after the settings above)

enable_compile_cache()
