"""Only the cells episodes can reach get policy tables (riskplan.engine.rollout.reach): the set is exactly the cells
within horizon - 1 moves of a start, and every batch is the same, bit for bit, as with the tables of every cell."""

from __future__ import annotations

import numpy as np
import pytest
from support import setup_of

from riskplan.engine import rng, rollout
from riskplan.engine.policy import tables


def cells_within(world, starts, moves: int) -> set[tuple[int, int]]:
    """The (x, y) cells within `moves` moves (blocked moves stay) of any start, by brute force over every path."""
    here = {int(s) for s in starts}
    seen = set(here)
    for _ in range(moves):
        here = {int(world.next_cell[c, a]) for c in here for a in range(5)} - seen
        seen |= here
    return {tuple(int(v) for v in world.xy(c)) for c in seen}


@pytest.mark.slow  # over half a second (the quick tier stays under a minute)
def test_the_reach_is_the_cells_within_horizon_minus_one_moves():
    near = ["world.sources.0.position=[0,3]", "world.sources.1.position=[1,2]"]  # within the horizon's reach
    setup = setup_of("world.horizon=4", "world.obstacles=[[1,0],[1,1]]", *near)
    got = rollout.reach(setup.kernel, setup.world.starts)
    cells = {tuple(int(v) for v in setup.world.xy(c)) for c in got}
    # from (0, 0) with (1, 0) and (1, 1) walled: up the column x = 0, and round the wall's top
    assert cells == {(0, 0), (0, 1), (0, 2), (0, 3), (1, 2)}
    assert cells == cells_within(setup.world, setup.world.starts, 3)
    assert list(got) == sorted(got)
    one = setup_of("world.horizon=1", "world.sources.0.position=[1,0]", "world.sources.1.position=[0,1]")
    assert rollout.reach(one.kernel, one.world.starts).tolist() == [0]  # a move is picked at the start only
    mobile = setup_of("world.sources.0.motion.kind=random_walk", "world.sources.0.motion.prob=0.5")
    assert len(rollout.reach(mobile.kernel, mobile.world.starts)) == 0  # moves computed at each step


@pytest.mark.parametrize(
    "overrides",
    [
        ("world.size=[64,48]", "world.regions.1.rect=[0,0,63,47]"),
        ("experiment=paper_team", "team.starts=[[0,0],[11,0],[5,5]]"),
        ("policy.features=[signals,risky,stay]", "world.obstacles=[[2,2],[3,3]]"),
        ("world.stop_at_source=false", "world.horizon=30", "world.regions.1.reward={bernoulli: 0.5}"),
    ],
)
@pytest.mark.parametrize("record", [False, True])
def test_batches_are_the_same_as_with_every_cells_tables(overrides, record, monkeypatch):
    setup = setup_of(*overrides)
    thetas = np.tile(setup.theta0, (setup.robots, 1)) * np.linspace(0.5, 2.0, setup.robots)[:, None]
    starts = setup.world.starts if len(setup.world.starts) == setup.robots else np.repeat(setup.world.starts, 3)
    keys = rng.robot_keys(7, rng.TRAIN, 0, setup.robots)
    run = lambda: rollout.simulate(setup.world, setup.kernel, thetas, starts, keys, 500, record=record)
    restricted = run()
    monkeypatch.setattr(rollout, "reach", lambda kernel, starts: np.arange(setup.world.cells))
    full = run()
    for name in ("total_reward", "score", "risky_steps", "source_reached", "steps", "path_cells", "path_rewards"):
        a, b = getattr(restricted, name), getattr(full, name)
        assert (a is None) == (b is None), name
        if a is not None:
            np.testing.assert_array_equal(a, b, err_msg=name)


def test_the_reachable_rows_of_the_tables_are_those_of_the_full_tables():
    setup = setup_of("world.size=[40,30]", "world.regions.1.rect=[0,0,39,29]")
    thetas = np.array([[20.0, 20.0], [3.0, -7.0]] * 10)  # 20 policies: the parallel fill too
    cells = rollout.reach(setup.kernel, setup.world.starts)
    cum, score = tables(setup.world, thetas, setup.kernel.features)
    part_cum, part_score = tables(setup.world, thetas, setup.kernel.features, cells)
    np.testing.assert_array_equal(part_cum[:, cells], cum[:, cells])
    np.testing.assert_array_equal(part_score[:, cells], score[:, cells])
    np.testing.assert_array_equal(rollout.move_bins(part_cum, cells)[:, cells], rollout.move_bins(cum)[:, cells])
