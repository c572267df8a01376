"""Conversion of official PyTorch PSMNet (stacked hourglass) weights to sljax variables.

Layouts (PyTorch -> flax):
* Conv2d weight (out, in, kh, kw) -> kernel (kh, kw, in, out).
* Conv3d weight (out, in, kd, kh, kw) -> kernel (kd, kh, kw, in, out).
* ConvTranspose3d weight (in, out, kd, kh, kw) -> spatially flipped, then (kd, kh, kw, in, out):
  `ConvTranspose3D` applies its kernel unflipped to the stride-dilated input, PyTorch's
  transposed convolution is the adjoint of a correlation, i.e. the same with the kernel flipped.
* BatchNorm weight / bias -> params scale / bias; running_mean / running_var -> batch_stats
  mean / var. Both use epsilon 1e-5 and normalise by sqrt(var + eps) in evaluation, so the
  statistics carry over unchanged; PyTorch's momentum 0.1 is flax's momentum 0.9 (see
  sljax.nets.layers). `num_batches_tracked` counters are dropped.

The key mapping is derived from the model itself: every variable of sljax's PSMNet is named
by `sljax.nets.psmnet.reference_key`, and which kernels belong to transposed convolutions is
recorded while the model is traced. Keys left over on either side are errors listing them.

A converted model is a directory with config.json ({"model": "psmnet", "model_kwargs": ...})
and variables.npz ('/'-joined paths such as "params/dres0/convbn_0/conv/kernel").
"""

from __future__ import annotations

import functools
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from sljax.errors import SljaxError, require
from sljax.io import files
from sljax.io.files import read_json_object
from sljax.kernels import ConvTranspose3D
from sljax.nets.psmnet import PSMNet, reference_key

CONFIG_FILE = "config.json"
VARIABLES_FILE = "variables.npz"
FORMAT = "sljax-converted-psmnet"
_IGNORED_SUFFIXES = ("num_batches_tracked",)


def conv_weight_to_flax(w: np.ndarray) -> np.ndarray:
  """PyTorch ConvNd weight (out, in, *k) -> flax kernel (*k, in, out)."""
  nd = w.ndim - 2
  return np.ascontiguousarray(np.transpose(w, tuple(range(2, 2 + nd)) + (1, 0)))


def conv_transpose_weight_to_flax(w: np.ndarray) -> np.ndarray:
  """PyTorch ConvTransposeNd weight (in, out, *k) -> flipped flax kernel (*k, in, out)."""
  nd = w.ndim - 2
  spatial = tuple(range(2, 2 + nd))
  return np.ascontiguousarray(np.transpose(np.flip(w, spatial), spatial + (0, 1)))


def _flatten(tree: Mapping, prefix: tuple[str, ...] = ()) -> dict[tuple[str, ...], Any]:
  out = {}
  for k, v in tree.items():
    if isinstance(v, Mapping):
      out.update(_flatten(v, prefix + (k,)))
    else:
      out[prefix + (k,)] = v
  return out


def _unflatten(flat: Mapping[tuple[str, ...], Any]) -> dict:
  tree: dict = {}
  for path, v in flat.items():
    node = tree
    for k in path[:-1]:
      node = node.setdefault(k, {})
    node[path[-1]] = v
  return tree


@functools.lru_cache(maxsize=4)
def psmnet_template(in_channels: int = 3) -> tuple[dict, frozenset[tuple[str, ...]]]:
  """Shapes of sljax PSMNet's variables and the module paths of its transposed convolutions.

  Cached (tracing takes seconds); callers must not modify the returned tree.
  """
  transposed: set[tuple[str, ...]] = set()

  def record(next_fun, args, kwargs, context):
    if isinstance(context.module, ConvTranspose3D) and context.method_name == "__call__":
      transposed.add(tuple(context.module.path))
    return next_fun(*args, **kwargs)

  # Parameter shapes do not depend on the image size or maxdisp: trace the smallest model.
  model = PSMNet(maxdisp=16, in_channels=in_channels)
  x = jnp.zeros((1, 16, 16, in_channels), jnp.float32)
  with nn.intercept_methods(record):
    shapes = jax.eval_shape(model.init, jax.random.PRNGKey(0), x, x)
  return jax.tree.map(lambda s: tuple(s.shape), shapes), frozenset(transposed)


def _strip_module(state_dict: Mapping[str, Any]) -> dict[str, np.ndarray]:
  out = {}
  for k, v in state_dict.items():
    if k.endswith(_IGNORED_SUFFIXES):
      continue
    out[k[len("module."):] if k.startswith("module.") else k] = np.asarray(v)
  return out


def convert_state_dict(state_dict: Mapping[str, Any]) -> dict:
  """Reference PSMNet state_dict (numpy arrays; 'module.' prefixes allowed) -> sljax variables.

  Returns {"params": ..., "batch_stats": ...} nested dicts of float32 numpy arrays for
  `build_model("psmnet", in_channels=...)`, the input channels read from the first conv.
  """
  sd = _strip_module(state_dict)
  first = "feature_extraction.firstconv.0.0.weight"
  require(first in sd, f"not a PSMNet state_dict: no key {first!r} (found e.g. "
          f"{', '.join(sorted(sd)[:3]) or 'nothing'})")
  in_channels = int(sd[first].shape[1])
  template, transposed = psmnet_template(in_channels)
  flat = {}
  missing, bad_shape = [], []
  used = set()
  for (collection, *path), shape in _flatten(template).items():
    key = reference_key(tuple(path))
    if key not in sd:
      missing.append(key)
      continue
    used.add(key)
    w = np.asarray(sd[key], np.float32)
    if path[-1] == "kernel":
      w = (conv_transpose_weight_to_flax(w) if tuple(path[:-1]) in transposed
           else conv_weight_to_flax(w))
    if w.shape != tuple(shape):
      bad_shape.append(f"{key}: {tuple(sd[key].shape)} does not give {tuple(shape)}")
      continue
    flat[(collection, *path)] = w
  unused = sorted(set(sd) - used)
  problems = []
  if missing:
    problems.append(f"{len(missing)} missing key(s): {', '.join(missing)}")
  if unused:
    problems.append(f"{len(unused)} unexpected key(s): {', '.join(unused)}")
  if bad_shape:
    problems.append(f"{len(bad_shape)} wrong shape(s): {'; '.join(bad_shape)}")
  require(not problems, "state_dict does not match PSMNet (stacked hourglass): "
          + " | ".join(problems))
  return _unflatten(flat)


def read_state_dict(path: str | Path) -> dict[str, np.ndarray]:
  """Reads a PyTorch checkpoint ({'state_dict': ...} or a bare state_dict) or an .npz of one."""
  path = Path(path)
  require(path.is_file(), f"checkpoint {path} does not exist")
  if path.suffix == ".npz":
    return files.read_npz(path, "a PyTorch state_dict")
  try:
    import torch
  except ImportError as e:
    raise SljaxError(f"reading {path} needs PyTorch: pip install \"sljax[torch]\"") from e
  try:
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
  except Exception as e:  # torch raises many types for foreign or unsafe files
    raise SljaxError(f"cannot read {path} as a PyTorch checkpoint: {e}") from e
  sd = ckpt.get("state_dict", ckpt) if isinstance(ckpt, dict) else None
  require(isinstance(sd, Mapping) and all(hasattr(v, "shape") for v in sd.values()),
          f"{path} holds no state_dict (expected a dict with 'state_dict' of tensors)")
  return {k: v.detach().cpu().numpy() for k, v in sd.items()}


def save_converted(out: str | Path, variables: Mapping, model_kwargs: Mapping[str, Any],
                   overwrite: bool = False, source: str | None = None) -> Path:
  """Writes OUT/config.json and OUT/variables.npz; refuses to overwrite unless asked."""
  out = Path(out)
  targets = [out / CONFIG_FILE, out / VARIABLES_FILE]
  existing = [str(f) for f in targets if f.exists()]
  require(overwrite or not existing,
          f"{', '.join(existing)} already exist(s); pass --overwrite to replace")
  require(not out.exists() or out.is_dir(), f"{out} exists and is not a directory")
  out.mkdir(parents=True, exist_ok=True)
  flat = {"/".join(p): np.asarray(v, np.float32) for p, v in _flatten(variables).items()}
  config = {"model": "psmnet", "model_kwargs": dict(model_kwargs), "format": FORMAT}
  if source is not None:
    config["source"] = source
  # Both whole or neither: a full disk keeps an earlier conversion (--overwrite) intact.
  with files.replacing(*targets) as (config_tmp, variables_tmp):
    np.savez(variables_tmp, **flat)
    config_tmp.write_text(json.dumps(config, indent=2) + "\n")
  return out


def is_converted(path: str | Path) -> bool:
  """True when path is a directory written by save_converted."""
  path = Path(path)
  return (path / CONFIG_FILE).is_file() and (path / VARIABLES_FILE).is_file()


def load_converted(path: str | Path) -> tuple[str, dict, dict]:
  """Reads a converted directory -> (model_name, model_kwargs, variables as numpy arrays)."""
  path = Path(path)
  cfg = path / CONFIG_FILE
  if cfg.is_file() and (is_converted(path) or (path / "checkpoints").is_dir()):
    config = read_json_object(cfg, str(cfg))  # a damaged config.json says so, not "not a ..."
  # Also reached for any folder given where a checkpoint is expected, so name every kind.
  require(is_converted(path), f"{path}: not a checkpoint (expected a training workdir with "
          f"config.json and checkpoints/, its checkpoints folder, or a converted PSMNet folder "
          f"with {CONFIG_FILE} and {VARIABLES_FILE})")
  require("model" in config,
          f"{path / CONFIG_FILE} has no 'model' entry")
  arrays = files.read_npz(path / VARIABLES_FILE, "converted PSMNet variables")
  flat = {tuple(k.split("/")): v for k, v in arrays.items()}
  return config["model"], dict(config.get("model_kwargs", {})), _unflatten(flat)
