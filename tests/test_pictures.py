import cv2
import numpy as np

from sljax.io import pictures


def test_save_panels_writes_png_of_expected_layout(tmp_path):
  rng = np.random.default_rng(0)
  disp = rng.uniform(0, 10, (32, 40)).astype(np.float32)
  disp[:4] = np.inf
  panels = [pictures.Panel("left", rng.uniform(size=(32, 40, 3))),
            pictures.Panel("gray", rng.uniform(size=(32, 40, 1))),
            pictures.Panel("disparity", disp, cmap="turbo", label="px")]
  out = tmp_path / "sub" / "fig.png"
  pictures.save_panels(out, panels, ncols=2, title="t")
  img = cv2.imread(str(out))
  assert img is not None and img.shape[0] > 100 and img.shape[1] > 100
  # Two columns, two rows: wider than a single tile and not blank.
  assert img.std() > 10


def _scene_dir(tmp_path):
  from sljax.data.scene import Scene, write_scene
  rng = np.random.default_rng(1)
  scene = Scene(name="s", im0=rng.uniform(size=(16, 16, 3)).astype(np.float32),
                im1=rng.uniform(size=(16, 16, 3)).astype(np.float32),
                disp0=rng.uniform(1, 4, (16, 16)).astype(np.float32))
  write_scene(tmp_path / "s", scene)
  return tmp_path / "s"


def test_show_refuses_an_existing_picture_and_unknown_formats(tmp_path, capsys):
  from sljax import cli
  scene = _scene_dir(tmp_path)
  out = tmp_path / "sheet.png"
  out.write_bytes(b"an earlier picture")

  def one_error(argv, match):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("sljax show: error: ") and match in err[0], err
  one_error(["show", str(scene), "--out", str(out)],
            f"{out}: exists (pass --overwrite to replace it)")
  assert out.read_bytes() == b"an earlier picture"
  for name, what in (("s.txt", "'.txt' is not a picture format"),
                     ("sheet", "no extension is not a picture format")):
    one_error(["show", str(scene), "--out", str(tmp_path / name)], what)
    assert not (tmp_path / name).exists()
  one_error(["show", str(scene), "--out", str(tmp_path)], "not a picture format")
  one_error(["show", str(tmp_path / "nope"), "--out", str(tmp_path / "x.png")], "no such scene")
  assert cli.main(["show", str(scene), "--out", str(out), "--overwrite"]) == 0
  assert cv2.imread(str(out)) is not None
  for fmt in ("pdf", "svg", "jpg"):
    assert cli.main(["show", str(scene), "--out", str(tmp_path / f"s.{fmt}")]) == 0
  assert sorted(p.name for p in tmp_path.iterdir()) == ["s", "s.jpg", "s.pdf", "s.svg",
                                                        "sheet.png"]  # no temporary left


def test_failed_save_keeps_the_earlier_picture(tmp_path, monkeypatch):
  """savefig failing part-way (a full disk) leaves the earlier file byte for byte, no temp."""
  import errno
  from matplotlib.figure import Figure
  out = tmp_path / "fig.png"
  out.write_bytes(b"earlier")

  def full(self, fname, **kwargs):
    with open(fname, "wb") as f:
      f.write(b"half a pict")
    raise OSError(errno.ENOSPC, "No space left on device", str(fname))
  monkeypatch.setattr(Figure, "savefig", full)
  try:
    pictures.save_panels(out, [pictures.Panel("x", np.zeros((4, 4)))])
  except OSError as e:
    assert e.filename == str(out) and e.errno == errno.ENOSPC
  else:
    raise AssertionError("no error")
  assert out.read_bytes() == b"earlier" and [p.name for p in tmp_path.iterdir()] == ["fig.png"]
