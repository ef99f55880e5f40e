"""riskplan.util.blas_threads: a `riskplan` command-line process loads OpenBLAS with one thread (no pool spinning
beside numba's kernels), and a value the user set is kept."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from riskplan.util.blas_threads import BLAS_THREADS, single_threaded_blas

# `riskplan --help` through the entry point, then numpy loads: its OpenBLAS pool's threads are this process's tasks
AFTER_MAIN = """
import os, sys
sys.argv = ["riskplan", "--help"]
from riskplan.cli import main
try:
    main()
except SystemExit:
    pass
import numpy
print(os.environ.get("OPENBLAS_NUM_THREADS"), len(os.listdir("/proc/self/task")), file=sys.stderr)
"""


def test_unset_it_becomes_one(monkeypatch):
    monkeypatch.delenv(BLAS_THREADS, raising=False)
    single_threaded_blas()
    assert os.environ[BLAS_THREADS] == "1"


def test_a_value_the_user_set_is_kept(monkeypatch):
    monkeypatch.setenv(BLAS_THREADS, "3")
    single_threaded_blas()
    assert os.environ[BLAS_THREADS] == "3"


def _after_main(user_value: str | None) -> tuple[str, int]:
    env = {k: v for k, v in os.environ.items() if k not in (BLAS_THREADS, "OMP_NUM_THREADS", "GOTO_NUM_THREADS")}
    if user_value is not None:
        env[BLAS_THREADS] = user_value
    done = subprocess.run([sys.executable, "-c", AFTER_MAIN], capture_output=True, text=True, env=env, check=True)
    value, tasks = done.stderr.split()[-2:]
    return value, int(tasks)


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="counts threads in /proc (Linux)")
@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="OpenBLAS starts no pool on one core")
@pytest.mark.skipif(
    "openblas" not in np.show_config(mode="dicts")["Build Dependencies"]["blas"]["name"].lower(),
    reason="numpy here is not built with OpenBLAS",
)
def test_the_command_line_loads_openblas_without_a_pool_unless_the_user_asks():
    assert _after_main(None) == ("1", 1)  # the main thread alone
    value, tasks = _after_main("2")
    assert value == "2" and tasks == 2  # the user's two: the main thread and one of OpenBLAS's
