"""The final policies' evaluation table (riskplan.run.evaluation.evaluate): one row per episode, each policy's
rows from its own streams, a kernel call per EVAL_BATCH episodes."""

from __future__ import annotations

import numpy as np
from support import setup_of

from riskplan.engine import rng
from riskplan.engine.rollout import simulate
from riskplan.run import evaluation
from riskplan.run.evaluation import evaluate
from riskplan.run.log_format import EVAL_COLUMNS


def test_each_policys_rows_are_its_own_streams_batch_by_batch(monkeypatch):
    """A team of 3 and its network average, 23 episodes each in kernel calls of 10, 10 and 3: every row is the
    episode the policy's stream for that call gives, in order, with its robot, episode number and health."""
    monkeypatch.setattr(evaluation, "EVAL_BATCH", 10)
    setup = setup_of("experiment=paper_team", "team.robots=3", "team.graph=complete", "train.eval_episodes=23")
    thetas = np.array([[0.5, -0.2], [1.0, 0.3], [-0.4, 0.8]])
    table = evaluate(setup, thetas)
    policies = [*thetas, thetas.mean(axis=0)]
    assert [(name, str(values.dtype)) for name, values in table.items()] == list(EVAL_COLUMNS.items())
    assert table["robot"].tolist() == [r for r in (0, 1, 2, -1) for _ in range(23)]
    assert table["episode"].tolist() == list(range(23)) * 4
    assert table["healthy"].all() and table["healthy"].dtype == bool
    start = setup.world.starts[:1]
    for p, theta in enumerate(policies):
        for first, size in ((0, 10), (10, 10), (20, 3)):
            key = np.array([rng.stream_key(setup.params.seed, rng.EVAL, p, first)], dtype=np.uint64)
            batch = simulate(setup.world, setup.kernel, theta[None], start, key, size, scores=False)
            rows = slice(23 * p + first, 23 * p + first + size)
            for name in ("total_reward", "risky_steps", "source_reached", "steps"):
                assert np.array_equal(table[name][rows], getattr(batch, name)), (p, first, name)
                assert table[name].dtype == getattr(batch, name).dtype
    assert len(np.unique(table["total_reward"][:23])) > 1  # the episodes differ: the streams moved on
