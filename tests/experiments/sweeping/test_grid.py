"""Expanding and checking a sweep's grid (riskplan.experiments.sweeping.grid), before anything runs: Hydra's
expansion, folders named by what varies, and sweeps counted without expanding them."""

from __future__ import annotations

import re

import pytest

from riskplan.experiments.sweeping import constant_keys, expand, sweep_size
from riskplan.experiments.sweeping.grid import check_size
from riskplan.run.compose import parse_overrides
from riskplan.util.errors import BadInput


def test_expansion_is_hydras_and_folders_name_what_varies():
    from riskplan.run.compose import parse_overrides

    args = ["risk.beta=0.05,0.1", "seed=range(0,3)", "team.graph=line", "train.iterations=5"]
    combos = expand(parse_overrides(args), args)
    assert len(combos) == 6 and combos[0] == ["risk.beta=0.05", "seed=0", "team.graph=line", "train.iterations=5"]
    assert constant_keys(combos) == ["team.graph", "train.iterations"]
    assert constant_keys([["seed=0", "risk.beta=0.1"]]) == []  # nothing varies: keep every override in the name
    assert constant_keys([["seed=0", "risk.beta=0.1"]], {"seed"}) == ["risk.beta"]  # seed=range(0,1) was a sweep


@pytest.mark.parametrize(
    "args",
    [
        ["risk.beta=0.05,0.1", "seed=range(0,3)", "team.graph=line"],
        ["seed=0", "seed=4,5", "risk=cvar,neutral"],  # a key given twice keeps its first place, its last values
        ["+extra=1", "~seed", "risk.beta=choice(0.1,0.2)", "train.theta0=[1,2]"],
        ["world.sources.0.reward={normal:[1,2]}", "seed=range(3,0,-1)", "risk.measure=cvar"],
        ["experiment=glob(paper_*)", "seed=1"],
        [],
    ],
)
def test_the_grid_is_the_one_hydras_basic_sweeper_makes(args):
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper  # the reference riskplan's sweeper replaces

    from riskplan.experiments.sweeping.grid import combinations, override_parser

    parsed = override_parser().parse_overrides(args)
    (hydras,) = BasicSweeper.split_arguments(parsed, None)
    assert combinations(parsed) == [list(job) for job in hydras]


@pytest.mark.parametrize(
    "args, count",
    [
        (["seed=range(0,100000000)"], 100_000_000),
        (["seed=range(0,10,3)", "risk=neutral,cvar"], 8),
        (["seed=range(5,0,-1)", "train.iterations=5"], 5),
        (["risk.beta=range(0.1,0.5,0.1)"], 4),
        (["risk=glob(*)", "seed=0,1"], 10),  # conf/risk: cvar, entropic, mean_cvar, neutral, wang
        (["seed=shuffle(range(0,3))"], 3),
        (["seed=range(0,0)"], 0),
        (["seed=range(0,100000000000000000000000000000)"], 10**29),  # more than a C integer holds
        (["risk.beta=range(0,1,0.3)"], 4),
    ],
)
def test_a_sweep_is_counted_without_expanding_it(args, count):
    assert sweep_size(parse_overrides(args))[0] == count


@pytest.mark.parametrize("arg", ["risk.beta=range(0,inf)", "risk.beta=range(0,nan)", "seed=range(0,5,0)"])
def test_a_range_without_an_end_or_a_step_is_bad_input(arg):
    with pytest.raises(BadInput, match=re.escape(f"override '{arg}': has a range")):
        sweep_size(parse_overrides([arg]))


@pytest.mark.parametrize(
    "args, where, problem",
    [
        (["seed=1,range(1,2)"], "override 'seed=1,range(1,2)'", "cannot be an item of a list"),  # was Set[str]
        (["seed=0,1", "risk=glob(nomatch*)"], "override 'risk=glob(nomatch*)'", "matches no option of its group"),
        (["seed=range(3,3)"], "override 'seed=range(3,3)'", "holds no value, so the sweep has no job"),
    ],
)
def test_a_grid_that_cannot_expand_names_its_override_and_why(args, where, problem):
    with pytest.raises(BadInput) as err:
        expand(parse_overrides(args), args)
    assert err.value.where == where and problem in err.value.problem


def test_a_job_count_of_hundreds_of_digits_is_said_as_a_power_of_ten():
    with pytest.raises(BadInput, match=r"expands to about 10\^311 jobs, more than the "):
        check_size(parse_overrides(["seed=range(0,1000000000000)", "risk.beta=range(0,1,1e-300)"]))
