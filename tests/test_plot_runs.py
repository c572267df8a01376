import json

import pytest

from sljax import cli
from sljax.commands import plot_runs


def _workdir(root, name, config, maes, extra=None):
  w = root / name
  w.mkdir()
  (w / "config.json").write_text(json.dumps(config))
  lines = []
  for e, m in enumerate(maes, 1):
    rec = {"epoch": e, "step": 10 * e, "loss_disp": 1.0 / e}
    if m is not None:
      rec["val_mae"] = m
      rec.update(extra or {})
    lines.append(json.dumps(rec))
  (w / "epochs.jsonl").write_text("\n".join(lines) + "\n")
  return w


def test_plot_runs_writes_figure_and_table(tmp_path, capsys):
  a = _workdir(tmp_path, "a", {"model": "psmnet", "strategy": "stl"}, [21.3, 9.9, 8.4, 9.5])
  b = _workdir(tmp_path, "b", {"model": "psmnet", "strategy": "unc"}, [11.3, None, 7.9, 6.0],
               extra={"val_bad_2": 12.5})
  c = _workdir(tmp_path, "c", {"model": "unet-sl", "strategy": "stl"}, [3.0])
  out = tmp_path / "fig" / "runs.png"
  rc = cli.main(["plot-runs", str(a), str(b), str(c), "--out", str(out)])
  assert rc == 0
  assert out.stat().st_size > 1000 and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
  table = (tmp_path / "fig" / "runs.md").read_text()
  assert table in capsys.readouterr().out
  rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[1:-1]]
          for line in table.splitlines()[2:]}
  assert set(rows) == {"psmnet/stl", "psmnet/unc", "unet-sl"}
  # final = last epoch with a val_mae; best = its minimum with the epoch.
  assert rows["psmnet/stl"][2:5] == ["4", "9.500", "8.400 (3)"]
  assert rows["psmnet/unc"][2:6] == ["4", "6.000", "6.000 (4)", "12.5"]
  assert rows["unet-sl"][3] == "3.000" and rows["unet-sl"][5] == "-"


def test_duplicate_labels_get_folder_names(tmp_path):
  runs = [plot_runs.read_run(_workdir(tmp_path, n, {"model": "psmnet", "strategy": "cg_a"}, [1.0]))
          for n in ("s0", "s1")]
  assert [r["label"] for r in runs] == ["psmnet/cg_a", "psmnet/cg_a"]
  rc = cli.main(["plot-runs", runs[0]["workdir"], runs[1]["workdir"], "--out",
                 str(tmp_path / "x.png")])
  assert rc == 0
  table = (tmp_path / "x.md").read_text()
  assert "psmnet/cg_a (s0)" in table and "psmnet/cg_a (s1)" in table


def test_workdir_without_epochs_is_an_error(tmp_path, capsys):
  (tmp_path / "empty").mkdir()
  rc = cli.main(["plot-runs", str(tmp_path / "empty"), "--out", str(tmp_path / "x.png")])
  err = capsys.readouterr().err
  assert rc == 2 and "empty" in err and "epochs.jsonl" in err


def test_existing_outputs_need_overwrite(tmp_path, capsys):
  """The PNG and its .md are replaced only with --overwrite, and refused before any reading."""
  a = _workdir(tmp_path, "a", {"model": "psmnet", "strategy": "stl"}, [2.0, 1.0])
  png, md = tmp_path / "c.png", tmp_path / "c.md"
  for existing in (png, md):
    png.unlink(missing_ok=True)
    md.unlink(missing_ok=True)
    existing.write_bytes(b"earlier")
    for workdir in (a, tmp_path / "nope"):  # refused before the workdirs are read
      assert cli.main(["plot-runs", str(workdir), "--out", str(png)]) == 2
      err = capsys.readouterr().err.strip().splitlines()
      assert err == [f"sljax plot-runs: error: {existing}: exists (pass --overwrite to replace "
                     "it)"]
    assert existing.read_bytes() == b"earlier" and sorted(tmp_path.iterdir()) == [a, existing]
  assert cli.main(["plot-runs", str(a), "--out", str(png), "--overwrite"]) == 0
  assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and "psmnet/stl" in md.read_text()
  assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "c.md", "c.png"]


@pytest.mark.parametrize("line, problem", [
    (b'{"epoch": 2, "val_mae": 1\xff}', "line 2 is not UTF-8 text (byte 26 of the line)"),
    (b'{"epoch": 2, "val_', "line 2 is not JSON (Unterminated string"),
    (b"[2]", "line 2 has no 'epoch' key")])
def test_damaged_epochs_line_is_one_line_naming_file_and_line(tmp_path, capsys, line, problem):
  run = tmp_path / "run"
  run.mkdir()
  (run / "epochs.jsonl").write_bytes(b'{"epoch": 1, "val_mae": 2.0}\n' + line + b"\n")
  rc = cli.main(["plot-runs", str(run), "--out", str(tmp_path / "x.png")])
  err = capsys.readouterr().err
  assert rc == 2 and f"{run / 'epochs.jsonl'}: {problem}" in err and "Traceback" not in err
  assert not (tmp_path / "x.png").exists()
