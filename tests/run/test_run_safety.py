"""A run's results are never lost or mixed: claimed and locked run directories, real read-only mounts and full
disks, O(1) validated checkpoints, and no NaN or infinity written as a result.

Most tests drive real `riskplan train` processes or the CLI (those are slow); the mount tests need root (they are
skipped with the reason otherwise), because root ignores permission bits and only a real read-only mount or full
disk refuses it. The lock itself is tested in tests/util/test_lock.py, config strings in
tests/config/test_hydra_safety.py.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from support import (
    TINY,
    assert_same_outputs,
    child_env,
    files,
    kill_after_iteration,
    mounted,
    resume_cli,
    riskplan_command,
    run_cli,
    setup_of,
    train_cli,
)
from typer.testing import CliRunner

import riskplan.engine.step as engine_step
import riskplan.run.training as training
from riskplan import compose, load_run
from riskplan.cli import app
from riskplan.engine.step import NumericalTrouble
from riskplan.run.checkpoint import CHECKPOINT
from riskplan.run.record import RunLog
from riskplan.run.recorder import STOP_ENV
from riskplan.run.training import prepare_resume
from riskplan.util.errors import BadInput
from riskplan.util.lock import LOCK, holder

RUN = [*TINY, "train.iterations=12", "train.checkpoint_every=4"]  # the tests know its 12 iterations

runner = CliRunner()


def strict_json(text: str):
    """json.loads that refuses NaN and Infinity (which are not JSON)."""

    def refuse(token):
        raise ValueError(f"non-finite number {token} in JSON")

    return json.loads(text, parse_constant=refuse)


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """A finished run of RUN through the real CLI."""
    out = tmp_path_factory.mktemp("finished") / "run"
    result = train_cli(RUN, out)
    assert result.returncode == 0, result.stderr
    return out


# ------------------------------------------------------------------------------------ claimed, locked directories
@pytest.mark.slow  # the `finished` run: `riskplan train` in a subprocess
def test_a_second_run_into_a_finished_run_directory_is_refused_and_changes_nothing(finished, tmp_path, monkeypatch):
    before = files(finished)
    monkeypatch.chdir(tmp_path)  # in this process: refused before anything runs, as bad input
    result = CliRunner().invoke(app, ["train", *RUN, "seed=7", f"hydra.run.dir={finished}"])  # another config
    assert result.exit_code == 2
    assert result.stderr.strip() == (
        f"error: hydra.run.dir: {finished} already holds a run; resume it with riskplan "
        f"train --resume {finished}, or give a new directory"
    )
    assert files(finished) == before
    assert load_run(finished).complete and load_run(finished).config["seed"] == 0


@pytest.mark.slow  # the `finished` run: `riskplan train` in a subprocess
def test_the_python_api_refuses_a_directory_that_holds_another_run(finished, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(finished, copy)
    before = files(copy)
    with pytest.raises(BadInput, match="already holds a run; resume it with riskplan train --resume"):
        training.train(compose([*RUN, "seed=3"]), copy)
    assert files(copy) == before


@pytest.mark.slow  # `riskplan train` in subprocesses
def test_two_processes_never_write_one_run_directory(tmp_path):
    out = tmp_path / "run"
    first = subprocess.Popen(
        [*riskplan_command(), "train", *RUN, f"hydra.run.dir={out}"],
        cwd=tmp_path,
        env=child_env(**{STOP_ENV: "2"}),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        _, status = os.waitpid(first.pid, os.WUNTRACED)  # it stops itself after iteration 2, holding the lock
        assert os.WIFSTOPPED(status)
        assert holder(out) == first.pid
        before = files(out)
        for args in (["train", *RUN, f"hydra.run.dir={out}"], ["train", "--resume", str(out)]):
            second = run_cli(args, tmp_path)
            assert second.returncode == 2, second.stderr
            assert second.stderr.strip() == (
                f"error: {out}: is in use by another riskplan process (pid {first.pid}); "
                f"one process writes a run directory at a time: wait for it to end or "
                f"stop it"
            )
        assert files(out) == before
        first.send_signal(signal.SIGCONT)
        assert first.wait(timeout=300) == 0
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert holder(out) is None and load_run(out).complete  # the lock dies with its holder


# ------------------------------------------------------------------------------------ read-only mounts, full disks
@pytest.mark.slow  # runs refused on a read-only mount (near a second)
def test_a_read_only_output_directory_is_one_line_and_nothing_written(tmp_path, monkeypatch):
    source = tmp_path / "source"
    source.mkdir()
    runner = CliRunner()  # in this process: refused before anything runs, as bad input
    with mounted(tmp_path / "ro", "--bind", str(source)) as target:
        assert subprocess.run(["mount", "-o", "remount,bind,ro", str(target)]).returncode == 0
        monkeypatch.chdir(tmp_path)
        result = runner.invoke(app, ["train", *RUN, f"hydra.run.dir={target / 'run'}"])
        assert result.exit_code == 2
        assert result.stderr.strip() == (
            f"error: hydra.run.dir: {target / 'run'} is on a read-only filesystem; give a directory you can write"
        )
        monkeypatch.chdir(target)
        default = runner.invoke(app, ["train", *RUN])  # outputs/runs/<timestamp> below a read-only working directory
        monkeypatch.chdir(tmp_path)  # out of the mount before it goes
        assert default.exit_code == 2
        assert default.stderr.strip() == (
            "error: outputs/runs: outputs/runs is on a read-only filesystem; give a directory you can write"
        )
    assert list(source.iterdir()) == []


@pytest.mark.slow  # `riskplan train` in subprocesses
def test_a_full_disk_fails_in_one_line_keeps_every_checkpoint_and_resumes_to_the_same_result(tmp_path, finished):
    with mounted(tmp_path / "small", "-t", "tmpfs", "-o", "size=160k", "tmpfs") as disk:
        out = disk / "run"
        result = train_cli([*RUN, "train.eval_episodes=20000"], out)  # the eval table does not fit
        assert result.returncode == 1
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and "No space left on device" in lines[0] and "--resume" in lines[0], result.stderr
        assert "Traceback" not in result.stderr
        leftovers = [
            p.name
            for p in out.rglob("*")
            if p.is_file() and (p.name.endswith(".tmp") or (p.stat().st_size == 0 and p.name not in ("app.log", LOCK)))
        ]  # Hydra's log and the lock are empty
        assert leftovers == []
        assert json.loads((out / CHECKPOINT).read_text())["iteration"] == 12  # every iteration was kept
        assert len(load_run(out).metrics) == 12

        assert subprocess.run(["mount", "-o", "remount,size=8m", str(disk)]).returncode == 0  # space again
        again = run_cli(["train", "--resume", str(out)], tmp_path)
        assert again.returncode == 0, again.stderr
        reference = tmp_path / "reference"  # trained here: the numbers of a `riskplan train` (test_determinism.py)
        training.train(compose([*RUN, "train.eval_episodes=20000"]), reference)
        assert_same_outputs(out, reference)


@pytest.mark.slow  # killed `riskplan train` processes
@pytest.mark.parametrize("extra", [[], ["train.iterations=14"]])
def test_a_run_stopped_before_its_first_checkpoint_resumes_from_its_start(tmp_path, extra):
    """Killed at iteration 2 of 12, before the checkpoint at 4: --resume trains it again in its directory (nothing
    of it was kept), to the numbers of an uninterrupted run, rather than sending the user to start it again, which
    the directory's own run would refuse."""
    out = tmp_path / "early"
    assert kill_after_iteration(RUN, out, 2) == -signal.SIGKILL
    assert not (out / CHECKPOINT).exists() and (out / "run.mcap").is_file()
    again = resume_cli(out, *extra)
    assert again.returncode == 0, again.stderr
    assert again.stdout.startswith(f"restarting (no checkpoint yet): {out}")
    reference = tmp_path / "reference"
    training.train(compose([*RUN, *extra]), reference)
    assert_same_outputs(out, reference)


# ------------------------------------------------------------------------------------ checkpoints
@pytest.mark.slow  # a 60-iteration team run
def test_a_checkpoint_costs_the_same_at_every_iteration(tmp_path):
    """A checkpoint holds the state (theta, the consensus buffers), not the rows so far: O(1) per checkpoint."""
    sizes = {}
    real_replace = os.replace

    def record(src, dst):
        if Path(dst).name == CHECKPOINT:
            sizes[json.loads(Path(src).read_text())["iteration"]] = Path(src).stat().st_size
        real_replace(src, dst)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(os, "replace", record)
        training.train(
            compose(
                [
                    "experiment=paper_team",
                    "team.delay.max=2",
                    *TINY,
                    "train.iterations=60",
                    "train.samples=100",
                    "train.checkpoint_every=5",
                ]
            ),
            tmp_path / "run",
        )
    assert sorted(sizes) == list(range(5, 61, 5))
    assert max(sizes.values()) - min(sizes.values()) < 0.1 * min(sizes.values())  # digits of theta only


@pytest.mark.slow  # the `finished` run: `riskplan train` in a subprocess
def test_a_log_whose_rows_do_not_match_the_checkpoint_is_bad_input(finished, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(finished, out)
    log = RunLog(out / "run.mcap")  # a log with one row too many in every iteration (robot 5 of one robot)
    row = pd.read_parquet(finished / "metrics.parquet").iloc[0].to_dict()
    for iteration in range(12):
        log.iteration([{**row, "iteration": iteration}, {**row, "iteration": iteration, "robot": 5}])
    log.close()
    with pytest.raises(BadInput, match="holds rows that do not match the checkpoint"):
        prepare_resume(compose(RUN), out)


@pytest.mark.slow  # the `finished` run: `riskplan train` in a subprocess
@pytest.mark.parametrize(("key", "value"), [("seed", 5), ("risk.beta", 0.3), ("train.samples", 60)])
@pytest.mark.parametrize("extra", [[], ["train.iterations=14"]], ids=["resumed", "extended"])
def test_a_hand_edited_config_is_not_resumed(finished, tmp_path, monkeypatch, key, value, extra):
    """A resume goes on with the run's own config: a .hydra/config.yaml edited since (another seed or beta) would
    train the rest of the run under another config, a result of neither. run.mcap recorded the config it ran."""
    out = tmp_path / "run"
    shutil.copytree(finished, out)
    config = yaml.safe_load((out / ".hydra" / "config.yaml").read_text())
    node, leaf = config, key.split(".")
    for part in leaf[:-1]:
        node = node[part]
    node[leaf[-1]] = value
    (out / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config))
    before = files(out)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["train", "--resume", str(out), *extra])
    assert result.exit_code == 2, result.output
    assert result.stderr.strip() == (
        f"error: {out}/.hydra/config.yaml: differs from the config run.mcap recorded for this run in {key}; "
        f"restore it: a resumed run goes on with its own config (only train.iterations=N may be given), or train a "
        f"new run"
    )
    assert files(out) == before


@pytest.mark.slow  # the `finished` run: `riskplan train` in a subprocess
def test_a_run_whose_config_folder_links_to_another_runs_is_not_extended(finished, tmp_path, monkeypatch):
    """Extending a run rewrites its config: through a linked .hydra, that was another run's, which a later resume of
    that run then extended unasked."""
    other, linked = tmp_path / "other", tmp_path / "linked"
    shutil.copytree(finished, other)
    shutil.copytree(finished, linked)
    shutil.rmtree(linked / ".hydra")
    (linked / ".hydra").symlink_to(other / ".hydra")
    before = files(other)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["train", "--resume", str(linked), "train.iterations=14"])
    assert result.exit_code == 2 and result.stderr.strip() == (
        f"error: {linked}/.hydra: is a symbolic link; a run keeps its own config: copy the run rather than link it"
    )
    assert files(other) == before


# ------------------------------------------------------------------------------------ never a non-finite result
def test_a_non_finite_reward_stops_the_run_with_one_line_and_writes_no_result(tmp_path, monkeypatch):
    real = engine_step.simulator  # the episode kernel the engine's step runs

    def overflowing_kernel(setup):
        kernel = real(setup)

        def overflowing(*args, **kwargs):
            batch = kernel(*args, **kwargs)
            batch.total_reward[0] = np.inf  # what a reward program that overflows would give
            return batch

        return overflowing

    monkeypatch.setattr(engine_step, "simulator", overflowing_kernel)
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["train", *RUN, f"hydra.run.dir={tmp_path / 'run'}"])
    assert result.exit_code == 1
    assert result.stderr.strip().startswith(
        "error: run failed: iteration 0: an episode's total reward is not finite (overflow)"
    )
    assert not (tmp_path / "run" / "summary.json").exists() and not (tmp_path / "run" / CHECKPOINT).exists()
    assert json.loads((tmp_path / "run" / "status.json").read_text())["status"] == "failed"


@pytest.mark.slow  # the `finished` run: `riskplan train` in a subprocess
def test_summary_json_holds_no_nan_or_infinity(finished):
    summary = strict_json((finished / "summary.json").read_text())
    assert summary["throughput_episodes_per_s"] > 0
    with pytest.raises(NumericalTrouble):
        engine_step.check_finite("x", np.array([1.0, np.nan]))


def test_a_key_a_later_riskplan_added_is_no_difference_from_the_logged_config(tmp_path):
    """A run logged before a key existed resumes: the key's default is what it ran with. A changed value is not."""
    from riskplan.run.run_directory import _check_logged_config

    config = setup_of(*RUN).config
    older = {name: value for name, value in config.items() if name != "engine"}  # as if logged before `engine`
    _check_logged_config(tmp_path / "run.mcap", older, config)
    changed = {**older, "train": {**older["train"], "samples": older["train"]["samples"] + 1}}
    with pytest.raises(BadInput, match=r"differs from the config run.mcap recorded for this run in train.samples;"):
        _check_logged_config(tmp_path / "run.mcap", changed, config)
