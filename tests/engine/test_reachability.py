"""Fewest moves and shortest paths (riskplan.engine.reachability) on tiny worlds whose answers are known: an open
grid (Manhattan distance), a walled-off cell (-1, no path), a corridor (the way round a wall)."""

from __future__ import annotations

import itertools

import numpy as np

from riskplan.config.schema import MotionConf, MotionKind, SourceConf, WorldConf
from riskplan.engine.reachability import distances, move_distances, shortest_path, source_distances
from riskplan.engine.world import World, build_world


def world_of(width: int, height: int, obstacles=(), sources=((0, 0),), start=(0, 0), mobile=False) -> World:
    """A width x height world with these obstacle cells and sources (random walks if `mobile`: they may start behind walls)."""
    walk = MotionConf(kind=MotionKind.random_walk, prob=0.5)
    conf = WorldConf(
        size=[width, height],
        start=list(start),
        horizon=100,
        obstacles=[list(o) for o in obstacles],
        sources=[SourceConf(position=list(s), motion=walk if mobile else MotionConf()) for s in sources],
    )
    return build_world(conf)


def cell(world: World, x: int, y: int) -> int:
    return x * world.height + y


def test_on_an_open_grid_the_distance_is_manhattan():
    world = world_of(5, 4)
    start = cell(world, 1, 2)
    x, y = world.xy(np.arange(world.cells))
    got = move_distances(world, start)
    assert got.dtype == np.int64 and got.shape == (20,)
    assert got.tolist() == (np.abs(x - 1) + np.abs(y - 2)).tolist()


def test_a_walled_off_cell_is_minus_one_and_has_no_path():
    # (4, 0) in the corner of a 5 x 3 grid, shut in by (3, 0) and (4, 1)
    world = world_of(5, 3, obstacles=[(3, 0), (4, 1)], sources=[(0, 2)], mobile=True)
    got = move_distances(world, cell(world, 0, 0))
    assert got[cell(world, 4, 0)] == -1
    assert got[cell(world, 3, 0)] == -1 and got[cell(world, 4, 1)] == -1  # obstacles are never stood on
    assert got[cell(world, 4, 2)] == 6
    assert shortest_path(world, cell(world, 0, 0), cell(world, 4, 0)).size == 0


def test_a_corridor_leads_round_the_wall():
    # a 4 x 3 grid with a wall on x = 1 but for its top cell: from (0, 0) to (2, 0) up, across and down
    world = world_of(4, 3, obstacles=[(1, 0), (1, 1)], sources=[(2, 0)])
    start, target = cell(world, 0, 0), cell(world, 2, 0)
    path = shortest_path(world, start, target)
    assert [tuple(int(v) for v in world.xy(c)) for c in path] == [
        (0, 0),
        (0, 1),
        (0, 2),
        (1, 2),
        (2, 2),
        (2, 1),
        (2, 0),
    ]
    assert move_distances(world, start)[target] == 6 == len(path) - 1
    assert shortest_path(world, start, start).tolist() == [start]


def test_source_distances_are_per_start_and_source():
    world = world_of(6, 6, obstacles=[(3, y) for y in range(6)], sources=[(1, 1), (5, 5)], mobile=True)
    starts = np.array([cell(world, 0, 0), cell(world, 2, 5)])
    got = source_distances(world, starts)
    assert got.dtype == np.int64
    # the second source lies beyond a full wall (a random walk may start there): no path from either start
    assert got.tolist() == [[2, -1], [5, -1]]


def test_a_limit_stops_the_search():
    world = world_of(5, 1)
    assert distances(world.next_cell, np.array([0]), limit=2).tolist() == [0, 1, 2, -1, -1]
    assert distances(world.next_cell, np.array([0, 4]), limit=1).tolist() == [0, 1, -1, 1, 0]


def test_targets_stop_the_search_once_each_has_its_distance():
    world = world_of(6, 1)
    assert distances(world.next_cell, np.array([0]), targets=np.array([2])).tolist() == [0, 1, 2, -1, -1, -1]
    assert distances(world.next_cell, np.array([0]), targets=np.array([0])).tolist() == [0, -1, -1, -1, -1, -1]


def test_a_shortest_path_is_made_of_moves_and_as_long_as_the_distance():
    # a 9 x 7 grid with obstacles at random (the start and its neighbours kept free): every step of the path is
    # one of the kernel's moves, and it takes exactly the fewest moves
    rng = np.random.default_rng(3)
    blocked = [
        (x, y) for x in range(9) for y in range(7) if rng.random() < 0.3 and (x, y) not in ((0, 0), (1, 0), (0, 1))
    ]
    world = world_of(9, 7, obstacles=blocked, sources=[(0, 0)])
    dist = move_distances(world, 0)
    for target in np.flatnonzero(dist > 0):
        path = shortest_path(world, 0, int(target))
        assert path[0] == 0 and path[-1] == target and len(path) - 1 == dist[target]
        assert all(b in world.next_cell[a] and a != b for a, b in itertools.pairwise(path))
    assert (dist > 0).sum() >= 20 and (dist[world.obstacle] == -1).all()
