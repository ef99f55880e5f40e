"""Sizes that would exhaust memory or time are bad input before anything big is allocated (riskplan.run.budget)."""

from __future__ import annotations

import pytest
from support import bad_input, setup_of

from riskplan.run import budget
from riskplan.run import build as setup_code
from riskplan.run.compose import compose
from riskplan.util import limits


@pytest.fixture(autouse=True)
def machine(monkeypatch):
    """The same limits on every machine: 16 GB and 24 hours."""
    monkeypatch.setenv(limits.MEMORY_ENV, "16")
    monkeypatch.setenv(limits.HOURS_ENV, "24")


BIG = 10**30


@pytest.mark.parametrize(
    "overrides, key, kind",
    [
        (["world.size=[100000,100000]"], "world.size", "memory"),
        ([f"train.samples={BIG}"], "train.samples", "memory"),
        (["train.samples_growth=50"], "train.samples_growth", "memory"),
        ([f"train.eval_episodes={BIG}"], "train.eval_episodes", "memory"),
        ([f"train.bootstrap={BIG}"], "train.bootstrap", "memory"),
        (["train.bootstrap=100000000", "train.eval_episodes=100000"], "train.bootstrap", "time"),
        ([f"train.iterations={BIG}"], "train.iterations", "memory"),
        ([f"world.horizon={BIG}"], "world.horizon", "memory"),
        (["world.horizon=1000000000000", "train.paths=0"], "world.horizon", "time"),
        (["train.paths=100000000"], "train.paths", "memory"),
        ([f"team.robots={BIG}"], "team.robots", "memory"),
        (["team.robots=100000"], "team.robots", "memory"),
        ([f"team.delay.max={BIG}"], "team.delay.max", "memory"),
        (["team.delay.max=1000000000"], "team.delay.max", "memory"),  # even one robot allocates the buffers
        ([f"team.consensus_rounds={BIG}"], "team.consensus_rounds", "memory"),
        (["team.robots=50", "team.graph=random_geometric", f"team.resample={BIG}"], "team.resample", "time"),
        ([f"world.size=[{10**400},1]"], "world.size", "memory"),  # a 400-digit int is a number, not an OverflowError
    ],
)
@pytest.mark.slow  # 17 cases, each composed and sized
def test_the_dominant_key_is_named(overrides, key, kind):
    err = bad_input(*overrides)
    assert err.where == key
    if kind == "memory":
        assert (
            "of memory, more than the 16 GB allowed (RISKPLAN_MEMORY_GB); lower it, or raise the limit with "
            "RISKPLAN_MEMORY_GB=<GB>" in err.problem
        )
    else:
        assert (
            "more than the 24.0 h allowed; lower it, or raise the limit with RISKPLAN_MAX_HOURS=<hours>" in err.problem
        )


def test_a_huge_grid_fails_before_the_world_is_built(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("build_world ran before the size check")

    monkeypatch.setattr(setup_code, "build_world", refuse)
    assert bad_input("world.size=[100000,100000]").where == "world.size"


def test_a_small_memory_limit_names_the_key_and_raising_it_lets_the_run_through(monkeypatch):
    monkeypatch.setenv(limits.MEMORY_ENV, "0.05")
    err = bad_input("world.size=[400,400]", "world.regions.1.rect=[0,0,399,399]")
    assert err.where == "world.size"
    assert "the 400 x 400 grid" in err.problem and "more than the 50 MB allowed (RISKPLAN_MEMORY_GB)" in err.problem
    monkeypatch.setenv(limits.MEMORY_ENV, "1")
    setup_of("world.size=[400,400]", "world.regions.1.rect=[0,0,399,399]")


def test_samples_growth_counts_the_last_iteration(monkeypatch):
    monkeypatch.setenv(limits.MEMORY_ENV, "1")
    # W_L = 200 * 3^10 = 11.8M episodes in the last of 3 iterations: about 0.9 GB of batch, plus the rest
    err = bad_input("train.samples_growth=10", "train.samples=2000")
    assert err.where == "train.samples_growth"


@pytest.mark.parametrize(
    "experiment, extra",
    [
        ("paper_single", []),
        ("paper_team", []),
        ("paper_single", ["train.iterations=60", "train.eval_episodes=20000", "train.bootstrap=200"]),
    ],
)
def test_the_paper_set_ups_are_well_inside_the_limits(experiment, extra):
    cfg = compose([f"experiment={experiment}", *extra], validate=False)
    sizes = budget.sizes_of(cfg, 12, 12, 2, int(cfg.team.robots))
    memory, time = budget.estimate(sizes)
    assert sum(part[0] for part in memory) < 1e9  # under 1 GB of the 24 GB machine
    assert sum(part[0] for part in time) / limits.STEPS_PER_SECOND < 600  # under 10 minutes of the 24 hours


def test_estimates_are_python_floats_for_any_size():
    sizes = budget.Sizes(
        10**400,
        10**400,
        2,
        10**400,
        10**400,
        10**400,
        10**400,
        1e300,
        10**400,
        10**400,
        0,
        10**400,
        10**400,
        10**400,
        True,
        1,
    )
    memory, time = budget.estimate(sizes)
    for amount, _, _ in memory + time:
        assert isinstance(amount, float) and not amount != amount  # never nan (no 0 * inf)
