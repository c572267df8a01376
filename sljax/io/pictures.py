"""Pictures: panels of images and colour-mapped maps with scale bars (PNG, PDF, SVG, ...)."""

import dataclasses
import functools
import os
from pathlib import Path

import numpy as np

from sljax.errors import SljaxError
from sljax.io import files


def new_figure(**kw):
  """A matplotlib Figure, imported when first drawn: matplotlib took 0.25 s of every training
  run's start, which draws nothing."""
  from matplotlib.figure import Figure  # noqa: PLC0415
  return Figure(**kw)


@dataclasses.dataclass(frozen=True)
class Panel:
  """One tile of a figure: an image (HxW or HxWx3 in [0, 1]) or a scalar map with a colour bar."""
  title: str
  image: np.ndarray
  cmap: str | None = None  # None: show as an image; else a matplotlib colour map + scale bar
  vmin: float | None = None
  vmax: float | None = None
  label: str = ""  # unit written beside the scale bar, e.g. "px"


@functools.cache
def figure_formats() -> tuple[str, ...]:
  """File name extensions a figure can be saved as (matplotlib's canvas picks the format by it)."""
  return tuple(sorted(new_figure().canvas.get_supported_filetypes()))


def check_figure_path(path: str | os.PathLike, option: str = "--out") -> Path:
  """path, or SljaxError when its extension is no picture format (checked before any work)."""
  path = Path(path)
  suffix = path.suffix.lower().lstrip(".")
  if suffix not in figure_formats():
    what = f"'.{suffix}'" if suffix else "no extension"
    raise SljaxError(f"{option} {path}: {what} is not a picture format; use .png, .pdf, .svg or "
                     f".jpg (any of {', '.join('.' + f for f in figure_formats())})")
  return path


def save_panels(path: str | os.PathLike, panels: list[Panel], ncols: int = 4,
                title: str | None = None, tile_inches: float = 3.0) -> None:
  """Writes a grid of panels to a picture (PNG, PDF, ... by path's extension); non-finite map
  values are drawn grey."""
  ncols = max(1, min(ncols, len(panels)))
  nrows = -(-len(panels) // ncols)
  import matplotlib  # noqa: PLC0415  (see new_figure)
  fig = new_figure(figsize=(tile_inches * ncols * 1.15, tile_inches * nrows))
  axes = fig.subplots(nrows, ncols, squeeze=False)
  for ax in axes.flat:
    ax.axis("off")
  for ax, p in zip(axes.flat, panels):
    img = np.asarray(p.image, dtype=np.float32)
    if img.ndim == 3 and img.shape[-1] == 1:
      img = img[..., 0]
    if p.cmap is None:
      ax.imshow(np.clip(img, 0, 1), cmap="gray" if img.ndim == 2 else None, vmin=0, vmax=1,
                interpolation="nearest")
    else:
      finite = img[np.isfinite(img)]
      vmin = p.vmin if p.vmin is not None else (float(finite.min()) if finite.size else 0.0)
      vmax = p.vmax if p.vmax is not None else (float(finite.max()) if finite.size else 1.0)
      cmap = matplotlib.colormaps[p.cmap].with_extremes(bad="0.5")
      im = ax.imshow(np.ma.masked_invalid(img), cmap=cmap, vmin=vmin, vmax=vmax,
                     interpolation="nearest")
      bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
      if p.label:
        bar.set_label(p.label)
    ax.set_title(p.title, fontsize=9)
  if title:
    fig.suptitle(title)
  fig.tight_layout()
  path = check_figure_path(path, "picture")
  os.makedirs(path.absolute().parent, exist_ok=True)
  files.save_figure(fig, path, dpi=100)
