"""The report's figures, drawn from the logged tables only (the report never re-simulates).

Every builder returns a `FigureSpec` (or the reason it is not drawn) holding a matplotlib `Figure`:

- `figure_registry`: every figure by name (FIGURES), the one list the report, its page, the docs and the tests read;
- `paper`: Figs. 1-4 of Section V (the paper's pair and titles only for a reproduction's runs);
- `beyond`: consensus by order, the reward distribution, the risk frontier, the team's θ, soft risk, the landscape;
- `studies`: the studies of riskplan reproduce beyond the paper;
- `naming`: what a figure calls its groups (only what differs between them) and its small multiples;
- `drawing`: the style, panels, curves with bands, and the files (`figure_files`).
"""

from __future__ import annotations

import matplotlib

from riskplan.experiments.reporting.collect import Collection
from riskplan.experiments.reporting.figures.beyond import (
    fig_distribution,
    fig_frontier,
    fig_landscape,
    fig_orders,
    fig_soft_risk,
    fig_thetas,
)
from riskplan.experiments.reporting.figures.drawing import STYLE, FigureSpec, figure_files, uncollected
from riskplan.experiments.reporting.figures.figure_registry import FIGURES, LANDSCAPE, Figure, study_figure
from riskplan.experiments.reporting.figures.paper import fig_consensus, fig_cvar, fig_paths, fig_team, risk_name
from riskplan.experiments.reporting.parallel import Progress


def make_figures(collected: Collection, progress: Progress | None = None) -> tuple[list[FigureSpec], dict[str, str]]:
    """Every figure the runs support, and for the others why not (name -> reason). Never raises. `progress(done,
    total)`: the builders run so far."""
    specs: list[FigureSpec] = []
    skipped: dict[str, str] = {}
    with matplotlib.rc_context(STYLE), uncollected():
        jobs = [(figure.name, figure.build) for figure in FIGURES if figure.main]
        landscapes = [
            (f"{LANDSCAPE}{'' if i == 0 else f'_{i + 1}'}", (lambda c, scan=scan, i=i: fig_landscape(c, scan, i)))
            for i, scan in enumerate(collected.landscapes)
        ]
        tell = progress or (lambda done, total: None)
        total = len(jobs) + len(landscapes) + len(collected.studies)
        for done, (name, build) in enumerate(jobs + landscapes):
            tell(done, total)
            if not collected.runs and not name.startswith(LANDSCAPE):
                skipped[name] = "no usable runs"
                continue
            try:
                result = build(collected)
            except Exception as err:
                skipped[name] = f"failed: {type(err).__name__}: {err}"
                continue
            if isinstance(result, FigureSpec):
                specs.append(result)
            elif isinstance(result, list):  # one figure of each of several things (world: each distinct world)
                specs += result
            else:
                skipped[name] = result
        for done, study in enumerate(collected.studies, start=len(jobs) + len(landscapes)):
            tell(done, total)  # reproduce's studies, each from its own runs
            name = study_figure(study.name).name
            try:
                result = study_figure(study.name).build(study.collection)
            except Exception as err:
                result = f"failed: {type(err).__name__}: {err}"
            if isinstance(result, FigureSpec):
                taken = {s.name for s in specs}
                if result.name in taken:  # the main runs drew one too
                    result.name = next(f"{name}_{k}" for k in range(2, len(taken) + 3) if f"{name}_{k}" not in taken)
                result.study = study.name
                specs.append(result)
                skipped.pop(name, None)
            else:
                skipped.setdefault(name, f"{study.name}/: {result}")
        tell(total, total)
    return specs, skipped


__all__ = [
    "FIGURES",
    "LANDSCAPE",
    "Figure",
    "FigureSpec",
    "fig_consensus",
    "fig_cvar",
    "fig_distribution",
    "fig_frontier",
    "fig_orders",
    "fig_paths",
    "fig_soft_risk",
    "fig_team",
    "fig_thetas",
    "figure_files",
    "make_figures",
    "risk_name",
]
