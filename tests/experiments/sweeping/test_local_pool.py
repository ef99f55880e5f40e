"""The local worker processes of sweeps and batches (riskplan.experiments.sweeping.launch.local_pool)."""

from __future__ import annotations

import threading

import numba
import pytest
from joblib import delayed
from joblib.externals.loky import get_reusable_executor
from joblib.externals.loky.process_executor import _ExecutorManagerThread

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


@pytest.mark.slow  # worker processes started
def test_stopping_the_workers_with_work_still_queued_leaves_no_thread_failing(monkeypatch):
    """loky's manager thread, stopped with kill_workers=True, cancelled the queued work and then failed on a work
    id still in its queue (KeyError, a traceback from "ExecutorManagerThread" under a bad input's line, once in
    CI): here the manager thread holds the new work back as a busy one would, until the executor shuts down."""
    failed = []
    monkeypatch.setattr(threading, "excepthook", failed.append)
    stop_workers()
    executor = get_reusable_executor(max_workers=2)
    assert executor.submit(abs, -1).result() == 1  # the workers are up
    feed = _ExecutorManagerThread.add_call_item_to_queue

    def held_back(manager):
        if manager.executor_flags.shutdown:
            feed(manager)

    monkeypatch.setattr(_ExecutorManagerThread, "add_call_item_to_queue", held_back)
    queued = executor.submit(abs, -2)
    manager = executor._executor_manager_thread
    stop_workers()
    manager.join(timeout=30)
    assert not manager.is_alive() and failed == []
    assert isinstance(queued.exception(timeout=30), Exception)  # the queued work failed, quietly
