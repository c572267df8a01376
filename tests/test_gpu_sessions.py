"""The GPU session scripts' plumbing (benchmarks/gpu_*_session.sh, gpu_common.sh) on any machine.

Python is replaced by a stub that notes its arguments, so these tests check what each script
runs, in which order, what it logs and which parts the deadline skips: not the benchmarks
themselves (their own tests and `dry` runs do that).
"""

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _session(tmp_path, script, *args, deadline=None, reference=False, **env_extra):
    """Run one session script with a stub Python; (exit code, session.log, stub calls, stderr).
    The stub also notes each call's XLA_FLAGS in flags.txt beside it."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    stub = tmp_path / "python"
    calls = tmp_path / "calls.txt"
    stub.write_text(f'#!/bin/sh\necho "$*" >> {calls}\necho "${{XLA_FLAGS:-}}" >> '
                    f'{tmp_path / "flags.txt"}\necho "| stub |"\n')
    stub.chmod(0o755)
    out = tmp_path / "out"
    env = {k: v for k, v in os.environ.items()
           if k not in ("DEADLINE", "REFERENCE", "OUT", "PARTS", "XLA_FLAGS")}
    env.update(OUT=str(out), PYTHON=str(stub), **env_extra)
    if deadline is not None:
        env["DEADLINE"] = str(deadline)
    if reference:
        ref = tmp_path / "PSMNet"
        (ref / "models").mkdir(parents=True)
        (ref / "models" / "stackhourglass.py").write_text("")
        env["REFERENCE"] = str(ref)
    else:
        env["REFERENCE"] = str(tmp_path / "no-such-checkout")
    proc = subprocess.run(["bash", str(ROOT / "benchmarks" / script), *args], env=env,
                          capture_output=True, text=True, timeout=120)
    log = (out / "session.log").read_text() if (out / "session.log").exists() else ""
    ran = calls.read_text().splitlines() if calls.exists() else []
    return proc.returncode, log, ran, proc.stderr


def _benchmarks(calls):
    """The benchmark scripts the stub was asked to run, in order."""
    return [c.split()[0] for c in calls if c.startswith("benchmarks/")]


def test_issue42_session_runs_its_three_parts_in_order_with_the_reference(tmp_path):
    rc, log, calls, err = _session(tmp_path, "gpu_issue42_session.sh", "dry", deadline=300,
                                   reference=True)
    assert rc == 0, err
    assert _benchmarks(calls) == ["benchmarks/bench_compile.py", "benchmarks/profile_step.py",
                                  "benchmarks/bench_fullres.py"]
    fullres = next(c for c in calls if c.startswith("benchmarks/bench_fullres.py"))
    assert f"--reference {tmp_path / 'PSMNet'}" in fullres
    assert "--preset quick" in calls[[c.split()[0] for c in calls].index(
        "benchmarks/bench_compile.py")]  # the dry run's tiny sizes
    assert "gpu_issue42_session (dry run); reference: --reference" in log
    assert log.count("exit code 0") == 3 and log.rstrip().endswith("done")


def test_issue42_session_skips_what_the_deadline_leaves_no_time_for(tmp_path):
    rc, log, calls, err = _session(tmp_path, "gpu_issue42_session.sh", "dry", deadline=1)
    assert rc == 0, err
    assert _benchmarks(calls) == ["benchmarks/bench_compile.py"]
    assert "2. skipped: 1 s left" in log and "3. skipped: 1 s left" in log
    assert "reference: none (no " in log


def test_issue49_session_runs_its_parts_in_order_each_with_its_flags(tmp_path):
    rc, log, calls, err = _session(tmp_path, "gpu_issue49_session.sh", "dry", deadline=900,
                                   reference=True)
    assert rc == 0, err
    assert _benchmarks(calls) == ["benchmarks/bench_compile.py", "benchmarks/bench_gpu.py",
                                  "benchmarks/bench_fullres.py", "benchmarks/profile_step.py",
                                  "benchmarks/bench_gpu.py", "benchmarks/bench_compile.py"]
    work = [c for c in calls if c.startswith("benchmarks/")]
    flags = [f for c, f in zip(calls, (tmp_path / "flags.txt").read_text().splitlines())
             if c.startswith("benchmarks/")]
    step, nhwc = work[1], work[4]
    assert "--precisions fp32,bf16" in step and f"--reference {tmp_path / 'PSMNet'}" in step
    assert "--precisions fp32 " in nhwc and "--reference" not in nhwc  # sljax alone
    assert "--kernels analytic,indexed,nchwToNhwc" in work[3]
    assert [f.split() for f in flags] == [[], [], [], [], ["--xla_gpu_force_conv_nhwc=true"],
                                          ["--xla_gpu_autotune_level=0"]]
    assert log.count("exit code 0") == 6 and log.rstrip().endswith("done")


def test_issue49_session_runs_the_parts_asked_for_while_time_is_left(tmp_path):
    rc, log, calls, err = _session(tmp_path, "gpu_issue49_session.sh", "dry",
                                   PARTS="kernels,autotune")
    assert rc == 0, err
    assert _benchmarks(calls) == ["benchmarks/profile_step.py", "benchmarks/bench_compile.py"]
    rc, log, calls, err = _session(tmp_path / "late", "gpu_issue49_session.sh", "dry",
                                   deadline=1)
    assert rc == 0, err
    assert _benchmarks(calls) == ["benchmarks/bench_compile.py"]  # the first step always runs
    for name in ("step", "fullres", "kernels", "nhwc", "autotune"):
        assert f"{name}: skipped, 1 s left" in log


def test_convT_session_passes_its_deadline_on_and_skips_the_crop_without_time(tmp_path):
    rc, log, calls, err = _session(tmp_path, "gpu_convT_session.sh", "dry", deadline=1)
    assert rc == 0, err
    assert _benchmarks(calls) == ["benchmarks/bench_convT.py", "benchmarks/bench_gpu.py"]
    assert "--deadline -4" in calls[-1]  # one second left, less the five kept for the log
    assert "3. skipped" in log
    rc, log, calls, err = _session(tmp_path / "long", "gpu_convT_session.sh", "dry", deadline=900)
    assert rc == 0, err
    assert _benchmarks(calls) == ["benchmarks/bench_convT.py", "benchmarks/bench_gpu.py",
                                  "benchmarks/bench_gpu.py"]


@pytest.mark.parametrize("part, runs", [
    ("suite", ["-m pip", "-m pytest"]),
    ("speed", ["benchmarks/bench_gpu.py"]),
    ("step", ["benchmarks/bench_train.py"] * 4),
])
def test_gpu_session_parts(tmp_path, part, runs):
    rc, log, calls, err = _session(tmp_path, "gpu_session.sh", part, "dry", reference=True)
    assert rc == 0, err
    work = [c for c in calls if not c.startswith("-c ")]  # the header's version lines
    assert len(work) == len(runs) and all(c.startswith(r) for c, r in zip(work, runs))
    assert f"gpu_session part {part} (dry run);" in log and log.rstrip().endswith("done")
    if part == "speed":
        assert f"--reference {tmp_path / 'PSMNet'}" in work[0]


def test_gpu_session_refuses_an_unknown_part(tmp_path):
    rc, log, calls, err = _session(tmp_path, "gpu_session.sh", "fast")
    assert rc == 2 and "usage: bash benchmarks/gpu_session.sh suite|speed|step" in err
    assert calls == []
