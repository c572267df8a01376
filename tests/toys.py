"""Tiny stand-in models shared by the tests (inference, evaluation, the training loop),
another process holding a folder, and a child process's environment."""

import contextlib
import functools
import os
import subprocess
import sys
from pathlib import Path

import flax.linen as nn
import jax.numpy as jnp

from sljax.nets import registry
from sljax.nets.model_config import INIT_COMPILER_OPTIONS
from sljax.train import state as train_state
from sljax.train import step as stp

ROOT = Path(__file__).resolve().parent.parent


class ToySL(nn.Module):
  """Pattern logits = +-20 from the views themselves (t = channels), both views."""
  in_channels: int = 3
  conv_impl: str | None = None

  @nn.compact
  def __call__(self, left, right, train=False):
    gain = self.param("gain", nn.initializers.ones, ())
    return {"sl_logits": 20.0 * gain * (2.0 * left - 1.0),
            "sl_logits_right": 20.0 * gain * (2.0 * right - 1.0)}


def toy_spec(name: str, cls: type, outputs: tuple[str, ...] = ("disparity",), pad: str = "zero",
             gray: bool = True) -> registry.NetSpec:
  """A registry entry for a toy network of the tests (a flax module at a module's top level
  with in_channels and conv_impl fields, as ModelConfig.build passes them)."""
  return registry.NetSpec(name, f"{cls.__module__}:{cls.__qualname__}", parts=(),
                          tasks=("disp",), gray=gray, outputs=outputs, options=(), pad=pad)


@contextlib.contextmanager
def registered(*specs: registry.NetSpec):
  """The toy networks in sljax.nets.registry.NETS while the block runs."""
  added = [s.name for s in specs if s.name not in registry.NETS]
  registry.NETS.update({s.name: s for s in specs if s.name in added})
  try:
    yield
  finally:
    for name in added:
      del registry.NETS[name]


class TinyTwin(nn.Module):
  """A stand-in for the PSMNet twin with the same outputs (compiles in a second)."""
  maxdisp: int
  t: int

  @nn.compact
  def __call__(self, left, right, train: bool = False):
    # No bias before BatchNorm (as PSMNet): its gradient would be rounding noise only.
    h = nn.Conv(4, (3, 3), use_bias=False)(jnp.concatenate([left, right], -1))
    h = nn.relu(nn.BatchNorm(use_running_average=not train)(h))
    d = self.maxdisp * nn.sigmoid(nn.Conv(3, (1, 1))(h))
    out = {"disparity": d[..., 2], "sl_logits": nn.Conv(self.t, (1, 1))(h)}
    if train:
      out["disparities"] = (d[..., 0], d[..., 1], d[..., 2])
    return out


@functools.lru_cache(maxsize=None)
def tiny_steps(model_config, disp_loss, lr, lr_drop_step, mesh, ynn="on"):
  """Drop-in for sljax.train.loop.compiled_steps that trains TinyTwin for any PSMNet."""
  model = TinyTwin(maxdisp=model_config.maxdisp, t=model_config.t or 4)
  tx = train_state.make_optimizer(lr, lr_drop_step)
  opts = INIT_COMPILER_OPTIONS
  return (model, tx,
          stp.make_train_step(model, model_config, disp_loss=disp_loss, tx=tx, mesh=mesh,
                              compiler_options=opts),
          stp.make_eval_step(model, model_config, mesh=mesh, compiler_options=opts))


_HOLD = """import sys, time
from sljax.io import files
with files.exclusive(sys.argv[1], sys.argv[2]):
  print("held", flush=True)
  time.sleep(600)
"""


def hold(folder, what: str) -> subprocess.Popen:
  """Another process holding folder with sljax.io.files.exclusive (kill it to end the hold)."""
  proc = subprocess.Popen([sys.executable, "-c", _HOLD, str(folder), what], text=True,
                          stdout=subprocess.PIPE, env=dict(os.environ, PYTHONPATH=str(ROOT)))
  assert proc.stdout.readline() == "held\n"
  return proc


def same_device_env() -> dict:
  """A child's environment for a run that is compared bitwise with this process's: the same
  platform (a run killed on the CPU and resumed on a GPU differs by float rounding: exact-resume
  tests failed so on an H200 and an H100) and no preallocation (this process holds a GPU)."""
  import jax  # pylint: disable=import-outside-toplevel
  env = dict(os.environ, PYTHONPATH=str(ROOT), XLA_PYTHON_CLIENT_PREALLOCATE="false")
  if jax.default_backend() == "cpu":  # elsewhere the child picks the accelerator as this did
    env["JAX_PLATFORMS"] = "cpu"
  return env


def need_submitit() -> None:
  """Skips the test without submitit (the [cluster] extra), without importing it here: its
  import reconfigures logging, closing pytest's handlers (sljax.experiment.running.submit imports it
  so that it does not)."""
  import importlib.util  # pylint: disable=import-outside-toplevel
  import pytest  # pylint: disable=import-outside-toplevel
  if importlib.util.find_spec("submitit") is None:
    pytest.skip("submitit is not installed (pip install -e '.[cluster]')")


def tree(folder) -> dict[str, bytes]:
  """Every file below folder (hidden ones included) with its bytes; {} when folder is absent:
  the all-or-nothing tests compare an output place before and after a failed command."""
  folder = Path(folder)
  return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
          if p.is_file()} if folder.exists() else {}


def break_deflate(path) -> None:
  """Damages a PNG as a broken encoder would: valid chunks and CRCs, the first IDAT's data
  replaced by bytes that do not inflate. The checks that inflate (`info --check`, the
  pre-flight, decode's) name it up front; a reader that only reads the header fails later."""
  import struct  # pylint: disable=import-outside-toplevel
  import zlib  # pylint: disable=import-outside-toplevel
  data = bytearray(Path(path).read_bytes())
  pos = data.index(b"IDAT") - 4
  length = struct.unpack(">I", data[pos:pos + 4])[0]
  junk = b"\x78\x9c" + b"\xff" * (length - 2)  # a zlib header, then an invalid deflate block
  data[pos + 8:pos + 8 + length] = junk
  data[pos + 8 + length:pos + 12 + length] = struct.pack(">I", zlib.crc32(b"IDAT" + junk))
  Path(path).write_bytes(bytes(data))
