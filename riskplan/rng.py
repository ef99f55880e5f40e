"""Counter-based random numbers: every episode owns a stream keyed by (seed, purpose, iteration, robot, episode).

Keys make results independent of thread count, chunking and resume: no generator carries state across episodes.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

MASK = (1 << 64) - 1
SEED_LIMIT = 1 << 63  # seeds are whole numbers 0 <= seed < 2^63 (checked by riskplan.setup): none alias under MASK
GOLDEN = 0x9E3779B97F4A7C15

# Stream purposes: independent streams for each use of randomness.
TRAIN, EVAL, PATHS, BOOTSTRAP, LANDSCAPE = 1, 2, 3, 4, 5


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
    """One uint64 key per robot for an iteration's episodes."""
    return np.array([stream_key(seed, purpose, iteration, r) for r in range(robots)], dtype=np.uint64)


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


@njit(inline="always")
def next_uniform(state):
    """Advance a stream: (new state, uniform in the open interval (0, 1))."""
    state = state + np.uint64(GOLDEN)
    return state, ((mix(state) >> np.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0)


@njit(inline="always")
def normal_quantile(p):
    """Inverse standard-normal CDF (Acklam's rational approximation, relative error < 1.2e-9)."""
    if p < 0.02425:
        q = math.sqrt(-2.0 * math.log(p))
        return (((((-7.784894002430293e-03 * q - 3.223964580411365e-01) * q - 2.400758277161838e00) * q
                  - 2.549732539343734e00) * q + 4.374664141464968e00) * q + 2.938163982698783e00) / (
            (((7.784695709041462e-03 * q + 3.224671290700398e-01) * q + 2.445134137142996e00) * q
             + 3.754408661907416e00) * q + 1.0)
    if p > 0.97575:
        q = math.sqrt(-2.0 * math.log(1.0 - p))
        return -(((((-7.784894002430293e-03 * q - 3.223964580411365e-01) * q - 2.400758277161838e00) * q
                   - 2.549732539343734e00) * q + 4.374664141464968e00) * q + 2.938163982698783e00) / (
            (((7.784695709041462e-03 * q + 3.224671290700398e-01) * q + 2.445134137142996e00) * q
             + 3.754408661907416e00) * q + 1.0)
    q = p - 0.5
    r = q * q
    return (((((-3.969683028665376e01 * r + 2.209460984245205e02) * r - 2.759285104469687e02) * r
              + 1.383577518672690e02) * r - 3.066479806614716e01) * r + 2.506628277459239e00) * q / (
        ((((-5.447609879822406e01 * r + 1.615858368580409e02) * r - 1.556989798598866e02) * r
          + 6.680131188771972e01) * r - 1.328068155288572e01) * r + 1.0)
