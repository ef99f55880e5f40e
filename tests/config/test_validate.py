"""Ranges checked once per build (riskplan.config.validate): seeds, the team's order and its start cells. Most other
ranges are checked by tests/commands/test_bad_input.py (the table of docs/robustness.md) and beside the module
that needs them (tests/engine/test_world.py, tests/engine/team/test_network.py, tests/run/test_budget.py)."""

from __future__ import annotations

import warnings

import pytest
from support import bad_input, setup_of

from riskplan import compose
from riskplan.util.errors import BadInput


@pytest.mark.parametrize("seed", [-1, 2**63, 2**64, 2**64 + 5, 10**30])
def test_seeds_outside_0_to_2_63_are_bad_input(seed):
    # 2^64 + 5 and 5 gave identical streams (masked to 64 bits); -1 was silently masked
    err = bad_input(f"seed={seed}")
    assert err.where == "seed" and "0 <= seed < 2^63" in err.problem


def test_the_largest_seed_is_accepted():
    assert setup_of(f"seed={2**63 - 1}").config["seed"] == 2**63 - 1


def test_too_few_bootstrap_resamples_for_a_95_percent_interval_warn():
    with pytest.warns(UserWarning, match=r"^train.bootstrap=39 is too few resamples for a 95% interval .* use >= 40"):
        compose(["train.bootstrap=39"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        compose(["train.bootstrap=40"])


def test_unknown_order_is_bad_input():
    with pytest.raises(BadInput) as err:
        compose(["team.order=sideways"])
    assert err.value.where == "team.order"


def test_starts_must_match_the_team_size():
    with pytest.raises(BadInput) as err:
        compose(["experiment=paper_team", "team.starts=[[0,0]]"])
    assert err.value.where == "team.starts"


@pytest.mark.parametrize(
    ("overrides", "where", "words"),
    [
        (["world.sources.0.name=none"], "world.sources.0.name", "got 'none', the name the results give the episodes"),
        (["world.sources.1.name=safe"], "world.sources.1.name", "'safe' is also the name of world.sources.0; the"),
        # an unnamed source is source_<j>: a user's name may not take it
        (["world.sources.0.name=source_1", "world.sources.1.name=''"], "world.sources.1.name", "'source_1' is also"),
        (["world.sources.0.name='a\rb'"], "world.sources.0.name", "holds the character '\\r'; give a name of"),
        (["world.regions.1.name='x\x1b[31m'"], "world.regions.1.name", "holds the character '\\x1b'"),
        (["world.regions.0.name='a\u202eb'"], "world.regions.0.name", "holds the character '\\u202e'"),  # RTL override
        (
            [f"world.sources.0.name={'A' * 65}"],
            "world.sources.0.name",
            "is 65 characters long; give a name of at most 64",
        ),
    ],
)
def test_source_and_region_names_are_each_sources_own_and_printable(overrides, where, words):
    """summary.json counts the episodes reaching each source by its name and those reaching none as 'none': a name
    shared, or 'none', merged two counts into one. Names also reach logs, CSV headers, SVGs and metric names."""
    err = bad_input(*overrides)
    assert err.where == where and words in err.problem


def test_names_of_64_printable_characters_any_script_are_accepted():
    setup = setup_of(
        f"world.sources.0.name={'A' * 64}", "world.sources.1.name='Quelle ☢ 源'", "world.regions.0.name=safe"
    )
    assert setup.world.source_names == ("A" * 64, "Quelle ☢ 源")
