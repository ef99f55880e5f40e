"""report.html: one self-contained page (inline CSS, figures embedded as data: URIs, no scripts, no network)."""

from __future__ import annotations

import base64
import datetime as dt
import html
import math
from pathlib import Path

import pandas as pd

from riskplan.experiments.reporting.collect import Collection
from riskplan.experiments.reporting.figures import FIGURES, FigureSpec
from riskplan.version import __version__

CSS = """
body { font-family: "DejaVu Sans", Helvetica, Arial, sans-serif; margin: 2em auto; max-width: 1100px;
       color: #222; line-height: 1.45; padding: 0 1em; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; } h2 { font-size: 1.25em; margin-top: 2em;
     border-bottom: 1px solid #ddd; padding-bottom: 0.2em; }
.meta { color: #666; font-size: 0.9em; }
table { border-collapse: collapse; font-size: 0.85em; margin: 0.8em 0; }
th, td { border: 1px solid #ddd; padding: 0.25em 0.55em; text-align: left; vertical-align: top; }
td:first-child { min-width: 16em; }  /* the group names: readable, the numbers scroll */
th { background: #f4f4f4; } td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
figure { margin: 1.5em 0; } figure img { max-width: 100%; height: auto; border: 1px solid #eee; }
figcaption { font-size: 0.9em; color: #444; max-width: 900px; }
.skipped { color: #a33; } .note { color: #666; font-size: 0.9em; }
.wide { overflow-x: auto; }
.swatch { display: inline-block; width: 0.9em; height: 0.9em; border-radius: 2px; margin-right: 0.4em;
          vertical-align: -0.1em; }
"""


def _esc(value) -> str:
    return html.escape("" if value is None else str(value))


MISSING = "n/a"  # what a missing or non-finite value shows as (never 'nan' or 'inf')


def _missing(value) -> bool:
    """None, NaN, pd.NA or +-inf."""
    if value is None or value is pd.NA:
        return True
    try:
        return not math.isfinite(value)
    except (TypeError, ValueError):
        return False


def _text(value) -> str:
    """Any cell value, escaped; missing ones as n/a."""
    return MISSING if _missing(value) else _esc(value)


def _num(value, digits: int = 1) -> str:
    if _missing(value):
        return MISSING
    if isinstance(value, float):
        return f"{value:,.{digits}f}"
    return _esc(value)


def _interval(row: pd.Series, name: str, percent: bool = False) -> str:
    value, low, high = row.get(name), row.get(f"{name}_low"), row.get(f"{name}_high")
    if _missing(value):
        return MISSING
    scale, unit, fmt = (100.0, "%", ".1f") if percent else (1.0, "", ",.1f")
    text = f"{scale * value:{fmt}}{unit}"
    if not (_missing(low) or _missing(high)):
        text += f" [{scale * low:{fmt}}, {scale * high:{fmt}}]"
    return text


def _table(head: list[str], rows: list[list[str]], numeric: set[int] = frozenset()) -> str:
    out = ['<div class="wide"><table>', "<tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>"]
    for row in rows:
        cells = "".join(f'<td class="num">{c}</td>' if i in numeric else f"<td>{c}</td>" for i, c in enumerate(row))
        out.append(f"<tr>{cells}</tr>")
    out.append("</table></div>")
    return "\n".join(out)


def configs_section(collected: Collection) -> str:
    """The groups and the config keys that differ between them."""
    if not collected.groups:
        return "<p>No usable runs.</p>"
    keys = collected.differing
    head = ["group", "seeds"] + [f"<code>{_esc(k)}</code>" for k in keys]
    rows = []
    for g in collected.groups:
        swatch = f'<span class="swatch" style="background:{g.color}"></span>'
        rows.append(
            [swatch + _esc(g.label), _esc(", ".join(str(s) for s in g.seeds))] + [_esc(g.settings.get(k)) for k in keys]
        )
    text = (
        "<p>Runs are grouped by every config key except <code>seed</code>; the seeds of a group are pooled "
        "(curves: across-seed mean with a 95% band).</p>"
    )
    if not keys:
        c = collected.groups[0].config
        text += (
            f"<p>All runs share one configuration: experiment <code>{_esc(c.get('experiment'))}</code>, "
            f"risk <code>{_esc(c.get('risk'))}</code>, team.robots={_esc(c.get('team', {}).get('robots'))}, "
            f"train.iterations={_esc(c.get('train', {}).get('iterations'))}, "
            f"train.samples={_esc(c.get('train', {}).get('samples'))}.</p>"
        )
    return text + _table(head, rows)


def comparison_section(table: pd.DataFrame) -> str:
    """report.csv as a table with intervals."""
    if table.empty:
        return "<p>No usable runs.</p>"
    reached = [c for c in table.columns if c.startswith("reached_") and not c.endswith(("_low", "_high"))]
    head = ["group", "policy", "β", "seeds", "mean", "CVaR<sub>β</sub>", "VaR<sub>β</sub>", "P(risky)"] + [
        f"P(reach {_esc(c[len('reached_') :])})" for c in reached
    ]
    rows, degenerate = [], []
    for _, row in table.iterrows():
        flagged = not _missing(row.get("degenerate"))
        if flagged:  # it learned something degenerate: marked, and said why below the table
            degenerate.append(f"<li><b>{_esc(row['group'])}</b>: {_esc(row['degenerate'])}</li>")
        rows.append(
            [
                _esc(row["group"])
                + (' <b class="skipped" title="degenerate: see below">⚠ degenerate</b>' if flagged else ""),
                _esc(row["policy"]),
                f"{row['beta']:g}",
                _esc(row["seeds"]),
                _interval(row, "mean"),
                _interval(row, "cvar"),
                _interval(row, "value_at_risk"),
                _interval(row, "risky_fraction", True),
            ]
            + [_interval(row, c, True) for c in reached]
        )
    methods = sorted(set(table["interval"]))
    note = (
        f'<p class="note">Final policies on their evaluation episodes (team runs: the network average θ̄). '
        f"Brackets: {'; '.join(_esc(m) for m in methods)}. P(risky): share of episodes with at least one step "
        f"in a risky region. The same numbers, unrounded, are in <code>report.csv</code>.</p>"
    )
    if degenerate:
        note += (
            f'<p class="skipped"><b>{len(degenerate)} group(s) learned something degenerate</b> (report.csv\'s '
            f"<code>degenerate</code>):</p><ul>{''.join(degenerate)}</ul>"
        )
    return _table(head, rows, numeric=set(range(2, len(head)))) + note


def landscape_section(table: pd.DataFrame) -> str:
    if table.empty:
        return ""
    head = [
        "landscape",
        "β",
        "grid",
        "max mean at θ",
        "max CVaR at θ",
        "group",
        "objective",
        "final θ",
        "distance to optimum",
        "smoothed optimum (distance)",
        "objective at final θ",
        "gap to grid max",
        "SE at max",
    ]
    rows = []
    for _, r in table.iterrows():
        gap_percent = r.get("gap_percent")
        rows.append(
            [
                _esc(Path(r["landscape"]).name),
                _num(r.get("beta"), 3),
                f"{_whole(r.get('points'))}² × {_whole(r.get('episodes'))}",
                f"{_text(r.get('best_mean_theta'))}: {_num(r.get('best_mean'))}",
                f"{_text(r.get('best_cvar_theta'))}: {_num(r.get('best_cvar'))}",
                _text(r.get("group")),
                _text(r.get("objective")),
                _text(r.get("final_theta")),
                _num(r.get("distance_to_optimum")),
                f"{_text(r.get('smoothed_optimum_theta'))} ({_num(r.get('distance_to_smoothed_optimum'))})"
                if not _missing(r.get("distance_to_smoothed_optimum"))
                else MISSING,
                _num(r.get("landscape_at_final")),
                _num(r.get("gap_to_optimum")) + ("" if _missing(gap_percent) else f" ({_num(gap_percent, 2)}%)")
                if not _missing(r.get("gap_to_optimum"))
                else MISSING,
                _num(r.get("standard_error_at_optimum")),
            ]
        )
    return (
        "<h2>Landscape optima</h2>"
        + _table(head, rows, numeric={8, 9, 10, 11, 12})
        + '<p class="note">Objective: CVaR for risk-averse groups, mean for risk-neutral ones, as evaluated on '
        "the landscape grid; distance is Euclidean in θ between the across-seed mean final θ and the grid "
        "maximum (smoothed: the maximum of the 3×3 moving average, robust to single noisy points); the gap is the "
        "grid maximum minus the grid value nearest the final θ; SE is the estimator's "
        "standard error at the maximum (one grid point, its episodes), the scale of the noise in the "
        "surface.</p>"
    )


def soft_risk_section(table: pd.DataFrame | None) -> str:
    """soft_risk.csv: per seed, each soft-risk group against its twin with the paper's fixed beta."""
    if table is None or table.empty:
        return ""
    reached = [c for c in table.columns if c.startswith("reached_")]
    head = (
        ["group", "schedule", "seed", "mean", "CVaR<sub>β</sub>"]
        + [f"P(reach {_esc(c[len('reached_') :])})" for c in reached]
        + ["final θ"]
    )
    rows = []
    for _, r in table.iterrows():
        schedule = _esc(r["schedule"]) + (
            ""
            if r["schedule"] == "none"
            else f" ({_num(r.get('schedule_start'), 2)} → β = {r['beta']:g} over "
            f"{_whole(r.get('schedule_iterations'))} iterations)"
        )
        rows.append(
            [_esc(r["group"]), schedule, _esc(r["seed"]), _num(r.get("mean")), _num(r.get("cvar"))]
            + [_num(100 * r[c], 1) + "%" if not _missing(r[c]) else MISSING for c in reached]
            + [_text(r.get("theta_final"))]
        )
    return (
        "<h2>Soft risk</h2>"
        + _table(head, rows, numeric=set(range(3, 5 + len(reached))))
        + '<p class="note">Each seed\'s final policy on its evaluation episodes, CVaR at risk.beta. A soft-risk '
        "schedule (CeSoR) ascends CVaR at a level β_l that falls from risk.schedule.start to β over "
        "risk.schedule.iterations; kind none is the paper's fixed β. The same numbers are in "
        "<code>soft_risk.csv</code>.</p>"
    )


STUDY_TEXT = {  # the question each study of riskplan reproduce answers, above its table
    "measures": (
        "Risk measures",
        "One robot in the paper world from the paper's θ0, trained with each risk measure at its group defaults "
        "(<code>risk=cvar,neutral,wang,mean_cvar,entropic</code>). The trained objective is each measure's own value "
        "on the evaluation episodes; CVaR is at the common level β.",
    ),
    "policies": (
        "Policies that see more",
        "One robot from θ0 = 0 under CVaR: the paper's policy (the sources' signals), a policy that also sees the "
        "risky region, and a tabular policy (one logit per cell and move). Does the richer policy reach the safe "
        "source where the paper's does not, and how close does each come to the best CVaR of the paper's "
        "two-parameter policy over the landscape's grid?",
    ),
    "hetero_team": (
        "A heterogeneous team",
        "Robots that start apart (<code>team.starts</code>) have different objectives, so Δ^i − Δ^j does not vanish "
        "at the optimum: with a constant step, combine-then-adapt (eq. 14) keeps a consensus error of order "
        "ε·‖Δ^i − Δ^j‖ and its average θ̄ is off the optimum by O(ε), while gradient tracking removes both. The "
        "floor is the mean consensus error over the last quarter of the iterations; the disagreement is the largest "
        "distance between two robots' θ averaged over that quarter (sampling noise averages out, a systematic "
        "floor does not); the gap and the distance are to the centralized run of the same seed.",
    ),
    "floor_plan": (
        "A floor plan with a watched corridor",
        "One robot on a map read from ROS map files (<code>experiment=floor_plan</code>): a hallway leads to the safe "
        "source, a shorter corridor an adversary watches (a risky region drawn as an image mask) to the risky one. "
        "Which way does each policy learn to go? Export the runs with <code>riskplan export DIR --to ros2</code> to "
        "play them in Foxglove or RViz.",
    ),
    "faults": (
        "A Byzantine robot and resilient consensus",
        "One robot sends a fixed θ from the first iteration. With the plain mean (eq. 14) every healthy robot "
        "averages it in; a trimmed mean that drops the F largest and smallest received values per coordinate "
        "ignores it. The figures are the healthy robots' network average θ̄ on its evaluation episodes, against "
        "the fault-free team of the same seed.",
    ),
}


def study_section(name: str, table: pd.DataFrame, figures: list[tuple[FigureSpec, dict]], collected=None) -> str:
    """A study beyond the paper: what it asks, the groups it compares, its table and its figure."""
    if (table is None or table.empty) and not figures:
        return ""
    title, text = STUDY_TEXT[name]
    parts = [f'<h2 id="study-{_esc(name)}">{_esc(title)}</h2>', f"<p>{text}</p>"]
    if collected is not None:
        parts.append(configs_section(collected))
    if table is not None and not table.empty:
        parts.append(STUDY_TABLES[name](table))
        parts.append(
            f'<p class="note">Brackets: 95% Student-t intervals over the seeds (one seed: over its evaluation '
            f"episodes). The same numbers, unrounded, are in <code>{_esc(name)}.csv</code>.</p>"
        )
    parts += [figure_html(spec, files) for spec, files in figures]
    return "\n".join(parts)


def _reached(table: pd.DataFrame) -> list[str]:
    return [c for c in table.columns if c.startswith("reached_") and not c.endswith(("_low", "_high"))]


def _outcome_head(reached: list[str]) -> list[str]:
    """The outcome columns the study tables share: mean, CVaR, P(risky), then P(reach) of each source."""
    return ["mean", "CVaR<sub>β</sub>", "P(risky)"] + [f"P(reach {_esc(c[len('reached_') :])})" for c in reached]


def _outcomes(row: pd.Series, reached: list[str], cvar_note: str = "") -> list[str]:
    """A row's cells under _outcome_head, each with its interval (`cvar_note` follows the CVaR)."""
    return [
        _interval(row, "mean"),
        _interval(row, "cvar") + cvar_note,
        _interval(row, "risky_fraction", True),
    ] + [_interval(row, c, True) for c in reached]


def _measures_html(table: pd.DataFrame) -> str:
    reached = _reached(table)
    head = ["measure", "seeds", "trained objective"] + _outcome_head(reached)
    rows = [
        [_esc(r["name"]), _esc(r["seeds"]), _interval(r, "objective")] + _outcomes(r, reached, f" (β={r['beta']:g})")
        for _, r in table.iterrows()
    ]
    main = _table(head, rows, numeric=set(range(2, len(head))))
    under = [c for c in table.columns if c.startswith("under_")]
    if not under:
        return main
    names = dict(zip(table["measure"], table["name"]))
    cross = _table(
        ["final policy of ↓, scored under →"]
        + [_esc(names.get(c[len("under_") :], c[len("under_") :])) for c in under],
        [[_esc(r["name"])] + [_num(r[c]) for c in under] for _, r in table.iterrows()],
        numeric=set(range(1, len(under) + 1)),
    )
    return (
        main
        + '<p class="note">Each final policy scored under every measure (its evaluation episodes, the mean over its '
        "seeds): a measure whose own policy is not the best under it stopped short of its optimum.</p>" + cross
    )


def _policies_html(table: pd.DataFrame) -> str:
    reached = _reached(table)
    seeds = [c for c in table.columns if c.startswith("seeds_reaching_")]
    head = (
        ["policy", "parameters", "seeds"]
        + _outcome_head(reached)
        + [f"seeds mostly reaching {_esc(c[len('seeds_reaching_') :])}" for c in seeds]
        + ["landscape's best CVaR (θ)", "gap to it"]
    )
    rows = [
        [_esc(r["policy"]), _esc(r["theta_length"]), _esc(r["seeds"])]
        + _outcomes(r, reached)
        + [f"{_whole(r[c])} of {_whole(r['seeds'])}" for c in seeds]
        + [
            f"{_num(r.get('landscape_best_cvar'))} {_text(r.get('landscape_best_theta'))}",
            f"{_num(r.get('gap_to_landscape_best'))} ({_num(r.get('gap_percent'), 1)}%)"
            if not _missing(r.get("gap_to_landscape_best"))
            else MISSING,
        ]
        for _, r in table.iterrows()
    ]
    return _table(head, rows, numeric=set(range(1, len(head))))


def _hetero_html(table: pd.DataFrame) -> str:
    head = [
        "order (graph)",
        "ε",
        "seeds",
        "consensus error floor",
        "persistent disagreement",
        "team objective at θ̄",
        "gap to centralized",
        "‖θ̄ − θ̄<sub>centralized</sub>‖",
    ]
    rows = []
    for _, r in table.iterrows():
        name = "centralized (complete graph, exact average)" if r["centralized"] else f"{r['order']} ({r['graph']})"
        rows.append(
            [
                _esc(name),
                f"{r['step_size']:g}" + ("" if r["constant_step"] else " (last)"),
                _esc(r["seeds"]),
                _interval_sig(r, "consensus_floor"),
                _interval_sig(r, "theta_disagreement"),
                _interval(r, "team_objective"),
                _interval(r, "gap_to_central")
                + ("" if _missing(r.get("gap_percent")) else f" ({r['gap_percent']:.2f}%)"),
                _interval_sig(r, "distance_to_central"),
            ]
        )
    return _table(head, rows, numeric=set(range(1, len(head))))


def _interval_sig(row: pd.Series, name: str) -> str:
    """value [low, high] to three significant figures (small distances)."""
    value, low, high = row.get(name), row.get(f"{name}_low"), row.get(f"{name}_high")
    if _missing(value):
        return MISSING
    text = f"{value:.3g}"
    if not (_missing(low) or _missing(high)):
        text += f" [{low:.3g}, {high:.3g}]"
    return text


def _faults_html(table: pd.DataFrame) -> str:
    reached = _reached(table)
    head = (
        ["faults, aggregation", "seeds"]
        + _outcome_head(reached)
        + ["CVaR vs fault-free", "largest |difference|", "within 5%"]
    )
    rows = []
    for _, r in table.iterrows():
        within = r.get("within_tolerance")
        rows.append(
            [_esc(r["name"]), _esc(r["seeds"])]
            + _outcomes(r, reached)
            + [
                _interval(r, "cvar_vs_fault_free", True),
                MISSING
                if _missing(r.get("worst_cvar_vs_fault_free"))
                else f"{100 * r['worst_cvar_vs_fault_free']:.2f}%",
                MISSING if within is None or _missing(within) else ("yes" if within else "no"),
            ]
        )
    return _table(head, rows, numeric=set(range(1, len(head) - 1)))


def _floor_plan_html(table: pd.DataFrame) -> str:
    reached = _reached(table)
    head = ["policy", "seeds"] + _outcome_head(reached)
    rows = [
        [_esc(r["name"]), _esc(r["seeds"])] + _outcomes(r, reached, f" (β={r['beta']:g})") for _, r in table.iterrows()
    ]
    return _table(head, rows, numeric=set(range(2, len(head))))


STUDY_TABLES = {
    "floor_plan": _floor_plan_html,
    "measures": _measures_html,
    "policies": _policies_html,
    "hetero_team": _hetero_html,
    "faults": _faults_html,
}


def _whole(value) -> str:
    """A count (points, episodes) that may be missing or stored as a float."""
    if _missing(value):
        return MISSING
    try:
        return f"{int(value)}" if float(value) == int(value) else _esc(value)
    except (TypeError, ValueError):
        return _esc(value)


def runs_section(runs: pd.DataFrame) -> str:
    head = ["run directory", "status", "group", "seed", "note / reason", "mean", "CVaR", "final θ"]
    rows = []
    for _, r in runs.iterrows():
        status = _esc(r["status"])
        if r["status"] == "skipped":
            status = f'<span class="skipped">{status}</span>'
        rows.append(
            [
                f"<code>{_esc(r['path'])}</code>",
                status,
                "" if _missing(r.get("group")) else _esc(r.get("group")),
                "" if _missing(r.get("seed")) else _esc(int(r["seed"])),
                "" if _missing(r.get("note")) else _esc(r.get("note")),
                "" if r["status"] != "used" else _num(r.get("mean")),
                "" if r["status"] != "used" else _num(r.get("cvar")),
                "" if _missing(r.get("theta_final")) else _esc(r.get("theta_final")),
            ]
        )
    return _table(head, rows, numeric={5, 6})


def figure_html(spec: FigureSpec, files: dict[str, bytes]) -> str:
    """The figure's page image inline, linking its files (figures.figure_files: {format: bytes, "page": PNG})."""
    data = base64.b64encode(files["page"]).decode("ascii")
    links = " · ".join(
        f'<a href="{_esc(f"{spec.name}.{fmt}")}">{_esc(fmt.upper())}</a>' for fmt in files if fmt != "page"
    )
    return (
        f'<figure id="{_esc(spec.name)}"><img src="data:image/png;base64,{data}" alt="{_esc(spec.title)}">'
        f"<figcaption><b>{_esc(spec.title)}.</b> {_esc(spec.caption)}"
        + (f' <span class="note">Files: {links}.</span>' if links else "")
        + "</figcaption></figure>"
    )


def render(
    collected: Collection,
    figures: list[tuple[FigureSpec, dict]],
    skipped: dict[str, str],
    comparison: pd.DataFrame,
    runs: pd.DataFrame,
    landscapes: pd.DataFrame,
    soft_risk: pd.DataFrame | None = None,
    studies: dict[str, pd.DataFrame] | None = None,
) -> str:
    """The whole page (`studies`: the tables of the studies beyond the paper, study_tables.study_tables)."""
    worlds, paper, extra, of_study = _sort_figures(figures)
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        "<title>riskplan report</title>",
        f"<style>{CSS}</style></head><body>",
        "<h1>riskplan report</h1>",
        _meta(collected),
    ]
    if collected.broken:
        items = "".join(f"<li><code>{_esc(b.path)}</code>: {_esc(b.reason)}</li>" for b in collected.broken)
        parts.append(
            f'<p class="skipped"><b>Skipped {len(collected.broken)} broken or partial run(s):</b></p><ul>{items}</ul>'
        )
    if worlds:
        parts.append(f"<h2>The world{'s' * (len(worlds) > 1)}</h2>")
        parts += [figure_html(spec, files) for spec, files in worlds]
    parts += [
        "<h2>Configurations that differ</h2>",
        configs_section(collected),
        "<h2>Final policies</h2>",
        comparison_section(comparison),
    ]
    parts += _figure_sections(paper, extra)
    parts.append(landscape_section(landscapes))
    parts.append(soft_risk_section(soft_risk))
    for name, own_figures in of_study.items():
        own = [s.collection for s in collected.studies if s.name == name]
        parts.append(study_section(name, (studies or {}).get(name), own_figures, own[0] if own else None))
    if skipped:
        items = "".join(f"<li><b>{_esc(k)}</b>: {_esc(v)}</li>" for k, v in skipped.items())
        parts.append(f'<h2>Figures not drawn</h2><ul class="note">{items}</ul>')
    parts += ["<h2>Runs</h2>", runs_section(runs), "</body></html>"]
    return "\n".join(parts)


def _meta(collected: Collection) -> str:
    """The line under the title: version, time, inputs and what they held."""
    now = dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    inputs = ", ".join(f"<code>{_esc(p)}</code>" for p in collected.inputs)
    counts = (
        f"{len(collected.runs)} run(s) in {len(collected.groups)} group(s), {len(collected.landscapes)} landscape(s), "
        f"{len(collected.broken)} skipped"
    )
    if collected.studies:
        studied = sum(len(s.collection.runs) for s in collected.studies)
        counts += f" · {studied} run(s) in {len(collected.studies)} stud{'y' if len(collected.studies) == 1 else 'ies'} beyond the paper"
    return f'<p class="meta">riskplan {_esc(__version__)} · generated {now} · from {inputs} · {counts}</p>'


def _sort_figures(figures: list[tuple[FigureSpec, dict]]) -> tuple[list, list, list, dict]:
    """The figures by where the page shows them: the worlds (first, a section of their own), the paper's figures
    (fig...), the others, and each study's (a section each, in FIGURES' order; by its study, or a name starting
    with its study figure's)."""
    studied = {figure.study: figure.name for figure in FIGURES if figure.study}
    of_study = {
        name: [f for f in figures if f[0].study == name or (not f[0].study and f[0].name.startswith(stem))]
        for name, stem in studied.items()
    }
    taken = {id(f) for fs in of_study.values() for f in fs}
    paper = [f for f in figures if f[0].name.startswith("fig") and id(f) not in taken]
    extra = [f for f in figures if not f[0].name.startswith("fig") and id(f) not in taken]
    worlds = [f for f in extra if f[0].name == "world" or f[0].name.startswith("world_")]
    extra = [f for f in extra if f not in worlds]
    return worlds, paper, extra, of_study


def _figure_sections(paper: list, extra: list) -> list[str]:
    """A reproduction's runs: the paper's figures under the paper's heading, then the others; a user's runs: all
    under plain titles."""
    if any(spec.paper for spec, _ in paper):
        parts = ["<h2>The paper's figures (Section V)</h2>"] + [figure_html(spec, files) for spec, files in paper]
        if extra:
            parts.append("<h2>Beyond the paper</h2>")
            parts += [figure_html(spec, files) for spec, files in extra]
        return parts
    if paper or extra:
        return ["<h2>Figures</h2>"] + [figure_html(spec, files) for spec, files in paper + extra]
    return []
