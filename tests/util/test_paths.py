"""Output directories (riskplan.util.paths): directories claimed in the same second never collide. Read-only and
full disks are in tests/run/test_run_safety.py and tests/experiments/test_output_safety.py."""

from __future__ import annotations

from pathlib import Path

import pytest

from riskplan.util.errors import BadInput
from riskplan.util.paths import check_output_dir, claim_dir


def test_two_sweeps_in_the_same_second_get_their_own_directories(tmp_path):
    made = {claim_dir(tmp_path) for _ in range(3)}
    assert len(made) == 3 and all(p.is_dir() for p in made)


@pytest.mark.parametrize("below", ["", "/sub"])
def test_a_dangling_link_or_a_loop_on_an_output_path_is_named(tmp_path, below):
    """mkdir through a link to nothing, or a loop, failed with 'File exists' (exit 1); each is bad input naming the
    link."""
    (tmp_path / "gone").symlink_to(tmp_path / "nowhere")
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    with pytest.raises(BadInput) as dangling:
        check_output_dir(f"{tmp_path}/gone{below}", "--out")
    assert str(dangling.value) == (
        f"--out: {tmp_path}/gone{below}: {tmp_path}/gone is a symbolic link to {tmp_path}/nowhere, which does not "
        f"exist; give a directory path, or make the link's target first"
    )
    with pytest.raises(BadInput) as loop:
        check_output_dir(f"{tmp_path}/a{below}", "--out")
    assert (
        str(loop.value)
        == f"--out: {tmp_path}/a{below}: {tmp_path}/a is a symbolic link in a loop; give a directory path"
    )
    (tmp_path / "nowhere").mkdir()  # the link's target made: a directory like any other
    assert check_output_dir(f"{tmp_path}/gone{below}", "--out") == Path(f"{tmp_path}/gone{below}")
