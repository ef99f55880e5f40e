"""The estimators behind the risk measures (paper eqs. 4-9, Algorithm 1): plain arrays in, arrays out.

CVaR is the Rockafellar-Uryasev form at the empirical quantile:
    cvar = v + (1 / (beta W)) * sum_i (z_i - v) 1{z_i <= v},   v = z_(m), m = ceil(beta W)
which equals the mean of the m lowest samples when beta W is whole and there are no ties (eq. 6), and whose
score-function gradient is eq. (9).

A spectral measure, rho = int_0^1 phi(u) F^-1(u) du with distortion g(u) = int_0^u phi, is estimated by the
L-statistic sum_k z_(k) [g(k/W) - g((k-1)/W)], and its gradient E[S h(Z)], h(z) = -int_z^max phi(F(t)) dt, with
the empirical F (`spectral_estimates`, from the measure's tables of weights and phi). The measures themselves, one
object each, are in riskplan.engine.measures.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

from riskplan.engine import reductions
from riskplan.engine.sorting import argsort_into, workspace
from riskplan.util.errors import BadInput


def tail_count(beta: float, n: int) -> int:
    """m = ceil(beta * n), guarded against float error (0.07 * 100 gives 7, not 8)."""
    if isinstance(beta, (bool, np.bool_)) or not isinstance(beta, (int, float, np.integer, np.floating)):
        raise BadInput("beta", f"must be a number in (0, 1], got {beta!r}")  # a bool or "0.1" is no level
    if not 0.0 < beta <= 1.0:
        raise BadInput("beta", f"must be in (0, 1], got {beta}")
    if n < 1:
        raise BadInput("z", "need at least one sample")
    product = beta * n
    nearest = round(product)
    m = nearest if abs(product - nearest) <= 1e-9 * max(1.0, product) else math.ceil(product)
    return int(min(max(m, 1), n))


def value_at_risk(z: np.ndarray, beta: float) -> np.ndarray | float:
    """beta-VaR (eq. 5/8): the ceil(beta W)-th smallest sample, along the last axis; NaN for a row holding a NaN,
    as `cvar` and the mean give (numpy's partition would sort the NaN last and ignore it)."""
    z = as_sample(z)
    return _nan_where_nan(z, _quantile(z, beta))


def _nan_where_nan(z: np.ndarray, v: np.ndarray | float) -> np.ndarray | float:
    """v with NaN for each row of z that holds a NaN."""
    return np.where(np.isnan(z).any(axis=-1), np.nan, v)[()]


def cvar(z: np.ndarray, beta: float) -> np.ndarray | float:
    """beta-CVaR, Rockafellar-Uryasev form at the empirical quantile (last axis); cvar(z, 1) is mean(z) up to rounding.

    A finite row whose tail sum overflows (samples near the largest float) is measured again on z / 2^k, exact for
    such numbers, and scaled back: CVaR is positively homogeneous, and lies within the row's range."""
    return _without_overflow(lambda rows: _cvar(rows, beta), as_sample(z))


def mean(z: np.ndarray) -> np.ndarray | float:
    """The mean along the last axis; a finite row whose sum overflows (samples near the largest float) is its mean
    still, as for `cvar`."""
    return _without_overflow(lambda rows: rows.mean(axis=-1), as_sample(z))


def _without_overflow(measure, z: np.ndarray) -> np.ndarray | float:
    """measure(z) along the last axis. A finite row whose sums (or squares) overflow is measured again on z / 2^k,
    2^k the power of two just below its largest |z| (an exact division: every value within (-2, 2)), and scaled
    back: the measure is positively homogeneous, and within the row's range (or, for the std, half its width)."""
    with np.errstate(over="ignore", invalid="ignore"):
        value = np.asarray(measure(z))
    if np.isfinite(value).all():  # the common case: no second pass over z
        return value[()]
    overflowed = ~np.isfinite(value) & np.isfinite(z).all(axis=-1)
    if overflowed.any():
        peak = np.abs(np.where(np.isfinite(z), z, 0.0)).max(axis=-1, keepdims=True)
        scale = np.ldexp(1.0, np.frexp(np.maximum(peak, 1.0))[1] - 1)  # 2^(e-1) for peak = m 2^e, m in [0.5, 1)
        with np.errstate(over="ignore", invalid="ignore"):
            value = np.where(overflowed, np.asarray(measure(z / scale)) * scale[..., 0], value)
    return value[()]


def _cvar(z: np.ndarray, beta: float) -> np.ndarray | float:
    v = _quantile(z, beta)
    return v + _tail_weights(z, v).sum(axis=-1) / (beta * z.shape[-1])


def _quantile(z: np.ndarray, beta: float) -> np.ndarray | float:
    """The ceil(beta W)-th smallest sample of each row (a NaN sorts last)."""
    m = tail_count(beta, z.shape[-1])
    return np.partition(z, m - 1, axis=-1)[..., m - 1][()]  # [()] gives a scalar for 1-D input


def cvar_gradient(z: np.ndarray, scores: np.ndarray, beta: float, var=None, *, parallel: bool = False) -> np.ndarray:
    """Eq. (9): (1 / (beta W)) sum_i score_i (z_i - v) 1{z_i <= v}; z (..., W), scores (..., W, M) -> (..., M).

    `var`: value_at_risk(z, beta) when the caller has it already (it costs a partition of z). `parallel`: z and
    scores are finite (a training step's), and a large sample may take the parallel kernels
    (riskplan.engine.reductions): the same numbers.
    """
    z = as_sample(z)
    scores = as_scores(z, scores)
    if parallel and _large(z, scores):
        rows, table = _rows(z, scores)
        v = _row_values(z, var) if var is not None else reductions.value_at_risk(rows, tail_count(beta, z.shape[-1]))
        grads = reductions.tail_products(rows, table, v)
        return grads.reshape(scores.shape[:-2] + scores.shape[-1:]) / (beta * z.shape[-1])
    weights = _tail_weights(z, _quantile(z, beta) if var is None else var)
    return np.einsum("...w,...wm->...m", weights, scores) / (beta * z.shape[-1])


def mean_gradient(z: np.ndarray, scores: np.ndarray, baseline: bool = True, *, parallel: bool = False) -> np.ndarray:
    """REINFORCE estimate of grad E[Z] (eq. 4): mean of score_i (z_i - b), b = mean(z) by default, else 0.
    `parallel`: as `cvar_gradient`'s."""
    z = as_sample(z)
    scores = as_scores(z, scores)
    if parallel and _large(z, scores):
        rows, table = _rows(z, scores)
        centre = reductions.row_sums(rows) / z.shape[-1] if baseline else np.zeros(len(rows))
        grads = reductions.centred_products(rows, table, centre)
        return grads.reshape(scores.shape[:-2] + scores.shape[-1:]) / z.shape[-1]
    centred = z - np.expand_dims(mean(z), -1) if baseline else z
    return np.einsum("...w,...wm->...m", centred, scores) / z.shape[-1]


def summary_stats(z: np.ndarray, beta: float, *, parallel: bool = False) -> dict[str, np.ndarray | float]:
    """mean, cvar, value_at_risk at beta and std along the last axis, with one partition. `parallel`: z is finite
    (a training step's), and a large sample may take the parallel kernels (riskplan.engine.reductions): the same
    numbers."""
    z = np.asarray(z, dtype=float)
    if parallel and z.ndim >= 1 and z.shape[-1] >= reductions.PARALLEL_SAMPLES:
        return _summary_rows(z, beta)
    v = _quantile(z, beta)
    with np.errstate(over="ignore", invalid="ignore"):
        tail = v + _tail_weights(z, v).sum(axis=-1) / (beta * z.shape[-1])
    return {  # samples near the largest float: each measured again without overflow, as `cvar` and `mean` are
        "mean": mean(z),
        "cvar": tail if np.isfinite(tail).all() else cvar(z, beta),
        "value_at_risk": _nan_where_nan(z, v),
        "std": _without_overflow(lambda rows: rows.std(axis=-1), z),
    }


def _summary_rows(z: np.ndarray, beta: float) -> dict[str, np.ndarray | float]:
    """`summary_stats` of a large finite sample by the parallel kernels: numpy's sums in numpy's order, and the
    element numpy's partition selects."""
    n = z.shape[-1]
    rows = kernel_input(z.reshape(-1, n))
    mean = reductions.row_sums(rows) / n
    v = reductions.value_at_risk(rows, tail_count(beta, n))
    stats = {
        "mean": mean,
        "cvar": v + reductions.row_sums(rows, reductions.TAIL, v) / (beta * n),
        "value_at_risk": v,
        "std": np.sqrt(reductions.row_sums(rows, reductions.SQUARES, mean) / n),
    }
    return {name: values.reshape(z.shape[:-1])[()] for name, values in stats.items()}


def _large(z: np.ndarray, scores: np.ndarray) -> bool:
    """Whether a gradient of z (..., W) and scores (..., W, M) takes the parallel kernels: W >= PARALLEL_SAMPLES
    and M >= 2 (numpy's einsum sums M = 1 in SIMD lanes, an order the kernels do not keep)."""
    return (
        z.ndim >= 1
        and z.shape[-1] >= reductions.PARALLEL_SAMPLES
        and scores.shape[-1] >= 2
        and scores.shape[:-1] == z.shape
    )


def _rows(z: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """z as rows (R, W) and scores as (R, W, M), the kernels' layout."""
    n = z.shape[-1]
    return kernel_input(z.reshape(-1, n)), kernel_input(scores.reshape(-1, n, scores.shape[-1]))


def _row_values(z: np.ndarray, values) -> np.ndarray:
    """One value per row of z (..., W): `values` (z.shape[:-1]) as a (R,) array."""
    return np.ascontiguousarray(np.broadcast_to(np.asarray(values, dtype=float), z.shape[:-1]).reshape(-1))


def _tail_weights(z: np.ndarray, v: np.ndarray | float) -> np.ndarray:
    """(z_i - v) 1{z_i <= v}, broadcasting v over the last axis."""
    return np.minimum(z - np.expand_dims(v, -1), 0.0)


# --- Mean-CVaR, entropic, the L-statistics, Phi and Phi^-1 -----------------------------------------------------------------------------


def mean_cvar_mix(mean_part: np.ndarray, cvar_part: np.ndarray, weight: float) -> np.ndarray:
    """(1 - lambda) mean_part + lambda cvar_part, exactly the one part when lambda is 0 or 1: mean-CVaR's objective
    or gradient from its parts, which a caller may have already (the training loop's statistics)."""
    if weight == 0.0:
        return np.asarray(mean_part)
    if weight == 1.0:
        return np.asarray(cvar_part)
    return (1.0 - weight) * mean_part + weight * cvar_part


def entropic(z: np.ndarray, eta: float) -> np.ndarray | float:
    """-(1/eta) log E[exp(-eta Z)] along the last axis, stably for large eta |z| and for eta -> 0 (`_entropic_parts`)."""
    centre, log_mean, _ = _entropic_parts(as_sample(z), check_eta(eta))
    return (centre - log_mean / eta)[..., 0][()]


def entropic_gradient(z: np.ndarray, scores: np.ndarray, eta: float, *, baseline: bool = True) -> np.ndarray:
    """-(1/eta) sum_i (w_i - 1/W) S_i, w = softmax(-eta z): the self-normalised likelihood-ratio gradient.

    The -1/W is a baseline: sum_i S_i / W estimates E[S] = 0. `baseline=False` drops it.
    """
    eta = check_eta(eta)
    z = as_sample(z)
    scores = as_scores(z, scores)
    _, _, centred = _entropic_parts(z, eta)
    weights = centred if baseline else centred + 1.0 / z.shape[-1]
    return np.einsum("...w,...wm->...m", weights, scores) / -eta


def _entropic_parts(z: np.ndarray, eta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(c, log E[exp(x)], softmax(x) - 1/W) along the last axis, x = -eta (z - c), c = mean z; the first two
    keepdims. The entropic risk is c - log E[exp(x)] / eta, whatever c.

    The log-sum-exp shifted by max x, so nothing overflows, where max x >= 1; where max x < 1 (eta |z - mean| small),
    by expm1 and log1p, so -(1/eta) log E[exp(x)] and the weights keep their relative accuracy as eta -> 0. Where
    eta |z - mean| itself overflows (eta near the largest float), c is the row's smallest z instead: x <= 0 there,
    an exponential that underflows is 0, and the sum, >= 1, has a finite logarithm.
    """
    n = z.shape[-1]
    mean = z.mean(axis=-1, keepdims=True)
    with np.errstate(over="ignore"):  # an infinite x is taken care of below
        x = -eta * (z - mean)
    top = x.max(axis=-1, keepdims=True)
    wide = top == np.inf
    if np.any(wide):  # only there do the numbers differ from those of the mean as c
        low = z.min(axis=-1, keepdims=True)
        with np.errstate(over="ignore"):  # -inf: a weight of 0
            x = np.where(wide, -eta * (z - low), x)
        mean, top = np.where(wide, low, mean), np.where(wide, 0.0, top)
    small = (top < 1.0) & ~wide
    if np.any(small):
        u = np.expm1(np.where(small, x, 0.0))  # the large rows' x would overflow here: they take the other branch
        u_mean = u.mean(axis=-1, keepdims=True)
        small_parts = np.log1p(u_mean), (u - u_mean) / (n * (1.0 + u_mean))
        if np.all(small):
            return mean, *small_parts
    with np.errstate(over="ignore"):  # x - top below the largest -float: a weight of 0
        e = np.exp(x - top)
    total = e.sum(axis=-1, keepdims=True)
    large_parts = top + np.log(total / n), e / total - 1.0 / n
    if not np.any(small):
        return mean, *large_parts
    return mean, *(np.where(small, s, b) for s, b in zip(small_parts, large_parts))


def normal_cdf(x: np.ndarray) -> np.ndarray:
    """Phi(x) = erfc(-x / sqrt 2) / 2, vectorised (numba), accurate in both tails."""
    return _elementwise(_ndtr_flat, np.asarray(x, dtype=float))


def normal_quantile(p: np.ndarray) -> np.ndarray:
    """Phi^-1(p), vectorised (numba): Acklam's approximation + one Halley step; -inf at 0, inf at 1, nan outside."""
    return _elementwise(_ndtri_flat, np.asarray(p, dtype=float))


def l_statistics(z: np.ndarray, weights: np.ndarray) -> np.ndarray | float:
    """sum_k z_(k) weights[k] along the last axis (ascending order): a spectral measure's plug-in estimate, from its
    L-statistic weights g(k/W) - g((k-1)/W); a float for 1-D z."""
    rows = kernel_input(z.reshape(-1, z.shape[-1]))
    out = np.empty(rows.shape[0])
    _l_statistic_rows(rows, weights, out)
    return out.reshape(z.shape[:-1])[()]


def spectral_estimates(
    z: np.ndarray, scores: np.ndarray, weights: np.ndarray, phi: np.ndarray, baseline: bool
) -> tuple[np.ndarray | float, np.ndarray]:
    """(`l_statistics`, the spectral gradient) of z (..., W) and scores (..., W, M), from one sort of each row: the
    gradient is (1/W) sum_i S_i (h(z_i) - b), h(z_(k)) = -sum_{j=k}^{W-1} phi(j/W) (z_(j+1) - z_(j)), with
    phi[j - 1] = phi(j/W), and b = mean(h) or 0."""
    n = z.shape[-1]
    rows = kernel_input(z.reshape(-1, n))
    values, grads = np.empty(rows.shape[0]), np.empty((rows.shape[0], scores.shape[-1]))
    _spectral_rows(rows, kernel_input(scores.reshape(-1, n, scores.shape[-1])), weights, phi, baseline, values, grads)
    return values.reshape(z.shape[:-1])[()], grads.reshape(scores.shape[:-2] + scores.shape[-1:])


def check_eta(eta: Any) -> float:
    """A checked eta: a finite number > 0 (BadInput otherwise)."""
    if isinstance(eta, bool) or not isinstance(eta, (int, float, np.integer, np.floating)):
        raise BadInput("eta", f"must be a number, got {eta!r}")
    if not (math.isfinite(eta) and eta > 0.0):
        raise BadInput("eta", f"must be finite and > 0, got {eta}")
    return float(eta)


def as_count(n: Any) -> int:
    """A checked sample count W >= 1."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise BadInput("n", f"need at least one sample (W >= 1), got {n!r}")
    return int(n)


def as_sample(z: Any) -> np.ndarray:
    """z as a float array (..., W) with W >= 1: real numbers (a complex or text sample is refused, not cast)."""
    z = _real_array(z, "z")
    if z.ndim < 1 or z.shape[-1] < 1:
        raise BadInput("z", f"must have shape (..., W) with W >= 1 samples, got shape {z.shape}")
    return z


def as_scores(z: np.ndarray, scores: Any) -> np.ndarray:
    """scores as a float array of shape z.shape + (M,)."""
    scores = _real_array(scores, "scores")
    if scores.ndim != z.ndim + 1 or scores.shape[:-1] != z.shape:
        raise BadInput("scores", f"must have shape {(*z.shape, 'M')} for z of shape {z.shape}, got {scores.shape}")
    return scores


def _real_array(values: Any, key: str) -> np.ndarray:
    """values as a float array; BadInput naming `key` for values that are not real numbers (numpy would drop a
    complex number's imaginary part with a warning, or fail on text with a line that names no argument)."""
    array = np.asarray(values)
    if array.dtype.kind in "biuf":  # bool, integers, floats
        return array.astype(float, copy=False)
    if array.dtype.kind == "O":  # Python objects: real numbers among them are fine
        try:
            return array.astype(float)
        except (TypeError, ValueError):
            pass
    what = "complex numbers" if array.dtype.kind == "c" else f"values of dtype {array.dtype}"
    raise BadInput(key, f"got {what}; expected real numbers")


@njit(cache=True)
def _l_statistic_rows(z, weights, out):
    """out[r] = sum_k sort(z[r])_k weights[k] for each row of z (R, W)."""
    order = np.empty(z.shape[1], np.int64)
    keys, spare, counts = workspace(z.shape[1])
    for r in range(z.shape[0]):
        argsort_into(z[r], order, keys, spare, counts)
        total = 0.0
        for k in range(z.shape[1]):
            total += z[r, order[k]] * weights[k]
        out[r] = total


@njit(cache=True)
def _spectral_rows(z, scores, weights, phi, baseline, values, out):
    """`l_statistic` and `spectral_gradient` of each row: z (R, W), scores (R, W, M), the L-statistic weights,
    phi[j - 1] = phi(j/W) -> values (R,), out (R, M).

    The value sums z_(k) weights[k] in ascending order, as `_l_statistic_rows` does: the same number. h is
    accumulated from the top sample down (h(z_(W)) = 0), so tied samples get the same h whatever their order.
    """
    rows, n, dims = scores.shape
    h = np.empty(n)
    order = np.empty(n, np.int64)
    keys, spare, counts = workspace(n)
    for r in range(rows):
        argsort_into(z[r], order, keys, spare, counts)
        total = 0.0
        for k in range(n):
            total += z[r, order[k]] * weights[k]
        values[r] = total
        acc = 0.0
        total = 0.0
        above = z[r, order[n - 1]]
        h[order[n - 1]] = 0.0
        for k in range(n - 2, -1, -1):
            here = z[r, order[k]]
            acc -= phi[k] * (above - here)
            h[order[k]] = acc
            total += acc
            above = here
        b = total / n if baseline else 0.0
        for m in range(dims):
            out[r, m] = 0.0
        for i in range(n):
            c = h[i] - b
            for m in range(dims):
                out[r, m] += c * scores[r, i, m]
        for m in range(dims):
            out[r, m] /= n


# Acklam's rational approximation of Phi^-1 (relative error < 1.2e-9), coefficients as in riskplan.engine.rng
_A = (-3.969683028665376e01, 2.209460984245205e02, -2.759285104469687e02, 1.383577518672690e02, -3.066479806614716e01)
_A0 = 2.506628277459239e00
_B = (-5.447609879822406e01, 1.615858368580409e02, -1.556989798598866e02, 6.680131188771972e01, -1.328068155288572e01)
_C = (
    -7.784894002430293e-03,
    -3.223964580411365e-01,
    -2.400758277161838e00,
    -2.549732539343734e00,
    4.374664141464968e00,
)
_C0 = 2.938163982698783e00
_D = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e00, 3.754408661907416e00)
_SQRT2 = math.sqrt(2.0)
_SQRT2PI = math.sqrt(2.0 * math.pi)


@njit(cache=True)
def _ndtri_lower(p):
    """Phi^-1(p) for 0 < p <= 0.5: Acklam, then one Halley step on Phi(x) - p (relative error ~1e-16)."""
    if p < 0.02425:
        q = math.sqrt(-2.0 * math.log(p))
        x = (((((_C[0] * q + _C[1]) * q + _C[2]) * q + _C[3]) * q + _C[4]) * q + _C0) / (
            (((_D[0] * q + _D[1]) * q + _D[2]) * q + _D[3]) * q + 1.0
        )
    else:
        q = p - 0.5
        r = q * q
        x = (
            (((((_A[0] * r + _A[1]) * r + _A[2]) * r + _A[3]) * r + _A[4]) * r + _A0)
            * q
            / (((((_B[0] * r + _B[1]) * r + _B[2]) * r + _B[3]) * r + _B[4]) * r + 1.0)
        )
    if x > -37.5:  # below, exp(x^2 / 2) overflows (p < 1e-300): Acklam alone
        # Phi(x) - p, by erf near the centre (p - 0.5 is exact there) to keep the relative accuracy of a small x
        e = 0.5 * math.erf(x / _SQRT2) - (p - 0.5) if p > 0.25 else 0.5 * math.erfc(-x / _SQRT2) - p
        u = e * _SQRT2PI * math.exp(0.5 * x * x)
        x = x - u / (1.0 + 0.5 * x * u)
    return x


@njit(cache=True)
def _ndtri_scalar(p):
    """Phi^-1(p), by symmetry from the lower half (1 - p is exact for p >= 0.5); -inf at 0, inf at 1, nan outside."""
    if p > 0.0 and p < 1.0:
        return -_ndtri_lower(1.0 - p) if p > 0.5 else _ndtri_lower(p)
    if p == 0.0:
        return -np.inf
    if p == 1.0:
        return np.inf
    return np.nan


@njit(cache=True)
def _ndtri_flat(p, out):
    """out[i] = Phi^-1(p[i]) over 1-D arrays."""
    for i in range(p.size):
        out[i] = _ndtri_scalar(p[i])


@njit(cache=True)
def _ndtr_flat(x, out):
    """out[i] = Phi(x[i]) = erfc(-x[i] / sqrt 2) / 2 over 1-D arrays."""
    for i in range(x.size):
        out[i] = 0.5 * math.erfc(-x[i] / _SQRT2)


def kernel_input(values: np.ndarray) -> np.ndarray:
    """A float64, C-contiguous, writable array (copied only when it is not): a read-only input (a parquet column)
    would make numba compile, and cache, a second specialisation of every kernel it reaches."""
    return np.require(values, dtype=np.float64, requirements=["C", "W"])


def _elementwise(kernel, values: np.ndarray) -> np.ndarray:
    """kernel(flat, out) applied to an array of any shape (a 0-d input gives a numpy float)."""
    flat = kernel_input(values).ravel()
    out = np.empty_like(flat)
    kernel(flat, out)
    return out.reshape(np.shape(values))[()]
