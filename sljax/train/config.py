"""Training configuration: one frozen dataclass, the paper's defaults written once, presets."""

import dataclasses
import json
from typing import Any

from sljax.errors import SljaxError, require
from sljax.losses.disparity import DISP_LOSSES
from sljax.losses.weighting import STRATEGIES

MODELS = ("psmnet", "unet-sl", "unet-disp")
PRESETS = ("auto", "paper", "quick")
# Fields that may differ between a run and its --resume (they do not change the trajectory).
RESUME_MUTABLE = ("epochs", "preset", "val_every", "keep", "max_val")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """Everything that determines a training run (SPEC 3-4 defaults = the paper preset)."""
  model: str = "psmnet"            # psmnet (stl: plain; other strategies: the SL twin) | unet-*
  strategy: str = "stl"            # stl | cg_a | cg_b | epr | unc (PSMNet only)
  data: str | None = None          # scene-format folder; None = synthetic 'objects' on the fly
  synth_n: int = 8000              # synthetic scenes (train + val), ~the paper's virtual set
  synth_size: int = 256            # synthetic render size (square); batches are resized to size
  fraction: str = "1"              # fraction of the training split, e.g. "1/16"
  test_fraction: float = 0.2       # group-level held-out split (object level, SPEC 1)
  epochs: int = 120
  batch_size: int = 12             # reference PSMNet batch (global, over all devices)
  lr: float = 1e-4                 # Adam, fixed (paper)
  size: tuple[int, int] = (256, 256)
  maxdisp: int = 96
  seed: int = 0
  disp_loss: str = "l2"            # paper L2; "smooth_l1" = reference PSMNet
  gray: bool | None = None         # None: RGB for PSMNet, grayscale for the UNets (paper)
  val_every: int = 1               # epochs between validations
  save_every: int = 0              # steps between extra mid-epoch checkpoints (0 = epochs only)
  keep: int = 3                    # last checkpoints kept (plus the best by val MAE)
  max_val: int | None = None       # cap on validation scenes (None = whole held-out split)
  init_from: str | None = None     # checkpoint workdir or converted PSMNet to start from
  unet_depth: int = 4              # UNet levels (unet-sl, unet-disp)
  unet_width: int = 32             # UNet channels at the first level
  preset: str = "paper"

  @property
  def net(self) -> str:
    """Network name for sljax.nets.build_model."""
    if self.model == "psmnet":
      return "psmnet" if self.strategy == "stl" else "psmnet-mtl"
    return self.model

  @property
  def use_gray(self) -> bool:
    """Whether inputs are single-channel."""
    return self.model != "psmnet" if self.gray is None else bool(self.gray)

  @property
  def tasks(self) -> tuple[bool, bool]:
    """(needs SL targets, needs disparity targets)."""
    return {"psmnet": (False, True), "psmnet-mtl": (True, True), "unet-sl": (True, False),
            "unet-disp": (False, True)}[self.net]

  def to_json(self) -> dict[str, Any]:
    """JSON-able dict (tuples become lists)."""
    d = dataclasses.asdict(self)
    d["size"] = list(self.size)
    return d


PAPER = TrainConfig()
# Small enough to finish in < 10 min on a 2-core CPU while visibly learning.
QUICK = dataclasses.replace(PAPER, synth_n=120, synth_size=64, size=(64, 64), maxdisp=32,
                            epochs=8, batch_size=8, lr=1e-3, max_val=16, unet_width=16,
                            preset="quick")


def preset_config(name: str, backend: str) -> TrainConfig:
  """The preset's config; 'auto' = paper with an accelerator, quick on a CPU-only machine."""
  require(name in PRESETS, f"--preset: unknown preset {name!r}; choose from {PRESETS}")
  if name == "auto":
    name = "paper" if backend != "cpu" else "quick"
  return PAPER if name == "paper" else QUICK


def validate(config: TrainConfig) -> None:
  """Checks the options that need no data; SljaxError naming the option."""
  require(config.model in MODELS, f"--model: unknown model {config.model!r}; choose from {MODELS}")
  require(config.strategy in STRATEGIES,
          f"--strategy: unknown strategy {config.strategy!r}; choose from {STRATEGIES}")
  require(config.model == "psmnet" or config.strategy == "stl",
          f"--strategy {config.strategy}: weighting strategies apply to the PSMNet twin; "
          f"{config.model} trains a single task (use --strategy stl or leave it out)")
  require(config.disp_loss in DISP_LOSSES,
          f"--disp-loss: unknown loss {config.disp_loss!r}; choose from {DISP_LOSSES}")
  require(config.maxdisp > 0 and config.maxdisp % 16 == 0,
          f"--maxdisp {config.maxdisp}: must be a positive multiple of 16")
  h, w = config.size
  require(h > 0 and w > 0 and h % 16 == 0 and w % 16 == 0,
          f"--size {h}x{w}: height and width must be positive multiples of 16")
  require(config.epochs > 0, f"--epochs {config.epochs}: must be positive")
  require(config.batch_size > 0, f"--batch-size {config.batch_size}: must be positive")
  require(config.lr > 0, f"--lr {config.lr}: must be positive")
  require(config.synth_n >= 2, f"--synth-n {config.synth_n}: need at least 2 scenes")
  require(config.unet_depth > 0 and config.unet_width > 0,
          f"--unet-depth/--unet-width: must be positive, got {config.unet_depth}, "
          f"{config.unet_width}")
  require(config.model == "psmnet" or (config.size[0] % 2**config.unet_depth == 0
                                       and config.size[1] % 2**config.unet_depth == 0),
          f"--size {config.size[0]}x{config.size[1]}: must be a multiple of "
          f"2^unet_depth = {2**config.unet_depth}")
  require(config.val_every > 0, f"--val-every {config.val_every}: must be positive")
  require(config.save_every >= 0, f"--save-every {config.save_every}: must be >= 0")
  require(0 < config.test_fraction < 1,
          f"--test-fraction {config.test_fraction}: must be in (0, 1)")


def diff_configs(saved: dict[str, Any], new: dict[str, Any],
                 ignore: tuple[str, ...] = RESUME_MUTABLE) -> list[str]:
  """Names of the fields that differ between two config dicts (ignoring some)."""
  keys = sorted(set(saved) | set(new))
  return [k for k in keys if k not in ignore and saved.get(k) != new.get(k)]


def config_from_json(d: dict[str, Any]) -> TrainConfig:
  """TrainConfig from the dict written by to_json (unknown keys ignored)."""
  names = {f.name for f in dataclasses.fields(TrainConfig)}
  kw = {k: v for k, v in d.items() if k in names}
  if "size" in kw:
    kw["size"] = tuple(kw["size"])
  try:
    return TrainConfig(**kw)
  except TypeError as e:
    raise SljaxError(f"config.json: {e}") from None


def dumps(d: dict[str, Any]) -> str:
  """Stable pretty JSON."""
  return json.dumps(d, indent=2, sort_keys=True)
