"""PSMNet pinned to the real reference: JiaRenChang/PSMNet's outputs for deterministic weights.

tests/data/psmnet_reference.npz holds what the reference's models/stackhourglass.py computes
(on PyTorch, by tools/make_psmnet_fixture.py) for the weights of tests/reference_weights.py
on small inputs. Here the same weights are rebuilt with NumPy, converted with
sljax.nets.convert and run through sljax: evaluation mode, training mode (three outputs and
the updated BatchNorm statistics), pad mode at a size that is not a multiple of 16 (through
sljax.inference, against the reference's Test_img.py protocol), a 256x256 case where every
SPP pool has the reference's own kernel, and the twin's disparity path. Needs neither torch
nor the reference.
"""

import json

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import reference_weights as rw
from sljax import inference
from sljax.nets import ModelConfig, PSMNet, PSMNetMTL, detach_sl
from sljax.nets.convert import convert_state_dict
from sljax.nets.psmnet import reference_key

CASES = {c.name: c for c in rw.CASES}
# The float64 reference is stored; the reference's own float32 run deviates from it by up to
# 1e-4 px (the fixture's meta) and sljax's float32 by 1.2e-4 px at most. Planted wiring bugs
# move it by far more (SPP branches in the wrong order: 10-19 px).
DISP_ATOL = 1e-3
STATS_ATOL = 1e-5


@pytest.fixture(scope="module")
def fixture():
  with np.load(rw.FIXTURE_FILE) as z:
    data = {k: z[k] for k in z.files}
  data["meta"] = json.loads(str(data["meta"]))
  return data


@pytest.fixture(scope="module")
def variables():
  return jax.tree.map(jnp.asarray, convert_state_dict(rw.state_dict()))


def _inputs(case):
  return tuple(jnp.asarray(x) for x in rw.images(case))


def test_fixture_records_its_provenance_and_the_recipe_is_unchanged(fixture):
  meta = fixture["meta"]
  assert meta["seed"] == rw.SEED
  assert len(meta["commit"]) == 40 and meta["torch"]
  # A different fingerprint means the recipe (or NumPy's streams) changed: regenerate the
  # fixture with tools/make_psmnet_fixture.py rather than loosening a tolerance.
  assert meta["fingerprint"] == rw.fingerprint(), "recipe differs from the fixture's"
  for name, info in meta["cases"].items():
    assert 1.5 / CASES[name].maxdisp < info["peak"] < 0.5, (name, info["peak"])  # soft, not flat


def test_eval_mode_at_256x256_matches_the_reference(fixture, variables):
  """Every SPP pool with the reference's own kernel (64, 32, 16, 8 on the 64x64 map)."""
  name = "full"
  case = CASES[name]
  model = PSMNet(maxdisp=case.maxdisp)
  out = jax.jit(lambda v, a, b: model.apply(v, a, b, train=False))(variables, *_inputs(case))
  got = np.asarray(out["disparity"])[:, ::case.row_step]
  np.testing.assert_allclose(got, fixture[f"{name}/disparity"], rtol=0, atol=DISP_ATOL)


def _by_reference_key(batch_stats):
  return {reference_key(tuple(k.key for k in path)): np.asarray(v).ravel()
          for path, v in jax.tree_util.tree_flatten_with_path(batch_stats)[0]}


def _reference_order(by_key, suffix):
  """Per-key vectors -> one vector in the reference's key order (psmnet_keys.txt)."""
  return np.concatenate([by_key[k] for k in rw.reference_shapes() if k.endswith(suffix)])


def _values_per_channel(model, *args):
  """Reference key prefix of each BatchNorm -> values per channel n it averages in training."""
  seen = {}

  def record(next_fun, call_args, kwargs, context):
    if isinstance(context.module, nn.BatchNorm) and context.method_name == "__call__":
      x = call_args[0]
      # A layer of the feature extractor sees both views as one batch of `groups` groups.
      seen[reference_key(tuple(context.module.path) + ("mean",)).rsplit(".", 1)[0]] = (
          x.size // x.shape[-1] // getattr(context.module, "groups", 1))
    return next_fun(*call_args, **kwargs)

  with nn.intercept_methods(record):
    jax.eval_shape(lambda v, a, b: model.apply(v, a, b, train=True, mutable=["batch_stats"]),
                   *args)
  return seen


# "gpu": the transposed convolutions in the GPU's native form (sljax.kernels.conv3d), which
# converted weights must drive unchanged; None: this machine's default ("fast" on a CPU).
@pytest.mark.parametrize("impl", [None, "gpu"])
def test_train_mode_outputs_and_batch_statistics_match_the_reference(fixture, variables, impl):
  case = CASES["train"]
  model = PSMNet(maxdisp=case.maxdisp, conv_impl=impl)
  args = (variables,) + _inputs(case)
  out, updates = jax.jit(lambda v, a, b: model.apply(v, a, b, train=True,
                                                     mutable=["batch_stats"]))(*args)
  got = np.stack([np.asarray(d) for d in out["disparities"]])
  np.testing.assert_allclose(got, fixture["train/disparities"], rtol=0, atol=DISP_ATOL)
  ours = _by_reference_key(updates["batch_stats"])
  np.testing.assert_allclose(_reference_order(ours, "running_mean"),
                             fixture["train/running_mean"], rtol=0, atol=STATS_ATOL)
  # PyTorch averages the unbiased batch variance (x n / (n - 1)) into running_var. Where n is
  # small the biased one (flax's own BatchNorm) is far off: the SPP branches' 1x1 maps at
  # batch 2 have n = 2, a factor 2. The feature extractor runs on both views at once with
  # statistics per view, so its layers update twice (left, right), as in the reference.
  n_by_layer = _values_per_channel(model, *args)
  assert len(n_by_layer) == sum(k.endswith("running_var") for k in rw.reference_shapes())
  assert 2 in set(n_by_layer.values())
  np.testing.assert_allclose(_reference_order(ours, "running_var"),
                             fixture["train/running_var"], rtol=0, atol=STATS_ATOL)


def test_pad_mode_matches_the_reference_protocol(fixture, variables):
  case = CASES["pad"]
  assert case.height % 16 and case.width % 16
  predictor = inference.make_predictor("psmnet", {"maxdisp": case.maxdisp},
                                       convert_state_dict(rw.state_dict()), mode="pad")
  left, right = rw.images(case)
  got = predictor(left[0], right[0])["disparity"]
  assert got.shape == (case.height, case.width)
  np.testing.assert_allclose(got, fixture["pad/disparity"][0], rtol=0, atol=DISP_ATOL)


def _twin_variables(variables, model, case):
  """The twin's tree: PSMNet's converted variables plus a deterministic SL path."""
  x = jax.ShapeDtypeStruct((1, *case.padded, 3), jnp.float32)
  shapes = jax.eval_shape(lambda a: model.init(jax.random.PRNGKey(0), a, a), x)
  rng = np.random.default_rng(rw.SEED)

  def fill(path, s):
    scale = 0.05 if path[-1].key in ("kernel", "bias", "mean") else 1.0
    return jnp.asarray((1.0 + 0.1 * rng.random(s.shape) if path[-1].key in ("scale", "var") else
                        scale * rng.standard_normal(s.shape)).astype(np.float32))
  sl = {col: jax.tree_util.tree_map_with_path(fill, shapes[col]["sl"]) for col in shapes}
  twin = {col: dict(variables[col], sl=sl[col]) for col in variables}
  # The disparity path is exactly PSMNet's tree (names and shapes).
  assert jax.tree.structure(detach_sl(twin)) == jax.tree.structure(variables)
  return twin


def test_twin_disparity_path_matches_the_reference(fixture, variables):
  """psmnet-mtl with PSMNet's converted weights predicts the reference's disparity (pad mode)."""
  case = CASES["pad"]
  model = PSMNetMTL(maxdisp=case.maxdisp, t=4)
  twin = _twin_variables(variables, model, case)
  predictor = inference.Predictor(ModelConfig.of("psmnet-mtl", maxdisp=case.maxdisp, t=4,
                                                 conv_impl=model.conv_impl), twin)
  left, right = rw.images(case)
  out = predictor(left[0], right[0])
  assert out["patterns"].shape == (case.height, case.width, 4)
  np.testing.assert_allclose(out["disparity"], fixture["pad/disparity"][0], rtol=0,
                             atol=DISP_ATOL)
