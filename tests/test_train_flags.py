"""train.py flags: every flag parses to the same configuration as it always did.

The expected values are written out here, not read from sljax, so a change to a flag's name,
parsing or a preset's value fails this test.
"""

import pytest

from sljax.train import cli

# The quick preset as train.py resolves it with no flag on a CPU-only machine.
QUICK = {
    "model": "psmnet", "strategy": "stl", "data": None, "synth_n": 120, "synth_size": 64,
    "fraction": "1", "test_fraction": 0.2, "epochs": 8, "batch_size": 8, "lr": 1e-3,
    "size": (64, 64), "maxdisp": 32, "seed": 0, "disp_loss": "l2", "gray": None, "val_every": 1,
    "save_every": 0, "keep": 3, "max_val": 16, "init_from": None, "unet_depth": 4,
    "unet_width": 16, "preset": "quick",
    # Flags added later (their defaults are the paper's).
    "domain": "objects", "synth_t": None, "precision": "fp32", "log_every": 10,
    "corr_window": 17, "lr_drop_epoch": None,
}
# The paper preset (--preset paper, or auto with an accelerator).
PAPER = dict(QUICK, synth_n=8000, synth_size=256, epochs=120, batch_size=12, lr=1e-4,
             size=(256, 256), maxdisp=96, max_val=None, unet_width=32, preset="paper")

FLAGS = [
    (["--strategy", "epr"], {"strategy": "epr"}),
    (["--model", "unet-sl"], {"model": "unet-sl"}),
    (["--data", "data/objects"], {"data": "data/objects"}),
    (["--fraction", "1/16"], {"fraction": "1/16"}),
    (["--epochs", "5"], {"epochs": 5}),
    (["--batch-size", "4"], {"batch_size": 4}),
    (["--lr", "3e-4"], {"lr": 3e-4}),
    (["--size", "96x128"], {"size": (96, 128)}),
    (["--size", "48"], {"size": (48, 48)}),
    (["--maxdisp", "48"], {"maxdisp": 48}),
    (["--seed", "3"], {"seed": 3}),
    (["--disp-loss", "smooth_l1"], {"disp_loss": "smooth_l1"}),
    (["--gray"], {"gray": True}),
    (["--rgb"], {"gray": False}),
    (["--val-every", "2"], {"val_every": 2}),
    (["--save-every", "7"], {"save_every": 7}),
    (["--keep", "5"], {"keep": 5}),
    (["--max-val", "9"], {"max_val": 9}),
    (["--synth-n", "50"], {"synth_n": 50}),
    (["--synth-size", "128"], {"synth_size": 128}),
    (["--test-fraction", "0.3"], {"test_fraction": 0.3}),
    (["--unet-depth", "3"], {"unet_depth": 3}),
    (["--unet-width", "8"], {"unet_width": 8}),
    (["--init-from", "models/psmnet"], {"init_from": "models/psmnet"}),
    (["--domain", "tissue"], {"domain": "tissue"}),
    (["--synth-t", "6"], {"synth_t": 6}),
    (["--precision", "bf16"], {"precision": "bf16"}),
    (["--log-every", "5"], {"log_every": 5}),
    (["--corr-window", "5"], {"corr_window": 5}),
    (["--lr-drop-epoch", "6"], {"lr_drop_epoch": 6}),
    (["--strategy", "unc", "--fraction", "1/16", "--seed", "2", "--gray"],
     {"strategy": "unc", "fraction": "1/16", "seed": 2, "gray": True}),
]


def _config(argv, backend="cpu"):
  args = cli.build_parser().parse_args(argv)
  config, _, _ = cli.resolve(args, backend)
  return {k: getattr(config, k) for k in QUICK}


@pytest.mark.parametrize("argv, changed", FLAGS, ids=[" ".join(a) for a, _ in FLAGS])
def test_flag_parses_to_the_same_config(argv, changed):
  assert _config(argv) == dict(QUICK, **changed)
  assert _config(argv + ["--preset", "paper"]) == dict(PAPER, **changed)


def test_presets():
  assert _config([]) == QUICK
  assert _config([], backend="gpu") == PAPER
  assert _config(["--preset", "quick"], backend="gpu") == QUICK
  assert _config(["--preset", "paper"]) == PAPER


def test_run_flags():
  args = cli.build_parser().parse_args(
      ["--workdir", "runs/x", "--resume", "--distributed", "--stop-after", "12",
       "--no-progress"])
  assert (args.workdir, args.resume, args.overwrite, args.distributed, args.stop_after,
          args.no_progress) == ("runs/x", True, False, True, 12, True)
  assert cli.build_parser().parse_args(["--overwrite"]).overwrite
  # --resume --overwrite: which one was meant? (overwrite used to win, silently)
  with pytest.raises(SystemExit):
    cli.build_parser().parse_args(["--resume", "--overwrite"])
  args = cli.build_parser().parse_args([])
  assert (args.workdir, args.resume, args.overwrite, args.distributed, args.stop_after,
          args.no_progress, args.preset) == (None, False, False, False, None, False, "auto")


@pytest.mark.parametrize("argv", [["--gray", "--rgb"], ["--size", "12x"], ["--epochs", "x"],
                                  ["--disp-loss", "l1"], ["--precision", "fp16"],
                                  ["--domain", "mars"]])
def test_bad_flags_are_argparse_errors(argv, capsys):
  with pytest.raises(SystemExit) as e:
    cli.build_parser().parse_args(argv)
  assert e.value.code == 2
  assert "error" in capsys.readouterr().err


@pytest.mark.parametrize("field, value, kind", [("steps", "x", "an integer"),
                                                ("synth_t", 1.5, "an integer"),
                                                ("init_from", 3, "a string")])
def test_config_json_optional_fields_are_checked_by_their_type(field, value, kind):
  """A field whose default is None (optional) is judged by its flag's type once it has a value:
  a hand edit is one line naming config.json, not a TypeError in validation."""
  from sljax.errors import SljaxError  # pylint: disable=import-outside-toplevel
  from sljax.train import config  # pylint: disable=import-outside-toplevel
  saved = config.normalized({})
  assert config.config_from_json({**saved, field: None}).__getattribute__(field) is None
  with pytest.raises(SljaxError, match=f"W/config.json: {field} must be {kind}"):
    config.config_from_json({**saved, field: value}, "W/config.json")
