"""A reproduction's schedule (riskplan.experiments.timing): its stages, the ETA scaled by the finished stages, and
Section V alone (--paper-only)."""

from __future__ import annotations

import pytest

from riskplan.experiments.reproduction import EXPERIMENTS, check_seeds, chosen, experiment_jobs
from riskplan.experiments.timing import Schedule, Stage, plan_line


def test_the_eta_follows_how_the_finished_stages_compared_with_their_estimates():
    schedule = Schedule([Stage("a", 10.0, 2), Stage("b", 20.0, 4), Stage("c", 30.0)])
    assert schedule.total == 60.0 and schedule.remaining() == 60.0
    schedule.finished("a", 20.0)  # twice as slow as estimated: the rest will be too
    assert schedule.remaining() == pytest.approx(100.0)
    assert schedule.header("b").startswith("[stage 2 of 3: b] about 100 s left in all (ETA ")
    schedule.finished("b", 10.0)  # now 30 s against 30 s estimated
    assert schedule.remaining() == pytest.approx(30.0)


def test_one_odd_stage_moves_the_eta_at_most_tenfold():
    schedule = Schedule([Stage("a", 10.0), Stage("b", 10.0)])
    schedule.finished("a", 0.0)  # every job skipped
    assert schedule.remaining() == pytest.approx(1.0)


def test_paper_only_runs_section_v_alone():
    paper = chosen(paper_only=True)
    assert [folder for folder, *_ in paper] == ["single", "team"] and chosen(paper_only=False) == EXPERIMENTS
    assert experiment_jobs(10, paper) == [20, 10] and check_seeds(10, paper) == 30


@pytest.fixture
def cache(tmp_path, monkeypatch):
    from riskplan.run import cost

    monkeypatch.setenv(cost.CACHE_ENV, str(tmp_path / "cache"))
    return tmp_path / "cache"


def stages() -> list[Stage]:
    return [Stage("single", 40.0, 20), Stage("team", 30.0, 10), Stage("report", 5.0)]


def test_a_plan_reproduced_again_is_estimated_as_its_stages_took_last_time(cache):
    from riskplan.experiments.timing import plan_key

    plan, other = plan_key(seeds=10, quick=False), plan_key(seeds=2, quick=True)
    first = Schedule.remembered(stages(), plan)
    assert (first.total, first.measured) == (75.0, 0)  # nothing measured yet: the cost model's estimates
    first.finished("single", 8.0)
    first.finished("team", 60.0, whole=False)  # jobs skipped or failed: says nothing of a whole stage's time
    first.finished("report", 12.5)
    again = Schedule.remembered(stages(), plan)
    assert [stage.estimate for stage in again.stages] == [8.0, 30.0, 12.5] and again.measured == 2
    assert "2 stages as this machine's last reproduction of this plan took them, the rest by the cost model" in (
        plan_line(again, None)
    )
    again.finished("team", 4.0)
    third = Schedule.remembered(stages(), plan)
    assert third.total == pytest.approx(24.5) and third.measured == 3
    assert "estimated time about 24 s (each stage as this machine's last reproduction of this plan took it;" in (
        plan_line(third, 2)
    )
    assert Schedule.remembered(stages(), other).total == 75.0  # another plan: other jobs


def test_only_the_latest_plans_stage_times_are_kept_and_a_bad_file_is_no_memory(cache):
    from riskplan.experiments import timing
    from riskplan.run import cost

    for seeds in range(timing.PLANS_KEPT + 3):
        Schedule.remembered(stages(), timing.plan_key(seeds=seeds)).finished("single", float(seeds + 1))
    kept = [
        timing.Schedule.remembered(stages(), timing.plan_key(seeds=s)).measured for s in range(timing.PLANS_KEPT + 3)
    ]
    assert kept == [0, 0, 0] + [1] * timing.PLANS_KEPT
    cost.cache_file("stages").write_text("{not json")
    assert Schedule.remembered(stages(), timing.plan_key(seeds=5)).total == 75.0
    blocked = cache.parent / "a-file"
    blocked.write_text("")
    with pytest.MonkeyPatch.context() as patched:  # a cache that cannot be written (its folder is a file, even
        patched.setenv(cost.CACHE_ENV, str(blocked))  # for root): the time is lost, the reproduction goes on
        schedule = Schedule.remembered(stages(), timing.plan_key(seeds=5))
        schedule.finished("single", 1.0)
        assert schedule.taken == {"single": 1.0} and schedule.measured == 0
