"""Figures that follow what was swept (riskplan.experiments.reporting.figures): a curve per β of a β sweep, named by
β alone in a legend outside the axes; small multiples past eight groups; no figure wider than 2,000 px and no
library warning while one is drawn; the paper's titles only for a reproduction's runs; Fig. 3's centralized curves
seen beside the team's. The names on synthetic groups, the figures on tiny real runs."""

from __future__ import annotations

import io
import shutil
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from PIL import Image
from support import TINY

from riskplan import compose, train
from riskplan.experiments.reporting.collect import RunInfo, collect, flatten, group_runs
from riskplan.experiments.reporting.figures import fig_cvar, fig_paths, fig_team, figure_files, make_figures
from riskplan.experiments.reporting.figures.naming import MAX_CURVES, layout, names
from riskplan.experiments.reporting.page import render

BETAS = (0.05, 0.1, 0.2)
SAMPLES = (200, 250, 300)
WIDEST_PX = 2000


# ------------------------------------------------------------------------------------------------ names, no runs
def fake(config: dict, seed: int = 0) -> RunInfo:
    config = {"seed": seed, "risk": {"measure": "cvar", "beta": 0.1}, **config}
    run = SimpleNamespace(path=Path(f"/runs/{config}"), config=config, summary={}, metrics=pd.DataFrame())
    return RunInfo(run, {k: v for k, v in flatten(config).items() if k != "seed"}, rebuilt=False)


def grouped(configs: list[dict]):
    groups, _ = group_runs([fake(c) for c in configs])
    return groups


def test_a_name_says_only_what_differs_in_a_few_words():
    betas = grouped([{"risk": {"measure": "cvar", "beta": b}, "train": {"iterations": 200}} for b in BETAS])
    assert names(betas) == ["β=0.05", "β=0.1", "β=0.2"]
    teams = grouped(
        [{"team": {"robots": n, "graph": g, "delay": {"max": 0}}} for n, g in ((3, "line"), (5, "ring"), (5, "line"))]
    )
    assert sorted(names(teams)) == [
        "distributed N=3, graph=line",
        "distributed N=5, graph=line",
        "distributed N=5, graph=ring",
    ]
    pair = grouped([{"risk": {"measure": "neutral", "beta": 0.2}}, {"risk": {"measure": "cvar", "beta": 0.1}}])
    assert sorted(names(pair)) == ["risk-averse (CVaR β=0.1)", "risk-neutral"]  # the measure's label, as a table's
    mixed = grouped([{"risk": {"measure": m, "beta": b}} for m, b in (("neutral", 0.1), ("cvar", 0.1), ("cvar", 0.2))])
    assert sorted(names(mixed)) == ["risk-averse (CVaR β=0.1)", "risk-averse (CVaR β=0.2)", "risk-neutral"]
    assert all(len(n) < 30 for n in names(betas) + names(teams) + names(mixed))


def test_a_value_is_named_as_typed_never_as_mathtext():
    """A swept value is text: '$x^2$' keeps its dollars (escaped for matplotlib, which draws '\\$' as '$'), so the
    legend reads as typed and '$\\nosuchcmd$', which mathtext cannot parse, no longer loses the figure."""
    odd = grouped([{"team": {"address": a}} for a in ("$x^2$", "$\\nosuchcmd$")])
    assert sorted(names(odd)) == ["address=\\$\\nosuchcmd\\$", "address=\\$x^2\\$"]
    figure = Figure()
    for name in names(odd):
        figure.text(0, 0, name)
    FigureCanvasAgg(figure).draw()  # raised ValueError (mathtext) before


def test_past_eight_groups_one_panel_per_value_of_a_key():
    grid = grouped([{"risk": {"measure": "cvar", "beta": b}, "team": {"graph": g}} for b in BETAS for g in "ab"])
    assert len(layout(grid).panels) == 1  # six: one panel
    grid = grouped(
        [{"risk": {"measure": "cvar", "beta": b}, "team": {"graph": g}} for b in (*BETAS, 0.5) for g in "abc"]
    )
    lay = layout(grid)  # twelve: 3 panels of 4 betas (fewer panels than 4 of 3 graphs)
    assert [p.title for p in lay.panels] == ["graph=a", "graph=b", "graph=c"]
    assert all(p.names == ["β=0.05", "β=0.1", "β=0.2", "β=0.5"] for p in lay.panels)
    assert len(lay.legend()) == 4  # one colour per β, the same in every panel
    one_key = grouped([{"risk": {"measure": "cvar", "beta": b / 100}} for b in range(1, 13)])
    lay = layout(one_key)  # one key only: a panel per group
    assert len(lay.panels) == 12 and all(len(p.groups) == 1 for p in lay.panels)
    assert all(len(p.groups) <= MAX_CURVES for p in layout(grid).panels)


# ------------------------------------------------------------------------------------------------ real runs
@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    """A β sweep (2 seeds), a β x train.samples grid (9 groups), a team and its centralized runs, and a
    reproduction's single/ folder (the paper's pair)."""
    out = tmp_path_factory.mktemp("swept")
    for beta in BETAS:
        for seed in (0, 1):
            train(compose([*TINY, f"risk.beta={beta}", f"seed={seed}"]), out / "beta" / f"beta={beta},seed={seed}")
        for samples in SAMPLES:
            name = f"beta={beta},samples={samples}"
            train(compose([*TINY, f"risk.beta={beta}", f"train.samples={samples}"]), out / "grid" / name)
    for seed in (0, 1):
        train(compose([*TINY, "experiment=paper_team", f"seed={seed}"]), out / "teams" / f"team,seed={seed}")
        shutil.copytree(out / "beta" / f"beta=0.1,seed={seed}", out / "teams" / f"central,seed={seed}")
        shutil.copytree(out / "beta" / f"beta=0.1,seed={seed}", out / "repro" / "single" / f"cvar,seed={seed}")
        train(compose([*TINY, "risk=neutral", f"seed={seed}"]), out / "repro" / "single" / f"neutral,seed={seed}")
    return out


def labelled(ax) -> list:
    return [line for line in ax.get_lines() if not line.get_label().startswith("_")]


@pytest.mark.slow
def test_a_beta_sweep_draws_a_curve_per_beta_named_by_beta_outside_the_axes(root):
    collected = collect([root / "beta"])
    spec = fig_cvar(collected)
    (ax,) = spec.figure.axes
    lines = {line.get_label(): line for line in labelled(ax)}
    assert set(lines) == {f"β={b:g}" for b in BETAS} and all(len(label) < 30 for label in lines)
    assert len(ax.collections) == 3  # a band each (2 seeds)
    for beta in BETAS:
        runs = [root / "beta" / f"beta={beta},seed={s}" for s in (0, 1)]
        expected = np.mean([pd.read_parquet(r / "metrics.parquet").query("robot == 0").cvar for r in runs], axis=0)
        np.testing.assert_allclose(lines[f"β={beta:g}"].get_ydata(), expected, rtol=1e-12)
    assert ax.get_legend() is None
    (legend,) = spec.figure.legends
    assert sorted(t.get_text() for t in legend.get_texts()) == sorted(lines)
    renderer = spec.figure.canvas.get_renderer()
    spec.figure.draw_without_rendering()
    box, frame = legend.get_window_extent(renderer), ax.get_window_extent(renderer)
    assert not box.overlaps(frame)  # beside the axes, never over the curves
    paths = fig_paths(collected)  # Fig. 1: a panel of paths per β
    assert sorted(a.get_title() for a in paths.figure.axes) == [f"β={b:g}, seed 0" for b in BETAS]


@pytest.mark.slow
def test_past_eight_groups_a_figure_draws_small_multiples(root):
    collected = collect([root / "grid"])
    assert len(collected.groups) == 9
    specs, _ = make_figures(collected)
    figures = {s.name: s.figure for s in specs}
    curves = figures["fig2_cvar"].axes
    assert [ax.get_title() for ax in curves] == [f"β={b:g}" for b in BETAS]
    assert all(len(labelled(ax)) == 3 for ax in curves)  # every group drawn, 3 to a panel
    assert [t.get_text() for t in figures["fig2_cvar"].legends[0].get_texts()] == [f"samples={n}" for n in SAMPLES]
    for name in ("reward_distribution", "risk_frontier"):
        assert len(figures[name].axes) == 3, name
    assert len(figures["fig1_paths"].axes) == 9  # a world per group


def all_figures(root: Path) -> list:
    """Every figure of each collection, drawn to PNG and PDF, with the warnings raised while doing it."""
    drawn, caught = [], []
    for folder in ("beta", "grid", "teams", "repro"):
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            specs, _ = make_figures(collect([root / folder]))
            for spec in specs:
                files = figure_files(spec, ["png", "pdf"])
                assert not isinstance(files, str), (folder, spec.name, files)
                drawn.append((folder, spec, files))
        caught += [(folder, w) for w in seen]
    return drawn, caught


@pytest.mark.slow
def test_no_figure_is_wider_than_2000_px_and_none_warns(root):
    drawn, caught = all_figures(root)
    assert {spec.name for _, spec, _ in drawn} >= {"fig1_paths", "fig2_cvar", "fig3_team", "reward_distribution"}
    for folder, spec, files in drawn:
        width = Image.open(io.BytesIO(files["png"])).width
        assert width <= WIDEST_PX, (folder, spec.name, width)
    assert [f"{folder}: {w.category.__name__}: {w.message} ({w.filename})" for folder, w in caught] == []


@pytest.mark.slow
def test_the_papers_titles_only_for_a_reproductions_runs(root):
    for folder, paper in (("beta", False), ("repro", True)):
        collected = collect([root / folder])
        specs, skipped = make_figures(collected)
        page = render(collected, [(s, {"page": b""}) for s in specs], skipped, *[pd.DataFrame()] * 3)
        titles = {s.name: s.title for s in specs}
        assert ("The paper's figures (Section V)" in page) is paper
        if paper:
            assert titles["fig1_paths"].startswith("Fig. 1") and titles["fig2_cvar"].startswith("Fig. 2")
            fig2 = next(s for s in specs if s.name == "fig2_cvar")
            assert [t.get_text() for t in fig2.figure.legends[0].get_texts()] == [
                "risk-neutral",
                "risk-averse (CVaR β=0.1)",
            ]
        else:
            assert not any("paper" in t.lower() or "Fig." in t for t in titles.values()), titles
            assert "<h2>Figures</h2>" in page and "Beyond the paper" not in page


@pytest.mark.slow
def test_fig3_shows_the_centralized_curves_beside_the_teams(root):
    spec = fig_team(collect([root / "teams"]))
    mean, cvar, difference = spec.figure.axes
    for ax in (mean, cvar):
        team, central = (
            next(ln for ln in labelled(ax) if ln.get_label() == n) for n in ("distributed N=3", "centralized")
        )
        assert team.get_color() != central.get_color()
        assert (team.get_linestyle(), central.get_linestyle()) == ("-", "--") and central.get_marker() == "o"
        assert central.get_zorder() > team.get_zorder()  # drawn over the team's curve, which it would hide under
    assert difference.get_title() == "(c) difference" and len(difference.get_lines()) == 3  # mean, CVaR and zero


WIDE = ["world.size=[48,12]", "world.regions.1.rect=[0,0,47,11]"]  # four times as wide as high


@pytest.mark.slow  # a run trained and its figure drawn (near a second)
@pytest.mark.parametrize("world", [[], WIDE], ids=["paper", "wide"])
def test_fig1_fills_its_width_with_the_world_and_its_legend_sits_close(tmp_path, world):
    """Fig. 1's world at its aspect fills the figure's width (a wide one uses the widest figure), and the legend
    sits right below the axis labels: no empty band between them."""
    for risk in ("neutral", "cvar"):
        train(compose([*TINY, f"risk={risk}", *world]), tmp_path / risk)
    figure = fig_paths(collect([tmp_path])).figure
    figure.canvas.draw()
    renderer = figure.canvas.get_renderer()
    (ax,) = figure.axes
    (legend,) = figure.legends
    dpi = figure.dpi
    box, key = ax.get_tightbbox(renderer), legend.get_window_extent(renderer)
    assert (box.y0 - key.y1) / dpi < 0.2  # inches between the x label and the legend's frame
    drawn = ax.get_window_extent(renderer)  # the cells' area, equal-aspect
    assert drawn.width / drawn.height == pytest.approx(4.0 if world else 1.0, rel=0.02)
    assert drawn.width / figure.bbox.width > (0.8 if world else 0.75)
