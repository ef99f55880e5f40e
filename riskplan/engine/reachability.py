"""Where a robot can go: the fewest moves from a start to every cell, a shortest path, each source's distance.

Moves are the kernel's (`World.next_cell`: E, W, Stay, N, S; a move off the grid or into an obstacle stays put), so
a distance here is the first step at which an episode can stand on that cell, and a source is reachable within the
horizon exactly when its distance is at most `world.horizon`. One breadth-first search (`distances`) serves these
and the rollouts' reach (`riskplan.engine.rollout.reach`, the cells that need policy tables).
"""

from __future__ import annotations

import numpy as np

from riskplan.engine.world import World

UNREACHABLE = -1


def distances(
    next_cell: np.ndarray, starts: np.ndarray, limit: int | None = None, targets: np.ndarray | None = None
) -> np.ndarray:
    """Fewest moves from the nearest of `starts` to every cell, shape (C,) int64; -1 where no path of at most
    `limit` moves (None: any length) gets there. Breadth first over next_cell, a level at a time, in numpy; with
    `targets`, it stops once each of those cells has its distance (cells further away are left at -1)."""
    dist = np.full(next_cell.shape[0], UNREACHABLE, dtype=np.int64)
    frontier = np.unique(np.asarray(starts, dtype=np.int64))
    dist[frontier] = 0
    level = 0
    while frontier.size and (limit is None or level < limit):
        if targets is not None and np.all(dist[targets] != UNREACHABLE):
            break
        ahead = next_cell[frontier].ravel()
        ahead = np.unique(ahead[dist[ahead] == UNREACHABLE])
        level += 1
        dist[ahead] = level
        frontier = ahead
    return dist


def move_distances(world: World, start_cell: int) -> np.ndarray:
    """Fewest moves from `start_cell` to each cell of `world`, shape (cells,) int64, -1 where unreachable."""
    return distances(world.next_cell, np.array([start_cell]))


def shortest_path(world: World, start_cell: int, target_cell: int) -> np.ndarray:
    """One shortest path of cells from `start_cell` to `target_cell`, both included (empty if there is none).

    Walked back from the target: each step takes the first neighbour, in the order of the moves, one move nearer
    the start."""
    dist = distances(world.next_cell, np.array([start_cell]), targets=np.array([target_cell]))
    if dist[target_cell] == UNREACHABLE:
        return np.empty(0, dtype=np.int64)
    path = [int(target_cell)]
    cell = int(target_cell)
    while dist[cell] > 0:
        # A move between free cells can be undone, so the cells one move before `cell` are among those it leads to
        cell = next(int(prev) for prev in world.next_cell[cell] if dist[prev] == dist[cell] - 1)
        path.append(cell)
    return np.array(path[::-1], dtype=np.int64)


def source_distances(world: World, starts: np.ndarray) -> np.ndarray:
    """Fewest moves from each start cell to each source's initial cell, shape (starts, sources) int64, -1 for no
    path. A mobile source is measured at its initial cell (where its random walk begins)."""
    cells = world.source_cells
    rows = [distances(world.next_cell, np.array([start]), targets=cells)[cells] for start in np.asarray(starts)]
    return np.array(rows, dtype=np.int64).reshape(-1, world.sources)
