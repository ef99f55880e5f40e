"""The world's picture (figures.world_picture; riskplan check --draw): what it shows, checked on the drawn artists
and the rendered pixels, on the paper's world, the shipped floor plan and a map the test makes; the bad --draw paths
and the size of a warehouse-sized map's picture."""

from __future__ import annotations

import io
import subprocess
import sys
import warnings
from pathlib import Path
from types import SimpleNamespace

import matplotlib
import numpy as np
import pytest
from matplotlib.collections import LineCollection
from matplotlib.colors import to_rgb
from matplotlib.patches import PathPatch
from omegaconf import OmegaConf
from PIL import Image
from support import TINY, setup_of
from typer.testing import CliRunner

import riskplan
from riskplan.cli import app
from riskplan.experiments.reporting.collect import collect
from riskplan.experiments.reporting.figures import make_figures
from riskplan.experiments.reporting.figures import world_picture as wp
from riskplan.experiments.reporting.figures.drawing import STYLE, figure_bytes
from riskplan.run.compose import compose

runner = CliRunner()


def beyond(colour: str) -> np.ndarray:
    """A cell's colour greyed, beyond the horizon."""
    return (1 - wp.BEYOND_SHARE) * np.array(to_rgb(colour)) + wp.BEYOND_SHARE * wp.BEYOND_GREY


def drawn(*overrides: str):
    """(picture, figure, its world axes) of TINY plus overrides."""
    picture = wp.picture_of(setup_of(*overrides))
    figure = wp.draw_picture(picture)
    return picture, figure, figure.axes[0]


def cell_colours(ax) -> np.ndarray:
    """The drawn cells' colours, indexed [x, y] (the image artist's array, row 0 the bottom)."""
    return np.asarray(ax.images[0].get_array()).transpose(1, 0, 2)


def pixels_of_cell(figure, ax, x: int, y: int) -> np.ndarray:
    """The rendered RGB pixels inside cell (x, y), a margin left out (the grid's lines)."""
    figure.canvas.draw()
    rgba = np.asarray(figure.canvas.buffer_rgba())[..., :3] / 255.0
    (x0, y0), (x1, y1) = ax.transData.transform([(x - 0.3, y - 0.3), (x + 0.3, y + 0.3)])
    top, bottom = rgba.shape[0] - int(y1), rgba.shape[0] - int(y0)
    return rgba[top:bottom, int(x0) : int(x1)].reshape(-1, 3)


def markers(ax, marker: str) -> list[tuple[float, float]]:
    return [(float(x), float(y)) for line in ax.lines if line.get_marker() == marker for x, y in line.get_xydata()]


def path_lines(ax) -> list[np.ndarray]:
    """The drawn shortest paths: the lines of more than one point."""
    return [line.get_xydata() for line in ax.lines if line.get_linestyle() == "-" and len(line.get_xydata()) > 1]


def outline_length(ax) -> float:
    (lines,) = [c for c in ax.collections if type(c) is LineCollection]
    return float(sum(np.abs(np.diff(np.asarray(s), axis=0)).sum() for s in lines.get_segments()))


def test_paper_world_obstacle_dark_reach_greyed_beyond_the_horizon_start_sources_and_paths():
    picture, figure, ax = drawn("world.obstacles=[[6,2]]")
    colours = cell_colours(ax)
    # K = 20 from (0, 0): every cell but those more than 20 moves away, x + y > 20 (no wall in the way)
    x, y = np.meshgrid(np.arange(12), np.arange(12), indexing="ij")
    risky = y > x
    expected = np.where(risky[..., None], to_rgb(wp.RISKY_REGIONS[0]), to_rgb(wp.SAFE_REGIONS[0]))
    far = x + y > 20
    expected[far] = np.where(risky[far][:, None], beyond(wp.RISKY_REGIONS[0]), beyond(wp.SAFE_REGIONS[0]))
    expected[6, 2] = to_rgb(wp.OBSTACLE)
    assert np.allclose(colours, expected)
    # the reachable set's edge: the 12 x 12 square's 48 (the staircase corner's too), and 4 around the obstacle
    assert outline_length(ax) == 52
    # the obstacle renders dark; a free cell light
    assert np.median(pixels_of_cell(figure, ax, 6, 2)) < 0.3
    assert np.median(pixels_of_cell(figure, ax, 8, 1)) > 0.7
    assert markers(ax, "o") == [(0.0, 0.0)]
    assert markers(ax, "*") == [(9.0, 3.0), (3.0, 9.0)]
    for path, source in zip(path_lines(ax), [(9, 3), (3, 9)]):
        assert tuple(path[0]) == (0, 0) and tuple(path[-1]) == source
        assert len(path) == 13 and (np.abs(np.diff(path, axis=0)).sum(axis=1) == 1).all()
        assert (6, 2) not in {tuple(p) for p in path}
    assert list(picture.moves) == [12, 12]
    risky_patch = [p for p in ax.patches if isinstance(p, PathPatch)]
    assert len(risky_patch) == 1 and risky_patch[0].get_hatch() == "////"
    labels = [t.get_text() for t in figure.legends[0].get_texts()]
    assert "region 'risky' (risky)" in labels and "obstacle" in labels
    assert "1 'safe' (9, 3): 12 moves from (0, 0)" in labels
    assert not ax.child_axes  # no metres without a map


def test_shipped_floor_plan_walls_unknown_outside_start_sources_and_metres():
    picture, figure, ax = drawn("experiment=floor_plan")
    colours = cell_colours(ax)
    classes = picture.cells.classes
    assert tuple(colours[0, 0]) == pytest.approx(to_rgb(wp.UNKNOWN))  # the map's unknown space outside
    layout = picture.world.obstacle.reshape(30, 24)
    walls = layout & (classes == len(picture.cells.colours) - 1)
    assert walls.sum() > 100 and np.allclose(colours[walls], to_rgb(wp.OBSTACLE))
    wall_x, wall_y = np.argwhere(walls)[0]
    assert np.median(pixels_of_cell(figure, ax, int(wall_x), int(wall_y))) < 0.3
    assert markers(ax, "o") == [(3.0, 3.0)]
    assert markers(ax, "*") == [(3.0, 15.0), (15.0, 3.0)]
    for path, source in zip(path_lines(ax), [(3, 15), (15, 3)]):
        assert tuple(path[0]) == (3, 3) and tuple(path[-1]) == source and len(path) == 13
        assert not layout[path[:, 0].astype(int), path[:, 1].astype(int)].any()
    # metres: 0.25 m cells from the origin (0, 0): cell 0's centre at 0.125 m, cell 10's at 2.625 m
    top, right = ax.child_axes
    assert top.get_xlabel() == "x (m, map frame)" and right.get_ylabel() == "y (m, map frame)"
    forward, _ = top._functions
    assert forward(np.array([0.0, 10.0])) == pytest.approx([0.125, 2.625])


@pytest.fixture
def room_map(tmp_path) -> Path:
    """A 40 x 32-pixel map at 0.5 m, origin (-3, 1.5): unknown space above row 8 from the top, a walled building
    below it with an enclosed room (no door) in its right half, and a mask over the building's lower-left corner.
    world.map_cell=2 makes it 20 x 16 cells of 1 m."""
    image = np.full((32, 40), 254, np.uint8)
    image[:8] = 205  # unknown: the top 8 pixel rows, cells y 12-15
    image[8:10], image[-2:], image[8:, :2], image[8:, -2:] = 0, 0, 0, 0  # the building's walls
    image[12:24, 24:36] = 0  # the enclosed room's walls: cells x 12-17, y 4-9 ...
    image[14:22, 26:34] = 254  # ... around its free inside, cells x 13-16, y 5-8
    mask = np.full((32, 40), 255, np.uint8)
    mask[24:30, 2:12] = 0  # cells x 1-5, y 1-3
    for name, pixels in (("room.pgm", image), ("watched.pgm", mask)):
        (tmp_path / name).write_bytes(b"P5\n40 32\n255\n" + pixels.tobytes())
    (tmp_path / "room.yaml").write_text(
        "image: room.pgm\nresolution: 0.5\norigin: [-3.0, 1.5, 0.0]\nnegate: 0\noccupied_thresh: 0.65\n"
        "free_thresh: 0.196\n"
    )
    return tmp_path / "room.yaml"


ROOM = [
    "world.map_cell=2",
    "world.start=[2,6]",
    "world.horizon=20",
    "world.sources=[{name:near,position:[6,9],reward:1},{name:far,position:[18,2],reward:2}]",
    "world.regions=[{name:watched,mask:watched.pgm,risky:true,reward:-1}]",
]


def test_a_made_map_enclosed_room_unknown_space_mask_and_metres(room_map):
    picture, figure, ax = drawn(f"world.map={room_map}", *ROOM)
    colours = cell_colours(ax)
    assert colours.shape[:2] == (20, 16)
    assert np.allclose(colours[:, 12:16], to_rgb(wp.UNKNOWN))  # unknown space, all of it
    assert np.allclose(colours[12, 4:10], to_rgb(wp.OBSTACLE)) and np.allclose(colours[0, 0:12], to_rgb(wp.OBSTACLE))
    # the room's free inside is out of reach however long the horizon; the cell beside the start is within
    assert np.allclose(colours[13:17, 5:9], beyond(wp.FREE))
    assert tuple(colours[3, 6]) == pytest.approx(to_rgb(wp.FREE))
    # (18, 2) is 20 moves from (2, 6), below the room: within K = 20, and (18, 1) one more, beyond
    assert list(picture.moves) == [7, 20] and picture.reachable[18, 2] and not picture.reachable[18, 1]
    assert tuple(colours[18, 1]) == pytest.approx(tuple(beyond(wp.FREE)))
    far = path_lines(ax)[1]
    assert tuple(far[0]) == (2, 6) and tuple(far[-1]) == (18, 2) and len(far) == 21
    # the mask's cells x 1-5, y 1-3 are the risky region: coloured, and hatched by exactly their rectangle
    mask_cells = np.zeros((20, 16), bool)
    mask_cells[1:6, 1:4] = True
    assert np.allclose(colours[mask_cells], to_rgb(wp.RISKY_REGIONS[0]))
    (hatch,) = [p for p in ax.patches if isinstance(p, PathPatch)]
    assert hatch.get_path().get_extents().bounds == pytest.approx((0.5, 0.5, 5.0, 3.0))
    # metres: 1 m cells from (-3, 1.5): cell 0's centre at -2.5 m, cell y 4's at 6 m
    top, right = ax.child_axes
    assert top._functions[0](np.array([0.0])) == pytest.approx([-2.5])
    assert right._functions[0](np.array([4.0])) == pytest.approx([6.0])
    labels = [t.get_text() for t in figure.legends[0].get_texts()]
    assert "unknown (world.map_unknown=obstacle)" in labels and "region 'watched' (risky)" in labels


@pytest.mark.slow
@pytest.mark.parametrize(
    "overrides", [["experiment=paper_single"], ["experiment=floor_plan"], ["world.size=[40,10]"]], ids=str
)
def test_the_legend_sits_beside_or_below_the_world_without_a_blank_band(overrides):
    """The legend took a fixed 3.9 in beside the world: with the world's aspect fixed, its short labels left a band of
    1.1 in (the paper's world) and 0.7 in (the floor plan, its metre axis on the right) between the world and the
    legend; below a wide world, 0.33 in."""
    with matplotlib.rc_context(STYLE):
        figure = wp.draw_picture(wp.picture_of(setup_of(*overrides)))
        figure.draw_without_rendering()
        renderer = figure.canvas.get_renderer()
        world = [ax.get_tightbbox(renderer) for ax in figure.axes]  # the metre axes' labels included
        legend = figure.legends[0].get_window_extent(renderer)
    below = overrides == ["world.size=[40,10]"]
    band = min(box.y0 for box in world) - legend.y1 if below else legend.x0 - max(box.x1 for box in world)
    assert 0 < band / figure.dpi < 0.2
    assert figure.bbox.x0 <= legend.x0 and legend.x1 <= figure.bbox.x1 and figure.bbox.y0 <= legend.y0  # whole


def test_a_wandering_source_is_drawn_where_its_walk_begins():
    _, figure, ax = drawn("world.sources.1.motion={kind:random_walk,prob:0.5}")
    assert markers(ax, "*") == [(9.0, 3.0), (3.0, 9.0)]
    labels = [t.get_text() for t in figure.legends[0].get_texts()]
    assert "2 'risky' (3, 9, a random walk from here): 12 moves from (0, 0)" in labels


@pytest.mark.slow  # over half a second (the quick tier stays under a minute)
@pytest.mark.parametrize(("size", "source"), [("[1,12]", "[0,5]"), ("[12,1]", "[5,0]")])
def test_a_world_one_cell_wide_is_drawn_without_contours(size, source):
    """matplotlib's contour needs 2 x 2 values: `check --draw` of such a world was a traceback, and in a report it
    took the world figure of every other run with it."""
    _, _, ax = drawn(f"world.size={size}", f"world.sources=[{{position:{source},reward:1}}]", "world.regions=[]",
                     "train.theta0=[1]")  # fmt: skip
    x, y = (float(v) for v in source.strip("[]").split(","))
    assert markers(ax, "*") == [(x, y)]
    assert [type(c).__name__ for c in ax.collections] == ["LineCollection"]  # the grid's lines, no QuadContourSet


def test_a_turned_map_has_no_metre_axes(room_map):
    """With a yaw in the map's origin, the frame's x and y do not run along the cells: no metre axes, said so."""
    room_map.write_text(room_map.read_text().replace("origin: [-3.0, 1.5, 0.0]", "origin: [-3.0, 1.5, 0.5]"))
    _, _, ax = drawn(f"world.map={room_map}", *ROOM)
    assert not ax.child_axes and "turned 0.5 rad (no metre axes)" in " ".join(ax.get_title().split())


@pytest.mark.slow  # over a second
def test_check_draws_a_new_map_alone_when_its_start_is_not_placed_yet(room_map, in_tmp):
    """A new map with the default start (0, 0), a wall of it: the error line, and the map drawn alone to place the
    start and the sources on (its cells, unknown space and walls; no start, source or reach)."""
    result = runner.invoke(app, ["check", f"world.map={room_map}", "world.map_cell=2", "world.regions=[]",
                                 "--draw", "map.png"])  # fmt: skip
    assert result.exit_code == 2
    assert result.stderr.startswith("error: world.start: (0, 0) is an obstacle") and result.stderr.count("\n") == 1
    assert result.stderr.rstrip().endswith("(the map alone is drawn to map.png, to place things on)")
    assert (in_tmp / "map.png").read_bytes().startswith(b"\x89PNG")
    setup_free = ["world.start=[2,6]", "world.sources=[{name:a,position:[6,9],reward:1}]", "train.theta0=[20.0]"]
    world = setup_of(f"world.map={room_map}", "world.map_cell=2", "world.regions=[]", *setup_free).params.world
    picture = wp.map_alone(world, wp.maps.read_map(world), "world.start is bad")
    figure = wp.draw_picture(picture)
    ax = figure.axes[0]
    colours = cell_colours(ax)
    assert np.allclose(colours[:, 12:16], to_rgb(wp.UNKNOWN)) and np.allclose(colours[12, 4:10], to_rgb(wp.OBSTACLE))
    assert np.allclose(colours[13:17, 5:9], to_rgb(wp.FREE))  # no start: nothing greyed as out of reach
    assert not markers(ax, "o") and not markers(ax, "*") and not path_lines(ax)
    assert ax.child_axes and "the map alone (world.start is bad)" in " ".join(ax.get_title().split())


def test_check_draws_nothing_when_the_map_itself_is_bad(in_tmp):
    result = runner.invoke(app, ["check", "world.map=gone.yaml", "--draw", "map.png"])
    assert result.exit_code == 2 and result.stderr.startswith("error: world.map: no map file gone.yaml")
    assert "drawn" not in result.stderr and not (in_tmp / "map.png").exists()


def test_check_draws_nothing_for_bad_input_outside_the_world(in_tmp):
    """The map alone is drawn to place a start or sources on; a bad risk.beta is bad input like any other."""
    result = runner.invoke(app, ["check", "experiment=floor_plan", "risk.beta=7", "--draw", "map.png"])
    assert result.exit_code == 2 and result.stderr == "error: risk.beta: got 7.0; expected 0 < beta <= 1\n"
    assert not (in_tmp / "map.png").exists()


@pytest.mark.parametrize("cell, words", [("0", "got 0; expected k >= 1"), ("-2", "got -2; expected k >= 1")])
def test_check_draws_nothing_when_the_map_cell_is_bad(room_map, in_tmp, cell, words):
    # the map reads, but cannot be cut into cells of k < 1 pixels: the map_cell line, not a traceback
    result = runner.invoke(app, ["check", f"world.map={room_map}", f"world.map_cell={cell}", "--draw", "map.png"])
    assert result.exit_code == 2 and result.stderr == f"error: world.map_cell: {words} (one cell is k x k map pixels)\n"
    assert not (in_tmp / "map.png").exists()


@pytest.mark.slow
def test_check_draws_each_format(in_tmp):
    for name, head in (("world.png", b"\x89PNG"), ("world.svg", b"<?xml"), ("world.pdf", b"%PDF")):
        result = runner.invoke(app, ["check", "--draw", name, "world.obstacles=[[5,5]]"])
        assert result.exit_code == 0, result.output
        assert f"world drawn: {name}" in result.output and "config OK" in result.output
        assert (in_tmp / name).read_bytes().startswith(head)
    assert sorted(p.name for p in in_tmp.iterdir()) == ["world.pdf", "world.png", "world.svg"]


@pytest.mark.slow
def test_check_imports_matplotlib_only_to_draw(tmp_path):
    """riskplan check stays as light as it was without --draw: matplotlib comes with --draw alone."""
    code = (
        "import sys; from typer.testing import CliRunner; from riskplan.cli import app; "
        "runner = CliRunner(); before = runner.invoke(app, ['check']).exit_code, 'matplotlib' in sys.modules; "
        "after = runner.invoke(app, ['check', '--draw', 'w.png']).exit_code, 'matplotlib' in sys.modules; "
        "print(before, after)"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "(0, False) (0, True)"


@pytest.mark.parametrize(
    ("path", "problem"),
    [
        ("world.gif", "world.gif has suffix '.gif'; give a path ending .png, .svg or .pdf"),
        ("world", "world has suffix ''; give a path ending .png, .svg or .pdf"),
        ("notes.txt/world.png", "notes.txt/world.png cannot be written: notes.txt is a file, not a folder; give a"),
        ("gone/world.png", "gone/world.png cannot be written: no folder gone; give a path in an existing folder"),
        ("folder.png", "folder.png is a folder; give a file path ending .png, .svg or .pdf"),
        ("/dev/full.png", "/dev/full.png is under /dev, a kernel filesystem; give a file on a disk"),  # was written
        ("/dev/shm/../w.png", "/dev/shm/../w.png is under /dev, a kernel filesystem"),
    ],
)
def test_bad_draw_paths_are_one_line_and_exit_2_leaving_nothing(in_tmp, path, problem):
    (in_tmp / "notes.txt").write_text("a file, not a folder")
    (in_tmp / "folder.png").mkdir()
    before = sorted(p.name for p in in_tmp.rglob("*"))
    result = runner.invoke(app, ["check", "--draw", path])
    assert result.exit_code == 2
    assert result.stderr.startswith(f"error: --draw: {problem}") and result.stderr.count("\n") == 1
    assert sorted(p.name for p in in_tmp.rglob("*")) == before


@pytest.mark.slow
def test_a_warehouse_sized_map_is_drawn_in_blocks_within_2000_pixels(tmp_path):
    """1006 x 1674 cells (a warehouse's map at one pixel a cell): blocks of 4 x 4 cells, a one-cell shelf still
    dark, and the PNG within 2,000 px on its longer side."""
    image = np.full((1674, 1006), 254, np.uint8)
    image[:, 500] = 0  # a one-cell shelf from top to bottom, x = 500, with a gap at the bottom ...
    image[-10:, 500] = 254  # ... cells y 0-9
    (tmp_path / "big.pgm").write_bytes(b"P5\n1006 1674\n255\n" + image.tobytes())
    (tmp_path / "big.yaml").write_text(
        "image: big.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\noccupied_thresh: 0.65\n"
        "free_thresh: 0.196\n"
    )
    sources = "world.sources=[{name:a,position:[900,1500],reward:1,covariance:[[900,0],[0,900]]}]"
    where = [f"world.map={tmp_path / 'big.yaml'}", "world.start=[10,5]", "world.horizon=2400", "world.regions=[]"]
    setup = setup_of(*where, sources, "train.theta0=[20.0]")
    picture = wp.picture_of(setup)
    figure = wp.draw_picture(picture)
    colours = cell_colours(figure.axes[0])
    assert colours.shape[:2] == (252, 419) and wp.block_of(1006, 1674) == 4
    assert np.allclose(colours[125, 3:], to_rgb(wp.OBSTACLE))  # block x 125 holds x = 500: dark all along
    assert picture.moves[0] == 890 + 1495  # Manhattan: the gap lets it through without a detour
    with matplotlib.rc_context(STYLE):
        png = Image.open(io.BytesIO(figure_bytes(figure, "png")))
    assert max(png.size) <= 2000


@pytest.mark.slow
def test_the_report_draws_each_distinct_world_of_its_runs(tmp_path):
    """Three tiny runs in two worlds (two measures on the paper's, one with a wall): the report's world and
    world_2 figures, each the picture of its world, on the page."""
    runs = {"neutral": ["risk=neutral"], "cvar": [], "walled": ["world.obstacles=[[1,1],[2,1]]"]}
    for name, extra in runs.items():
        riskplan.train(riskplan.compose([*TINY, *extra]), tmp_path / "runs" / name)
    specs, _ = make_figures(collect([tmp_path / "runs"]))
    worlds = {spec.name: spec for spec in specs if spec.name.startswith("world")}
    assert sorted(worlds) == ["world", "world_2"]
    dark = {name: cell_colours(w.figure.axes[0]).sum(axis=2) < 1 for name, w in worlds.items()}
    assert sorted(map(tuple, np.argwhere(dark["world_2"]).tolist())) == [(1, 1), (2, 1)] and not dark["world"].any()
    page = riskplan.report(tmp_path / "runs", tmp_path / "report", formats=["png"])
    html = page.read_text()
    assert '<figure id="world">' in html and '<figure id="world_2">' in html
    assert html.index("<h2>The worlds</h2>") < html.index('<figure id="world">') < html.index("Configurations that")
    assert (tmp_path / "report" / "world.png").read_bytes().startswith(b"\x89PNG")


@pytest.mark.slow
def test_a_thin_world_with_one_sure_reward_beside_the_papers_is_reported_whole(tmp_path):
    """A world one cell wide (no contours: its figure failed, and took the paper world's with it) whose episodes
    all pay the same (the distribution's tail panel had equal limits: matplotlib's warning on stderr)."""
    thin = ["world.size=[12,1]", "world.sources=[{position:[5,0],reward:1}]", "world.regions=[]", "train.theta0=[1]"]
    riskplan.train(riskplan.compose([*TINY, *thin]), tmp_path / "runs" / "thin", progress=False)
    riskplan.train(riskplan.compose(TINY), tmp_path / "runs" / "paper", progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no figure fails, and matplotlib says nothing
        specs, skipped = make_figures(collect([tmp_path / "runs"]))
    assert not [reason for reason in skipped.values() if reason.startswith("failed")], skipped
    assert {"world", "world_2", "reward_distribution"} <= {spec.name for spec in specs}


@pytest.mark.slow
def test_the_report_draws_at_most_max_worlds_and_says_how_many_it_left_out():
    """A sweep over world.horizon has a world per value: the first MAX_WORLDS are drawn, the last says the rest."""
    groups = [
        SimpleNamespace(label=f"K={k}", config=OmegaConf.to_container(compose([*TINY, f"world.horizon={k}"])))
        for k in range(20, 20 + wp.MAX_WORLDS + 2)
    ]
    specs = wp.fig_world(SimpleNamespace(groups=groups))
    assert [spec.name for spec in specs] == ["world"] + [f"world_{i}" for i in range(2, wp.MAX_WORLDS + 1)]
    assert specs[-1].caption.endswith("The runs of K=27. 2 more worlds are not drawn.")
    assert "K = 21" in specs[1].figure.axes[0].get_title()


@pytest.mark.slow
def test_the_report_draws_the_world_of_a_run_placed_in_metres(tmp_path):
    """A run whose start and sources are given in metres (its recorded config holds {metres: [x, y]}) is reported,
    not skipped, and its world drawn with them at the cells they became."""
    placed = ["world.start=${metres:0.9,0.9}", "world.sources.0.position=${metres:0.9,3.9}"]
    riskplan.train(riskplan.compose([*TINY, "experiment=floor_plan", *placed]), tmp_path / "runs" / "metres")
    collected = collect([tmp_path / "runs"])
    assert len(collected.runs) == 1 and not collected.broken
    (world,) = [spec for spec in make_figures(collected)[0] if spec.name.startswith("world")]
    assert markers(world.figure.axes[0], "o") == [(3.0, 3.0)]
    assert markers(world.figure.axes[0], "*") == [(3.0, 15.0), (15.0, 3.0)]


def test_names_are_drawn_as_typed_never_as_mathtext():
    """A name is text: '$x$' is drawn with its dollars, not as an italic x, and '$\\nosuchcmd$', which mathtext cannot
    parse, no longer loses the picture (SVG keeps text as text, so the file shows what was drawn)."""
    _, figure, _ = drawn("world.sources.0.name='$x$'", "world.regions.0.name='$\\nosuchcmd$'")
    with matplotlib.rc_context(STYLE):
        svg = figure_bytes(figure, "svg").decode()
    assert ">1 '$x$' (9, 3): 12 moves from (0, 0)</text>" in svg
    assert ">region '$\\nosuchcmd$' (risky)</text>" in svg
