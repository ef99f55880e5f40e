"""The grid world of paper Sections II and V: cells, moves, regions, obstacles, sources and their signals.

Cells are numbered c = x * height + y, so an array of shape (width, height) ravels into cell order.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from riskplan.config.schema import MapUnknown, MotionKind, WorldConf, source_names
from riskplan.engine import distributions
from riskplan.engine.distributions import Dist
from riskplan.util.errors import BadInput

MOVES = np.array([[1, 0], [-1, 0], [0, 0], [0, 1], [0, -1]], dtype=np.int64)  # E, W, Stay, N, S
MOVE_NAMES = ("E", "W", "Stay", "N", "S")
MAX_STACK = 64  # stack slots of the kernel's reward-program interpreter
SIGNAL_LIMIT = 1e100  # largest peak |signal| w / (2 pi sqrt(det Sigma)): keeps logits and scores finite
PEAK_BEYOND = f"beyond the limit of {SIGNAL_LIMIT:g} that keeps logits and scores finite"
PRECISION_LIMIT = 1e150  # largest |entry| of Sigma^-1: the quadratic form stays finite on any allowed grid
EDGE = 1e-9  # pixels a point may fall short of a pixel's edge by rounding and still be on it (Frame.pixel_of)
FAR = 2.0**31  # pixels: a point farther off the map is taken as this far, so its pixel stays a finite int64


@dataclass(frozen=True)
class Frame:
    """Where a map world's cells lie in the map frame: a cell is `cell` x `cell` of the map's `pixels`, each
    `resolution` metres wide, counted from the lower-left pixel's corner `origin` (x, y) and turned by its yaw."""

    resolution: float  # metres per pixel
    cell: int  # world.map_cell: pixels per cell side
    origin: tuple[float, float, float]  # (x, y, yaw)
    pixels: tuple[int, int]  # (width, height) of the map's image

    def pixel_of(self, x: float, y: float) -> tuple[int, int]:
        """The pixel (column from the left, row from the bottom) under the map-frame point (x, y); off the image for
        a point off the map (at most FAR pixels off, so that 1e308 m is an integer too). A point on a pixel's edge is
        the pixel beyond it (pixels are [a, b)), also where the decimal point's float falls a rounding error short of
        the edge (-2.0 + 0.2 is 0.19999999999999996)."""
        ox, oy, yaw = self.origin
        cos, sin = math.cos(yaw), math.sin(yaw)
        u = cos * (x - ox) + sin * (y - oy)
        v = cos * (y - oy) - sin * (x - ox)
        return tuple(math.floor(min(max(w / self.resolution + EDGE, -FAR), FAR)) for w in (u, v))

    def on_map(self, pixel: tuple[int, int]) -> bool:
        return 0 <= pixel[0] < self.pixels[0] and 0 <= pixel[1] < self.pixels[1]

    def centre(self, x: int, y: int) -> tuple[float, float]:
        """The map-frame point at the centre of cell (x, y)."""
        size = self.resolution * self.cell
        u, v = (x + 0.5) * size, (y + 0.5) * size
        ox, oy, yaw = self.origin
        cos, sin = math.cos(yaw), math.sin(yaw)
        return ox + cos * u - sin * v, oy + sin * u + cos * v


@dataclass(frozen=True)
class Placement:
    """A position the config gave in metres ({metres: [x, y]}; a rect's two corners) and the cells it became."""

    key: str  # world.start, team.starts.1, world.sources.0.position, world.regions.2.rect
    metres: tuple[float, ...]  # (x, y), or a rect's (x0, y0, x1, y1)
    cells: tuple[int, ...]  # (x, y), or the rect's [x0, y0, x1, y1] in cells


@dataclass(frozen=True)
class World:
    """Immutable world parameters, as plain arrays (cell-indexed)."""

    width: int
    height: int
    horizon: int
    stop_at_source: bool
    next_cell: np.ndarray  # (C, 5) int64: the cell a move leads to; blocked moves stay
    obstacle: np.ndarray  # (C,) bool
    region_of: np.ndarray  # (C,) int64: first matching region, -1 for none (reward 0)
    region_names: tuple[str, ...]
    region_risky: np.ndarray  # (R,) bool
    region_rewards: tuple[Dist, ...]
    source_names: tuple[str, ...]
    source_cells: np.ndarray  # (M,) int64: initial source cells
    source_rewards: tuple[Dist, ...]
    source_motion: np.ndarray  # (M,) float64: probability of a random-walk step per time step (0 = static)
    source_amplitude: np.ndarray  # (M,) float64: w / (2 pi sqrt(det Sigma))
    source_precision: np.ndarray  # (M, 3) float64: (P_xx, P_xy, P_yy) of Sigma^-1
    starts: np.ndarray  # (N,) int64: start cell of each robot
    placements: tuple[Placement, ...] = ()  # the positions given in metres, and the cells they became

    @property
    def cells(self) -> int:
        """Number of grid cells."""
        return self.width * self.height

    @property
    def sources(self) -> int:
        """Number of sources M (= length of theta)."""
        return len(self.source_cells)

    @property
    def mobile(self) -> bool:
        """Whether any source moves."""
        return bool(np.any(self.source_motion > 0))

    def xy(self, cell: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """Cell index to (x, y)."""
        return np.divmod(cell, self.height)

    def signals(self, source_cells: np.ndarray | None = None) -> np.ndarray:
        """Signal strength s^j(c) of eq. (1) at every cell, shape (C, M), for sources at `source_cells`."""
        src = self.source_cells if source_cells is None else source_cells
        x, y = self.xy(np.arange(self.cells))
        sx, sy = self.xy(src)
        dx = x[:, None] - sx[None, :]
        dy = y[:, None] - sy[None, :]
        p = self.source_precision
        quad = p[:, 0] * dx * dx + 2.0 * p[:, 1] * dx * dy + p[:, 2] * dy * dy
        return self.source_amplitude * np.exp(-0.5 * quad)


@dataclass(frozen=True)
class Layout:
    """A world's cells read from a map (riskplan.run.maps reads the files): plain arrays indexed [x, y], x to the
    right and y up from the map's lower-left corner."""

    occupied: np.ndarray  # (W, H) bool: the map's occupied cells
    unknown: np.ndarray  # (W, H) bool: cells neither occupied nor free (world.map_unknown says what they become)
    masks: tuple[np.ndarray | None, ...]  # per world.regions entry: (W, H) bool of a `mask` region, None otherwise
    name: str = "world.map"  # how messages name the map
    frame: Frame | None = None  # where the cells lie in the map frame: positions in metres need it

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in cells."""
        return int(self.occupied.shape[0]), int(self.occupied.shape[1])


def build_world(world: WorldConf, starts: list | None = None, layout: Layout | None = None) -> World:
    """Build a World from a validated `world` config (and optional per-robot starts), checking what needs the grid:
    cells on it, obstacles, reachability, covariances, reward programs and their bounds. With a `layout`
    (world.map), the grid's size is the map's, its occupied cells are obstacles beside world.obstacles, its unknown
    cells follow world.map_unknown, and `mask` regions take their cells from it."""
    width, height = grid_size(world.size) if layout is None else layout.size
    obstacle, occupied = _obstacles(world, layout, width, height)
    places = _Places(width, height, obstacle, None if layout is None else layout.frame, occupied)
    start_key = "world.start" if starts is None else None  # None: team.starts.<i>
    start_cells = _start_cells([world.start] if starts is None else starts, start_key, places)
    names, src_cells, rewards, motion, amplitude, precision = _sources(world, places)
    region_of, region_names, region_risky, region_rewards = _regions(world, layout, places)
    next_cell = _next_cell(width, height, obstacle)
    if obstacle.any():
        _check_reachable(next_cell, obstacle, start_cells, start_key, src_cells, names, motion, height, world.horizon)
    _check_total_reward(rewards, region_rewards, world.horizon, bool(world.stop_at_source))
    return World(
        width=width,
        height=height,
        horizon=world.horizon,
        stop_at_source=bool(world.stop_at_source),
        next_cell=next_cell,
        obstacle=obstacle,
        region_of=region_of,
        region_names=tuple(region_names),
        region_risky=np.array(region_risky, dtype=bool),
        region_rewards=tuple(region_rewards),
        source_names=tuple(names),
        source_cells=np.array(src_cells, dtype=np.int64),
        source_rewards=tuple(rewards),
        source_motion=np.array(motion, dtype=np.float64),
        source_amplitude=np.array(amplitude, dtype=np.float64),
        source_precision=np.array(precision, dtype=np.float64).reshape(-1, 3),
        starts=np.array(start_cells, dtype=np.int64),
        placements=tuple(places.placed),
    )


def _obstacles(world: WorldConf, layout: Layout | None, width: int, height: int) -> tuple[np.ndarray, str]:
    """The obstacles (C,): world.obstacles, a map's occupied (and unknown) cells; and how messages name one."""
    obstacle = np.zeros((width, height), dtype=bool)
    for i, cell in enumerate(world.obstacles):
        x, y = _cell(cell, width, height, f"world.obstacles.{i}")
        obstacle[x, y] = True
    occupied = "is an obstacle"
    if layout is not None:
        kind = "occupied or unknown" if world.map_unknown == MapUnknown.obstacle else "occupied"
        occupied = f"is an obstacle (an {kind} cell of {layout.name})"
        obstacle |= layout.occupied
        if world.map_unknown == MapUnknown.obstacle:
            obstacle |= layout.unknown
    return obstacle.ravel(), occupied


def _start_cells(start_list: list, start_key: str | None, places: _Places) -> list[int]:
    """The free cell of each start: world.start's (`start_key`), or each of team.starts' (start_key None)."""
    cells = []
    for i, start in enumerate(start_list):
        here = start_key or f"team.starts.{i}"
        x, y = places.cell(start, here)
        if places.obstacle[x * places.height + y]:
            raise BadInput(here, f"({x}, {y}) {places.occupied}; choose a free cell")
        cells.append(x * places.height + y)
    return cells


def _sources(world: WorldConf, places: _Places) -> tuple[list, list, list, list, list, list]:
    """Each source's name, free cell (its own), reward, walk probability and `_signal_shape`, as six lists."""
    if len(world.sources) == 0:
        raise BadInput("world.sources", "no sources; the policy needs at least one signal (M >= 1)")
    names, cells, rewards, motion, amplitude, precision = source_names(world.sources), [], [], [], [], []
    for j, source in enumerate(world.sources):
        here = f"world.sources.{j}"
        x, y = places.cell(source.position, f"{here}.position")
        cell = x * places.height + y
        if places.obstacle[cell]:
            raise BadInput(f"{here}.position", f"({x}, {y}) {places.occupied}; move the source or the obstacle")
        if cell in cells:
            raise BadInput(
                f"{here}.position",
                f"({x}, {y}) is also the cell of world.sources.{cells.index(cell)}; two sources "
                f"on one cell cannot be told apart; give each source its own cell",
            )
        peak, inverse = _signal_shape(source, here)
        cells.append(cell)
        rewards.append(_dist(source.reward, f"{here}.reward"))
        motion.append(source.motion.prob if source.motion.kind == MotionKind.random_walk else 0.0)
        amplitude.append(peak)
        precision.append(inverse)
    return names, cells, rewards, motion, amplitude, precision


def _signal_shape(source: Any, here: str) -> tuple[float, tuple[float, float, float]]:
    """A source signal's peak w / (2 pi sqrt(det Sigma)) and precision (P_xx, P_xy, P_yy) of Sigma^-1, in bounds."""
    cov = _covariance(source.covariance, f"{here}.covariance")
    with np.errstate(all="ignore"):
        det = float(np.linalg.det(cov))
        inv = np.linalg.inv(cov)
    if not (math.isfinite(det) and np.all(np.isfinite(inv)) and np.max(np.abs(inv)) <= PRECISION_LIMIT):
        raise BadInput(
            f"{here}.covariance",
            f"{cov.tolist()} is too extreme: its determinant or inverse overflows (inverse entries must stay below "
            f"{PRECISION_LIMIT:g}); give entries between about 1e-100 and 1e100",
        )
    if source.scale is None:
        peak = 1.0  # w = 2 pi sqrt(det Sigma): exactly 1, even where sqrt(det) would round
    else:
        scale = float(source.scale)
        if not math.isfinite(scale):
            raise BadInput(f"{here}.scale", f"got {source.scale!r}; expected a finite number or null (peak 1)")
        peak = scale / (2.0 * math.pi * math.sqrt(det))
        faint = abs(peak) < 1 / SIGNAL_LIMIT  # too faint to sense; |peak|: a negative w is read with its sign
        if faint or not abs(peak) <= SIGNAL_LIMIT:
            limit = f"below {1 / SIGNAL_LIMIT:g}, where the policy cannot sense the source" if faint else PEAK_BEYOND
            larger = "a larger |scale|" if faint else "a smaller scale"
            raise BadInput(
                f"{here}.scale",
                f"got {scale:g}; the signal would peak at about {abs(peak):.3g}, {limit}; give {larger}, or null for "
                f"a peak of 1",
            )
    return peak, (inv[0, 0], inv[0, 1], inv[1, 1])


def _regions(world: WorldConf, layout: Layout | None, places: _Places) -> tuple[np.ndarray, list, list, list]:
    """The region of each cell (C,), the first matching one, -1 for none; and each region's name, risky flag and
    reward program (the map's unknown cells a first region with world.map_unknown=risky)."""
    region_of = np.full(places.width * places.height, -1, dtype=np.int64)
    names, risky, rewards = [], [], []
    for r, region in enumerate(world.regions):
        here = f"world.regions.{r}"
        mask = None if layout is None or r >= len(layout.masks) else layout.masks[r]
        member = _region_cells(region, places, here, mask)
        region_of[(region_of < 0) & member] = r
        names.append(region.name or f"region_{r}")
        risky.append(bool(region.risky))
        rewards.append(_dist(region.reward, f"{here}.reward"))
    if layout is not None and world.map_unknown == MapUnknown.risky and layout.unknown.any():
        _unknown_region(world, layout, region_of, names, risky, rewards)
    return region_of, names, risky, rewards


def _check_reachable(
    next_cell: np.ndarray,
    obstacle: np.ndarray,
    starts: list[int],
    start_key: str | None,
    sources: list[int],
    names: list[str],
    motion: list[float],
    height: int,
    horizon: int,
) -> None:
    """Every static source can be reached from every start cell through free cells (the 4 moves).

    A pair that cannot is blamed on the side in the smaller walled-off pocket: the start when it is shut in, the
    source when it is. Mobile sources walk over obstacles, so only static ones are checked.
    """
    label = _components(next_cell, obstacle)
    size = np.bincount(label[label >= 0])
    for i, start in enumerate(starts):
        here = start_key or f"team.starts.{i}"
        for j, (cell, prob) in enumerate(zip(sources, motion)):
            if prob > 0 or label[cell] == label[start]:
                continue
            sx, sy = divmod(start, height)
            cx, cy = divmod(cell, height)
            if size[label[start]] < size[label[cell]]:
                free = int(size[label[start]])
                raise BadInput(
                    here,
                    f"({sx}, {sy}) is walled in by obstacles (a pocket of {free} free "
                    f"cell{'' if free == 1 else 's'}): world.sources.{j} '{names[j]}' at ({cx}, {cy}) cannot be "
                    f"reached from it; remove obstacles or move the start",
                )
            raise BadInput(
                f"world.sources.{j}.position",
                f"'{names[j]}' at ({cx}, {cy}) is walled off by obstacles: no path from the start ({sx}, {sy}) "
                f"at any world.horizon (now {horizon}); remove obstacles or move the source",
            )


@njit(cache=True)
def _components(next_cell, obstacle):
    """Label of the connected free region of every cell (-1 for obstacles): one breadth-first pass over the grid."""
    cells = next_cell.shape[0]
    label = np.full(cells, -1, dtype=np.int64)
    queue = np.empty(cells, dtype=np.int64)
    count = 0
    for seed in range(cells):
        if obstacle[seed] or label[seed] >= 0:
            continue
        label[seed] = count
        head, tail = 0, 1
        queue[0] = seed
        while head < tail:
            cell = queue[head]
            head += 1
            for a in range(5):
                nxt = next_cell[cell, a]
                if label[nxt] < 0:
                    label[nxt] = count
                    queue[tail] = nxt
                    tail += 1
        count += 1
    return label


def _check_total_reward(sources: list[Dist], regions: list[Dist], horizon: int, stop_at_source: bool) -> None:
    """No episode's total reward can exceed REWARD_LIMIT in size (each program was bounded when parsed)."""
    limit = distributions.REWARD_LIMIT
    first = lambda pair: pair[0]
    bounds = [(distributions.bound(d), f"world.regions.{r}.reward") for r, d in enumerate(regions)]
    region = max(bounds, default=(0.0, ""), key=first)
    source = max(((distributions.bound(d), f"world.sources.{j}.reward") for j, d in enumerate(sources)), key=first)
    source_steps = 1.0 if stop_at_source else float(horizon)
    total = float(horizon) * region[0] + source_steps * source[0]
    if total <= limit:
        return
    bound, key = region if float(horizon) * region[0] >= source_steps * source[0] else source
    paid = "step" if key.startswith("world.regions") or not stop_at_source else "episode"
    raise BadInput(
        key,
        f"draws up to about {bound:.3g} per {paid}; over world.horizon={horizon} moves an episode's "
        f"total reward could reach about {min(total, 1.8e308):.3g}, beyond the limit of {limit:g} "
        f"that keeps means, variances and gradients finite; give smaller rewards or a shorter horizon",
    )


def world_map(world: World, starts: np.ndarray) -> dict:
    """The world as the record layer's map dict (arrays indexed [x, y]), with each robot's start cell."""
    shape = (world.width, world.height)
    risky = np.zeros(world.cells, dtype=bool)
    inside = world.region_of >= 0
    risky[inside] = world.region_risky[world.region_of[inside]]
    sx, sy = world.xy(world.source_cells)
    rx, ry = world.xy(starts)
    return {
        "width": world.width,
        "height": world.height,
        "cell_region": world.region_of.reshape(shape),
        "region_names": list(world.region_names),
        "risky": risky.reshape(shape),
        "obstacles": world.obstacle.reshape(shape),
        "sources": [{"name": n, "x": int(x), "y": int(y)} for n, x, y in zip(world.source_names, sx, sy)],
        "start": [[int(x), int(y)] for x, y in zip(rx, ry)],
    }


def _next_cell(width: int, height: int, obstacle: np.ndarray) -> np.ndarray:
    """Successor of every (cell, move); moves off the grid or into an obstacle stay put."""
    x, y = np.divmod(np.arange(width * height), height)
    nx = x[:, None] + MOVES[None, :, 0]
    ny = y[:, None] + MOVES[None, :, 1]
    inside = (nx >= 0) & (nx < width) & (ny >= 0) & (ny < height)
    target = np.where(inside, nx * height + ny, 0)
    blocked = ~inside | obstacle[target]
    stay = np.broadcast_to(np.arange(width * height)[:, None], target.shape)
    return np.where(blocked, stay, target).astype(np.int64)


def _unknown_region(
    world: WorldConf, layout: Layout, region_of: np.ndarray, names: list, risky: list, rewards: list
) -> None:
    """world.map_unknown=risky: the map's unknown cells become a first, risky region `unknown`, paid as the first
    region with risky: true (region indices shift by one)."""
    first = next((r for r, region in enumerate(world.regions) if region.risky), None)
    if first is None:
        raise BadInput(
            "world.map_unknown",
            f"got risky, and world.regions has no region with risky: true whose reward the unknown cells of "
            f"{layout.name} would take; add one, or use world.map_unknown=obstacle or free",
        )
    unknown = layout.unknown.ravel()
    region_of[region_of >= 0] += 1
    region_of[unknown] = 0
    names.insert(0, "unknown")
    risky.insert(0, True)
    rewards.insert(0, rewards[first])


def _region_cells(region: Any, places: _Places, where: str, mask: np.ndarray | None = None) -> np.ndarray:
    """Membership mask (C,) of a region given as exactly one of rect, halfplane, cells, mask (`mask`: its cells,
    read from the image by riskplan.run.maps; a rect's corners may be in metres on a map world)."""
    width, height = places.width, places.height
    given = [k for k in ("rect", "halfplane", "cells", "mask") if getattr(region, k, None) is not None]
    if len(given) != 1:
        raise BadInput(where, f"gives {given or 'no shape'}; give exactly one of rect, halfplane, cells, mask")
    if given[0] == "mask":
        if mask is None:
            raise BadInput(f"{where}.mask", "a mask region needs world.map (the mask is drawn over the map's image)")
        return np.asarray(mask, dtype=bool).ravel()
    x, y = np.divmod(np.arange(width * height), height)
    if given[0] == "rect":
        x0, y0, x1, y1 = rect = places.rect(region.rect, f"{where}.rect")
        if x0 > x1 or y0 > y1:
            raise BadInput(f"{where}.rect", f"got {rect}; need x0 <= x1 and y0 <= y1")
        return (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    if given[0] == "halfplane":
        hp = list(region.halfplane)
        if len(hp) != 3 or not all(math.isfinite(v) for v in hp):
            raise BadInput(f"{where}.halfplane", f"got {hp}; expected [a, b, c] of finite numbers for a*x + b*y > c")
        if hp[0] == 0 == hp[1]:
            raise BadInput(f"{where}.halfplane", f"got {hp}; expected [a, b, c] for a*x + b*y > c with (a, b) != 0")
        top = max(abs(v) for v in hp)
        a, b, c = (v / top for v in hp) if top > 1.0 else hp  # same half-plane, no overflow of a*x + b*y
        return a * x + b * y > c
    member = np.zeros((width, height), dtype=bool)
    for i, cell in enumerate(region.cells):
        cx, cy = _cell(cell, width, height, f"{where}.cells.{i}")
        member[cx, cy] = True
    return member.ravel()


class _Places:
    """The cells a config gives: [x, y], or on a map world {metres: [x, y]}, a point of the map frame turned into the
    cell under it (`Frame`). Each point given in metres is kept as a Placement, and one off the map, or (for a start
    or a source) on an obstacle, is BadInput naming the point, its cell and the nearest free cell."""

    def __init__(self, width: int, height: int, obstacle: np.ndarray, frame: Frame | None, occupied: str):
        self.width, self.height, self.obstacle, self.frame, self.occupied = width, height, obstacle, frame, occupied
        self.placed: list[Placement] = []

    def cell(self, value: Any, where: str) -> tuple[int, int]:
        """An on-grid (x, y); one given in metres is a free cell too (a start's, a source's)."""
        metres = self._metres(value, where, "[x, y]")
        if metres is None:
            return _cell(value, self.width, self.height, where)
        x, y = self._locate(metres, where, free=True)
        self.placed.append(Placement(where, metres, (x, y)))
        return x, y

    def rect(self, value: Any, where: str) -> list:
        """A rect's [x0, y0, x1, y1]: as given, or from two opposite corners in metres (each on the map)."""
        metres = self._metres(value, where, "[x0, y0, x1, y1]")
        if metres is None:
            return _whole(value, 4, where, "[x0, y0, x1, y1]")
        (ax, ay), (bx, by) = self._locate(metres[:2], where, free=False), self._locate(metres[2:], where, free=False)
        cells = [min(ax, bx), min(ay, by), max(ax, bx), max(ay, by)]
        self.placed.append(Placement(where, metres, tuple(cells)))
        return cells

    def _metres(self, value: Any, where: str, shape: str) -> tuple[float, ...] | None:
        """The numbers of a {metres: [...]} value (None for any other value: cells)."""
        if not isinstance(value, Mapping):
            return None
        numbers = value.get("metres") if set(value) == {"metres"} else None
        count = shape.count(",") + 1
        if not (
            isinstance(numbers, (list, tuple))
            and len(numbers) == count
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in numbers)
        ):
            raise BadInput(
                where,
                f"got {_mapping(value)}; expected {shape} in cells, or {{metres: {shape}}} of finite numbers (a point "
                f"of the map frame)",
            )
        if self.frame is None:
            raise BadInput(
                where,
                f"got {{metres: {list(numbers)}}}; a position in metres needs world.map (its origin and resolution "
                f"place it on the grid); give {shape} in cells",
            )
        return tuple(float(v) for v in numbers)

    def _locate(self, point: tuple[float, ...], where: str, free: bool) -> tuple[int, int]:
        """The cell under a map-frame point, which must lie on the map (and on a free cell if `free`)."""
        pixel = self.frame.pixel_of(*point)
        x, y = pixel[0] // self.frame.cell, pixel[1] // self.frame.cell
        shown = f"{{metres: [{_m(point[0])}, {_m(point[1])}]}}"
        if max(abs(pixel[0]), abs(pixel[1])) >= FAR:  # pixel_of caps it there: no cell number to show
            problem = f"{shown} is far off the map (beyond {FAR:,.0f} pixels), off the {self.width}x{self.height} grid"
        elif not self.frame.on_map(pixel):
            problem = f"{shown} is off the map: it falls in cell ({x}, {y}), off the {self.width}x{self.height} grid"
        elif free and self.obstacle[x * self.height + y]:
            problem = f"{shown} is cell ({x}, {y}), which {self.occupied}"
        else:
            return x, y
        usable = ~self.obstacle if free else np.ones_like(self.obstacle)
        if not usable.any():
            raise BadInput(where, f"{problem}; the map has no free cell")
        cx, cy = np.divmod(np.flatnonzero(usable), self.height)
        best = int(np.argmin((cx - x) ** 2 + (cy - y) ** 2))
        near_x, near_y = int(cx[best]), int(cy[best])
        mx, my = self.frame.centre(near_x, near_y)
        kind = "free cell" if free else "cell on the map"
        raise BadInput(
            where,
            f"{problem}; the nearest {kind} is ({near_x}, {near_y}), {{metres: [{_m(mx)}, {_m(my)}]}} at its centre",
        )


def _mapping(value: Mapping) -> str:
    """A mapping as the config writes it ({meters: [1, 1]}), not as Python prints a dict ({'meters': [1, 1]})."""
    return "{" + ", ".join(f"{key}: {item}" for key, item in value.items()) + "}"


def _m(value: float) -> str:
    """Metres as a message shows them: to the millimetre, no trailing zeros."""
    return f"{round(value, 3):g}"


def grid_size(size: Any) -> tuple[int, int]:
    """Validated (width, height), before any array is built (riskplan.run.budget bounds width * height)."""
    values = list(size)
    if len(values) != 2 or any(int(v) != v or v < 1 for v in values):
        raise BadInput("world.size", f"got {values}; expected [width, height] of whole numbers >= 1")
    return int(values[0]), int(values[1])


def _cell(cell: Any, width: int, height: int, where: str) -> tuple[int, int]:
    """A validated on-grid (x, y)."""
    x, y = _whole(cell, 2, where, "[x, y]")
    if not (0 <= x < width and 0 <= y < height):
        raise BadInput(where, f"({x}, {y}) is off the {width}x{height} grid; need 0 <= x < {width}, 0 <= y < {height}")
    return x, y


def _whole(value: Any, count: int, where: str, shape: str) -> list[int]:
    """`count` whole numbers (a cell's [x, y], a rect's corners; 0.5 is no cell), or BadInput."""
    values = list(value) if isinstance(value, (list, tuple)) else [value]
    if len(values) != count or any(not isinstance(v, int) or isinstance(v, bool) for v in values):
        raise BadInput(where, f"got {value!r}; expected {shape} of whole numbers")
    return values


def _covariance(cov: Any, where: str) -> np.ndarray:
    """A symmetric positive-definite 2x2 matrix, or BadInput."""
    try:
        matrix = np.array([list(row) for row in cov], dtype=float)
    except (TypeError, ValueError):
        raise BadInput(where, f"got {cov!r}; expected [[a, b], [b, c]]") from None
    if matrix.shape != (2, 2) or not np.all(np.isfinite(matrix)):
        raise BadInput(where, f"got {matrix.tolist()}; expected a finite 2x2 matrix [[a, b], [b, c]]")
    if matrix[0, 1] != matrix[1, 0]:
        raise BadInput(where, f"{matrix.tolist()} is not symmetric; the off-diagonal entries must be equal")
    with np.errstate(all="ignore"):  # a determinant that overflows is caught by the caller, with a reason
        det = np.linalg.det(matrix)
    if matrix[0, 0] <= 0 or det <= 0:
        raise BadInput(where, f"{matrix.tolist()} is not positive definite; need a > 0 and a*c - b^2 > 0")
    return matrix


def _dist(data: Any, where: str) -> Dist:
    """Parse a reward distribution whose program fits the kernel's stack."""
    try:
        dist = distributions.parse(data, where)
    except RecursionError:
        raise BadInput(
            where,
            f"the reward program nests more than {distributions.MAX_LEVELS} levels deep; flatten "
            f"it (a sum or a mixture takes a list of any length)",
        ) from None
    if distributions.depth(dist) > MAX_STACK:
        raise BadInput(where, f"nests too deeply; at most {MAX_STACK} stack slots")
    distributions.check_bound(dist, where)
    return dist
