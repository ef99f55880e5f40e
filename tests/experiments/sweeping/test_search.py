"""Search spaces of an optimising sweeper (riskplan.experiments.sweeping.search): the sample values a search-space
override is checked with before the study runs, and the ranges and intervals refused as bad input. The study
itself runs in test_optuna_sweeper.py."""

from __future__ import annotations

import pytest

from riskplan.experiments.sweeping.search import search_samples
from riskplan.run.compose import parse_overrides
from riskplan.util.errors import BadInput


@pytest.mark.parametrize(
    "override, samples",
    [
        ("x=choice(0,3)", ["0", "3"]),  # every value of a choice
        ("x=choice(a,b,c)", ["a", "b", "c"]),
        ("x=range(2,9,3)", ["2"]),  # the start of a range
        ("x=range(0,1,0.25)", ["0.0"]),
        ("x=interval(0.05,1)", ["0.525"]),  # the middle of an interval
        ("x=tag(log,interval(1,100))", ["10.0"]),  # on a log scale: the geometric middle
    ],
)
def test_a_search_space_is_checked_with_values_of_the_types_the_sweeper_draws(override, samples):
    assert search_samples(parse_overrides([override])[0], "optuna") == samples


@pytest.mark.parametrize(
    "override, problem",
    [
        ("x=range(0,5,0)", "a step of 0"),
        ("x=range(5,0)", "is an empty range"),
        ("x=interval(1,0)", "has its lower bound 1.0 not below its upper bound 0.0"),
        ("x=tag(log,interval(0,1))", "a log interval needs a lower bound above 0"),
        ("x=glob(*)", "the optuna sweeper takes choice(...), comma lists, range(...) or interval(...), not glob(...)"),
    ],
)
def test_search_spaces_that_cannot_be_drawn_from_are_bad_input(override, problem):
    with pytest.raises(BadInput) as err:
        search_samples(parse_overrides([override])[0], "optuna")
    assert err.value.where == f"override '{override}'" and problem in err.value.problem


def test_a_sweeper_without_trial_settings_is_planned_with_a_worker_per_core(in_tmp):
    """Another Hydra sweeper (neither optuna nor a grid) names no trial count or batch: the plan gives the joblib
    launcher a worker per core rather than failing."""
    from dataclasses import dataclass

    from hydra.core.config_store import ConfigStore

    from riskplan.experiments.sweeping.plan import plan_sweep
    from riskplan.util.limits import cpu_count

    @dataclass
    class OtherSweeperConf:
        _target_: str = "hydra_plugins.riskplan_sweeper.plan_sweeper.RiskplanSweeper"
        jobs: str = ""

    ConfigStore.instance().store(group="hydra/sweeper", name="other_test_sweeper", node=OtherSweeperConf)
    plan = plan_sweep(["hydra/sweeper=other_test_sweeper", "seed=0,1", "train.iterations=2"])
    assert plan.sweeper == "other_test_sweeper" and plan.workers == cpu_count()


@pytest.mark.parametrize(
    "settings, where, problem",
    [
        (["hydra.sweeper.storage=notaurl"], "hydra.sweeper.storage", "Could not parse SQLAlchemy URL"),
        (["hydra.sweeper.storage=sqlite:////no/such/dir/x.db"], "hydra.sweeper.storage", "/no/such/dir is not a dir"),
        (
            ["hydra.sweeper.sampler._target_=optuna.samplers.RandomSampler"],  # over TPE's settings
            "hydra.sweeper.sampler",
            "RandomSampler cannot be made from these settings: TypeError: ",
        ),
        (["risk.beta=choice(0,2,-1)"], "override 'risk.beta=choice(0,2,-1)'", "the other 2 values likewise); no trial"),
        (["train.iterations=interval(2,4)"], "key 'train.iterations'", "; for whole numbers write int(interval(...))"),
    ],
)
@pytest.mark.slow  # imports optuna and SQLAlchemy: about a second a worker
def test_optuna_settings_that_fail_only_at_launch_are_bad_input_before_it(in_tmp, settings, where, problem):
    """A bad storage or sampler failed at launch (exit 1, a sweep folder left), and a choice of only rejected values
    ran every trial to fail; interval(2,4) is Hydra's float interval, which a whole-number key refuses."""
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper", reason="the optuna extra is not installed")
    from riskplan.experiments.sweeping.plan import plan_sweep

    search = [] if any("=choice" in s or "=interval" in s for s in settings) else ["risk.beta=interval(0.1,1)"]
    with pytest.raises(BadInput) as err:
        plan_sweep(["hydra/sweeper=optuna", "hydra.sweeper.n_trials=2", *search, *settings])
    assert err.value.where == where and problem in err.value.problem
    assert not (in_tmp / "outputs").exists()


@pytest.mark.slow  # imports optuna
def test_the_grid_sampler_runs_at_most_its_grid(in_tmp):
    """3 trials over a grid of 2 points ran 2 and said 'the sweeper ran 2 of 3 trials' (exit 1): optuna ends a grid
    study once every point ran."""
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper", reason="the optuna extra is not installed")
    from riskplan.experiments.sweeping.plan import plan_sweep

    plan = plan_sweep(
        ["hydra/sweeper=optuna", "hydra/sweeper/sampler=grid", "risk.beta=choice(0.1,0.5)", "hydra.sweeper.n_trials=3"]
    )
    assert plan.trials == 2
    plan = plan_sweep(
        ["hydra/sweeper=optuna", "hydra/sweeper/sampler=grid", "seed=range(0,4)", "hydra.sweeper.n_trials=3"]
    )
    assert plan.trials == 3
