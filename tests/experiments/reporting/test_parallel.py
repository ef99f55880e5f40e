"""Figures drawn on all cores (riskplan.experiments.reporting.parallel): work no worker delivered, whether the worker
died or could not be forked, is done in this process; a bad worker count is bad input. Whole reports drawn by
workers are compared with one process's in test_report_contents.py."""

from __future__ import annotations

import multiprocessing
import os
import sys

import pytest

from riskplan.experiments.reporting.parallel import WORKERS_ENV, shared_map, sharing
from riskplan.util.errors import BadInput

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="worker processes are forked on Linux")


@linux_only
def test_work_no_worker_delivered_is_done_in_this_process(monkeypatch):
    parent = os.getpid()

    def square(x):  # a worker dies at once
        if os.getpid() != parent:
            os._exit(1)
        return x * x

    monkeypatch.setenv(WORKERS_ENV, "3")
    assert shared_map(square, list(range(7)), cost=lambda x: x % 3) == [x * x for x in range(7)]

    def refused(process):
        raise OSError(11, "Resource temporarily unavailable")  # fork: no pids left

    monkeypatch.setattr(multiprocessing.context.ForkProcess, "start", refused)
    assert shared_map(square, list(range(7)), cost=float) == [x * x for x in range(7)]
    monkeypatch.setenv(WORKERS_ENV, "two")
    with pytest.raises(BadInput, match=WORKERS_ENV):
        shared_map(square, [1, 2], cost=float)


@linux_only
def test_the_block_runs_while_the_children_work_and_its_failure_ends_them(monkeypatch):
    monkeypatch.setenv(WORKERS_ENV, "3")
    with sharing(lambda x: x * x, list(range(7)), cost=float) as results:
        assert results == []  # filled on leaving the block, this process joining in
    assert results == [x * x for x in range(7)] and not multiprocessing.active_children()
    with pytest.raises(RuntimeError, match="tables"), sharing(lambda x: x * x, list(range(7)), cost=float) as results:
        raise RuntimeError("tables")
    assert results == [] and not multiprocessing.active_children()
