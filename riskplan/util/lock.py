"""One writer per directory: an OS lock (flock) on DIR/.riskplan.lock, held for the life of a run or sweep job.

The lock dies with its process (the kernel drops it), so a SIGKILLed run never leaves a stale lock. The loser
names the holder's pid, read from /proc/locks (so taking the lock rewrites nothing; where /proc/locks is missing,
the holder writes its pid into the file instead). Holding is re-entrant within a process (the CLI takes
the lock before Hydra starts; the training loop it calls takes it again), since two flock()s of one process on two
file descriptions would otherwise block each other.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path

from riskplan.util.errors import BadInput

LOCK = ".riskplan.lock"

_held: dict[str, list[int]] = {}  # real path of the directory -> [fd, depth]


def _key(directory: Path) -> str:
    return os.path.realpath(directory)


PROC_LOCKS = Path("/proc/locks")


def _read_pid(fd: int, proc_only: bool = False) -> str | None:
    """The holder's pid: from /proc/locks by the file's device and inode, else the pid note in the file (with
    `proc_only`, None when /proc/locks lists no lock on the file)."""
    info = os.fstat(fd)
    where = f"{os.major(info.st_dev):02x}:{os.minor(info.st_dev):02x}:{info.st_ino}"
    try:
        for line in PROC_LOCKS.read_text().splitlines():
            parts = line.split()
            if "FLOCK" in parts and where in parts:
                return parts[parts.index(where) - 1]
    except OSError:
        pass
    if proc_only:
        return None
    try:
        text = os.pread(fd, 32, 0).decode(errors="replace").strip()
    except OSError:
        text = ""
    return text if text.isdigit() else "unknown"


@contextlib.contextmanager
def hold_lock(directory: Path | str, what: str = "run directory", make: bool = False):
    """Hold DIR's lock for the `with` block; BadInput naming the holder's pid when another process has it. `make`:
    DIR is made if missing, and removed again if the block is refused (BadInput) before writing anything else."""
    directory = Path(directory)
    if make and not directory.exists():
        try:
            directory.mkdir(parents=True)
        except OSError as err:
            raise BadInput(str(directory), f"cannot be made ({err.strerror}); give a {what} you can write") from None
        try:
            with hold_lock(directory, what):
                yield
        except BadInput:
            with contextlib.suppress(OSError):
                directory.rmdir()
            raise
        return
    key = _key(directory)
    if key in _held:  # this process holds it already
        _held[key][1] += 1
        try:
            yield
        finally:
            _held[key][1] -= 1
        return
    path = directory / LOCK
    try:
        try:
            fd, created = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644), True
        except FileExistsError:
            fd, created = os.open(path, os.O_RDWR | os.O_CLOEXEC), False
    except OSError as err:
        raise BadInput(str(directory), f"cannot be written ({err.strerror}); give a {what} you can write") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        pid = _read_pid(fd)
        os.close(fd)
        raise BadInput(
            str(directory),
            f"is in use by another riskplan process (pid {pid}); one process writes a "
            f"{what} at a time: wait for it to end or stop it",
        ) from None
    try:
        if not PROC_LOCKS.exists():
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    except OSError:
        pass  # the lock holds without the pid note (a full disk); the loser then says "pid unknown"
    _held[key] = [fd, 1]
    try:
        yield
    except BadInput:
        if created:  # refused before anything else was written: leave the directory as it was
            path.unlink(missing_ok=True)
        raise
    finally:
        del _held[key]
        os.close(fd)  # releases the flock


def holder(directory: Path | str) -> int | None:
    """The pid of the process that holds DIR's lock, or None when nobody does (0 when the pid is unknown).

    Read from /proc/locks without touching the lock (a probe lock could make a real taker fail at that instant);
    only where /proc/locks is missing does it probe with a shared lock.
    """
    try:
        fd = os.open(Path(directory) / LOCK, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        if PROC_LOCKS.exists():
            pid = _read_pid(fd, proc_only=True)
            return None if pid is None else int(pid)
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            pid = _read_pid(fd)
            return int(pid) if pid.isdigit() else 0
        return None
    finally:
        os.close(fd)
