"""Datasets of scene folders: discovery, group-level splits, training fractions and batches.

A "source" is anything with __len__, __getitem__(i) -> Scene and group(i) -> str; FolderSource
reads scene folders lazily, the synthetic generator provides another.
"""

import fractions
import hashlib
import operator
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from sljax.data.scene import Scene, load_scene
from sljax.errors import SljaxError
from sljax.io import files
from sljax.io.files import read_json_object
from sljax.io.images import to_gray
from sljax.io.sizes import as_size

BATCH_PARTS = ("left", "right", "disp", "disp_right", "sl", "sl_right", "mask")
DEFAULT_PARTS = ("left", "right", "disp", "sl")
# Batch key -> (Scene attribute, scene-folder part that holds it).
PART_FIELD = {
    "left": ("im0", "im"), "right": ("im1", "im"), "disp": ("disp0", "disp"),
    "disp_right": ("disp1", "disp"), "sl": ("sl0", "sl"), "sl_right": ("sl1", "sl"),
    "mask": ("mask0", "mask"),
}
_SCENE_FILE = {"im0": "im0.png", "im1": "im1.png", "disp0": "disp0.pfm", "disp1": "disp1.pfm",
               "sl0": "sl0/", "sl1": "sl1/", "mask0": "mask0.png"}


class Source(Protocol):
  """What training and evaluation iterate over."""

  def __len__(self) -> int: ...

  def __getitem__(self, i: int) -> Scene: ...

  def group(self, i: int) -> str:
    """Group id of scene i for group-level splits."""


def find_scenes(root: str | os.PathLike) -> list[Path]:
  """Every folder at or below root that holds im0.png, sorted by relative path."""
  root = files.require_folder(root, "dataset folder")
  found = []
  for dirpath, dirnames, filenames in os.walk(root):
    dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
    if "im0.png" in filenames:
      found.append(Path(dirpath))
      # A scene's own pattern and capture folders hold no scenes; skip listing them.
      dirnames[:] = [d for d in dirnames if d not in ("sl0", "sl1", "raw0", "raw1")]
  if not found:
    raise SljaxError(f"{root}: empty dataset (no folder at or below it holds im0.png)")
  return sorted(found, key=lambda p: p.relative_to(root).as_posix())


class FolderSource:
  """Scenes below a root folder, loaded on access; reads the optional dataset.json (whose
  "patterns" t, where given, cuts every scene's sl0/sl1 to its t coarsest patterns)."""

  def __init__(self, root: str | os.PathLike, gray: bool | None = None):
    self.root = files.require_folder(root, "dataset folder")
    self.gray = gray
    self.paths = find_scenes(self.root)
    self._names = [p.relative_to(self.root).as_posix() for p in self.paths]
    if self._names == ["."]:  # the root is itself a scene
      self._names = [self.root.resolve().name]
    self._meta: dict[int, dict[str, Any]] = {}
    self.info = self._read_dataset_json()
    self.splits: dict[str, list[str]] | None = self.info.get("splits")
    # Named by the file it came from: dataset.json's, else the first scene's meta.json.
    where = self.root / "dataset.json" if "code" in self.info else self.paths[0] / "meta.json"
    code = self.info.get("code", self._meta_of(0).get("code"))
    if code not in (None, "binary", "gray"):
      raise SljaxError(f"{where}: code {code!r} must be 'binary' or 'gray'")
    self.code: str | None = code
    t = self.info.get("patterns")
    if t is None:
      sl0 = self.paths[0] / "sl0"
      t = sum(1 for p in sl0.glob("[0-9][0-9][0-9]*.png")) if sl0.is_dir() else None
    self.num_patterns: int | None = int(t) if t else None

  def _read_dataset_json(self) -> dict[str, Any]:
    path = self.root / "dataset.json"
    if not path.exists():
      return {}
    info = read_json_object(path, str(path))
    splits = info.get("splits")
    if splits is not None and not (
        isinstance(splits, dict) and set(splits) <= {"train", "test"}
        and all(isinstance(v, list) and all(isinstance(s, str) for s in v)
                for v in splits.values())):
      raise SljaxError(f"{path}: 'splits' must be {{\"train\": [scene paths], "
                       "\"test\": [scene paths]}}")
    if "patterns" in info and not (isinstance(info["patterns"], int) and info["patterns"] > 0):
      raise SljaxError(f"{path}: 'patterns' must be a positive integer")
    return info

  def _meta_of(self, i: int) -> dict[str, Any]:
    """Scene i's meta.json ({} when absent), read once."""
    if i not in self._meta:
      path = self.paths[i] / "meta.json"
      self._meta[i] = (read_json_object(path, f"scene {self.paths[i]}: meta.json")
                       if path.exists() else {})
    return self._meta[i]

  def meta(self, i: int) -> dict[str, Any]:
    """A copy of scene i's meta.json ({} when absent), without loading its images."""
    return dict(self._meta_of(self._index(i)))

  def __len__(self) -> int:
    return len(self.paths)

  def _index(self, i: int) -> int:
    if not -len(self) <= i < len(self):
      raise IndexError(f"scene index {i} out of range for {len(self)} scenes")
    return i % len(self)

  def get(self, i: int, parts: set[str] | None = None, gray: bool | None = None) -> Scene:
    """Loads scene i (only the given scene-folder parts; None = all present ones)."""
    i = self._index(i)
    scene = load_scene(self.paths[i], gray=self.gray if gray is None else gray, parts=parts)
    scene.name = self._names[i]
    t = self.info.get("patterns")
    if t:  # a network of t patterns takes the t coarsest of a scene that holds more
      scene.sl0, scene.sl1 = (None if p is None else p[..., :t] for p in (scene.sl0, scene.sl1))
    if parts is None or "meta" not in parts:
      scene.meta = self.meta(i)
    return scene

  def __getitem__(self, i: int) -> Scene:
    return self.get(i)

  def name(self, i: int) -> str:
    """The scene's path relative to the root."""
    return self._names[self._index(i)]

  def group(self, i: int) -> str:
    """meta.json "group", else the scene's relative path."""
    i = self._index(i)
    return str(self._meta_of(i).get("group", self._names[i]))


def _group_rank(group: str, seed: int) -> int:
  """A stable pseudo-random key per (seed, group); independent of Python's hash salt."""
  digest = hashlib.sha256(f"{seed}\x00{group}".encode("utf-8")).digest()
  return int.from_bytes(digest[:8], "big")


def _explicit_split(source, splits: dict[str, list[str]]) -> tuple[list[int], list[int]]:
  names = [source.name(i) for i in range(len(source))]
  root = getattr(source, "root", "dataset")

  def select(entries: list[str], which: str) -> set[int]:
    chosen = set()
    for entry in entries:
      e = entry.strip("/")
      hit = {i for i, n in enumerate(names) if n == e or n.startswith(e + "/")}
      if not hit:
        raise SljaxError(f"{root}/dataset.json: {which} split names {entry!r}, "
                         "which matches no scene")
      chosen |= hit
    return chosen

  test = select(splits.get("test", []), "test")
  train = select(splits["train"], "train") if "train" in splits else set(range(len(names))) - test
  if "train" in splits and "test" not in splits:
    test = set(range(len(names))) - train
  both = train & test
  if both:
    raise SljaxError(f"{root}/dataset.json: scene {names[min(both)]!r} is in both splits")
  return sorted(train), sorted(test)


def _pick_groups(groups: Sequence[str], fraction: float, seed: int) -> set[str]:
  """round(fraction * groups) of the distinct groups, the first in SHA-256 (seed, group) order;
  at least one when there are two or more and the fraction is positive, never all of them
  when the fraction is below 1."""
  unique = sorted(set(groups), key=lambda g: (_group_rank(g, seed), g))
  n = int(round(fraction * len(unique)))
  if fraction > 0 and len(unique) >= 2:
    n = max(n, 1)
  if fraction < 1 and len(unique) >= 2:
    n = min(n, len(unique) - 1)
  return set(unique[:n])


def split_indices(source, test_fraction: float = 0.2,
                  seed: int = 0) -> tuple[list[int], list[int]]:
  """Deterministic group-level (train, test) split; dataset.json "splits" wins when present.

  Groups are ordered by a SHA-256 hash of (seed, group) and the first round(test_fraction *
  groups) of them form the test set (at least one group when there are two or more and the
  fraction is positive), so no group is split across train and test. Training uses this
  split's test part for validation; split_three adds a separate test part.
  """
  if not 0.0 <= test_fraction <= 1.0:
    raise SljaxError(f"test fraction must be in [0, 1], got {test_fraction}")
  n = len(source)
  if n == 0:
    raise SljaxError("empty dataset: nothing to split")
  splits = getattr(source, "splits", None)
  if splits:
    return _explicit_split(source, splits)
  groups = [source.group(i) for i in range(n)]
  test_groups = _pick_groups(groups, test_fraction, seed)
  train = [i for i in range(n) if groups[i] not in test_groups]
  test = [i for i in range(n) if groups[i] in test_groups]
  return train, test


def split_three(source, val_fraction: float, test_fraction: float, seed: int,
                test_seed: int = 0) -> tuple[list[int], list[int], list[int]]:
  """Deterministic group-level (train, validation, test) split.

  The test groups depend on test_seed only (the same for every training seed; dataset.json
  "splits" "test" wins when present): split_indices(source, test_fraction, test_seed)'s test
  part. Validation is round(val_fraction * remaining groups) of the remaining groups, drawn
  with seed as split_indices draws its test part; the rest is training. No group is in two
  parts.
  """
  if not 0.0 <= val_fraction < 1.0:
    raise SljaxError(f"validation fraction must be in [0, 1), got {val_fraction}")
  rest, test = split_indices(source, test_fraction, seed=test_seed)
  groups = {i: source.group(i) for i in rest}
  val_groups = _pick_groups(list(groups.values()), val_fraction, seed)
  train = [i for i in rest if groups[i] not in val_groups]
  val = [i for i in rest if groups[i] in val_groups]
  return train, val, test


def parse_fraction(text: str | float) -> float:
  """'1/16', '0.0625', '6.25%' or a number -> a fraction in (0, 1]."""
  if isinstance(text, (int, float)):
    value = float(text)
  else:
    s = str(text).strip()
    try:
      value = float(s[:-1]) / 100 if s.endswith("%") else float(fractions.Fraction(s))
    except (ValueError, ZeroDivisionError):
      raise SljaxError(f"fraction {text!r}: expected e.g. 1/16, 0.0625 or 6.25%") from None
  if not 0.0 < value <= 1.0:
    raise SljaxError(f"fraction {text!r} must be in (0, 1]")
  return value


def take_fraction(indices: Sequence[int], fraction: str | float, seed: int = 0) -> list[int]:
  """A seeded subset of round(fraction * n) indices (at least one), returned sorted.

  Smaller fractions with the same seed give subsets of larger ones.
  """
  f = parse_fraction(fraction)
  pool = sorted(int(i) for i in indices)
  if not pool:
    raise SljaxError("cannot take a fraction of an empty set of scenes")
  n = max(1, int(round(f * len(pool))))
  order = np.random.default_rng(seed).permutation(len(pool))
  return sorted(pool[k] for k in order[:n])


def _nearest_index(n_out: int, n_in: int) -> np.ndarray:
  """Source index of each output pixel centre under nearest-neighbour resampling."""
  return np.minimum(((np.arange(n_out) + 0.5) * (n_in / n_out)).astype(np.int64), n_in - 1)


def resize_nearest(a: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
  """Nearest-neighbour resize of the first two axes (keeps inf/NaN and any channel count)."""
  ys = _nearest_index(hw[0], a.shape[0])
  xs = _nearest_index(hw[1], a.shape[1])
  return a[ys[:, None], xs[None, :]]


def resize_image(img: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
  """Area-averaging when shrinking, bilinear when enlarging; HxWxC float32."""
  if img.shape[:2] == tuple(hw):
    return img
  shrink = hw[0] * hw[1] < img.shape[0] * img.shape[1]
  interpolation = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
  out = cv2.resize(img, (hw[1], hw[0]), interpolation=interpolation)
  return out.reshape(hw[0], hw[1], img.shape[2])


def _crop_offset(seed: int, epoch: int, index: int, shape: tuple[int, int],
                 hw: tuple[int, int]) -> tuple[int, int]:
  rng = np.random.default_rng([seed, epoch, index])
  return int(rng.integers(0, shape[0] - hw[0] + 1)), int(rng.integers(0, shape[1] - hw[1] + 1))


def _scene_name(source, i: int, scene: Scene) -> str:
  name = getattr(source, "name", None)
  return name(i) if callable(name) else scene.name


def load_batch(source, indices: Sequence[int], *, size: int | Sequence[int] | None = None,
               mode: str = "resize", gray: bool = False, seed: int = 0, epoch: int = 0,
               parts: Sequence[str] = DEFAULT_PARTS) -> dict[str, np.ndarray]:
  """Loads the given scenes as one batch dict (keys = parts) of stacked arrays.

  size: (height, width) or an int; None keeps the native size (scenes must then agree).
  mode "resize": images area/bilinear, disparity nearest and scaled by new_width/old_width,
  patterns and masks nearest. mode "crop": a crop whose offset depends only on (seed, epoch,
  scene index). gray: True gives one channel, False three.
  """
  parts = tuple(parts)
  bad = [p for p in parts if p not in BATCH_PARTS]
  if bad:
    raise SljaxError(f"unknown batch part(s) {bad}; choose from {list(BATCH_PARTS)}")
  if mode not in ("resize", "crop"):
    raise SljaxError(f"mode must be 'resize' or 'crop', got {mode!r}")
  hw = as_size(size)
  if mode == "crop" and hw is None:
    raise SljaxError("crop mode needs a size")
  if len(indices) == 0:
    raise SljaxError("cannot load an empty batch")
  folder_parts = {PART_FIELD[p][1] for p in parts} | {"im"}
  out: dict[str, list[np.ndarray]] = {p: [] for p in parts}
  for i in indices:
    i = int(i)
    # Folder scenes load only the files the batch needs; other sources build whole scenes.
    scene = source.get(i, parts=folder_parts) if isinstance(source, FolderSource) else source[i]
    name = _scene_name(source, i, scene)
    native = tuple(scene.im0.shape[:2])
    target = native if hw is None else hw
    if mode == "crop":
      if native[0] < hw[0] or native[1] < hw[1]:
        raise SljaxError(f"scene {name}: {native[1]}x{native[0]} is smaller than the crop "
                         f"{hw[1]}x{hw[0]}")
      y0, x0 = _crop_offset(seed, epoch, i, native, hw)
    for p in parts:
      field = PART_FIELD[p][0]
      a = getattr(scene, field)
      if a is None:
        raise SljaxError(f"scene {name}: {_SCENE_FILE[field]}: missing (needed for batch "
                         f"part {p!r})")
      a = np.asarray(a)
      if p in ("left", "right"):
        a = a.astype(np.float32)
        a = to_gray(a) if gray else (np.repeat(a, 3, axis=2) if a.shape[2] == 1 else a)
      if mode == "crop":
        a = a[y0:y0 + hw[0], x0:x0 + hw[1]]
      elif target != native:
        if p in ("left", "right"):
          a = resize_image(a, target)
        else:
          a = resize_nearest(a, target)
          if p.startswith("disp"):
            a = a * np.float32(target[1] / native[1])
      if out[p] and a.shape != out[p][0].shape:
        raise SljaxError(f"scene {name}: {_SCENE_FILE[field]}: shape {a.shape} differs from "
                         f"the batch's {out[p][0].shape} (give a size, or patterns counts differ)")
      out[p].append(a)
  batch = {}
  for p, arrays in out.items():
    stacked = np.stack(arrays)
    batch[p] = stacked if p == "mask" else stacked.astype(np.float32, copy=False)
  return batch


def epoch_order(indices: Sequence[int], seed: int, epoch: int) -> list[int]:
  """The scene order of an epoch: a permutation of indices drawn from (seed, epoch) only."""
  perm = np.random.default_rng([seed, epoch]).permutation(len(indices))
  return [int(indices[k]) for k in perm]


def scene_indices(indices: Sequence[int], n: int) -> list[int]:
  """indices as ints, each within a source of n scenes; SljaxError naming the first bad one (a
  float or a string used to be truncated or fail inside the loader, mid-epoch)."""
  out = []
  for i in indices:
    try:
      out.append(operator.index(i))
    except TypeError:
      raise SljaxError(f"scene indices must be integers, got {i!r}") from None
    if not -n <= out[-1] < n:
      raise SljaxError(f"scene index {out[-1]} is out of range for {n} scenes")
  return out


def iterate_batches(source, indices: Sequence[int], batch_size: int, *, seed: int, epoch: int,
                    size: int | Sequence[int] | None = None, mode: str = "resize",
                    gray: bool = False, drop_last: bool = True, shuffle: bool = True,
                    parts: Sequence[str] = DEFAULT_PARTS) -> Iterator[dict[str, np.ndarray]]:
  """Batches over indices; with shuffle the order is a permutation drawn from (seed, epoch)."""
  indices = scene_indices(indices, len(source))
  if not indices:
    raise SljaxError("no scenes to iterate over (empty dataset or split)")
  if batch_size <= 0:
    raise SljaxError(f"batch size must be positive, got {batch_size}")
  if drop_last and batch_size > len(indices):
    raise SljaxError(f"batch size {batch_size} exceeds the {len(indices)} scenes available "
                     "(drop_last would give no batch)")
  if shuffle:
    indices = epoch_order(indices, seed, epoch)
  stop = len(indices) - len(indices) % batch_size if drop_last else len(indices)
  for start in range(0, stop, batch_size):
    yield load_batch(source, indices[start:start + batch_size], size=size, mode=mode, gray=gray,
                     seed=seed, epoch=epoch, parts=parts)
