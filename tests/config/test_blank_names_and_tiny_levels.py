"""A source's or region's name of whitespace alone was taken (a source labelled '   ' in every table and figure),
and a CVaR level so small that 1 / beta overflows (risk.beta=1e-320) leaked numpy's "overflow encountered in
divide" and labelled the run CVaR_9.99989e-321. Both are bad input, in one line."""

from __future__ import annotations

import warnings

import pytest
from support import bad_input, setup_of

from riskplan.config.validate import MIN_BETA

pytestmark = pytest.mark.slow  # many configs composed and checked: seconds in all (the quick tier stays under a minute)

BLANK = "only whitespace, which names nothing a reader can see; give a name, or leave it empty for the default name"


@pytest.mark.parametrize("key", ["world.sources.0.name", "world.regions.1.name"])
@pytest.mark.parametrize("name", ["   ", "\u3000", "\u00a0 "])  # spaces, an ideographic and a no-break space
def test_a_name_of_whitespace_alone_is_refused(key, name):
    err = bad_input(f"{key}='{name}'")
    assert (err.where, err.problem) == (key, f"got {name!r}, {BLANK}")


def test_an_empty_name_takes_the_default_and_a_spaced_name_is_its_own():
    world = setup_of("world.sources.0.name=''", "world.regions.1.name='a b'").world
    assert world.source_names[0] == "source_0" and world.region_names[1] == "a b"


@pytest.mark.parametrize("beta", ["1e-320", "5e-324", "1e-300", "9.9e-10"])
@pytest.mark.parametrize("key", ["risk.beta", "team.risk.0.beta"])
def test_a_level_below_the_smallest_is_one_line_without_numpy_warnings(key, beta):
    team = ["experiment=paper_team", "team.robots=1", "team.risk=[{measure: cvar, beta: 0.1}]"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's RuntimeWarning leaked before
        err = bad_input(*(team if key.startswith("team") else []), f"{key}={beta}")
    assert err.where == key
    assert err.problem == (
        f"got {float(beta):g}; expected 1e-09 <= beta <= 1: CVaR's tail holds ceil(beta x W) of an iteration's W "
        f"episodes, which below 1e-09 is one (a zero gradient) unless W is over 10^9"
    )


def test_the_smallest_level_builds():
    with pytest.warns(UserWarning, match=r"ceil\(1e-09 x 200\) = 1 episode"):  # and warns: its tail holds one
        assert setup_of(f"risk.beta={MIN_BETA}").params.risk.beta == MIN_BETA
