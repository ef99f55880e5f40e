"""Counter-based random numbers: every episode owns a stream keyed by (seed, purpose, iteration, robot, episode).

Keys make results independent of thread count, chunking and resume: no generator carries state across episodes.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

MASK = (1 << 64) - 1
SEED_LIMIT = 1 << 63  # seeds are whole numbers 0 <= seed < 2^63 (checked by riskplan.run.build): none alias under MASK
GOLDEN = 0x9E3779B97F4A7C15

# Stream purposes: independent streams for each use of randomness.
TRAIN, EVAL, PATHS, BOOTSTRAP, LANDSCAPE, ENVIRONMENT = 1, 2, 3, 4, 5, 6


def _mix_int(z: int) -> int:
    """splitmix64 finaliser on a Python int (matches `mix`)."""
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK
    return z ^ (z >> 31)


def stream_key(*parts: int) -> int:
    """Fold integers into one 64-bit key."""
    key = 0
    for part in parts:
        key = _mix_int((key + GOLDEN + (int(part) & MASK)) & MASK)
    return key


def robot_keys(seed: int, purpose: int, iteration: int, robots: int) -> np.ndarray:
    """One uint64 key per robot for an iteration's episodes: stream_key(seed, purpose, iteration, r) for every r,
    its last fold done for all robots at once in uint64 arithmetic (which wraps modulo 2^64, as MASK does)."""
    if robots <= 4:  # a few robots: Python ints are quicker than numpy's small-array overhead
        return np.array([stream_key(seed, purpose, iteration, r) for r in range(robots)], dtype=np.uint64)
    z = np.uint64((stream_key(seed, purpose, iteration) + GOLDEN) & MASK) + np.arange(robots, dtype=np.uint64)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(inline="always")
def mul(a, b):
    """a * b. The helpers below write a product that a sum takes as mul(a, b): riskplan.engine.cuda_rollout compiles
    their own source for the GPU with `mul` bound to a product rounded on its own (never fused into an FMA), so both
    devices round alike."""
    return a * b


@njit(inline="always")
def mix(z):
    """splitmix64 finaliser."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(inline="always")
def episode_state(key, episode):
    """Initial state of one episode's stream."""
    return mix(key ^ mix(np.uint64(episode) + np.uint64(GOLDEN)))


@njit(cache=True)
def episode_states(key, count):
    """The initial states of the streams of episodes 0..count-1 of `key` (uint64, (count,))."""
    states = np.empty(count, dtype=np.uint64)
    for e in range(count):
        states[e] = episode_state(key, e)
    return states


@njit(cache=True)
def resample_counts(key, b, n):
    """How often bootstrap resample b (its own stream of `key`) draws each of n indices: one 64-bit draw gives two
    indices, floor(u * n / 2^32) of its 32-bit halves u (Lemire's multiply-shift): half the draws, and each index's
    probability is within 2^-32 of 1/n (a relative error below n / 2^32)."""
    counts = np.empty(n, dtype=np.int32)
    count_resample(key, b, counts, np.empty(n, dtype=np.uint32))
    return counts


@njit(cache=True, nogil=True)
def count_resample(key, b, counts, drawn):
    """`resample_counts` into `counts` (n int32, overwritten), with `drawn` (n uint32) for scratch. A kernel that
    bootstraps many resamples passes the same two arrays each time (no 400 kB to allocate and zero per resample at
    n = 100,000), and the indices are drawn first, in a loop of independent steps the compiler vectorises, then
    counted: together 1.8 times quicker than drawing and counting each in turn."""
    n = counts.size
    size = np.uint64(n)
    half, low = np.uint64(32), np.uint64(0xFFFFFFFF)
    state = episode_state(key, b)
    for j in range(n // 2):
        state = state + np.uint64(GOLDEN)
        bits = mix(state)
        drawn[2 * j] = ((bits & low) * size) >> half
        drawn[2 * j + 1] = ((bits >> half) * size) >> half
    if n % 2:
        state = state + np.uint64(GOLDEN)
        drawn[n - 1] = ((mix(state) & low) * size) >> half
    counts[:] = 0
    for j in range(n):
        counts[drawn[j]] += 1


# Bootstrap resamples drawn and summed side by side (`count_lanes`, `lane_sums`: inlined into the kernels that call
# them, so a first run compiles no unit of their own).
LANES = 4


@njit(inline="always")
def count_lanes(key, first, used, lanes, drawn):
    """The counts of resamples first..first+used-1 (`count_resample`) into rows 0..used-1 of lanes (LANES, n int32);
    the other rows keep what they held."""
    for lane in range(used):
        count_resample(key, first + lane, lanes[lane], drawn)


@njit(inline="always")
def lane_sums(lanes, values):
    """sum_i lanes[k, i] * values[i] for each row k of lanes (LANES, n), each in the order i = 0..n-1: the four
    sums run side by side, since a sum's additions wait on each other and four chains keep the core busy (the same
    numbers as one sum at a time, a quarter of the time or less)."""
    c0, c1, c2, c3 = lanes[0], lanes[1], lanes[2], lanes[3]
    t0 = t1 = t2 = t3 = 0.0
    for i in range(values.size):
        value = values[i]
        t0 += c0[i] * value
        t1 += c1[i] * value
        t2 += c2[i] * value
        t3 += c3[i] * value
    return t0, t1, t2, t3


@njit(inline="always")
def next_bits(state):
    """Advance a stream: (new state, 53 random bits m as a uint64); the uniform of `next_uniform` is bits_uniform(m)."""
    state = state + np.uint64(GOLDEN)
    return state, mix(state) >> np.uint64(11)


@njit(inline="always")
def bits_uniform(m):
    """The uniform (m + 0.5) / 2^53 in the open interval (0, 1) of 53 random bits m."""
    return (m + 0.5) * (1.0 / 9007199254740992.0)


@njit(inline="always")
def next_uniform(state):
    """Advance a stream: (new state, uniform in the open interval (0, 1))."""
    state, m = next_bits(state)
    return state, bits_uniform(m)


# The stream and the ziggurat have a twin in experiments/baselines/one_kernel.py: a baseline may not import riskplan.
def _ziggurat(layers: int = 256, r: float = 3.6541528853610088) -> tuple[np.ndarray, np.ndarray]:
    """Marsaglia-Tsang ziggurat of exp(-x^2/2) in `layers` strips of equal area v (Doornik's ZIGNOR layout).

    Returns x (layers + 1,): x[0] = v / f(r) is the base strip's width (rectangle plus tail), x[1] = r, x[i + 1]
    the edge of the strip above x[i], x[layers] = 0; and ratio[i] = x[i + 1] / x[i], the fast-accept bound.
    """
    f = math.exp(-0.5 * r * r)
    v = r * f + math.sqrt(math.pi / 2.0) * math.erfc(r / math.sqrt(2.0))  # base strip: rectangle + tail
    x = np.zeros(layers + 1)
    x[0], x[1] = v / f, r
    for i in range(2, layers):
        x[i] = math.sqrt(-2.0 * math.log(v / x[i - 1] + f))
        f = math.exp(-0.5 * x[i] * x[i])
    return x, x[1:] / x[:-1]


ZIG_X, ZIG_RATIO = _ziggurat()
ZIG_R = float(ZIG_X[1])


@njit(inline="always")
def next_normal(state):
    """Advance a stream: (new state, a standard normal draw), by the ziggurat (exact; tests/engine/test_kernel_fast_paths.py).

    One 64-bit word gives the strip (low 8 bits) and a signed uniform (top 52 bits); 99% of draws are accepted at
    once, the rest (`_normal_edge`: wedges and the tail beyond r) take more words of the same stream. |draw| < 14.
    """
    state = state + np.uint64(GOLDEN)
    bits = mix(state)
    i = np.int64(bits & np.uint64(255))
    u = mul((bits >> np.uint64(12)) + 0.5, 1.0 / 2251799813685248.0) - 1.0  # (-1, 1), never 0, symmetric
    if abs(u) < ZIG_RATIO[i]:
        return state, mul(u, ZIG_X[i])
    return _normal_edge(state, i, u)


@njit
def _normal_edge(state, i, u):
    """The ziggurat's rare paths (1% of draws), out of line so the fast path stays small. On a GPU, exp and log are
    CUDA's (libdevice), so a draw on these paths can differ from the CPU's in its last bits (docs/gpu.md)."""
    while True:
        if i == 0:  # the tail beyond r (Marsaglia 1964)
            while True:
                state, a = next_uniform(state)
                state, b = next_uniform(state)
                t = -math.log(a) / ZIG_R
                if mul(-2.0, math.log(b)) >= mul(t, t):
                    return state, ZIG_R + t if u > 0.0 else -(ZIG_R + t)
        z = mul(u, ZIG_X[i])  # a wedge: accept under the curve
        f0 = math.exp(mul(-0.5, mul(ZIG_X[i], ZIG_X[i]) - mul(z, z)))
        f1 = math.exp(mul(-0.5, mul(ZIG_X[i + 1], ZIG_X[i + 1]) - mul(z, z)))
        state, c = next_uniform(state)
        if f1 + mul(c, f0 - f1) < 1.0:
            return state, z
        state = state + np.uint64(GOLDEN)  # rejected: start again from the next word
        bits = mix(state)
        i = np.int64(bits & np.uint64(255))
        u = mul((bits >> np.uint64(12)) + 0.5, 1.0 / 2251799813685248.0) - 1.0
        if abs(u) < ZIG_RATIO[i]:
            return state, mul(u, ZIG_X[i])


@njit(inline="always")
def _quantile_tail(q):
    """Acklam's tail approximation at q = sqrt(-2 log p), for p below 0.02425 (its mirror image above 0.97575)."""
    return (
        (
            (
                ((-7.784894002430293e-03 * q - 3.223964580411365e-01) * q - 2.400758277161838e00) * q
                - 2.549732539343734e00
            )
            * q
            + 4.374664141464968e00
        )
        * q
        + 2.938163982698783e00
    ) / (
        (((7.784695709041462e-03 * q + 3.224671290700398e-01) * q + 2.445134137142996e00) * q + 3.754408661907416e00)
        * q
        + 1.0
    )


@njit(inline="always")
def normal_quantile(p):
    """Inverse standard-normal CDF (Acklam's rational approximation, relative error < 1.2e-9).

    The kernel's normal sampler before the ziggurat (`simulate(..., reference=True)`): the reference that
    tests/engine/test_kernel_fast_paths.py compares the ziggurat and the kernel's return distributions against.
    """
    if p < 0.02425:
        return _quantile_tail(math.sqrt(-2.0 * math.log(p)))
    if p > 0.97575:
        return -_quantile_tail(math.sqrt(-2.0 * math.log(1.0 - p)))
    q = p - 0.5
    r = q * q
    return (
        (
            (
                (
                    ((-3.969683028665376e01 * r + 2.209460984245205e02) * r - 2.759285104469687e02) * r
                    + 1.383577518672690e02
                )
                * r
                - 3.066479806614716e01
            )
            * r
            + 2.506628277459239e00
        )
        * q
        / (
            (
                (
                    ((-5.447609879822406e01 * r + 1.615858368580409e02) * r - 1.556989798598866e02) * r
                    + 6.680131188771972e01
                )
                * r
                - 1.328068155288572e01
            )
            * r
            + 1.0
        )
    )
