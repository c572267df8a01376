"""sljax.io.files: outputs written whole, output folders checked, .npz files read with one-line
errors. The other tests reach these through the commands; here each rule is checked alone."""

import errno
import fcntl
import os
import socket
import threading

import numpy as np
import pytest

from sljax.errors import SljaxError
from sljax.io import files

import toys


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


def _tree(folder):
  """Every file below folder (hidden ones included) with its bytes."""
  return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
          if p.is_file()}


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_staged_leaves_an_absent_folder_absent_and_an_old_one_as_it_was(tmp_path, error):
  new = tmp_path / "a" / "b" / "out"  # its parents are made for the stage, and unmade
  with pytest.raises(error):
    with files.staged(new) as stage:
      assert files.is_temporary(stage)
      (stage / "x.txt").write_text("half")
      raise error()
  assert list(tmp_path.iterdir()) == []
  old = tmp_path / "old"
  (old / "sl0").mkdir(parents=True)
  (old / "sl0" / "000.png").write_bytes(b"old plane")
  (old / "keep.txt").write_text("kept")
  before = _tree(old)
  with pytest.raises(error):
    with files.staged(old, whole=frozenset({"sl0"})) as stage:
      assert stage.parent == old and files.is_temporary(stage)  # inside: one file system
      (stage / "keep.txt").write_text("new")
      raise error()
  assert _tree(old) == before


def test_staged_moves_in_merging_and_replacing_whole_folders(tmp_path):
  with files.staged(tmp_path / "new") as stage:
    (stage / "sub").mkdir()
    (stage / "sub" / "f.txt").write_text("f")
  assert _tree(tmp_path) == {"new/sub/f.txt": b"f"}
  out = tmp_path / "new"
  (out / "sl0").mkdir()
  (out / "sl0" / "000.png").write_bytes(b"0")
  (out / "sl0" / "001.png").write_bytes(b"stale")
  with files.staged(out, whole=frozenset({"sl0"})) as stage:
    (stage / "sub").mkdir()
    (stage / "sub" / "g.txt").write_text("g")  # merged beside f.txt
    (stage / "sl0").mkdir()
    (stage / "sl0" / "000.png").write_bytes(b"new")  # replaces sl0/ whole: 001.png goes
  assert _tree(out) == {"sub/f.txt": b"f", "sub/g.txt": b"g", "sl0/000.png": b"new"}
  (tmp_path / "file").write_text("x")
  with pytest.raises(SljaxError, match="file: exists and is not a folder$"):
    with files.staged(tmp_path / "file"):
      pass


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


def test_exclusive_refuses_a_second_process_until_the_first_ends(tmp_path):
  folder = tmp_path / "run"
  proc = toys.hold(folder, "sljax train (psmnet)")
  try:
    holder = (folder / files.LOCK_FILE).read_text()
    assert holder.startswith(f"sljax train (psmnet) (pid {proc.pid} on {socket.gethostname()}, "
                             "since ")
    with pytest.raises(SljaxError) as e:
      with files.exclusive(folder, "sljax train (unet)"):
        pytest.fail("entered a held folder")
    assert str(e.value) == (f"{folder}: in use by {holder}; wait for it to end or stop it (its "
                            "lock ends with it), or choose another folder")
    assert (folder / files.LOCK_FILE).read_text() == holder  # the holder's record kept
  finally:
    proc.kill()  # as kill -9: the lock ends with the process, its file stays behind
    proc.wait()
  assert os.listdir(folder) == [files.LOCK_FILE]
  with files.exclusive(folder, "second"):
    assert (folder / files.LOCK_FILE).read_text().startswith(f"second (pid {os.getpid()} ")
  assert os.listdir(folder) == []  # the lock file goes; the folder existed before, it stays


def test_exclusive_in_one_process_and_what_it_leaves(tmp_path):
  new = tmp_path / "a" / "b"
  with files.exclusive(new, "one"):
    with pytest.raises(SljaxError, match=rf"^{new}: in use by one \(pid {os.getpid()} on "):
      with files.exclusive(new, "two"):
        pass
    assert os.listdir(new) == [files.LOCK_FILE]
  assert not (tmp_path / "a").exists()  # created and left empty: removed, parents included
  with files.exclusive(new, "one"):
    (new / "config.json").write_text("{}")
  assert os.listdir(new) == ["config.json"]
  with files.exclusive(new, "again"):  # a run that wrote nothing leaves the folder as it was
    pass
  assert os.listdir(new) == ["config.json"]
  with files.exclusive(tmp_path / "c", "x", active=False):  # not the main process: no lock
    assert not (tmp_path / "c").exists()
  with pytest.raises(RuntimeError):
    with files.exclusive(tmp_path / "d", "x"):
      raise RuntimeError("the block failed")
  assert sorted(os.listdir(tmp_path)) == ["a"]


def test_exclusive_on_a_folder_it_cannot_write_leaves_the_error_to_the_block(tmp_path):
  a_file = tmp_path / "a_file"
  a_file.write_text("x")
  with files.exclusive(a_file, "x"):  # the block's own write will name the problem
    with pytest.raises(OSError):
      (a_file / "config.json").write_text("{}")
  assert a_file.read_text() == "x"


def test_holder_names_the_process_holding_a_folder_and_leaves_it_held(tmp_path):
  folder = tmp_path / "out"
  assert files.holder(folder) is None  # no folder
  folder.mkdir()
  assert files.holder(folder) is None  # no lock file
  proc = toys.hold(folder, "sljax experiment run fig7-v2")
  try:
    record = files.holder(folder)
    assert record.startswith(f"sljax experiment run fig7-v2 (pid {proc.pid} on ")
    assert files.holder(folder) == record  # asking twice changes nothing
    with pytest.raises(SljaxError, match="in use by sljax experiment run fig7-v2"):
      with files.exclusive(folder, "x"):  # still held after the probes
        pass
  finally:
    proc.kill()
    proc.wait()
  assert (folder / files.LOCK_FILE).exists() and files.holder(folder) is None  # a stale file


def test_exclusive_waits_out_a_holder_probe_and_keeps_anothers_lock_file(tmp_path):
  folder = tmp_path / "out"
  folder.mkdir()
  probe = os.open(folder / files.LOCK_FILE, os.O_RDWR | os.O_CREAT)
  fcntl.flock(probe, fcntl.LOCK_SH)  # as files.holder holds it, for a moment
  threading.Timer(0.08, os.close, [probe]).start()
  with files.exclusive(folder, "after the probe"):  # retried, not refused
    assert files.holder(folder).startswith("after the probe (pid ")
    # Someone deletes the lock file by hand and another process locks a new one: leaving,
    # this holder must not remove that process's file.
    (folder / files.LOCK_FILE).unlink()
    proc = toys.hold(folder, "the newer run")
  try:
    assert files.holder(folder).startswith(f"the newer run (pid {proc.pid} ")
  finally:
    proc.kill()
    proc.wait()


def test_exclusive_where_no_lock_can_be_taken_says_so(tmp_path, monkeypatch, capsys):
  folder = tmp_path / "out"
  real_open = os.open

  def no_write_open(path, flags, *mode):  # another user's lock file (root cannot chmod this)
    if flags & os.O_RDWR:
      raise PermissionError(13, "Permission denied", str(path))
    return real_open(path, flags, *mode)

  proc = toys.hold(folder, "another user's run")
  try:
    with monkeypatch.context() as m:
      m.setattr(files.os, "open", no_write_open)
      with pytest.raises(SljaxError, match="in use by another user's run"):
        with files.exclusive(folder, "x"):
          pass
  finally:
    proc.kill()
    proc.wait()
  with monkeypatch.context() as m:  # the holder is gone: go on, unlocked, and say so
    m.setattr(files.os, "open", no_write_open)
    with files.exclusive(folder, "x"):
      pass
  assert capsys.readouterr().err == (
      f"sljax: {folder / files.LOCK_FILE}: not locked (cannot open the lock file for writing); "
      f"a second process writing {folder} would not be refused\n")

  def no_locks(fd, op):
    raise OSError(errno.ENOLCK, "No locks available")

  with monkeypatch.context() as m:  # a file system without flock
    m.setattr(files.fcntl, "flock", no_locks)
    with files.exclusive(tmp_path / "nfs", "x"):
      pass
  assert "not locked (No locks available)" in capsys.readouterr().err
