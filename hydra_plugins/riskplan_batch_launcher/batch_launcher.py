"""`hydra/launcher=riskplan_batch`: a sweep's jobs trained as batches in this process (`riskplan sweep --batch`);
and with a cluster's launcher, a chunk of them per task (`riskplan sweep --batch hydra/launcher=submitit_slurm`).

Hydra finds launchers only in the `hydra_plugins` package, so this module is the plugin's face: its config and a
Launcher that hands the jobs to riskplan.experiments.sweeping.batched, and the Launchers that hand them to
riskplan.experiments.sweeping.cluster_batches. Hydra imports every plugin module whenever
it starts, so this one imports nothing heavy. (No `from __future__ import annotations`: Hydra's scan executes the
module before it is in sys.modules, where dataclasses would look string annotations up.)
"""

from collections.abc import Sequence
from dataclasses import dataclass

from hydra.core.config_store import ConfigStore
from hydra.plugins.launcher import Launcher


@dataclass
class RiskplanBatchLauncherConf:
    _target_: str = "hydra_plugins.riskplan_batch_launcher.batch_launcher.RiskplanBatchLauncher"
    memory_gb: float | None = None  # the memory a batch may use (default: riskplan's memory budget)
    workers: int | None = None  # processes a batch is split over (default: one per core when its work is large)


ConfigStore.instance().store(
    group="hydra/launcher", name="riskplan_batch", node=RiskplanBatchLauncherConf, provider="riskplan"
)


class RiskplanBatchLauncher(Launcher):
    """Jobs that share a world and a sample schedule train together, one kernel call per iteration over all their
    robots; each job keeps its folder, files and status as under any other launcher."""

    def __init__(self, memory_gb: float | None = None, workers: int | None = None) -> None:
        self.memory_gb, self.workers = memory_gb, workers
        self.config = self.hydra_context = self.task_function = None

    def setup(self, *, hydra_context, task_function, config) -> None:
        self.config, self.hydra_context, self.task_function = config, hydra_context, task_function

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int):
        from riskplan.experiments.sweeping.batched import launch_batches  # lazy: the whole training stack

        return launch_batches(self, job_overrides, initial_job_idx)


class ClusterBatchLauncher(RiskplanBatchLauncher):
    """`riskplan sweep --batch` with a cluster's launcher (submitit_slurm, submitit_local, ray, ray_cluster): riskplan
    puts this class in that launcher's `_target_`, so every hydra.launcher.* key of that launcher holds (`params`);
    each of its tasks trains a chunk of the sweep as one batch (riskplan.experiments.sweeping.cluster_batches)."""

    cluster = ""  # where the tasks run: submitit's slurm or local executor, or ray

    def __init__(self, **params) -> None:
        super().__init__()
        self.params = params

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int):
        from riskplan.experiments.sweeping.cluster_batches import launch_chunks  # lazy: the whole training stack

        return launch_chunks(self, job_overrides, initial_job_idx)


class SlurmBatchLauncher(ClusterBatchLauncher):
    cluster = "slurm"


class LocalBatchLauncher(ClusterBatchLauncher):
    cluster = "local"


class RayBatchLauncher(ClusterBatchLauncher):
    cluster = "ray"
