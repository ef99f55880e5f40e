"""Worlds from maps (riskplan.run.maps): ROS map YAMLs with PGM and PNG images, map_server's trinary rule, merged
cells, unknown pixels, mask regions, and one plain line for every bad map file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from support import TINY, bad_input, setup_of
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.run.maps import geometry, merge
from riskplan.util.errors import BadInput

# A 4 x 3 map as map_saver writes it: 0 occupied, 254 free, 205 unknown. Row 0 is the top row (y = 2).
ROWS = [
    [0, 254, 254, 205],
    [254, 254, 0, 254],
    [254, 254, 254, 254],
]
OCCUPIED = {(0, 2), (2, 1)}  # (x, y), y up from the bottom row
UNKNOWN = {(3, 2)}
# sources and start on free cells of the 4 x 3 map, and no regions (the paper's would fall off the grid)
SMALL = [
    "world.sources=[{name:a,position:[0,0],reward:1},{name:b,position:[3,0],reward:2}]",
    "world.regions=[]",
    "world.start=[1,1]",
]


def write_pgm(path: Path, rows, maxval: int = 255, binary: bool = True, comment: bool = True) -> Path:
    """A PGM of `rows` (row 0 the top): P5 (bytes) or P2 (text)."""
    height, width = len(rows), len(rows[0])
    head = f"{'P5' if binary else 'P2'}\n" + ("# made by a test\n" if comment else "") + f"{width} {height}\n{maxval}\n"
    if binary:
        dtype = np.uint8 if maxval < 256 else ">u2"
        path.write_bytes(head.encode() + np.array(rows, dtype=dtype).tobytes())
    else:
        path.write_text(head + "\n".join(" ".join(str(v) for v in row) for row in rows) + "\n")
    return path


def write_yaml(path: Path, image: str, **extra) -> Path:
    values = {
        "image": image,
        "resolution": 0.5,
        "origin": "[-1.0, 2.0, 0.0]",
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
        **extra,
    }
    path.write_text("".join(f"{k}: {v}\n" for k, v in values.items() if v is not None))
    return path


@pytest.fixture
def small_map(tmp_path) -> Path:
    write_pgm(tmp_path / "small.pgm", ROWS)
    return write_yaml(tmp_path / "small.yaml", "small.pgm")


def cells(mask: np.ndarray, world) -> set[tuple[int, int]]:
    x, y = np.nonzero(np.asarray(mask).reshape(world.width, world.height))
    return {(int(a), int(b)) for a, b in zip(x, y)}


def world_of(path: Path, *overrides: str):
    return setup_of(f"world.map={path}", *SMALL, *overrides).world


def test_occupied_pixels_are_exactly_the_obstacles_and_unknown_ones_too_by_default(small_map):
    world = world_of(small_map)
    assert (world.width, world.height) == (4, 3)
    assert cells(world.obstacle, world) == OCCUPIED | UNKNOWN
    free = world_of(small_map, "world.map_unknown=free")
    assert cells(free.obstacle, free) == OCCUPIED
    # the blocked moves follow: from (1, 1), east is the occupied (2, 1); from (1, 2), west is the occupied (0, 2)
    assert free.next_cell[1 * 3 + 1, 0] == 1 * 3 + 1
    assert free.next_cell[1 * 3 + 2, 1] == 1 * 3 + 2


@pytest.mark.slow  # builds the world of four image formats (near a second)
def test_p2_p5_16_bit_and_png_images_give_the_same_world(tmp_path, small_map):
    from PIL import Image

    reference = cells(world_of(small_map).obstacle, world_of(small_map))
    write_pgm(tmp_path / "text.pgm", ROWS, binary=False)
    write_pgm(tmp_path / "wide.pgm", [[v * 257 for v in row] for row in ROWS], maxval=65535)
    Image.fromarray(np.array(ROWS, dtype=np.uint8)).save(tmp_path / "grey.png")
    Image.fromarray(np.repeat(np.array(ROWS, dtype=np.uint8)[..., None], 3, axis=2)).save(tmp_path / "rgb.png")
    for image in ("text.pgm", "wide.pgm", "grey.png", "rgb.png"):
        world = world_of(write_yaml(tmp_path / f"{image}.yaml", image))
        assert cells(world.obstacle, world) == reference, image


@pytest.mark.slow  # builds a map's world several times (near a second)
def test_numbers_written_as_ros_writes_them_are_numbers(tmp_path, small_map):
    """25e-2 and 1e0 are numbers to ROS's YAML 1.2 reader, strings to PyYAML's 1.1: the map takes them as ROS does,
    the same world as 0.25 and 1.0 give; a word stays an error naming the key."""
    write_pgm(tmp_path / "small.pgm", ROWS)
    plain = write_yaml(tmp_path / "plain.yaml", "small.pgm", resolution=0.25, origin="[-1.0, 2.0, 0.0]")
    ros = write_yaml(tmp_path / "ros.yaml", "small.pgm", resolution="25e-2", origin="[-1e0, 2e0, 0e0]")
    read = [geometry(setup_of(f"world.map={path}", *SMALL).params.world) for path in (plain, ros)]
    assert read[0] == read[1] == (0.25, (-1.0, 2.0, 0.0))
    assert cells(world_of(ros).obstacle, world_of(ros)) == cells(world_of(plain).obstacle, world_of(plain))
    with pytest.raises(BadInput, match="resolution is 'fine'; expected a finite number"):
        world_of(write_yaml(tmp_path / "word.yaml", "small.pgm", resolution="fine"))


def test_the_thresholds_and_negate_follow_map_server(tmp_path):
    # p = (255 - v) / 255: 89 -> 0.651 occupied, 90 -> 0.647 unknown, 205 -> 0.196 unknown, 206 -> 0.192 free
    write_pgm(tmp_path / "levels.pgm", [[89, 90, 205, 206]])
    plain = world_of(write_yaml(tmp_path / "a.yaml", "levels.pgm"), "world.map_unknown=free", *FOUR_BY_ONE)
    assert cells(plain.obstacle, plain) == {(0, 0)}
    write_pgm(tmp_path / "levels2.pgm", [[254, 254, 254, 254], [89, 90, 205, 206]])  # a free row for the source
    grid = world_of(write_yaml(tmp_path / "b.yaml", "levels2.pgm"), *FOUR_BY_ONE_UNKNOWN)
    assert cells(grid.obstacle, grid) == {(0, 0), (1, 0), (2, 0)}
    # negate: p = v / 255, so 205 (0.804) and 206 (0.808) are occupied, 89 and 90 (0.35) unknown
    negated = world_of(write_yaml(tmp_path / "c.yaml", "levels.pgm", negate=1), "world.map_unknown=free", *NEG)
    assert cells(negated.obstacle, negated) == {(2, 0), (3, 0)}


FOUR_BY_ONE = ["world.start=[3,0]", "world.sources=[{position:[1,0],reward:1}]", "train.theta0=[20]"]
FOUR_BY_ONE_UNKNOWN = ["world.start=[3,0]", "world.sources=[{position:[3,1],reward:1}]", "train.theta0=[20]"]
NEG = ["world.start=[0,0]", "world.sources=[{position:[1,0],reward:1}]", "train.theta0=[20]"]


def test_map_cell_merges_k_by_k_pixels_from_the_lower_left(tmp_path):
    # 5 x 3 pixels, k = 2: cells of columns {0,1}, {2,3}, {4} and rows (from the bottom) {0,1}, {2}
    rows = [
        [254, 254, 254, 254, 0],  # y = 2: the occupied pixel (4, 2) -> cell (2, 1)
        [254, 254, 205, 254, 254],  # y = 1: the unknown pixel (2, 1) -> cell (1, 0)
        [0, 254, 254, 254, 254],  # y = 0: the occupied pixel (0, 0) -> cell (0, 0)
    ]
    write_pgm(tmp_path / "m.pgm", rows)
    path = write_yaml(tmp_path / "m.yaml", "m.pgm")
    world = setup_of(
        f"world.map={path}",
        "world.map_cell=2",
        "world.map_unknown=free",
        "world.regions=[]",
        "world.start=[0,1]",
        "world.sources=[{position:[1,1],reward:1}]",
        "train.theta0=[20]",
    ).world
    assert (world.width, world.height) == (3, 2)
    assert cells(world.obstacle, world) == {(0, 0), (2, 1)}
    blocked = setup_of(
        f"world.map={path}",
        "world.map_cell=2",
        "world.regions=[]",
        "world.start=[0,1]",
        "world.sources=[{position:[1,1],reward:1}]",
        "train.theta0=[20]",
    ).world
    assert cells(blocked.obstacle, blocked) == {(0, 0), (2, 1), (1, 0)}


def test_merge_is_each_k_by_k_blocks_or_whatever_k(tmp_path):
    """merge against the definition, block by block, on random pixels; a k far past the image is one cell, not a
    padded array of k x k pixels (world.map_cell=1e11 allocated terabytes: a traceback)."""
    rng = np.random.default_rng(0)
    for _ in range(100):
        w, h, k = (int(v) for v in rng.integers(1, 20, 3))
        pixels = rng.random((w, h)) < 0.1
        expected = [[pixels[i : i + k, j : j + k].any() for j in range(0, h, k)] for i in range(0, w, k)]
        assert merge(pixels, k).tolist() == expected
    assert merge(np.eye(3, dtype=bool), 10**11).tolist() == [[True]]
    assert merge(np.zeros((3, 4), dtype=bool), 10**11).tolist() == [[False]]


def test_a_mask_region_holds_the_dark_pixels_of_its_image(tmp_path, small_map):
    write_pgm(tmp_path / "mask.pgm", [[255, 255, 255, 255], [255, 127, 255, 255], [128, 0, 255, 255]])
    regions = "world.regions=[{name:watched,mask:mask.pgm,risky:true,reward:-5},{name:rest,rect:[0,0,3,2],reward:1}]"
    world = world_of(small_map, regions)
    assert world.region_names == ("watched", "rest")
    watched = cells(world.region_of == 0, world)
    assert watched == {(1, 1), (1, 0)}  # 127 < 127.5 and 0 are dark; 128 is not
    risky = world_of(small_map, regions, "world.map_unknown=risky")
    assert risky.region_names == ("unknown", "watched", "rest")
    assert cells(risky.region_of == 0, risky) == UNKNOWN and bool(risky.region_risky[0])
    assert cells(risky.region_of == 1, risky) == watched
    assert cells(risky.obstacle, risky) == OCCUPIED


def test_unknown_cells_as_risky_need_a_risky_region_to_take_their_reward(small_map):
    err = bad_input(f"world.map={small_map}", *SMALL, "world.map_unknown=risky")
    assert err.where == "world.map_unknown" and "risky: true" in err.problem


def test_a_start_or_source_on_an_occupied_cell_is_named(small_map):
    err = bad_input(f"world.map={small_map}", *SMALL, "world.start=[2,1]")
    assert err.where == "world.start"
    assert err.problem.startswith("(2, 1) is an obstacle (an occupied or unknown cell of world.map ")
    err = bad_input(f"world.map={small_map}", *SMALL, "world.sources.0.position=[0,2]")
    assert err.where == "world.sources.0.position" and "(0, 2) is an obstacle" in err.problem
    err = bad_input(f"world.map={small_map}", *SMALL, "world.start=[4,0]")
    assert err.where == "world.start" and "off the 4x3 grid" in err.problem


@pytest.mark.parametrize(
    ("make", "where", "words"),
    [
        (lambda d: write_yaml(d / "m.yaml", "gone.pgm"), "world.map", "the image gone.pgm of"),
        (lambda d: write_yaml(d / "m.yaml", "small.pgm", resolution=None), "world.map", "has no resolution"),
        (lambda d: write_yaml(d / "m.yaml", "small.pgm", resolution=-1), "world.map", "resolution is -1"),
        # a subnormal resolution would put a metre in cell -2147483648: positions in metres must keep their digits
        (lambda d: write_yaml(d / "m.yaml", "small.pgm", resolution=1e-320), "world.map", "in [1e-06, 1e+06]"),
        (lambda d: write_yaml(d / "m.yaml", "small.pgm", resolution=1e300), "world.map", "resolution is 1e+300"),
        (lambda d: write_yaml(d / "m.yaml", "small.pgm", origin="[1.7e308, 0, 0]"), "world.map", "within ±1e+09 m"),
        (lambda d: write_yaml(d / "m.yaml", "small.pgm", mode="fancy"), "world.map", "expected one of trinary"),
        (lambda d: write_yaml(d / "m.yaml", "small.pgm", free_thresh=0.9), "world.map", "free_thresh 0.9"),
        (lambda d: write_yaml(d / "m.yaml", "small.pgm", origin="[0, 0]"), "world.map", "expected [x, y, yaw]"),
        (lambda d: (d / "m.yaml").write_text("image: [unclosed\n") and d / "m.yaml", "world.map", "not valid YAML"),
        (lambda d: write_yaml(d / "m.yaml", "m.yaml"), "world.map", "is not a PGM (P2 or P5) or PNG image"),
    ],
)
@pytest.mark.slow  # 11 map files, each composed and read
def test_a_bad_map_yaml_is_one_line_naming_the_file(tmp_path, small_map, make, where, words):
    path = make(tmp_path)
    err = bad_input(f"world.map={path}", *SMALL)
    assert err.where == where
    assert words in err.problem


@pytest.mark.slow  # reads a dozen damaged images (near a second)
def test_truncated_and_corrupt_images_are_one_line(tmp_path):
    from PIL import Image

    data = write_pgm(tmp_path / "full.pgm", ROWS).read_bytes()
    (tmp_path / "cut.pgm").write_bytes(data[:-3])
    (tmp_path / "head.pgm").write_bytes(b"P5\n4 ")
    (tmp_path / "text.pgm").write_text("P2\n4 3\n255\n0 1 2 x 4 5 6 7 8 9 10 11\n")
    (tmp_path / "over.pgm").write_text("P2\n4 3\n100\n0 1 2 300 4 5 6 7 8 9 10 11\n")
    (tmp_path / "zero.pgm").write_text("P2\n4 3\n0\n0 0 0 0 0 0 0 0 0 0 0 0\n")
    Image.fromarray(np.array(ROWS, dtype=np.uint8)).save(tmp_path / "ok.png")
    png = (tmp_path / "ok.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(png[: len(png) // 2 + 10])
    expected = {
        "cut.pgm": "is truncated: 4x3 pixels need 12 bytes after the header, it has 9",
        "head.pgm": "corrupt or truncated PGM header",
        "text.pgm": "is corrupt: a P2 image holds whole numbers 0..255 only",
        "over.pgm": "is corrupt: a pixel of 300 above its maxval 100",
        "zero.pgm": "4x3 pixels and maxval 0; expected a width and height of at least 1 pixel and a maxval of 1 to 65535",
        "cut.png": "truncated or corrupt",
    }
    for name, words in expected.items():
        err = bad_input(f"world.map={write_yaml(tmp_path / (name + '.yaml'), name)}", *SMALL)
        assert err.where == "world.map" and words in err.problem, (name, err)


def test_a_mask_of_another_size_or_without_a_map_is_named(tmp_path, small_map):
    write_pgm(tmp_path / "mask.pgm", [[0, 0, 0], [0, 0, 0]])
    err = bad_input(f"world.map={small_map}", *SMALL, "world.regions=[{mask:mask.pgm}]")
    assert err.where == "world.regions.0.mask"
    assert "mask.pgm is 3x2 pixels and the map" in err.problem and "4x3" in err.problem
    err = bad_input("world.regions.0.halfplane=null", "world.regions.0.mask=mask.pgm")
    assert err.where == "world.regions.0.mask" and "needs world.map" in err.problem
    err = bad_input(f"world.map={small_map}", *SMALL, "world.regions=[{mask:missing.png}]")
    assert err.where == "world.regions.0.mask" and "is not there" in err.problem


def test_a_map_too_large_for_the_memory_budget_is_refused_before_its_pixels_are_read(tmp_path, monkeypatch):
    # a header that claims 60000 x 60000 pixels and no pixels at all: the budget refuses it from the header alone
    (tmp_path / "huge.pgm").write_bytes(b"P5\n60000 60000\n255\n")
    path = write_yaml(tmp_path / "huge.yaml", "huge.pgm")
    monkeypatch.setenv("RISKPLAN_MEMORY_GB", "1")
    err = bad_input(f"world.map={path}", *SMALL)
    assert err.where == "world.map"
    assert f"{path} is 60000x60000 pixels, a 60000x60000 grid at world.map_cell=1:" in err.problem
    assert "RISKPLAN_MEMORY_GB" in err.problem


def test_relative_paths_the_map_from_the_working_directory_its_image_from_its_folder(tmp_path, monkeypatch):
    folder = tmp_path / "maps"
    folder.mkdir()
    write_pgm(folder / "small.pgm", ROWS)
    write_yaml(folder / "small.yaml", "small.pgm")
    monkeypatch.chdir(tmp_path)
    world = setup_of("world.map=maps/small.yaml", *SMALL).world
    assert cells(world.obstacle, world) == OCCUPIED | UNKNOWN
    err = bad_input("world.map=maps/nothing.yaml", *SMALL)
    assert err.where == "world.map" and "no map file maps/nothing.yaml" in err.problem
    (tmp_path / "maps" / "folder.yaml").mkdir()
    err = bad_input("world.map=maps/folder.yaml", *SMALL)
    assert err.where == "world.map" and err.problem.startswith("maps/folder.yaml is a folder (")


def test_the_cli_gives_one_line_exit_2_and_no_run_directory_for_a_truncated_map(tmp_path, monkeypatch):
    data = write_pgm(tmp_path / "small.pgm", ROWS).read_bytes()
    (tmp_path / "small.pgm").write_bytes(data[:-1])
    write_yaml(tmp_path / "small.yaml", "small.pgm")
    monkeypatch.chdir(tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    done = CliRunner().invoke(app, ["train", *TINY, "world.map=small.yaml", *SMALL])
    assert done.exit_code == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: world.map: the image small.pgm of small.yaml is truncated")
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no outputs/ made
