"""`hydra/sweeper=riskplan`: a grid sweep launches exactly the jobs `riskplan sweep` planned.

riskplan's planner (riskplan.experiments.sweeping.plan) has already expanded the grid, composed and validated every
job, and found those that finished in an earlier launch. Hydra's basic sweeper would expand and compose every job
again, and launch the finished ones too; this one reads the planner's list of jobs still to run (a JSON file, given
as `hydra.sweeper.jobs`) and hands it to the launcher as one batch, in order.

Hydra imports every plugin module whenever it starts, so this one imports nothing heavy. (No `from __future__
import annotations`: Hydra's scan executes the module before it is in sys.modules, where dataclasses would look
string annotations up.)
"""

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from hydra.core.config_store import ConfigStore
from hydra.core.plugins import Plugins
from hydra.errors import HydraException
from hydra.plugins.sweeper import Sweeper
from omegaconf import OmegaConf


@dataclass
class RiskplanSweeperConf:
    _target_: str = "hydra_plugins.riskplan_sweeper.plan_sweeper.RiskplanSweeper"
    jobs: str = ""  # a JSON list of the jobs to launch, each its list of overrides (written by riskplan sweep)


ConfigStore.instance().store(group="hydra/sweeper", name="riskplan", node=RiskplanSweeperConf, provider="riskplan")


class RiskplanSweeper(Sweeper):
    """Launches the planned jobs, in the planner's order, as one batch."""

    def __init__(self, jobs: str = "") -> None:
        self.jobs = jobs
        self.config = self.launcher = None

    def setup(self, *, hydra_context, task_function, config) -> None:
        self.config = config
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config
        )

    def sweep(self, arguments: Sequence[str]) -> list:
        batch = planned_jobs(self.jobs)
        sweep_dir = Path(self.config.hydra.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(self.config, sweep_dir / "multirun.yaml")  # as Hydra's own sweepers do
        if not batch:
            return []
        results = self.launcher.launch(batch, initial_job_idx=0)
        for result in results:
            _ = result.return_value  # raises a job's exception, as the basic sweeper does
        return [results]


def planned_jobs(path: str) -> list[list[str]]:
    """The job list riskplan's planner wrote: a list of lists of override strings."""
    if not path:
        raise HydraException("hydra/sweeper=riskplan launches the jobs riskplan sweep planned: run `riskplan sweep`")
    jobs = json.loads(Path(path).read_text())
    if not isinstance(jobs, list) or not all(
        isinstance(job, list) and all(isinstance(o, str) for o in job) for job in jobs
    ):
        raise HydraException(f"hydra.sweeper.jobs: {path} does not hold a list of override lists")
    return jobs
