"""A reproduction's schedule (riskplan.experiments.timing): its stages, the ETA scaled by the finished stages, and
Section V alone (--paper-only)."""

from __future__ import annotations

import pytest

from riskplan.experiments.reproduction import EXPERIMENTS, check_seeds, chosen, experiment_jobs
from riskplan.experiments.timing import Schedule, Stage


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
