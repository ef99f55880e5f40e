"""The training loop (riskplan.run.training): its per-robot rows and norms equal the plain per-robot computation bit
for bit, and numerical trouble stops a run with one line, keeping the last good checkpoint and a log without NaN."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from support import CHECKPOINTED, TABLES, assert_log_holds_each_iteration_once, train_cli

import riskplan.engine.step as engine_step
import riskplan.run.training as training
from riskplan import compose, load_run
from riskplan.engine.step import NumericalTrouble
from riskplan.risk import summary_stats
from riskplan.run.checkpoint import CHECKPOINT
from riskplan.run.log_reader import read_log
from riskplan.run.metrics_rows import _robot_rows, metrics_row

# ---------------------------------------------------------------------------------------------- rows


@pytest.mark.parametrize("n", [1, 2, 5, 7, 100])
def test_robot_rows_are_the_per_robot_rows(n):
    g = np.random.default_rng(n)
    z = g.normal(size=(n, 50)) * 100
    stats = summary_stats(z, 0.1)
    thetas, grads = g.normal(size=(n, 2)), g.normal(size=(n, 2)) * 1e3
    levels, healthy = g.uniform(0.1, 1.0, size=n), g.random(n) < 0.7  # per robot: team.risk, team.faults
    rows = _robot_rows(4, stats, thetas, grads, 0.05, 1.25, 50, 0.5, levels, healthy)  # eps, error, samples, seconds
    expected = [
        metrics_row(
            4, i, {k: v[i] for k, v in stats.items()}, thetas[i], grads[i], 0.05, 1.25, 50, 0.5, levels[i], healthy[i]
        )
        for i in range(n)
    ]
    assert rows == expected
    for got, want in zip(rows, expected):
        assert list(got) == list(want)
        assert [type(v) for v in got.values()] == [type(v) for v in want.values()]
    assert rows[-1]["robot"] == n - 1 and rows[0]["grad_norm"] == float(np.linalg.norm(grads[0]))


@pytest.mark.parametrize("m", [1, 2, 3, 40])
def test_row_norms_are_numpy_norms_bit_for_bit(m):
    from riskplan.run.metrics_rows import _norms

    g = np.random.default_rng(m)
    vectors = g.normal(size=(2000, m)) * 10.0 ** g.integers(-150, 150, size=(2000, m))
    assert _norms(vectors) == [float(np.linalg.norm(v)) for v in vectors]
    assert _norms(np.array([[3.0, 4.0][:m] + [0.0] * (m - 2)] if m >= 2 else [[-5.0]])) == [5.0]


# ---------------------------------------------------------------------------------------------- numerical trouble


def _fail_at(monkeypatch, name: str, iteration: int, bad):
    """Make riskplan.engine.step.<name> return bad(result) from the given iteration on (the iteration is read off
    the `samples_at` call that opens every iteration)."""
    original, seen = getattr(engine_step, name), {"l": 0}
    original_samples = engine_step.samples_at

    def samples(l, train):
        seen["l"] = l
        return original_samples(l, train)

    def patched(*args, **kwargs):
        result = original(*args, **kwargs)
        return bad(result) if seen["l"] >= iteration else result

    monkeypatch.setattr(engine_step, "samples_at", samples)
    monkeypatch.setattr(engine_step, name, patched)


@pytest.mark.parametrize(
    "name, bad, message",
    [
        ("gradients", lambda r: (np.full_like(r[0], np.nan), *r[1:]), "theta or its gradient is not finite"),
        ("consensus_step", lambda t: np.full_like(t, 1.5e308), "overflows the softmax"),  # finite, but theta.s = inf
    ],
)
def test_numerical_trouble_stops_the_run_and_keeps_the_last_good_checkpoint(tmp_path, monkeypatch, name, bad, message):
    out = tmp_path / "run"
    config = compose(CHECKPOINTED)
    _fail_at(monkeypatch, name, 7, bad)
    with pytest.raises(NumericalTrouble, match=f"iteration 7: .*{message}.*lower train.step_size.initial"):
        training.train(config, out)

    state = json.loads((out / CHECKPOINT).read_text())
    assert state["iteration"] == 5 and all(math.isfinite(t) for t in state["thetas"][0])
    assert not (out / f"{CHECKPOINT}.tmp").exists()
    assert not any((out / f"{t}.parquet").exists() for t in TABLES) and not (out / "summary.json").exists()
    run = load_run(out)  # the log was closed cleanly, with no iteration 7 and no NaN in it
    assert not run.complete and "stopped after iteration 6" in run.problem
    assert list(run.metrics.iteration) == list(range(7))
    assert np.isfinite(run.metrics.drop(columns="consensus_error").to_numpy(dtype=float)).all()

    monkeypatch.undo()  # the cause gone, the run resumes from its last good checkpoint
    training.train(config, out, resume=True)
    assert_log_holds_each_iteration_once(out, 30, (0,))


@pytest.mark.slow  # `riskplan train` in a subprocess
def test_diverging_step_size_fails_with_one_line_and_no_nan(tmp_path):
    result = train_cli([*CHECKPOINTED, "train.step_size.initial=1e308"], tmp_path / "run")
    assert result.returncode == 1
    (line,) = result.stderr.strip().splitlines()  # no overflow warning, no traceback: one line
    assert line.startswith("error: run failed: iteration 0: theta or its gradient is not finite")
    assert "lower train.step_size.initial" in line
    assert not (tmp_path / "run" / "metrics.parquet").exists()
    assert read_log(tmp_path / "run" / "run.mcap").metrics.empty  # nothing non-finite was logged
