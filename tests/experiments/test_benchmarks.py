"""riskplan bench (riskplan.experiments.benchmarks): the plain-Python baseline has the kernel's semantics (else its
ratio would mean nothing), and the scaling table measures every dimension against its baseline row."""

from __future__ import annotations

import os

import numpy as np
import pytest

from riskplan.engine import rng
from riskplan.engine.rollout import simulate
from riskplan.experiments.benchmarks import bench_measures, python_rollouts
from riskplan.run.build import build_setup
from riskplan.run.compose import compose


def test_python_baseline_matches_the_kernel_in_distribution():
    setup = build_setup(compose(["train.theta0=[40,5]"]))
    python_z, python_steps = python_rollouts(setup.world, setup.theta0, 3000, seed=1)
    batch = simulate(
        setup.world,
        setup.kernel,
        setup.theta0[None, :],
        setup.world.starts,
        rng.robot_keys(1, rng.TRAIN, 0, 1),
        100_000,
    )
    stderr = np.sqrt(python_z.var() / python_z.size + batch.total_reward.var() / batch.total_reward.size)
    assert abs(python_z.mean() - batch.total_reward.mean()) < 5 * stderr
    assert abs(python_steps / 3000 - batch.steps.mean()) < 5 * batch.steps.std() / np.sqrt(3000)
    for q in (0.1, 0.5, 0.9):  # quantiles agree too, not only the mean
        a, b = np.quantile(python_z, q), np.quantile(batch.total_reward, q)
        assert abs(a - b) < 0.1 * batch.total_reward.std()


@pytest.mark.slow  # builds and times a dozen set-ups, draws the plot: about 5 s
def test_scaling_measures_every_dimension_against_the_baseline_row(tmp_path, monkeypatch):
    import json
    import math

    from riskplan.experiments import benchmarks as bench

    monkeypatch.setattr(bench, "ROUND_SECONDS", 0.001)  # structure only: no timed assertion
    small = ["train.samples=200"]
    dimensions = {
        "grid": [(12.0, small), (16.0, [*small, "world.size=[16,16]", "world.regions.1.rect=[0,0,15,15]"])],
        "horizon": [
            (10.0, [*small, "world.horizon=10", "world.stop_at_source=false"]),
            (30.0, [*small, "world.horizon=30", "world.stop_at_source=false"]),
        ],
        "sources": [(2.0, [*small, *bench.source_overrides(2)]), (5.0, [*small, *bench.source_overrides(5)])],
        "mobile": [
            (0.0, small),
            (1.0, [*small, "world.sources.0.motion.kind=random_walk", "world.sources.0.motion.prob=0.5"]),
        ],
        "robots": [
            (1.0, ["train.samples=300"]),
            (3.0, ["team.robots=3", "team.graph=random_geometric", "team.radius=1.5", "train.samples=100"]),
        ],
    }
    rows = bench.bench_scaling(quick=True, dimensions=dimensions, baseline=small)
    assert rows[0]["dimension"] == "baseline" and len(rows) == 1 + sum(len(v) for v in dimensions.values())
    assert {r["dimension"] for r in rows[1:]} == set(dimensions)
    base = rows[0]
    assert base["rate_ratio"] == base["kernel_ratio"] == base["bytes_ratio"] == 1.0
    for row in rows:
        for key in ("steps_per_s", "kernel_steps_per_s", "bytes_per_sample", "table_bytes"):
            assert math.isfinite(row[key]) and row[key] > 0, (row["dimension"], key)
        assert math.isclose(row["rate_ratio"], row["steps_per_s"] / base["steps_per_s"])
        assert math.isclose(row["kernel_ratio"], row["kernel_steps_per_s"] / base["kernel_steps_per_s"])
        assert math.isclose(row["bytes_ratio"], row["bytes_per_sample"] / base["bytes_per_sample"])
    robots = [r for r in rows if r["dimension"] == "robots"]
    assert robots[0]["samples"] == 300 and robots[1]["samples"] == 300  # same total samples
    assert [r["cells"] for r in rows if r["dimension"] == "grid"] == [144, 256]
    slopes = bench.scaling_slopes(rows, cache=1)  # every table "exceeds" a 1-byte cache: both slopes are fitted
    assert set(slopes) == {"grid", "horizon", "sources", "robots"}
    assert all(s["all"] is not None and s["beyond_cache"] is not None for s in slopes.values())
    table = bench.scaling_table(rows)
    assert len(table.splitlines()) == 2 + len(rows) and "paper world" in table
    plot = bench.plot_scaling(rows, tmp_path / "scaling.png")
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    json.dumps(rows)  # the --json file takes the rows as they are


@pytest.mark.slow  # builds a 64-source world: about a second
def test_the_scaling_dimensions_span_their_ranges_and_many_sources_compose():
    from riskplan.experiments import benchmarks as bench

    dims = bench.scaling_dimensions()
    values = {name: [v for v, _ in points] for name, points in dims.items()}
    assert values["grid"][0] == 12 and values["grid"][-1] == 256
    assert values["horizon"][0] == 20 and values["horizon"][-1] == 400
    assert values["sources"][0] == 2 and values["sources"][-1] == 64
    assert values["mobile"] == [0.0, 1.0]
    assert values["robots"][0] == 1 and values["robots"][-1] == 1000
    assert all(f"train.samples={bench.TEAM_SAMPLES // int(n)}" in ovs for n, ovs in dims["robots"])
    setup = build_setup(compose(bench.source_overrides(64)))
    assert setup.world.sources == 64 and setup.theta0.shape == (64,)


@pytest.mark.slow  # composes and times the paper set-up under four measures: a few seconds
def test_each_risk_measure_is_timed_against_a_cvar_iteration_on_the_same_episodes():
    rows = bench_measures(quick=True)
    assert [r["measure"] for r in rows] == [
        f"iteration under risk={m}, the paper set-up (s)" for m in ("wang", "mean_cvar", "entropic")
    ]
    assert len({r["baseline"] for r in rows}) == 1  # one CVaR iteration, the baseline of each
    for row in rows:
        assert row["value"] > 0 and row["ratio"] == pytest.approx(row["value"] / row["baseline"])
        assert row["ok"] == (row["value"] <= 1.2 * row["baseline"])


def _row(name: str, ok: bool) -> dict:
    return {"measure": name, "value": 1.0, "unit": "s", "target": "<= 1", "ok": ok, "baseline": 1.0, "ratio": 1.0}


@pytest.mark.parametrize(("per_core", "busy"), [(0.05, False), (3.0, True)])
def test_bench_counts_the_targets_met_and_says_when_the_machine_is_busy(monkeypatch, per_core, busy):
    from typer.testing import CliRunner

    from riskplan.cli import app
    from riskplan.experiments import benchmarks as bench

    for name in (
        "bench_rollout",
        "bench_training",
        "bench_measures",
        "bench_checkpoints",
        "bench_startup",
        "bench_team",
    ):
        monkeypatch.setattr(bench, name, lambda quick, name=name: [{**_row(name, name != "bench_team"), "note": ""}])
    monkeypatch.setattr(bench, "bench_jit", lambda: [{**_row("jit", True), "note": ""}])
    monkeypatch.setattr("riskplan.experiments.bench_gpu.bench_gpu", no_gpu)  # a GPU machine would measure it
    load = per_core * (os.cpu_count() or 1)
    monkeypatch.setattr("os.getloadavg", lambda: (load, load, load))
    result = CliRunner().invoke(app, ["bench"])
    assert result.exit_code == 0, result.output
    assert "6 of 7 targets met" in result.output and f"load average {load:.2f}" in result.output
    assert ("the machine is busy" in result.output) == busy
    assert "GPU rollout kernel: skipped; no GPU here" in result.output  # a line, not a target


def no_gpu(quick):
    from riskplan.experiments.bench_gpu import Skipped

    raise Skipped("no GPU here")
