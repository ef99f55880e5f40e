"""The report's CPU-bound work shared with forked children: drawing the figures is most of `riskplan report`.

    shared_map(draw, specs, cost) == [draw(spec) for spec in specs], on the CPUs this process may use

The children are forked, so they inherit what this process built (matplotlib figures) without pickling it, and
send back only their results; every file is still written by this process. Items are handed out one at a time from
a shared counter, costliest first, so whoever finishes first takes the next and the cheap ones at the end even out
the finish (the figures' costs differ threefold). Whatever a child did not deliver (it died) is computed here
afterwards: the result never depends on the children. `function` must not raise (return the failure instead), as
its exceptions would end a child.

Fork is Linux only here (unsafe on macOS, missing on Windows); elsewhere, and on one CPU, all runs in this process.
RISKPLAN_REPORT_WORKERS sets the number of processes (1: no children), e.g. to compare both paths in the tests.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
from collections.abc import Callable, Sequence
from typing import Any

from riskplan.util.errors import BadInput

WORKERS_ENV = "RISKPLAN_REPORT_WORKERS"


def workers() -> int:
    """Processes to share the work between (this one included)."""
    text = os.environ.get(WORKERS_ENV, "").strip()
    if text and not (text.isdigit() and int(text) >= 1):
        raise BadInput(WORKERS_ENV, f"got '{text}'; expected a whole number >= 1 (1: all in this process)")
    if not sys.platform.startswith("linux"):
        return 1
    return int(text) if text else len(os.sched_getaffinity(0))


def shared_map(function: Callable[[Any], Any], items: Sequence, cost: Callable[[Any], float]) -> list:
    """[function(item) for item in items], this process and forked children taking items in turn, in decreasing
    (estimated) cost."""
    children = min(workers(), len(items)) - 1
    if children < 1:
        return [function(item) for item in items]
    context = multiprocessing.get_context("fork")
    counter = context.Value("i", 0)  # the next position in `order`
    order = sorted(range(len(items)), key=lambda i: -cost(items[i]))
    started = []
    for _ in range(children):
        receive, send = context.Pipe(duplex=False)
        child = context.Process(target=_child, args=(function, items, order, counter, send), daemon=True)
        try:
            child.start()
        except (AssertionError, OSError):  # no fork here (a daemonic process, no memory or pids left): fewer hands
            receive.close()
            break
        finally:
            send.close()  # the child holds the only write end now: its death reads as EOF below
        started.append((child, receive))
    results = _share(function, items, order, counter)
    for child, receive in started:
        try:
            results.update(receive.recv())
        except (EOFError, OSError):
            pass  # the child died: its items are computed below
        receive.close()
        child.join()
    return [results[i] if i in results else function(item) for i, item in enumerate(items)]


def _share(function: Callable[[Any], Any], items: Sequence, order: list[int], counter) -> dict[int, Any]:
    """Take the next item until none is left; {index: result} of those taken."""
    results = {}
    while True:
        with counter.get_lock():
            position = counter.value
            counter.value += 1
        if position >= len(order):
            return results
        results[order[position]] = function(items[order[position]])


def _child(function: Callable[[Any], Any], items: Sequence, order: list[int], counter, send) -> None:
    send.send(_share(function, items, order, counter))
    send.close()
