"""`riskplan export --to ros2`: runs on a map (nav2_map_server's YAML + PGM, trinary, negate 0) trained, exported
as rosbag2 directories, and read back with rosbags, an independent reader: the topics, their types and counts, the
map's cells (exactly the PGM's occupied pixels), the regions, the sources and the sampled paths."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from support import TINY
from typer.testing import CliRunner

from riskplan import compose, train
from riskplan.cli import app
from riskplan.experiments.ros2_bag import msgdef, topic_name

rosbag2 = pytest.importorskip("rosbags.rosbag2")
typesys = pytest.importorskip("rosbags.typesys")
pytestmark = pytest.mark.slow  # two short runs, then exports

runner = CliRunner()
WIDTH, HEIGHT, RESOLUTION, ORIGIN = 10, 8, 0.25, (-2.0, 1.0, 0.0)
WALL, FREE, UNKNOWN = 0, 254, 205


def floor() -> np.ndarray:
    """A 10 x 8 room as map_saver writes one (row 0 the top): walls round it, an inner wall with a door, one unknown
    pixel."""
    image = np.full((HEIGHT, WIDTH), FREE, dtype=np.uint8)
    image[0, :] = image[-1, :] = image[:, 0] = image[:, -1] = WALL
    image[1:5, 5] = WALL  # the inner wall at x = 5, y = 3..6; its door is y = 1..2
    image[2, 2] = UNKNOWN  # (2, 5)
    return image


def occupied_cells(image: np.ndarray) -> set[tuple[int, int]]:
    rows, cols = np.nonzero(image == WALL)
    return {(int(c), HEIGHT - 1 - int(r)) for r, c in zip(rows, cols)}


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """One robot and a team of two trained on the map, exported to --out."""
    root = tmp_path_factory.mktemp("ros2")
    maps = root / "maps"
    maps.mkdir()
    image = floor()
    (maps / "room.pgm").write_bytes(f"P5\n{WIDTH} {HEIGHT}\n255\n".encode() + image.tobytes())
    mask = np.full((HEIGHT, WIDTH), 255, dtype=np.uint8)
    mask[1:4, 6:9] = 0  # the corridor: x 6..8, y 4..6
    (maps / "corridor.pgm").write_bytes(f"P5\n{WIDTH} {HEIGHT}\n255\n".encode() + mask.tobytes())
    (maps / "room.yaml").write_text(
        "image: room.pgm\nmode: trinary\nresolution: 0.25\norigin: [-2.0, 1.0, 0.0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"  # 205 (map_saver's unknown) stays unknown
    )
    world = [
        f"world.map={maps / 'room.yaml'}",
        "world.start=[1,1]",
        "world.sources=[{name:safe,position:[3,6],reward:1000},{name:risky,position:[7,5],reward:{normal:[2000,2000]}}]",
        "world.regions=[{name:the corridor,mask:corridor.pgm,risky:true,reward:{normal:[0,100]}},"
        "{name:floor,rect:[0,0,9,7],reward:{uniform:[0,100]}}]",
    ]
    runs = root / "runs"
    train(compose([*TINY, "train.paths=3", *world]), runs / "one")
    train(compose([*TINY, "train.paths=2", "experiment=paper_team", "team.robots=2", *world]), runs / "team")
    out = root / "bags"
    done = runner.invoke(app, ["export", str(runs), "--to", "ros2", "--out", str(out)])
    assert done.exit_code == 0, done.output
    return runs, out, image, done.output


def read_bag(directory: Path):
    """{topic: (type, [(log time, message)])} of a bag, read by rosbags."""
    store = typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
    topics: dict[str, tuple[str, list]] = {}
    with rosbag2.Reader(directory) as reader:
        for connection in reader.connections:
            topics[connection.topic] = (connection.msgtype, [])
        for connection, time, raw in reader.messages(reader.connections):
            topics[connection.topic][1].append((time, store.deserialize_cdr(raw, connection.msgtype)))
    return topics


def bag_of(out: Path, name: str) -> Path:
    (found,) = [p for p in out.iterdir() if p.name.startswith(f"{name}-")]
    return found


def test_the_bag_holds_the_topics_with_their_types_and_counts(bags):
    runs, out, _, output = bags
    assert "2 run(s) to ros2: 2 exported" in output
    single = read_bag(bag_of(out, "one"))
    first = pd.read_parquet(runs / "one" / "trajectories.parquet")
    final = first.loc[(first.policy == "final") & (first.robot == 0)]
    steps = int((final.episode == final.episode.min()).sum())
    assert {topic: (kind, len(messages)) for topic, (kind, messages) in single.items()} == {
        "/map": ("nav_msgs/msg/OccupancyGrid", 1),
        "/regions/the_corridor": ("nav_msgs/msg/OccupancyGrid", 1),
        "/regions/floor": ("nav_msgs/msg/OccupancyGrid", 1),
        "/sources": ("visualization_msgs/msg/MarkerArray", 1),
        "/robot_0/path": ("nav_msgs/msg/Path", 3),
        "/robot_0/pose": ("geometry_msgs/msg/PoseStamped", steps),
    }
    team = read_bag(bag_of(out, "team"))
    assert {t for t in team if t.startswith("/robot_")} == {
        "/robot_0/path",
        "/robot_0/pose",
        "/robot_1/path",
        "/robot_1/pose",
    }
    assert len(team["/robot_1/path"][1]) == 2


def test_the_map_is_exactly_the_occupied_pixels_at_the_map_resolution_and_origin(bags):
    _, out, image, _ = bags
    ((_, grid),) = read_bag(bag_of(out, "one"))["/map"][1]
    assert grid.header.frame_id == "map"
    assert (grid.info.width, grid.info.height) == (WIDTH, HEIGHT)
    assert math.isclose(grid.info.resolution, RESOLUTION)
    assert (grid.info.origin.position.x, grid.info.origin.position.y) == ORIGIN[:2]
    cells = np.asarray(grid.data).reshape(HEIGHT, WIDTH)  # row y, column x, from the lower-left corner
    occupied = {(int(x), int(y)) for y, x in zip(*np.nonzero(cells == 100))}
    assert occupied == occupied_cells(image) | {(2, 5)}  # the walls, and the unknown pixel as an obstacle
    assert set(np.unique(cells)) == {0, 100}


def test_regions_sources_and_paths_are_in_the_map_frame(bags):
    runs, out, _, _ = bags
    bag = read_bag(bag_of(out, "one"))
    ((_, corridor),) = bag["/regions/the_corridor"][1]
    inside = np.asarray(corridor.data).reshape(HEIGHT, WIDTH)
    assert {(int(x), int(y)) for y, x in zip(*np.nonzero(inside == 100))} == {
        (x, y) for x in range(6, 9) for y in range(4, 7)
    }

    def centre(x: int, y: int) -> tuple[float, float]:
        return ORIGIN[0] + (x + 0.5) * RESOLUTION, ORIGIN[1] + (y + 0.5) * RESOLUTION

    ((_, sources),) = bag["/sources"][1]
    spheres = [m for m in sources.markers if m.ns == "sources"]
    assert [(m.pose.position.x, m.pose.position.y) for m in spheres] == [centre(3, 6), centre(7, 5)]
    assert [m.text for m in sources.markers if m.ns == "source_names"] == ["safe", "risky"]

    table = pd.read_parquet(runs / "one" / "trajectories.parquet")
    final = table.loc[(table.policy == "final") & (table.robot == 0)].sort_values(["episode", "step"])
    first = final.loc[final.episode == final.episode.min()]
    poses = bag["/robot_0/pose"][1]
    assert [(m.pose.position.x, m.pose.position.y) for _, m in poses] == [
        centre(x, y) for x, y in zip(first.x, first.y)
    ]
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, m in poses]
    assert stamps == [t for t, _ in poses] and all(a < b for a, b in itertools.pairwise(stamps))
    paths = [m for _, m in bag["/robot_0/path"][1]]
    for (_, rows), path in zip(final.groupby("episode"), paths):
        assert [(p.pose.position.x, p.pose.position.y) for p in path.poses] == [
            centre(x, y) for x, y in zip(rows.x, rows.y)
        ]
        assert all(p.header.frame_id == "map" for p in path.poses)


def test_exporting_again_leaves_the_bags_alone_and_the_default_is_inside_each_run(bags):
    runs, out, _, _ = bags
    again = runner.invoke(app, ["export", str(runs / "one"), "--to", "ros2", "--out", str(out)])
    assert again.exit_code == 0 and "1 unchanged" in again.output
    inside = runner.invoke(app, ["export", str(runs / "one"), "--to", "ros2"])
    assert inside.exit_code == 0, inside.output
    assert set(read_bag(runs / "one" / "rosbag2")) == set(read_bag(bag_of(out, "one")))


def test_a_bag_and_a_tensorboard_log_never_replace_each_other(bags, tmp_path):
    """Both targets name a run's folder <run>-<hash>: pointed at the same directory, neither replaces the other's
    (the run is skipped, with the reason, and the other's folder left whole; with no run exported, exit code 1); a
    file URI names the TensorBoard directory itself."""
    runs, *_ = bags
    shared = tmp_path / "shared"
    assert runner.invoke(app, ["export", str(runs / "one"), "--to", "ros2", "--out", str(shared)]).exit_code == 0
    bag = bag_of(shared, "one")
    before = {p: p.read_bytes() for p in bag.rglob("*") if p.is_file()}
    done = runner.invoke(app, ["export", str(runs / "one"), "--to", "tensorboard", "--uri", shared.as_uri()])
    assert "is not a TensorBoard log of riskplan export's" in done.output, done.output
    assert done.exit_code == 1  # nothing exported is no success
    assert done.stderr.endswith("error: no run was exported: each of the 1 was skipped (see above)\n")
    assert {p: p.read_bytes() for p in bag.rglob("*") if p.is_file()} == before
    assert not (Path.cwd() / "file:").exists()

    logs = tmp_path / "logs"
    assert runner.invoke(app, ["export", str(runs / "one"), "--to", "tensorboard", "--uri", str(logs)]).exit_code == 0
    (log,) = [p for p in logs.iterdir() if p.is_dir()]
    before = {p: p.read_bytes() for p in log.rglob("*") if p.is_file()}
    done = runner.invoke(app, ["export", str(runs / "one"), "--to", "ros2", "--out", str(logs)])
    assert "1 skipped" in done.output and "is not a ROS 2 bag of riskplan export's" in done.output, done.output
    assert done.exit_code == 1
    assert {p: p.read_bytes() for p in log.rglob("*") if p.is_file()} == before


def test_out_belongs_to_ros2_and_uri_does_not(bags, tmp_path):
    runs, *_ = bags
    done = runner.invoke(app, ["export", str(runs), "--to", "tensorboard", "--out", str(tmp_path)])
    assert done.exit_code == 2 and "--out: only --to ros2 writes into --out" in done.stderr
    done = runner.invoke(app, ["export", str(runs), "--to", "ros2", "--uri", str(tmp_path)])
    assert done.exit_code == 2 and "--uri: --to ros2 writes its bags into --out DIR" in done.stderr


def test_a_missing_extra_is_one_line_naming_the_install(bags, monkeypatch, tmp_path):
    runs, *_ = bags
    monkeypatch.setitem(__import__("sys").modules, "mcap_ros2", None)
    done = runner.invoke(app, ["export", str(runs), "--to", "ros2", "--out", str(tmp_path / "x")])
    assert done.exit_code == 2
    assert "pip install 'riskplan[ros2]'" in done.stderr and not (tmp_path / "x").exists()


def test_schemas_list_each_type_they_use_once_and_names_become_topic_tokens():
    text = msgdef("nav_msgs/msg/Path")
    assert text.startswith("std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses\n")
    assert [line for line in text.splitlines() if line.startswith("MSG: ")] == [
        "MSG: std_msgs/Header",
        "MSG: builtin_interfaces/Time",
        "MSG: geometry_msgs/PoseStamped",
        "MSG: geometry_msgs/Pose",
        "MSG: geometry_msgs/Point",
        "MSG: geometry_msgs/Quaternion",
    ]
    taken: set[str] = set()
    assert [topic_name(n, taken) for n in ("risky", "risky", "2nd room", "Quelle ☢", "")] == [
        "risky",
        "risky_1",
        "r_2nd_room",
        "Quelle",
        "region",
    ]
