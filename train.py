"""Train a model: see `python train.py --help` (thin entry point over sljax.train.cli)."""

from sljax.runtime.hugepages import reexec

reexec()  # first: with huge pages the CPU step takes 0.86x the time (sljax/runtime/hugepages.py)

from sljax.train.cli import main  # noqa: E402

raise SystemExit(main())
