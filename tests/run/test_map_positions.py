"""Positions in metres on a map world ({metres: [x, y]}, or ${metres:X,Y} over a cell an earlier config gives): the
cell under the point by the map's origin, resolution and world.map_cell, what `riskplan check` prints for it, and
one line for a point off the map, on an obstacle or unknown space, or without a map.

The map is made here: 40 x 30 pixels of 0.1 m from the origin (-2.0, 1.5), read at world.map_cell=2 as 20 x 15
cells of 0.2 m. It has an enclosed room, a block of unknown space, a wall with a way round it, and a mask."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from support import TINY, bad_input, setup_of
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.engine.world import Frame

FREE, OCCUPIED, UNKNOWN = 254, 0, 205
ROOM = (12, 18, 8, 14)  # x0, x1, y0, y1 of the enclosed room's walls (cells)
WALL_X, WALL_TOP = 8, 9  # a wall on x = 8 from y = 0 to 9: the way east goes round its top
UNKNOWN_CELLS = (0, 3, 11, 14)  # x0, x1, y0, y1 of the unknown block
MASK = (4, 7, 0, 3)  # x0, x1, y0, y1 of the watched cells


def write_pgm(path: Path, cells: np.ndarray) -> None:
    """A P5 PGM of a (W, H) array of cell values, each cell 2 x 2 pixels, row 0 the top."""
    pixels = np.kron(cells, np.ones((2, 2), dtype=np.uint8)).T[::-1]
    path.write_bytes(f"P5\n{pixels.shape[1]} {pixels.shape[0]}\n255\n".encode() + pixels.tobytes())


@pytest.fixture
def room_map(tmp_path) -> Path:
    cells = np.full((20, 15), FREE, dtype=np.uint8)
    x0, x1, y0, y1 = ROOM
    cells[x0 : x1 + 1, [y0, y1]] = OCCUPIED
    cells[[x0, x1], y0 : y1 + 1] = OCCUPIED
    cells[WALL_X, : WALL_TOP + 1] = OCCUPIED
    ux0, ux1, uy0, uy1 = UNKNOWN_CELLS
    cells[ux0 : ux1 + 1, uy0 : uy1 + 1] = UNKNOWN
    write_pgm(tmp_path / "room.pgm", cells)
    mask = np.full((20, 15), 255, dtype=np.uint8)
    mx0, mx1, my0, my1 = MASK
    mask[mx0 : mx1 + 1, my0 : my1 + 1] = 0
    write_pgm(tmp_path / "watched.pgm", mask)
    (tmp_path / "room.yaml").write_text(
        "image: room.pgm\nresolution: 0.1\norigin: [-2.0, 1.5, 0.0]\nnegate: 0\noccupied_thresh: 0.65\n"
        "free_thresh: 0.196\n"
    )
    return tmp_path / "room.yaml"


def on_map(path: Path, start: str = "[1,1]", a: str = "[6,4]", b: str = "[10,12]", *more: str) -> list[str]:
    """Overrides of a world on the room map: the start, two sources (positions as given) and the watched mask."""
    sources = f"world.sources=[{{name:a,position:{a},reward:1}},{{name:b,position:{b},reward:2}}]"
    regions = "world.regions=[{name:watched,mask:watched.pgm,risky:true,reward:-1}]"
    return [*TINY, f"world.map={path}", "world.map_cell=2", f"world.start={start}", sources, regions, *more]


def xy(world, cell: int) -> tuple[int, int]:
    return tuple(int(v) for v in world.xy(cell))


def test_a_point_in_metres_is_the_cell_under_it(room_map):
    # x: (-0.75 + 2.0) / 0.1 = pixel 12.5 -> 12 -> cell 6; y: (2.35 - 1.5) / 0.1 = pixel 8.5 -> 8 -> cell 4
    world = setup_of(*on_map(room_map, "${metres:-1.75,1.75}", "{metres:[-0.75,2.35]}")).world
    assert xy(world, world.source_cells[0]) == (6, 4)
    assert xy(world, world.starts[0]) == (1, 1)  # (0.25 / 0.1 -> 2 -> 1, 0.25 / 0.1 -> 2 -> 1)
    assert [(p.key, p.metres, p.cells) for p in world.placements] == [
        ("world.start", (-1.75, 1.75), (1, 1)),
        ("world.sources.0.position", (-0.75, 2.35), (6, 4)),
    ]
    # the mask's cells and the map's obstacles are where the test drew them
    watched = world.region_of.reshape(world.width, world.height) == 0
    assert {(int(x), int(y)) for x, y in zip(*np.nonzero(watched))} == {
        (x, y) for x in range(MASK[0], MASK[1] + 1) for y in range(MASK[2], MASK[3] + 1)
    }
    assert world.obstacle.reshape(20, 15)[ROOM[0], ROOM[2]] and world.obstacle.reshape(20, 15)[0, 14]


def test_team_starts_and_a_rect_in_metres(room_map):
    # team.starts as a whole list takes the mapping form; a rect's two corners in any order give its cells
    starts = "team.starts=[{metres:[-1.75,1.75]},{metres:[-0.15,4.0]},[3,3]]"
    rect = "world.regions=[{name:lobby,rect:{metres:[0.1,3.1,-1.9,1.6]},reward:1}]"
    world = setup_of(*on_map(room_map), "team.robots=3", starts, rect).world
    assert [xy(world, c) for c in world.starts] == [(1, 1), (9, 12), (3, 3)]
    lobby = world.region_of.reshape(world.width, world.height) == 0
    # x -1.9 -> pixel 1 -> cell 0, 0.1 -> pixel 21 -> cell 10; y 1.6 -> pixel 1 -> cell 0, 3.1 -> pixel 16 -> cell 8
    assert lobby[0:11, 0:9].all() and lobby.sum() == 11 * 9
    assert world.placements[-1].cells == (0, 0, 10, 8)
    # a corner off the map is one line naming the nearest cell on the map (a rect's corner may be an obstacle)
    err = bad_input(*on_map(room_map), "world.regions=[{name:lobby,rect:{metres:[-2.5,1.6,0.1,3.1]},reward:1}]")
    assert err.where == "world.regions.0.rect"
    assert "{metres: [-2.5, 1.6]} is off the map: it falls in cell (-3, 0)" in err.problem
    assert "the nearest cell on the map is (0, 0), {metres: [-1.9, 1.6]} at its centre" in err.problem


def test_frame_follows_origin_resolution_map_cell_and_yaw():
    # docs/maps.md's example: a depot map of 0.05 m pixels at world.map_cell=10, its origin at (-10, -5)
    frame = Frame(resolution=0.05, cell=10, origin=(-10.0, -5.0, 0.0), pixels=(604, 307))
    assert frame.pixel_of(-9.97, -4.98) == (0, 0)
    assert frame.pixel_of(-10.01, -4.98) == (-1, 0)  # west of the origin: off the map
    assert frame.pixel_of(2.33, -1.23) == (246, 75)  # 12.33 / 0.05 = 246.6, 3.77 / 0.05 = 75.4: cell (24, 7)
    assert frame.centre(24, 7) == pytest.approx((2.25, -1.25))
    # on a pixel's edge: the pixel beyond it, though -10 + 0.1 and 0.1 / 0.05 round below the edge in floats
    assert frame.pixel_of(-9.9, -4.9) == (2, 2) and frame.pixel_of(-9.95, -5.0) == (1, 0)
    # a quarter turn: the map's x axis points along the frame's y
    turned = Frame(resolution=0.5, cell=1, origin=(1.0, 2.0, math.pi / 2), pixels=(4, 4))
    assert turned.pixel_of(0.2, 3.3) == (2, 1)  # u = y - 2 = 1.3, v = -(x - 1) = 0.8
    assert turned.centre(2, 1) == pytest.approx((0.25, 3.25))
    for x in range(4):
        for y in range(4):
            px, py = turned.pixel_of(*turned.centre(x, y))
            assert (px // turned.cell, py // turned.cell) == (x, y)


@pytest.mark.parametrize(
    "start, words",
    [
        # off the map, east: pixel 60 -> cell 30; the nearest free cell of row 1 is the map's last column
        ("${metres:4.05,1.75}", "{metres: [4.05, 1.75]} is off the map: it falls in cell (30, 1), off the 20x15 "
         "grid; the nearest free cell is (19, 1), {metres: [1.9, 1.8]} at its centre"),
        # on the room's south wall: the nearest free cell is just below it
        ("${metres:1.05,3.25}", "{metres: [1.05, 3.25]} is cell (15, 8), which is an obstacle (an occupied or "
         "unknown cell of world.map"),
        # in the unknown block (world.map_unknown=obstacle): the nearest free cell is below it
        ("${metres:-1.55,3.95}", "{metres: [-1.55, 3.95]} is cell (2, 12), which is an obstacle"),
    ],
)  # fmt: skip
def test_a_point_off_the_map_or_on_an_obstacle_names_its_cell_and_the_nearest_free_one(room_map, start, words):
    err = bad_input(*on_map(room_map, start))
    assert err.where == "world.start" and words in err.problem
    assert "the nearest free cell is" in err.problem


@pytest.mark.slow  # over half a second (the quick tier stays under a minute)
def test_the_nearest_free_cell_is_the_closest(room_map):
    assert (
        "the nearest free cell is (15, 7), {metres: [1.1, 3]}"
        in bad_input(*on_map(room_map, "${metres:1.05,3.25}")).problem
    )
    assert (
        "the nearest free cell is (2, 10), {metres: [-1.5, 3.6]}"
        in bad_input(*on_map(room_map, "${metres:-1.55,3.95}")).problem
    )


@pytest.mark.parametrize("far", ["1e308", "1e12", "-1e308"])
def test_a_point_too_far_to_count_its_pixels_is_off_the_map(room_map, far):
    """1e308 m is 1e309 pixels, beyond any integer a float turns into: taken as FAR (2**31) pixels, whose cell
    (2**30) the message showed as if it were the point's; it says far off the map instead."""
    err = bad_input(*on_map(room_map, f"${{metres:{far},1.75}}"))
    assert err.where == "world.start"
    assert "is far off the map (beyond 2,147,483,648 pixels), off the 20x15 grid" in err.problem
    assert "falls in cell" not in err.problem and "the nearest free cell is (" in err.problem


@pytest.mark.slow  # composes a dozen configs (near a second)
def test_metres_without_a_map_or_malformed_are_one_line(room_map):
    err = bad_input("world.start=${metres:1,2}")
    assert err.where == "world.start" and "a position in metres needs world.map" in err.problem
    err = bad_input(*on_map(room_map, a="{meters:[1,2]}"))
    assert err.where == "world.sources.0.position"
    assert err.problem.startswith("got {meters: [1, 2]}; ")  # as the config writes it, not Python's {'meters': ...}
    assert "expected [x, y] in cells, or {metres: [x, y]} of finite numbers" in err.problem
    err = bad_input(*on_map(room_map, a="{metres:[1]}"))
    assert "{metres: [x, y]}" in err.problem


def test_a_mapping_over_a_cell_given_earlier_says_how_to_write_it(room_map):
    err = bad_input(*on_map(room_map), "world.start={metres:[0.25,0.25]}")
    assert err.where == "key 'world.start'"
    assert "a mapping cannot replace the list an earlier config gives it" in err.problem
    assert "${metres:X,Y}" in err.problem


def test_the_room_map_from_the_command_line(room_map, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    runner = CliRunner()
    args = on_map(room_map, "${metres:-1.75,1.75}", "{metres:[-0.75,2.35]}", "[10,12]")
    with pytest.warns(UserWarning, match=r"source 1 'b' is reached by 0\.0% of the initial policy's episodes"):
        result = runner.invoke(app, ["check", *args])  # at the horizon's very edge, theta0 never gets there
    assert result.exit_code == 0, result.output
    assert "world.start: {metres: [-1.75, 1.75]} -> cell (1, 1)" in result.output
    assert "world.sources.0.position: {metres: [-0.75, 2.35]} -> cell (6, 4)" in result.output
    # b at (10, 12) is 20 moves away: up the west side of the wall, round its top (x = 8, up to y = 9)
    assert "source 1 'b': 20 moves" in result.output
    # a source inside the enclosed room is bad input: one line, exit 2
    walled = runner.invoke(app, ["check", *on_map(room_map, b="[15,11]")])
    assert walled.exit_code == 2
    assert walled.output.strip().splitlines() == [
        "error: world.sources.1.position: 'b' at (15, 11) is walled off by obstacles: no path from the start (1, 1) "
        "at any world.horizon (now 20); remove obstacles or move the source"
    ]


@pytest.mark.slow  # trains a run through the CLI
def test_a_run_placed_in_metres_reads_back_in_a_process_that_typed_no_config(tmp_path, monkeypatch):
    from omegaconf import OmegaConf

    from riskplan.config.typed import register_metres
    from riskplan.run.results import load_run

    monkeypatch.chdir(tmp_path)
    args = ["train", *TINY, "experiment=floor_plan", "world.start=${metres:0.9,0.9}", "hydra.run.dir=run"]
    assert CliRunner().invoke(app, args).exit_code == 0
    assert "${metres:0.9,0.9}" in (tmp_path / "run" / ".hydra" / "config.yaml").read_text()  # as Hydra saved it
    OmegaConf.clear_resolver("metres")  # as in `riskplan report`, which reads runs without typing a config
    try:
        assert load_run(tmp_path / "run").config["world"]["start"] == {"metres": [0.9, 0.9]}
    finally:
        register_metres()
