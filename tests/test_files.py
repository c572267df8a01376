"""sljax.files: outputs written whole, output folders checked, .npz files read with one-line
errors. The other tests reach these through the commands; here each rule is checked alone."""

import os

import numpy as np
import pytest

from sljax import files
from sljax.errors import SljaxError


def test_replacing_keeps_the_old_files_when_the_block_fails(tmp_path):
  a, b = tmp_path / "a.txt", tmp_path / "b.txt"
  a.write_text("old a")
  with pytest.raises(RuntimeError):
    with files.replacing(a, b) as (ta, tb):
      ta.write_text("new a")
      tb.write_text("new b")
      raise RuntimeError("disk full")
  assert a.read_text() == "old a" and not b.exists()
  assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]  # no temporaries left
  with files.replacing(a, b) as (ta, tb):
    ta.write_text("new a")
    tb.write_text("new b")
  assert (a.read_text(), b.read_text()) == ("new a", "new b")


def test_temporaries_are_recognised_and_nothing_else(tmp_path):
  for name in ("metrics.json", "im0.png", "000.png", "variables.npz", "README"):
    tmp = files.temp_path(tmp_path / name)
    assert files.is_temporary(tmp), tmp
    assert tmp.parent == tmp_path  # the same folder: the rename is atomic
    assert name == "README" or tmp.suffix == os.path.splitext(name)[1]  # picks cv2's format
    assert not files.is_temporary(tmp_path / name)
  for name in (".gitignore", ".hidden.png", ".tmp", "a.tmp1.png", ".DS_Store"):
    assert not files.is_temporary(tmp_path / name), name


def test_output_folder_refuses_a_file_and_a_used_folder_but_not_leftovers(tmp_path):
  f = tmp_path / "file"
  f.write_text("x")
  with pytest.raises(SljaxError, match=f"^--out {f}: exists and is not a folder$"):
    files.check_output_folder(f, overwrite=True)
  out = tmp_path / "out"
  assert files.check_output_folder(out, False, must_be_empty=True) == out
  assert not out.exists()  # checked, not created
  out.mkdir()
  files.temp_path(out / "metrics.json").write_text("killed half-way")
  files.check_output_folder(out, False, must_be_empty=True)  # a leftover is not a result
  (out / "metrics.json").write_text("{}")
  with pytest.raises(SljaxError, match=r"^OUT .*out: folder is not empty \(pass --overwrite"):
    files.check_output_folder(out, False, label="OUT", must_be_empty=True)
  files.check_output_folder(out, True, must_be_empty=True)
  files.check_output_folder(out, False)  # only folders that must be empty are refused


def test_read_npz_reads_arrays_and_names_each_problem(tmp_path):
  good = tmp_path / "good.npz"
  np.savez(good, a=np.arange(3), b=np.eye(2))
  arrays = files.read_npz(good, "predictions")
  assert sorted(arrays) == ["a", "b"] and arrays["b"].tolist() == [[1, 0], [0, 1]]
  cases = {
      "empty.npz": (b"", "empty file (0 bytes)"),
      "text.npz": (b"hello world", "not a zip archive"),
      "cut.npz": (good.read_bytes()[:60], "damaged or truncated"),
  }
  for name, (data, why) in cases.items():
    (tmp_path / name).write_bytes(data)
    with pytest.raises(SljaxError) as err:
      files.read_npz(tmp_path / name, "predictions")
    assert str(err.value).startswith(f"{tmp_path / name}: not an .npz archive of predictions (")
    assert why in str(err.value), str(err.value)
  np.save(tmp_path / "single.npy", np.arange(3))
  (tmp_path / "single.npy").rename(tmp_path / "single.npz")
  with pytest.raises(SljaxError, match="a single .npy array; save the arrays with numpy.savez"):
    files.read_npz(tmp_path / "single.npz", "predictions")
  # A valid archive with an array of Python objects: named as such (not "not an .npz"), and
  # never unpickled.
  np.savez(tmp_path / "objects.npz", ok=np.zeros(2), meta=np.array([{"x": 1}], dtype=object))
  with pytest.raises(SljaxError) as err:
    files.read_npz(tmp_path / "objects.npz", "predictions")
  assert str(err.value) == (
      f"{tmp_path / 'objects.npz'}: array 'meta' holds Python objects (dtype object), which are "
      "not loaded (unpickling can run code); save predictions as numeric arrays")


def test_require_folder_tells_a_file_from_a_missing_folder(tmp_path):
  (tmp_path / "f").write_text("x")
  assert files.require_folder(tmp_path, "dataset folder") == tmp_path
  with pytest.raises(SljaxError, match=f"^{tmp_path / 'f'}: is a file, not a keyframe folder$"):
    files.require_folder(tmp_path / "f", "keyframe folder")
  with pytest.raises(SljaxError, match=f"^{tmp_path / 'g'}: dataset folder does not exist$"):
    files.require_folder(tmp_path / "g", "dataset folder")
