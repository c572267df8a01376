"""Training configuration: one frozen dataclass whose fields are the train.py flags, presets.

Each field is written once, with its default (the paper preset), its help text and how its
flag parses (`option`); `sljax.train.cli` generates the flags from the fields.
"""

import argparse
import dataclasses
import json
import math
from pathlib import Path
from typing import Any

from sljax.errors import SljaxError, require
from sljax.io import sizes
from sljax.losses.disparity import DISP_LOSSES
from sljax.losses.weighting import STRATEGIES
from sljax.nets import registry
from sljax.render.synth_config import DOMAINS
from sljax.train import tensorboard

MODELS = registry.MODELS
PRESETS = ("auto", "paper", "quick")
PRECISIONS = ("fp32", "bf16")
YNN = ("auto", "on", "off", "forward-off", "train-off")
CONV_IMPLS = ("auto", "lax", "fast", "gpu", "gpu-phase")  # sljax.kernels.impl.IMPLS (no jax here)


def parse_size(text: str) -> tuple[int, int]:
  """sizes.parse_size for argparse, which prints an ArgumentTypeError as a usage error."""
  try:
    return sizes.parse_size(text, "size")
  except SljaxError as e:
    raise argparse.ArgumentTypeError(str(e)) from None


def option(default: Any, help: str, *, parse: Any = None, choices: tuple[str, ...] | None = None,
           switch: tuple[tuple[str, str], tuple[str, str]] | None = None, resumable: bool = False,
           flag: bool = True) -> Any:
  """A TrainConfig field with its flag: help text, parser (default: the default's type),
  choices, an on/off `switch` pair of (flag, help) for an optional bool, and whether a
  --resume may change it (`resumable`: it does not change what the run computes)."""
  # pylint: disable=redefined-builtin
  return dataclasses.field(default=default, metadata={
      "help": help, "parse": parse or type(default), "choices": choices, "switch": switch,
      "resumable": resumable, "flag": flag})


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """Everything that determines a training run (SPEC 3-4 defaults = the paper preset)."""
  model: str = option("psmnet", "network: psmnet (stl: plain PSMNet; other strategies: the "
                      "twin with the SL path), unet-sl or unet-disp", choices=MODELS)
  strategy: str = option("stl", "loss weighting (PSMNet): stl = plain PSMNet; cg_a/cg_b/epr/unc "
                         "= the twin with the SL path", choices=STRATEGIES)
  data: str | None = option(None, "scene-format folder (default: synthetic scenes rendered on "
                            "the fly)", parse=str)
  domain: str = option("objects", "synthetic domain when --data is not given", choices=DOMAINS)
  synth_n: int = option(8000, "synthetic scenes (train + held-out); ~the paper's virtual set")
  synth_size: int = option(256, "synthetic render size (square); batches are resized to --size")
  synth_t: int | None = option(None, "synthetic patterns per view (default: 8 binary for "
                               "objects, 9 Gray for tissue)", parse=int)
  fraction: str = option("1", "fraction of the training split, e.g. 1/16")
  test_fraction: float = option(0.2, "held-out fraction of the groups (object level, SPEC 1)")
  epochs: int = option(120, "training epochs", resumable=True)
  steps: int | None = option(None, "training budget in optimizer steps instead of epochs (the "
                             "last epoch may end part-way)", parse=int, resumable=True)
  batch_size: int = option(12, "global batch (all devices; the reference PSMNet's 12)")
  lr: float = option(1e-4, "Adam learning rate (fixed, paper)")
  lr_drop_epoch: int | None = option(None, "epoch from which the learning rate is 10x lower "
                                     "(the PSMNet reference's step decay; default: fixed, as "
                                     "the paper)", parse=int)
  size: tuple[int, int] = option((256, 256), "training size N or HEIGHTxWIDTH (multiples of 16)",
                                 parse=parse_size)
  maxdisp: int = option(96, "PSMNet disparity range (multiple of 16)")
  seed: int = option(0, "seed of the synthetic data, split, subset, initial weights and order")
  disp_loss: str = option("l2", "l2 (paper) or smooth_l1 (reference PSMNet)",
                          choices=DISP_LOSSES)
  gray: bool | None = option(None, "input channels", switch=(
      ("--gray", "grayscale inputs (default for the UNets)"),
      ("--rgb", "RGB inputs (default for PSMNet)")))
  precision: str = option("fp32", "fp32, or bf16: bfloat16 computation with float32 "
                          "parameters, optimiser state, losses and disparity softmax",
                          choices=PRECISIONS)
  ynn: str = option("auto", "XLA:CPU YNNPACK fusions per program kind: auto (this machine's "
                    "`sljax tune` measurement, else the choice measured on its CPU kind; "
                    "SLJAX_TUNE=0 keeps XLA's default), on, off, forward-off (validation programs) or train-off; the "
                    "resolved value is saved in config.json, so a resume compiles the same "
                    "programs", choices=YNN)
  conv_impl: str = option("auto", "convolution kernels: auto (fast on a CPU, gpu on a GPU, "
                          "else lax), lax (XLA's as written), fast (sljax's exact CPU kernels), "
                          "gpu or gpu-phase (XLA's, the transposed 3D conv in forms cuDNN runs "
                          "natively); all equal in value and gradient (sljax.kernels); "
                          "$SLJAX_CONV3D sets what auto means", choices=CONV_IMPLS)
  val_every: int = option(1, "epochs between validations", resumable=True)
  val_every_steps: int | None = option(
      None, "validate every K steps and at the last (rows in validation.jsonl, a checkpoint at "
      "each) instead of every --val-every epochs", parse=int, resumable=True)
  save_every: int = option(0, "also checkpoint every N steps (default: at each epoch end only)")
  keep: int = option(3, "checkpoints kept (the last N, plus the best by validation MAE)",
                     resumable=True)
  max_val: int | None = option(None, "cap on validation scenes", parse=int, resumable=True)
  log_every: int = option(10, "steps between fetches of the step metrics from the device "
                          "(every step is still logged)", resumable=True)
  init_from: str | None = option(None, "start from a training workdir or a converted PSMNet "
                                 "(sljax convert-psmnet)", parse=str)
  corr_window: int = option(17, "window (px, odd) of the correlation that turns unet-sl's "
                            "patterns into disparity (paper: 17 at 256x256)")
  unet_depth: int = option(4, "UNet levels")
  unet_width: int = option(32, "UNet channels at the first level")
  tensorboard: bool = option(False, "live curves", switch=(
      ("--tensorboard", "also write TensorBoard event files to WORKDIR/tensorboard (losses, "
       "task weights, sigmas, validation MAE, samples/s); watch with tensorboard --logdir runs/ "
       "(needs tensorboardX: pip install 'sljax[tensorboard]')"),
      ("--no-tensorboard", "no TensorBoard event files (default)")), resumable=True)
  preset: str = option("paper", "the preset the run started from", flag=False, resumable=True)

  @property
  def net(self) -> str:
    """Network name for sljax.nets.build_model (the twin for weighting strategies)."""
    return registry.trained_net(self.model, self.strategy)

  @property
  def spec(self) -> registry.NetSpec:
    """The trained network's entry in sljax.nets.registry.NETS."""
    return registry.spec(self.net)

  @property
  def model_conv_impl(self) -> str | None:
    """ModelConfig's conv_impl: None for "auto", so that $SLJAX_CONV3D sets the default."""
    return None if self.conv_impl == "auto" else self.conv_impl

  @property
  def use_gray(self) -> bool:
    """Whether inputs are single-channel."""
    return self.spec.gray if self.gray is None else bool(self.gray)

  @property
  def tasks(self) -> tuple[bool, bool]:
    """(needs SL targets, needs disparity targets)."""
    return "sl" in self.spec.tasks, "disp" in self.spec.tasks

  def to_json(self) -> dict[str, Any]:
    """JSON-able dict (tuples become lists)."""
    d = dataclasses.asdict(self)
    d["size"] = list(self.size)
    return d


FIELDS = {f.name: f for f in dataclasses.fields(TrainConfig)}
# Fields added after experiment records were written: a cell's spec omits them at their default,
# so the committed plan.json files still name the same runs.
LATER_FIELDS = ("steps", "val_every_steps")
# Fields that may differ between a run and its --resume (they do not change the trajectory).
RESUME_MUTABLE = tuple(name for name, f in FIELDS.items() if f.metadata["resumable"])

PAPER = TrainConfig()
# Small enough to finish in < 10 min on a 2-core CPU while visibly learning.
QUICK = dataclasses.replace(PAPER, synth_n=120, synth_size=64, size=(64, 64), maxdisp=32,
                            epochs=8, batch_size=8, lr=1e-3, max_val=16, unet_width=16,
                            preset="quick")


PATH_FIELDS = ("data", "init_from")  # folders: new runs record them absolute (resolved)


def with_absolute_paths(config: TrainConfig) -> TrainConfig:
  """The config with its existing folders absolute and resolved, so that config.json names them
  from any directory (a missing one stays as given, for its error message to show)."""
  paths = {k: str(Path(getattr(config, k)).resolve()) for k in PATH_FIELDS
           if getattr(config, k) is not None and Path(getattr(config, k)).exists()}
  return dataclasses.replace(config, **paths)


def preset_config(name: str, backend: str) -> TrainConfig:
  """The preset's config; 'auto' = paper with an accelerator, quick on a CPU-only machine."""
  require(name in PRESETS, f"--preset: unknown preset {name!r}; choose from {PRESETS}")
  if name == "auto":
    name = "paper" if backend != "cpu" else "quick"
  return PAPER if name == "paper" else QUICK


def validate(config: TrainConfig) -> None:
  """Checks the options that need no data; SljaxError naming the option."""
  for name, f in FIELDS.items():
    choices = f.metadata["choices"]
    value = getattr(config, name)
    require(choices is None or value in choices,
            f"--{name.replace('_', '-')}: unknown value {value!r}; choose from {choices}")
  spec = config.spec
  require(registry.spec(config.model).twin is not None or config.strategy == "stl",
          f"--strategy {config.strategy}: weighting strategies apply to the PSMNet twin; "
          f"{config.model} trains a single task (use --strategy stl or leave it out)")
  registry.check_maxdisp(config.maxdisp, f"--maxdisp {config.maxdisp}")
  h, w = config.size
  require(h > 0 and w > 0 and h % 16 == 0 and w % 16 == 0,
          f"--size {h}x{w}: height and width must be positive multiples of 16")
  for name in ("epochs", "batch_size", "lr", "val_every", "log_every", "unet_depth",
               "unet_width"):
    require(getattr(config, name) > 0,
            f"--{name.replace('_', '-')} {getattr(config, name)}: must be positive")
  for name in ("steps", "val_every_steps"):
    require(getattr(config, name) is None or getattr(config, name) > 0,
            f"--{name.replace('_', '-')} {getattr(config, name)}: must be positive")
  require(config.lr_drop_epoch is None or config.lr_drop_epoch >= 1,
          f"--lr-drop-epoch {config.lr_drop_epoch}: must be at least 1")
  require(config.synth_n >= 2, f"--synth-n {config.synth_n}: need at least 2 scenes")
  require(config.corr_window > 0 and config.corr_window % 2 == 1,
          f"--corr-window {config.corr_window}: must be a positive odd number")
  require(config.synth_t is None or 1 <= config.synth_t <= 12,
          f"--synth-t {config.synth_t}: must be in 1..12")
  require("depth" not in spec.options or (h % 2**config.unet_depth == 0
                                          and w % 2**config.unet_depth == 0),
          f"--size {h}x{w}: must be a multiple of 2^unet_depth = {2**config.unet_depth}")
  # numpy's generators take non-negative seeds; jax's key keeps 32 bits (2**32 would equal 0).
  require(0 <= config.seed < 2**32, f"--seed {config.seed}: must be in 0..{2**32 - 1}")
  require(config.max_val is None or config.max_val >= 1,
          f"--max-val {config.max_val}: leaves no validation scene; give at least 1 (or leave "
          "it out to validate on the whole held-out split)")
  require(config.save_every >= 0, f"--save-every {config.save_every}: must be >= 0")
  require(0 < config.test_fraction < 1,
          f"--test-fraction {config.test_fraction}: must be in (0, 1)")
  if config.tensorboard:
    tensorboard.summary_writer_class()  # installed? (else one line now, before anything runs)


def normalized(d: dict[str, Any]) -> dict[str, Any]:
  """A saved config dict with the fields it predates set to their defaults (older runs)."""
  out = dict(d)
  for name, f in FIELDS.items():
    if name not in out:
      out[name] = list(f.default) if isinstance(f.default, tuple) else f.default
  return out


def diff_configs(saved: dict[str, Any], new: dict[str, Any],
                 ignore: tuple[str, ...] = RESUME_MUTABLE) -> list[str]:
  """Names of the fields that differ between two config dicts (ignoring some)."""
  saved, new = normalized(saved), normalized(new)
  keys = sorted(set(saved) | set(new))
  return [k for k in keys if k not in ignore and saved.get(k) != new.get(k)]


def _json_type_problem(value: Any, default: Any) -> str | None:
  """What a saved value must be, judged by its field's default (None: it is that, or the
  default is None and any JSON scalar is let through to validate)."""
  if type(default) is bool:
    return None if type(value) is bool else "true or false"
  if type(default) is int:
    return None if type(value) is int else "an integer"
  if type(default) is float:
    ok = type(value) in (int, float) and math.isfinite(value)
    return None if ok else "a finite number"
  if type(default) is str:
    return None if isinstance(value, str) else "a string"
  if isinstance(default, tuple):
    ok = isinstance(value, list) and len(value) == len(default) and all(
        type(v) is int for v in value)
    return None if ok else f"a list of {len(default)} integers"
  return None if value is None or type(value) in (bool, int, float, str) else "a JSON scalar"


def config_from_json(d: dict[str, Any], where: str = "config.json") -> TrainConfig:
  """TrainConfig from the dict written by to_json (unknown keys ignored); SljaxError starting
  with `where` (the file) for a value of the wrong type."""
  kw = {k: v for k, v in d.items() if k in FIELDS}
  kw.setdefault("ynn", "on")  # written before the option existed: XLA's default was used
  for name, value in kw.items():  # a hand edit would otherwise fail far from the file
    field = FIELDS[name]
    like = field.default
    if like is None and value is not None and field.metadata["parse"] in (int, float, str):
      like = field.metadata["parse"]()  # an optional number or string: judged as one
    problem = _json_type_problem(value, like)
    if problem is not None:
      raise SljaxError(f"{where}: {name} must be {problem}, got {value!r}")
  if "size" in kw:
    kw["size"] = tuple(kw["size"])
  try:
    return TrainConfig(**kw)
  except TypeError as e:
    raise SljaxError(f"{where}: {e}") from None


def dumps(d: dict[str, Any]) -> str:
  """Stable pretty JSON."""
  return json.dumps(d, indent=2, sort_keys=True)
