"""Checkpoints know their bytes (issue 62, item 3): each step folder carries the SHA-256 of its
files, checked before a restore reads them. A flipped byte, a file cut short or emptied, a file
where a folder goes (and the reverse), the newest step emptied, a lost digest: each is refused
in one line naming the step and the file, on --resume and in load_params (predict, evaluate,
export, --init-from), never a traceback; --resume-skip-damaged and predict fall back with a
line; a checkpoint from before digests still loads, with a line saying it is unchecked."""

import json
import shutil
from pathlib import Path

import pytest

from sljax.errors import SljaxError
from sljax.models import checkpoint as ckpt
from sljax.models import digest
from sljax.models import load as trained
from sljax.train import cli

# The finished TinyTwin run (checkpoints 3, 4, 6) that test_train_faults damages, copied per test.
from test_train_faults import _copy, base, tiny  # noqa: F401  (fixtures)

pytestmark = pytest.mark.filterwarnings("ignore")


def _largest(step_dir: Path) -> Path:
  return max((p for p in step_dir.rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)


def _flip_two(step_dir: Path) -> str:
  path = _largest(step_dir)
  raw = bytearray(path.read_bytes())
  for i in (len(raw) // 2, len(raw) // 2 + 1):
    raw[i] ^= 0x01
  path.write_bytes(bytes(raw))
  return path.relative_to(step_dir).as_posix()


def _cut_in_half(step_dir: Path) -> str:
  path = _largest(step_dir)
  path.write_bytes(path.read_bytes()[:path.stat().st_size // 2])
  return path.relative_to(step_dir).as_posix()


def _empty_every_file(step_dir: Path) -> str:
  for p in step_dir.rglob("*"):
    if p.is_file():
      p.write_bytes(b"")
  return "_CHECKPOINT_METADATA"  # orbax reads it first, on opening the folder


def _folder_for_file(step_dir: Path) -> str:
  path = _largest(step_dir)
  path.unlink()
  path.mkdir()
  return path.relative_to(step_dir).as_posix()


def _file_for_folder(step_dir: Path) -> str:
  shutil.rmtree(step_dir)
  step_dir.write_text("not a checkpoint")
  return step_dir.name


def _empty_folder(step_dir: Path) -> str:
  shutil.rmtree(step_dir)
  step_dir.mkdir()
  return "an empty folder"


def _lose_digest(step_dir: Path) -> str:
  (step_dir / digest.DIGEST_FILE).unlink()
  return digest.DIGEST_FILE


DAMAGE = {"two flipped bytes": _flip_two, "cut in half": _cut_in_half,
          "every file emptied": _empty_every_file, "a folder where a file goes": _folder_for_file,
          "a file where the step's folder goes": _file_for_folder,
          "newest step emptied": _empty_folder, "digest lost": _lose_digest}


def _run(argv, capsys):
  code = cli.main(argv)
  out = capsys.readouterr()
  return code, out.out, out.err


@pytest.mark.parametrize("damage", DAMAGE)
def test_damage_is_refused_in_one_line_naming_the_file(damage, base, tmp_path, capsys):
  wd = _copy(base, tmp_path)
  checkpoints = wd / "checkpoints"
  named = DAMAGE[damage](checkpoints / "6")
  code, _, err = _run(["--workdir", str(wd), "--resume", "--epochs", "3", "--no-progress"],
                      capsys)
  assert code == 2, err
  assert err.startswith(f"train.py: error: {checkpoints / '6'}: checkpoint 6 is damaged or "
                        "incomplete (")
  assert named in err
  assert "earlier checkpoints: steps 3, 4" in err and "--resume-skip-damaged" in err
  assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
  # --init-from, and an explicit step (predict/evaluate/export WORKDIR/checkpoints/6): refused.
  with pytest.raises(SljaxError, match=r"checkpoints/6: checkpoint 6 is damaged or incomplete"):
    trained.load_params(wd)
  with pytest.raises(SljaxError, match=r"checkpoints/6: checkpoint 6 is damaged or incomplete"):
    trained.load_for_inference(checkpoints / "6")


def test_two_flipped_bytes_name_the_file_and_say_why(base, tmp_path, capsys):
  wd = _copy(base, tmp_path)
  named = _flip_two(wd / "checkpoints" / "6")
  code, _, err = _run(["--workdir", str(wd), "--resume", "--epochs", "3", "--no-progress"],
                      capsys)
  assert code == 2
  assert f"({named}: its bytes differ from those written)" in err


@pytest.mark.parametrize("damage", ["two flipped bytes", "newest step emptied",
                                    "a file where the step's folder goes", "every file emptied"])
def test_skip_damaged_resumes_from_the_step_before_with_a_line(damage, base, tmp_path, capsys):
  wd = _copy(base, tmp_path)
  checkpoints = wd / "checkpoints"
  DAMAGE[damage](checkpoints / "6")
  code, out, err = _run(["--workdir", str(wd), "--resume", "--resume-skip-damaged", "--epochs",
                         "3", "--no-progress"], capsys)
  assert code == 0, err
  assert (f"--resume-skip-damaged: skipped {checkpoints / '6'}: checkpoint 6 is damaged or "
          "incomplete") in out
  assert "moved to 6.damaged" in out and "resuming from step 4" in out
  assert (checkpoints / "6.damaged").exists()
  assert (checkpoints / "9").is_dir()  # the run went on past the skipped step


@pytest.mark.parametrize("damage", ["two flipped bytes", "every file emptied"])
def test_skip_damaged_with_every_step_damaged_is_one_line(damage, base, tmp_path, capsys):
  """Nothing intact is left: one line, not a traceback (every file emptied: orbax's opening
  moves each step aside before any is restored)."""
  wd = _copy(base, tmp_path)
  for step in ckpt.step_entries(wd / "checkpoints"):
    DAMAGE[damage](wd / "checkpoints" / str(step))
  code, _, err = _run(["--workdir", str(wd), "--resume", "--resume-skip-damaged", "--epochs",
                       "3", "--no-progress"], capsys)
  assert code == 2 and "no intact checkpoint is left" in err, err
  assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_skip_damaged_needs_resume(base, tmp_path, capsys):
  code, _, err = _run(["--workdir", str(tmp_path / "x"), "--resume-skip-damaged"], capsys)
  assert code == 2 and "--resume-skip-damaged: only with --resume" in err


# 6 is the newest and the best: flipped, the newest intact step before it (4) is used; emptied,
# its metrics are gone too and orbax's best of the others (3, the one with a validation MAE).
@pytest.mark.parametrize("damage, used", [("two flipped bytes", 4), ("newest step emptied", 3)])
def test_predict_falls_back_to_an_intact_step_with_a_line(damage, used, base, tmp_path):
  wd = _copy(base, tmp_path)
  DAMAGE[damage](wd / "checkpoints" / "6")
  lines = []
  _, _, step = trained.load_params(wd, fallback=True, note=lines.append)
  assert step == used
  assert len(lines) == 1 and "checkpoints/6: checkpoint 6 is damaged or incomplete" in lines[0]
  assert f"using step {used}" in lines[0]


def test_an_old_checkpoint_without_a_digest_loads_unchecked_with_a_line(base, tmp_path, capsys):
  wd = _copy(base, tmp_path)
  for step in (3, 4, 6):  # as written before digests: no digest file, no digest in meta
    folder = wd / "checkpoints" / str(step)
    (folder / digest.DIGEST_FILE).unlink()
    meta = json.loads((folder / "meta" / "metadata").read_text())
    meta.pop(ckpt.DIGEST_KEY)
    (folder / "meta" / "metadata").write_text(json.dumps(meta))
  lines = []
  assert trained.load_params(wd, note=lines.append)[2] == 6
  assert lines == [f"{wd / 'checkpoints' / '6'}: checkpoint 6 has no digest (saved before sljax "
                   "recorded checkpoint bytes); restoring it unchecked"]
  code, out, err = _run(["--workdir", str(wd), "--resume", "--epochs", "3", "--no-progress"],
                        capsys)
  assert code == 0, err
  assert "checkpoint 6 has no digest" in out and "resuming from step 6" in out
  # The checkpoints written from now on have their digest.
  assert (wd / "checkpoints" / "9" / digest.DIGEST_FILE).is_file()


def test_every_saved_step_has_a_digest_of_its_files(base):
  for step in (3, 4, 6):
    folder = base[1] / "checkpoints" / str(step)
    assert digest.read_digest(folder) == digest.file_digests(folder)
    assert "meta/metadata" in digest.read_digest(folder)
