"""A run as load_run reads it (riskplan.run.results): its config what OmegaConf resolves, read the same way whether
or not it holds an interpolation; a damaged summary read from the log instead."""

from __future__ import annotations

import json

import pytest
import yaml
from omegaconf import OmegaConf
from support import TINY

from riskplan import load_run
from riskplan.run.compose import compose
from riskplan.run.results import run_config
from riskplan.run.training import train

DOCS = {
    "a composed config": None,  # filled from compose() below
    "an interpolation": {"train": {"iterations": 7, "paths": "${train.iterations}"}},
    "a number key": {"world": {3: "x"}},
    "text that looks like a number": {"train": {"step": "1e-05", "on": "yes"}},
}


@pytest.mark.parametrize("name", list(DOCS))
def test_a_config_is_what_omegaconf_resolves(tmp_path, name):
    data = DOCS[name]
    if data is None:
        data = OmegaConf.to_container(compose(["experiment=paper_team"]), resolve=True, enum_to_str=True)
    (tmp_path / ".hydra").mkdir()
    (tmp_path / ".hydra" / "config.yaml").write_text(yaml.safe_dump(data))
    read = yaml.safe_load((tmp_path / ".hydra" / "config.yaml").read_text())
    assert run_config(tmp_path) == OmegaConf.to_container(OmegaConf.create(read), resolve=True)
    if name == "an interpolation":
        assert run_config(tmp_path)["train"]["paths"] == 7


@pytest.mark.slow  # over half a second (the quick tier stays under a minute)
@pytest.mark.parametrize("text", ["NaN", "[1, 2]", '"done"'])
def test_a_summary_that_is_not_an_object_is_rebuilt_from_the_log(tmp_path, text):
    """summary.json holding JSON that is not an object (riskplan writes none) is a damaged file: load_run reads the
    run from run.mcap instead, says so, and its summary is the log's own."""
    out = tmp_path / "run"
    train(compose(TINY), out)
    expected = json.loads((out / "summary.json").read_text())
    (out / "summary.json").write_text(text)
    run = load_run(out)
    assert run.complete and "rebuilt from run.mcap" in run.problem and "not an object" in run.problem
    assert run.summary["cvar"] == expected["cvar"]
