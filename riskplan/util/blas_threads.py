"""numpy's BLAS threads in a process that is the `riskplan` command line.

riskplan's compute runs in numba kernels, which own the cores (`numba.set_num_threads`). BLAS gets only small
problems (a source's 2x2 covariance, a gradient's norm), which OpenBLAS runs on the calling thread whatever its pool
holds. Yet numpy's OpenBLAS (and scipy's, where installed) starts a pool at import whose threads spin while they
wait for work: on a machine with few cores they took a core from the command itself (docs/benchmarks.md has the
figures). A command-line process therefore starts OpenBLAS with one thread, and so do the processes that
inherit its environment (local sweep jobs, SLURM jobs; Ray gives its workers OMP_NUM_THREADS=1 itself). An
OPENBLAS_NUM_THREADS the user set is kept. Results do not depend on it.
"""

from __future__ import annotations

import os

BLAS_THREADS = "OPENBLAS_NUM_THREADS"  # read once, when numpy (or scipy) loads OpenBLAS


def single_threaded_blas() -> None:
    """OpenBLAS, when it loads in this process or its children, runs one thread unless OPENBLAS_NUM_THREADS says
    otherwise."""
    os.environ.setdefault(BLAS_THREADS, "1")
