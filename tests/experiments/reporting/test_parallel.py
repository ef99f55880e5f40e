"""Figures drawn on all cores (riskplan.experiments.reporting.parallel): work no worker delivered, whether the worker
died or could not be forked, is done in this process; a bad worker count is bad input. Whole reports drawn by
workers are compared with one process's in test_report_contents.py."""

from __future__ import annotations

import multiprocessing
import os
import signal
import subprocess
import sys
import time

import pytest
from support import alive

from riskplan.experiments.reporting.parallel import WORKERS_ENV, shared_map, sharing
from riskplan.util.errors import BadInput
from riskplan.util.interrupt import descendants

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


PARENT = """
import os, sys, time
from riskplan.experiments.reporting.parallel import shared_map
shared_map(lambda item: time.sleep(60), list(range(4)), cost=lambda item: 1.0)
"""


@pytest.mark.slow  # a second each: the children are given time to start working
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGKILL])
def test_children_end_with_a_parent_killed_while_they_work(tmp_path, signum):
    """A report or export killed by SIGTERM or SIGKILL runs no `except`: its forked children outlived it, each
    blocked for good on the pipe no one would read. Now the kernel ends them with it (PR_SET_PDEATHSIG)."""
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT], env={**os.environ, WORKERS_ENV: "3"}, stderr=subprocess.DEVNULL
    )
    deadline = time.time() + 30
    while len(descendants(parent.pid)) < 2 and time.time() < deadline:
        time.sleep(0.05)
    children = descendants(parent.pid)
    assert len(children) == 2
    parent.send_signal(signum)
    parent.wait(timeout=30)
    deadline = time.time() + 10
    while any(alive(pid) for pid in children) and time.time() < deadline:
        time.sleep(0.05)
    assert not any(alive(pid) for pid in children)
