"""Not riskplan: the baseline of `riskplan bench`'s first-run row: a program that imports numba and compiles one parallel rollout
kernel of riskplan's kind, and nothing else (numpy and numba only; run as a script, it never imports riskplan).

The kernel runs the paper world's episodes as riskplan's training kernel does (riskplan.engine.rollout): one
counter-based SplitMix64 stream per episode, the move picked by integer compares of 53 random bits against the
policy's bins, the score accumulated from per-(cell, move) tables, a region reward clip(c + w U + s N) with
ziggurat normals (the rare edge draws out of line), a source's reward mean + sd N, risky steps, the source reached
and the steps taken, episodes in parallel chunks of 64. It is written plainly, for one world and one policy kind:
the least a run must compile. With an empty NUMBA_CACHE_DIR, its wall time from start to exit is what a first
`riskplan train` is compared with.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

# The stream and the ziggurat below twin riskplan.engine.rng's: a baseline may not import riskplan
# (tests/experiments/test_baselines.py holds their numbers equal, bit for bit).
GOLDEN = np.uint64(0x9E3779B97F4A7C15)
CHUNK = 64


def ziggurat(layers: int = 256, r: float = 3.6541528853610088) -> tuple[np.ndarray, np.ndarray]:
    """Strip edges x (layers + 1,) and fast-accept ratios of exp(-x^2/2) in strips of equal area."""
    f = math.exp(-0.5 * r * r)
    v = r * f + math.sqrt(math.pi / 2.0) * math.erfc(r / math.sqrt(2.0))
    x = np.zeros(layers + 1)
    x[0], x[1] = v / f, r
    for i in range(2, layers):
        x[i] = math.sqrt(-2.0 * math.log(v / x[i - 1] + f))
        f = math.exp(-0.5 * x[i] * x[i])
    return x, x[1:] / x[:-1]


ZIG_X, ZIG_RATIO = ziggurat()
ZIG_R = float(ZIG_X[1])


@njit(inline="always")
def mix(z):
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(inline="always")
def next_bits(state):
    state = state + GOLDEN
    return state, mix(state) >> np.uint64(11)


@njit(inline="always")
def next_uniform(state):
    state, m = next_bits(state)
    return state, (m + 0.5) * (1.0 / 9007199254740992.0)


@njit(cache=True)
def normal_edge(state, i, u):
    """The ziggurat's wedges and tail."""
    while True:
        if i == 0:
            while True:
                state, a = next_uniform(state)
                state, b = next_uniform(state)
                t = -math.log(a) / ZIG_R
                if -2.0 * math.log(b) >= t * t:
                    return state, ZIG_R + t if u > 0.0 else -(ZIG_R + t)
        z = u * ZIG_X[i]
        f0 = math.exp(-0.5 * (ZIG_X[i] * ZIG_X[i] - z * z))
        f1 = math.exp(-0.5 * (ZIG_X[i + 1] * ZIG_X[i + 1] - z * z))
        state, c = next_uniform(state)
        if f1 + c * (f0 - f1) < 1.0:
            return state, z
        state = state + GOLDEN  # rejected: next_normal's fast path again, written out as rng._normal_edge does
        bits = mix(state)
        i = np.int64(bits & np.uint64(255))
        u = ((bits >> np.uint64(12)) + 0.5) * (1.0 / 2251799813685248.0) - 1.0
        if abs(u) < ZIG_RATIO[i]:
            return state, u * ZIG_X[i]


@njit(inline="always")
def next_normal(state):
    state = state + GOLDEN
    bits = mix(state)
    i = np.int64(bits & np.uint64(255))
    u = ((bits >> np.uint64(12)) + 0.5) * (1.0 / 2251799813685248.0) - 1.0
    if abs(u) < ZIG_RATIO[i]:
        return state, u * ZIG_X[i]
    return normal_edge(state, i, u)


@njit(parallel=True, cache=True, error_model="numpy")
def rollout(bins, score, starts, keys, episodes, next_cell, region, risky_cell, source_at, source_reward, horizon, out):
    """Episodes of P policies (bins (P, C, 4), score (P, C, 5, M)); out = (z, score, risky, reached, steps)."""
    out_z, out_score, out_risky, out_reached, out_steps = out
    total = bins.shape[0] * episodes
    for chunk in prange((total + CHUNK - 1) // CHUNK):
        acc = np.empty(score.shape[3])
        for e in range(chunk * CHUNK, min(total, (chunk + 1) * CHUNK)):
            p = e // episodes
            state = mix(keys[p] ^ mix(np.uint64(e - p * episodes) + GOLDEN))
            cell, z, risky, reached, steps = starts[p], 0.0, 0, -1, 0
            acc[:] = 0.0
            for _ in range(horizon):
                state, m = next_bits(state)
                m = np.int64(m)
                b = bins[p, cell]
                a = (m >= b[0]) + (m >= b[1]) + (m >= b[2]) + (m >= b[3])
                for j in range(acc.shape[0]):
                    acc[j] += score[p, cell, a, j]
                cell = next_cell[cell, a]
                steps += 1
                state, u = next_uniform(state)
                state, g = next_normal(state)
                reward = region[cell, 0] + region[cell, 1] * u + region[cell, 2] * g
                reward = min(max(reward, region[cell, 3]), region[cell, 4])
                risky += risky_cell[cell]
                hit = source_at[cell]
                if hit >= 0:
                    state, g = next_normal(state)
                    reward += source_reward[hit, 0] + source_reward[hit, 1] * g
                    if reached < 0:
                        reached = hit
                z += reward
                if hit >= 0:
                    break
            out_z[e], out_risky[e], out_reached[e], out_steps[e] = z, risky, reached, steps
            out_score[e, :] = acc


def main() -> None:
    """Compile the kernel, and run it on the paper world's 12 x 12 grid (uniform moves, its 2 sources)."""
    side, sources, episodes = 12, 2, 100
    cells = side * side
    cum = np.cumsum(np.full((1, cells, 5), 0.2), axis=2)
    bins = np.minimum(cum[..., :4] * 2.0**53, 2.0**53).astype(np.int64)
    score = np.zeros((1, cells, 5, sources))
    x, y = np.divmod(np.arange(cells), side)
    moves = [(1, 0), (-1, 0), (0, 0), (0, 1), (0, -1)]
    next_cell = np.stack([np.clip(x + dx, 0, side - 1) * side + np.clip(y + dy, 0, side - 1) for dx, dy in moves], 1)
    region = np.tile([0.0, 100.0, 0.0, -np.inf, np.inf], (cells, 1))
    region[y > x] = [0.0, 200.0, 100.0, -1e4, 1e4]
    source_at = np.full(cells, -1)
    source_at[9 * side + 3], source_at[3 * side + 9] = 0, 1
    source_reward = np.array([[1000.0, 0.0], [2000.0, 2000.0]])
    out = (np.empty(episodes), np.empty((episodes, sources)), *(np.empty(episodes, np.int64) for _ in range(3)))
    keys = np.array([12345], dtype=np.uint64)
    starts = np.zeros(1, dtype=np.int64)
    risky = (y > x).astype(np.int64)
    rollout(bins, score, starts, keys, episodes, next_cell, region, risky, source_at, source_reward, 20, out)


if __name__ == "__main__":
    main()
