"""A start on a source's cell: `riskplan check 'world.start=[3,9]'` said source 1 'risky' was 0 moves away, while the
episodes count a source reached when a move ends on it, so those starting there counted as not reaching it at step 0.
Such a start is refused in one line, like two sources on one cell."""

from __future__ import annotations

import pytest
from support import bad_input, setup_of
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.engine.reachability import source_distances

runner = CliRunner()
ON_SOURCE = "an episode reaches a source when a move ends on it, never where it starts: choose a start off the sources"


def test_check_refuses_a_start_on_a_source_in_one_line_and_writes_nothing(in_tmp):
    result = runner.invoke(app, ["check", "world.start=[3,9]"])
    assert result.exit_code == 2
    assert result.stderr == f"error: world.start: (3, 9) is the cell of world.sources.1 'risky'; {ON_SOURCE}\n"
    assert list(in_tmp.iterdir()) == []


@pytest.mark.parametrize(
    ("overrides", "key", "cell"),
    [
        (["experiment=paper_team", "team.robots=3", "team.starts=[[0,0],[9,3],[1,1]]"], "team.starts.1", "(9, 3)"),
        (  # a random walk begins on its cell: the episode's first step is the same
            ["world.start=[9,3]", "world.sources.0.motion.kind=random_walk", "world.sources.0.motion.prob=0.5"],
            "world.start",
            "(9, 3)",
        ),
    ],
)
def test_each_robots_start_and_a_random_walks_cell_count(overrides, key, cell):
    err = bad_input(*overrides)
    assert (err.where, err.problem) == (key, f"{cell} is the cell of world.sources.0 'safe'; {ON_SOURCE}")


def test_a_start_next_to_a_source_is_taken_one_move_away():
    world = setup_of("world.start=[3,8]").world
    assert source_distances(world, world.starts).tolist() == [[11, 1]]
