"""Train a model: see `python train.py --help` (thin entry point over sljax.train.cli)."""

from sljax.train.cli import main

raise SystemExit(main())
