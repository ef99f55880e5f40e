"""The report's CPU-bound work shared with forked children: drawing the figures is most of `riskplan report`,
loading the runs most of the rest.

    shared_map(draw, specs, cost) == [draw(spec) for spec in specs], on the CPUs this process may use
    with sharing(draw, specs, cost) as drawn:  # the children start at once; this process works on the tables
        tables = ...
    drawn == [draw(spec) for spec in specs]  # this process joined in on leaving the block

The children are forked, so they inherit what this process built (matplotlib figures) without pickling it, and
send back only their results; every file is still written by this process. Items are handed out one at a time from
a shared counter, costliest first, so whoever finishes first takes the next and the cheap ones at the end even out
the finish (the figures' costs differ threefold). Whatever a child did not deliver (it died) is computed here
afterwards: the result never depends on the children. `function` should not raise (return the failure instead): an
exception ends a child, and its items then raise here. The children die with this process, however it dies (a
SIGTERM or SIGKILL runs no clean-up here): none is left waiting on a pipe no one reads.

While the items are shared, what existed before (the runs, the figures) is out of the garbage collector's full
passes (gc.freeze): they walked every object, in this process and into each child's copy.

`progress(done, total)`, where given, hears in this process how much of the work has finished, whoever did it:
the items' `weight` (1 each by default) summed as they finish, e.g. runs where an item is a condition's seeds.

Fork is Linux only here (unsafe on macOS, missing on Windows); elsewhere, and on one CPU, all runs in this process.
RISKPLAN_REPORT_WORKERS sets the number of processes (1: no children), e.g. to compare both paths in the tests.
"""

from __future__ import annotations

import contextlib
import gc
import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from riskplan.util.errors import BadInput
from riskplan.util.interrupt import die_with_parent

WORKERS_ENV = "RISKPLAN_REPORT_WORKERS"


def workers() -> int:
    """Processes to share the work between (this one included)."""
    text = os.environ.get(WORKERS_ENV, "").strip()
    if text and not (text.isascii() and text.isdigit() and int(text) >= 1):  # '²' is a digit int() refuses
        raise BadInput(WORKERS_ENV, f"got '{text}'; expected a whole number >= 1 (1: all in this process)")
    if not sys.platform.startswith("linux"):
        return 1
    return int(text) if text else len(os.sched_getaffinity(0))


Progress = Callable[[int, int], None]  # progress(done, total), in the items' weights


def shared_map(
    function: Callable[[Any], Any],
    items: Sequence,
    cost: Callable[[Any], float],
    progress: Progress | None = None,
    weight: Callable[[Any], int] = lambda item: 1,
) -> list:
    """[function(item) for item in items], this process and forked children taking items in turn, in decreasing
    (estimated) cost."""
    with sharing(function, items, cost, progress, weight) as results:
        pass
    return results


@contextlib.contextmanager
def sharing(
    function: Callable[[Any], Any],
    items: Sequence,
    cost: Callable[[Any], float],
    progress: Progress | None = None,
    weight: Callable[[Any], int] = lambda item: 1,
) -> Iterator[list]:
    """shared_map begun on entering: the children take items while the block runs here, and this process joins
    them on leaving; the list yielded then holds [function(item) for item in items]. When the block (or `function`
    here) raises, the children are ended."""
    results: list = []
    children = min(workers(), len(items)) - 1
    weights = [weight(item) for item in items]
    with _long_lived():
        if children < 1:
            finished = _Finished(_Count(), weights, progress)
            yield results
            for i, item in enumerate(items):
                results.append(function(item))
                finished.add(i)
            return
        context = multiprocessing.get_context("fork")
        counter = context.Value("i", 0)  # the next position in `order`
        finished = _Finished(context.Value("q", 0), weights, progress)
        order = sorted(range(len(items)), key=lambda i: -cost(items[i]))
        started = _fork(context, children, function, items, order, counter, finished)
        try:
            yield results
            done = _share(function, items, order, counter, finished)
            done.update(_gather(started, finished))
        except BaseException:  # the block, or `function` here: no child is left waiting to be read
            for child, receive in started:
                child.terminate()
                child.join()
                receive.close()
            raise
        for i, item in enumerate(items):
            if i not in done:  # a child died with it
                done[i] = function(item)
                finished.add(i)
        results.extend(done[i] for i in range(len(items)))


class _Finished:
    """The weight of the items finished so far by any process (`value`: shared with the children), told to
    `progress` when it grows in this process (the children only add). At most the total: the items a child
    finished before it died are added again when this process computes them."""

    def __init__(self, value, weights: list[int], progress: Progress | None):
        self.value, self.weights, self.progress = value, weights, progress
        self.total, self.home = sum(weights), os.getpid()

    def add(self, index: int) -> None:
        with self.value.get_lock():
            self.value.value += self.weights[index]
        self.tell()

    def tell(self) -> None:
        if self.progress is not None and os.getpid() == self.home:
            self.progress(min(int(self.value.value), self.total), self.total)


class _Count:
    """A Value's interface for one process: no lock needed."""

    value = 0

    def get_lock(self) -> contextlib.nullcontext:
        return contextlib.nullcontext()


def _gather(started: list, finished: _Finished) -> dict[int, Any]:
    """The children's results as each sends them ({index: result}; nothing of one that died), telling the
    progress meanwhile."""
    done: dict[int, Any] = {}
    waiting = {receive: child for child, receive in started}
    while waiting:
        for receive in multiprocessing.connection.wait(list(waiting), timeout=0.1):
            try:
                done.update(receive.recv())
            except (EOFError, OSError):
                pass  # the child died: its items are computed afterwards
            receive.close()
            waiting.pop(receive).join()
        finished.tell()
    return done


@contextlib.contextmanager
def _long_lived() -> Iterator[None]:
    """The objects alive now (the runs, the figures) out of the collector's full passes while the block runs
    (gc.freeze), here and in the children forked meanwhile: each pass over them cost a tenth of the report, and
    made a child copy every page it touched. Left alone when something else froze objects first (only it may
    release them)."""
    if gc.get_freeze_count():
        yield
        return
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def _fork(
    context, children: int, function: Callable[[Any], Any], items: Sequence, order: list[int], counter, finished
) -> list:
    """Up to `children` forked children taking items (fewer when fork fails): (process, the end of its pipe that
    this process reads)."""
    started = []
    for _ in range(children):
        receive, send = context.Pipe(duplex=False)
        child = context.Process(
            target=_child, args=(function, items, order, counter, finished, send, os.getpid()), daemon=True
        )
        try:
            child.start()
        except (AssertionError, OSError):  # no fork here (a daemonic process, no memory or pids left): fewer hands
            receive.close()
            break
        finally:
            send.close()  # the child holds the only write end now: its death reads as EOF below
        started.append((child, receive))
    return started


def _share(
    function: Callable[[Any], Any], items: Sequence, order: list[int], counter, finished: _Finished
) -> dict[int, Any]:
    """Take the next item until none is left; {index: result} of those taken, each added to `finished`."""
    results = {}
    while True:
        with counter.get_lock():
            position = counter.value
            counter.value += 1
        if position >= len(order):
            return results
        results[order[position]] = function(items[order[position]])
        finished.add(order[position])


def _child(
    function: Callable[[Any], Any], items: Sequence, order: list[int], counter, finished, send, parent: int
) -> None:
    # Ctrl-C reaches the whole process group: the parent stops the report; a child's KeyboardInterrupt would only
    # print its traceback ("Process ForkProcess-4: ...") before the parent's one line
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # a parent killed (SIGTERM, SIGKILL) runs no `except`: its children would wait forever to send their results
    die_with_parent()
    if os.getppid() != parent:  # it died before the line above
        os._exit(1)
    send.send(_share(function, items, order, counter, finished))
    send.close()
