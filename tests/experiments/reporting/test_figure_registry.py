"""Every figure of the registry (riskplan.experiments.reporting.figures.figure_registry.FIGURES), with no test code of its
own: a name of its own that the docs list, a study that reproduce has, and, on small real runs (main and study
folders), a figure within the widest allowed or a reason it is not drawn, never a failure. A new figure's line in
FIGURES puts it under these tests."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest
from support import TINY

import riskplan
from riskplan.experiments.reporting.collect import STUDIES, collect
from riskplan.experiments.reporting.figures import FIGURES, LANDSCAPE, Figure, make_figures
from riskplan.experiments.reporting.figures.drawing import WIDEST

DOCS = Path(__file__).resolve().parents[3] / "docs"
IDS = [figure.name for figure in FIGURES]


def test_each_figure_has_a_file_name_of_its_own():
    assert len(set(IDS)) == len(IDS)
    assert all(re.fullmatch(r"[a-z][a-z0-9_]*", name) for name in IDS)
    assert not any(re.fullmatch(rf"{LANDSCAPE}(_\d+)?", name) for name in IDS)  # the landscapes' names


def test_each_study_of_reproduce_has_one_figure_and_each_study_figure_a_study():
    studied = [figure.study for figure in FIGURES if figure.study]
    assert sorted(studied) == sorted(STUDIES)
    assert all(figure.main or figure.study for figure in FIGURES)  # drawn from some runs


@pytest.mark.parametrize("figure", FIGURES, ids=IDS)
def test_the_docs_list_the_figure(figure: Figure):
    assert f"`{figure.name}`" in (DOCS / "contract.md").read_text()


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """Two tiny runs of the paper world, risk-neutral and CVaR."""
    root = tmp_path_factory.mktemp("runs")
    for name, extra in {"neutral": ["risk=neutral"], "cvar": []}.items():
        riskplan.train(riskplan.compose([*TINY, *extra]), root / name)
    return root


@pytest.fixture(scope="module")
def made(runs):
    """made(root): make_figures of the runs below root, drawn once for every figure of the registry that asks."""
    drawn: dict[Path, tuple] = {}

    def of(root: Path) -> tuple:
        if root not in drawn:
            drawn[root] = make_figures(collect([root]))
        return drawn[root]

    return of


def drawn_or_why(runs: Path, figure: Figure, made) -> tuple:
    """The figure make_figures draws from `runs` under its name (in its study's folder for a study figure), or
    the reason it gives."""
    root = runs
    if figure.study:
        root = runs.parent / f"{runs.name}-{figure.study}"
        if not root.exists():  # the runs, and a copy in the study's first folder
            shutil.copytree(runs, root / "runs")
            shutil.copytree(runs, root / STUDIES[figure.study][1][0])
    specs, skipped = made(root)
    drawn = [spec for spec in specs if spec.name == figure.name]
    return (drawn[0] if drawn else None), skipped.get(figure.name)


@pytest.mark.slow
@pytest.mark.parametrize("figure", FIGURES, ids=IDS)
def test_the_figure_is_drawn_within_the_widest_or_says_why_not(runs, made, figure: Figure):
    spec, why = drawn_or_why(runs, figure, made)
    assert (spec is None) != (why is None), (spec, why)  # one or the other
    if spec is None:
        assert why and not why.startswith("failed") and "failed:" not in why, why
    else:
        assert spec.figure.get_figwidth() <= WIDEST
        assert spec.title and spec.caption
