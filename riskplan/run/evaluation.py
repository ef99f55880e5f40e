"""The end of a run: the final policies on fresh episodes (eval.parquet), sampled paths (trajectories.parquet) and
summary.json, and the check that no non-finite number is ever recorded as a result."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from riskplan.engine import rng
from riskplan.engine.risk_measures import summary_stats
from riskplan.engine.rollout import simulate
from riskplan.run.budget import EVAL_BATCH
from riskplan.run.build import Setup, starts
from riskplan.run.checkpoint import State
from riskplan.run.intervals import bootstrap_intervals
from riskplan.run.provenance import provenance

if TYPE_CHECKING:  # pandas loads after the training loop (see riskplan.run.training)
    import pandas as pd

SCHEMA_VERSION = 1  # of summary.json
AVERAGE = -1  # the `robot` id of the network average in team tables


class NumericalTrouble(RuntimeError):
    """theta or a gradient stopped being finite; the last good checkpoint is kept."""


def check_finite(what: str, *arrays) -> None:
    """NumericalTrouble unless every value is finite: a NaN or infinity is never recorded as a result."""
    for values in arrays:
        if not np.all(np.isfinite(values)):
            raise NumericalTrouble(f"{what} is not finite (overflow); use smaller rewards or fewer steps")


def policies(setup: Setup, thetas: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The evaluated policies: (robot ids, thetas, start cells); teams add the network average (robot -1)."""
    ids = np.arange(setup.robots)
    cells = starts(setup)
    if not setup.team:
        return ids, thetas, cells
    return np.append(ids, AVERAGE), np.vstack([thetas, thetas.mean(axis=0)]), np.append(cells, cells[0])


def evaluate(setup: Setup, thetas: np.ndarray) -> pd.DataFrame:
    """The final policies on fresh episodes (own stream), one row per episode."""
    import pandas as pd

    count = setup.params.train.eval_episodes
    ids, evaluated, cells = policies(setup, thetas)
    frames = []
    for p, robot in enumerate(ids):
        parts = []
        for first in range(0, count, EVAL_BATCH):
            key = np.array([rng.stream_key(setup.params.seed, rng.EVAL, p, first)], dtype=np.uint64)
            size = min(EVAL_BATCH, count - first)
            parts.append(simulate(setup.world, setup.kernel, evaluated[p : p + 1], cells[p : p + 1], key, size))
        frames.append(
            pd.DataFrame(
                {
                    "episode": np.arange(count, dtype=np.int64),
                    "robot": np.full(count, robot, dtype=np.int64),
                    "total_reward": np.concatenate([b.total_reward for b in parts]),
                    "risky_steps": np.concatenate([b.risky_steps for b in parts]),
                    "source_reached": np.concatenate([b.source_reached for b in parts]),
                    "steps": np.concatenate([b.steps for b in parts]),
                }
            )
        )
    return pd.concat(frames, ignore_index=True)


def sample_paths(setup: Setup, thetas: np.ndarray) -> pd.DataFrame:
    """A few sampled paths of the initial and the final policies (own stream), one row per step."""
    import pandas as pd

    count = setup.params.train.paths
    frames = []
    for name, policy_thetas in (("initial", np.tile(setup.theta0, (setup.robots, 1))), ("final", thetas)):
        ids, evaluated, cells = policies(setup, policy_thetas)
        keys = rng.robot_keys(setup.params.seed, rng.PATHS, 0 if name == "initial" else 1, len(ids))
        batch = simulate(setup.world, setup.kernel, evaluated, cells, keys, count, record=True)
        alive = batch.path_cells >= 0
        episode, step = np.nonzero(alive)
        x, y = setup.world.xy(batch.path_cells[alive])
        frames.append(
            pd.DataFrame(
                {
                    "policy": name,
                    "episode": (episode % max(count, 1)).astype(np.int64),
                    "robot": ids[episode // max(count, 1)].astype(np.int64),
                    "step": step.astype(np.int64),
                    "x": x.astype(np.int64),
                    "y": y.astype(np.int64),
                    "reward": batch.path_rewards[alive],
                }
            )
        )
    return pd.concat(frames, ignore_index=True)


def summarize(
    setup: Setup, state: State, evaluation: pd.DataFrame, metrics: pd.DataFrame, train_seconds: float
) -> dict:
    """summary.json: headline policy's figures with intervals, per-policy basics, timing, provenance."""
    params = setup.params
    headline = AVERAGE if setup.team else 0
    z = evaluation.loc[evaluation.robot == headline]
    check_finite("the evaluation's total reward", evaluation.total_reward.to_numpy())
    figures = bootstrap_intervals(z.total_reward.to_numpy(), params.risk.beta, params.train.bootstrap, params.seed)
    check_finite("the summary's figures", *[v for f in figures.values() for v in f.values()])
    steps = float(metrics.samples[metrics.robot >= 0].sum())
    per_policy = {}
    for robot, group in evaluation.groupby("robot"):
        per_policy[str(robot)] = {
            **{k: float(v) for k, v in summary_stats(group.total_reward.to_numpy(), params.risk.beta).items()},
            "risky_fraction": float((group.risky_steps > 0).mean()),
            "source_reached": {
                name: float((group.source_reached == j).mean()) for j, name in enumerate(setup.world.source_names)
            }
            | {"none": float((group.source_reached < 0).mean())},
        }
    _, final_thetas, _ = policies(setup, state.thetas)
    return {
        "schema_version": SCHEMA_VERSION,
        "experiment": params.experiment,
        "risk": params.risk.measure,
        "beta": params.risk.beta,
        "robots": setup.robots,
        "headline_robot": headline,
        **figures,
        "risky_fraction": per_policy[str(headline)]["risky_fraction"],
        "source_reached": per_policy[str(headline)]["source_reached"],
        "theta_final": final_thetas[-1].tolist() if setup.team else final_thetas[0].tolist(),
        "policies": per_policy,
        "iterations": state.iteration,
        "eval_episodes": params.train.eval_episodes,
        "wall_time": train_seconds,
        "throughput_episodes_per_s": steps / train_seconds if train_seconds > 0 else None,
        "provenance": provenance(),
    }
