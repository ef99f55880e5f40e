"""The training step's statistics and gradients of a large sample on every core, bit for bit numpy's numbers.

A floating-point sum depends on its order, so these kernels keep numpy's:
  * numpy sums a row pairwise (a tree whose leaves are blocks of at most 128 values, each summed by 8
    accumulators): the tree's top levels are cut into LEAVES subtrees, summed in parallel, then added up the tree
    as numpy adds them. The mean, the standard deviation and CVaR's tail sum are numpy's.
  * VaR is the ceil(beta W)-th smallest value, one element of the row: a parallel histogram of the row's values
    in BUCKETS intervals over a strided sample's range (a monotone map, so the element lies in the bucket where
    the counts reach its rank), then numpy's partition of that bucket's few values; the same element, so the same
    number. With one thread numpy's partition is the quicker, and runs instead.
  * numpy's einsum of a gradient, sum_i w_i S_im, adds the products in index order for each m (M >= 2): the
    kernels take the (robot, m) sums in parallel, each in index order. CVaR's weights vanish outside the tail
    (z_i >= v), and adding 0 leaves a sum unchanged, so its gradient adds the tail's products alone.

Used for W >= PARALLEL_SAMPLES, where it pays (riskplan bench --threads measures it), by callers that pass
finite samples and scores (`parallel=True` in riskplan.engine.estimators: the training step checks z, and its
scores are finite by construction). Smaller samples and M = 1 (einsum then sums in SIMD lanes) take numpy itself,
and with one thread so do the plain sum and VaR, where numpy's own loops are the quicker.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np
from numba import njit, prange

PARALLEL_SAMPLES = 1 << 15  # samples per row from which the step's statistics run in parallel
LEAVES = 64  # numpy's pairwise tree cut at depth 6: every leaf holds > 128 values for W >= PARALLEL_SAMPLES
BLOCK = 128  # numpy's PW_BLOCKSIZE: a block summed by 8 accumulators
BUCKETS = 256  # intervals of VaR's histogram
REFINE = 4096  # a VaR bucket with more values than this is split again before numpy partitions it
PROBE = 4096  # values of the strided sample whose range VaR's buckets span
COLUMNS = 8  # gradient columns m summed side by side by one task (a cache line of scores per sample)
SUM, TAIL, SQUARES = 0, 1, 2  # what `_pairwise` sums: x, min(x - shift, 0) (CVaR's tail), (x - shift)^2 (std)


@functools.lru_cache(maxsize=64)
def leaves(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The first index and the length of each of the LEAVES subtrees of numpy's pairwise sum of n values, left to
    right: each node of more than BLOCK values splits at n2 = n // 2 rounded down to a multiple of 8."""
    nodes = [(0, n)]
    while len(nodes) < LEAVES:
        split = []
        for first, count in nodes:
            if count <= BLOCK:
                raise ValueError(f"{n} values are too few for {LEAVES} pairwise leaves")
            half = count // 2
            half -= half % 8
            split += [(first, half), (first + half, count - half)]
        nodes = split
    first, count = np.array(nodes, dtype=np.int64).T
    return np.ascontiguousarray(first), np.ascontiguousarray(count)


def row_sums(z: np.ndarray, mode: int = SUM, shift: np.ndarray | None = None) -> np.ndarray:
    """numpy's z.sum(axis=-1) of z (R, W) (mode SUM), of np.minimum(z - shift, 0) (TAIL) or of (z - shift)**2
    (SQUARES), shift (R,) one per row: numpy's pairwise tree, its leaves in parallel."""
    if mode == SUM and numba.get_num_threads() == 1:  # one thread: numpy's own loop is the quicker
        return z.sum(axis=-1)
    first, count = leaves(z.shape[1])
    shifts = np.zeros(z.shape[0]) if shift is None else np.ascontiguousarray(shift, dtype=np.float64)
    parts = np.empty((z.shape[0], LEAVES))
    _leaf_sums(z, first, count, mode, shifts, parts)
    while parts.shape[1] > 1:  # up the tree: each node is its left subtree's sum plus its right's
        parts = parts[:, 0::2] + parts[:, 1::2]
    return 0.0 + parts[:, 0]  # the reduction's identity, 0.0, plus the tree's sum


def value_at_risk(z: np.ndarray, m: int) -> np.ndarray:
    """np.partition(z, m - 1, axis=-1)[:, m - 1] of finite z (R, W): each row's m-th smallest element."""
    if numba.get_num_threads() == 1:  # one thread: numpy's introselect is the quicker
        return np.partition(z, m - 1, axis=-1)[:, m - 1]
    bounds = np.linspace(0, z.shape[1], LEAVES + 1).astype(np.int64)  # a row's chunks
    return np.array([_select(row, bounds, m - 1) for row in z])


def _select(row: np.ndarray, bounds: np.ndarray, k: int) -> float:
    """The k-th smallest (from 0) of `row`: the bucket where the counts pass k, split again while it holds more
    than REFINE values, then numpy's partition of its values. The buckets span a strided sample's range (values
    outside it fall in the end buckets: the map stays monotone)."""
    probe = row[:: max(1, row.size // PROBE)]
    low, high = probe.min(), probe.max()
    while True:
        with np.errstate(over="ignore", divide="ignore"):
            scale = BUCKETS / (high - low)
        if not (np.isfinite(scale) and scale > 0.0):  # a span of one value, or too wide to bucket
            return np.partition(row, k)[k]
        counts = np.zeros((len(bounds) - 1, BUCKETS), dtype=np.int64)
        negative_zero = np.zeros(len(bounds) - 1, dtype=np.int64)
        _bucket_counts(row, bounds, low, scale, counts, negative_zero)
        if negative_zero.any():  # -0.0 and 0.0 tie: which one numpy returns is its own affair
            return np.partition(row, k)[k]
        below = np.cumsum(counts.sum(axis=0))  # values in buckets 0..b
        bucket = int(np.searchsorted(below, k, side="right"))  # the first bucket with more than k values up to it
        k -= int(below[bucket - 1]) if bucket else 0
        offsets = np.concatenate([[0], np.cumsum(counts[:, bucket])])
        values = np.empty(int(offsets[-1]))
        _gather_bucket(row, bounds, low, scale, bucket, offsets, values)
        low, high = values.min(), values.max()
        if low == high:  # every value of the bucket is the k-th
            return low
        if values.size <= REFINE:
            return np.partition(values, k)[k]
        row, bounds = values, np.linspace(0, values.size, len(bounds)).astype(np.int64)


def tail_products(z: np.ndarray, scores: np.ndarray, v: np.ndarray) -> np.ndarray:
    """numpy's einsum("rw,rwm->rm", np.minimum(z - v[:, None], 0), scores) for M >= 2: per (row, m), the products
    of the tail (z_i < v) added in index order (the other weights are 0, which leaves a sum unchanged)."""
    rows, n = z.shape
    first, count = leaves(n)
    found = np.empty((rows, LEAVES), dtype=np.int64)
    _tail_counts(z, first, count, v, found)
    offsets = np.concatenate([[0], np.cumsum(found)])
    tail = np.empty(int(offsets[-1]), dtype=np.int64)
    _tail_indices(z, first, count, v, offsets, tail)
    out = np.empty((rows, scores.shape[2]))
    _indexed_products(z, scores, tail, offsets[::LEAVES].copy(), v, out)
    return out


def centred_products(z: np.ndarray, scores: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """numpy's einsum("rw,rwm->rm", z - centre[:, None], scores) for M >= 2: per (row, m), in index order."""
    out = np.empty((z.shape[0], scores.shape[2]))
    _centred_products(z, scores, np.ascontiguousarray(centre, dtype=np.float64), out)
    return out


@njit(cache=True)
def _term(x, mode, shift):
    """The summand of x in `_pairwise`'s mode."""
    if mode == TAIL:
        return min(x - shift, 0.0)
    if mode == SQUARES:
        d = x - shift
        return d * d
    return x


@njit(cache=True)
def _pairwise(z, first, n, mode, shift):
    """numpy's pairwise sum (loops_utils.h.src, pairwise_sum) of the n terms from z[first]."""
    if n < 8:
        res = 0.0
        for i in range(first, first + n):
            res += _term(z[i], mode, shift)
        return res
    if n <= BLOCK:
        r0 = _term(z[first], mode, shift)
        r1 = _term(z[first + 1], mode, shift)
        r2 = _term(z[first + 2], mode, shift)
        r3 = _term(z[first + 3], mode, shift)
        r4 = _term(z[first + 4], mode, shift)
        r5 = _term(z[first + 5], mode, shift)
        r6 = _term(z[first + 6], mode, shift)
        r7 = _term(z[first + 7], mode, shift)
        i = 8
        while i < n - n % 8:
            at = first + i
            r0 += _term(z[at], mode, shift)
            r1 += _term(z[at + 1], mode, shift)
            r2 += _term(z[at + 2], mode, shift)
            r3 += _term(z[at + 3], mode, shift)
            r4 += _term(z[at + 4], mode, shift)
            r5 += _term(z[at + 5], mode, shift)
            r6 += _term(z[at + 6], mode, shift)
            r7 += _term(z[at + 7], mode, shift)
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < n:
            res += _term(z[first + i], mode, shift)
            i += 1
        return res
    half = n // 2
    half -= half % 8
    return _pairwise(z, first, half, mode, shift) + _pairwise(z, first + half, n - half, mode, shift)


@njit(parallel=True, cache=True)
def _leaf_sums(z, first, count, mode, shifts, out):
    """out[r, j] = the pairwise sum of leaf j of row r, every (row, leaf) in parallel."""
    leaves_per_row = first.shape[0]
    for task in prange(z.shape[0] * leaves_per_row):
        r, j = task // leaves_per_row, task % leaves_per_row
        out[r, j] = _pairwise(z[r], first[j], count[j], mode, shifts[r])


@njit(cache=True, inline="always")
def _bucket(x, low, scale):
    """The histogram bucket of x, the end buckets taking what lies beyond [low, low + BUCKETS / scale]: monotone
    in x (x <= y gives bucket(x) <= bucket(y))."""
    return np.int64(min(max((x - low) * scale, 0.0), BUCKETS - 1.0))


@njit(parallel=True, cache=True)
def _bucket_counts(row, bounds, low, scale, counts, negative_zero):
    """counts[c, b]: the values of chunk c in bucket b; negative_zero[c]: its values -0.0."""
    for c in prange(bounds.shape[0] - 1):
        zeros = 0
        for i in range(bounds[c], bounds[c + 1]):
            x = row[i]
            counts[c, _bucket(x, low, scale)] += 1
            if x == 0.0 and math.copysign(1.0, x) < 0.0:
                zeros += 1
        negative_zero[c] = zeros


@njit(parallel=True, cache=True)
def _gather_bucket(row, bounds, low, scale, bucket, offsets, out):
    """The values of bucket `bucket`, chunk c's from out[offsets[c]] on."""
    for c in prange(bounds.shape[0] - 1):
        k = offsets[c]
        for i in range(bounds[c], bounds[c + 1]):
            if _bucket(row[i], low, scale) == bucket:
                out[k] = row[i]
                k += 1


@njit(parallel=True, cache=True)
def _tail_counts(z, first, count, v, out):
    """out[r, j]: the values below v[r] in leaf j of row r."""
    leaves_per_row = first.shape[0]
    for task in prange(z.shape[0] * leaves_per_row):
        r, j = task // leaves_per_row, task % leaves_per_row
        found = 0
        for i in range(first[j], first[j] + count[j]):
            if z[r, i] < v[r]:
                found += 1
        out[r, j] = found


@njit(parallel=True, cache=True)
def _tail_indices(z, first, count, v, offsets, out):
    """The indices of the values below v[r], in order, (row r, leaf j)'s from out[offsets[r * leaves + j]] on."""
    leaves_per_row = first.shape[0]
    for task in prange(z.shape[0] * leaves_per_row):
        r, j = task // leaves_per_row, task % leaves_per_row
        k = offsets[task]
        for i in range(first[j], first[j] + count[j]):
            if z[r, i] < v[r]:
                out[k] = i
                k += 1


@njit(parallel=True, cache=True)
def _indexed_products(z, scores, index, row_offsets, v, out):
    """out[r, m] = sum over row r's listed indices i, in order, of min(z[r, i] - v[r], 0) scores[r, i, m]: a task
    per (row, m) below COLUMNS columns (a row of scores is within a cache line), else per (row, block of COLUMNS
    m's) summed side by side (a cache line of scores per sample)."""
    dims = scores.shape[2]
    width = 1 if dims < COLUMNS else COLUMNS
    blocks = (dims + width - 1) // width
    for task in prange(z.shape[0] * blocks):
        r, b = task // blocks, task % blocks
        if width == 1:
            acc = 0.0
            for k in range(row_offsets[r], row_offsets[r + 1]):
                i = index[k]
                acc += min(z[r, i] - v[r], 0.0) * scores[r, i, b]
            out[r, b] = acc
        else:
            first, last = b * width, min(dims, (b + 1) * width)
            sums = np.zeros(width)
            for k in range(row_offsets[r], row_offsets[r + 1]):
                i = index[k]
                w = min(z[r, i] - v[r], 0.0)
                for m in range(first, last):
                    sums[m - first] += w * scores[r, i, m]
            out[r, first:last] = sums[: last - first]


@njit(parallel=True, cache=True)
def _centred_products(z, scores, centre, out):
    """out[r, m] = sum over i, in order, of (z[r, i] - centre[r]) scores[r, i, m]; tasks as `_indexed_products`.
    Its twin over every index: one kernel for both would read an index or branch on the weight at every product."""
    dims = scores.shape[2]
    width = 1 if dims < COLUMNS else COLUMNS
    blocks = (dims + width - 1) // width
    for task in prange(z.shape[0] * blocks):
        r, b = task // blocks, task % blocks
        if width == 1:
            acc = 0.0
            for i in range(z.shape[1]):
                acc += (z[r, i] - centre[r]) * scores[r, i, b]
            out[r, b] = acc
        else:
            first, last = b * width, min(dims, (b + 1) * width)
            sums = np.zeros(width)
            for i in range(z.shape[1]):
                w = z[r, i] - centre[r]
                for m in range(first, last):
                    sums[m - first] += w * scores[r, i, m]
            out[r, first:last] = sums[: last - first]
