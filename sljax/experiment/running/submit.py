"""`sljax experiment submit`: N `experiment run` workers on one OUT through submitit (the
[cluster] extra): a SLURM job array, or local processes (one GPU each where there are several).

Each job runs one worker (sljax.experiment.running.workers): the workers divide the grid's cells between
them. On SLURM's warning signal (SIGUSR2, `--signal=USR2@120` in the job script that submitit
writes) a worker stops training at a step (sljax.experiment.running.runner: the second fetch of the
step metrics after the signal), releases its cell's claim (the cell's checkpoints stay) and
hands the signal to submitit, which calls WorkerJob.checkpoint and requeues the job; the
requeued worker, or any other, resumes the cell from its last checkpoint exactly. Not tried on
a real SLURM cluster here: the tests submit to stand-ins for sbatch and srun and check the job
script submitit gives them, and run the local path end to end.
"""

import dataclasses
import os
import re
import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sljax.errors import SljaxError, require
from sljax.experiment import records
from sljax.experiment.design.cells import Plan
from sljax.experiment.running import workers

LOGS_DIR = "submitit"   # OUT/submitit/: submitit's job files and each worker's log
LOG_LEVEL = "SUBMITIT_LOG_LEVEL"


@dataclasses.dataclass(frozen=True)
class Resources:
  """What each worker asks of SLURM (or of this machine, --local)."""
  workers: int
  partition: str | None = None
  gpus_per_worker: int | None = None   # None: 1 where the machine (or cluster) has GPUs
  cpus_per_worker: int | None = None
  minutes: int = 24 * 60
  account: str | None = None
  sbatch: tuple[tuple[str, str], ...] = ()   # other sbatch options: (name, value)
  setup: tuple[str, ...] = ()                # shell lines before the worker (module load ...)
  signal_delay_s: int = 120                  # SLURM's warning before the time limit

  def __post_init__(self):
    require(self.workers >= 1, f"--workers {self.workers}: at least 1")


def parse_minutes(text: str) -> int:
  """sbatch's --time formats (MIN, MIN:SEC, H:MM:SS, D-H, D-H:MM, D-H:MM:SS) in minutes."""
  m = re.fullmatch(r"(?:(\d+)-)?(\d+)(?::(\d+))?(?::(\d+))?", text.strip())
  require(m is not None, f"--time {text}: use minutes, H:MM:SS or D-H:MM:SS (as sbatch)")
  days, a, b, c = (int(g) if g else None for g in m.groups())
  if days is not None:   # D-H[:MM[:SS]]
    minutes = days * 1440 + a * 60 + (b or 0) + ((c or 0) + 59) // 60
  elif c is not None:    # H:MM:SS
    minutes = a * 60 + b + (c + 59) // 60
  else:                  # MIN or MIN:SEC
    minutes = a + ((b or 0) + 59) // 60
  require(minutes >= 1, f"--time {text}: at least a minute")
  return minutes


def parse_sbatch(options: list[str]) -> tuple[tuple[str, str], ...]:
  """--sbatch NAME=VALUE (or a flag NAME) options as (name, value) pairs."""
  pairs = []
  for opt in options:
    name, _, value = opt.lstrip("-").partition("=")
    require(re.fullmatch(r"[a-z][a-z0-9-]*", name) is not None,
            f"--sbatch {opt}: expected NAME=VALUE with an sbatch option's long name, e.g. "
            "qos=preemptible or constraint=a100")
    pairs.append((name, value))
  return tuple(pairs)


def slurm_parameters(res: Resources, name: str) -> dict[str, Any]:
  """The submitit SlurmExecutor parameters of the job array (`update_parameters`)."""
  extra: dict[str, Any] = {"requeue": True}  # preempted jobs come back (PreemptMode=REQUEUE)
  for key, value in res.sbatch:
    extra[key.replace("-", "_")] = value if value != "" else True
  params = {"job_name": name, "time": res.minutes, "nodes": 1, "ntasks_per_node": 1,
            "gpus_per_node": 1 if res.gpus_per_worker is None else res.gpus_per_worker,
            "array_parallelism": res.workers, "signal_delay_s": res.signal_delay_s,
            "additional_parameters": extra, "setup": list(res.setup)}
  for key, value in (("partition", res.partition), ("cpus_per_task", res.cpus_per_worker),
                     ("account", res.account)):
    if value is not None:
      params[key] = value
  return params


def local_gpus() -> list[str]:
  """This machine's GPUs as CUDA_VISIBLE_DEVICES names them (that variable's list when set,
  else nvidia-smi's), [] without any."""
  visible = os.environ.get("CUDA_VISIBLE_DEVICES")
  if visible is not None:
    return [d for d in visible.split(",") if d.strip() and d.strip() != "-1"]
  if shutil.which("nvidia-smi") is None:
    return []
  try:
    listing = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=30,
                             check=True).stdout
  except (OSError, subprocess.SubprocessError):
    return []
  return [str(k) for k, line in enumerate(listing.splitlines()) if line.startswith("GPU ")]


class WorkerJob:
  """One `sljax experiment run` worker as a submitit job: entry(argv) is the command line's
  entry point, sljax.cli.main (pickled by reference: the nodes import the same sljax).
  Checkpointable: on SLURM's warning the worker has already stopped at a step and released
  its cell (workers.Stop) when submitit calls `checkpoint`, which asks for the same worker
  again; the requeued job claims whatever cell is free, its own among them."""

  def __init__(self, argv: list[str], entry: Callable[[list[str]], int]):
    self.argv, self.entry = list(argv), entry

  def __call__(self, index: int = 0) -> int:
    """Runs the worker (index: its place in the array); its exit code."""
    del index  # every worker runs the same command; the claims divide the cells
    submitit = _submitit()
    try:
      log = str(submitit.JobEnvironment().paths.stdout)
    except RuntimeError:  # not in a submitit job (called directly)
      log = None
    return self.entry(self.argv + (["--log-path", log] if log else []))

  def checkpoint(self, *args, **kwargs):
    """The same worker again, for submitit's requeue."""
    return _submitit().helpers.DelayedSubmission(WorkerJob(self.argv, self.entry), *args,
                                                 **kwargs)

  __submitit_checkpoint__ = checkpoint  # the name later submitit releases look for


def _submitit():
  """The submitit module, or SljaxError saying how to install it."""
  # Its import configures logging, which closes the handlers the importing program has (a
  # notebook's, pytest's); the jobs, processes of their own, keep submitit's log lines.
  before = os.environ.get(LOG_LEVEL)
  os.environ[LOG_LEVEL] = "NOCONFIG"
  try:
    import submitit  # pylint: disable=import-outside-toplevel
  except ImportError:
    raise SljaxError("sljax experiment submit needs submitit: pip install 'sljax[cluster]' "
                     "(or pip install submitit)") from None
  finally:
    if before is None:
      os.environ.pop(LOG_LEVEL, None)
    else:
      os.environ[LOG_LEVEL] = before
  return submitit


def check_available(local: bool) -> None:
  """SljaxError unless submitit (and, without --local, SLURM's sbatch and srun) is at hand."""
  _submitit()
  missing = [] if local else [c for c in ("sbatch", "srun") if shutil.which(c) is None]
  require(not missing, f"no SLURM here ({' and '.join(missing)} not found): submit from a "
          "SLURM login node, or pass --local to run the workers on this machine")


def submit_slurm(job: WorkerJob, res: Resources, folder: Path, name: str) -> list[Any]:
  """A job array of res.workers workers; its jobs."""
  submitit = _submitit()
  check_available(local=False)
  executor = submitit.SlurmExecutor(folder=folder, max_num_timeout=30)
  executor.update_parameters(**slurm_parameters(res, name))
  return executor.map_array(job, range(res.workers))


def local_parameters(res: Resources, gpus: list[str]) -> list[dict[str, Any]]:
  """The LocalExecutor parameters of each of res.workers local workers, given this machine's
  GPUs (local_gpus): one GPU each where there are GPUs (round robin, jax's preallocation off,
  when the workers outnumber them), none on a machine without."""
  each = (1 if gpus else 0) if res.gpus_per_worker is None else res.gpus_per_worker
  require(each <= len(gpus), f"--gpus-per-worker {each}: this machine has {len(gpus)} GPU(s)")
  shared = each and res.workers * each > len(gpus)
  setup = list(res.setup) + (["export XLA_PYTHON_CLIENT_PREALLOCATE=false"] if shared else [])
  params = []
  for k in range(res.workers):
    mine = [gpus[(k * each + j) % len(gpus)] for j in range(each)]
    if all(g.isdigit() for g in mine):  # submitit's visible_gpus takes indices
      gpu = {"gpus_per_node": len(mine), "visible_gpus": tuple(int(g) for g in mine),
             "setup": setup}
    else:  # UUIDs (GPU-...): the job's shell sets them
      gpu = {"gpus_per_node": 0, "setup": setup + [f"export CUDA_VISIBLE_DEVICES={','.join(mine)}"]}
    params.append({"timeout_min": res.minutes, "signal_delay_s": res.signal_delay_s, **gpu})
  return params


def submit_local(job: WorkerJob, res: Resources, folder: Path) -> list[tuple[Any, str]]:
  """res.workers local workers through submitit's local executor (local_parameters); (job,
  its GPUs)."""
  submitit = _submitit()
  jobs = []
  for params in local_parameters(res, local_gpus()):
    executor = submitit.LocalExecutor(folder=folder)
    executor.update_parameters(**params)
    gpus = params.get("visible_gpus") or [l.split("=", 1)[1] for l in params["setup"]
                                          if l.startswith("export CUDA_VISIBLE_DEVICES=")]
    jobs.append((executor.submit(job), ",".join(map(str, gpus)) or "none"))
  return jobs


def worker_argv(plan_name: str, out: Path, scale: str, seeds: int, data: str | None,
                eval_data: list[str], lease: float) -> list[str]:
  """The `sljax experiment run` command line every worker runs."""
  argv = ["experiment", "run", plan_name, str(out.absolute()), "--scale", scale, "--seeds",
          str(seeds), "--no-progress", "--lease", f"{lease:g}"]
  if data is not None:
    argv += ["--data", str(Path(data).absolute())]
  for folder in eval_data:
    argv += ["--eval-data", str(Path(folder).absolute())]
  return argv


def submit(job: WorkerJob, out: Path, res: Resources, local: bool, wait: bool, name: str,
           log: Callable[[str], None] = print) -> None:
  """Submits the workers (SLURM job array, or local processes) and logs the job ids, each
  worker's log and how to follow; with wait, then how each worker ended."""
  folder = out.absolute() / LOGS_DIR / "%j"
  status = f"sljax experiment status {out}"
  if local:
    jobs = submit_local(job, res, folder)
    log(f"started {len(jobs)} local worker(s) on {out} through submitit's local executor:")
    for one, gpus in jobs:
      log(f"  job {one.job_id} (GPU {gpus}): log {one.paths.stdout}, errors {one.paths.stderr}")
    log(f"follow with: {status} (it lists the workers' pids; kill -TERM one to stop it: its "
        "cell's claim is released and its checkpoint kept)")
    plain = [one for one, _ in jobs]
  else:
    plain = submit_slurm(job, res, folder, name)
    array = plain[0].job_id.split("_")[0]
    if len(plain) == 1:  # submitit submits a single job, not an array of one
      logs = plain[0].paths.stdout
      log(f"submitted job {array}: 1 worker on {out}")
      log(f"  log: {logs} (and .err beside it)")
    else:
      logs = Path(str(plain[0].paths.stdout).replace(plain[0].job_id, f"{array}_<task>"))
      log(f"submitted job {array}: an array of {len(plain)} worker(s) on {out}")
      log(f"  logs: {logs} (and .err beside it), task 0 to {len(plain) - 1}")
    log(f"follow with: {status}; squeue -j {array}; tail -f {logs}")
  try:
    folder.rmdir()  # submitit makes the pattern's folder itself; each job has its own
  except OSError:
    pass
  for one in plain if wait else ():
    try:
      log(f"  job {one.job_id} ended: exit code {one.result()}")
    except Exception as e:  # pylint: disable=broad-except  (the worker's log says more)
      log(f"  job {one.job_id} failed: {(str(e).strip().splitlines() or ['?'])[-1][:300]}")


def submit_grid(plan: Plan, out: Path, res: Resources, *, local: bool, wait: bool,
                lease: float, entry: Callable[[list[str]], int],
                log: Callable[[str], None] = print, grid: Plan | None = None) -> None:
  """Records the plan under OUT (refused in one line here, as a worker would be, rather than
  in N job logs) and submits res.workers workers of it (see `submit`); grid: the plan the
  workers run when `plan` is its calibration (the workers go on to it)."""
  check_available(local)
  with workers.plan_lock(out):
    records.register(out, plan)
  target = plan if grid is None else grid
  argv = worker_argv(target.name, out, target.scale.name, len(target.seeds), target.data,
                     list(target.eval_data), lease)
  submit(WorkerJob(argv, entry), out, res, local, wait, f"sljax-{target.name}", log)
