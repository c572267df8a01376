"""Parameter counts per part and output shapes of a model, without running it (jax.eval_shape)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from sljax.nets import build_model

_AGGREGATION = ("dres0", "dres1", "dres2", "dres3", "dres4")
_CLASSIFIERS = ("classif1", "classif2", "classif3")


@dataclasses.dataclass(frozen=True)
class ModelSummary:
  """Parameter counts (rows of (part, count, indent)) and output shapes per mode."""
  name: str
  input_shape: tuple[int, ...]
  rows: tuple[tuple[str, int, int], ...]
  total: int
  batch_stats: int
  outputs: Mapping[str, Mapping[str, Any]]  # mode -> output key -> shape (tuples for lists)


def count_params(tree: Any) -> int:
  """Number of scalars in a (possibly abstract) pytree of arrays."""
  return int(sum(int(np.prod(x.shape)) for x in jax.tree_util.tree_leaves(tree)))


def _count_keys(params: Mapping[str, Any], predicate) -> int:
  return count_params({k: v for k, v in params.items() if predicate(k)})


def _rows(name: str, params: Mapping[str, Any]) -> list[tuple[str, int, int]]:
  if name.startswith("psmnet"):
    agg = _count_keys(params, lambda k: k in _AGGREGATION)
    cls = _count_keys(params, lambda k: k in _CLASSIFIERS)
    rows = [("features (feature_extraction, shared)", count_params(params["feature_extraction"]),
             0),
            ("disparity path", agg + cls, 0),
            ("cost aggregation (dres0-dres4)", agg, 1),
            ("classifiers (classif1-3)", cls, 1)]
    if "sl" in params:
      sl = params["sl"]
      sl_agg = _count_keys(sl, lambda k: k in _AGGREGATION)
      rows += [("SL path (sl)", count_params(sl), 0),
               ("cost aggregation (sl/dres0-dres4)", sl_agg, 1),
               ("SL head", count_params(sl) - sl_agg, 1),
               ("PSMNet part (detach_sl)", count_params(params) - count_params(sl), 0)]
    return rows
  enc = _count_keys(params, lambda k: k.startswith("down") or k == "bottleneck")
  dec = _count_keys(params, lambda k: k.startswith("up"))
  return [("encoder (down*, bottleneck)", enc, 0), ("decoder (upconv*, up*)", dec, 0),
          ("head", count_params(params["head"]), 0)]


def _shapes(tree: Any) -> Any:
  return jax.tree_util.tree_map(lambda x: tuple(x.shape), tree)


def param_summary(name: str, size: tuple[int, int] = (256, 256), batch: int = 1,
                  **model_kwargs: Any) -> ModelSummary:
  """Counts parameters per part and derives output shapes of `name` for a [batch, H, W] input."""
  model = build_model(name, **model_kwargs)
  h, w = size
  x = jax.ShapeDtypeStruct((batch, h, w, model.in_channels), jnp.float32)
  variables = jax.eval_shape(lambda a, b: model.init(jax.random.PRNGKey(0), a, b), x, x)
  params = variables["params"]
  outputs = {"eval": _shapes(jax.eval_shape(
      lambda v, a, b: model.apply(v, a, b, train=False), variables, x, x))}
  train_out, _ = jax.eval_shape(
      lambda v, a, b: model.apply(v, a, b, train=True, mutable=["batch_stats"]), variables, x, x)
  outputs["train"] = _shapes(train_out)
  return ModelSummary(name=name, input_shape=(batch, h, w, model.in_channels),
                      rows=tuple(_rows(name, params)), total=count_params(params),
                      batch_stats=count_params(variables.get("batch_stats", {})),
                      outputs=outputs)


def format_summary(s: ModelSummary) -> str:
  """A plain-text table of a ModelSummary."""
  lines = [f"model {s.name}: input left/right {'x'.join(map(str, s.input_shape))}", "",
           f"{'part':<44}{'parameters':>14}"]
  for label, count, indent in s.rows:
    lines.append(f"{'  ' * indent + label:<44}{count:>14,}")
  lines.append(f"{'total':<44}{s.total:>14,}")
  lines.append(f"{'(batch statistics, not trained)':<44}{s.batch_stats:>14,}")
  for mode, outs in s.outputs.items():
    lines += ["", f"outputs ({mode}):"]
    for key in sorted(outs):
      shape = outs[key]
      if shape and isinstance(shape[0], tuple):
        text = ", ".join("x".join(map(str, sh)) for sh in shape)
      else:
        text = "x".join(map(str, shape))
      lines.append(f"  {key:<18}{text}")
  return "\n".join(lines)
