"""The jitted training step: one compilation serves every strategy, stl, epr, unc and both
UNets overfit one batch (cg_a and cg_b differ from epr only in weight values); unc's log-sigma
update; the sharded step equals the single-device step (8 forced host devices)."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sljax.losses import weighting as wt
from sljax.nets import ModelConfig, build_model, registry
from sljax.nets.model_config import INIT_COMPILER_OPTIONS, init_variables
from sljax.train import state as st
from sljax.train import step as stp

ROOT = Path(__file__).resolve().parents[1]
H = W = 16
MAXDISP = 16
T = 3
LR = 2e-3
# Tests compile without XLA backend optimisations: compiling dominates, the steps are tiny.
FAST = INIT_COMPILER_OPTIONS


def _batch(b: int = 2) -> dict[str, np.ndarray]:
  """An easy batch to memorise: textured views, constant GT with unknown / out-of-range parts."""
  rng = np.random.default_rng(0)
  left = rng.random((b, H, W, 3)).astype(np.float32)
  disp = np.full((b, H, W), 6.0, np.float32)
  disp[:, :2] = np.inf        # unknown
  disp[:, 2:4] = 40.0         # beyond maxdisp: masked out
  sl = np.zeros((b, H, W, T), np.float32)
  sl[..., 0] = 1.0
  sl[:, :, :3] = np.nan       # projector shadow
  return {"left": left, "right": np.roll(left, -6, axis=2), "disp": disp, "sl": sl,
          "sl_right": sl.copy()}


def _fresh(variables, tx, mesh):
  # create_state shares the variables' buffers and steps donate the state: copy first. Placing
  # it replicated like the step's output keeps one compilation for every call.
  state = st.create_state(jax.tree.map(jnp.copy, variables), tx)
  return jax.device_put(state, stp.shardings(mesh)[0])


def _overfit(step, state, batch, weights, n):
  first = None
  for _ in range(n):
    state, m = step(state, batch, weights)
    m = jax.device_get(m)
    first = first or m
  return state, first, m


@pytest.fixture(scope="module")
def twin():
  model = build_model("psmnet-mtl", maxdisp=MAXDISP, t=T, in_channels=3)
  return model, init_variables(model, 0, H, W, 3)


@pytest.fixture(scope="module")
def mesh():
  return stp.make_mesh()


STEPS = 12  # both task losses fall > 10x within ~10 steps at LR
# cg_a, cg_b and epr differ only in the weights' values, which are inputs of the one compiled
# step: epr's unequal DWA weights overfit for all three, cg_a and cg_b take two steps (their
# loss is checked to be their weighted sum), saving 20 compiled-step runs of the suite.
OVERFIT = ("stl", "epr", "unc")


@pytest.fixture(scope="module")
def twin_runs(twin, mesh):
  """Overfits one batch with one compiled step under every strategy (the strategy is an input)."""
  model, variables = twin
  tx = st.make_optimizer(LR)
  step = stp.make_train_step(model, ModelConfig("psmnet-mtl", 3, MAXDISP, T), disp_loss="l2",
                             tx=tx, mesh=mesh, compiler_options=FAST)
  batch = stp.put_batch({k: v for k, v in _batch().items() if k != "sl_right"}, mesh)
  out = {}
  history = [(0.8, 9.0), (0.5, 8.0)]  # a DWA history giving unequal weights
  for name in wt.STRATEGIES:
    w = jnp.asarray(wt.step_weights(name, history))
    state = _fresh(variables, tx, mesh)
    metrics = []
    for i in range(STEPS if name in OVERFIT else 2):
      state, m = step(state, batch, w)
      metrics.append(jax.device_get(m))
      if i == 0:
        after_one = jax.device_get(state.params["uncertainty"])
    out[name] = (metrics, np.asarray(w), after_one)
  assert step._cache_size() == 1  # one compilation for all five strategies
  return out


@pytest.mark.parametrize("name", wt.STRATEGIES)
def test_twin_step_under_every_strategy(twin_runs, name):
  metrics, w, _ = twin_runs[name]
  first, last = metrics[0], metrics[-1]
  if name in OVERFIT:
    assert last["loss_disp"] * 10 <= first["loss_disp"], (first, last)
  if name == "stl":
    assert last["loss_sl"] > 0.1  # SL path untrained under stl weights
  elif name in OVERFIT:
    assert last["loss_sl"] * 10 <= first["loss_sl"], (first, last)
  else:
    assert last["loss_disp"] < first["loss_disp"] and last["loss_sl"] < first["loss_sl"]
  if name != "unc":
    np.testing.assert_allclose([last["w_sl"], last["w_disp"]], w[:2])
    np.testing.assert_allclose(first["loss"], w[0] * first["loss_sl"] + w[1] * first["loss_disp"],
                               rtol=1e-5)
    assert last["sigma_sl"] == 1.0 and last["sigma_disp"] == 1.0  # zero gradient: untouched
  assert np.isfinite(last["grad_norm"]) and last["grad_norm"] > 0


def test_twin_unc_weights_and_log_sigma_gradient(twin_runs):
  metrics, _, after_one = twin_runs["unc"]
  m0 = metrics[0]
  # Initial sigmas 1: weights 0.5 / 2 and 1 / 2, total = 0.25 L_sl + 0.5 L_disp + 0.
  np.testing.assert_allclose([m0["sigma_sl"], m0["sigma_disp"], m0["w_sl"], m0["w_disp"]],
                             [1, 1, 0.25, 0.5], rtol=1e-6)
  np.testing.assert_allclose(m0["loss"], 0.25 * m0["loss_sl"] + 0.5 * m0["loss_disp"], rtol=1e-5)
  # Adam's first update is -lr * sign(grad); d total / d log sigma = -2 w L + 1 (hand-derived).
  g_sl = -2 * 0.25 * m0["loss_sl"] + 1
  g_d = -2 * 0.5 * m0["loss_disp"] + 1
  np.testing.assert_allclose([after_one["log_sigma_sl"], after_one["log_sigma_disp"]],
                             [-LR * np.sign(g_sl), -LR * np.sign(g_d)], rtol=1e-3)
  last = metrics[-1]
  sig = np.exp([np.log(last["sigma_sl"]), np.log(last["sigma_disp"])])
  np.testing.assert_allclose([last["w_sl"], last["w_disp"]], [0.25 / sig[0]**2, 0.5 / sig[1]**2],
                             rtol=1e-5)


@pytest.mark.parametrize("net", ["unet-sl", "unet-disp"])
def test_unets_overfit_one_batch(net, mesh):
  model = build_model(net, t=T, in_channels=3, depth=2, base_width=8)
  variables = init_variables(model, 0, H, W, 3)
  tx = st.make_optimizer(2e-2)
  config = ModelConfig(net, 3, MAXDISP, T, (("base_width", 8), ("depth", 2)))
  step = stp.make_train_step(model, config, disp_loss="l2", tx=tx, mesh=mesh,
                             compiler_options=FAST)
  batch = stp.put_batch({k: v for k, v in _batch().items() if k in registry.spec(net).parts}, mesh)
  w = jnp.asarray([1.0, 0.0, 0.0] if net == "unet-sl" else [0.0, 1.0, 0.0])
  _, first, last = _overfit(step, _fresh(variables, tx, mesh), batch, w, 60)
  key = "loss_sl" if net == "unet-sl" else "loss_disp"
  assert last[key] * 10 <= first[key], (first, last)
  assert last["loss"] == pytest.approx(last[key])


_SHARDED = textwrap.dedent("""
    import jax, jax.numpy as jnp, numpy as np
    assert jax.device_count() == 8, jax.devices()
    from sljax.nets import ModelConfig, build_model
    from sljax.nets.model_config import INIT_COMPILER_OPTIONS, init_variables
    from sljax.train import state as st, step as stp
    model = build_model("unet-disp", in_channels=3, depth=2, base_width=8)
    v = init_variables(model, 0, 32, 32, 3)
    tx = st.make_optimizer(1e-3)
    rng = np.random.default_rng(1)
    left = rng.random((8, 32, 32, 3)).astype(np.float32)
    disp = (rng.random((8, 32, 32)) * 20).astype(np.float32)
    disp[:, :3] = np.inf
    host = {"left": left, "right": np.roll(left, -2, 2), "disp": disp}
    res = []
    for devices in (jax.devices()[:1], jax.devices()):
      mesh = stp.make_mesh(devices)
      step = stp.make_train_step(model, ModelConfig("unet-disp", 3, 16), disp_loss="l2", tx=tx,
                                 mesh=mesh, compiler_options=INIT_COMPILER_OPTIONS)
      s = jax.device_put(st.create_state(jax.tree.map(jnp.copy, v), tx),
                         stp.shardings(mesh)[0])
      b = stp.put_batch(host, mesh)
      assert len(b["left"].sharding.device_set) == len(devices)
      for _ in range(2):
        s, m = step(s, b, jnp.asarray([0.0, 1.0, 0.0]))
      res.append(jax.device_get((s.params, s.batch_stats, m)))
    (p1, b1, m1), (p8, b8, m8) = res
    for a, b in zip(jax.tree.leaves((p1, b1)), jax.tree.leaves((p8, b8))):
      np.testing.assert_allclose(a, b, rtol=2e-4, atol=2e-6)
    for k in m1:
      np.testing.assert_allclose(m1[k], m8[k], rtol=2e-4, atol=1e-6)
    print("SHARDED_OK", len(jax.tree.leaves(p1)), float(m1["loss"]))
""")


def test_sharded_step_equals_single_device():
  flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=8"
  env = dict(os.environ, XLA_FLAGS=flags.strip(), JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT))
  r = subprocess.run([sys.executable, "-c", _SHARDED], env=env, cwd=ROOT, capture_output=True,
                     text=True, timeout=600)
  assert r.returncode == 0 and "SHARDED_OK" in r.stdout, r.stdout + r.stderr[-3000:]


_HOST_INIT = textwrap.dedent("""
    import tempfile
    from pathlib import Path
    import jax, numpy as np
    from sljax.nets import build_model
    from sljax.nets import model_config as mc
    from sljax.runtime import kept_programs
    assert jax.device_count() == 2, jax.devices()
    model = build_model("unet-disp", in_channels=3, depth=2, base_width=8)
    plain = jax.device_get(mc.init_variables(model, 3, 32, 32, 3))
    ran_on = []
    real = kept_programs.Program.__call__
    def spy(self, *args):
      ran_on.append((str(self.device), sorted(d.id for a in args for d in a.devices())))
      return real(self, *args)
    kept_programs.Program.__call__ = spy
    kept_programs.enable(Path(tempfile.mkdtemp()))
    origins = []
    for _ in range(2):  # compiled and kept, then loaded by a fresh program
      mc._init_fn.cache_clear()
      with jax.default_device(jax.devices()[1]):
        v = mc.init_variables(model, 3, 32, 32, 3)
      origins.append(mc._init_fn(model, 32, 32, 3, jax.devices()[0]).origin)
      leaves = jax.tree.leaves(v)
      assert all(a.devices() == {jax.devices()[1]} for a in leaves), leaves[0].devices()
      assert jax.tree.structure(v) == jax.tree.structure(plain)
      for a, b in zip(leaves, jax.tree.leaves(plain)):
        np.testing.assert_array_equal(np.asarray(a), b)
    assert ran_on == [("cpu:0", [0])] * 2 and origins == ["compiled", "loaded"], (ran_on, origins)
    print("HOST_INIT_OK")
""")


def test_initial_values_come_from_the_host_cpu_and_land_on_the_default_device():
  """Where the default device is not the host's CPU (a GPU; here a second CPU device stands in
  for it), the init program runs on the host (a GPU compiles its hundreds of small random-value
  fusions kernel by kernel), the variables arrive on the default device bit for bit as a plain
  init gives them, and a kept init program loads for the host in the next process."""
  flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2"
  env = dict(os.environ, XLA_FLAGS=flags.strip(), JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT),
             SLJAX_PROGRAM_CACHE="on")
  r = subprocess.run([sys.executable, "-c", _HOST_INIT], env=env, cwd=ROOT, capture_output=True,
                     text=True, timeout=600)
  assert r.returncode == 0 and "HOST_INIT_OK" in r.stdout, r.stdout + r.stderr[-3000:]


def test_grad_block_values_reach_the_kernel_gradients(twin, mesh):
  """The step traces its gradients inside grad_blocks(grad_block_values): one-plane kernel
  gradients put loops into the program that the layers' own blocks do not have, and the
  gradients stay the same to float rounding (only the sums' order changes; plain SGD, so the
  update is the gradient: Adam's first step would magnify rounding in near-zero components)."""
  import optax
  model, variables = twin
  tx = optax.sgd(1.0)
  config = ModelConfig("psmnet-mtl", 3, MAXDISP, T)
  batch = stp.put_batch({k: v for k, v in _batch().items() if k != "sl_right"}, mesh)
  w = jnp.asarray(wt.step_weights("epr", [(0.8, 9.0), (0.5, 8.0)]))
  runs = []
  for values in (None, 1):
    step = stp.make_train_step(model, config, disp_loss="l2", tx=tx, mesh=mesh,
                               compiler_options=FAST, grad_block_values=values)
    state = _fresh(variables, tx, mesh)
    before = jax.device_get(state.params)  # the step donates the state
    loops = step.lower(state, batch, w).as_text().count("stablehlo.while")
    state, m = step(state, batch, w)
    grads = jax.tree.map(lambda a, b: a - b, before, jax.device_get(state.params))
    runs.append((loops, jax.device_get(m), grads))
  (loops, m0, g0), (more, m1, g1) = runs
  assert more > loops
  for key in ("loss", "loss_sl", "loss_disp", "grad_norm"):
    np.testing.assert_allclose(m1[key], m0[key], rtol=1e-5)
  for a, b in zip(jax.tree.leaves(g1), jax.tree.leaves(g0)):
    np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-5 * max(np.abs(b).max(), 1e-6))
