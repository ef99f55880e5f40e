"""Output directories (riskplan.util.paths): directories claimed in the same second never collide. Read-only and
full disks are in tests/run/test_run_safety.py and tests/experiments/test_output_safety.py."""

from __future__ import annotations

from riskplan.util.paths import claim_dir


def test_two_sweeps_in_the_same_second_get_their_own_directories(tmp_path):
    made = {claim_dir(tmp_path) for _ in range(3)}
    assert len(made) == 3 and all(p.is_dir() for p in made)
