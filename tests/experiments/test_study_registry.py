"""Every experiment of reproduce and every study of its report (riskplan.experiments.study_registry), with no test
code of their own: a folder of its own, each job of its sweep a valid run, and a study whose folders are
experiments and which the report can show (its figure, table and text)."""

from __future__ import annotations

import pytest

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
    assert experiment.seeds is None or experiment.seeds >= 1
    jobs = combinations(override_parser().parse_overrides(experiment.overrides))
    assert jobs
    for job in jobs:
        setup = build_setup(compose([*job, *SMALL]))  # BadInput for a job that is not a valid run
        assert setup.params.train.iterations == 1


@pytest.mark.parametrize("name", list(STUDIES))
def test_each_study_holds_experiments_and_the_report_can_show_it(name):
    title, folders = STUDIES[name]
    assert title and folders and set(folders) <= set(FOLDERS)
    assert [figure.name for figure in FIGURES if figure.study == name]  # its figure
    assert name in STUDY_TEXT and name in STUDY_TABLES  # its section's text and table


def test_no_folder_is_in_two_studies():
    held = [folder for _, folders in STUDIES.values() for folder in folders]
    assert len(set(held)) == len(held)
