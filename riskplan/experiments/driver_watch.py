"""A sweep's local workers end with their driver, however it died (SIGKILL included), and never write after it.

The driver (`riskplan sweep`, `reproduce`) names itself in RISKPLAN_SWEEP_DRIVER to the workers it starts on this
machine (joblib's, submitit_local's, a local Ray instance's): its pid, its start time (so that a recycled pid is
never taken for it) and its host. It names itself only to those (`name_driver`): SLURM jobs and jobs on a Ray
cluster are not its workers and must outlive it.

Three things end the workers:
- a guardian, a small process of its own session that the driver starts with the first name it gives: it checks
  the driver every WATCH_SECONDS and, once it is gone, kills every process whose environment names it (workers
  idle or busy, their children, the resource trackers they share), then exits (`guard`);
- in a worker, `arrive` runs as a job arrives, before Hydra or the job writes anything (unpickling the job's
  `FolderNames` callback calls it, and so do the job functions): a worker whose driver is gone kills itself there,
  and a child of the driver asks the kernel for SIGKILL when the driver's thread that spawned it ends
  (PR_SET_PDEATHSIG: at once, even inside a compiled kernel). The driver spawns workers only from threads that
  last as long as it does (see `launch.warm_workers`). `exit_if_orphaned` checks again before a job writes its
  status;
- while it launches, the driver keeps its name in the sweep folder (DRIVER_FILE): a re-run into that folder that
  finds the name of a driver now dead ends what it left running, the same way, before it starts (`end_leftovers`),
  for when the guardian was killed with it.

The driver's workers keep their scratch files in a temporary folder of the driver's (`scratch`), which the guardian
removes once the workers are gone: a worker killed mid-way (a bad input after the warm-up began, a Ctrl-C, a killed
driver) leaves nothing behind in the machine's temporary folder.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

from riskplan.util.interrupt import die_with_parent, repeated
from riskplan.util.paths import write_atomic

ENV = "RISKPLAN_SWEEP_DRIVER"  # pid:start-time@host of the driver, in its local workers' environment
DRIVER_FILE = ".driver"  # the same, in the sweep folder while a launch lasts
WATCH_SECONDS = 0.1  # how often the watchdog checks the driver
GONE_SECONDS = 5.0  # how long a re-run waits for the leftovers it killed to be gone

_guardian: list[subprocess.Popen] = []  # the guardian of this process, once it named itself
_scratch: list[Path] = []  # this driver's scratch folder for its workers, which its guardian removes


def identity(pid: int) -> str | None:
    """`pid:start-time@host` of a living process (its start time in clock ticks since boot, from /proc), or None
    when there is no such process or it has exited (a zombie)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    if fields[0] in ("Z", "X"):  # exited, not yet reaped
        return None
    return f"{pid}:{fields[19]}@{socket.gethostname()}"  # field 22 of stat: starttime


def _pid(name: str) -> int:
    return int(name.split(":", 1)[0])


def name_driver(local: bool) -> None:
    """Name this process to the workers it will start (`local`: a launcher whose jobs run on this machine below
    it), or to none (a cluster's jobs must outlive it)."""
    me = identity(os.getpid()) if local else None
    if me is None:
        os.environ.pop(ENV, None)
        return
    if not _guardian:
        atexit.register(_leave_guardian)
        with contextlib.suppress(OSError):  # no temporary folder at all: the workers go without (and no warm-up)
            _scratch.append(Path(tempfile.mkdtemp(prefix="riskplan-driver-")))
        _guardian.append(
            subprocess.Popen(
                [sys.executable, "-m", __name__, me, *map(str, _scratch)],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                start_new_session=True,  # not in the driver's process group: a signal to the group spares it
                close_fds=True,
                env={key: value for key, value in os.environ.items() if key != ENV},  # not a worker of it
            )
        )
    os.environ[ENV] = me


def scratch() -> Path | None:
    """This driver's scratch folder for its local workers (private to this user, removed by the guardian once the
    driver and its workers are gone), or None before it named itself to local workers."""
    return _scratch[0] if _scratch else None


def _leave_guardian() -> None:
    """At exit: the guardian outlives this process by design (it waits for it to end), so dropping its handle is no
    leak: without the warning Popen gives for a child still running, a second line after a bad input's one."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ResourceWarning)
        _guardian.clear()


def driver() -> str | None:
    """The driver this process is a local worker of, or None (no driver named, another host's, or this process)."""
    name = os.environ.get(ENV, "")
    pid, _, host = name.partition(":")
    if not pid.isdigit() or not host.endswith("@" + socket.gethostname()) or int(pid) == os.getpid():
        return None
    return name


def _die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def exit_if_orphaned() -> None:
    """Kill this process, before it writes anything more, when it is a local worker whose driver is gone."""
    name = driver()
    if name is not None and identity(_pid(name)) != name:
        _die()


def arrive() -> str | None:
    """In a local worker: die now if the driver is gone, else ask to die with it (PR_SET_PDEATHSIG, for a child
    of it). Returns the driver's name, or None where this process is not a local worker."""
    name = driver()
    if name is None:
        return None
    if os.getppid() == _pid(name):
        die_with_parent()
    exit_if_orphaned()  # after prctl: a driver that died just before it is caught here
    return name


_working: list[bool] = []  # whether this local worker is in a job now (nested: a job and its set-up)


@contextlib.contextmanager
def working():
    """In a local worker's main thread, a job: while the block runs, Ctrl-C raises KeyboardInterrupt in it (handlers
    of its own, a training's, take over from this one); outside it, the idle worker ends at once and quietly, as
    its driver is stopping too (Python's default printed a traceback from loky's loop). Elsewhere it does nothing.
    The driver spawned the worker with SIGINT blocked (`launch.start_workers`): see `take_interrupts`."""
    local = driver() is not None and threading.current_thread() is threading.main_thread()
    if local:
        signal.signal(signal.SIGINT, _stop_or_end)
    _working.append(local)
    try:
        yield
    finally:
        _working.pop()


def take_interrupts() -> None:
    """In a local worker's main thread, once its job handles SIGINT (`working`, or a StopSignals): let SIGINT in. A
    Ctrl-C that came while the worker started, held back since, is taken here."""
    if driver() is not None and threading.current_thread() is threading.main_thread():
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def _stop_or_end(signum: int, frame) -> None:
    if _working:
        if _stopped and repeated(signum, signal.SIGINT, _stopped[-1]):
            return  # the driver passing on the Ctrl-C this job stops by already
        _stopped.append(time.monotonic())
        raise KeyboardInterrupt
    os._exit(128 + signum)


_stopped: list[float] = []  # when this worker's Ctrl-C's stopped a job (time.monotonic)


@contextlib.contextmanager
def recorded(sweep_dir: Path):
    """Keep this driver's name in the sweep folder while the block runs (a launch); a killed driver leaves it."""
    path = Path(sweep_dir) / DRIVER_FILE
    write_atomic(path, identity(os.getpid()) or "")
    try:
        yield
    finally:
        path.unlink(missing_ok=True)


def _environment(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/environ").read_bytes()
    except OSError:
        return b""


def leftovers(name: str) -> dict[int, str]:
    """The living processes whose environment names the driver `name` (its workers, and the helpers they share),
    each with its identity (so that a pid recycled since is never killed)."""
    mark = f"{ENV}={name}".encode()
    found = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and int(entry.name) != os.getpid():
            pid = int(entry.name)
            if mark in _environment(pid).split(b"\0") and (now := identity(pid)):
                found[pid] = now
    return found


def end(name: str) -> list[int]:
    """Kill what the driver `name` left running and wait (GONE_SECONDS at most) until it is gone; their pids."""
    found = leftovers(name)
    for pid, who in found.items():
        if identity(pid) == who:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)
    deadline = time.monotonic() + GONE_SECONDS
    while any(identity(pid) == who for pid, who in found.items()) and time.monotonic() < deadline:
        time.sleep(WATCH_SECONDS)  # their job folders' locks are free once they are gone
    return sorted(found)


def guard(name: str, scratch_dir: Path | None) -> None:
    """The guardian's life: wait for the driver `name` to end, then end what it left running and remove its scratch
    folder. The signals that stop a sweep, which its driver passes on to the processes below it, are not the
    guardian's to stop by."""
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, signal.SIG_IGN)
    while identity(_pid(name)) == name:
        time.sleep(WATCH_SECONDS)
    end(name)
    if scratch_dir is not None:
        shutil.rmtree(scratch_dir, ignore_errors=True)  # after end(): no worker writes in it any more


def end_leftovers(sweep_dir: Path) -> str | None:
    """End the processes an earlier, killed driver of this sweep folder left running; one line saying so, or None
    when there were none. A driver still alive is left alone (the folder's lock keeps a second driver out)."""
    try:
        name = (Path(sweep_dir) / DRIVER_FILE).read_text().strip()
    except OSError:
        return None
    if not name or identity(_pid(name)) == name:
        return None
    pids = end(name)
    (Path(sweep_dir) / DRIVER_FILE).unlink(missing_ok=True)
    if not pids:
        return None
    plural = "es" if len(pids) != 1 else ""
    return (
        f"ended {len(pids)} process{plural} left running by this folder's earlier sweep (its driver, pid "
        f"{_pid(name)}, was killed): pid{'s' if len(pids) != 1 else ''} {', '.join(map(str, pids))}"
    )


if __name__ == "__main__":
    guard(sys.argv[1], Path(sys.argv[2]) if len(sys.argv) > 2 else None)
