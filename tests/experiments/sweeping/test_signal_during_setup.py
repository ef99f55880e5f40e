"""Ctrl-C while a batched sweep sets its jobs up: the driver noted the signal, but the batch it launched next used
to install handlers of its own, never saw it, and trained every job to the end before the sweep said
"interrupted". Now the jobs set up are marked interrupted without training (none left "running"), the sweep ends
with the signal's code, and running it again trains them to the numbers of a sweep never interrupted."""

from __future__ import annotations

import json
import os
import signal

import pandas as pd
import pytest
from support import TINY
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.experiments.sweeping import batched
from riskplan.util.interrupt import StopSignals, pending_signal

runner = CliRunner()
ARGS = [*TINY, "train.iterations=4", "seed=0,1,2"]
FIGURES = ["mean", "cvar", "value_at_risk"]


def test_a_nested_stop_takes_up_the_signal_its_enclosing_one_noted():
    with StopSignals() as outer:
        assert pending_signal() is None
        os.kill(os.getpid(), signal.SIGTERM)
        assert outer.received == pending_signal() == signal.SIGTERM
        with StopSignals() as inner:
            assert inner.received == signal.SIGTERM  # its first chance to stop loses nothing
    assert pending_signal() is None


@pytest.mark.slow  # three tiny sweeps
def test_a_signal_while_jobs_are_set_up_leaves_them_interrupted_and_resumable(tmp_path, monkeypatch):
    plain = runner.invoke(app, ["sweep", *ARGS, f"hydra.sweep.dir={tmp_path / 'plain'}"])
    assert plain.exit_code == 0, plain.output
    prepare = batched.prepare_jobs

    def prepare_then_ctrl_c(*args, **kwargs):
        prepared = prepare(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C as the last job's folder is written
        return prepared

    monkeypatch.setattr(batched, "prepare_jobs", prepare_then_ctrl_c)
    stopped = runner.invoke(app, ["sweep", *ARGS, f"hydra.sweep.dir={tmp_path / 's'}"])
    assert stopped.exit_code == 130, stopped.output
    assert "error: interrupted by SIGINT: 3 jobs did not finish" in stopped.stderr
    for seed in (0, 1, 2):
        job = tmp_path / "s" / f"seed={seed}"
        status = json.loads((job / "status.json").read_text())
        assert (status["status"], status["error"]) == ("interrupted", "interrupted by SIGINT before it trained")
        assert not (job / "run.mcap").exists()  # not one iteration trained
        assert (job / "job.log").read_text().endswith("=== interrupted by SIGINT before it trained\n")

    monkeypatch.setattr(batched, "prepare_jobs", prepare)
    again = runner.invoke(app, ["sweep", *ARGS, f"hydra.sweep.dir={tmp_path / 's'}"])
    assert again.exit_code == 0, again.output
    after, before = (pd.read_parquet(tmp_path / name / "summary.parquet") for name in ("s", "plain"))
    assert after.status.tolist() == ["done"] * 3
    pd.testing.assert_frame_equal(after[FIGURES], before[FIGURES])
