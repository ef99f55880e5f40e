"""Shared fixtures: a fast config for end-to-end runs, and typed team settings for the engine's team tests."""

from __future__ import annotations

import pytest

from riskplan.config.schema import TeamConf
from riskplan.config.typed import typed
from riskplan.config.validate import check_team

FAST = ["train.iterations=5", "train.samples=500", "train.eval_episodes=2000", "train.bootstrap=50", "train.paths=3"]


@pytest.fixture
def fast_overrides() -> list[str]:
    """Overrides that make a run take well under a second."""
    return list(FAST)


def team_conf(**values) -> TeamConf:
    """The typed TeamConf of these `team` values (nested dicts allowed), checked as a build checks it: BadInput
    naming `team.<key>` on a bad type, choice or range."""
    team = typed({"team": values}).team
    check_team(team)
    return team
