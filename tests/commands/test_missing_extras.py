"""A missing optional package is bad input: every row of the missing-extras table in docs/robustness.md is run through
the real CLI (typer's CliRunner) with the row's module hidden (`sys.modules[name] = None` makes it look
uninstalled), and must exit with code 2, print exactly the row's line on stderr, and leave the directory as it was:
no run directory, no sweep directory. The same holds for a value set in an experiment file rather than typed."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.config.validate import check_extra
from riskplan.run.compose import check_extras
from riskplan.util.checks import installed
from riskplan.util.errors import BadInput, MissingExtra

DOCS = Path(__file__).resolve().parents[2] / "docs" / "robustness.md"
BEGIN, END = "<!-- missing-extras-table: begin -->", "<!-- missing-extras-table: end -->"
RAY_LINE = "error: team.backend=ray: needs Ray, which is not installed; pip install 'riskplan[distributed]'"

runner = CliRunner()


def table_rows() -> list[tuple[str, list[str], str]]:
    """(module to hide, argv, expected stderr line) for each row of the docs' table."""
    text = DOCS.read_text()
    body = text[text.index(BEGIN) + len(BEGIN) : text.index(END)]
    rows = []
    for line in body.strip().splitlines()[2:]:  # the header and the --- row
        _, module, command, expected = (cell.strip().strip("`") for cell in line.strip().strip("|").split(" | "))
        argv = shlex.split(command)
        assert argv[0] == "riskplan", line
        rows.append((module, argv[1:], expected))
    return rows


ROWS = table_rows()


def snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else b"") for p in sorted(root.rglob("*"))}


def refused(argv: list[str], root: Path) -> str:
    """Run the CLI; check exit code 2, one plain line, no traceback and nothing written below root; the line."""
    before = snapshot(root)
    result = runner.invoke(app, argv)
    assert result.exit_code == 2, f"exit {result.exit_code}: {result.output}{result.exception!r}"
    assert "Traceback" not in result.output
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert snapshot(root) == before, "bad input left something behind"
    return result.stderr.splitlines()[0]


def test_the_table_covers_check_train_sweep_and_export_and_every_extra():
    assert {argv[0] for _, argv, _ in ROWS} == {"check", "train", "sweep", "export"}
    assert {module for module, _, _ in ROWS} == {
        "ray",
        "hydra_plugins.hydra_submitit_launcher",
        "hydra_plugins.hydra_optuna_sweeper",
        "mlflow",
        "tensorboard",
        "numba_cuda",
    }


@pytest.mark.parametrize("module, argv, expected", ROWS, ids=[" ".join(argv[:2]) + f" [{m}]" for m, argv, _ in ROWS])
def test_a_missing_extra_is_bad_input_and_makes_no_directory(in_tmp, monkeypatch, module, argv, expected):
    (in_tmp / "outputs" / "runs").mkdir(parents=True)  # export's input: the extra is checked before the runs
    monkeypatch.setitem(sys.modules, module, None)  # as if it were not installed
    assert refused(argv, in_tmp) == expected
    assert not (in_tmp / "outputs" / "sweeps").exists() and list((in_tmp / "outputs" / "runs").iterdir()) == []


@pytest.fixture
def config_dir(in_tmp) -> Path:
    """An experiment file that sets team.backend=ray itself (no override names it)."""
    folder = in_tmp / "mine" / "experiment"
    folder.mkdir(parents=True)
    (folder / "ray_team.yaml").write_text(
        "# @package _global_\nexperiment: ray_team\ntrain: {iterations: 2, samples: 100}\n"
        "team: {robots: 2, backend: ray}\n"
    )
    return in_tmp / "mine"


@pytest.mark.parametrize(
    "argv",
    [
        ["check", "-cd", "mine", "experiment=ray_team"],
        ["train", "-cd", "mine", "experiment=ray_team"],
        ["sweep", "-cd", "mine", "experiment=ray_team", "seed=0,1"],
        ["sweep", "-cd", "mine", "experiment=paper_single,ray_team"],  # only some jobs need Ray: still the whole sweep
    ],
    ids=["check", "train", "sweep", "sweep-some-jobs"],
)
def test_ray_set_in_an_experiment_file_is_bad_input_too(config_dir, in_tmp, monkeypatch, argv):
    monkeypatch.setitem(sys.modules, "ray", None)
    assert refused(argv, in_tmp) == RAY_LINE
    assert not (in_tmp / "outputs").exists()


def test_the_check_names_the_key_and_value_and_passes_what_is_installed(monkeypatch):
    check_extra("team.backend", "simulated")  # needs nothing
    check_extra("hydra/launcher", "joblib")  # riskplan's own dependency
    check_extra("team.backend", "ray")  # installed in the test environment
    assert installed("ray") and not installed("riskplan_no_such_module") and not installed("no_such_parent.child")
    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(MissingExtra) as err:
        check_extra("team.backend", "ray")
    assert isinstance(err.value, BadInput) and str(err.value) == RAY_LINE.removeprefix("error: ")


def test_with_the_extras_installed_the_same_commands_pass_the_check(in_tmp):
    result = runner.invoke(app, ["check", "experiment=paper_team", "team.backend=ray"])
    assert result.exit_code == 0, result.output
    assert result.stdout.rstrip().endswith("config OK")


def test_the_overrides_are_read_as_a_sweep_gives_them(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)
    for given in ("team.backend=ray", "team.backend=simulated,ray", "team.backend=choice(simulated,ray)"):
        with pytest.raises(MissingExtra, match=r"^team\.backend=ray: needs Ray"):
            check_extras(["seed=0,1", given])
    # what needs no extra, a glob over a config group, a malformed override (the command's own checks name it)
    check_extras(["team.backend=simulated", "risk=glob(*)", "hydra/launcher=glob(*)", "~team.backend", "risk.beta=="])
