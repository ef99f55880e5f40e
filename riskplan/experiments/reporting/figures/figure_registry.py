"""The report's figures by name: the one list that `riskplan report` draws (in this order), that the report page
sorts into its sections, and that the docs and the registry-wide tests (tests/experiments/reporting/
test_figure_registry.py) read.

A new figure is a `fig_<name>(collected) -> FigureSpec | str` (the figure, or why the runs do not support it) in a
module of this package, and its line in FIGURES (docs/extending.md has a worked example). The landscapes are drawn
apart, one figure per landscape found (LANDSCAPE, LANDSCAPE_2, ...).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from riskplan.experiments.reporting.collect import Collection
from riskplan.experiments.reporting.figures.beyond import (
    fig_distribution,
    fig_frontier,
    fig_orders,
    fig_soft_risk,
    fig_thetas,
)
from riskplan.experiments.reporting.figures.drawing import FigureSpec
from riskplan.experiments.reporting.figures.paper import fig_consensus, fig_cvar, fig_paths, fig_team
from riskplan.experiments.reporting.figures.studies import fig_faults, fig_hetero, fig_measures, fig_policies
from riskplan.experiments.reporting.figures.world_picture import fig_world

LANDSCAPE = "landscape"  # the landscapes' figures: landscape, landscape_2, ... (figures.beyond.fig_landscape)


@dataclass(frozen=True)
class Figure:
    """A figure of the report: its files' name (<name>.png, .pdf, .svg), how it is drawn, and what it shows."""

    name: str
    build: Callable[[Collection], FigureSpec | list[FigureSpec] | str]  # a list: <name>, <name>_2, ...
    about: str  # what it shows, in a few words
    study: str = ""  # the study of reproduce (collect.STUDIES) whose own runs it is drawn from too, if any
    main: bool = True  # drawn from the runs given (False: from its study's runs only)


def fig_floor_plan(collected: Collection) -> FigureSpec | str:
    """The floor-plan study of riskplan reproduce: each policy's sampled paths on the map (Fig. 1's drawing)."""
    spec = fig_paths(collected)
    if isinstance(spec, FigureSpec):
        spec.name, spec.title = "floor_plan_paths", "A floor plan with a watched corridor: sampled paths"
    return spec


FIGURES = (
    Figure("world", fig_world, "each distinct world of the runs, as riskplan check --draw draws it"),
    Figure("fig1_paths", fig_paths, "the paper's Fig. 1: sampled paths of each policy"),
    Figure("fig2_cvar", fig_cvar, "the paper's Fig. 2: CVaR and the mean over the iterations"),
    Figure("fig3_team", fig_team, "the paper's Fig. 3: the team's CVaR against the centralized run"),
    Figure("fig4_consensus", fig_consensus, "the paper's Fig. 4: the consensus error over the iterations"),
    Figure("consensus_orders", fig_orders, "the consensus error of each consensus order"),
    Figure("reward_distribution", fig_distribution, "the final policies' total rewards, VaR and CVaR marked"),
    Figure("risk_frontier", fig_frontier, "mean against CVaR of the final policies, by beta"),
    Figure("team_thetas", fig_thetas, "each robot's theta over the iterations"),
    Figure("soft_risk", fig_soft_risk, "soft risk (risk.schedule) against the fixed beta"),
    Figure("risk_measures", fig_measures, "each risk measure's final policy", study="measures"),
    Figure("richer_policies", fig_policies, "policies that see more, and a tabular one", study="policies"),
    Figure("hetero_team", fig_hetero, "a heterogeneous team: gradient tracking against eq. (14)", study="hetero_team"),
    Figure("faults", fig_faults, "a Byzantine robot: the mean against resilient rules", study="faults"),
    Figure("floor_plan_paths", fig_floor_plan, "sampled paths on a floor plan's map", study="floor_plan", main=False),
)


def study_figure(study: str) -> Figure:
    """The figure drawn from a study's own runs."""
    return next(figure for figure in FIGURES if figure.study == study)
