"""Foxglove message builders (JSON encoding) and the official Foxglove JSON schemas they follow.

The schemas are Foxglove's own, shipped verbatim as package data in riskplan/schemas/ (origin: the npm package
`@foxglove/schemas` 2.1.0, see riskplan/schemas/README.md). `schema_bytes(name)` gives the compact form
that `riskplan.run.record` writes as MCAP schema data (schema encoding "jsonschema", message encoding "json").

Foxglove's JSON encoding: timestamps are {"sec", "nsec"}, `bytes` fields are base64 strings, enums are ints.

World coordinates: frame "grid", 1 m per cell, cell (x, y) covers [x, x+1] x [y, y+1]; anything placed at a
cell is drawn at its centre (x + 0.5, y + 0.5).

`/world/map` Grid fields (cell_stride 4 bytes, little-endian, row-major with y-major rows as Foxglove wants):
- "cell"   UINT8 at offset 0: 0 = free and safe, 1 = risky, 2 = obstacle (an obstacle wins over risky);
- "region" INT16 at offset 2: region index into world["region_names"], -1 = no region.
"""

from __future__ import annotations

import base64
import json
from collections.abc import Iterator, Mapping
from functools import cache
from importlib import resources
from typing import Any

import numpy as np

FRAME = "grid"

GRID = "foxglove.Grid"
SCENE_UPDATE = "foxglove.SceneUpdate"

CELL_FREE, CELL_RISKY, CELL_OBSTACLE = 0, 1, 2

# foxglove.NumericType
UINT8, INT16 = 1, 4
# foxglove.LineType
LINE_STRIP = 0
# foxglove.SceneEntityDeletionType
DELETE_ALL = 1

ROBOT_COLORS = [
    (0.12, 0.47, 0.71),
    (1.00, 0.50, 0.05),
    (0.17, 0.63, 0.17),
    (0.84, 0.15, 0.16),
    (0.58, 0.40, 0.74),
    (0.55, 0.34, 0.29),
    (0.89, 0.47, 0.76),
    (0.50, 0.50, 0.50),
    (0.74, 0.74, 0.13),
    (0.09, 0.75, 0.81),
]
NETWORK_COLOR = (0.10, 0.10, 0.10)


# ----------------------------------------------------------------------------------------------- primitives
def time(ns: int) -> dict:
    ns = int(ns)
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def duration_zero() -> dict:
    return {"sec": 0, "nsec": 0}


def vec3(x: float, y: float, z: float) -> dict:
    return {"x": float(x), "y": float(y), "z": float(z)}


def pose(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> dict:
    return {"position": vec3(x, y, z), "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}


def color(rgb: tuple[float, float, float], a: float = 1.0) -> dict:
    return {"r": float(rgb[0]), "g": float(rgb[1]), "b": float(rgb[2]), "a": float(a)}


def robot_color(robot: int) -> tuple[float, float, float]:
    robot = int(robot)
    return NETWORK_COLOR if robot < 0 else ROBOT_COLORS[robot % len(ROBOT_COLORS)]


def entity(id: str, t_ns: int, **primitives: list) -> dict:
    """A complete foxglove.SceneEntity (every field present, as the schema requires) in frame "grid"."""
    e = {
        "timestamp": time(t_ns),
        "frame_id": FRAME,
        "id": id,
        "lifetime": duration_zero(),
        "frame_locked": False,
        "metadata": [],
        "arrows": [],
        "cubes": [],
        "spheres": [],
        "cylinders": [],
        "lines": [],
        "triangles": [],
        "texts": [],
        "models": [],
    }
    for k, v in primitives.items():
        if k not in e:
            raise KeyError(f"not a SceneEntity primitive list: {k}")
        e[k] = v
    return e


def cube(x: float, y: float, z: float, sx: float, sy: float, sz: float, rgb, a: float = 1.0) -> dict:
    return {"pose": pose(x, y, z), "size": vec3(sx, sy, sz), "color": color(rgb, a)}


def sphere(x: float, y: float, z: float, d: float, rgb, a: float = 1.0) -> dict:
    return {"pose": pose(x, y, z), "size": vec3(d, d, d), "color": color(rgb, a)}


def text(x: float, y: float, z: float, s: str, size: float = 0.5, rgb=(0.0, 0.0, 0.0)) -> dict:
    return {
        "pose": pose(x, y, z),
        "billboard": True,
        "font_size": float(size),
        "scale_invariant": False,
        "color": color(rgb),
        "text": str(s),
    }


def line_strip(points: list[tuple[float, float, float]], rgb, thickness: float = 0.08, a: float = 0.8) -> dict:
    return {
        "type": LINE_STRIP,
        "pose": pose(),
        "thickness": float(thickness),
        "scale_invariant": False,
        "points": [vec3(*p) for p in points],
        "color": color(rgb, a),
        "colors": [],
        "indices": [],
    }


def scene_update(entities: list[dict], deletions: list[dict] | None = None) -> dict:
    return {"deletions": deletions or [], "entities": entities}


def delete_all(t_ns: int) -> dict:
    return {"timestamp": time(t_ns), "type": DELETE_ALL, "id": ""}


# ----------------------------------------------------------------------------------------------- world
def cell_codes(world: dict) -> np.ndarray:
    """(width, height) uint8: 0 free safe, 1 risky, 2 obstacle."""
    w, h = int(world["width"]), int(world["height"])
    codes = np.zeros((w, h), dtype=np.uint8)
    risky = world.get("risky")
    if risky is not None:
        codes[np.asarray(risky, dtype=bool)] = CELL_RISKY
    obstacles = world.get("obstacles")
    if obstacles is not None:
        codes[np.asarray(obstacles, dtype=bool)] = CELL_OBSTACLE
    return codes


def grid(world: dict, t_ns: int) -> dict:
    """foxglove.Grid of the world: fields "cell" (UINT8 @0) and "region" (INT16 @2), 1 m cells, origin (0, 0)."""
    w, h = int(world["width"]), int(world["height"])
    cells = np.zeros((h, w), dtype=np.dtype([("cell", "u1"), ("pad", "u1"), ("region", "<i2")]))
    cells["cell"] = cell_codes(world).T
    region = world.get("cell_region")
    cells["region"] = -1 if region is None else np.asarray(region, dtype=np.int64).T
    return {
        "timestamp": time(t_ns),
        "frame_id": FRAME,
        "pose": pose(),
        "column_count": w,
        "cell_size": {"x": 1.0, "y": 1.0},
        "row_stride": 4 * w,
        "cell_stride": 4,
        "fields": [
            {"name": "cell", "offset": 0, "type": UINT8},
            {"name": "region", "offset": 2, "type": INT16},
        ],
        "data": base64.b64encode(cells.tobytes()).decode("ascii"),
    }


def decode_grid(msg: dict) -> np.ndarray:
    """Inverse of `grid` for the "cell" field: (width, height) uint8 codes."""
    w = int(msg["column_count"])
    raw = np.frombuffer(base64.b64decode(msg["data"]), dtype=np.uint8)
    rows = raw.reshape(-1, int(msg["row_stride"]))
    return rows[:, 0 : 4 * w : 4].T.copy()


def world_markers(world: dict, t_ns: int) -> dict:
    """foxglove.SceneUpdate: obstacles (cubes), sources (spheres + names), start cells (flat cubes + labels)."""
    obstacles = world.get("obstacles")
    obs_cubes = []
    if obstacles is not None:
        for x, y in np.argwhere(np.asarray(obstacles, dtype=bool)):
            obs_cubes.append(cube(x + 0.5, y + 0.5, 0.25, 1.0, 1.0, 0.5, (0.25, 0.25, 0.25)))
    src_spheres, src_texts = [], []
    for j, s in enumerate(world.get("sources", [])):
        x, y = float(s["x"]) + 0.5, float(s["y"]) + 0.5
        src_spheres.append(sphere(x, y, 0.4, 0.7, (1.0, 0.84, 0.0)))
        src_texts.append(text(x, y, 1.2, f"{j}: {s.get('name', j)}", 0.45))
    start_cubes, start_texts = [], []
    for r, xy in enumerate(world.get("start", [])):
        x, y = float(xy[0]) + 0.5, float(xy[1]) + 0.5
        start_cubes.append(cube(x, y, 0.03, 0.85, 0.85, 0.06, robot_color(r), 0.6))
        start_texts.append(text(x, y, 0.9, f"start {r}", 0.35, robot_color(r)))
    return scene_update(
        [
            entity("obstacles", t_ns, cubes=obs_cubes),
            entity("sources", t_ns, spheres=src_spheres, texts=src_texts),
            entity("start", t_ns, cubes=start_cubes, texts=start_texts),
        ]
    )


def network_scene(network: dict, t_ns: int) -> dict:
    """foxglove.SceneUpdate in frame "team": robots as coloured spheres, links as lines (random-geometric
    robots at their drawn positions, others on a circle), 10 m across."""
    n = int(network["robots"])
    positions = network.get("positions")
    if positions is None:
        angle = 2 * np.pi * np.arange(n) / max(n, 1)
        xy = np.stack([0.5 + 0.5 * np.cos(angle), 0.5 + 0.5 * np.sin(angle)], axis=1) if n > 1 else np.full((1, 2), 0.5)
    else:
        xy = np.asarray(positions, dtype=float)
    xy = 10.0 * xy
    nodes = [sphere(x, y, 0.0, 0.6, robot_color(r)) for r, (x, y) in enumerate(xy)]
    labels = [text(x, y, 0.8, f"robot {r}", 0.4, robot_color(r)) for r, (x, y) in enumerate(xy)]
    links = [
        line_strip([(xy[j][0], xy[j][1], 0.0), (xy[i][0], xy[i][1], 0.0)], (0.4, 0.4, 0.4), 0.05)
        for i, j in network.get("edges", [])
    ]
    team = entity("team", t_ns, spheres=nodes, texts=labels, lines=links)
    team["frame_id"] = "team"
    return scene_update([team])


# ----------------------------------------------------------------------------------------------- paths
def path_scenes(
    table: Mapping[str, Any], t0_ns: int, step_ns: int, width: int | None = None, height: int | None = None
) -> Iterator[tuple[int, dict]]:
    """Yield (log_time_ns, foxglove.SceneUpdate) to replay sampled paths.

    Each (policy, episode) group, in order of first appearance, is played one after the other: at its first
    step all earlier entities are deleted, a line strip per robot ("path/<r>") shows the whole path and a label
    names the policy and episode; then one message per step moves a sphere per robot ("robot/<r>") to its cell
    centre. Consecutive steps are `step_ns` apart, and groups are separated by a pause of 4 steps.
    """
    xs = np.asarray(table["x"], dtype=np.float64) + 0.5
    if len(xs) == 0:
        return
    ys = np.asarray(table["y"], dtype=np.float64) + 0.5
    if width is None:
        width = int(np.nanmax(xs[np.isfinite(xs)], initial=0.5))
    if height is None:
        height = int(np.nanmax(ys[np.isfinite(ys)], initial=0.5))
    policies, episodes = np.asarray(table["policy"], dtype=object), np.asarray(table["episode"], dtype=object)
    numbers: dict[tuple, int] = {}  # (policy, episode) -> its group, numbered in order of first appearance
    group = np.array([numbers.setdefault(key, len(numbers)) for key in zip(policies, episodes)], dtype=np.int64)
    steps = np.asarray(table["step"])
    robots = np.asarray(table["robot"])
    order = np.lexsort((robots, steps, group))
    bounds = np.flatnonzero(np.diff(group[order])) + 1
    t = int(t0_ns)
    step_ns = int(step_ns)
    for idx in np.split(order, bounds):
        policy, episode = policies[idx[0]], episodes[idx[0]]
        g_steps, g_robots = steps[idx].tolist(), robots[idx].tolist()
        g_x, g_y = xs[idx].tolist(), ys[idx].tolist()
        paths: dict[int, list] = {}
        for r, x, y in zip(g_robots, g_x, g_y):
            paths.setdefault(int(r), []).append((x, y, 0.05))
        try:
            ep = int(episode)
        except (TypeError, ValueError):
            ep = episode
        i, k, m = -1, 0, len(idx)
        while k < m:
            i += 1
            ts = t + i * step_ns
            s = g_steps[k]
            ents = []
            if i == 0:
                for r, pts in paths.items():
                    ents.append(entity(f"path/{r}", ts, lines=[line_strip(pts, robot_color(r))]))
                label = text(width / 2.0, height + 0.8, 0.5, f"{policy} policy, episode {ep}", 0.6)
                ents.append(entity("label", ts, texts=[label]))
            while k < m and g_steps[k] == s:
                r = int(g_robots[k])
                ents.append(entity(f"robot/{r}", ts, spheres=[sphere(g_x[k], g_y[k], 0.3, 0.6, robot_color(r))]))
                k += 1
            yield ts, scene_update(ents, [delete_all(ts)] if i == 0 else None)
        t += (i + 1 + 4) * step_ns


# ----------------------------------------------------------------------------------------------- schemas
@cache
def schema(name: str) -> dict[str, Any]:
    """An official Foxglove JSON schema, shipped verbatim as package data (riskplan/schemas/)."""
    return json.loads(resources.files("riskplan.run").joinpath("schemas", f"{name}.json").read_text())


@cache
def schema_bytes(name: str) -> bytes:
    return json.dumps(schema(name), separators=(",", ":")).encode()
