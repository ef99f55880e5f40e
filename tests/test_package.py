"""Package hygiene: licence and citation files that agree with the package, shell completion, a readable Run in a
terminal and in a notebook, and progress bars in notebooks and terminals."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import tomllib
import yaml
from rich.console import Console
from support import TINY
from typer.testing import CliRunner

import riskplan
import riskplan.util.progress as progress
from riskplan.cli import app

ROOT = Path(__file__).resolve().parents[1]
PAPER_TITLE = "Risk-Averse Sensor Planning using Distributed Policy Gradient"  # Ma, Dentcheva, Zavlanos, ACC 2017


def test_the_licence_file_is_the_one_pyproject_declares():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == {"file": "LICENSE"}
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
    assert "License :: OSI Approved :: MIT License" in project["classifiers"]


def test_citation_cff_cites_this_version_and_the_paper():
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert citation["cff-version"] == "1.2.0" and citation["type"] == "software"
    assert citation["version"] == riskplan.__version__ and citation["license"] == "MIT"
    (paper,) = citation["references"]
    assert paper["type"] == "conference-paper"
    assert paper["title"] == PAPER_TITLE
    assert [a["family-names"] for a in paper["authors"]] == ["Ma", "Dentcheva", "Zavlanos"]
    assert paper["collection-title"] == "2017 American Control Conference (ACC)" and paper["year"] == 2017
    # the docs cite the paper by the same title (the package metadata and the site's home page)
    assert PAPER_TITLE in (ROOT / "mkdocs.yml").read_text() and PAPER_TITLE in (ROOT / "docs" / "index.md").read_text()


def test_shell_completion_is_on_and_completes_commands_and_options():
    shown = CliRunner().invoke(app, ["--help"])
    assert "--install-completion" in shown.output and "--show-completion" in shown.output
    script = Path(sys.executable).with_name("riskplan")
    if not script.is_file():
        pytest.skip("the riskplan console script is not installed next to this interpreter")
    # the script a shell sources (what --show-completion prints; asked for by name, whatever shell runs the tests)
    source = subprocess.run(
        [str(script)],
        env={**os.environ, "_RISKPLAN_COMPLETE": "source_bash"},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert source.returncode == 0 and "_RISKPLAN_COMPLETE=complete_bash" in source.stdout, source.stderr
    for words, cword, want in (("riskplan tr", "1", "train"), ("riskplan report --f", "2", "--format")):
        env = {**os.environ, "COMP_WORDS": words, "COMP_CWORD": cword, "_RISKPLAN_COMPLETE": "complete_bash"}
        done = subprocess.run([str(script)], env=env, capture_output=True, text=True, timeout=60)
        assert done.returncode == 0 and done.stdout.split() == [want]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return riskplan.train(riskplan.compose(TINY), tmp_path_factory.mktemp("run") / "run", progress=False)


def test_a_run_reads_in_one_line_and_as_a_table_in_a_notebook(run, tmp_path):
    cvar = run.summary["cvar"]
    assert repr(run) == (
        f"Run('{run.path}': paper_single, cvar beta=0.1, 3 iterations, CVaR {cvar['value']:.1f} "
        f"[{cvar['low']:.1f}, {cvar['high']:.1f}])"
    )
    html = run._repr_html_()
    assert html.startswith("<table>") and f"{cvar['value']:.1f}" in html and "metrics 3 rows" in html
    killed = riskplan.load_run(run.path)
    killed.complete, killed.problem = False, "truncated after iteration 1 (<test>)"
    assert "incomplete: truncated after iteration 1 (&lt;test&gt;)" in killed._repr_html_()  # escaped
    assert repr(killed).endswith("3 iterations, incomplete: truncated after iteration 1 (<test>))")


@pytest.mark.filterwarnings('ignore:install "ipywidgets"')  # the bar's live widget needs riskplan[notebook]
def test_the_training_bar_runs_in_a_notebook(monkeypatch):
    monkeypatch.setattr(progress, "console", Console(force_jupyter=True, file=io.StringIO()))
    bar = progress.TrainingBar()
    with bar as update:
        update(1, 3, {"mean": 1.0, "cvar": 2.0})
        assert not bar._bar.disable  # shown in Jupyter although stderr is not a terminal
    monkeypatch.setattr(progress, "console", Console(force_jupyter=False, force_terminal=False, file=io.StringIO()))
    quiet = progress.TrainingBar()
    with quiet as update:  # neither a notebook nor a terminal (pytest's stderr): no bar, the callback still works
        update(1, 3, {"mean": 1.0, "cvar": 2.0})
        assert quiet._bar.disable


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_the_report_bars_show_each_phase_on_a_terminal_without_a_thread(monkeypatch):
    """riskplan report's bars: one per phase as it comes, drawn without rich's refresh thread (the report forks
    while they are up); nothing at all where stderr is no terminal."""
    shown = io.StringIO()
    monkeypatch.setattr(progress, "console", Console(file=shown, force_terminal=True, width=100))
    monkeypatch.setattr(sys, "stderr", Terminal())
    threads = threading.active_count()
    with progress.PhaseBars() as update:
        update("loading runs", 0, 5)
        update("loading runs", 5, 5)
        update("drawing figures", 3, 4)
        assert threading.active_count() == threads
    text = shown.getvalue()
    assert "loading runs" in text and "5/5" in text and "drawing figures" in text and "3/4" in text
    monkeypatch.setattr(progress, "console", Console(file=(quiet := io.StringIO())))
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    with progress.PhaseBars() as update:
        update("loading runs", 5, 5)
    assert quiet.getvalue() == ""


@pytest.mark.slow  # a sweep and a report
def test_sweep_and_report_are_api_functions(tmp_path, monkeypatch):
    """riskplan.sweep and riskplan.report do what the commands do (the submodules sweeping/reporting do not shadow
    them), and return what a notebook wants: the summary table and the page."""
    monkeypatch.chdir(tmp_path)
    import riskplan.experiments.reporting
    import riskplan.experiments.sweeping

    done = riskplan.sweep([*TINY, "seed=0,1"], jobs=1)
    assert done.ok and list(done.summary.status) == ["done", "done"] and list(done.summary.seed) == [0, 1]
    assert done.sweep_dir.parent == Path("outputs") / "sweeps" and (done.sweep_dir / "summary.parquet").is_file()
    again = riskplan.sweep([*TINY, "seed=0,1"], sweep_dir=done.sweep_dir)
    assert again.ran == 0 and again.skipped == 2  # finished jobs are skipped
    page = riskplan.report(done.sweep_dir)
    assert page == done.sweep_dir / "report" / "report.html" and page.is_file()
    assert "<html" in page.read_text()[:200].lower()
