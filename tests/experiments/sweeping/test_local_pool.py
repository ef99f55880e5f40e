"""The local worker processes of sweeps and batches (riskplan.experiments.sweeping.launch.local_pool)."""

from __future__ import annotations

import numba
import pytest
from joblib import delayed

from riskplan.experiments.reproduction import stop_workers
from riskplan.experiments.sweeping.launch import NUMBA_THREADS_ENV, local_pool


@pytest.mark.slow  # a worker process started
def test_a_local_worker_keeps_numbas_whole_pool_of_threads(monkeypatch):
    """joblib would start each of 2 workers with numba's pool capped at cores // 2 threads for its whole life; the
    local pool's workers keep this process's pool, so that a part of a batch can take the cores its finished
    siblings left (FreedCores), while each uses the share it sets."""
    monkeypatch.setenv(NUMBA_THREADS_ENV, "0")  # so that the variable local_pool sets is removed again after
    monkeypatch.delenv(NUMBA_THREADS_ENV)
    stop_workers()  # a pool this session started before, with another environment, is not reused
    try:
        seen = local_pool(2)(delayed(lambda: numba.config.NUMBA_NUM_THREADS)() for _ in range(2))
    finally:
        stop_workers()
    assert seen == [numba.config.NUMBA_NUM_THREADS] * 2
