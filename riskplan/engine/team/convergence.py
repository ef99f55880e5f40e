"""How far a team is from agreement: the consensus error max ||theta^i - theta^j||, and the SLEM of a mixing matrix
(the per-round contraction that consensus on a fixed graph achieves)."""

from __future__ import annotations

import math

import numpy as np


def second_largest_eigenvalue_modulus(weights2d: np.ndarray) -> float:
    """SLEM of an N x N weight matrix: the per-round consensus contraction on a fixed graph (0 for N = 1)."""
    w = np.asarray(weights2d, dtype=float)
    if w.ndim != 2 or w.shape[0] != w.shape[1]:
        raise ValueError(f"expected a square matrix, got shape {w.shape}")
    if len(w) <= 1:
        return 0.0
    # eigvalsh is exact to rounding for the symmetric (undirected, doubly stochastic) case.
    values = np.linalg.eigvalsh(w) if np.allclose(w, w.T, rtol=0, atol=1e-14) else np.linalg.eigvals(w)
    return float(np.sort(np.abs(values))[-2])


def consensus_error(thetas: np.ndarray) -> float:
    """max_{i,j} ||theta^i - theta^j||_2 over the rows of an (N, M) array; 0.0 for N = 1.

    Exact: the very number of the brute force over all pairs (`_largest_squared_gap` of every row against all
    rows), found    without its N x N x M temporaries. Around the centroid c, any pair is at most r_i + r_j apart (r = |theta - c|),
    so the rows are taken farthest first, each against all rows, until no pair of the rows left can beat the best
    gap found (`_gap_bound`, which allows for rounding). A round cloud needs a few dozen rows; the worst case (every
    row as far from c) takes them all, in blocks.

    Finite rows whose squared gaps overflow (gaps beyond about 1e154, where the brute force says inf) are measured
    again scaled by a power of two (`_rescaled`): the true error when a float holds it, else inf (the engine's step
    stops on that: riskplan.engine.step.check_agreement). Every other answer is the brute force's, bit for bit.
    """
    t = np.asarray(thetas, dtype=float)
    if t.ndim != 2:
        raise ValueError(f"expected thetas of shape (N, M), got {t.shape}")
    with np.errstate(over="ignore"):  # a square that overflows gives inf, measured again just below
        error = _unscaled_error(t)
    if error == math.inf and np.isfinite(t).all():
        return _rescaled(t)
    return error


def _rescaled(t: np.ndarray) -> float:
    """consensus_error of finite rows whose squared gaps overflow: the rows scaled by 2^-e, e the exponent of the
    widest coordinate's half range (so every scaled gap is below 2 and no square overflows), measured, and the
    error scaled back by 2^e (exact scalings: the brute force's number in a float of unbounded exponent); inf when
    it is beyond the largest float."""
    half_range = float(np.max(t.max(axis=0) * 0.5 - t.min(axis=0) * 0.5))  # no overflow: each term <= 0.9e308
    exponent = int(np.frexp(half_range)[1])
    with np.errstate(over="ignore"):
        return float(np.ldexp(_unscaled_error(np.ldexp(t, -exponent)), exponent))


def _unscaled_error(t: np.ndarray) -> float:
    """consensus_error as computed in t's own scale (inf when a squared gap overflows)."""
    n, m = t.shape
    if n <= 1:
        return 0.0
    if (t == t[0]).all():
        return 0.0  # every gap is exactly 0 (this also covers M = 0)
    if n <= _GAP_ROWS or not np.isfinite(t).all():
        return float(np.sqrt(_largest_squared_gap(t, np.arange(n))))
    with np.errstate(over="ignore"):  # huge rows give infinite radii: no pruning, the brute force's own answer
        radii = np.sqrt(((t - t.mean(axis=0)) ** 2).sum(axis=-1))
    order = np.argsort(-radii, kind="stable")
    radii = radii[order]
    best, done, k = -np.inf, 0, _GAP_ROWS
    while done < n:
        best = np.maximum(best, _largest_squared_gap(t, order[done:k]))
        done = k
        if done >= n - 1 or _gap_bound(radii[done] + radii[done + 1], m) ** 2 <= best:
            break  # every pair not compared has both rows within radii[done] of c
        k = min(n, 2 * k)
    return float(np.sqrt(best))


_GAP_ROWS = 32  # rows compared with all rows in the first block of consensus_error
_GAP_BLOCK = 1 << 20  # at most this many numbers in one block's (rows, N, M) temporary


def _largest_squared_gap(t: np.ndarray, rows: np.ndarray) -> float:
    """max over `rows` i and all j of the brute force's squared gap sum_m (t_im - t_jm)^2 (computed alike)."""
    per_block = max(1, _GAP_BLOCK // max(1, t.size))
    best = -np.inf
    for first in range(0, len(rows), per_block):
        gaps = t[rows[first : first + per_block], None, :] - t[None, :, :]
        best = np.maximum(best, (gaps**2).sum(axis=-1).max())  # NaN stays NaN, as in the brute force
    return best


def _gap_bound(radii_sum: float, m: int) -> float:
    """An upper bound on any computed gap |theta^i - theta^j| of two rows whose computed radii sum to `radii_sum`.

    The exact gap is at most the exact radii's sum (triangle inequality); each computed norm is within a relative
    (M + 3) 2^-53 of its exact value, and an underflowing square loses at most 2^-1074 each. The slack below is
    orders of magnitude wider than that and still tight enough to stop early.
    """
    return radii_sum * (1.0 + (m + 4) * 2.0**-40) + 1e-150
