"""A stable argsort of float64 rows by LSD radix: the spectral measures' L-statistics sort every sample of every
iteration, and a comparison sort of W = 6000 fresh returns (numba's quicksort) mispredicts its branches, where six
counting passes do not branch on the data. Any correct sort gives the same sorted values, so the numbers do not
change."""

from __future__ import annotations

import numpy as np
from numba import njit

DIGIT_BITS = 11  # 6 passes cover 64 bits; 2048 counters per pass stay in L1
PASSES = 6
SMALL = 256  # below this many samples a comparison sort wins: the counters would cost more than the sort


@njit(cache=True)
def workspace(n):
    """The scratch arrays of `argsort_into` for rows of n samples: (keys (2, n), indices (n,), counts)."""
    return np.empty((2, n), np.uint64), np.empty(n, np.int64), np.empty((PASSES, 1 << DIGIT_BITS), np.int64)


@njit(cache=True)
def argsort_into(row, order, keys, spare, counts):
    """order = np.argsort(row, kind="stable") for a row without NaN: LSD radix on the order-preserving uint64 keys
    of its bits (negatives: all bits flipped; others: the sign bit set; -0.0 counts as 0.0, as comparisons do), one
    counting pass per 11-bit digit, skipping a digit that all keys share. `keys`, `spare` and `counts` come from
    `workspace`."""
    n = row.shape[0]
    if n < SMALL:
        order[:] = np.argsort(row, kind="mergesort")
        return
    mask = np.uint64((1 << DIGIT_BITS) - 1)
    sign = np.uint64(1) << np.uint64(63)
    counts[:] = 0
    for i in range(n):
        b = np.float64(row[i] + 0.0).view(np.uint64)
        k = ~b if b & sign else b | sign
        keys[0, i] = k
        order[i] = i
        for d in range(PASSES):
            counts[d, (k >> np.uint64(DIGIT_BITS * d)) & mask] += 1
    source, target = order, spare
    here = 0
    for d in range(PASSES):
        shift = np.uint64(DIGIT_BITS * d)
        count = counts[d]
        if count[(keys[here, 0] >> shift) & mask] == n:
            continue
        total = 0
        for j in range(count.shape[0]):
            c = count[j]
            count[j] = total
            total += c
        for i in range(n):
            k = keys[here, i]
            j = (k >> shift) & mask
            p = count[j]
            count[j] = p + 1
            keys[1 - here, p] = k
            target[p] = source[i]
        here = 1 - here
        source, target = target, source
    if source is not order:
        order[:] = source
