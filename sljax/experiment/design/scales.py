"""The scales of the experiment plans: image and pattern sizes, data, optimiser, networks, and
at each scale the budgets and choices of the v1 schedule and the v2, v3 and v4 designs
(docs/plan-v2.md "Scales", plan-v3.md, plan-v4.md). sljax.experiment.design.plans builds cells from
them."""

import dataclasses

from sljax.errors import require

NO_REGIME = "no fraction overfits"  # V3Design.regime when the v3 pilot found none


@dataclasses.dataclass(frozen=True)
class Schedule:
  """v1's budgets and validation cadence at a scale (docs/results-v1.md, "Why this scale")."""
  epochs: int              # objects training, all of the training split
  small_epochs: int        # objects training on 1/16 of it
  finetune_epochs: int
  val_every: int           # epochs between validations (training curves)
  small_val_every: int


@dataclasses.dataclass(frozen=True)
class V2Design:
  """The v2 choices at a scale (docs/plan-v2.md): unet-sl's candidate correlation windows, the
  fixed test sets' scenes per domain, the budgets ((arm or "*", phase), epochs) set by the
  calibration rule (empty: not calibrated) and the long calibration runs' (phase, epochs)."""
  windows: tuple[int, ...] = ()
  test_n: int = 0
  budgets: tuple[tuple[tuple[str, str], int], ...] = ()
  calib_epochs: tuple[tuple[str, int], ...] = ()


@dataclasses.dataclass(frozen=True)
class V3Design:
  """The v3 choices at a scale (docs/plan-v3.md): the pilot's training fractions (largest
  first), its fixed budget, the validation cadence of every v3 cell and the pilot's first
  seed."""
  fractions: tuple[str, ...]
  pilot_epochs: int
  val_every: int
  first_seed: int
  # (training fraction, epochs) the regime rule chose on the pilot (committed with the pilot's
  # outcome in docs/plan-v3.md); NO_REGIME: the rule found none (v3 ends there); None: the
  # pilot has not been run yet.
  regime: tuple[str, int] | str | None = None


@dataclasses.dataclass(frozen=True)
class V4Design:
  """The v4 pilot at a scale (docs/plan-v4.md): budgets in optimizer steps, validation every
  val_every steps. From scratch: stl on objects at scratch_fractions. The paper's setting: an
  objects model of pretrain_steps on all the data, fine-tuned on finetune_fractions of the
  tissue training split at finetune_lr. Learning rates constant."""
  scratch_fractions: tuple[str, ...]   # largest first (objects training split)
  scratch_steps: int
  pretrain_steps: int
  pretrain_val_every: int
  finetune_fractions: tuple[str, ...]  # largest first (tissue training split)
  finetune_steps: int
  val_every: int
  finetune_lr: float
  first_seed: int
  # The test grid (docs/plan-v4.md). regime: (setting, fraction, steps) the rule chose on the
  # pilot, committed with the pilot's outcome; NO_REGIME: no setting overfits (v4 stops there);
  # None: the pilot has not finished. grid_seeds: n by the plan's 24-hour rule, committed
  # before the first grid cell (None: not yet).
  grid_first_seed: int = 300
  regime: tuple[str, str, int] | str | None = None
  grid_seeds: int | None = None
  # What the 24-hour rule counts (docs/plan-v4.md): stl's seconds per step and per validation
  # of val_scenes scenes (the pilot's timing run), and each arm's (step, validation) cost as a
  # ratio to stl's (benchmarks/bench_arms.py); () where not measured.
  step_seconds: float | None = None
  val_seconds: float | None = None
  val_scenes: int = 80
  arm_ratios: tuple[tuple[str, float, float], ...] = ()


@dataclasses.dataclass(frozen=True)
class V5Design:
  """The v5 grid at a scale (docs/plan-v5.md): each arm's objects model on all the data, its
  epochs set by the plateau rule on calibration cells run in the grid's own OUT (budgets
  committed here win where they exist: none are), then fine-tuned on tissue_fraction of the
  tissue training split for finetune_steps at finetune_lr, validated every val_every steps on
  the whole tissue validation split. Seeds first_seed.. (at most `seeds`, the pre-registered
  count); the rule's margin and smoothing are fixed in docs/plan-v5.md."""
  arms: tuple[str, ...]
  tissue_fraction: str
  finetune_steps: int
  val_every: int
  finetune_lr: float
  first_seed: int
  seeds: int
  budgets: tuple[tuple[tuple[str, str], int], ...] = ()


@dataclasses.dataclass(frozen=True)
class Scale:
  """The sizes of a plan: images and patterns, data, optimiser, networks, and the schedules and
  designs of v1, v2 and v3 at this scale."""
  name: str
  size: int                # training = render size (square)
  t: int                   # patterns per view, both domains (objects binary, tissue Gray)
  maxdisp: int
  objects_n: int           # synthetic objects scenes (train + held-out)
  tissue_n: int            # synthetic tissue scenes: the scarce fine-tuning set
  batch_size: int
  lr: float
  lr_drop: bool            # lr 10x lower for the last quarter of the epochs; fine-tuning
                           # continues at the lower rate (else fixed, as the paper)
  corr_window: int         # unet-sl's correlation window (17 at 256 px, scaled with size)
  unet_width: int
  unet_depth: int
  max_val: int | None      # validation scenes for the curves (the report scores all)
  schedule: Schedule
  note: str
  v2: V2Design = V2Design()
  v3: V3Design | None = None
  v4: V4Design | None = None
  v5: V5Design | None = None
  # --ynn and --conv-impl of every cell: "auto" tunes and chooses per machine; the smoke scale
  # keeps XLA's defaults and lax, since its programs run for seconds (benchmarks/bench_smoke.py).
  ynn: str = "auto"
  conv_impl: str = "auto"

  def budget(self, arm: str, phase: str) -> int:
    """The v2 epochs of an arm in a phase (its own calibrated budget, else the scale's "*");
    SljaxError when the scale has none yet."""
    table = dict(self.v2.budgets)
    epochs = table.get((arm, phase), table.get(("*", phase)))
    require(epochs is not None,
            f"scale {self.name} has no calibrated budget for {arm} ({phase}) yet: run `sljax "
            f"experiment calibrate PLAN OUT --scale {self.name}` and commit the budgets it "
            "prints (docs/plan-v2.md)")
    return epochs


# One row per scale; where each value came from is in docs/plan-v2.md ("Scales").
SCALES = {s.name: s for s in (
    Scale("smoke", size=32, t=5, maxdisp=16, objects_n=40, tissue_n=20, batch_size=2, lr=1e-3,
          lr_drop=False, corr_window=3, unet_width=4, unet_depth=2, max_val=4,
          schedule=Schedule(2, 2, 2, val_every=1, small_val_every=1),
          note="a few minutes on a CPU; the tests run it",
          v2=V2Design(windows=(3, 5), test_n=20,
                      budgets=((("*", "objects"), 2), (("*", "1/16"), 2), (("*", "finetune"), 2)),
                      calib_epochs=(("objects", 3), ("1/16", 3), ("finetune", 3))),
          v3=V3Design(("1/4", "1/8"), pilot_epochs=4, val_every=2, first_seed=100,
                      regime=("1/4", 4)),
          v4=V4Design(("1/4", "1/8"), scratch_steps=6, pretrain_steps=4, pretrain_val_every=2,
                      finetune_fractions=("1/2",), finetune_steps=4, val_every=2,
                      finetune_lr=1e-4, first_seed=200, regime=("finetune", "1/2", 4),
                      grid_seeds=3),
          # Two arms keep the suite's end-to-end test short; the paper scale runs all five.
          v5=V5Design(("stl", "unc"), tissue_fraction="1/4", finetune_steps=4, val_every=2,
                      finetune_lr=1e-4, first_seed=500, seeds=2),
          ynn="on", conv_impl="lax"),
    Scale("cpu", size=64, t=6, maxdisp=16, objects_n=400, tissue_n=80, batch_size=4, lr=1e-3,
          lr_drop=True, corr_window=5, unet_width=16, unet_depth=4, max_val=40,
          schedule=Schedule(12, 96, 40, val_every=1, small_val_every=8),
          note="fits a 2-core CPU: 64x64 with 6 patterns keeps the finest stripe about "
               "1.5 px wide, as 8 patterns at 256x256; Adam 1e-3 dropping to 1e-4 for the "
               "last quarter of the epochs brings validation to a plateau within the budget; "
               "the 1/16 runs take 8x the epochs (half the full runs' steps), which their "
               "plateau needs",
          v2=V2Design(windows=(5, 9, 17), test_n=500,
                      budgets=((("*", "objects"), 12), (("*", "1/16"), 96),
                               (("*", "finetune"), 40)),
                      calib_epochs=(("objects", 36), ("1/16", 288), ("finetune", 120))),
          v3=V3Design(("1/16", "1/32", "1/64"), pilot_epochs=240, val_every=4, first_seed=100,
                      regime=NO_REGIME),
          # 10 and 5 of the 320 objects training scenes; 10 and 5 of the 60 tissue ones. The
          # budgets are the plan's 6,000, 2,400 and 4,000 steps shrunk by its budget rule
          # (docs/plan-v4.md, the timing run: r = 0.441, rounded up to the cadences).
          v4=V4Design(("1/32", "1/64"), scratch_steps=2700, pretrain_steps=1200,
                      pretrain_val_every=200, finetune_fractions=("1/6", "1/12"),
                      finetune_steps=1800, val_every=100, finetune_lr=1e-4, first_seed=200,
                      # The seed rule's inputs: the timing run's s and v (stl, frozen code);
                      # the arms' ratios, the mean of two bench_arms runs in opposite orders.
                      step_seconds=1.059, val_seconds=5.12, val_scenes=80,
                      arm_ratios=(("stl", 1.0, 1.0), ("unc", 1.17, 1.20),
                                  ("epr", 1.28, 1.43)),
                      # The pilot's outcome (docs/plan-v4.md): no setting overfits.
                      regime=NO_REGIME)),
    Scale("cpu128", size=128, t=7, maxdisp=32, objects_n=400, tissue_n=80, batch_size=4,
          lr=1e-3, lr_drop=True, corr_window=9, unet_width=16, unet_depth=4, max_val=40,
          schedule=Schedule(12, 96, 40, val_every=1, small_val_every=8),
          note="the second CPU scale: 128x128 with 7 patterns keeps the finest stripe 1.68 px "
               "wide (docs/plan-v2.md), maxdisp 32 covers the disparities (<= 0.22 x 128 = "
               "28 px); unet-sl's window is chosen on validation from 5, 9, 13, 17, 25; every "
               "budget is set on validation by the calibration rule",
          v2=V2Design(windows=(5, 9, 13, 17, 25), test_n=500,
                      budgets=((("unet-sl", "objects"), 60), (("unet-sl", "finetune"), 120),
                               (("unet-disp", "objects"), 60), (("unet-disp", "finetune"), 120)),
                      calib_epochs=(("objects", 60), ("1/16", 288), ("finetune", 120)))),
    Scale("paper", size=256, t=8, maxdisp=96, objects_n=8000, tissue_n=500, batch_size=12,
          lr=1e-4, lr_drop=False, corr_window=17, unet_width=32, unet_depth=4, max_val=None,
          schedule=Schedule(120, 120, 40, val_every=1, small_val_every=1),
          note="the paper's sizes (256x256, maxdisp 96, 120 epochs, Adam 1e-4); for an "
               "accelerator",
          # No budget committed: a plan calibrates in its own OUT (`experiment run`), its long
          # runs the paper's 120 epochs on all the data (its own "balance of computation time
          # and convergence") and three times its 1/16 and fine-tuning budgets, as at cpu.
          v2=V2Design(test_n=500,
                      calib_epochs=(("objects", 120), ("1/16", 360), ("finetune", 120))),
          # docs/plan-v5.md: 25 of the 400 tissue training scenes, 4,000 steps (v4's planned
          # fine-tuning budget), validated every 50 steps on the 100 validation scenes.
          v5=V5Design(("stl", "unc", "cg_a", "cg_b", "epr"), tissue_fraction="1/16",
                      finetune_steps=4000, val_every=50, finetune_lr=1e-4, first_seed=500,
                      seeds=6)),
)}
