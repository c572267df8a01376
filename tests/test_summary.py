"""param_summary and `sljax summary`."""

import pytest

from sljax import cli
from sljax.nets.summary import format_summary, param_summary


def _rows(s):
  return {label: count for label, count, _ in s.rows}


def test_psmnet_parts_add_up():
  s = param_summary("psmnet", size=(64, 128), maxdisp=32)
  r = _rows(s)
  assert s.total == 5_224_768
  assert r["features (feature_extraction, shared)"] + r["disparity path"] == s.total
  assert (r["cost aggregation (dres0-dres4)"] + r["classifiers (classif1-3)"]
          == r["disparity path"])
  assert s.outputs["eval"] == {"disparity": (1, 64, 128)}
  assert s.outputs["train"]["disparities"] == ((1, 64, 128),) * 3


def test_twin_parts():
  s = param_summary("psmnet-mtl", size=(64, 64), maxdisp=16, t=9, batch=2)
  r = _rows(s)
  assert r["PSMNet part (detach_sl)"] == 5_224_768
  assert r["SL path (sl)"] == s.total - 5_224_768
  assert r["cost aggregation (sl/dres0-dres4)"] == r["cost aggregation (dres0-dres4)"]
  assert s.outputs["eval"]["sl_logits"] == (2, 64, 64, 9)


def test_unet_parts_and_format():
  s = param_summary("unet-disp", size=(37, 51), gray=True)
  r = _rows(s)
  assert sum(r.values()) == s.total
  assert r["head"] == 32 + 1
  text = format_summary(s)
  assert f"{s.total:,}" in text and "37x51" in text


def test_cli_summary(capsys):
  assert cli.main(["summary", "--model", "unet-sl", "--size", "37", "51", "--t", "9",
                   "--gray", "--batch", "2"]) == 0
  out = capsys.readouterr().out
  assert "sl_logits_right" in out and "2x37x51x9" in out and "2x37x51x1" in out


@pytest.mark.parametrize("argv, match", [
    (["--model", "psmnet", "--size", "50", "64"], "multiple of 16"),
    (["--model", "unet-sl", "--size", "0", "64"], "--size"),
    (["--model", "psmnet", "--maxdisp", "20"], "maxdisp"),
])
def test_cli_bad_input(argv, match, capsys):
  assert cli.main(["summary"] + argv) == 2
  assert match in capsys.readouterr().err
