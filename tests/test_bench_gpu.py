"""The GPU plan's own arithmetic and plumbing, checked on the CPU before any GPU session: the
agreement summary against hand-computed differences, where an accelerator's records go, and the
training-step benchmark's parent (canned children) and reference child (a stand-in checkout)."""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_gpu  # noqa: E402  (after the path)
import common  # noqa: E402

CPU = {"vendor": "AMD", "model_name": "AMD EPYC", "family": 25, "model": 17, "isa": ["AVX2"],
       "cores": 2}


def test_agreement_by_hand():
  ref = np.array([[1.0, 2.0], [3.0, 4.0]], np.float32)
  got = ref + np.array([[0.0, 5e-4], [2e-3, -0.25]], np.float32)
  a = bench_gpu.agreement(got, ref)
  assert np.isclose(a["max_px"], 0.25, atol=1e-6)
  assert np.isclose(a["mean_px"], (0 + 5e-4 + 2e-3 + 0.25) / 4, atol=1e-6)
  assert a["over_1e-3_pct"] == 50.0  # 2e-3 and 0.25 exceed the reference test's 1e-3 px


def test_records_of_an_accelerator_are_named_by_it(monkeypatch):
  monkeypatch.setattr(common, "cpu_key", lambda cpu: "amd-epyc-f25-m17-avx512")
  assert common.records_key(CPU, "cpu", "cpu") == "amd-epyc-f25-m17-avx512"
  assert common.records_key(CPU, "gpu", "NVIDIA H100 80GB HBM3") == "gpu-nvidia-h100-80gb-hbm3"
  assert common.records_key(CPU, "cuda", "NVIDIA H200") == "cuda-nvidia-h200"


def test_records_table_of_an_accelerator_by_hand():
  import records  # noqa: E402  (benchmarks/ is on the path above)
  entry = {"time": "2026-11-25T00:42:06+00:00", "benchmark": "bench_gpu", "cpu": CPU,
           "backend": "gpu", "machine": "Xeon; 1 x NVIDIA H100 80GB HBM3 (gpu)", "commit": "c0ffee",
           "loadavg_1min": 4.0,
           "rows": [{"table": "agreement", "model": "psmnet", "size": 256, "maxdisp": 96,
                     "precision": "default", "max_px": 23.1, "mean_px": 0.0252,
                     "over_1e-3_pct": 18.014},
                    {"table": "models", "model": "psmnet", "mode": "fwd", "size": 256,
                     "batch": 4, "sljax_default_s": 0.0127, "sljax_highest_s": 0.0281,
                     "torch_fp32_s": 0.046, "torch_tf32_s": 0.0412, "torch_side": "reference"},
                    {"table": "models", "model": "unet-sl", "mode": "fwd", "size": 256,
                     "batch": 4, "sljax_default_s": 0.0019, "sljax_highest_s": 0.0046}]}
  assert records.headlines(entry) == [
      ("psmnet forward vs CPU, 256px, default precision",
       "max 23 px, mean 0.025 px, 18.01% of pixels over 1e-3 px"),
      ("psmnet fwd, 256px b4 (ms a call)",
       "default 12.7 ms, highest 28.1 ms; torch (reference) fp32 46.0 ms, TF32 41.2 ms"),
      ("unet-sl fwd, 256px b4 (ms a call)", "default 1.9 ms, highest 4.6 ms")]
  text = records.table({"gpu-nvidia-h100-80gb-hbm3": [entry]})
  assert "**Xeon; 1 x NVIDIA H100 80GB HBM3 (gpu)** (`gpu-nvidia-h100-80gb-hbm3`)" in text
  assert "| 2026-11-25 | c0ffee | 4.0 | measured |" in text


def test_a_figure_under_other_xla_flags_is_recorded_and_labelled_apart(tmp_path, monkeypatch):
  import records  # noqa: E402  (benchmarks/ is on the path above)
  monkeypatch.setattr(common, "RESULTS", tmp_path)
  row = {"what": "(a) compiled step", "steps_per_s": 2.0, "samples_per_s": 24.0, "ratio_to_a": 1.0}
  extra = {"preset": "paper", "net": "psmnet", "batch": 12, "precision": "fp32"}
  monkeypatch.setenv("XLA_FLAGS", " --xla_gpu_deterministic_ops=true ")
  path = common.record("bench_train", [row], quiet=True, **extra)
  monkeypatch.setenv("XLA_FLAGS", "")
  common.record("bench_train", [row], quiet=True, **extra)
  flagged, plain = (json.loads(line) for line in path.read_text().splitlines())
  assert flagged["xla_flags"] == "--xla_gpu_deterministic_ops=true" and "xla_flags" not in plain
  assert records.headlines(flagged) == [
      ("train loop paper psmnet [--xla_gpu_deterministic_ops=true]: (a) compiled step",
       "24.00 samples/s (1.000x step)")]
  assert records.headlines(plain)[0][0] == "train loop paper psmnet: (a) compiled step"


def test_step_shapes_and_inputs():
  assert bench_gpu.step_shape("paper") == (256, 256, 96, 12)
  assert bench_gpu.step_shape("crop") == (256, 512, 192, 8)
  assert bench_gpu.step_shape("64x128x16x3") == (64, 128, 16, 3)
  a, b = bench_gpu.step_inputs(8, 16, 32, 2, patterns=4), bench_gpu.step_inputs(8, 16, 32, 2)
  assert {k: v.shape for k, v in a.items()} == {"left": (2, 8, 16, 3), "right": (2, 8, 16, 3),
                                                "disp": (2, 8, 16), "sl": (2, 8, 16, 4)}
  assert all(v.dtype == np.float32 for v in a.values()) and set(np.unique(a["sl"])) == {0, 1}
  assert 0 <= a["disp"].min() and (a["disp"] >= 32).any() and a["disp"].max() < 32 * 1.1
  assert np.array_equal(a["left"], b["left"])  # every child sees the same arrays


def test_timed_steps_by_hand():
  calls, syncs = [], []
  setup = time.perf_counter() - 5.0
  out = bench_gpu.timed_steps(lambda: calls.append(1), lambda: syncs.append(len(calls)),
                              warmup=3, steps=4, t0=0.0, setup=setup)
  assert len(calls) == 7 and syncs == [1, 3, 7]  # the first step, the warm-up, the timed
  assert out["steps"] == 4 and out["warmup"] == 3 and out["step_s"] >= 0
  assert 5.0 <= out["setup_s"] < 6.0  # up to the first step only
  assert out["first_step_s"] > 1e9  # since t0 (the epoch here): the launch in a child


# A parent whose children are canned: what it launches, in which order, with which
# environment, and what it prints and records. Run in a fresh process, to check as well that
# the parent never starts jax's backend (on a GPU that would take memory from the children).
PARENT = r"""
import json, os, sys, types
sys.path.insert(0, sys.argv[1])
import bench_gpu
sys.modules.setdefault("torch", types.ModuleType("torch"))  # the parent only asks if it is there
launched = []

def fake_run_child(script, args, env=None, timeout=None, check=True):
  a = dict(zip(args[::2], args[1::2]))
  launched.append({"side": a["--child"], "net": a["--net"], "impl": a["--impl"],
                   "cache": env["SLJAX_COMPILE_CACHE"], "timeout": timeout, "check": check})
  if a["--child"] == "reference":
    return {"first_step_s": 14.0, "step_s": 0.4, "impl": "cudnn.benchmark",
            "peak_gib": 25.3}, 900.0
  if a["--impl"] == "broken":
    return None, 100.0
  second = sum(1 for l in launched if l["impl"] == a["--impl"]) == 2
  return {"first_step_s": 5.0 if second else 60.0, "step_s": {"gpu": 0.2, "lax": 0.6}.get(
              a["--impl"], 0.3), "impl": a["--impl"], "cache_hits": 2 if second else 0,
          "backend": "gpu", "device_kind": "NVIDIA H200",
          "machine": "Xeon; 1 x NVIDIA H200"}, 2048.0

bench_gpu.run_child = fake_run_child
args = bench_gpu.argparse.Namespace(
    shapes="paper", precisions="fp32,bf16", impls="gpu,lax,broken", twin="auto",
    warm_start=True, cache=None, reference=sys.argv[2], steps=20, warmup=4, profile_top=0,
    deadline=None)
bench_gpu.step_part(args)
from jax._src import xla_bridge
print(json.dumps({"launched": launched, "backends": list(xla_bridge._backends)}))
"""


def test_step_parent_launches_one_child_per_side_and_records_ratios(tmp_path):
  bench = Path(__file__).resolve().parents[1] / "benchmarks"
  env = dict(os.environ, SLJAX_BENCH_RESULTS=str(tmp_path / "records"))
  out = subprocess.run([sys.executable, "-c", PARENT, str(bench), str(tmp_path)], env=env,
                       capture_output=True, text=True, check=True).stdout
  result = json.loads(out.strip().splitlines()[-1])
  assert result["backends"] == []  # the parent never started jax's backend
  sides = [(c["side"], c["net"], c["impl"]) for c in result["launched"]]
  per_precision = [("reference", "psmnet", "-"), ("sljax", "psmnet", "gpu"),
                   ("sljax", "psmnet", "lax"), ("sljax", "psmnet", "broken"),
                   ("sljax", "psmnet-mtl", "auto")]
  # The reference first (the ratios need it); the first sljax child again once, right after
  # itself (its programs then come from the cache: the warm start).
  assert sides == per_precision[:2] + [("sljax", "psmnet", "gpu")] + per_precision[2:] + \
      per_precision
  caches = {c["cache"] for c in result["launched"]}
  assert len(caches) == 1 and "sljax-step-cache-" in caches.pop()  # one fresh folder
  assert not any(c["check"] for c in result["launched"])  # a failed child is a row, not an end
  assert "| paper 256x256 d96 b12 | fp32 | sljax psmnet gpu | 60.0 | 0.200 | 60 | 2.00 | 0.50x |" \
      in out
  assert "sljax psmnet gpu (second run: warm cache) [2 programs from the cache] | 5.0 |" in out
  assert "| paper | bf16 | sljax psmnet broken | failed (see its output above) |" in out
  records = (tmp_path / "records" / "gpu-nvidia-h200.jsonl").read_text().splitlines()
  assert len(records) == 2  # one per shape and precision, named by the children's device
  entry = json.loads(records[0])
  assert entry["machine"] == "Xeon; 1 x NVIDIA H200" and entry["backend"] == "gpu"
  rows = {(r["impl"], r["run"]): r for r in entry["rows"] if r["side"] == "sljax"}
  assert rows[("lax", "first")]["ratio"] == pytest.approx(1.5)
  assert rows[("broken", "first")]["failed"] and ("gpu", "second") in rows
  ref = next(r for r in entry["rows"] if r["side"] == "reference")
  assert ref["peak_gib"] == 25.3 and rows[("gpu", "first")]["peak_gib"] == 2.0  # RSS: MiB/1024
  import records as rec  # noqa: E402  (benchmarks/ is on the path above)
  heads = dict(rec.headlines(entry))
  assert heads["training step sljax psmnet gpu, 256x256 maxdisp 96 b12 fp32"] == \
      "200 ms (0.50x reference), first step 60 s, peak 2.0 GiB"
  assert heads["training step reference, 256x256 maxdisp 96 b12 fp32"] == \
      "400 ms, first step 14 s, peak 25.3 GiB"


REFERENCE_STANDIN = """
import torch
from torch import nn


class PSMNet(nn.Module):
  # JiaRenChang/PSMNet's interface: three [B, 1, H, W] predictions in training.
  def __init__(self, maxdisp):
    super().__init__()
    self.maxdisp, self.conv = maxdisp, nn.Conv2d(6, 3, 3, padding=1)

  def forward(self, left, right):
    d = torch.sigmoid(self.conv(torch.cat([left, right], 1))) * self.maxdisp
    return (d[:, :1], d[:, 1:2], d[:, 2:]) if self.training else d[:, 2:]
"""


def test_reference_child_trains_a_stand_in_of_the_reference(tmp_path):
  """The reference child end to end on a stand-in checkout (models/stackhourglass.py with
  the reference's interface), under bf16 autocast (fp32 is the same path without it): its
  JSON line, the loss of the reference's main.py, Adam."""
  pytest.importorskip("torch")
  (tmp_path / "models").mkdir()
  (tmp_path / "models" / "stackhourglass.py").write_text(REFERENCE_STANDIN)
  script = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_gpu.py"
  out = subprocess.run(
      [sys.executable, str(script), "--child", "reference", "--net", "psmnet", "--impl", "-",
       "--shape", "16x24x16x2", "--precision", "bf16", "--steps", "2", "--warmup", "1",
       "--t0", repr(time.time()), "--reference", str(tmp_path)],
      capture_output=True, text=True, check=True).stdout
  res = json.loads(out.strip().splitlines()[-1])
  assert res["steps"] == 2 and res["warmup"] == 1 and res["step_s"] > 0
  assert 0 < res["first_call_s"] <= res["first_step_s"] < 120
  assert np.isfinite(res["loss"]) and res["loss"] > 0


def test_records_of_the_transposed_conv_benchmark_by_hand():
  import records  # noqa: E402  (benchmarks/ is on the path above)
  entry = {"benchmark": "bench_convT", "rows": [
      {"table": "convT", "shape": "paper", "layer": "conv6", "form": "gpu", "dtype": "float32",
       "x": [12, 12, 32, 32, 64], "cout": 32, "fwd_ms": 0.41, "dk_ms": 1.5, "both_ms": 2.5,
       "both_over_lax": 0.05}]}
  assert records.headlines(entry) == [("transposed conv conv6 12x32x32x64 b12 gpu float32",
                                       "fwd 0.41 ms, dk 1.50 ms, both 2.50 ms (0.05x lax)")]


def test_device_kernels_of_a_gpu_trace_by_hand():
  """A trace as XProf writes a GPU's (a process per device, a thread per stream and derived
  lines of XLA operations and modules): kernels summed by name from the stream lines only."""
  import profile_step  # noqa: E402  (benchmarks/ is on the path above)
  meta = lambda kind, pid, tid, name: {"ph": "M", "name": kind, "pid": pid, "tid": tid,
                                       "args": {"name": name}}
  fallback = "sm80_xmma_fprop_implicit_gemm_indexed_wo_smem_tf32f32"
  events = [meta("process_name", 1, None, "/host:CPU"), meta("thread_name", 1, 7, "python"),
            meta("process_name", 2, None, "/device:GPU:0"),
            meta("thread_name", 2, 10, "Stream #13(Compute)"),
            meta("thread_name", 2, 11, "XLA Ops"), meta("thread_name", 2, 12, "XLA Modules"),
            {"ph": "X", "pid": 1, "tid": 7, "name": "PjitFunction(step)", "ts": 0, "dur": 900},
            {"ph": "X", "pid": 2, "tid": 12, "name": "jit_step", "ts": 0, "dur": 800},
            {"ph": "X", "pid": 2, "tid": 11, "name": "cudnn-conv.3", "ts": 0, "dur": 500}]
  for i, (name, dur, op) in enumerate([(fallback, 450, "cudnn-conv.3"),
                                        ("sm90_xmma_wgrad", 100, None),
                                        (fallback, 150, "cudnn-conv.9")]):
    events.append({"ph": "X", "pid": 2, "tid": 10, "name": name, "ts": 10 * i, "dur": dur,
                   "args": {"hlo_op": op} if op else {}})
  rows = profile_step.kernel_rows(events, calls=3, top=5)
  # the fallback kernel ran for two layers: the row names the one it spent most time in
  assert [(r["kernel"], r["where"], r["hlo_op"]) for r in rows] == [
      (fallback, "device", "cudnn-conv.3 (+1 more)"), ("sm90_xmma_wgrad", "device", "")]
  assert rows[0]["ms_per_call"] == pytest.approx(0.2)  # 600 us over 3 calls
  assert rows[0]["share"] == pytest.approx(600 / 700)
