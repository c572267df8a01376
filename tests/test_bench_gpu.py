"""The GPU plan's own arithmetic, checked on the CPU before any GPU session: the agreement
summary against hand-computed differences, and where an accelerator's records go."""

import json
import sys
from pathlib import Path

import numpy as np

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
