"""The example floor plan: the files shipped in conf/maps are the ones riskplan.experiments.floor_plan draws, and
`experiment=floor_plan` builds a world whose obstacles are exactly the map's walls and unknown outside, with the
watched corridor as its risky region."""

from __future__ import annotations

import numpy as np
from support import setup_of

from riskplan.config.schema import CONF_DIR
from riskplan.experiments import floor_plan


def test_the_shipped_files_are_the_ones_the_module_draws(tmp_path):
    shipped = {name: (CONF_DIR / "maps" / name).read_bytes() for name in floor_plan.NAMES}
    assert shipped == floor_plan.files()
    written = floor_plan.write(tmp_path / "again")
    assert {p.name: p.read_bytes() for p in written} == shipped


def test_the_floor_plan_experiment_is_the_map_with_its_corridor(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)  # maps/floor_plan.yaml is found in riskplan's conf/, from anywhere
    world = setup_of("experiment=floor_plan").world
    cells = floor_plan.plan()
    assert (world.width, world.height) == (floor_plan.WIDTH, floor_plan.HEIGHT)
    obstacle = world.obstacle.reshape(world.width, world.height)
    np.testing.assert_array_equal(obstacle, cells != floor_plan.FREE)  # walls, and the unknown outside
    assert world.region_names == ("watched", "safe")
    watched = (world.region_of == 0).reshape(world.width, world.height)
    np.testing.assert_array_equal(watched, floor_plan.watched() == 0)
    x, y = world.xy(world.source_cells)
    assert list(zip(x.tolist(), y.tolist())) == [floor_plan.SAFE, floor_plan.RISKY]
    assert tuple(int(v) for v in world.xy(world.starts[0])) == floor_plan.START
    start, safe, risky = floor_plan.START, floor_plan.SAFE, floor_plan.RISKY
    assert (
        abs(safe[0] - start[0]) + abs(safe[1] - start[1]) == 12 == abs(risky[0] - start[0]) + abs(risky[1] - start[1])
    )
