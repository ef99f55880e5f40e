"""riskplan bench (the riskplan.experiments.bench_* modules): the plain-Python baseline has the kernel's semantics
(else its ratio would mean nothing), and the scaling table measures every dimension against its baseline row."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numba
import numpy as np
import pytest
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.engine import rng
from riskplan.engine.rollout import simulate
from riskplan.experiments.baselines.python_loop import python_rollouts
from riskplan.experiments.bench_rollout import python_world
from riskplan.experiments.bench_training import bench_measures
from riskplan.run.build import build_setup
from riskplan.run.compose import compose


@pytest.mark.slow  # over a second
def test_python_baseline_matches_the_kernel_in_distribution():
    setup = build_setup(compose(["train.theta0=[40,5]"]))
    python_z, python_steps = python_rollouts(python_world(setup.world), setup.theta0, 3000, seed=1)
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

    from riskplan.experiments import bench_scaling as bench

    monkeypatch.setattr(bench, "ROUND_SECONDS", 0.001)  # structure only: no timed assertion
    small = ["train.samples=200"]
    dimensions = {
        "grid": [(12.0, small), (16.0, [*small, "world.size=[16,16]", "world.regions.1.rect=[0,0,15,15]"])],
        "horizon": [
            (12.0, [*small, "world.horizon=12", "world.stop_at_source=false"]),  # the sources are 12 moves away
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
    from riskplan.experiments import bench_scaling as bench

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

    for module, name in (
        ("bench_rollout", "bench_rollout"),
        ("bench_training", "bench_training"),
        ("bench_training", "bench_measures"),
        ("bench_loop", "bench_loop"),
        ("bench_training", "bench_checkpoints"),
        ("bench_startup", "bench_startup"),
        ("bench_training", "bench_team"),
    ):
        monkeypatch.setattr(
            f"riskplan.experiments.{module}.{name}",
            lambda quick, name=name: [{**_row(name, name != "bench_team"), "note": ""}],
        )
    monkeypatch.setattr("riskplan.experiments.bench_startup.bench_jit", lambda: [{**_row("jit", True), "note": ""}])
    monkeypatch.setattr(
        "riskplan.experiments.bench_first_run.bench_first_run", lambda quick: [{**_row("first", True), "note": ""}]
    )
    monkeypatch.setattr("riskplan.experiments.bench_gpu.bench_gpu", no_gpu)  # a GPU machine would measure it
    load = per_core * (os.cpu_count() or 1)
    monkeypatch.setattr("os.getloadavg", lambda: (load, load, load))
    result = CliRunner().invoke(app, ["bench"])
    assert result.exit_code == 0, result.output
    assert "8 of 9 targets met" in result.output and f"load average {load:.2f}" in result.output
    assert ("the machine is busy" in result.output) == busy
    assert "GPU rollout kernel: skipped; no GPU here" in result.output  # a line, not a target


def no_gpu(quick):
    from riskplan.experiments.bench_gpu import Skipped

    raise Skipped("no GPU here")


def test_the_first_run_rows_compare_each_cold_command_with_one_kernel(monkeypatch):
    """Structure only: every command in a new process with an empty cache of its own, the best of its rounds, each
    paper set-up against the training kernel alone, and the plain kernel in the note."""
    from riskplan.experiments import bench_first_run as first

    seconds = {"kernel": 4.0, "plain": 2.5, "paper_single": 5.0, "paper_team": 7.0}
    caches = []

    def fake_wall(argv, cwd, marker=None, env=None):
        caches.append(env["NUMBA_CACHE_DIR"])
        assert not any(Path(env["NUMBA_CACHE_DIR"]).iterdir())  # empty: every kernel compiled
        name = "kernel" if "-c" in argv else "plain" if argv[-1].endswith("baselines/one_kernel.py") else None
        if name is None:
            name = "paper_team" if "experiment=paper_team" in argv else "paper_single"
            assert argv[-1].startswith("hydra.run.dir=")
        return seconds[name] + 0.1 * len(caches)  # later rounds slower: the best is the first

    monkeypatch.setattr(first, "wall", fake_wall)
    rows = first.bench_first_run(quick=False)
    assert len(caches) == 8 and len(set(caches)) == 8  # 4 commands x 2 rounds, a fresh cache each
    assert [r["measure"].split(", ")[1] for r in rows] == ["paper_single", "paper_team"]
    for row, value in zip(rows, (5.3, 7.4)):  # the first round: kernel +0.1, plain +0.2, single +0.3, team +0.4
        assert row["value"] == pytest.approx(value) and row["baseline"] == pytest.approx(4.1)
        assert row["ratio"] == pytest.approx(value / 4.1) and row["ok"] == (value <= 1.5 * 4.1)
        assert "2.70 s" in row["note"]  # the plain kernel's best


@pytest.mark.slow  # compiles the two baselines in new processes: a few seconds with a warm cache
def test_the_first_run_baselines_run_as_they_are():
    """The training kernel's child code calls the kernel with its current arguments, and the plain kernel runs."""
    import subprocess
    import sys

    from riskplan.experiments import bench_first_run as first

    subprocess.run([sys.executable, "-c", first.TRAINING_KERNEL], check=True, capture_output=True)
    plain = Path(first.__file__).with_name("baselines") / "one_kernel.py"
    subprocess.run([sys.executable, str(plain)], check=True, capture_output=True)


def test_thread_counts_double_up_to_the_cores():
    from riskplan.experiments.bench_threads import thread_counts

    assert thread_counts(1) == [1]
    assert thread_counts(2) == [1, 2]
    assert thread_counts(6) == [1, 2, 4, 6]
    assert thread_counts(16) == [1, 2, 4, 8, 16]


@pytest.mark.slow  # builds and times two small set-ups: a few seconds
def test_thread_scaling_rows_are_each_measure_against_one_thread(monkeypatch):
    """Structure only (no timed assertion): a kernel and an iteration row per sample size and thread count above
    1, each against the same measure at 1 thread; the thread count is restored."""
    from riskplan.experiments import bench_threads

    monkeypatch.setattr(bench_threads, "ROUND_SECONDS", 0.001)
    before = numba.get_num_threads()
    rows = bench_threads.bench_threads(quick=True, samples=(300, 2000), counts=[1, 2])
    assert numba.get_num_threads() == before
    assert [r["measure"] for r in rows] == [
        f"{name}, W={w:,}, 2 threads (trajectory-steps/s)" for w in (300, 2000) for name in ("kernel", "iteration")
    ]
    for row in rows:
        assert row["value"] > 0 and row["baseline"] > 0
        assert row["ratio"] == pytest.approx(row["value"] / row["baseline"])
    kernel, iteration = rows[0], rows[1]
    assert iteration["ok"] == (iteration["ratio"] >= bench_threads.EFFICIENCY * kernel["ratio"])


def test_bench_threads_prints_the_thread_scaling_rows_alone(monkeypatch):
    from typer.testing import CliRunner

    from riskplan.cli import app

    row = {**_row("iteration, W=600,000, 2 threads", True), "note": "against 1 thread"}
    monkeypatch.setattr("riskplan.experiments.bench_threads.bench_threads", lambda quick: [row])
    result = CliRunner().invoke(app, ["bench", "--threads", "--quick"])
    assert result.exit_code == 0, result.output
    assert "iteration, W=600,000, 2 threads" in result.output and "1 of 1 targets met" in result.output


def test_the_plain_loops_policy_and_gradient_are_riskplans():
    """The loop row's baseline computes what riskplan computes: the softmax policy's move probabilities and scores
    (eqs. 2-3) and the CVaR gradient of eq. (9)."""
    from riskplan.engine.estimators import cvar_gradient, tail_count
    from riskplan.engine.policy import probabilities, scores
    from riskplan.experiments.baselines import plain_loop
    from riskplan.experiments.bench_loop import plain_world

    setup = build_setup(compose([]))
    features = plain_world(setup)["features"]
    theta = np.array([12.0, -3.0])
    bins, score = plain_loop.policy_tables(features, theta)
    probs = probabilities(features, theta)
    np.testing.assert_allclose(np.diff(bins[0], prepend=0, axis=1) / plain_loop.BITS, probs[:, :4], atol=1e-12)
    np.testing.assert_allclose(score[0], scores(features, probs), atol=1e-12)

    z, s = np.random.default_rng(3).normal(size=(2, 997)), np.random.default_rng(4).normal(size=(997, 2))
    for beta in (0.05, 0.1, 0.5):
        got = plain_loop.cvar_gradient(z[0], s, tail_count(beta, z[0].size), beta)
        np.testing.assert_allclose(got, cvar_gradient(z[0], s, beta), rtol=1e-12)


def test_the_start_up_rows_are_the_best_of_their_new_processes(monkeypatch):
    """Structure only: the first train run is not timed, each row is its processes' best, and the loop row is the
    quickest recorded loop against its own run's compute."""
    import json

    import pandas as pd

    from riskplan.experiments import bench_startup as startup

    calls = []

    def fake_wall(argv, cwd, marker=None, env=None):
        calls.append(argv)
        if "train" in argv:  # the whole command: its run's files, and later runs quicker
            k = sum("train" in a for a in calls) - 1
            out = Path(argv[-1].removeprefix("hydra.run.dir="))
            out.mkdir(parents=True)
            (out / "summary.json").write_text(json.dumps({"wall_time": 1.0 - 0.1 * k}))
            pd.DataFrame({"seconds": [0.2, 0.3 + k]}).to_parquet(out / "metrics.parquet")
            return 2.0 - 0.1 * k
        seconds = {"FIRST-ITERATION": 0.8, "import numba": 0.5, "--help": 0.25, "import typer": 0.1}
        return next(v for k, v in seconds.items() if k in argv or k == marker) + 0.01 * len(calls)

    monkeypatch.setattr(startup, "wall", fake_wall)
    whole, loop, first, helps = startup.bench_startup(quick=True)
    assert sum("train" in argv for argv in calls) == 3 and len(calls) == 3 + 2 + 2 + 4 + 4
    assert whole["value"] == pytest.approx(1.8) and whole["baseline"] == pytest.approx(0.5 + 0.01 * 6)
    assert (loop["value"], loop["baseline"]) == (pytest.approx(0.8), pytest.approx(2.5))  # the third run's
    assert first["value"] == pytest.approx(0.84) and helps["value"] == pytest.approx(0.33)
    assert helps["baseline"] == pytest.approx(0.1 + 0.01 * 12) and "best of 4" in helps["note"]


@pytest.mark.parametrize(("batched", "same", "met"), [(29.0, True, True), (31.0, True, False), (20.0, False, False)])
def test_the_reproduce_row_is_the_batched_reproduction_against_job_by_job(monkeypatch, batched, same, met):
    """--reproduce's one row: batched reproduce --quick against job by job, met within 30 s and with equal numbers."""
    import pandas as pd
    from typer.testing import CliRunner

    from riskplan.cli import app
    from riskplan.experiments import bench_reproduce

    def numbers(cvar):
        return {"single": pd.DataFrame({"job": ["risk=cvar"], "status": ["done"], "cvar": [cvar]})}

    def fake(out, extra):
        return (36.0, numbers(1.0)) if extra else (batched, numbers(1.0 if same else 2.0))

    monkeypatch.setattr(bench_reproduce, "reproduce", fake)
    (row,) = bench_reproduce.bench_reproduce(quick=True)
    assert (row["value"], row["baseline"], row["ok"]) == (batched, 36.0, met)
    assert row["ratio"] == pytest.approx(batched / 36.0)
    assert ("THE NUMBERS DIFFER" in row["note"]) == (not same)
    result = CliRunner().invoke(app, ["bench", "--reproduce", "--quick"])
    assert result.exit_code == 0, result.output
    assert "riskplan reproduce --quick, 50 runs" in result.output and f"{int(met)} of 1 targets met" in result.output


@pytest.mark.parametrize(
    ("wall", "statuses", "faithful", "met"),
    [
        (70.0, ["done", "done"], True, True),
        (80.0, ["done", "done"], True, False),
        (70.0, ["done", "failed"], True, False),
        (70.0, ["done", "done"], False, False),
    ],
)
def test_the_whole_reproduction_row_is_its_wall_time_against_its_replayed_kernels(
    monkeypatch, wall, statuses, faithful, met
):
    """--reproduce's second row: the whole reproduction, met within 75 s with every run done and replayed as it
    ran; its baseline the episode and bootstrap kernels' seconds of the runs done, found in each sweep's folder by
    job."""
    import pandas as pd

    from riskplan.experiments import bench_reproduce
    from riskplan.experiments.bench_kernel_share import Replay

    def fake(out, extra, quick=True):
        assert not quick and extra == []
        return wall, {"single": pd.DataFrame({"job": ["seed=0", "seed=1"], "status": statuses})}

    replayed = []

    def replay(paths):
        replayed.extend(path.relative_to(path.parents[1]) for path in paths)
        return Replay(14.0, 6.0, faithful)

    monkeypatch.setattr(bench_reproduce, "reproduce", fake)
    monkeypatch.setattr(bench_reproduce, "replay", replay)
    row = bench_reproduce.full_row()
    assert replayed == [Path("single/seed=0"), *([Path("single/seed=1")] if statuses[1] == "done" else [])]
    assert (row["value"], row["baseline"], row["ok"]) == (wall, 20.0, met)
    assert row["ratio"] == pytest.approx(wall / 20.0) and row["measure"] == "riskplan reproduce, 2 runs (s)"
    assert ("DIFFERENT from the replay's" in row["note"]) == (not faithful)
    assert "(14.0 s and 6.0 s)" in row["note"]


@pytest.mark.slow  # two short runs trained and replayed
def test_the_replay_simulates_the_runs_own_episodes(tmp_path):
    """The kernel floors replay every episode of finished runs, a team's robots each at its own logged theta and a
    single run in the same kernel calls: the replayed training episodes give every robot's logged means bit for
    bit, a run whose log says otherwise is caught, and only the kernels are timed: the episode kernels, and apart
    the bootstrap kernels of the summaries' intervals."""
    import pandas as pd
    from support import CHECKPOINTED_TEAM, TINY

    from riskplan.engine import rollout, threads
    from riskplan.experiments.bench_kernel_share import kernel_clock, replay
    from riskplan.run.intervals import bootstrap_intervals
    from riskplan.run.training import train_summary

    single, team = tmp_path / "single", tmp_path / "team"
    train_summary(build_setup(compose([*TINY, "train.iterations=4"])), single)
    train_summary(
        build_setup(
            compose([*CHECKPOINTED_TEAM, "train.iterations=6", "team.faults=[{robot: 1, kind: crash, from: 3}]"])
        ),
        team,
    )
    floor = replay([single, team])
    assert floor.faithful and floor.episodes > 0 and floor.bootstrap > 0
    log = team / "metrics.parquet"  # a robot whose logged mean is not its episodes'
    metrics = pd.read_parquet(log)
    metrics.loc[(metrics["iteration"] == 5) & (metrics["robot"] == 2), "mean"] += 1e-9
    metrics.to_parquet(log)
    assert replay([single, team]).faithful is False
    assert replay([single]).faithful is True

    kernel, spread = rollout._simulate_affine, threads.over_threads
    with kernel_clock() as spent:
        assert rollout._simulate_affine is not kernel and threads.over_threads is not spread
        assert spent == {"episodes": 0.0, "bootstrap": 0.0}
        rollout.simulate(*_paper_call())
        assert spent["episodes"] > 0 and spent["bootstrap"] == 0.0
        bootstrap_intervals(np.arange(1000.0), 0.1, 100, 0)
        assert spent["bootstrap"] > 0
    assert (rollout._simulate_affine, threads.over_threads) == (kernel, spread)  # themselves once the block ends


def _paper_call():
    setup = build_setup(compose([]))
    return setup.world, setup.kernel, setup.theta0[None], np.zeros(1, np.int64), np.array([7], np.uint64), 100


@pytest.mark.parametrize(
    "args, line",
    [
        (["--json", "adir"], "error: --json: adir is a folder; give a file path ending .json"),
        (["--json", "nodir/x.json"], "error: --json: nodir/x.json cannot be written: no folder nodir"),
        (["--scaling", "--csv", "adir"], "error: --csv: adir is a folder; give a file path ending .csv"),
        (["--scaling", "--plot", "x.jpg"], "error: --plot: got x.jpg; give a file path ending .png, .pdf, .svg"),
        (["--csv", "x.csv"], "error: --csv: got x.csv; it applies with --scaling only"),  # was ignored
        (["--plot", "x.png"], "error: --plot: got x.png; it applies with --scaling only"),
        (["--scaling", "--sweep"], "error: --sweep: given with --scaling; each runs instead of the targets: give one"),
        (["--threads", "--reproduce"], "error: --threads: given with --reproduce;"),  # only the first ran
    ],
)
def test_the_files_bench_writes_are_checked_before_it_measures(tmp_path, monkeypatch, args, line):
    """A --json, --csv or --plot the bench could not write is one line and exit code 2 at once, not a traceback
    after minutes of measuring (and the lost figures)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "adir").mkdir()
    measured = []
    monkeypatch.setattr("riskplan.commands.bench._sections", lambda *a, **k: measured.append(a) or ())
    result = CliRunner().invoke(app, ["bench", "--quick", *args])
    assert result.exit_code == 2 and result.stderr.splitlines()[0].startswith(line), result.output
    assert len(result.stderr.splitlines()) == 1 and measured == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir"]


def test_bench_json_says_ok_as_true_or_false_whatever_type_a_measure_gave(tmp_path, monkeypatch):
    """The rollout and team-memory rows computed "ok" as numpy floats (0.0, 1.0), written as numbers."""
    rows = [
        {**_row(name, ok), "note": ""} for name, ok in (("a", np.float64(1.0)), ("b", np.bool_(False)), ("c", True))
    ]
    monkeypatch.setattr("riskplan.commands.bench._sections", lambda *a, **k: (lambda: rows,))
    result = CliRunner().invoke(app, ["bench", "--json", str(tmp_path / "b.json")])
    assert result.exit_code == 0, result.output
    written = json.loads((tmp_path / "b.json").read_text())
    assert [row["ok"] for row in written] == [True, False, True]
    # and how it was measured: not --quick, at the load average of its section's end
    assert all(
        row["quick"] is False and row["load_average"] == pytest.approx(os.getloadavg()[0], abs=2) for row in written
    )
