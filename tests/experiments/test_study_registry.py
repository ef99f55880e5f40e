"""Every experiment of reproduce and every study of its report (riskplan.experiments.study_registry), with no test
code of their own: a folder of its own, each job of its sweep a valid run, and a study whose folders are
experiments and which the report can show (its figure, table and text)."""

from __future__ import annotations

import warnings

import pytest

from riskplan.config.validate import IgnoredKey
from riskplan.experiments.reporting.figures import FIGURES
from riskplan.experiments.reporting.page import STUDY_TABLES, STUDY_TEXT
from riskplan.experiments.study_registry import EXPERIMENTS, STUDIES
from riskplan.experiments.sweeping.grid import combinations, override_parser
from riskplan.run.build import build_setup
from riskplan.run.compose import compose

FOLDERS = [experiment.folder for experiment in EXPERIMENTS]
SMALL = ["train.iterations=1", "train.samples=21", "train.eval_episodes=8", "train.bootstrap=40", "train.paths=1"]


def test_each_experiment_has_a_folder_of_its_own():
    assert len(set(FOLDERS)) == len(FOLDERS)
    assert all(folder.isidentifier() and folder.islower() for folder in FOLDERS)


@pytest.mark.slow  # every study's every job built (about 3 s in all); tests/e2e/test_reproduce.py runs them too
@pytest.mark.parametrize("experiment", EXPERIMENTS, ids=FOLDERS)
def test_each_job_of_the_experiments_sweep_is_a_valid_run(experiment):
    """...and warns of nothing but the hetero studies' constant step (their point), or a key that a variant the
    sweep runs ignores (a sweep leaves that warning out: team.aggregate=mean,trimmed_mean team.trim=1)."""
    assert experiment.seeds is None or experiment.seeds >= 1
    parsed = override_parser().parse_overrides(experiment.overrides)
    swept = {o.key_or_group for o in parsed if o.is_sweep_override()}
    jobs = combinations(parsed)
    assert jobs
    for job in jobs:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            setup = build_setup(compose([*job, *SMALL]))  # BadInput for a job that is not a valid run
        assert setup.params.train.iterations == 1
        for w in caught:
            expected = isinstance(w.message, IgnoredKey) and w.message.chooser in swept
            expected |= experiment.folder.startswith("hetero") and "breaks Assumption 6" in str(w.message)
            assert expected, str(w.message)


@pytest.mark.parametrize("name", list(STUDIES))
def test_each_study_holds_experiments_and_the_report_can_show_it(name):
    title, folders = STUDIES[name]
    assert title and folders and set(folders) <= set(FOLDERS)
    assert [figure.name for figure in FIGURES if figure.study == name]  # its figure
    assert name in STUDY_TEXT and name in STUDY_TABLES  # its section's text and table


def test_no_folder_is_in_two_studies():
    held = [folder for _, folders in STUDIES.values() for folder in folders]
    assert len(set(held)) == len(held)
