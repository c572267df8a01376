"""The GPU plan's own arithmetic, checked on the CPU before any GPU session: the agreement
summary against hand-computed differences, and where an accelerator's records go."""

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
