"""Not riskplan: `riskplan bench`'s rollout baseline, episodes one by one in plain Python with the kernel's semantics
(moves from the softmax policy, each entered cell's region reward, a source's reward, stopping at a source). It
imports nothing of riskplan's (riskplan.experiments.baselines)."""

from __future__ import annotations

import random

import numpy as np


def python_draw(dist, rand: random.Random) -> float:
    """One draw of a reward law in plain Python (the baseline's reward model): `dist` has riskplan's Dist shape, a
    kind, its params and its children."""
    kind, p = dist.kind, dist.params
    if kind == "constant":
        return p[0]
    if kind == "uniform":
        return p[0] + (p[1] - p[0]) * rand.random()
    if kind == "normal":
        return rand.gauss(p[0], p[1])
    if kind == "bernoulli":
        return 1.0 if rand.random() < p[0] else 0.0
    if kind == "scale":
        return p[0] * python_draw(dist.children[0], rand)
    if kind == "clip":
        return min(max(python_draw(dist.children[0], rand), p[0]), p[1])
    if kind == "sum":
        return sum(python_draw(c, rand) for c in dist.children)
    pick = rand.choices(range(len(p)), weights=p)[0]
    return python_draw(dist.children[pick], rand)


def python_rollouts(world: dict, theta: np.ndarray, episodes: int, seed: int) -> tuple[np.ndarray, int]:
    """The baseline: a plain per-trajectory Python loop with the kernel's semantics (static sources). `world`: the
    signals (C, M), next_cell (C, 5), region_of (C,), region_rewards and source_rewards (laws as `python_draw` reads
    them), source_cells (S,), the start cell, the horizon and stop_at_source. The total rewards and the moves made."""
    rand = random.Random(seed)
    signals, next_cell, region_of = world["signals"], world["next_cell"], world["region_of"]
    source_at = {int(c): j for j, c in reversed(list(enumerate(world["source_cells"])))}
    totals, steps = np.empty(episodes), 0
    for e in range(episodes):
        cell, z, score = world["start"], 0.0, np.zeros(len(world["source_cells"]))
        for _ in range(world["horizon"]):
            feats = signals[next_cell[cell]]  # (5, M)
            logits = feats @ theta
            weights = np.exp(logits - logits.max())
            probs = weights / weights.sum()
            move = rand.choices(range(5), weights=probs)[0]
            score += feats[move] - probs @ feats
            cell = int(next_cell[cell, move])
            steps += 1
            region = region_of[cell]
            z += python_draw(world["region_rewards"][region], rand) if region >= 0 else 0.0
            hit = source_at.get(cell, -1)
            if hit >= 0:
                z += python_draw(world["source_rewards"][hit], rand)
                if world["stop_at_source"]:
                    break
        totals[e] = z
    return totals, steps
