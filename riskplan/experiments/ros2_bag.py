"""`riskplan export --to ros2`: one rosbag2 directory per run, `metadata.yaml` and an MCAP file of CDR messages with
`ros2msg` schemas, written by mcap-ros2-support (the `ros2` extra) without a ROS installation.

    write_run(run_dir, config, trajectories, out_dir=None, start=0.0, fingerprint="") -> (action, bag directory)

Topics, all in the frame `map` (cell (x, y) at its centre: the map's origin, plus (x + 1/2, y + 1/2) cells of
resolution x world.map_cell metres, turned by the origin's yaw; 1 m cells from (0, 0) without a map):

- `/map` (nav_msgs/msg/OccupancyGrid): the world's cells, 100 for an obstacle and 0 for a free cell, at the map's
  resolution (x world.map_cell) and origin;
- `/regions/<name>` (nav_msgs/msg/OccupancyGrid): 100 inside the region (the cells it wins, first match first),
  0 elsewhere; a name is made a valid ROS name (other characters as `_`);
- `/sources` (visualization_msgs/msg/MarkerArray): a sphere and a label per source, at its first cell;
- `/robot_<i>/path` (nav_msgs/msg/Path): one message per sampled episode of robot i's final policy
  (the run's trajectories table: trajectories.parquet, or rebuilt from run.mcap), the k-th pose stamped k steps
  after the bag's start;
- `/robot_<i>/pose` (geometry_msgs/msg/PoseStamped): along the first of those episodes, one per step, facing
  the way it moves.

Time: the bag starts at the run's start (its .hydra/config.yaml's time) and a step takes STEP_NS; the map, the
regions and the sources come first, latched (transient local, as map_server publishes /map), and the paths follow
one per step. Written beside the target and renamed into place, with a marker (riskplan-export.json) holding the
run's fingerprint: exporting it again leaves an unchanged bag alone and replaces a changed one.
"""

from __future__ import annotations

import hashlib
import math
import re
from pathlib import Path

import numpy as np
import pandas as pd
import yaml
from mcap.writer import CompressionType, Writer

from riskplan.run.build import build_setup
from riskplan.run.maps import geometry
from riskplan.util.errors import BadInput
from riskplan.util.names import unique
from riskplan.util.paths import is_marked, replace_marked_dir, write_atomic

BAG = "rosbag2"  # the bag's directory inside a run directory when no --out is given
FOREIGN = "exists and is not a ROS 2 bag of riskplan export's; move it away or give another --out"
FRAME = "map"
STEP_NS = 500_000_000  # one move of an episode: half a second of the bag's time
OCCUPIED, FREE = 100, 0
PATH_COLUMNS = ("policy", "robot", "episode", "step", "x", "y")  # what the paths are read from
INFINITE = {"sec": 9223372036, "nsec": 854775807}  # rosbag2's "no deadline / lifespan"

# The ROS 2 message definitions (Humble's; Jazzy's only add a Marker constant), each type's own fields: a schema is
# a type's fields followed by each type it uses, as rosbag2 writes them.
TYPES = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec",
    "builtin_interfaces/Duration": "int32 sec\nuint32 nanosec",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "std_msgs/ColorRGBA": "float32 r\nfloat32 g\nfloat32 b\nfloat32 a",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\ngeometry_msgs/Pose pose",
    "nav_msgs/MapMetaData": (
        "builtin_interfaces/Time map_load_time\nfloat32 resolution\nuint32 width\nuint32 height\n"
        "geometry_msgs/Pose origin"
    ),
    "nav_msgs/OccupancyGrid": "std_msgs/Header header\nnav_msgs/MapMetaData info\nint8[] data",
    "nav_msgs/Path": "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses",
    "sensor_msgs/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data",
    "visualization_msgs/UVCoordinate": "float32 u\nfloat32 v",
    "visualization_msgs/MeshFile": "string filename\nuint8[] data",
    "visualization_msgs/Marker": (
        "int32 ARROW=0\nint32 CUBE=1\nint32 SPHERE=2\nint32 CYLINDER=3\nint32 LINE_STRIP=4\nint32 LINE_LIST=5\n"
        "int32 CUBE_LIST=6\nint32 SPHERE_LIST=7\nint32 POINTS=8\nint32 TEXT_VIEW_FACING=9\nint32 MESH_RESOURCE=10\n"
        "int32 TRIANGLE_LIST=11\nint32 ADD=0\nint32 MODIFY=0\nint32 DELETE=2\nint32 DELETEALL=3\n"
        "std_msgs/Header header\nstring ns\nint32 id\nint32 type\nint32 action\ngeometry_msgs/Pose pose\n"
        "geometry_msgs/Vector3 scale\nstd_msgs/ColorRGBA color\nbuiltin_interfaces/Duration lifetime\n"
        "bool frame_locked\ngeometry_msgs/Point[] points\nstd_msgs/ColorRGBA[] colors\nstring texture_resource\n"
        "sensor_msgs/CompressedImage texture\nvisualization_msgs/UVCoordinate[] uv_coordinates\nstring text\n"
        "string mesh_resource\nvisualization_msgs/MeshFile mesh_file\nbool mesh_use_embedded_materials"
    ),
    "visualization_msgs/MarkerArray": "visualization_msgs/Marker[] markers",
}
GRID, MARKERS, PATH, POSE = (
    "nav_msgs/msg/OccupancyGrid",
    "visualization_msgs/msg/MarkerArray",
    "nav_msgs/msg/Path",
    "geometry_msgs/msg/PoseStamped",
)
SPHERE, TEXT = 2, 9


def msgdef(name: str) -> str:
    """The ros2msg schema of `pkg/msg/Type`: its fields, then each type it uses (depth first, once each)."""
    short = name.replace("/msg/", "/")
    order: list[str] = []

    def visit(typ: str) -> None:
        for line in TYPES[typ].splitlines():
            field = line.split()[0].removesuffix("[]")
            if "/" in field and field not in order:
                order.append(field)
                visit(field)

    visit(short)
    parts = [TYPES[short]] + [f"{'=' * 80}\nMSG: {typ}\n{TYPES[typ]}" for typ in order]
    return "\n".join(parts) + "\n"


def topic_name(name: str, taken: set[str]) -> str:
    """A region's name as one valid ROS topic token (letters, digits and `_`, not starting with a digit), unique."""
    token = re.sub(r"[^A-Za-z0-9_]", "_", name).strip("_") or "region"
    token = re.sub(r"_+", "_", token)
    return unique(f"r_{token}" if token[0].isdigit() else token, taken)


def bag_dir(run_dir: Path, out_dir: Path | None) -> Path:
    """Where a run's bag goes: `<run>/rosbag2`, or `<out>/<run name>-<hash of its path>` with --out."""
    if out_dir is None:
        return run_dir / BAG
    safe = re.sub(r"[^A-Za-z0-9._=,+-]", "_", run_dir.name).strip(".") or "run"
    digest = hashlib.sha256(str(run_dir).encode()).hexdigest()[:8]
    return out_dir / f"{safe[:100]}-{digest}"


def write_run(
    run_dir: Path,
    config: dict,
    trajectories: pd.DataFrame,
    out_dir: Path | None = None,
    start: float = 0.0,
    fingerprint: str = "",
) -> tuple[str, Path]:
    """Write one run's bag: ("exported" | "replaced" | "unchanged", its directory). `trajectories`: the run's table
    as loaded (riskplan.run.results.load_run). BadInput when its world cannot be rebuilt from its config (a map file
    moved) or the table lacks a column, before anything is written."""
    target = bag_dir(run_dir, out_dir)
    marker = {"run_dir": str(run_dir), "fingerprint": fingerprint, "format": "rosbag2 mcap", "version": 1}
    if is_marked(target, marker, lambda: BadInput(str(target), FOREIGN)):
        return "unchanged", target
    messages = run_messages(config, trajectories, round(start * 1e9))
    status = replace_marked_dir(target, marker, lambda tmp: write_bag(tmp, target.name, messages))
    return status, target


Message = tuple[str, str, int, dict]  # (topic, type, log time in ns, the message as a dict)


def run_messages(config: dict, trajectories: pd.DataFrame, t0: int) -> list[Message]:
    """Every message of a run's bag, in time order (stable: the static topics first)."""
    setup = build_setup(config)
    world = setup.world
    size, origin = geometry(setup.params.world)
    place = _placer(size, origin)
    stamp = _stamp(t0)
    grid = grid_message(world.obstacle.reshape(world.width, world.height), size, origin, stamp)
    messages: list[Message] = [("/map", GRID, t0, grid)]
    taken: set[str] = set()
    for r, name in enumerate(world.region_names):
        inside = (world.region_of == r).reshape(world.width, world.height)
        grid = grid_message(inside, size, origin, stamp)
        messages.append((f"/regions/{topic_name(name, taken)}", GRID, t0, grid))
    messages.append(("/sources", MARKERS, t0, source_markers(world, place, stamp, size)))
    paths = _final_paths(trajectories)
    for robot, episodes in paths.items():
        for e, cells in enumerate(episodes):
            poses = [_pose_stamped(place(cells, k), _stamp(t0 + k * STEP_NS)) for k in range(len(cells))]
            messages.append(
                (f"/robot_{robot}/path", PATH, t0 + e * STEP_NS, {"header": stamp_header(stamp), "poses": poses})
            )
        first = episodes[0] if episodes else []
        for k in range(len(first)):
            time = t0 + k * STEP_NS
            messages.append((f"/robot_{robot}/pose", POSE, time, _pose_stamped(place(first, k), _stamp(time))))
    return sorted(messages, key=lambda m: m[2])


def grid_message(cells: np.ndarray, size: float, origin, stamp: dict) -> dict:
    """An OccupancyGrid of a (width, height) boolean array: 100 where set, 0 elsewhere, row-major from (0, 0)."""
    width, height = cells.shape
    data = np.where(cells.T, OCCUPIED, FREE).astype(np.int8).ravel()  # row j is y = j, column i is x = i
    return {
        "header": stamp_header(stamp),
        "info": {
            "map_load_time": stamp,
            "resolution": float(size),
            "width": int(width),
            "height": int(height),
            "origin": _pose(origin[0], origin[1], origin[2]),
        },
        "data": data.tolist(),
    }


def source_markers(world, place, stamp: dict, size: float) -> dict:
    """A sphere and a text label per source at its first cell."""
    markers = []
    for j, (name, cell) in enumerate(zip(world.source_names, world.source_cells)):
        x, y = divmod(int(cell), world.height)
        pose = place([(x, y)], 0)
        colour = {"r": 1.0, "g": 0.75, "b": 0.0, "a": 1.0}
        markers.append(
            {
                "header": stamp_header(stamp),
                "ns": "sources",
                "id": j,
                "type": SPHERE,
                "action": 0,
                "pose": pose,
                "scale": {"x": size, "y": size, "z": size},
                "color": colour,
                "frame_locked": False,
            }
        )
        label = {**pose, "position": {**pose["position"], "z": size}}
        markers.append(
            {
                "header": stamp_header(stamp),
                "ns": "source_names",
                "id": j,
                "type": TEXT,
                "action": 0,
                "pose": label,
                "scale": {"x": 0.0, "y": 0.0, "z": size},
                "color": {"r": 1.0, "g": 1.0, "b": 1.0, "a": 1.0},
                "text": str(name),
            }
        )
    return {"markers": markers}


def stamp_header(stamp: dict) -> dict:
    return {"stamp": stamp, "frame_id": FRAME}


def _stamp(ns: int) -> dict:
    return {"sec": int(ns // 1_000_000_000), "nanosec": int(ns % 1_000_000_000)}


def _pose(x: float, y: float, yaw: float) -> dict:
    return {
        "position": {"x": float(x), "y": float(y), "z": 0.0},
        "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2.0), "w": math.cos(yaw / 2.0)},
    }


def _pose_stamped(pose: dict, stamp: dict) -> dict:
    return {"header": stamp_header(stamp), "pose": pose}


def _placer(size: float, origin):
    """place(cells, k): the pose in the map frame of the k-th (x, y) cell of a path, facing its next move (its last
    one at the end; the map's x axis if it never moves)."""
    ox, oy, yaw = origin
    cos, sin = math.cos(yaw), math.sin(yaw)

    def point(cell: tuple[int, int]) -> tuple[float, float]:
        u, v = (cell[0] + 0.5) * size, (cell[1] + 0.5) * size
        return ox + cos * u - sin * v, oy + sin * u + cos * v

    def place(cells: list[tuple[int, int]], k: int) -> dict:
        here = point(cells[k])
        ahead = next((j for j in range(k + 1, len(cells)) if cells[j] != cells[k]), None)
        behind = next((j for j in range(k - 1, -1, -1) if cells[j] != cells[k]), None)
        heading = yaw
        if ahead is not None or behind is not None:
            (x0, y0), (x1, y1) = (here, point(cells[ahead])) if ahead is not None else (point(cells[behind]), here)
            heading = math.atan2(y1 - y0, x1 - x0)
        return _pose(here[0], here[1], heading)

    return place


def _final_paths(table: pd.DataFrame) -> dict[int, list[list[tuple[int, int]]]]:
    """Each robot's sampled episodes of its final policy as (x, y) cells, robots 0, 1, ...; BadInput naming the
    columns a table not written by riskplan lacks."""
    missing = [c for c in PATH_COLUMNS if c not in table.columns]
    if missing:
        raise BadInput(
            "trajectories table",
            f"lacks the column(s) {', '.join(missing)}: it was not written by riskplan; remove trajectories.parquet "
            "and the run's tables are rebuilt from run.mcap",
        )
    table = table.loc[(table.policy == "final") & (table.robot >= 0)].sort_values(["robot", "episode", "step"])
    out: dict[int, list[list[tuple[int, int]]]] = {}
    for (robot, _episode), rows in table.groupby(["robot", "episode"], sort=True):
        out.setdefault(int(robot), []).append([(int(x), int(y)) for x, y in zip(rows.x, rows.y)])
    return out


def qos(latched: bool) -> str:
    """offered_qos_profiles as rosbag2 writes them (metadata version 5): reliable, and transient local for the
    static topics so that a player's late subscribers (RViz) get them."""
    return (
        "- history: 1\n  depth: 1\n  reliability: 1\n"
        f"  durability: {1 if latched else 2}\n"
        f"  deadline:\n    sec: {INFINITE['sec']}\n    nsec: {INFINITE['nsec']}\n"
        f"  lifespan:\n    sec: {INFINITE['sec']}\n    nsec: {INFINITE['nsec']}\n"
        "  liveliness: 1\n"
        f"  liveliness_lease_duration:\n    sec: {INFINITE['sec']}\n    nsec: {INFINITE['nsec']}\n"
        "  avoid_ros_namespace_conventions: false"
    )


def write_bag(directory: Path, name: str, messages: list[Message]) -> None:
    """`<name>_0.mcap` and metadata.yaml (rosbag2 version 5, storage mcap) in `directory`. The MCAP file is as
    rosbag2's MCAP storage writes it: profile ros2, ros2msg schemas, CDR messages, each channel's QoS in its
    metadata (the same as metadata.yaml's)."""
    from mcap_ros2._dynamic import serialize_dynamic  # optional: the ros2 extra (its writer's own CDR encoder)

    file = f"{name}_0.mcap"
    counts: dict[str, int] = {}
    types: dict[str, str] = {}
    with open(directory / file, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="riskplan")
        schemas, encoders, channels = {}, {}, {}
        for typ in sorted({m[1] for m in messages}):
            text = msgdef(typ)
            schemas[typ] = writer.register_schema(typ, "ros2msg", text.encode())
            encoders[typ] = serialize_dynamic(typ, text)[typ]
        for topic, typ, time, message in messages:
            if topic not in channels:
                profile = qos(typ in (GRID, MARKERS))
                channels[topic] = writer.register_channel(topic, "cdr", schemas[typ], {"offered_qos_profiles": profile})
                types[topic] = typ
            writer.add_message(channels[topic], time, encoders[typ](message), time, sequence=counts.get(topic, 0))
            counts[topic] = counts.get(topic, 0) + 1
        writer.finish()
    first = min((m[2] for m in messages), default=0)
    last = max((m[2] for m in messages), default=0)
    span = lambda: {"nanoseconds": last - first}  # fresh dicts: the YAML has no anchors and aliases
    begin = lambda: {"nanoseconds_since_epoch": first}
    info = {
        "version": 5,
        "storage_identifier": "mcap",
        "duration": span(),
        "starting_time": begin(),
        "message_count": len(messages),
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": topic,
                    "type": types[topic],
                    "serialization_format": "cdr",
                    "offered_qos_profiles": qos(types[topic] in (GRID, MARKERS)),
                },
                "message_count": count,
            }
            for topic, count in counts.items()
        ],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [file],
        "files": [{"path": file, "starting_time": begin(), "duration": span(), "message_count": len(messages)}],
    }
    text = yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False, default_flow_style=False)
    write_atomic(directory / "metadata.yaml", text)
