"""Figures drawn on all cores (riskplan.experiments.reporting.parallel): work no worker delivered, whether the worker
died or could not be forked, is done in this process; a bad worker count is bad input. Whole reports drawn by
workers are compared with one process's in test_report_contents.py."""

from __future__ import annotations

import multiprocessing
import os
import sys
import time

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
    before = set(multiprocessing.active_children())  # an earlier test's sweep workers (loky's, kept for reuse)
    with sharing(lambda x: x * x, list(range(7)), cost=float) as results:
        assert results == []  # filled on leaving the block, this process joining in
    assert results == [x * x for x in range(7)] and set(multiprocessing.active_children()) <= before
    with pytest.raises(RuntimeError, match="tables"), sharing(lambda x: x * x, list(range(7)), cost=float) as results:
        raise RuntimeError("tables")
    assert results == [] and set(multiprocessing.active_children()) <= before


@pytest.mark.parametrize("workers", ["1", "3"])
def test_progress_hears_the_weight_finished_so_far_up_to_the_total(monkeypatch, workers):
    monkeypatch.setenv(WORKERS_ENV, workers)
    heard = []
    batches = [[1, 2], [3], [4, 5, 6], [7]]  # e.g. a condition's seeds: progress counts the runs
    assert shared_map(sum, batches, cost=len, progress=lambda *told: heard.append(told), weight=len) == [3, 3, 15, 7]
    done = [d for d, _ in heard]
    assert {t for _, t in heard} == {7} and done == sorted(done) and done[-1] == 7
    if workers == "1":
        assert done == [2, 3, 6, 7]  # each batch as it finishes, in order


@linux_only
def test_progress_stays_within_the_total_when_a_child_dies(monkeypatch):
    parent, taken = os.getpid(), []

    def square(x):  # the child finishes one item and dies on its next: this process computes that item again
        if os.getpid() == parent:
            time.sleep(0.2 if x == 6 else 0.0)  # the costliest, taken first: the child meanwhile takes the next
        else:
            taken.append(x)
            if len(taken) == 2:
                os._exit(1)
        return x * x

    monkeypatch.setenv(WORKERS_ENV, "2")
    heard = []
    assert shared_map(square, list(range(7)), cost=float, progress=lambda *told: heard.append(told)) == [
        x * x for x in range(7)
    ]
    assert heard[-1] == (7, 7) and all(d <= t == 7 for d, t in heard)
