"""A key only another variant uses (riskplan.config.validate.VARIANT_KEYS), set away from its default, is one warning
naming the key and the variant chosen; the median, which takes no team.trim, is not said to break a condition
that team.trim sets."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
from support import TINY

from riskplan.config.schema import Aggregate
from riskplan.engine.team.robustness import condition
from riskplan.run.compose import compose

TEAM = "experiment=paper_team"


@pytest.mark.parametrize(
    ("overrides", "line"),
    [
        (
            [TEAM, "team.graph=ring", "team.edges=[[0,1]]"],
            "team.edges=[[0, 1]] is ignored with team.graph=ring: only team.graph=edges uses it; drop it",
        ),
        (
            [TEAM, "team.matrix=[[1,0],[0,1]]"],
            "team.matrix=[[1, 0], [0, 1]] is ignored with team.weights=metropolis: only team.weights=matrix uses it; "
            "drop it",
        ),
        (
            [TEAM, "team.trim=1"],
            "team.trim=1 is ignored with team.aggregate=mean: only team.aggregate=trimmed_mean or wmsr uses it; drop it",
        ),
        (
            [TEAM, "team.aggregate=median", "team.trim=5"],
            "team.trim=5 is ignored with team.aggregate=median: only team.aggregate=trimmed_mean or wmsr uses it; "
            "drop it",
        ),
        (
            [TEAM, "team.speeds=[2,1,1]"],
            "team.speeds=[2.0, 1.0, 1.0] is ignored with team.backend=simulated: only team.backend=ray uses it; drop it",
        ),
        (
            [TEAM, "team.address=auto"],
            "team.address=auto is ignored with team.backend=simulated: only team.backend=ray uses it; drop it",
        ),
        (
            ["world.sources.1.motion.prob=0.5"],
            "world.sources.1.motion.prob=0.5 is ignored with world.sources.1.motion.kind=static: only "
            "world.sources.1.motion.kind=random_walk uses it; drop it",
        ),
    ],
)
def test_a_key_the_chosen_variant_ignores_is_one_warning(overrides, line):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        compose([*TINY, *overrides])
    assert [str(w.message) for w in caught] == [line]


@pytest.mark.parametrize(
    "overrides",
    [
        [TEAM, "team.graph=edges", "team.edges=[[0,1],[1,2]]"],
        [TEAM, "team.robots=2", "team.weights=matrix", "team.matrix=[[0.5,0.5],[0.5,0.5]]"],
        [TEAM, "team.robots=5", "team.graph=complete", "team.aggregate=wmsr", "team.trim=1"],
        ["world.sources.1.motion.kind=random_walk", "world.sources.1.motion.prob=0.5"],
        [TEAM, "team.trim=0", "team.speeds=null", "world.sources.0.motion.prob=0"],  # the defaults, given
    ],
)
def test_a_key_its_variant_uses_or_left_at_its_default_is_no_warning(overrides):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        compose([*TINY, *overrides])


def test_the_median_takes_its_f_from_the_faults_not_from_team_trim():
    """trim=5 on a line of 3 robots said 'not 11-robust', though the median drops nothing whatever trim is."""
    line = np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]], dtype=bool)
    met = condition(line, Aggregate.median, 5, ())
    assert met.warning is None and met.met is True
    assert met.lines[0] == (
        "resilience: team.aggregate=median, F=0 (the most faulty in-neighbours of a healthy robot; median takes no "
        "team.trim); faults: none"
    )
    trimmed = condition(line, Aggregate.trimmed_mean, 5, ())
    assert re.match(r"team\.aggregate=trimmed_mean with team\.trim=5: the graph is not 11-robust", trimmed.warning)
