"""One writer per directory: an OS lock (flock) on DIR/.riskplan.lock, held for the life of a run or sweep job.

The lock dies with its process (the kernel drops it), so a SIGKILLed run never leaves a stale lock. The loser
names the holder's pid, read from /proc/locks (so taking the lock rewrites nothing; where /proc/locks is missing
or does not list the lock, the holder writes its pid into the file instead, as one fixed-width note). Holding is
re-entrant within a process (the CLI takes the lock before Hydra starts; the training loop it calls takes it again),
since two flock()s of one process on two file descriptions would otherwise block each other.

The lock file is removed only by the process that holds its lock (remove_held); a taker that opened it before
then finds, once it has the lock, that the file it locked is gone, and takes the one there now.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import time
from pathlib import Path

from riskplan.util.errors import BadInput

LOCK = ".riskplan.lock"
NOTE_WIDTH = 12  # the pid note: digits, spaces, a newline; one pwrite overwrites any earlier note whole
NOTE_TRIES = 10  # reads of a note that is missing or partial (its holder is writing it), 1 ms apart
TAKE_TRIES = 5  # opens of a lock file its holder removes as this process takes it

_held: dict[str, list[int]] = {}  # real path of the directory -> [fd, depth]


def _key(directory: Path) -> str:
    return os.path.realpath(directory)


PROC_LOCKS = Path("/proc/locks")


def _proc_locks() -> str | None:
    """The kernel's table of locks, or None where it is missing or cannot be read (some containers)."""
    try:
        return PROC_LOCKS.read_text()
    except OSError:
        return None


def _listed(table: str | None, fd: int) -> str | None:
    """The pid /proc/locks gives for a flock on fd's file (by its device and inode), or None."""
    if table is None:
        return None
    info = os.fstat(fd)
    where = f"{os.major(info.st_dev):02x}:{os.minor(info.st_dev):02x}:{info.st_ino}"
    for line in table.splitlines():
        parts = line.split()
        if "FLOCK" in parts and where in parts:
            return parts[parts.index(where) - 1]
    return None


def _note(fd: int) -> str | None:
    """The pid note in the file, or None while it is missing or partial (no newline yet)."""
    try:
        text = os.pread(fd, 32, 0).decode(errors="replace")
    except OSError:
        return None
    line, newline, _ = text.partition("\n")
    return line.strip() if newline and line.strip().isdigit() else None


def _pause() -> None:
    time.sleep(0.001)


def _read_pid(fd: int) -> str:
    """The holder's pid: from /proc/locks, else its note in the file, read again briefly while missing or partial
    (the holder may not have written it yet); "unknown" when none comes (a full disk left none)."""
    pid = _listed(_proc_locks(), fd)
    for attempt in range(NOTE_TRIES):
        if pid is not None:
            return pid
        if attempt:
            _pause()
        pid = _note(fd)
    return pid or "unknown"


def _same_file(fd: int, path: Path) -> bool:
    """Whether path still names the file fd has open (its last holder may have removed it)."""
    try:
        there, mine = os.stat(path), os.fstat(fd)
    except OSError:
        return False
    return (there.st_dev, there.st_ino) == (mine.st_dev, mine.st_ino)


def _unwritable(directory: Path, what: str, err: OSError) -> BadInput:
    return BadInput(str(directory), f"cannot be written ({err.strerror}); give a {what} you can write")


def _in_use(directory: Path, what: str, pid: str) -> BadInput:
    return BadInput(
        str(directory),
        f"is in use by another riskplan process (pid {pid}); one process writes a "
        f"{what} at a time: wait for it to end or stop it",
    )


def _take(directory: Path, what: str) -> tuple[int, bool]:
    """Open DIR's lock file and flock it: (fd, whether this process made the file); BadInput when another holds it."""
    path = directory / LOCK
    for _ in range(TAKE_TRIES):
        try:
            fd, created = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644), True
        except FileExistsError:
            try:
                fd, created = os.open(path, os.O_RDWR | os.O_CLOEXEC), False
            except FileNotFoundError:
                continue  # removed by its holder meanwhile: make it anew
            except OSError as err:
                raise _unwritable(directory, what, err) from None
        except OSError as err:
            raise _unwritable(directory, what, err) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            pid = _read_pid(fd)
            os.close(fd)
            raise _in_use(directory, what, pid) from None
        if _same_file(fd, path):
            return fd, created
        os.close(fd)  # its holder removed it before letting go: a lock on that file guards nothing now
    raise _in_use(directory, what, "unknown")


def _write_note(fd: int) -> None:
    """The pid note, where /proc/locks does not name this holder: one fixed-width pwrite over the old note, never a
    truncate first, which let a loser read an empty file and say "pid unknown"."""
    if _listed(_proc_locks(), fd) == str(os.getpid()):
        return
    with contextlib.suppress(OSError):  # the lock holds without the note (a full disk); the loser says "pid unknown"
        os.pwrite(fd, f"{os.getpid():<{NOTE_WIDTH - 1}}\n".encode(), 0)


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
    fd, created = _take(directory, what)
    _write_note(fd)
    _held[key] = [fd, 1]
    try:
        yield
    except BadInput:
        if created:  # refused before anything else was written: leave the directory as it was
            remove_held(directory)
        raise
    finally:
        del _held[key]
        os.close(fd)  # releases the flock


def remove_held(directory: Path | str) -> bool:
    """Remove DIR's lock file while this process holds its lock (a directory it made goes again): True when removed.
    A lock file this process does not hold, another process's, stays."""
    held = _held.get(_key(Path(directory)))
    path = Path(directory) / LOCK
    if held is None or not _same_file(held[0], path):
        return False
    try:
        path.unlink()
    except OSError:
        return False
    return True


def holder(directory: Path | str) -> int | None:
    """The pid of the process that holds DIR's lock, or None when nobody does (0 when the pid is unknown).

    Read from /proc/locks without touching the lock (a probe lock could make a real taker fail at that instant);
    only where /proc/locks cannot be read does it probe with a shared lock.
    """
    try:
        fd = os.open(Path(directory) / LOCK, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        table = _proc_locks()
        if table is not None:
            pid = _listed(table, fd)
            return None if pid is None else int(pid)
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            pid = _read_pid(fd)
            return int(pid) if pid.isdigit() else 0
        return None
    finally:
        os.close(fd)
