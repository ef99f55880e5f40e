"""A sweep job's config composed once per choice of config groups (grid.JobConfigs) is exactly the config Hydra's
own load_sweep_config composes for it, hydra node included."""

from __future__ import annotations

import pytest
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.types import RunMode
from omegaconf import OmegaConf

from riskplan.config import schema
from riskplan.experiments.sweeping.grid import JobConfigs
from riskplan.run.compose import CONF_DIR

JOBS = [
    ["seed=1", "risk.beta=0.2"],
    ["seed=2", "risk.beta=0.2"],
    ["experiment=paper_team", "team.drop=0.1", "seed=2"],
    ["risk=wang", "risk.eta=0.3"],
    ["world.start=[1,1]", "train.theta0=[0,0]"],
    ["risk=neutral", "seed=3", "experiment=paper_team"],
    ["+hydra.job.env_set.X=1", "seed=4"],
    ["team.robots=999999999999999999999", "seed=5"],
]


@pytest.fixture(scope="module")
def loader_and_master():
    schema.register()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        loader = GlobalHydra.instance().config_loader()
        master = loader.load_configuration("config", ["hydra/launcher=riskplan_batch", "seed=0,1"], RunMode.MULTIRUN)
        yield loader, master
    GlobalHydra.instance().clear()


@pytest.mark.slow  # about a second
def test_each_job_config_is_hydras_own(loader_and_master):
    loader, master = loader_and_master
    configs = JobConfigs(loader, master)
    for overrides in JOBS:
        want = loader.load_sweep_config(master, list(overrides))
        got = configs(list(overrides))
        assert OmegaConf.to_yaml(got) == OmegaConf.to_yaml(want), overrides
    assert len(configs.bases) <= 5  # the groups composed once each (plus what had to be composed whole)
