"""The example floor plan that riskplan ships (conf/maps/floor_plan.*, `experiment=floor_plan`): a lobby, a hallway
north to the safe source, a corridor east to the risky source that an adversary watches, rooms and doors. Drawn here,
cell by cell, so that the map is the project's own and can be made again:

    python -m riskplan.experiments.floor_plan [FOLDER]   # default: riskplan's conf/maps

writes `floor_plan.yaml` and `floor_plan.pgm` (a ROS map as map_saver writes one: 0 occupied, 254 free, 205
unknown, trinary, negate 0) and `floor_plan_watched.pgm`, the mask of the adversary's view (black inside).

The world is the paper's Section V one with walls: the start (3, 3) is 12 moves from each source, the safe one
(3, 15) up the hallway and the risky one (15, 3) down the watched corridor.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from riskplan.config.schema import CONF_DIR

WIDTH, HEIGHT = 30, 24  # cells = pixels (world.map_cell=1)
RESOLUTION = 0.25  # metres per pixel
WALL, FREE, UNKNOWN = 0, 254, 205  # map_saver's grey levels
START, SAFE, RISKY = (3, 3), (3, 15), (15, 3)
WATCHED = (10, 2, 27, 4)  # x0, y0, x1, y1 (inclusive): the corridor the adversary sees, with its entrance
NAMES = ("floor_plan.yaml", "floor_plan.pgm", "floor_plan_watched.pgm")
YAML = """\
# riskplan's example floor plan, drawn by `python -m riskplan.experiments.floor_plan` (a ROS map YAML, as
# map_server and nav2_map_server read it). 30 x 24 cells of 0.25 m: a lobby (start), a hallway north to the safe
# source, a corridor east to the risky source that an adversary watches (floor_plan_watched.pgm), rooms and doors.
image: floor_plan.pgm
mode: trinary
resolution: 0.25
origin: [0.0, 0.0, 0.0]
negate: 0
occupied_thresh: 0.65
free_thresh: 0.196
"""


def plan() -> np.ndarray:
    """The map as grey levels indexed [x, y] (y up): WALL, FREE inside the building, UNKNOWN outside it."""
    cells = np.full((WIDTH, HEIGHT), UNKNOWN, dtype=np.uint8)
    cells[1:29, 1:23] = WALL
    cells[2:28, 2:22] = FREE

    def wall(x0: int, y0: int, x1: int, y1: int, *doors: tuple[int, int]) -> None:
        cells[x0 : x1 + 1, y0 : y1 + 1] = WALL
        for x, y in doors:
            cells[x, y] = FREE

    wall(1, 10, 28, 10, (3, 10), (4, 10))  # south wing | north wing; the hallway's door above the start
    wall(10, 1, 10, 10, (10, 2), (10, 3), (10, 4))  # the lobby's east wall, open onto the corridor
    wall(10, 5, 28, 5, (13, 5), (19, 5), (25, 5))  # the corridor's north wall, with a door into each room
    wall(16, 5, 16, 10)  # rooms north of the corridor
    wall(22, 5, 22, 10)
    wall(6, 10, 6, 22, (6, 13), (6, 19))  # the hallway's east wall, two doors into the north rooms
    wall(6, 16, 28, 16, (10, 16), (18, 16), (25, 16))  # north rooms
    wall(14, 10, 14, 22, (14, 13), (14, 19))
    wall(21, 10, 21, 22, (21, 13), (21, 19))
    return cells


def watched() -> np.ndarray:
    """The adversary's view as a mask indexed [x, y]: 0 (dark, in the region) on the corridor, 255 elsewhere."""
    mask = np.full((WIDTH, HEIGHT), 255, dtype=np.uint8)
    x0, y0, x1, y1 = WATCHED
    mask[x0 : x1 + 1, y0 : y1 + 1] = 0
    return mask


def pgm(cells: np.ndarray) -> bytes:
    """A binary PGM (P5) of an [x, y] array: image row 0 is the top row, y = HEIGHT - 1."""
    image = np.ascontiguousarray(cells.T[::-1])
    return f"P5\n{image.shape[1]} {image.shape[0]}\n255\n".encode() + image.tobytes()


def files() -> dict[str, bytes]:
    """The three files by name, as they are written."""
    return {NAMES[0]: YAML.encode(), NAMES[1]: pgm(plan()), NAMES[2]: pgm(watched())}


def write(folder: Path) -> list[Path]:
    """Write the floor plan's files into `folder`; their paths."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, data in files().items():
        (folder / name).write_bytes(data)
        written.append(folder / name)
    return written


if __name__ == "__main__":
    for path in write(Path(sys.argv[1]) if len(sys.argv) > 1 else CONF_DIR / "maps"):
        print(path)
