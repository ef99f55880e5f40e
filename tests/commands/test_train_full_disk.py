"""`riskplan train` on a disk that is full as the run begins (a real tmpfs, filled): Hydra writes the run's .hydra/
files in place, so it left a zero-byte config.yaml, an empty app.log and the lock, a folder that then refused a new
run ("already holds a run") and a resume (its empty config read as {}). Now the line is the write error's, and a run
that trained nothing leaves nothing: the folder it made is removed, the empty folder it was given emptied again.
The mounts need root; without it the tests are skipped, saying why."""

from __future__ import annotations

import contextlib
import subprocess
from pathlib import Path

import pytest
from support import TINY, files, mounted, train_cli

pytestmark = pytest.mark.slow  # `riskplan train` in subprocesses, on a mounted tmpfs


@contextlib.contextmanager
def full_tmpfs(target: Path):
    """A 300k tmpfs at target, filled to the last byte by a file `fill`; unmounted afterwards."""
    with mounted(target, "-t", "tmpfs", "-o", "size=300k", "tmpfs"):
        subprocess.run(["dd", "if=/dev/zero", f"of={target / 'fill'}", "bs=4k"], capture_output=True)
        yield target


def test_a_full_disk_at_the_start_is_the_write_errors_line_and_leaves_no_run(tmp_path):
    with full_tmpfs(tmp_path / "full") as disk:
        out = disk / "r0"
        result = train_cli(TINY, out)
        assert result.returncode == 1
        assert result.stderr.splitlines() == [
            f"error: run failed: cannot write {out}/.hydra/config.yaml: No space left on device; free space, then "
            f"riskplan train again (nothing was trained, so {out} was removed)"
        ]
        assert not out.exists()

        given = disk / "given"  # an empty folder the user made: emptied again, not removed
        given.mkdir()
        result = train_cli(TINY, given)
        assert result.returncode == 1
        assert result.stderr.splitlines()[-1].endswith(f"(nothing was trained, so {given} was emptied again)")
        assert set(files(given)) <= {".riskplan.lock"}

        (disk / "fill").unlink()  # space freed: the same folder takes the run
        result = train_cli(TINY, out)
        assert result.returncode == 0, result.stderr
        assert (out / "summary.json").is_file()
