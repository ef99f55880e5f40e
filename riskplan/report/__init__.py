"""`riskplan report`: the paper's figures, tables, the objective landscape and a self-contained report.html.

    build_report([Path("outputs/sweeps/...")], Path("report"), ["png", "pdf"]) -> Path("report/report.html")

The report reads the runs' tables (parquet, or rebuilt from run.mcap when missing) and never re-simulates.
Broken or partial runs are listed with the reason and skipped; a path holding no run at all is BadInput.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from riskplan.errors import BadInput

FORMATS = ("png", "pdf", "svg")
DEFAULT_FORMATS = ("png", "pdf")


def check_formats(formats: list[str] | str) -> list[str]:
    """Normalise and validate figure formats ('png,pdf' or a list)."""
    if isinstance(formats, str):
        formats = formats.split(",")
    out = [f.strip().lower().lstrip(".") for f in formats if f.strip()]
    bad = [f for f in out if f not in FORMATS]
    if bad or not out:
        raise BadInput("--format", f"got {','.join(formats) or 'nothing'}; expected a comma-separated subset of "
                                   f"{','.join(FORMATS)}, e.g. png,pdf")
    return list(dict.fromkeys(out))


@dataclass
class Report:
    """What write_report made: the page, the collection it drew from, the figure names and those not drawn."""

    page: Path
    collection: object  # riskplan.report.collect.Collection
    figures: list[str]
    skipped: dict[str, str]


def build_report(paths: list[Path], out_dir: Path, formats: list[str] = DEFAULT_FORMATS) -> Path:
    """Find the runs under `paths`, write figures, report.csv, runs.csv and report.html to out_dir; return the page.

    Raises BadInput (before writing anything) for a path that holds no run or for an unknown format.
    """
    return write_report(paths, out_dir, formats).page


def write_report(paths: list[Path], out_dir: Path, formats: list[str] = DEFAULT_FORMATS) -> Report:
    """build_report, returning what was made (for the CLI's listing)."""
    from riskplan.report.collect import collect
    from riskplan.report.figures import make_figures, save
    from riskplan.report.page import render
    from riskplan.report.tables import comparison_table, landscape_table, runs_table

    formats = check_formats(list(formats))
    coll = collect([Path(p) for p in paths])
    comparison = comparison_table(coll)
    runs = runs_table(coll)
    landscapes = landscape_table(coll)
    specs, skipped = make_figures(coll)

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figures = []
    try:
        for spec in specs:
            figures.append((spec, save(spec, out, formats)))
    finally:
        for spec in specs:
            spec.figure.clear()
    comparison.to_csv(out / "report.csv", index=False)
    runs.to_csv(out / "runs.csv", index=False)
    if not landscapes.empty:
        landscapes.to_csv(out / "landscape.csv", index=False)
    page = out / "report.html"
    page.write_text(render(coll, figures, skipped, comparison, runs, landscapes), encoding="utf-8")
    return Report(page, coll, [spec.name for spec in specs], skipped)


__all__ = ["build_report", "write_report", "Report", "check_formats", "FORMATS", "DEFAULT_FORMATS"]
