"""A serial numba kernel (nogil) run over a range split among numba's thread count of threads.

Each item of the range is computed on its own (a bootstrap resample), so the numbers do not depend on the split.
Threads rather than a parallel (prange) kernel: a serial kernel compiles in a third of the time, and a run's first
start compiles it (riskplan bench: the first run).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numba


def over_threads(kernel, count: int, *args) -> None:
    """kernel(*args, begin, end) over consecutive parts of range(count), a thread each (none when one would do)."""
    workers = max(1, min(numba.get_num_threads(), count))
    if workers == 1:
        kernel(*args, 0, count)
        return
    bounds = [count * k // workers for k in range(workers + 1)]
    with ThreadPoolExecutor(workers) as pool:
        for done in [pool.submit(kernel, *args, bounds[k], bounds[k + 1]) for k in range(workers)]:
            done.result()
