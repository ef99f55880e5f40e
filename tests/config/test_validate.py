"""Ranges checked once per build (riskplan.config.validate): seeds, the team's order and its start cells. Most other
ranges are checked by tests/commands/test_bad_input.py (the table of docs/robustness.md) and beside the module
that needs them (tests/engine/test_world.py, tests/engine/team/test_network.py, tests/run/test_budget.py)."""

from __future__ import annotations

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


def test_unknown_order_is_bad_input():
    with pytest.raises(BadInput) as err:
        compose(["team.order=sideways"])
    assert err.value.where == "team.order"


def test_starts_must_match_the_team_size():
    with pytest.raises(BadInput) as err:
        compose(["experiment=paper_team", "team.starts=[[0,0]]"])
    assert err.value.where == "team.starts"
