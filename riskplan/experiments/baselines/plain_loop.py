"""Not riskplan: the baseline of `riskplan bench`'s loop row: Algorithm 1's training loop written plainly, with numpy and numba
only (it imports nothing of riskplan's): each iteration the softmax policy's tables in numpy, W episodes by the
plain rollout kernel of `one_kernel` (a numba kernel of riskplan's kind), VaR by a partition, the CVaR gradient of
eq. (9) as a masked product, and theta's step. Nothing is recorded, checked or checkpointed: what is left is the
arithmetic a training run cannot do without, which `riskplan train`'s recorded loop is measured against.

The world comes in as plain arrays (the bench reads them off riskplan's built paper world): the move features
F (C, 5, M) (each source's signal at the cell a move enters), next_cell (C, 5), each cell's reward as
clip(c + w U + s N, lo, hi) (C, 5), the risky cells (C,), the source at each cell (C,) and each source's reward's
mean and sd (S, 2).
"""

from __future__ import annotations

import numpy as np

from .one_kernel import rollout  # relative: nothing of riskplan's is imported

BITS = 2.0**53


def policy_tables(features: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The softmax policy's move bins (1, C, 4) as 53-bit integers, and its scores (1, C, 5, M) (eqs. 2-3)."""
    logits = features @ theta
    weights = np.exp(logits - logits.max(axis=1, keepdims=True))
    probs = weights / weights.sum(axis=1, keepdims=True)
    bins = np.minimum(np.cumsum(probs, axis=1)[:, :4] * BITS, BITS).astype(np.int64)
    scores = features - np.einsum("ca,cam->cm", probs, features)[:, None, :]
    return bins[None], scores[None]


def train(world: dict, theta0: np.ndarray, start: int, iterations: int, episodes: int, beta: float, step) -> np.ndarray:
    """`iterations` steps of the CVaR policy gradient from theta0 at W = `episodes`; `step(l)` is eps_l. The final
    theta."""
    theta = np.array(theta0, dtype=float)
    sources = theta.size
    out = (np.empty(episodes), np.empty((episodes, sources)), *(np.empty(episodes, np.int64) for _ in range(3)))
    starts = np.array([start], dtype=np.int64)
    tail = int(np.ceil(beta * episodes))  # riskplan's tail_count, without its guard against round-off
    for l in range(iterations):
        bins, scores = policy_tables(world["features"], theta)
        keys = np.array([0x5EED + l], dtype=np.uint64)
        rollout(
            bins,
            scores,
            starts,
            keys,
            episodes,
            world["next_cell"],
            world["region"],
            world["risky"],
            world["source_at"],
            world["source_reward"],
            world["horizon"],
            out,
        )
        theta = theta + step(l) * cvar_gradient(out[0], out[1], tail, beta)
    return theta


def cvar_gradient(z: np.ndarray, score: np.ndarray, tail: int, beta: float) -> np.ndarray:
    """Eq. (9): (1 / (beta W)) sum_i score_i (z_i - VaR) 1{z_i <= VaR}, VaR the tail-th smallest z."""
    var = np.partition(z, tail - 1)[tail - 1]
    return np.minimum(z - var, 0.0) @ score / (beta * z.size)
