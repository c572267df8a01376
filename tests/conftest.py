"""Suite-wide settings: no per-CPU tuning (tests must not depend on timings; tests/test_tune.py
turns it on where it tests it)."""

import os

os.environ.setdefault("SLJAX_TUNE", "0")
