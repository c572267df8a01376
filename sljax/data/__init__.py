"""sljax.data: scenes on disk and in memory, the renderer, datasets and batches.

The main names are importable from here (`from sljax.data import FolderSource`); each is
imported on first use, so importing one submodule does not load the others."""

import importlib
from typing import Any

_HOMES = {
    "Scene": "scene", "load_scene": "scene", "write_scene": "scene",
    "FolderSource": "dataset", "iterate_batches": "dataset", "load_batch": "dataset",
    "SynthConfig": "synthetic", "SyntheticSource": "synthetic", "render_scene": "synthetic",
    "Calib": "calib", "read_calib": "calib", "write_calib": "calib",
}
__all__ = sorted(_HOMES)


def __getattr__(name: str) -> Any:
  if name in _HOMES:
    return getattr(importlib.import_module(f"sljax.data.{_HOMES[name]}"), name)
  raise AttributeError(f"module 'sljax.data' has no attribute {name!r}")
