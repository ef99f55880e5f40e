"""The world (riskplan.engine.world): degenerate worlds and values out of range are one BadInput naming the key, with
a reason: sources on one cell, cells walled off or in by obstacles, non-finite half-planes, reward totals and
programs that could overflow, programs nested too deep, extreme covariances and scales."""

from __future__ import annotations

import numpy as np
import pytest
from support import bad_input, setup_of


def wall(x: int, gap: int | None = None) -> str:
    """Obstacles on the whole column x of the 12 x 12 grid, but for row `gap`."""
    return "world.obstacles=[" + ",".join(f"[{x},{y}]" for y in range(12) if y != gap) + "]"


def test_two_sources_on_one_cell():
    err = bad_input("world.sources.1.position=[9,3]")
    assert err.where == "world.sources.1.position"
    assert "(9, 3) is also the cell of world.sources.0" in err.problem


def test_a_source_behind_a_wall_of_obstacles_is_unreachable():
    # column 6 walls off x >= 7, where source 0 (9, 3) sits; the start (0, 0) is on the larger side
    err = bad_input(wall(6))
    assert err.where == "world.sources.0.position"
    assert (
        "'safe' at (9, 3) is walled off by obstacles: no path from the start (0, 0) at any world.horizon (now 20)"
        in (err.problem)
    )
    setup_of(wall(6, gap=3))  # one gap in the wall is enough (12 moves, within the horizon of 20)


def test_a_walled_in_start_is_named():
    err = bad_input("world.obstacles=[[1,0],[0,1]]")
    assert err.where == "world.start"
    assert "(0, 0) is walled in by obstacles (a pocket of 1 free cell)" in err.problem
    err = bad_input("team.robots=2", "team.starts=[[5,5],[11,11]]", "world.obstacles=[[10,11],[11,10]]")
    assert err.where == "team.starts.1"


def test_a_mobile_source_may_start_behind_a_wall():
    # a random walk ignores obstacles, so it can leave the pocket
    setup_of(wall(6), "world.sources.0.motion.kind=random_walk", "world.sources.0.motion.prob=0.5")


@pytest.mark.parametrize("value", ["[1,nan,0]", "[inf,1,0]", "[1,1,-inf]"])
def test_halfplane_coefficients_must_be_finite(value):
    err = bad_input(f"world.regions.0.halfplane={value}")
    assert err.where == "world.regions.0.halfplane"
    assert "finite numbers" in err.problem


def test_huge_halfplane_coefficients_give_the_same_cells_as_small_ones():
    small = setup_of("world.regions.0.halfplane=[-1,1,0]").world.region_of
    huge = setup_of("world.regions.0.halfplane=[-1e308,1e308,0]").world.region_of
    np.testing.assert_array_equal(small, huge)


def test_an_episode_total_that_could_overflow_is_rejected():
    # each draw is allowed (1e99 < 1e100), but 20 moves of it are not
    err = bad_input("world.regions.1.reward=1e99", "world.regions.0.reward=1e99")
    assert err.where == "world.regions.0.reward"
    assert "over world.horizon=20 moves an episode's total reward could reach about 2e+100" in err.problem
    setup_of("world.regions.1.reward=1e98", "world.regions.0.reward=1e98")


@pytest.mark.parametrize(
    "override, where",
    [
        ("world.sources.0.reward=1e200", "world.sources.0.reward"),
        ("world.sources.1.reward={uniform:[-1e308,1e308]}", "world.sources.1.reward"),
        ("world.sources.1.reward={normal:[0,1e300]}", "world.sources.1.reward"),
    ],
)
def test_a_reward_program_that_could_overflow_is_rejected(override, where):
    assert bad_input(override).where == where


def test_a_deeply_nested_reward_program_is_one_line():
    program = "1"
    for _ in range(40):
        program = "{scale:1,of:" + program + "}"
    err = bad_input(f"world.sources.0.reward={program}")
    assert "nests more than 32 levels deep" in err.problem


@pytest.mark.slow  # worlds with extreme covariances composed and built (near a second)
def test_extreme_covariances_and_scales():
    assert bad_input("world.sources.0.covariance=[[1e300,0],[0,1e300]]").where == "world.sources.0.covariance"
    assert bad_input("world.sources.0.covariance=[[1e-10,0],[0,1e-300]]").where == "world.sources.0.covariance"
    assert bad_input("world.sources.0.scale=1e200").where == "world.sources.0.scale"
    world = setup_of("world.sources.0.covariance=[[1e100,0],[0,1e100]]").world  # wide but fine: a flat signal
    assert np.all(np.isfinite(world.signals())) and world.source_amplitude[0] == 1.0
