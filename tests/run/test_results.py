"""A run's config as load_run reads it (riskplan.run.results): what OmegaConf resolves, read the same way whether
or not it holds an interpolation."""

from __future__ import annotations

import pytest
import yaml
from omegaconf import OmegaConf

from riskplan.run.compose import compose
from riskplan.run.results import run_config

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
