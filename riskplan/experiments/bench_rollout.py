"""`riskplan bench`'s rollout row: the batched kernel against a plain per-trajectory Python loop with its semantics
(the baseline's reward model and moves drawn in Python), on the paper world."""

from __future__ import annotations

import random
import time

import numpy as np

from riskplan.engine import rng
from riskplan.engine.distributions import Dist
from riskplan.engine.rollout import simulate
from riskplan.experiments.bench_meters import best_time
from riskplan.run.build import build_setup
from riskplan.run.compose import compose


def python_draw(dist: Dist, rand: random.Random) -> float:
    """One draw of a reward distribution in plain Python (the baseline's reward model)."""
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


def python_rollouts(world, theta: np.ndarray, episodes: int, seed: int) -> tuple[np.ndarray, int]:
    """The baseline: a plain per-trajectory Python loop with the kernel's semantics (static sources)."""
    rand = random.Random(seed)
    signals = world.signals()
    source_at = {int(c): j for j, c in reversed(list(enumerate(world.source_cells)))}
    totals, steps = np.empty(episodes), 0
    for e in range(episodes):
        cell, z, score = int(world.starts[0]), 0.0, np.zeros(world.sources)
        for _ in range(world.horizon):
            feats = signals[world.next_cell[cell]]  # (5, M)
            logits = feats @ theta
            weights = np.exp(logits - logits.max())
            probs = weights / weights.sum()
            move = rand.choices(range(5), weights=probs)[0]
            score += feats[move] - probs @ feats
            cell = int(world.next_cell[cell, move])
            steps += 1
            region = world.region_of[cell]
            z += python_draw(world.region_rewards[region], rand) if region >= 0 else 0.0
            hit = source_at.get(cell, -1)
            if hit >= 0:
                z += python_draw(world.source_rewards[hit], rand)
                if world.stop_at_source:
                    break
        totals[e] = z
    return totals, steps


def bench_rollout(quick: bool) -> list[dict]:
    """Batched kernel vs the plain Python loop on the paper world at theta0, W = 6000."""
    setup = build_setup(compose([]))
    theta = setup.theta0[None, :]
    keys = rng.robot_keys(0, rng.TRAIN, 0, 1)
    batch = simulate(setup.world, setup.kernel, theta, setup.world.starts, keys, 6000)  # warm (JIT cache)
    # the same 5 x 40 calls with --quick: fewer gave readings that were too low on a noisy machine
    seconds = best_time(lambda: simulate(setup.world, setup.kernel, theta, setup.world.starts, keys, 6000), 5, 40)
    kernel_rate = batch.steps.sum() / seconds
    episodes = 50 if quick else 300
    start = time.perf_counter()
    _, steps = python_rollouts(setup.world, setup.theta0, episodes, 0)
    python_rate = steps / (time.perf_counter() - start)
    return [
        {
            "measure": "rollout, W=6000, theta0 (trajectory-steps/s)",
            "value": kernel_rate,
            "unit": "steps/s",
            "target": ">= 1.5e8",
            "ok": kernel_rate >= 1.5e8,
            "baseline": python_rate,
            "ratio": kernel_rate / python_rate,
            "note": f"{seconds * 1e3:.2f} ms per batch; baseline: plain Python "
            f"loop, {episodes} trajectories (ratio target > 1000x)",
        },
    ]
