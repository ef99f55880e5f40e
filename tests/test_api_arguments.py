"""The Python API's arguments (riskplan/__init__.py, riskplan.util.api_args): a wrong type or value is BadInput
naming the argument, one line, as the CLI's bad input is; and a run never starts among other files."""

from __future__ import annotations

import pytest
from support import TINY

import riskplan
from riskplan import BadInput


def _edited(**values):
    config = riskplan.compose(TINY)
    for key, value in values.items():
        config[key] = value
    return config


@pytest.mark.parametrize(
    "call, words",
    [
        (lambda: riskplan.compose("risk=neutral"), ["overrides", "got the string 'risk=neutral'"]),
        (lambda: riskplan.compose(None), ["overrides", "got None"]),
        (lambda: riskplan.compose(["seed=3", 5]), ["overrides", "holds 5"]),
        (lambda: riskplan.train(None, "out", progress=False), ["config", "got None"]),
        (lambda: riskplan.train(["seed=3"], "out", progress=False), ["config", "give a composed config"]),
        (lambda: riskplan.train(riskplan.compose(TINY), None, progress=False), ["out_dir", "got None"]),
        (lambda: riskplan.train(riskplan.compose(TINY), "", progress=False), ["out_dir", "got ''"]),
        (lambda: riskplan.load_run(None), ["path", "got None"]),
        (lambda: riskplan.load_run("missing"), ["missing", "does not exist"]),
        (lambda: riskplan.sweep("seed=0,1"), ["overrides", "got the string"]),
        (lambda: riskplan.sweep([*TINY, "seed=0,1"], jobs=0), ["jobs", "got 0"]),
        (lambda: riskplan.sweep([*TINY, "seed=0,1"], jobs="2"), ["jobs", "got '2'"]),
        (lambda: riskplan.sweep([*TINY, "seed=0,1"], batch="no"), ["batch", "got 'no'"]),
        (lambda: riskplan.sweep([*TINY, "seed=0,1"], sweep_dir="notes.txt"), ["sweep_dir", "is a file"]),
        (lambda: riskplan.report([]), ["paths", "is empty"]),
        (lambda: riskplan.report(None), ["paths", "got None"]),
        (lambda: riskplan.report(["missing"], out_dir=3), ["out_dir", "got 3"]),
        (lambda: riskplan.compose({"seed": 3}), ["overrides", "got a mapping", "['seed=3']"]),  # was "malformed"
        (lambda: riskplan.train(riskplan.compose(TINY), "out", progress="no"), ["progress", "give True or False"]),
        (lambda: riskplan.report(["missing"], formats=["gif"]), ["formats: got gif"]),  # named --format
        # a value edited in after compose, which the command line refuses (rows 80, 250): not read back as it ran
        (lambda: riskplan.train(_edited(seed="${oc.env:HOME}"), "out", progress=False), ["key 'seed'", "oc.env"]),
        (lambda: riskplan.train(_edited(seed="${now:%S}"), "out", progress=False), ["key 'seed'", "${now:...}"]),
    ],
)
def test_a_wrong_argument_is_one_line_naming_it(tmp_path, monkeypatch, call, words):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(BadInput) as refused:
        call()
    line = str(refused.value)
    assert "\n" not in line and all(word in line for word in words), line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


@pytest.mark.parametrize("where", [".", "sub"])
def test_a_run_never_starts_among_other_files(tmp_path, monkeypatch, where):
    """As `riskplan train hydra.run.dir=DIR` refuses a DIR that holds other files, so does riskplan.train."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "keep.txt").write_text("mine")
    (tmp_path / "notes.txt").write_text("mine")
    before = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*"))
    with pytest.raises(BadInput, match="is not empty and holds no run"):
        riskplan.train(riskplan.compose(TINY), where, progress=False)
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == before


@pytest.mark.slow  # a run and its report
def test_figure_formats_may_be_one_string(tmp_path):
    riskplan.train(riskplan.compose(TINY), tmp_path / "run", progress=False)
    page = riskplan.report(tmp_path / "run", tmp_path / "report", formats="png")
    assert (
        page.is_file() and list((tmp_path / "report").glob("*.png")) and not list((tmp_path / "report").glob("*.pdf"))
    )
