import json

import numpy as np
import pytest

from sljax.data.dataset import (FolderSource, find_scenes, iterate_batches, load_batch,
                                parse_fraction, split_indices, take_fraction)
from sljax.data.scene import Scene, write_scene
from sljax.errors import SljaxError

H, W, T = 8, 12, 3
N = 12


def _scene(k: int) -> Scene:
  rng = np.random.default_rng(k)
  disp = np.full((H, W), k + 1.0, np.float32)  # identifies the scene inside a batch
  disp[0, 0] = np.inf
  sl = rng.integers(0, 2, (H, W, T)).astype(np.float32)
  sl[1, 2, 0] = np.nan
  meta = {"group": f"g{k // 2}", "code": "gray"} if k < 10 else {}
  return Scene(name=str(k), im0=rng.uniform(0, 1, (H, W, 3)).astype(np.float32),
               im1=rng.uniform(0, 1, (H, W, 3)).astype(np.float32), disp0=disp, sl0=sl,
               sl1=sl, mask0=rng.uniform(size=(H, W)) > 0.5, meta=meta)


@pytest.fixture(scope="module")
def root(tmp_path_factory):
  r = tmp_path_factory.mktemp("ds")
  for k in range(N):
    # Nested layout: scenes at different depths.
    sub = f"a/s{k:02d}" if k % 3 else f"b/deep/s{k:02d}"
    write_scene(r / sub, _scene(k))
  return r


@pytest.fixture(scope="module")
def src(root):
  return FolderSource(root)


def test_find_scenes_sorted_and_nested(root):
  found = find_scenes(root)
  rel = [p.relative_to(root).as_posix() for p in found]
  assert rel == sorted(rel) and len(rel) == N and "b/deep/s00" in rel


def test_empty_dataset(tmp_path):
  (tmp_path / "nothing" / "here").mkdir(parents=True)
  with pytest.raises(SljaxError, match="nothing.*empty dataset"):
    find_scenes(tmp_path / "nothing")
  with pytest.raises(SljaxError, match="nothing"):
    FolderSource(tmp_path / "nothing")
  with pytest.raises(SljaxError, match="missing_root"):
    find_scenes(tmp_path / "missing_root")


def test_data_that_is_a_file_says_so(tmp_path, capsys):
  """--data naming a file: 'is a file', not 'does not exist'."""
  from sljax import cli
  f = tmp_path / "data.txt"
  f.write_text("x")
  with pytest.raises(SljaxError) as info:
    find_scenes(f)
  assert str(info.value) == f"{f}: is a file, not a dataset folder"
  with pytest.raises(SljaxError) as info:
    find_scenes(tmp_path / "nope")
  assert str(info.value) == f"{tmp_path / 'nope'}: dataset folder does not exist"
  assert cli.main(["experiment", "run", "table1", str(tmp_path / "o"), "--data", str(f)]) == 2
  assert capsys.readouterr().err.strip().endswith(f"{f}: is a file, not a dataset folder")
  assert not (tmp_path / "o").exists()


def test_folder_source(src):
  assert len(src) == N
  k = int(src.name(3)[-2:])
  s = src[3]
  assert s.name == src.name(3)
  np.testing.assert_array_equal(s.disp0[1:, 1:], k + 1.0)
  assert src.group(3) == (f"g{k // 2}" if k < 10 else src.name(3))
  assert src.code == "gray" and src.num_patterns == T
  with pytest.raises(IndexError):
    src[N]


def test_root_that_is_a_scene(root):
  s = FolderSource(root / "a" / "s01")
  assert len(s) == 1 and s.name(0) == "s01" and s.group(0) == "g0"


def _naive_split(groups, fraction, seed):
  """Reference: rank groups by sha256(seed NUL group) and take the first round(f * n)."""
  import hashlib
  unique = sorted(set(groups), key=lambda g: (
      int.from_bytes(hashlib.sha256(f"{seed}\x00{g}".encode()).digest()[:8], "big"), g))
  test_groups = set(unique[:max(1, round(fraction * len(unique)))])
  return [i for i, g in enumerate(groups) if g in test_groups]


@pytest.mark.parametrize("seed", [0, 1, 7])
def test_split_group_disjoint_and_deterministic(src, seed):
  train, test = split_indices(src, seed=seed)
  assert (train, test) == split_indices(src, seed=seed)
  assert sorted(train + test) == list(range(N))
  groups = [src.group(i) for i in range(N)]
  assert not {groups[i] for i in train} & {groups[i] for i in test}
  assert len({groups[i] for i in test}) == round(0.2 * len(set(groups)))  # 7 groups -> 1
  assert test == _naive_split(groups, 0.2, seed)


def test_split_fraction_and_seed_change(src):
  splits = {tuple(split_indices(src, 0.5, seed=s)[1]) for s in range(6)}
  assert len(splits) > 1  # the seed matters
  groups = {src.group(i) for i in split_indices(src, 0.5, seed=0)[1]}
  assert len(groups) == round(0.5 * 7)


def test_explicit_splits(tmp_path):
  for k in range(4):
    write_scene(tmp_path / f"s{k}", _scene(k))
  (tmp_path / "dataset.json").write_text(json.dumps(
      {"name": "x", "code": "binary", "patterns": T, "splits": {"test": ["s2"]}}))
  s = FolderSource(tmp_path)
  assert s.code == "binary" and s.num_patterns == T
  assert split_indices(s) == ([0, 1, 3], [2])
  (tmp_path / "dataset.json").write_text(json.dumps(
      {"splits": {"train": ["s0", "s1"], "test": ["s3"]}}))
  assert split_indices(FolderSource(tmp_path)) == ([0, 1], [3])
  (tmp_path / "dataset.json").write_text(json.dumps({"splits": {"test": ["nope"]}}))
  with pytest.raises(SljaxError, match="dataset.json.*nope"):
    split_indices(FolderSource(tmp_path))
  (tmp_path / "dataset.json").write_text("{bad")
  with pytest.raises(SljaxError, match="dataset.json"):
    FolderSource(tmp_path)


def test_parse_fraction():
  assert parse_fraction("1/16") == 0.0625
  assert parse_fraction("0.25") == 0.25 and parse_fraction("50%") == 0.5
  assert parse_fraction(1) == 1.0
  for bad in ["0", "2", "abc", "1/0", "-1/4"]:
    with pytest.raises(SljaxError, match="fraction"):
      parse_fraction(bad)


def test_take_fraction():
  idx = list(range(100, 164))
  a = take_fraction(idx, "1/16", seed=3)
  assert a == take_fraction(list(reversed(idx)), 0.0625, seed=3)  # deterministic
  assert len(a) == 4 and set(a) <= set(idx) and a == sorted(a)
  assert set(a) <= set(take_fraction(idx, "1/4", seed=3))  # nested
  assert take_fraction(idx, "1/16", seed=4) != a
  assert len(take_fraction([5, 6], "1/16")) == 1  # at least one scene
  assert take_fraction(idx, 1) == idx


def _ref_nearest(a, h, w):
  """Reference nearest resampling: output pixel centre mapped back, float64 loop."""
  out = np.empty((h, w) + a.shape[2:], a.dtype)
  for y in range(h):
    for x in range(w):
      out[y, x] = a[min(int((y + 0.5) * a.shape[0] / h), a.shape[0] - 1),
                    min(int((x + 0.5) * a.shape[1] / w), a.shape[1] - 1)]
  return out


def test_load_batch_resize(src):
  b = load_batch(src, [0, 5], size=(H // 2, W // 3), parts=("left", "disp", "sl", "mask"))
  assert b["left"].shape == (2, H // 2, W // 3, 3) and b["left"].dtype == np.float32
  assert b["mask"].dtype == bool and b["sl"].shape == (2, H // 2, W // 3, T)
  s = src[5]
  # Integer-factor area resampling = block mean.
  block = s.im0.reshape(H // 2, 2, W // 3, 3, 3).mean(axis=(1, 3))
  np.testing.assert_allclose(b["left"][1], block, atol=1e-5)
  np.testing.assert_array_equal(b["disp"][1], _ref_nearest(s.disp0, H // 2, W // 3) / 3)
  np.testing.assert_array_equal(b["sl"][1], _ref_nearest(s.sl0, H // 2, W // 3))
  np.testing.assert_array_equal(b["mask"][1], _ref_nearest(s.mask0, H // 2, W // 3))
  up = load_batch(src, [5], size=(2 * H, 2 * W), gray=True, parts=("left", "disp"))
  assert up["left"].shape == (1, 2 * H, 2 * W, 1)
  np.testing.assert_array_equal(up["disp"][0], _ref_nearest(s.disp0, 2 * H, 2 * W) * 2)


def test_load_batch_native_and_missing_part(src, tmp_path):
  b = load_batch(src, [1, 2], parts=("left", "right", "sl_right"))
  assert b["right"].shape == (2, H, W, 3) and b["sl_right"].shape == (2, H, W, T)
  with pytest.raises(SljaxError, match="disp1.pfm"):
    load_batch(src, [1], parts=("disp_right",))
  with pytest.raises(SljaxError, match="unknown batch part"):
    load_batch(src, [1], parts=("depth",))


def _disp_ids(batch):
  return [int(d[-1, -1]) - 1 for d in batch["disp"]]


def test_iterate_batches_order(src):
  idx = list(range(N))
  ep0 = [k for b in iterate_batches(src, idx, 4, seed=1, epoch=0,
                                    parts=("disp",)) for k in _disp_ids(b)]
  scene_id = [int(src.name(i)[-2:]) for i in idx]
  perm = np.random.default_rng([1, 0]).permutation(N)
  assert ep0 == [scene_id[idx[p]] for p in perm]  # order = permutation(seed, epoch)
  ep1 = [k for b in iterate_batches(src, idx, 4, seed=1, epoch=1,
                                    parts=("disp",)) for k in _disp_ids(b)]
  assert sorted(ep1) == sorted(ep0) and ep1 != ep0
  batches = list(iterate_batches(src, idx, 5, seed=1, epoch=0, parts=("disp",)))
  assert len(batches) == 2  # drop_last
  batches = list(iterate_batches(src, idx, 5, seed=1, epoch=0, parts=("disp",),
                                 drop_last=False, shuffle=False))
  assert [len(b["disp"]) for b in batches] == [5, 5, 2]
  assert [k for b in batches for k in _disp_ids(b)] == scene_id
  with pytest.raises(SljaxError, match="no scenes"):
    next(iterate_batches(src, [], 2, seed=0, epoch=0))


def test_crop_independent_of_batch_size(src):
  kw = dict(seed=3, epoch=2, size=(5, 7), mode="crop", shuffle=False, parts=("left", "disp", "sl"))
  one = [b for b in iterate_batches(src, range(4), 1, **kw)]
  two = [b for b in iterate_batches(src, range(4), 2, **kw)]
  for k in range(4):
    np.testing.assert_array_equal(one[k]["left"][0], two[k // 2]["left"][k % 2])
  # The crop is a window of the scene, with the same offset for every part.
  s = src[2]
  crop = one[2]["left"][0]
  hits = [(y, x) for y in range(H - 4) for x in range(W - 6)
          if np.array_equal(s.im0[y:y + 5, x:x + 7], crop)]
  assert len(hits) == 1
  y, x = hits[0]
  np.testing.assert_array_equal(one[2]["sl"][0], s.sl0[y:y + 5, x:x + 7])
  np.testing.assert_array_equal(one[2]["disp"][0], s.disp0[y:y + 5, x:x + 7])  # not rescaled
  other_epoch = load_batch(src, [2], size=(5, 7), mode="crop", seed=3, epoch=5)
  with pytest.raises(SljaxError, match="smaller than the crop"):
    load_batch(src, [2], size=(H + 1, W), mode="crop")
  assert other_epoch["left"].shape == (1, 5, 7, 3)


class _ListSource:
  """A minimal in-memory source (what SyntheticSource provides)."""

  def __init__(self, scenes):
    self.scenes = scenes

  def __len__(self):
    return len(self.scenes)

  def __getitem__(self, i):
    return self.scenes[i]

  def group(self, i):
    return self.scenes[i].group


def test_generic_source():
  s = _ListSource([_scene(k) for k in range(6)])
  train, test = split_indices(s, seed=0)
  assert sorted(train + test) == list(range(6)) and len(test) == 2  # 3 groups -> 1 test group
  b = load_batch(s, test, gray=True, parts=("left", "sl"))
  assert b["left"].shape == (2, H, W, 1)
