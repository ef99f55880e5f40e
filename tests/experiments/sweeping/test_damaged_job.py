"""A sweep job killed mid-way whose checkpoint is then damaged: the next run of the sweep trains it again from
scratch, saying why in its job.log, to the numbers of an undamaged sweep, batched or job by job (a run of riskplan
train instead asks its user, since its folder is the user's)."""

from __future__ import annotations

import json

import pandas as pd
import pytest
from support import TINY
from typer.testing import CliRunner

from riskplan.cli import app

pytestmark = pytest.mark.slow  # real sweeps, kept tiny
runner = CliRunner()
ARGS = [*TINY, "train.iterations=6", "train.checkpoint_every=2", "seed=0,1"]


@pytest.mark.parametrize("how", [[], ["--jobs", "1"]], ids=["batched", "job by job"])
def test_a_killed_job_with_a_damaged_checkpoint_trains_again_to_the_same_numbers(tmp_path, how):
    assert runner.invoke(app, ["sweep", *ARGS, f"hydra.sweep.dir={tmp_path / 's'}", *how]).exit_code == 0
    job = tmp_path / "s" / "seed=0"
    before = pd.read_parquet(tmp_path / "s" / "summary.parquet")
    status = json.loads((job / "status.json").read_text())
    (job / "status.json").write_text(json.dumps({**status, "status": "running"}))  # as a kill leaves it
    (job / "checkpoint").write_text('{"iteration": 1')  # and a checkpoint riskplan never wrote

    result = runner.invoke(app, ["sweep", *ARGS, f"hydra.sweep.dir={tmp_path / 's'}", *how])

    assert result.exit_code == 0, result.output
    after = pd.read_parquet(tmp_path / "s" / "summary.parquet")
    assert after.status.tolist() == ["done", "done"]
    figures = ["mean", "cvar", "value_at_risk"]
    pd.testing.assert_frame_equal(after[figures], before[figures])
    opening = [line for line in (job / "job.log").read_text().splitlines() if line.startswith("=== riskplan")][-1]
    assert opening.startswith("=== riskplan sweep job started again (its checkpoint could not be resumed: ")
    assert "checkpoint: is damaged (JSONDecodeError" in opening
