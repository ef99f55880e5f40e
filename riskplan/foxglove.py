"""Foxglove message builders (JSON encoding) and the official Foxglove JSON schemas they follow.

The schema texts at the bottom of this module are Foxglove's own, embedded verbatim (origin: the npm package
`@foxglove/schemas` 2.1.0, see tests/data/foxglove/README.md). `schema_bytes(name)` gives the compact form
that `riskplan.record` writes as MCAP schema data (schema encoding "jsonschema", message encoding "json").

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
from functools import lru_cache
from typing import Any, Iterator

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
    (0.12, 0.47, 0.71), (1.00, 0.50, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16),
    (0.58, 0.40, 0.74), (0.55, 0.34, 0.29), (0.89, 0.47, 0.76), (0.50, 0.50, 0.50),
    (0.74, 0.74, 0.13), (0.09, 0.75, 0.81),
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
    links = [line_strip([(xy[j][0], xy[j][1], 0.0), (xy[i][0], xy[i][1], 0.0)], (0.4, 0.4, 0.4), 0.05)
             for i, j in network.get("edges", [])]
    team = entity("team", t_ns, spheres=nodes, texts=labels, lines=links)
    team["frame_id"] = "team"
    return scene_update([team])


# ----------------------------------------------------------------------------------------------- paths
def path_scenes(
    df, t0_ns: int, step_ns: int, width: int | None = None, height: int | None = None
) -> Iterator[tuple[int, dict]]:
    """Yield (log_time_ns, foxglove.SceneUpdate) to replay sampled paths.

    Each (policy, episode) group, in order of first appearance, is played one after the other: at its first
    step all earlier entities are deleted, a line strip per robot ("path/<r>") shows the whole path and a label
    names the policy and episode; then one message per step moves a sphere per robot ("robot/<r>") to its cell
    centre. Consecutive steps are `step_ns` apart, and groups are separated by a pause of 4 steps.
    """
    n = len(df)
    if n == 0:
        return
    xs = df["x"].to_numpy(dtype=np.float64) + 0.5
    ys = df["y"].to_numpy(dtype=np.float64) + 0.5
    if width is None:
        width = int(np.nanmax(xs[np.isfinite(xs)], initial=0.5))
    if height is None:
        height = int(np.nanmax(ys[np.isfinite(ys)], initial=0.5))
    group = df.groupby(["policy", "episode"], sort=False).ngroup().to_numpy()
    steps = df["step"].to_numpy()
    robots = df["robot"].to_numpy()
    order = np.lexsort((robots, steps, group))
    labels = df[["policy", "episode"]].to_numpy()
    bounds = np.flatnonzero(np.diff(group[order])) + 1
    t = int(t0_ns)
    step_ns = int(step_ns)
    for idx in np.split(order, bounds):
        policy, episode = labels[idx[0]]
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
def schemas() -> dict[str, str]:
    """Official schema name -> schema text (verbatim)."""
    return {GRID: GRID_SCHEMA_JSON, SCENE_UPDATE: SCENE_UPDATE_SCHEMA_JSON}


@lru_cache(maxsize=None)
def schema(name: str) -> dict[str, Any]:
    return json.loads(schemas()[name])


@lru_cache(maxsize=None)
def schema_bytes(name: str) -> bytes:
    return json.dumps(schema(name), separators=(",", ":")).encode()


# Official Foxglove JSON schemas, verbatim (npm @foxglove/schemas 2.1.0, dist/jsonschema/index.js).
GRID_SCHEMA_JSON = r'''{
  "title": "foxglove.Grid",
  "description": "A 2D grid of data",
  "$comment": "Generated by https://github.com/foxglove/foxglove-sdk",
  "type": "object",
  "properties": {
    "timestamp": {
      "type": "object",
      "title": "time",
      "properties": {
        "sec": {
          "type": "integer",
          "minimum": 0
        },
        "nsec": {
          "type": "integer",
          "minimum": 0,
          "maximum": 999999999
        }
      },
      "description": "Timestamp of grid"
    },
    "frame_id": {
      "type": "string",
      "description": "Frame of reference"
    },
    "pose": {
      "title": "foxglove.Pose",
      "description": "Origin of grid's corner relative to frame of reference; grid is positioned in the x-y plane relative to this origin",
      "type": "object",
      "properties": {
        "position": {
          "title": "foxglove.Vector3",
          "description": "Point denoting position in 3D space",
          "type": "object",
          "properties": {
            "x": {
              "type": "number",
              "description": "x component"
            },
            "y": {
              "type": "number",
              "description": "y component"
            },
            "z": {
              "type": "number",
              "description": "z component"
            }
          },
          "required": [
            "x",
            "y",
            "z"
          ]
        },
        "orientation": {
          "title": "foxglove.Quaternion",
          "description": "Quaternion denoting orientation in 3D space",
          "type": "object",
          "properties": {
            "x": {
              "type": "number",
              "description": "x value"
            },
            "y": {
              "type": "number",
              "description": "y value"
            },
            "z": {
              "type": "number",
              "description": "z value"
            },
            "w": {
              "type": "number",
              "description": "w value"
            }
          },
          "required": [
            "x",
            "y",
            "z",
            "w"
          ]
        }
      },
      "required": [
        "position",
        "orientation"
      ]
    },
    "column_count": {
      "type": "integer",
      "minimum": 0,
      "description": "Number of grid columns"
    },
    "cell_size": {
      "title": "foxglove.Vector2",
      "description": "Size of single grid cell along x and y axes, relative to `pose`",
      "type": "object",
      "properties": {
        "x": {
          "type": "number",
          "description": "x component"
        },
        "y": {
          "type": "number",
          "description": "y component"
        }
      },
      "required": [
        "x",
        "y"
      ]
    },
    "row_stride": {
      "type": "integer",
      "minimum": 0,
      "description": "Number of bytes between rows in `data`"
    },
    "cell_stride": {
      "type": "integer",
      "minimum": 0,
      "description": "Number of bytes between cells within a row in `data`"
    },
    "fields": {
      "type": "array",
      "items": {
        "title": "foxglove.PackedElementField",
        "description": "A field present within each element in a byte array of packed elements.",
        "type": "object",
        "properties": {
          "name": {
            "type": "string",
            "description": "Name of the field"
          },
          "offset": {
            "type": "integer",
            "minimum": 0,
            "description": "Byte offset from start of data buffer"
          },
          "type": {
            "title": "foxglove.NumericType",
            "description": "Type of data in the field. Integers are stored using little-endian byte order.",
            "oneOf": [
              {
                "title": "UNKNOWN",
                "const": 0,
                "description": "Unknown numeric type"
              },
              {
                "title": "UINT8",
                "const": 1,
                "description": "Unsigned 8-bit integer"
              },
              {
                "title": "INT8",
                "const": 2,
                "description": "Signed 8-bit integer"
              },
              {
                "title": "UINT16",
                "const": 3,
                "description": "Unsigned 16-bit integer"
              },
              {
                "title": "INT16",
                "const": 4,
                "description": "Signed 16-bit integer"
              },
              {
                "title": "UINT32",
                "const": 5,
                "description": "Unsigned 32-bit integer"
              },
              {
                "title": "INT32",
                "const": 6,
                "description": "Signed 32-bit integer"
              },
              {
                "title": "FLOAT32",
                "const": 7,
                "description": "32-bit floating-point number"
              },
              {
                "title": "FLOAT64",
                "const": 8,
                "description": "64-bit floating-point number"
              }
            ]
          }
        },
        "required": [
          "name",
          "offset",
          "type"
        ]
      },
      "description": "Fields in `data`. `red`, `green`, `blue`, and `alpha` are optional for customizing the grid's color.\nTo enable RGB color visualization in the [3D panel](https://docs.foxglove.dev/docs/visualization/panels/3d#rgba-separate-fields-color-mode), include **all four** of these fields in your `fields` array:\n\n- `red` - Red channel value\n- `green` - Green channel value\n- `blue` - Blue channel value\n- `alpha` - Alpha/transparency channel value\n\n**note:** All four fields must be present with these exact names for RGB visualization to work. The order of fields doesn't matter, but the names must match exactly.\n\nRecommended type: `UINT8` (0-255 range) for standard 8-bit color channels.\n\nExample field definitions:\n\n**RGB color only:**\n\n```javascript\nfields: [\n { name: \"red\", offset: 0, type: NumericType.UINT8 },\n { name: \"green\", offset: 1, type: NumericType.UINT8 },\n { name: \"blue\", offset: 2, type: NumericType.UINT8 },\n { name: \"alpha\", offset: 3, type: NumericType.UINT8 },\n];\n```\n\n**RGB color with elevation (for 3D terrain visualization):**\n\n```javascript\nfields: [\n { name: \"red\", offset: 0, type: NumericType.UINT8 },\n { name: \"green\", offset: 1, type: NumericType.UINT8 },\n { name: \"blue\", offset: 2, type: NumericType.UINT8 },\n { name: \"alpha\", offset: 3, type: NumericType.UINT8 },\n { name: \"elevation\", offset: 4, type: NumericType.FLOAT32 },\n];\n```\n\nWhen these fields are present, the 3D panel will offer additional \"Color Mode\" options including \"RGBA (separate fields)\" to visualize the RGB data directly. For elevation visualization, set the \"Elevation field\" to your elevation layer name."
    },
    "data": {
      "type": "string",
      "contentEncoding": "base64",
      "description": "Grid cell data, interpreted using `fields`, in row-major (y-major) order.\nFor the data element starting at byte offset i, the coordinates of its corner closest to the origin will be:\n\n- y = i / row_stride * cell_size.y\n- x = (i % row_stride) / cell_stride * cell_size.x"
    }
  },
  "required": [
    "timestamp",
    "frame_id",
    "pose",
    "column_count",
    "cell_size",
    "row_stride",
    "cell_stride",
    "fields",
    "data"
  ]
}
'''

SCENE_UPDATE_SCHEMA_JSON = r'''{
  "title": "foxglove.SceneUpdate",
  "description": "An update to the entities displayed in a 3D scene",
  "$comment": "Generated by https://github.com/foxglove/foxglove-sdk",
  "type": "object",
  "properties": {
    "deletions": {
      "type": "array",
      "items": {
        "title": "foxglove.SceneEntityDeletion",
        "description": "Command to remove previously published entities",
        "type": "object",
        "properties": {
          "timestamp": {
            "type": "object",
            "title": "time",
            "properties": {
              "sec": {
                "type": "integer",
                "minimum": 0
              },
              "nsec": {
                "type": "integer",
                "minimum": 0,
                "maximum": 999999999
              }
            },
            "description": "Timestamp of the deletion. Only matching entities earlier than this timestamp will be deleted."
          },
          "type": {
            "title": "foxglove.SceneEntityDeletionType",
            "description": "Type of deletion action to perform",
            "oneOf": [
              {
                "title": "MATCHING_ID",
                "const": 0,
                "description": "Delete the existing entity on the same topic that has the provided `id`"
              },
              {
                "title": "ALL",
                "const": 1,
                "description": "Delete all existing entities on the same topic"
              }
            ]
          },
          "id": {
            "type": "string",
            "description": "Identifier which must match if `type` is `MATCHING_ID`."
          }
        },
        "required": [
          "timestamp",
          "type",
          "id"
        ]
      },
      "description": "Scene entities to delete"
    },
    "entities": {
      "type": "array",
      "items": {
        "title": "foxglove.SceneEntity",
        "description": "A visual element in a 3D scene. An entity may be composed of multiple primitives which all share the same frame of reference.",
        "type": "object",
        "properties": {
          "timestamp": {
            "type": "object",
            "title": "time",
            "properties": {
              "sec": {
                "type": "integer",
                "minimum": 0
              },
              "nsec": {
                "type": "integer",
                "minimum": 0,
                "maximum": 999999999
              }
            },
            "description": "Timestamp of the entity"
          },
          "frame_id": {
            "type": "string",
            "description": "Frame of reference"
          },
          "id": {
            "type": "string",
            "description": "Identifier for the entity. A entity will replace any prior entity on the same topic with the same `id`."
          },
          "lifetime": {
            "type": "object",
            "title": "duration",
            "properties": {
              "sec": {
                "type": "integer"
              },
              "nsec": {
                "type": "integer",
                "minimum": 0,
                "maximum": 999999999
              }
            },
            "description": "Length of time (relative to `timestamp`) after which the entity should be automatically removed. Zero value indicates the entity should remain visible until it is replaced or deleted."
          },
          "frame_locked": {
            "type": "boolean",
            "description": "Whether the entity should keep its location in the fixed frame (false) or follow the frame specified in `frame_id` as it moves relative to the fixed frame (true)"
          },
          "metadata": {
            "type": "array",
            "items": {
              "title": "foxglove.KeyValuePair",
              "description": "A key with its associated value",
              "type": "object",
              "properties": {
                "key": {
                  "type": "string",
                  "description": "Key"
                },
                "value": {
                  "type": "string",
                  "description": "Value"
                }
              },
              "required": [
                "key",
                "value"
              ]
            },
            "description": "Additional user-provided metadata associated with the entity. Keys must be unique."
          },
          "arrows": {
            "type": "array",
            "items": {
              "title": "foxglove.ArrowPrimitive",
              "description": "A primitive representing an arrow",
              "type": "object",
              "properties": {
                "pose": {
                  "title": "foxglove.Pose",
                  "description": "Position of the arrow's tail and orientation of the arrow. Identity orientation means the arrow points in the +x direction.",
                  "type": "object",
                  "properties": {
                    "position": {
                      "title": "foxglove.Vector3",
                      "description": "Point denoting position in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x component"
                        },
                        "y": {
                          "type": "number",
                          "description": "y component"
                        },
                        "z": {
                          "type": "number",
                          "description": "z component"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z"
                      ]
                    },
                    "orientation": {
                      "title": "foxglove.Quaternion",
                      "description": "Quaternion denoting orientation in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x value"
                        },
                        "y": {
                          "type": "number",
                          "description": "y value"
                        },
                        "z": {
                          "type": "number",
                          "description": "z value"
                        },
                        "w": {
                          "type": "number",
                          "description": "w value"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z",
                        "w"
                      ]
                    }
                  },
                  "required": [
                    "position",
                    "orientation"
                  ]
                },
                "shaft_length": {
                  "type": "number",
                  "description": "Length of the arrow shaft"
                },
                "shaft_diameter": {
                  "type": "number",
                  "description": "Diameter of the arrow shaft"
                },
                "head_length": {
                  "type": "number",
                  "description": "Length of the arrow head"
                },
                "head_diameter": {
                  "type": "number",
                  "description": "Diameter of the arrow head"
                },
                "color": {
                  "title": "foxglove.Color",
                  "description": "Color of the arrow",
                  "type": "object",
                  "properties": {
                    "r": {
                      "type": "number",
                      "description": "Red value between 0 and 1"
                    },
                    "g": {
                      "type": "number",
                      "description": "Green value between 0 and 1"
                    },
                    "b": {
                      "type": "number",
                      "description": "Blue value between 0 and 1"
                    },
                    "a": {
                      "type": "number",
                      "description": "Alpha value between 0 and 1"
                    }
                  },
                  "required": [
                    "r",
                    "g",
                    "b",
                    "a"
                  ]
                }
              },
              "required": [
                "pose",
                "shaft_length",
                "shaft_diameter",
                "head_length",
                "head_diameter",
                "color"
              ]
            },
            "description": "Arrow primitives"
          },
          "cubes": {
            "type": "array",
            "items": {
              "title": "foxglove.CubePrimitive",
              "description": "A primitive representing a cube or rectangular prism",
              "type": "object",
              "properties": {
                "pose": {
                  "title": "foxglove.Pose",
                  "description": "Position of the center of the cube and orientation of the cube",
                  "type": "object",
                  "properties": {
                    "position": {
                      "title": "foxglove.Vector3",
                      "description": "Point denoting position in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x component"
                        },
                        "y": {
                          "type": "number",
                          "description": "y component"
                        },
                        "z": {
                          "type": "number",
                          "description": "z component"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z"
                      ]
                    },
                    "orientation": {
                      "title": "foxglove.Quaternion",
                      "description": "Quaternion denoting orientation in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x value"
                        },
                        "y": {
                          "type": "number",
                          "description": "y value"
                        },
                        "z": {
                          "type": "number",
                          "description": "z value"
                        },
                        "w": {
                          "type": "number",
                          "description": "w value"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z",
                        "w"
                      ]
                    }
                  },
                  "required": [
                    "position",
                    "orientation"
                  ]
                },
                "size": {
                  "title": "foxglove.Vector3",
                  "description": "Size of the cube along each axis",
                  "type": "object",
                  "properties": {
                    "x": {
                      "type": "number",
                      "description": "x component"
                    },
                    "y": {
                      "type": "number",
                      "description": "y component"
                    },
                    "z": {
                      "type": "number",
                      "description": "z component"
                    }
                  },
                  "required": [
                    "x",
                    "y",
                    "z"
                  ]
                },
                "color": {
                  "title": "foxglove.Color",
                  "description": "Color of the cube",
                  "type": "object",
                  "properties": {
                    "r": {
                      "type": "number",
                      "description": "Red value between 0 and 1"
                    },
                    "g": {
                      "type": "number",
                      "description": "Green value between 0 and 1"
                    },
                    "b": {
                      "type": "number",
                      "description": "Blue value between 0 and 1"
                    },
                    "a": {
                      "type": "number",
                      "description": "Alpha value between 0 and 1"
                    }
                  },
                  "required": [
                    "r",
                    "g",
                    "b",
                    "a"
                  ]
                }
              },
              "required": [
                "pose",
                "size",
                "color"
              ]
            },
            "description": "Cube primitives"
          },
          "spheres": {
            "type": "array",
            "items": {
              "title": "foxglove.SpherePrimitive",
              "description": "A primitive representing a sphere or ellipsoid",
              "type": "object",
              "properties": {
                "pose": {
                  "title": "foxglove.Pose",
                  "description": "Position of the center of the sphere and orientation of the sphere",
                  "type": "object",
                  "properties": {
                    "position": {
                      "title": "foxglove.Vector3",
                      "description": "Point denoting position in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x component"
                        },
                        "y": {
                          "type": "number",
                          "description": "y component"
                        },
                        "z": {
                          "type": "number",
                          "description": "z component"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z"
                      ]
                    },
                    "orientation": {
                      "title": "foxglove.Quaternion",
                      "description": "Quaternion denoting orientation in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x value"
                        },
                        "y": {
                          "type": "number",
                          "description": "y value"
                        },
                        "z": {
                          "type": "number",
                          "description": "z value"
                        },
                        "w": {
                          "type": "number",
                          "description": "w value"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z",
                        "w"
                      ]
                    }
                  },
                  "required": [
                    "position",
                    "orientation"
                  ]
                },
                "size": {
                  "title": "foxglove.Vector3",
                  "description": "Size (diameter) of the sphere along each axis",
                  "type": "object",
                  "properties": {
                    "x": {
                      "type": "number",
                      "description": "x component"
                    },
                    "y": {
                      "type": "number",
                      "description": "y component"
                    },
                    "z": {
                      "type": "number",
                      "description": "z component"
                    }
                  },
                  "required": [
                    "x",
                    "y",
                    "z"
                  ]
                },
                "color": {
                  "title": "foxglove.Color",
                  "description": "Color of the sphere",
                  "type": "object",
                  "properties": {
                    "r": {
                      "type": "number",
                      "description": "Red value between 0 and 1"
                    },
                    "g": {
                      "type": "number",
                      "description": "Green value between 0 and 1"
                    },
                    "b": {
                      "type": "number",
                      "description": "Blue value between 0 and 1"
                    },
                    "a": {
                      "type": "number",
                      "description": "Alpha value between 0 and 1"
                    }
                  },
                  "required": [
                    "r",
                    "g",
                    "b",
                    "a"
                  ]
                }
              },
              "required": [
                "pose",
                "size",
                "color"
              ]
            },
            "description": "Sphere primitives"
          },
          "cylinders": {
            "type": "array",
            "items": {
              "title": "foxglove.CylinderPrimitive",
              "description": "A primitive representing a cylinder, elliptic cylinder, or truncated cone",
              "type": "object",
              "properties": {
                "pose": {
                  "title": "foxglove.Pose",
                  "description": "Position of the center of the cylinder and orientation of the cylinder. The flat face(s) are perpendicular to the z-axis.",
                  "type": "object",
                  "properties": {
                    "position": {
                      "title": "foxglove.Vector3",
                      "description": "Point denoting position in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x component"
                        },
                        "y": {
                          "type": "number",
                          "description": "y component"
                        },
                        "z": {
                          "type": "number",
                          "description": "z component"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z"
                      ]
                    },
                    "orientation": {
                      "title": "foxglove.Quaternion",
                      "description": "Quaternion denoting orientation in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x value"
                        },
                        "y": {
                          "type": "number",
                          "description": "y value"
                        },
                        "z": {
                          "type": "number",
                          "description": "z value"
                        },
                        "w": {
                          "type": "number",
                          "description": "w value"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z",
                        "w"
                      ]
                    }
                  },
                  "required": [
                    "position",
                    "orientation"
                  ]
                },
                "size": {
                  "title": "foxglove.Vector3",
                  "description": "Size of the cylinder's bounding box",
                  "type": "object",
                  "properties": {
                    "x": {
                      "type": "number",
                      "description": "x component"
                    },
                    "y": {
                      "type": "number",
                      "description": "y component"
                    },
                    "z": {
                      "type": "number",
                      "description": "z component"
                    }
                  },
                  "required": [
                    "x",
                    "y",
                    "z"
                  ]
                },
                "bottom_scale": {
                  "type": "number",
                  "description": "0-1, ratio of the diameter of the cylinder's bottom face (min z) to the bottom of the bounding box"
                },
                "top_scale": {
                  "type": "number",
                  "description": "0-1, ratio of the diameter of the cylinder's top face (max z) to the top of the bounding box"
                },
                "color": {
                  "title": "foxglove.Color",
                  "description": "Color of the cylinder",
                  "type": "object",
                  "properties": {
                    "r": {
                      "type": "number",
                      "description": "Red value between 0 and 1"
                    },
                    "g": {
                      "type": "number",
                      "description": "Green value between 0 and 1"
                    },
                    "b": {
                      "type": "number",
                      "description": "Blue value between 0 and 1"
                    },
                    "a": {
                      "type": "number",
                      "description": "Alpha value between 0 and 1"
                    }
                  },
                  "required": [
                    "r",
                    "g",
                    "b",
                    "a"
                  ]
                }
              },
              "required": [
                "pose",
                "size",
                "bottom_scale",
                "top_scale",
                "color"
              ]
            },
            "description": "Cylinder primitives"
          },
          "lines": {
            "type": "array",
            "items": {
              "title": "foxglove.LinePrimitive",
              "description": "A primitive representing a series of points connected by lines",
              "type": "object",
              "properties": {
                "type": {
                  "title": "foxglove.LineType",
                  "description": "Drawing primitive to use for lines",
                  "oneOf": [
                    {
                      "title": "LINE_STRIP",
                      "const": 0,
                      "description": "Connected line segments: 0-1, 1-2, ..., (n-1)-n"
                    },
                    {
                      "title": "LINE_LOOP",
                      "const": 1,
                      "description": "Closed polygon: 0-1, 1-2, ..., (n-1)-n, n-0"
                    },
                    {
                      "title": "LINE_LIST",
                      "const": 2,
                      "description": "Individual line segments: 0-1, 2-3, 4-5, ..."
                    }
                  ]
                },
                "pose": {
                  "title": "foxglove.Pose",
                  "description": "Origin of lines relative to reference frame",
                  "type": "object",
                  "properties": {
                    "position": {
                      "title": "foxglove.Vector3",
                      "description": "Point denoting position in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x component"
                        },
                        "y": {
                          "type": "number",
                          "description": "y component"
                        },
                        "z": {
                          "type": "number",
                          "description": "z component"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z"
                      ]
                    },
                    "orientation": {
                      "title": "foxglove.Quaternion",
                      "description": "Quaternion denoting orientation in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x value"
                        },
                        "y": {
                          "type": "number",
                          "description": "y value"
                        },
                        "z": {
                          "type": "number",
                          "description": "z value"
                        },
                        "w": {
                          "type": "number",
                          "description": "w value"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z",
                        "w"
                      ]
                    }
                  },
                  "required": [
                    "position",
                    "orientation"
                  ]
                },
                "thickness": {
                  "type": "number",
                  "description": "Line thickness"
                },
                "scale_invariant": {
                  "type": "boolean",
                  "description": "Indicates whether `thickness` is a fixed size in screen pixels (true), or specified in world coordinates and scales with distance from the camera (false)"
                },
                "points": {
                  "type": "array",
                  "items": {
                    "title": "foxglove.Point3",
                    "description": "A point representing a position in 3D space",
                    "type": "object",
                    "properties": {
                      "x": {
                        "type": "number",
                        "description": "x coordinate position"
                      },
                      "y": {
                        "type": "number",
                        "description": "y coordinate position"
                      },
                      "z": {
                        "type": "number",
                        "description": "z coordinate position"
                      }
                    },
                    "required": [
                      "x",
                      "y",
                      "z"
                    ]
                  },
                  "description": "Points along the line"
                },
                "color": {
                  "title": "foxglove.Color",
                  "description": "Solid color to use for the whole line. Ignored if `colors` is non-empty.",
                  "type": "object",
                  "properties": {
                    "r": {
                      "type": "number",
                      "description": "Red value between 0 and 1"
                    },
                    "g": {
                      "type": "number",
                      "description": "Green value between 0 and 1"
                    },
                    "b": {
                      "type": "number",
                      "description": "Blue value between 0 and 1"
                    },
                    "a": {
                      "type": "number",
                      "description": "Alpha value between 0 and 1"
                    }
                  },
                  "required": [
                    "r",
                    "g",
                    "b",
                    "a"
                  ]
                },
                "colors": {
                  "type": "array",
                  "items": {
                    "title": "foxglove.Color",
                    "description": "A color in RGBA format",
                    "type": "object",
                    "properties": {
                      "r": {
                        "type": "number",
                        "description": "Red value between 0 and 1"
                      },
                      "g": {
                        "type": "number",
                        "description": "Green value between 0 and 1"
                      },
                      "b": {
                        "type": "number",
                        "description": "Blue value between 0 and 1"
                      },
                      "a": {
                        "type": "number",
                        "description": "Alpha value between 0 and 1"
                      }
                    },
                    "required": [
                      "r",
                      "g",
                      "b",
                      "a"
                    ]
                  },
                  "description": "Per-point colors (if non-empty, must have the same length as `points`)."
                },
                "indices": {
                  "type": "array",
                  "items": {
                    "type": "integer",
                    "minimum": 0
                  },
                  "description": "Indices into the `points` and `colors` attribute arrays, which can be used to avoid duplicating attribute data.\n\nIf omitted or empty, indexing will not be used. This default behavior is equivalent to specifying [0, 1, ..., N-1] for the indices (where N is the number of `points` provided)."
                }
              },
              "required": [
                "type",
                "pose",
                "thickness",
                "scale_invariant",
                "points",
                "color",
                "colors",
                "indices"
              ]
            },
            "description": "Line primitives"
          },
          "triangles": {
            "type": "array",
            "items": {
              "title": "foxglove.TriangleListPrimitive",
              "description": "A primitive representing a set of triangles or a surface tiled by triangles",
              "type": "object",
              "properties": {
                "pose": {
                  "title": "foxglove.Pose",
                  "description": "Origin of triangles relative to reference frame",
                  "type": "object",
                  "properties": {
                    "position": {
                      "title": "foxglove.Vector3",
                      "description": "Point denoting position in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x component"
                        },
                        "y": {
                          "type": "number",
                          "description": "y component"
                        },
                        "z": {
                          "type": "number",
                          "description": "z component"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z"
                      ]
                    },
                    "orientation": {
                      "title": "foxglove.Quaternion",
                      "description": "Quaternion denoting orientation in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x value"
                        },
                        "y": {
                          "type": "number",
                          "description": "y value"
                        },
                        "z": {
                          "type": "number",
                          "description": "z value"
                        },
                        "w": {
                          "type": "number",
                          "description": "w value"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z",
                        "w"
                      ]
                    }
                  },
                  "required": [
                    "position",
                    "orientation"
                  ]
                },
                "points": {
                  "type": "array",
                  "items": {
                    "title": "foxglove.Point3",
                    "description": "A point representing a position in 3D space",
                    "type": "object",
                    "properties": {
                      "x": {
                        "type": "number",
                        "description": "x coordinate position"
                      },
                      "y": {
                        "type": "number",
                        "description": "y coordinate position"
                      },
                      "z": {
                        "type": "number",
                        "description": "z coordinate position"
                      }
                    },
                    "required": [
                      "x",
                      "y",
                      "z"
                    ]
                  },
                  "description": "Vertices to use for triangles, interpreted as a list of triples (0-1-2, 3-4-5, ...)"
                },
                "color": {
                  "title": "foxglove.Color",
                  "description": "Solid color to use for the whole shape. Ignored if `colors` is non-empty.",
                  "type": "object",
                  "properties": {
                    "r": {
                      "type": "number",
                      "description": "Red value between 0 and 1"
                    },
                    "g": {
                      "type": "number",
                      "description": "Green value between 0 and 1"
                    },
                    "b": {
                      "type": "number",
                      "description": "Blue value between 0 and 1"
                    },
                    "a": {
                      "type": "number",
                      "description": "Alpha value between 0 and 1"
                    }
                  },
                  "required": [
                    "r",
                    "g",
                    "b",
                    "a"
                  ]
                },
                "colors": {
                  "type": "array",
                  "items": {
                    "title": "foxglove.Color",
                    "description": "A color in RGBA format",
                    "type": "object",
                    "properties": {
                      "r": {
                        "type": "number",
                        "description": "Red value between 0 and 1"
                      },
                      "g": {
                        "type": "number",
                        "description": "Green value between 0 and 1"
                      },
                      "b": {
                        "type": "number",
                        "description": "Blue value between 0 and 1"
                      },
                      "a": {
                        "type": "number",
                        "description": "Alpha value between 0 and 1"
                      }
                    },
                    "required": [
                      "r",
                      "g",
                      "b",
                      "a"
                    ]
                  },
                  "description": "Per-vertex colors (if specified, must have the same length as `points`)."
                },
                "indices": {
                  "type": "array",
                  "items": {
                    "type": "integer",
                    "minimum": 0
                  },
                  "description": "Indices into the `points` and `colors` attribute arrays, which can be used to avoid duplicating attribute data.\n\nIf omitted or empty, indexing will not be used. This default behavior is equivalent to specifying [0, 1, ..., N-1] for the indices (where N is the number of `points` provided)."
                }
              },
              "required": [
                "pose",
                "points",
                "color",
                "colors",
                "indices"
              ]
            },
            "description": "Triangle list primitives"
          },
          "texts": {
            "type": "array",
            "items": {
              "title": "foxglove.TextPrimitive",
              "description": "A primitive representing a text label",
              "type": "object",
              "properties": {
                "pose": {
                  "title": "foxglove.Pose",
                  "description": "Position of the center of the text box and orientation of the text. Identity orientation means the text is oriented in the xy-plane and flows from -x to +x.",
                  "type": "object",
                  "properties": {
                    "position": {
                      "title": "foxglove.Vector3",
                      "description": "Point denoting position in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x component"
                        },
                        "y": {
                          "type": "number",
                          "description": "y component"
                        },
                        "z": {
                          "type": "number",
                          "description": "z component"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z"
                      ]
                    },
                    "orientation": {
                      "title": "foxglove.Quaternion",
                      "description": "Quaternion denoting orientation in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x value"
                        },
                        "y": {
                          "type": "number",
                          "description": "y value"
                        },
                        "z": {
                          "type": "number",
                          "description": "z value"
                        },
                        "w": {
                          "type": "number",
                          "description": "w value"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z",
                        "w"
                      ]
                    }
                  },
                  "required": [
                    "position",
                    "orientation"
                  ]
                },
                "billboard": {
                  "type": "boolean",
                  "description": "Whether the text should respect `pose.orientation` (false) or always face the camera (true)"
                },
                "font_size": {
                  "type": "number",
                  "description": "Font size (height of one line of text)"
                },
                "scale_invariant": {
                  "type": "boolean",
                  "description": "Indicates whether `font_size` is a fixed size in screen pixels (true), or specified in world coordinates and scales with distance from the camera (false)"
                },
                "color": {
                  "title": "foxglove.Color",
                  "description": "Color of the text",
                  "type": "object",
                  "properties": {
                    "r": {
                      "type": "number",
                      "description": "Red value between 0 and 1"
                    },
                    "g": {
                      "type": "number",
                      "description": "Green value between 0 and 1"
                    },
                    "b": {
                      "type": "number",
                      "description": "Blue value between 0 and 1"
                    },
                    "a": {
                      "type": "number",
                      "description": "Alpha value between 0 and 1"
                    }
                  },
                  "required": [
                    "r",
                    "g",
                    "b",
                    "a"
                  ]
                },
                "text": {
                  "type": "string",
                  "description": "Text"
                }
              },
              "required": [
                "pose",
                "billboard",
                "font_size",
                "scale_invariant",
                "color",
                "text"
              ]
            },
            "description": "Text primitives"
          },
          "models": {
            "type": "array",
            "items": {
              "title": "foxglove.ModelPrimitive",
              "description": "A primitive representing a 3D model file loaded from an external URL or embedded data",
              "type": "object",
              "properties": {
                "pose": {
                  "title": "foxglove.Pose",
                  "description": "Origin of model relative to reference frame",
                  "type": "object",
                  "properties": {
                    "position": {
                      "title": "foxglove.Vector3",
                      "description": "Point denoting position in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x component"
                        },
                        "y": {
                          "type": "number",
                          "description": "y component"
                        },
                        "z": {
                          "type": "number",
                          "description": "z component"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z"
                      ]
                    },
                    "orientation": {
                      "title": "foxglove.Quaternion",
                      "description": "Quaternion denoting orientation in 3D space",
                      "type": "object",
                      "properties": {
                        "x": {
                          "type": "number",
                          "description": "x value"
                        },
                        "y": {
                          "type": "number",
                          "description": "y value"
                        },
                        "z": {
                          "type": "number",
                          "description": "z value"
                        },
                        "w": {
                          "type": "number",
                          "description": "w value"
                        }
                      },
                      "required": [
                        "x",
                        "y",
                        "z",
                        "w"
                      ]
                    }
                  },
                  "required": [
                    "position",
                    "orientation"
                  ]
                },
                "scale": {
                  "title": "foxglove.Vector3",
                  "description": "Scale factor to apply to the model along each axis",
                  "type": "object",
                  "properties": {
                    "x": {
                      "type": "number",
                      "description": "x component"
                    },
                    "y": {
                      "type": "number",
                      "description": "y component"
                    },
                    "z": {
                      "type": "number",
                      "description": "z component"
                    }
                  },
                  "required": [
                    "x",
                    "y",
                    "z"
                  ]
                },
                "color": {
                  "title": "foxglove.Color",
                  "description": "Solid color to use for the whole model if `override_color` is true.",
                  "type": "object",
                  "properties": {
                    "r": {
                      "type": "number",
                      "description": "Red value between 0 and 1"
                    },
                    "g": {
                      "type": "number",
                      "description": "Green value between 0 and 1"
                    },
                    "b": {
                      "type": "number",
                      "description": "Blue value between 0 and 1"
                    },
                    "a": {
                      "type": "number",
                      "description": "Alpha value between 0 and 1"
                    }
                  },
                  "required": [
                    "r",
                    "g",
                    "b",
                    "a"
                  ]
                },
                "override_color": {
                  "type": "boolean",
                  "description": "Whether to use the color specified in `color` instead of any materials embedded in the original model."
                },
                "url": {
                  "type": "string",
                  "description": "URL pointing to model file. One of `url` or `data` should be non-empty."
                },
                "media_type": {
                  "type": "string",
                  "description": "[Media type](https://developer.mozilla.org/en-US/docs/Web/HTTP/Basics_of_HTTP/MIME_types) of embedded model (e.g. `model/gltf-binary`). Required if `data` is provided instead of `url`. Overrides the inferred media type if `url` is provided."
                },
                "data": {
                  "type": "string",
                  "contentEncoding": "base64",
                  "description": "Embedded model. One of `url` or `data` should be non-empty. If `data` is non-empty, `media_type` must be set to indicate the type of the data."
                }
              },
              "required": [
                "pose",
                "scale",
                "color",
                "override_color",
                "url",
                "media_type",
                "data"
              ]
            },
            "description": "Model primitives"
          }
        },
        "required": [
          "timestamp",
          "frame_id",
          "id",
          "lifetime",
          "frame_locked",
          "metadata",
          "arrows",
          "cubes",
          "spheres",
          "cylinders",
          "lines",
          "triangles",
          "texts",
          "models"
        ]
      },
      "description": "Scene entities to add or replace"
    }
  },
  "required": [
    "deletions",
    "entities"
  ]
}
'''
