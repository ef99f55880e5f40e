"""A sweep planned before anything runs (riskplan.experiments.sweeping.plan): every combination composed and
checked, its folder named by what varies, the model's rejections kept per job, the launcher's arguments; bad input
claims no directory. The same sweeps run through the CLI in test_sweep_command.py."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from support import TINY

from riskplan.experiments.sweeping.plan import plan_sweep
from riskplan.util.errors import BadInput


def test_a_grid_is_planned_job_by_job_before_anything_runs(in_tmp):
    plan = plan_sweep(["risk.beta=0.2,1.5", "seed=0,1", *TINY], jobs=2)
    assert plan.sweep_dir.parent == Path("outputs") / "sweeps" and list(plan.sweep_dir.iterdir()) == []  # claimed
    assert (plan.launcher, plan.workers, plan.sweeper) == ("joblib", 2, "riskplan")
    assert [job.folder for job in plan.jobs] == [
        "risk.beta=0.2,seed=0",
        "risk.beta=0.2,seed=1",
        "risk.beta=1.5,seed=0",
        "risk.beta=1.5,seed=1",
    ]
    assert [job.overrides[:2] for job in plan.jobs][2] == ["risk.beta=1.5", "seed=0"]
    assert [job.invalid is None for job in plan.jobs] == [True, True, False, False]  # beta=1.5 fails alone
    assert plan.jobs[2].invalid.startswith("risk.beta: got 1.5")
    assert len({job.sha for job in plan.jobs}) == 4 and all(job.path is None for job in plan.jobs)
    assert "hydra/launcher=joblib" in plan.argv and "hydra.launcher.n_jobs=2" in plan.argv
    assert "hydra/sweeper=riskplan" in plan.argv  # riskplan's sweeper launches the planned jobs


def test_joblib_workers_given_by_hand_are_a_pool_riskplan_starts_unless_other_joblib_settings_come_with_them(in_tmp):
    """hydra.launcher.n_jobs alone is the pool riskplan would start, of the user's size (pre-started with SIGINT held
    back, so an early Ctrl-C prints no worker's traceback); with other joblib settings the pool is Hydra's to make."""
    plan = plan_sweep(["seed=0,1,2", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", *TINY])
    assert plan.workers == 2 and plan.argv[plan.workers_arg] == "hydra.launcher.n_jobs=2"
    plan = plan_sweep(
        ["seed=0,1", "hydra/launcher=joblib", "hydra.launcher.n_jobs=8", *TINY]
    )  # no more workers than jobs
    assert plan.workers == 2 and plan.argv[plan.workers_arg] == "hydra.launcher.n_jobs=2"
    plan = plan_sweep(
        ["seed=0,1,2", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "hydra.launcher.verbose=1", *TINY]
    )
    assert plan.workers_arg is None and "hydra.launcher.n_jobs=2" in plan.argv


@pytest.mark.parametrize("typed", ["basic", "riskplan"])
def test_a_typed_grid_sweeper_is_riskplans_and_sweeper_settings_are_refused(in_tmp, typed):
    plan = plan_sweep(["seed=0,1", f"hydra/sweeper={typed}", *TINY])
    assert [a for a in plan.argv if a.startswith("hydra/sweeper")] == ["hydra/sweeper=riskplan"]
    assert plan.sweeper == "riskplan" and len(plan.jobs) == 2
    for setting in ("hydra.sweeper.max_batch_size=1", "hydra.sweeper.jobs=/etc/passwd"):
        with pytest.raises(BadInput, match="a grid sweep takes no sweeper settings"):
            plan_sweep(["seed=0,1", setting, *TINY])


@pytest.mark.parametrize(
    "args", [["risk.bta=0.1,0.2"], ["risk.beta=2,3"], ["seed=0,0"], ["risk.beta=interval(0,1)"], ["--jobs"]]
)
def test_bad_input_claims_no_directory(in_tmp, args):
    with pytest.raises(BadInput):
        plan_sweep([*args, *TINY])
    assert not (in_tmp / "outputs").exists()


@pytest.mark.parametrize("args", [["seed=1,2", "seed=3"], ["seed=range(0,2)", "seed=range(0,2)"]])
def test_a_swept_key_given_again_is_refused_not_replaced(in_tmp, args):
    """Hydra keeps the last value: `seed=1,2 seed=3` ran seed 3 alone, a dimension of the sweep gone unsaid."""
    with pytest.raises(BadInput, match=rf"^seed: swept by '{re.escape(args[0])}', then given again as "):
        plan_sweep([*args, *TINY], jobs=1)
    assert not Path("outputs").exists()
    plan = plan_sweep([*TINY, "train.iterations=2,3", "seed=4", "seed=5"], jobs=1)  # a plain value: the last wins
    assert [job.folder for job in plan.jobs] == ["train.iterations=2", "train.iterations=3"]
    assert all("seed=5" in job.overrides for job in plan.jobs)
