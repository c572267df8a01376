"""The GPU figures the dry run prices a plan with (`experiment run --dry-run --gpu h100|h200`):
a few measured times copied from the benchmark records (benchmarks/results/*.jsonl, and one
from docs/benchmarks/gpu.md), each with its record, date and commit, so that the package
needs no benchmarks/ folder at run time. tests/test_price.py checks each against its record.

Every figure is at the paper scale's shape: 256x256, maxdisp 96, a training batch of 12, TF32
(XLA's default precision). A network or GPU with no measured figure gets a stand-in made
from measured ones by a stated rule (sljax.experiment.running.price).
"""

import dataclasses

# The shape every figure was measured at: (size, maxdisp, training batch).
SHAPE = (256, 96, 12)
GPUS = {"h100": "NVIDIA H100 80GB HBM3", "h200": "NVIDIA H200"}
RECORDS = {"h100": "benchmarks/results/gpu-nvidia-h100-80gb-hbm3.jsonl",
           "h200": "benchmarks/results/gpu-nvidia-h200.jsonl"}


@dataclasses.dataclass(frozen=True)
class Measured:
  """One measured figure: `raw` is the record's `field` in the row matching `row`; seconds is
  raw (or 1/raw for a rate) divided by `per` (a batch's forward shared by its scenes)."""
  gpu: str                 # "h100" | "h200"
  net: str                 # sljax.nets.registry name
  what: str                # "step" (a training step of 12) | "forward" (a scene) | "start"
  raw: float
  field: str
  row: tuple[tuple[str, object], ...]
  source: str              # the records file (or docs page) it was copied from
  time: str                # the record's time (the measurement's date)
  commit: str
  note: str
  rate: bool = False       # raw is per second
  per: int = 1

  @property
  def seconds(self) -> float:
    """The figure in seconds."""
    return (1.0 / self.raw if self.rate else self.raw) / self.per

  def cite(self) -> str:
    """Where the figure comes from, in one phrase."""
    return f"{self.note}; {self.source}, {self.time[:10]}, {self.commit}"


MEASURED = (
    # PSMNet's whole step with Adam, bench_gpu.py's figure at main 72985c4: in the project's
    # shared measurements and docs/benchmarks/gpu.md, not in the H100's records file.
    Measured("h100", "psmnet", "step", 0.108, "sljax s/step",
             (("shape", "256x256, maxdisp 96, batch 12 (the paper preset)"),
              ("precision", "TF32")),
             "docs/benchmarks/gpu.md (shared measurements gpu-h100-2026-11-27)",
             "2026-11-27", "72985c4", "PSMNet's training step, TF32"),
    Measured("h100", "psmnet", "forward", 0.012741468000058376, "sljax_default_s",
             (("table", "models"), ("model", "psmnet"), ("mode", "fwd"), ("batch", 4)),
             RECORDS["h100"], "2026-11-25T00:46:16+00:00", "a871f4a+dirty",
             "PSMNet's forward, batch 4, before the `gpu` form of the 3D transposed convolutions",
             per=4),
    Measured("h100", "unet-sl", "step", 80.91583389032496, "steps_per_s",
             (("what", "(a) compiled step, fixed batch, fp32"),),
             RECORDS["h100"], "2026-11-26T13:30:59+00:00", "15fc63d+dirty",
             "unet-sl's compiled step (bench_train.py --preset paper --step-only)", rate=True),
    Measured("h100", "unet-sl", "forward", 0.0019144809999716017, "sljax_default_s",
             (("table", "models"), ("model", "unet-sl"), ("mode", "fwd"), ("batch", 4)),
             RECORDS["h100"], "2026-11-25T00:48:01+00:00", "a871f4a+dirty",
             "unet-sl's forward, batch 4", per=4),
    Measured("h200", "psmnet", "step", 0.10768939929999988, "step_s",
             (("table", "step"), ("shape", "paper"), ("precision", "fp32"), ("side", "sljax"),
              ("net", "psmnet")),
             RECORDS["h200"], "2026-11-28T06:01:41+00:00", "166d4f0+dirty",
             "PSMNet's training step, TF32 (bench_gpu.py)"),
    # The twin's step as the main job runs it (train.py --strategy epr --preset paper, scenes
    # rendered on the fly), a later step once warm: what a grid cell's step costs.
    Measured("h200", "psmnet-mtl", "step", 0.14243602199999827, "later_step",
             (("table", "run"), ("kind", "warm")),
             RECORDS["h200"], "2026-11-28T06:29:42+00:00", "166d4f0+dirty",
             "the twin's step in the main job (epr, bench_compile.py)"),
    # A cell's start: from launch to the end of the first step, the compile cache warm.
    Measured("h200", "psmnet-mtl", "start", 10.578619241714478, "to_first_end",
             (("table", "run"), ("kind", "warm")),
             RECORDS["h200"], "2026-11-28T06:29:42+00:00", "166d4f0+dirty",
             "launch to the first step's end, warm compile cache (bench_compile.py)"),
)


def measured(gpu: str, net: str, what: str) -> Measured | None:
  """The measured figure of a network on a GPU, or None."""
  return next((m for m in MEASURED if (m.gpu, m.net, m.what) == (gpu, net, what)), None)
