"""`riskplan bench`'s rollout row: the batched kernel against a plain per-trajectory Python loop with its semantics
(riskplan.experiments.baselines.python_loop: the baseline's reward model and moves drawn in Python), on the paper
world."""

from __future__ import annotations

import time

from riskplan.engine import rng
from riskplan.engine.rollout import simulate
from riskplan.experiments.baselines.python_loop import python_rollouts
from riskplan.experiments.bench_meters import best_time
from riskplan.run.build import build_setup
from riskplan.run.compose import compose


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
    _, steps = python_rollouts(python_world(setup.world), setup.theta0, episodes, 0)
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


def python_world(world) -> dict:
    """The built world as python_loop takes it: plain arrays, and the reward laws as riskplan's Dist trees (read by
    their kind, params and children alone)."""
    return {
        "signals": world.signals(),
        "next_cell": world.next_cell,
        "region_of": world.region_of,
        "region_rewards": list(world.region_rewards),
        "source_cells": world.source_cells,
        "source_rewards": list(world.source_rewards),
        "start": int(world.starts[0]),
        "horizon": int(world.horizon),
        "stop_at_source": bool(world.stop_at_source),
    }
