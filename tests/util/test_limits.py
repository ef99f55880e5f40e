"""The environment variables riskplan reads for its limits and threads: each bad value is one line naming it."""

from __future__ import annotations

import subprocess
import sys

import pytest

from riskplan.experiments.reporting.parallel import WORKERS_ENV, workers
from riskplan.util.errors import BadInput
from riskplan.util.limits import JOBS_ENV, MEMORY_ENV, check_numba_threads, duration, job_budget, memory_budget


@pytest.mark.parametrize(
    "env, value, problem, good, budget, expected",
    [
        # 0.5 read as 0 ('2 jobs, more than the 0 allowed') and 1.9 as 1
        (JOBS_ENV, "0.5", "expected a whole number of jobs >= 1$", "2.0", job_budget, 2),
        (JOBS_ENV, "1.9", "expected a whole number of jobs >= 1$", "2.0", job_budget, 2),
        # a limit below one byte was shown as "more than the 1e-311 B allowed"
        (MEMORY_ENV, "1e-320", r"expected at least 1e-9 GB \(one byte\)", "1e-9", memory_budget, (1.0, MEMORY_ENV)),
        (MEMORY_ENV, "1e-10", r"expected at least 1e-9 GB \(one byte\)", "1e-9", memory_budget, (1.0, MEMORY_ENV)),
    ],
)
def test_a_limit_no_run_could_meet_is_refused_naming_its_variable(
    monkeypatch, env, value, problem, good, budget, expected
):
    monkeypatch.setenv(env, value)
    with pytest.raises(BadInput, match=rf"^{env}: got '{value}'; {problem}"):
        budget()
    monkeypatch.setenv(env, good)
    assert budget() == expected


def test_a_duration_below_a_second_keeps_its_digits():
    assert [duration(s) for s in (0.00036, 0.5, 1.0, 90.0)] == ["0.00036 s", "0.5 s", "1 s", "90 s"]


@pytest.mark.parametrize("value", ["0", "-1", "abc", "", "²", "1.5"])
def test_numba_threads_that_numba_would_fail_on_are_one_line(monkeypatch, value):
    monkeypatch.setenv("NUMBA_NUM_THREADS", value)
    with pytest.raises(BadInput, match=r"^NUMBA_NUM_THREADS: got '.*'; expected a whole number of threads >= 1"):
        check_numba_threads()


def test_the_command_line_says_so_before_numba_loads(tmp_path):
    env = {"NUMBA_NUM_THREADS": "0", "PATH": "/usr/bin:/bin"}
    done = subprocess.run(
        [sys.executable, "-m", "riskplan", "check"], cwd=tmp_path, env=env, capture_output=True, text=True
    )
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr == (
        "error: NUMBA_NUM_THREADS: got '0'; expected a whole number of threads >= 1, or unset it (every core)\n"
    )


def test_report_workers_take_ascii_digits_only(monkeypatch):
    """'²' passes str.isdigit but not int(): it raised a ValueError traceback."""
    monkeypatch.setenv(WORKERS_ENV, "²")
    with pytest.raises(BadInput, match=rf"^{WORKERS_ENV}: got '²'; expected a whole number >= 1"):
        workers()
