"""Every command's last line of defence (riskplan.commands.common.bad_input_exits): bad input is one line and exit
code 2; a file that cannot be written at run time (a full disk) is one line and exit code 1, which says what to do."""

from __future__ import annotations

import errno
import signal

import pytest
import typer
from typer.testing import CliRunner

import riskplan.run.compose as compose_module
from riskplan.cli import app
from riskplan.commands.common import bad_input_exits
from riskplan.util.errors import BadInput
from riskplan.util.interrupt import Interrupted


def failing(error: Exception):
    @bad_input_exits
    def command():
        raise error

    return command


@pytest.mark.parametrize(
    "error, code, line",
    [
        (
            BadInput("risk.beta", "got 2; expected a level in (0, 1]"),
            2,
            "error: risk.beta: got 2; expected a level in (0, 1]",
        ),
        (
            OSError(errno.ENOSPC, "No space left on device", "out/s/summary.parquet"),
            1,
            "error: cannot write out/s/summary.parquet: No space left on device; free space (or give another "
            "directory), then run the same command again: what finished is kept",
        ),
        (
            OSError(errno.ENOSPC, "No space left on device"),  # a write() names no file
            1,
            "error: cannot write: No space left on device; free space (or give another directory), then run the "
            "same command again: what finished is kept",
        ),
        (
            OSError(errno.EFBIG, "File too large", "out/run.mcap"),  # ulimit -f: freeing space would not help
            1,
            "error: cannot write out/run.mcap: File too large; raise the file size limit (ulimit -f) (or give "
            "another directory), then run the same command again: what finished is kept",
        ),
        (
            OSError(errno.EACCES, "Permission denied", "out"),
            1,
            "error: cannot write out: Permission denied; make the directory writable (or give another directory), "
            "then run the same command again: what finished is kept",
        ),
    ],
)
def test_a_failure_is_one_line_with_its_exit_code(capsys, error, code, line):
    with pytest.raises(typer.Exit) as stop:
        failing(error)()
    assert stop.value.exit_code == code
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [line] and captured.out == ""


@pytest.mark.parametrize(
    "stop, code, line",
    [
        (KeyboardInterrupt(), 130, "error: interrupted by SIGINT"),  # Ctrl-C where no handler of riskplan's ran
        (Interrupted(signal.SIGTERM, 7), 143, "error: interrupted by SIGTERM"),  # a scratch run a signal stopped
    ],
)
def test_a_signal_that_stops_a_command_is_one_line_with_the_shells_code(monkeypatch, stop, code, line):
    """typer answers Ctrl-C with a silent exit 130 (click with "Aborted!"), and a benchmark's scratch run stopped
    by a signal printed a traceback ending in Interrupted."""

    def stopped(*args, **kwargs):
        raise stop

    monkeypatch.setattr(compose_module, "compose", stopped)
    result = CliRunner().invoke(app, ["check"])
    assert (result.exit_code, result.stderr) == (code, line + "\n")
