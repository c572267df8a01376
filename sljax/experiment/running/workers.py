"""Workers sharing one experiment folder: who a worker is, when a cell's holder is gone and its
claim may be taken over, the worker itself (its claims and the heartbeat that renews them),
who holds what for `experiment status`, and the signals that stop a worker.

OUT/claims/CELL/...         the cells' claims and heartbeats (sljax.experiment.running.claims)
OUT/workers/ID.json         a live worker: host, pid, job, since, its log; its mtime is the
                            worker's clock on the shared file system, removed when it ends

A claim is taken over when its holder is gone: on the same host, its pid has ended (or is
another process now); a claim from an earlier run of the same SLURM job (requeued) at once; on
another host, once its heartbeat is older than its lease. Ages are measured between two mtimes
on the shared file system (the claim's and this worker's own file, touched now), so the hosts'
clocks need not agree. Since numbers only grow, the holder sees at each heartbeat whether a
later claim superseded its own (a worker stalled past its lease) and then gives the cell up.
"""

import contextlib
import dataclasses
import json
import os
import secrets
import signal
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from sljax.experiment.running import claims
from sljax.io import files

try:
  import fcntl
except ImportError:  # Windows: plan.json is registered unlocked (see plan_lock)
  fcntl = None

WORKERS_DIR = "workers"
LEASE_S = 300.0
HOST_ENV = "SLJAX_WORKER_HOST"   # a host name for claims (containers that share a hostname)


@dataclasses.dataclass(frozen=True)
class Identity:
  """Who a worker is, as its claims record it."""
  token: str
  host: str
  pid: int
  started: str | None   # the process's start time (/proc), so a reused pid is not taken for it
  job: str | None       # the SLURM (or submitit local) job, array task included
  lease: float
  since: float

  def record(self) -> dict[str, Any]:
    """The JSON fields of a claim or worker file."""
    return dataclasses.asdict(self)

  @property
  def name(self) -> str:
    """The worker as messages name it."""
    return describe(self.record())


def describe(rec: dict[str, Any]) -> str:
  """host:pid (job J) of a claim or worker record."""
  job = f", job {rec['job']}" if rec.get("job") else ""
  return f"{rec.get('host', '?')} pid {rec.get('pid', '?')}{job}"


def job_id() -> str | None:
  """This process's job: SLURM's array job and task, or its job, or submitit's local job."""
  env = os.environ
  if env.get("SLURM_ARRAY_JOB_ID") and env.get("SLURM_ARRAY_TASK_ID"):
    return f"{env['SLURM_ARRAY_JOB_ID']}_{env['SLURM_ARRAY_TASK_ID']}"
  return env.get("SLURM_JOB_ID") or env.get("SUBMITIT_LOCAL_JOB_ID") or None


def process_started(pid: int) -> str | None:
  """The start time of a process in clock ticks since boot (/proc/PID/stat), None when it does
  not exist or this system has no /proc."""
  try:
    stat = Path(f"/proc/{pid}/stat").read_text(encoding="utf-8")
  except OSError:
    return None
  return stat.rsplit(")", 1)[1].split()[19]  # field 22; the name in () may hold spaces


def host_name() -> str:
  """This host as claims name it."""
  return os.environ.get(HOST_ENV) or socket.gethostname()


def identity(lease: float = LEASE_S) -> Identity:
  """This process as a worker."""
  pid = os.getpid()
  return Identity(secrets.token_hex(6), host_name(), pid, process_started(pid), job_id(),
                  float(lease), time.time())


def pid_alive(pid: int, started: str | None) -> bool:
  """Whether the process pid of this host still runs and is the one that started then."""
  try:
    os.kill(pid, 0)
  except ProcessLookupError:
    return False
  except PermissionError:  # another user's live process
    pass
  now = process_started(pid)
  return started is None or now is None or now == started


# ----------------------------------------------------------------------------- take-over


def gone(t: claims.Top, me: Identity, now: float) -> str | None:
  """Why the holder of a claimed cell is gone (its claim may be taken over), or None while it
  may live. now: the shared file system's time (Worker.clock)."""
  rec = t.record
  if not t.held or rec.get("token") == me.token:
    return None
  if rec.get("host") == me.host:
    alive = pid_alive(int(rec.get("pid", -1)), rec.get("started"))
    return None if alive else f"its worker ({describe(rec)}) has ended"
  if me.job is not None and rec.get("job") == me.job:
    return f"an earlier run of this job ({me.job}) held it"  # SLURM runs a job once at a time
  age = now - (t.beat or 0.0)
  lease = float(rec.get("lease", LEASE_S))
  if age > lease:
    return f"its worker ({describe(rec)}) last beat {age:.0f} s ago, over its {lease:g} s lease"
  return None


def late(t: claims.Top, now: float) -> bool:
  """Whether a held claim missed two heartbeats (its holder may be dead; the lease decides)."""
  return t.held and now - (t.beat or 0.0) > 2 * float(t.record.get("lease", LEASE_S)) / 3


# ----------------------------------------------------------------------------- plan.json


@contextlib.contextmanager
def plan_lock(out: Path) -> Iterator[None]:
  """OUT itself locked (flock on the folder) while a worker reads and extends plan.json, so
  that two workers registering different plans at once keep both; unlocked where the file
  system has no flock on folders (the workers of one grid write the same record anyway)."""
  out.mkdir(parents=True, exist_ok=True)
  fd = os.open(out, os.O_RDONLY)
  try:
    try:
      if fcntl is not None:
        fcntl.flock(fd, fcntl.LOCK_EX)
    except OSError:
      pass
    yield
  finally:
    os.close(fd)  # drops the lock


# ----------------------------------------------------------------------------- a worker


@dataclasses.dataclass
class Held:
  """A claim this worker holds, and the step its cell reached."""
  cell: str
  path: Path
  step: int = 0
  lost: bool = False


class Worker:
  """One worker's presence under OUT: its file, its claims and the heartbeat that renews them
  (a thread, every lease/3 s)."""

  def __init__(self, out: Path, me: Identity, log_path: str | None = None):
    self.out, self.me = out, me
    self.file = out / WORKERS_DIR / f"{me.host}-{me.pid}-{me.token}.json"
    self.held: Held | None = None
    self._lock = threading.Lock()
    self._writing = threading.RLock()  # the heartbeat thread and a claim write the same files
    self._stop = threading.Event()
    self._thread: threading.Thread | None = None
    self._log_path = log_path

  def __enter__(self) -> "Worker":
    self.file.parent.mkdir(parents=True, exist_ok=True)
    files.write_text(self.file, json.dumps(dict(self.me.record(), log=self._log_path)) + "\n")
    self._thread = threading.Thread(target=self._beat_loop, name="sljax-heartbeat", daemon=True)
    self._thread.start()
    return self

  def __exit__(self, *exc) -> None:
    self._stop.set()
    if self._thread is not None:
      self._thread.join()
    self.file.unlink(missing_ok=True)

  def clock(self) -> float:
    """Now on the shared file system: the mtime of this worker's file, touched now."""
    with self._writing:
      try:
        os.utime(self.file)
      except FileNotFoundError:  # removed by hand: write it again
        files.write_text(self.file, json.dumps(self.me.record()) + "\n")
      return self.file.stat().st_mtime

  def claim(self, cell: str) -> bool:
    """Claims a cell (free, released, or held by a worker that is gone); False when another
    worker holds it or claimed it first."""
    assert self.held is None, "one cell at a time"
    t = claims.top(self.out, cell)
    why = gone(t, self.me, self.clock()) if t.held else None
    if t.held and why is None:
      return False
    path = claims.claim_path(self.out, cell, t.number + 1)
    record = dict(self.me.record(), kind=claims.CLAIM, since=time.time(), took_over=why)
    if not claims.create_exclusive(path, record):
      return False
    with self._lock:
      self.held = Held(cell, path)
    self._renew()
    return True

  def release(self, why: str) -> None:
    """Lets go of the held cell (unless a later claim superseded it)."""
    with self._lock:
      held, self.held = self.held, None
    if held is None or not self._owns(held):
      return
    claims.create_exclusive(held.path.with_name(f"{int(held.path.stem) + 1:04d}.json"),
                            {"kind": claims.RELEASE, "token": self.me.token,
                             "host": self.me.host, "pid": self.me.pid, "job": self.me.job,
                             "why": why, "step": held.step, "at": time.time()})

  def progress(self, step: int) -> None:
    """The held cell's training reached step (shown by `experiment status`)."""
    with self._lock:
      if self.held is not None:
        self.held.step = step

  @property
  def lost(self) -> bool:
    """Whether the held cell was taken over by another worker (this one stalled too long)."""
    held = self.held
    return held is not None and held.lost

  def _owns(self, held: Held) -> bool:
    """Whether no later claim superseded the held one."""
    return not held.path.with_name(f"{int(held.path.stem) + 1:04d}.json").exists()

  def _renew(self) -> None:
    """One heartbeat: this worker's file, and the held claim's beat with its step."""
    with self._writing:
      self.clock()
      with self._lock:
        held = self.held
      if held is None or held.lost:
        return
      if not self._owns(held):
        held.lost = True
        return
      files.write_text(claims.beat_path(held.path),
                       json.dumps({"step": held.step, "token": self.me.token}) + "\n")

  def _beat_loop(self) -> None:
    """Renews every lease/3 s until the worker ends (a failed write is retried next time)."""
    while not self._stop.wait(self.me.lease / 3):
      try:
        self._renew()
      except OSError:
        pass


# ----------------------------------------------------------------------------- who holds what


def holders(out: Path, cells: list[str]) -> dict[str, tuple[dict[str, Any], int | None, float]]:
  """{cell: (claim record, last step, seconds since its heartbeat)} of the claimed cells among
  cells, ages by the shared file system's clock (a probe file touched now)."""
  tops = {cell: t for cell in cells if (t := claims.top(out, cell)).held}
  now = claims.fs_now(out) if tops else 0.0
  found = {}
  for cell, t in tops.items():
    beat = claims.read_beat(claims.claim_path(out, cell, t.number))
    step = beat.get("step") if beat.get("token") == t.record.get("token") else None
    found[cell] = (t.record, step, now - (t.beat or now))
  return found


def live_workers(out: Path) -> list[str]:
  """The workers with a file under OUT/workers: who, since when, their log; one that looks
  gone (its pid ended on this host, or no heartbeat for its lease) says so."""
  found = sorted((out / WORKERS_DIR).glob("*.json"))
  if not found:
    return []
  now, said = claims.fs_now(out), []
  for path in found:
    try:
      rec, age = json.loads(path.read_text(encoding="utf-8")), now - path.stat().st_mtime
    except (OSError, ValueError):
      continue  # ended (removed) while read
    if not isinstance(rec, dict) or not claims.is_identity(rec):
      said.append(f"{path}: not an sljax worker file (delete it if nothing else wrote it)")
      continue
    dead = (not pid_alive(int(rec.get("pid", -1)), rec.get("started"))
            if rec.get("host") == host_name() else age > float(rec.get("lease", LEASE_S)))
    said.append(f"{describe(rec)} since {when(rec.get('since'))}"
                + (f", log {rec['log']}" if rec.get("log") else "")
                + (" (gone: it ended without removing its file)" if dead else ""))
  return said


def late_holders(out: Path, cells: list[str], now: float) -> list[str]:
  """The cells among cells whose holder missed two heartbeats (`late`)."""
  return [cell for cell in cells if late(claims.top(out, cell), now)]


def held_by(out: Path, cells: list[str]) -> dict[str, str]:
  """{cell: "held by WORKER since T, step S" or "not claimed"} for a worker's last words."""
  held = holders(out, cells)
  said = {}
  for cell in cells:
    if cell not in held:
      said[cell] = "not claimed"
      continue
    rec, step, _ = held[cell]
    said[cell] = (f"held by {describe(rec)} since {when(rec.get('since'))}"
                  + (f", step {step}" if step is not None else ""))
  return said


def when(stamp: float | None) -> str:
  """A claim's time, local, to the minute."""
  return "?" if stamp is None else time.strftime("%Y-%m-%d %H:%M", time.localtime(stamp))


# ----------------------------------------------------------------------------- stopping


class Stopped(BaseException):
  """The worker was asked to stop (a signal) or lost its cell; raised where the cell's work
  can end cleanly (between training steps, between evaluation sets)."""


class Stop:
  """SIGTERM and the cluster's warning (SIGUSR2: submitit's preemption and time-limit signal),
  while the block runs in the main thread: they ask the worker to stop at a step (where the
  runner checks: `check`). Ctrl-C stays the trainer's (sljax.train.interrupt). `hand_over`
  then passes the signal to the handler it replaced: submitit's checkpoints the job and
  requeues it."""

  SIGNALS = ("SIGTERM", "SIGUSR2")

  def __init__(self):
    self.signum: int | None = None
    self._previous: dict[int, Any] = {}

  def __enter__(self) -> "Stop":
    if threading.current_thread() is threading.main_thread():
      for name in self.SIGNALS:
        sig = getattr(signal, name, None)
        if sig is not None:
          self._previous[sig] = signal.signal(sig, self._handle)
    return self

  def __exit__(self, *exc) -> None:
    for sig, handler in self._previous.items():
      signal.signal(sig, signal.SIG_DFL if handler is None else handler)

  def _handle(self, signum, frame) -> None:  # pylint: disable=unused-argument
    """Only a flag: an exception raised here could land inside jax and be lost."""
    self.signum = signum
    os.write(2, f"\n{signal.Signals(signum).name}: stopping after this step, with a checkpoint "
                "at it; the cell's claim is released\n".encode())

  @property
  def name(self) -> str | None:
    """The signal that asked to stop, or None."""
    return None if self.signum is None else signal.Signals(self.signum).name

  def check(self) -> None:
    """Stopped when a signal asked to stop."""
    if self.signum is not None:
      raise Stopped(self.name)

  def hand_over(self) -> None:
    """Passes the signal on to the handler this one replaced, if Python set one (submitit's
    checkpoints and requeues, then exits)."""
    handler = self._previous.get(self.signum)
    if callable(handler):
      handler(self.signum, None)
