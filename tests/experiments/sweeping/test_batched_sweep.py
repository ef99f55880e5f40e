"""`riskplan sweep --batch` (riskplan.experiments.sweeping.batched): the same folders and files as the sweep
without it, bit for bit the same numbers, a bad job failing alone, a killed batch resuming to the same numbers,
and batches cut to the memory budget."""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from types import SimpleNamespace

import numba
import pandas as pd
import pytest
import yaml
from support import FAST, TINY, assert_same_outputs, riskplan_cli
from test_sweep_command import job_dirs, sweep_dir_of

from riskplan import compose, train
from riskplan.experiments.sweeping import batched
from riskplan.experiments.sweeping.batched import FreedCores, own_seconds, plan_chunks, side_by_side, train_part
from riskplan.run import batch
from riskplan.run.batch import BatchRun
from riskplan.run.build import build_setup

GRID = ["risk.beta=0.1,0.3", "seed=range(0,2)", "experiment=paper_single,paper_team", *FAST]


def files_of(job) -> set[str]:
    return {str(p.relative_to(job)) for p in job.rglob("*") if p.is_file()}


@pytest.mark.slow
def test_a_batched_sweep_leaves_the_same_folders_files_and_numbers(tmp_path):
    plain = riskplan_cli(tmp_path, "sweep", *GRID, "hydra.sweep.dir=plain")
    batched = riskplan_cli(tmp_path, "sweep", *GRID, "hydra.sweep.dir=batched", "--batch")
    assert plain.returncode == 0 and batched.returncode == 0, plain.stderr + batched.stderr
    assert "batched: 8 runs in 1 group of a shared world, trained as 1 batch" in batched.stdout
    assert "estimated time:" in batched.stdout and "memory budget" in batched.stdout
    want, got = job_dirs(tmp_path / "plain"), job_dirs(tmp_path / "batched")
    assert [d.name for d in got] == [d.name for d in want] and len(got) == 8
    for a, b in zip(got, want):
        assert files_of(a) == files_of(b)
        assert_same_outputs(a, b)
        assert (a / ".hydra" / "config.yaml").read_text() == (b / ".hydra" / "config.yaml").read_text()
        assert (
            json.loads((a / "status.json").read_text())["config_sha"]
            == json.loads((b / "status.json").read_text())["config_sha"]
        )
    summaries = [pd.read_parquet(tmp_path / d / "summary.parquet") for d in ("batched", "plain")]
    columns = ["job", "status", "mean", "cvar", "value_at_risk"]
    pd.testing.assert_frame_equal(summaries[0][columns], summaries[1][columns])
    assert not (tmp_path / "batched" / ".batch_progress.json").exists()
    # run again: every job is finished and skipped
    again = riskplan_cli(tmp_path, "sweep", *GRID, "hydra.sweep.dir=batched", "--batch")
    assert again.returncode == 0 and "8 jobs: 0 to run, 8 already finished" in again.stdout


@pytest.mark.slow
def test_a_bad_job_in_a_batch_fails_alone(tmp_path):
    result = riskplan_cli(
        tmp_path, "sweep", "seed=0,1", "train.step_size.initial=0.1,1e308", "world.start=[0,0],[40,0]", *FAST, "--batch"
    )
    assert result.returncode == 1
    summary = pd.read_parquet(sweep_dir_of(result, tmp_path) / "summary.parquet")
    done = summary[summary.status == "done"]
    assert len(summary) == 8 and len(done) == 2
    assert set(done["train.step_size.initial"]) == {0.1} and set(done["world.start"].astype(str)) == {"[0, 0]"}
    errors = " ".join(summary.error.dropna())
    assert "theta or its gradient is not finite" in errors and "world.start" in errors


@pytest.mark.slow
def test_a_killed_batched_sweep_resumes_to_the_same_numbers(tmp_path):
    run = [*FAST, "train.iterations=6", "train.checkpoint_every=2"]
    args = ["sweep", "seed=0,1", "risk.beta=0.1,0.2", *run]
    # the uninterrupted runs, trained here: a sweep's job is its run alone (tests/e2e/test_determinism.py)
    reference = {}
    for seed in (0, 1):
        for beta in (0.1, 0.2):
            reference[seed, beta] = tmp_path / "plain" / f"{seed},{beta}"
            train(compose([*run, f"seed={seed}", f"risk.beta={beta}"]), reference[seed, beta])
    killed = riskplan_cli(
        tmp_path, *args, "hydra.sweep.dir=s", "--batch", env={"RISKPLAN_TEST_KILL_IN_CHECKPOINT": "4"}
    )
    assert killed.returncode != 0
    statuses = [json.loads(p.read_text())["status"] for p in (tmp_path / "s").glob("*/status.json")]
    assert statuses and "done" not in statuses  # killed while training: none recorded as done
    resumed = riskplan_cli(tmp_path, *args, "hydra.sweep.dir=s", "--batch")
    assert resumed.returncode == 0, resumed.stderr
    again = [json.loads((a / "status.json").read_text()) for a in job_dirs(tmp_path / "s")]
    assert any(status["resumed"] for status in again)  # from a checkpoint, not from scratch
    jobs = job_dirs(tmp_path / "s")
    assert len(jobs) == 4
    for job in jobs:
        config = yaml.safe_load((job / ".hydra" / "config.yaml").read_text())
        assert_same_outputs(job, reference[config["seed"], config["risk"]["beta"]])


def test_batch_and_a_launcher_or_jobs_are_bad_input(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from riskplan.cli import app

    monkeypatch.chdir(tmp_path)
    for extra in (["hydra/launcher=basic"], ["--jobs", "2"], ["hydra/sweeper=basic"]):
        result = CliRunner().invoke(app, ["sweep", "seed=0,1", *FAST, "--batch", *extra])
        assert result.exit_code == 2, result.output
        assert len(result.stderr.strip().splitlines()) == 1 and result.stderr.startswith("error: ")
    assert not (tmp_path / "outputs").exists()


def test_batches_are_the_groups_cut_to_the_memory_budget():
    jobs = [
        SimpleNamespace(batch=key, memory=memory) for key, memory in [("a", 4), ("a", 4), ("b", 1), ("a", 4), ("a", 9)]
    ]
    chunks = plan_chunks(jobs, 10, key=lambda j: j.batch, size=lambda j: j.memory)
    assert [[(j.batch, j.memory) for j in chunk] for chunk in chunks] == [
        [("a", 4), ("a", 4)],
        [("a", 4)],
        [("a", 9)],  # larger than the rest of the budget: a batch of its own
        [("b", 1)],
    ]


def test_small_batches_of_different_worlds_train_side_by_side_within_the_memory_budget():
    jobs = [SimpleNamespace(batch=key, memory=memory) for key, memory in [("a", 3), ("b", 3), ("c", 3), ("d", 9)]]
    chunks = plan_chunks(jobs, 10, key=lambda j: j.batch, size=lambda j: j.memory)
    rounds = side_by_side(chunks, 10, size=lambda j: j.memory)
    assert [[[j.batch for j in chunk] for chunk in chunks] for chunks in rounds] == [[["a"], ["b"], ["c"]], [["d"]]]


@pytest.mark.slow
def test_hydra_launcher_memory_gb_cuts_the_batches_the_plan_says(tmp_path):
    """The plan's batches and the launcher's are the same, cut to hydra.launcher.memory_gb when it is given."""
    from riskplan.run.build import build_setup
    from riskplan.run.compose import compose
    from riskplan.run.cost import run_bytes

    need = run_bytes(build_setup(compose([*FAST, "train.iterations=2"])))
    limit_gb = 2.5 * need / 1e9  # room for two runs a batch
    result = riskplan_cli(
        tmp_path,
        "sweep",
        "seed=range(0,5)",
        *FAST,
        "train.iterations=2",
        "--batch",
        f"hydra.launcher.memory_gb={limit_gb}",
    )
    assert result.returncode == 0, result.stderr
    assert "trained as 3 batches" in result.stdout and "hydra.launcher.memory_gb" in result.stdout
    sizes = sorted(
        int(line.rsplit("in a batch of ", 1)[1].rstrip(")\n"))
        for job in job_dirs(sweep_dir_of(result, tmp_path))
        for line in (job / "job.log").read_text().splitlines()
        if "in a batch of" in line
    )
    assert sizes == [1, 2, 2, 2, 2]
    # each job's wall time is its own share of its batch, not its batch's (or the launch's) whole time: the three
    # batches train one after another in this process, so the shares add up to less than the sweep took
    seconds = [
        json.loads((job / "status.json").read_text())["seconds"] for job in job_dirs(sweep_dir_of(result, tmp_path))
    ]
    took = float(result.stdout.rsplit(" skipped, ", 1)[1].split(" s)", 1)[0])
    assert sum(seconds) < took


@pytest.mark.parametrize("value", ["-1", "0", "nan", "inf", "lots", "true"])
def test_a_memory_limit_that_is_not_a_positive_number_is_bad_input(tmp_path, monkeypatch, value):
    from typer.testing import CliRunner

    from riskplan.cli import app

    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["sweep", "seed=0,1", *FAST, "--batch", f"hydra.launcher.memory_gb={value}"])
    assert result.exit_code == 2, result.output
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith("error: hydra.launcher.memory_gb: got ") and "positive number of GB" in line
    assert not (tmp_path / "outputs").exists()


@pytest.mark.parametrize(
    "override, expected",
    [
        ("hydra.launcher.memory_gb=1e-12", "got 1e-12; expected at least 1e-9 GB (one byte) that a batch may use"),
        ("hydra.launcher.workers=0", "got 0; expected a whole number of processes >= 1, or null"),
        ("hydra.launcher.workers=-1", "got -1; expected a whole number of processes >= 1, or null"),
        ("hydra.launcher.workers=1.5", "got 1.5; expected a whole number of processes >= 1, or null"),
    ],
)
def test_batch_settings_no_batch_could_use_are_bad_input(tmp_path, monkeypatch, override, expected):
    """A limit below one byte planned "within the 0.001 B memory budget"; workers 0 and -1 ran as the default."""
    from typer.testing import CliRunner

    from riskplan.cli import app

    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["sweep", "seed=0,1", *FAST, "--batch", override])
    assert result.exit_code == 2, result.output
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith(f"error: {override.partition('=')[0]}: {expected}")
    assert not (tmp_path / "outputs").exists()


def test_a_batched_job_gets_its_own_share_of_its_part():
    """A finished run's own seconds, plus an equal share of what the part spent on no run alone; a failed run
    (no own seconds) gets only that share; together they are the part's time."""
    runs = [BatchRun(None, Path(name)) for name in "abc"]
    runs[0].seconds, runs[1].seconds = 1.0, 3.0  # runs[2] failed
    assert own_seconds(runs, 7.0) == [2.0, 4.0, 1.0]
    assert sum(own_seconds(runs, 7.0)) == 7.0


needs_two_threads = pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="numba runs one thread here")


def test_a_part_takes_its_share_of_the_cores_its_finished_siblings_left(tmp_path, monkeypatch):
    """Four cores, four parts: one thread each while all train, two once two siblings have marked their files
    finished (the cores over the parts left), never fewer than it was given."""
    monkeypatch.setattr(batched, "cpu_count", lambda: 4)
    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 4)  # numba's own pool has 2 threads here: set_num_threads
    monkeypatch.setattr(numba, "set_num_threads", lambda n: calls.append(n))  # is recorded, not made
    monkeypatch.setattr(numba, "get_num_threads", lambda: calls[-1] if calls else 1)
    calls: list[int] = []
    siblings = [tmp_path / f"part.{i}.json" for i in range(3)]
    freed = FreedCores(1, siblings)
    freed.take()
    assert calls == []  # every sibling trains (no file yet)
    siblings[0].write_text(json.dumps({"done": 5, "total": 20, "finished": True}))
    siblings[1].write_text(json.dumps({"done": 5, "total": 20}))  # trained, still evaluating
    freed.take()
    assert calls == []  # 4 cores over 3 parts: still one thread
    siblings[1].write_text(json.dumps({"done": 5, "total": 20, "finished": True}))
    siblings[2].write_text("{not json")  # a file being replaced: not finished
    freed.take()
    assert calls == [2]
    siblings[2].write_text(json.dumps({"done": 5, "total": 20, "finished": True}))
    freed.take()
    assert calls == [2, 4]
    assert FreedCores(3, []).take() is None and calls == [2, 4]  # no siblings: nothing to take


@pytest.mark.slow
@needs_two_threads
def test_a_part_whose_siblings_finished_evaluates_on_both_cores_to_the_same_numbers(tmp_path, monkeypatch):
    """The same two runs as a part on one thread, once beside a sibling still training and once after its
    sibling finished: the second evaluates them on two threads, the first on one, and every number is the same;
    the part's file ends marked finished."""
    monkeypatch.setattr(batched, "cpu_count", lambda: 2)
    threads: list[int] = []
    finish = batch._finish
    monkeypatch.setattr(batch, "_finish", lambda *a, **k: (threads.append(numba.get_num_threads()), finish(*a, **k)))
    configs = [compose([*FAST, f"seed={seed}"]) for seed in (0, 1)]
    sibling = tmp_path / "progress.1.json"
    before = numba.get_num_threads()  # train_part sets this thread's: put back after
    try:
        for name, state in (
            ("alone", {"done": 3, "total": 20}),
            ("freed", {"done": 10, "total": 20, "finished": True}),
        ):
            sibling.write_text(json.dumps(state))
            outs = [tmp_path / name / f"seed={seed}" for seed in (0, 1)]
            mine = tmp_path / f"{name}.0.json"
            records = train_part([build_setup(c) for c in configs], outs, [False, False], 1, mine, 20, [sibling])
            assert [r["status"] for r in records] == ["done", "done"]
            assert json.loads(mine.read_text()) == {"done": 10, "total": 20, "finished": True}
    finally:
        numba.set_num_threads(before)
    assert threads == [1, 1, 2, 2]
    for seed in (0, 1):
        assert_same_outputs(tmp_path / "freed" / f"seed={seed}", tmp_path / "alone" / f"seed={seed}")


def test_a_part_built_in_a_worker_leaves_its_configs_warnings_to_the_driver(tmp_path):
    """A worker's part printed Python's raw warning (path, line, source) for each run, after the driver's own line."""
    with pytest.warns(UserWarning, match="breaks Assumption 6"):  # the driver's planning warns here, once
        config = compose([*TINY, "train.step_size.power=0.3"])
    before = numba.get_num_threads()  # train_part sets this thread's: put back after
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            (record,) = train_part([config], [tmp_path / "job"], [False], 1, tmp_path / "progress.0.json", 3)
    finally:
        numba.set_num_threads(before)
    assert record["status"] == "done"
    assert not [w for w in caught if issubclass(w.category, UserWarning)]
