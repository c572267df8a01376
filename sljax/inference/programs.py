"""The compiled inference programs of a process, and the twin's two-program split.

Every predictor runs its network through `PROGRAMS`, one explicit cache per process: a jitted
function per program kind, XLA:CPU YNNPACK choice and equal model (flax modules compare by
their fields), so jax keeps one compilation per model and input shape.
Both resolution modes, or several checkpoints of one configuration, share it (in resize mode
the input is always the training size). Where a command line keeps compiled programs on disk
(`sljax.runtime.kept_programs`: `sljax predict`, `evaluate`, ...), each program is kept whole, keyed by
its kind, the model's fields and the compiler options, so a second command neither traces,
lowers nor compiles it (a warm `sljax predict` of one 256x256 pair with the twin: 3.1 s
instead of 4.4 s on a 2-core Zen 5).

Memory at full resolution: the twin (psmnet-mtl) holds two stacks of 3D activations; when its
cost volume is large (TWIN_SPLIT_BYTES) it runs as two programs, PSMNet on the disparity
path's variables and then its SL path alone (`SLOnly`), with the same outputs.
"""

import collections
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from sljax.nets.model_config import ModelConfig
from sljax.nets.psmnet import PSMNet
from sljax.nets.psmnet_mtl import SLOnly, detach_sl
from sljax.runtime import choices, kept_programs

# The twin runs as two programs when its cost volume would exceed this many bytes; the two 3D
# stacks are then never alive together (1024x1280, maxdisp 192: peak 9.2 -> 6.2 GiB with the
# unblocked convolutions, 4.0 GiB with sljax.kernels' blocked ones).
TWIN_SPLIT_BYTES = 256 * 2**20
SHAPE_CACHE = 16  # abstract runs kept (an experiment grid loads many checkpoints of one model)


def outputs(model, variables, left, right) -> dict[str, jax.Array]:
  """Eval-mode outputs: float32 disparity and pattern probabilities (sigmoid of the logits)."""
  out = model.apply(variables, left, right, train=False)
  res = {}
  if "disparity" in out:
    res["disparity"] = out["disparity"].astype("float32")
  if "sl_logits" in out:
    res["patterns"] = jax.nn.sigmoid(out["sl_logits"])
  if "sl_logits_right" in out:
    res["patterns_right"] = jax.nn.sigmoid(out["sl_logits_right"])
  return res


def sl_outputs(model, variables, left, right) -> dict[str, jax.Array]:
  """Pattern probabilities of the twin's SL path alone (SLOnly)."""
  return {"patterns": jax.nn.sigmoid(model.apply(variables, left, right, train=False))}


KINDS = {"forward": outputs, "sl": sl_outputs}


class Programs:
  """The jitted inference programs of this process, shared by every predictor.

  `run(kind, ynn, model, ...)` calls the jitted KINDS[kind] with XLA:CPU's YNNPACK fusions on
  or off (sljax.runtime.choices's forward choice); `traces(model)` says how often a model was traced
  (compiled) here; `variable_shapes` keeps the last SHAPE_CACHE abstract initialisations
  (tracing a PSMNet takes seconds).
  """

  def __init__(self):
    self._programs: dict[tuple[str, bool, Any], kept_programs.Program] = {}
    self._traces: collections.Counter = collections.Counter()
    self._shapes: collections.OrderedDict = collections.OrderedDict()

  def traces(self, model) -> int:
    """How often `model` (or an equal one) was traced in this process."""
    return self._traces[model]

  def run(self, kind: str, ynn: bool, model, variables, left, right) -> dict[str, jax.Array]:
    """The compiled program of `kind` applied to prepared inputs."""
    return self._program(kind, bool(ynn), model)(variables, left, right)

  def _program(self, kind: str, ynn: bool, model) -> kept_programs.Program:
    """The program of `kind` for `model` (one per equal model): jitted, and kept on disk
    where a command line keeps compiled programs."""
    key = (kind, ynn, model)
    if key not in self._programs:
      def counted(variables, left, right, fn=KINDS[kind]):
        self._traces[model] += 1  # runs only while tracing: counts compilations
        return fn(model, variables, left, right)
      options = choices.KernelChoice(forward_ynn=ynn).compiler_options("forward")
      self._programs[key] = kept_programs.Program(jax.jit(counted, compiler_options=options),
                                                f"inference-{kind}", (repr(model), options))
    return self._programs[key]

  def variable_shapes(self, model, channels: int, h: int, w: int) -> dict[str, Any]:
    """The variables' shapes (ShapeDtypeStructs) of `model` on 1 x h x w x channels inputs."""
    key = (model, channels, h, w)
    if key not in self._shapes:
      x = jax.ShapeDtypeStruct((1, h, w, channels), jnp.float32)
      self._shapes[key] = jax.eval_shape(
          lambda a, b: model.init(jax.random.PRNGKey(0), a, b, train=False), x, x)
      if len(self._shapes) > SHAPE_CACHE:
        self._shapes.popitem(last=False)
    self._shapes.move_to_end(key)
    return self._shapes[key]


PROGRAMS = Programs()


def twin_split_needed(config: ModelConfig, shape: tuple[int, ...]) -> bool:
  """True for a twin whose cost volume for a BxHxWxC input exceeds TWIN_SPLIT_BYTES."""
  if config.spec.single is None:
    return False
  b, h, w = shape[0], shape[1], shape[2]
  return 4 * b * (config.maxdisp // 4) * (h // 4) * (w // 4) * 64 > TWIN_SPLIT_BYTES


def twin_halves(model) -> tuple[PSMNet, SLOnly]:
  """(PSMNet, SLOnly) with a twin's configuration."""
  kw = {"maxdisp": model.maxdisp, "in_channels": model.in_channels,
        "align_corners": model.align_corners, "conv_impl": model.conv_impl}
  return PSMNet(**kw), SLOnly(t=model.t, **kw)


def forward(config: ModelConfig, model, variables, left, right, split: bool | None = None,
            ynn: bool = True) -> dict[str, jax.Array]:
  """The network's eval outputs (disparity, pattern probabilities) for prepared inputs;
  split: the twin as two programs (None: when large); ynn: the YNNPACK fusions on or off."""
  if split is None:
    split = twin_split_needed(config, np.shape(left))
  if not split:
    return PROGRAMS.run("forward", ynn, model, variables, left, right)
  plain, sl_only = twin_halves(model)
  out = dict(PROGRAMS.run("forward", ynn, plain, detach_sl(variables), left, right))
  out.update(PROGRAMS.run("sl", ynn, sl_only, variables, left, right))
  return out
