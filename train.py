"""Train a model: see `python train.py --help` (thin entry point over sljax.train.cli)."""

from sljax.runtime.hugepages import reexec

reexec()  # first: with huge pages the CPU step takes 0.86x the time (sljax/runtime/hugepages.py)

import sys  # noqa: E402

from sljax.runtime.compile_cache import load_last_programs  # noqa: E402

load_last_programs(sys.argv[1:])  # the last such launch's step loads while the rest imports

from sljax.train.cli import main  # noqa: E402

raise SystemExit(main())
