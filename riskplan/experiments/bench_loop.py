"""`riskplan bench`'s loop row: the recorded training loop of the paper's single-robot run (`riskplan train`'s
loop: the engine's loop with rows into run.mcap, checkpoints and progress, evaluation excluded) against the same
training as a plain numba loop that records nothing (riskplan.experiments.baselines.plain_loop), in the same bench run."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from riskplan.engine.policy import move_features
from riskplan.engine.rollout import affine_form
from riskplan.engine.schedules import step_size
from riskplan.experiments.baselines import plain_loop
from riskplan.run.build import build_setup
from riskplan.run.compose import compose
from riskplan.run.training import train_summary

SMALL_EVALUATION = ["train.eval_episodes=1000", "train.bootstrap=40", "train.paths=2"]  # the loop is what is timed
TARGET = 1.0  # the recorded loop at most this many times the plain loop's time


def plain_world(setup) -> dict:
    """The built world as plain_loop takes it (its sources' rewards must be normal: the paper's are)."""
    tables, world = setup.kernel.tables, setup.world
    rewards = [affine_form(reward) for reward in world.source_rewards]
    return {
        "features": move_features(world),
        "next_cell": tables.next_cell,
        "region": tables.cell_affine,
        "risky": tables.cell_risky,
        "source_at": tables.source_at,
        "source_reward": np.array([[form[0], form[2]] for form in rewards]),
        "horizon": tables.horizon,
    }


def bench_loop(quick: bool) -> list[dict]:
    """paper_single's 200 iterations at W = 6000 (50 with --quick), recorded, against the plain loop: the best of
    three each, after a warm-up of both."""
    overrides = [*SMALL_EVALUATION, *(["train.iterations=50"] if quick else [])]
    setup = build_setup(compose(overrides))
    params = setup.params
    world = plain_world(setup)
    start = int(setup.world.starts[0])

    def plain(iterations: int) -> float:
        started = time.perf_counter()
        plain_loop.train(
            world,
            setup.theta0,
            start,
            iterations,
            params.train.samples,
            params.risk.beta,
            lambda l: step_size(l, params.train.step_size),
        )
        return time.perf_counter() - started

    def recorded(folder: Path) -> float:
        return train_summary(setup, folder)["wall_time"]  # the loop's own time, after the kernels are loaded

    with tempfile.TemporaryDirectory() as tmp:
        plain(2), recorded(Path(tmp) / "warm-up")
        plains = [plain(params.train.iterations) for _ in range(3)]
        recordeds = [recorded(Path(tmp) / f"run{i}") for i in range(3)]
    value, baseline = min(recordeds), min(plains)
    ratio = value / baseline
    return [
        {
            "measure": f"the recorded loop, paper_single {params.train.iterations} iterations at W=6000 (s)",
            "value": value,
            "unit": "s",
            "target": f"<= {TARGET:g}x a plain numba loop",
            "ok": ratio <= TARGET,
            "baseline": baseline,
            "ratio": ratio,
            "note": "baseline: the same training as a plain loop (riskplan.experiments.baselines.plain_loop: numpy policy "
            "tables, a plain numba rollout kernel, numpy VaR and CVaR gradient, nothing recorded); value: riskplan "
            "train's loop with its rows, run.mcap and checkpoints (summary.json's wall_time); best of 3 each",
        }
    ]
