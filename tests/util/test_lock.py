"""One writer per run directory (riskplan.util.lock): the lock is reentrant within a process and exclusive between
processes; where /proc/locks cannot be read, the loser names the holder from its pid note, which is never seen
empty; only the holder removes the lock file. Whole runs and sweeps that meet a held lock are in
tests/run/test_run_safety.py and tests/experiments/sweeping/test_sweep_safety.py."""

from __future__ import annotations

import fcntl
import os
import subprocess

import pytest

from riskplan.util import lock
from riskplan.util.errors import BadInput
from riskplan.util.lock import hold_lock, holder


def test_the_lock_is_reentrant_within_a_process_and_exclusive_between_processes(tmp_path):
    with hold_lock(tmp_path):
        with hold_lock(tmp_path):  # the CLI holds it while Hydra runs the training loop, which takes it again
            assert holder(tmp_path) == os.getpid()
        probe = subprocess.run(
            [
                "python",
                "-c",
                "import sys; from riskplan.util.lock import hold_lock\n"
                "from riskplan.util.errors import BadInput\n"
                f"try:\n    with hold_lock({str(tmp_path)!r}): sys.exit(0)\n"
                "except BadInput as err:\n    print(err); sys.exit(3)",
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert probe.returncode == 3 and f"(pid {os.getpid()})" in probe.stdout
    assert holder(tmp_path) is None


@pytest.fixture(params=["missing", "unreadable"])
def no_proc_locks(request, tmp_path, monkeypatch):
    """/proc/locks missing (some kernels, gVisor) or unreadable (a directory stands in): the pid note names holders."""
    stand_in = tmp_path / "proc-locks"
    if request.param == "unreadable":
        stand_in.mkdir()
    monkeypatch.setattr(lock, "PROC_LOCKS", stand_in)


def _note_of(path) -> str:
    """The pid note as a reader finds it: its first line, once complete (with its newline), else ''."""
    line, newline, _ = path.read_text().partition("\n")
    return line.strip() if newline else ""


def test_where_proc_locks_cannot_be_read_the_note_is_one_write_never_emptied_first(
    tmp_path, monkeypatch, no_proc_locks
):
    """A loser reading the file at any step of the holder's finds a whole pid: the previous holder's, then this
    one's; a truncate before the write let it read an empty file and say "pid unknown"."""
    path = tmp_path / lock.LOCK
    path.write_text("1\n")  # an earlier holder's note
    seen = []

    def watched(call):
        def step(*args):
            seen.append(_note_of(path))
            result = call(*args)
            seen.append(_note_of(path))
            return result

        return step

    monkeypatch.setattr(os, "ftruncate", watched(os.ftruncate))
    monkeypatch.setattr(os, "pwrite", watched(os.pwrite))
    with hold_lock(tmp_path):
        assert holder(tmp_path) == os.getpid()  # probed with a shared lock, then read from the note
    assert seen and all(note.isdigit() for note in seen), seen
    assert _note_of(path) == str(os.getpid())


@pytest.mark.parametrize("first", [b"", b"42"], ids=["not-yet-written", "half-written"])
def test_a_loser_that_finds_the_note_unwritten_reads_it_again_and_names_the_holder(
    tmp_path, monkeypatch, no_proc_locks, first
):
    fd = os.open(tmp_path / lock.LOCK, os.O_RDWR | os.O_CREAT, 0o644)  # the holder: another open file, locked
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        os.pwrite(fd, first, 0)
        # the holder finishes its note while the loser waits to read it again
        monkeypatch.setattr(lock, "_pause", lambda: os.pwrite(fd, b"4242       \n", 0), raising=False)
        with pytest.raises(BadInput, match=r"\(pid 4242\)"):
            with hold_lock(tmp_path):
                pass
    finally:
        os.close(fd)


def test_a_note_that_never_comes_is_pid_unknown_after_a_few_reads(tmp_path, monkeypatch, no_proc_locks):
    pauses = []
    monkeypatch.setattr(lock, "_pause", lambda: pauses.append(1), raising=False)
    fd = os.open(tmp_path / lock.LOCK, os.O_RDWR | os.O_CREAT, 0o644)  # a holder whose disk took no note
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        with pytest.raises(BadInput, match=r"\(pid unknown\)"):
            with hold_lock(tmp_path):
                pass
        assert holder(tmp_path) == 0
    finally:
        os.close(fd)
    assert 0 < len(pauses) <= 2 * lock.NOTE_TRIES


def test_a_lock_file_its_holder_removes_as_this_process_takes_it_is_made_again(tmp_path, monkeypatch):
    """The holder of a directory it made removes its lock file as it lets go (Output.abandon); a lock on the removed
    file would guard nothing, so the taker takes the file there now."""
    path = tmp_path / lock.LOCK
    path.write_text("")
    flock = fcntl.flock
    removed = []

    def removed_first(fd, how):
        if not removed:
            removed.append(path)
            path.unlink()
        return flock(fd, how)

    monkeypatch.setattr(fcntl, "flock", removed_first)
    with hold_lock(tmp_path):
        assert removed and path.exists()
        assert holder(tmp_path) == os.getpid()


def test_only_the_holder_removes_the_lock_file(tmp_path):
    assert not lock.remove_held(tmp_path)  # not held here: another process's file, or none
    with hold_lock(tmp_path):
        assert lock.remove_held(tmp_path) and not (tmp_path / lock.LOCK).exists()
