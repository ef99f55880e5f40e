"""The jobs of a sweep: one job (Job), a planned sweep (Plan), what a launch left (Outcome), and where each
job's folder and state are on disk."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from riskplan.experiments.driver_watch import DRIVER_FILE
from riskplan.experiments.sweep_worker import SAME_CONFIGS, foreign_run, read_status
from riskplan.run.run_files import is_run_dir, other_output
from riskplan.util import lock
from riskplan.util.errors import BadInput, one_line

SWEEPS_ROOT = Path("outputs") / "sweeps"


SUMMARY = "summary.parquet"
SWEEP_MARKS = ("sweep.log", "multirun.yaml", DRIVER_FILE)  # what a launch writes first: a sweep's directory


DEFAULT_LAUNCHER = "joblib"
BATCH_LAUNCHER = "riskplan_batch"  # riskplan sweep --batch (hydra_plugins.riskplan_batch_launcher)
LOCAL = ("joblib", "submitit_local", "basic", BATCH_LAUNCHER)  # launchers whose jobs run below the driver
POOLS = ("joblib", BATCH_LAUNCHER)  # those of riskplan's own worker pools, which take a repeated signal as one stop
# --batch on a cluster: each task of the launcher trains a chunk of the sweep as one batch; the launcher's own
# config, with riskplan's class as its _target_ (hydra_plugins.riskplan_batch_launcher)
CLUSTER_BATCHES = {
    name: f"hydra_plugins.riskplan_batch_launcher.batch_launcher.{cls}"
    for name, cls in (
        ("submitit_slurm", "SlurmBatchLauncher"),
        ("submitit_local", "LocalBatchLauncher"),
        ("ray", "RayBatchLauncher"),
        ("ray_cluster", "RayBatchLauncher"),
    )
}
TASKS = ".batch_tasks.json"  # a cluster batch's tasks, each its jobs' overrides: the launcher's error names them
# the callback that travels with every job: folder names, and a local worker that ends with its driver
TRAVELS = "+hydra.callbacks.riskplan_folders._target_=riskplan.experiments.sweep_worker.FolderNames"
GRID_SWEEPER = "riskplan"  # launches the planned grid's jobs still to run (hydra_plugins.riskplan_sweeper)


@dataclass
class Job:
    """One combination of the sweep."""

    overrides: list[str]  # as Hydra passes them to the job (and writes them to .hydra/overrides.yaml)
    sha: str  # riskplan.experiments.sweep_worker.config_sha of its composed config
    invalid: str | None = None  # why the model rejects it (the job will fail with this error)
    path: Path | None = None  # its folder, once known
    label: str = ""  # the overrides that vary between jobs: its name until its folder exists
    folder: str | None = None  # the folder name Hydra will give it (None when the user set hydra.sweep.subdir)
    trial: int = -1  # under an optimising sweeper: its trial number (hydra.job.num)
    steps: float = 0.0  # its estimated cost in trajectory-step equivalents (riskplan.run.cost)
    batch: str = ""  # what it must share with the jobs of its batch (riskplan.engine.step.batch_key)
    memory: float = 0.0  # the bytes it needs in a batch (riskplan.experiments.sweeping.batched.run_bytes)

    @property
    def key(self) -> tuple[str, ...]:
        return tuple(sorted(self.overrides))

    @property
    def name(self) -> str:
        return self.path.name if self.path is not None else (self.label or ",".join(self.overrides))

    @property
    def shown(self) -> str:
        """How progress names it: the overrides that vary, as typed (its folder name is percent-encoded), on one
        line."""
        return one_line(self.label or ",".join(self.overrides) or self.name)


@dataclass
class Plan:
    """A validated sweep, ready to launch."""

    sweep_dir: Path
    argv: list[str]  # Hydra's command line (after the program name)
    jobs: list[Job]
    launcher: str
    workers: int | None
    warnings: list[str] = field(default_factory=list)
    workers_arg: int | None = None  # index in argv of the hydra.launcher.n_jobs=... riskplan sized (its pool)
    sweeper: str = GRID_SWEEPER  # an optimiser (optuna) chooses the jobs as it goes: `jobs` is empty until they ran
    trials: int | None = None  # how many jobs such a sweeper runs, when known
    search: list[str] = field(default_factory=list)  # the keys it searches
    memory: tuple[float, str] | None = None  # a batched sweep's hydra.launcher.memory_gb: (bytes, where it was set)
    local: bool = False  # its jobs run on this machine below the driver (launcher_settings.runs_here), and end with it
    batch: bool = False  # --batch: its jobs train as batches, in this process or a chunk per cluster task
    tasks: object = None  # on a cluster, what a task may hold (sweeping.cluster_batches.TaskSize)

    @property
    def on_cluster(self) -> bool:
        """--batch on a cluster launcher: a chunk of the jobs per task (sweeping.cluster_batches)."""
        return self.batch and self.launcher in CLUSTER_BATCHES


@dataclass
class Outcome:
    """What a sweep left: its directory, the summary table and the jobs that did not finish."""

    sweep_dir: Path
    summary: object  # pandas.DataFrame
    failed: list[tuple[str, str]]  # (job folder name, error)
    ran: int
    skipped: int
    seconds: float
    launcher_error: str | None = None
    command: list[str] = field(default_factory=list)  # the `riskplan sweep` arguments that resume this sweep
    best: str | None = None  # an optimising sweeper's best trial, as it reports it
    optimiser: bool = False
    interrupted: int | None = None  # the signal that stopped the sweep (SIGINT, SIGTERM), if one did

    @property
    def ok(self) -> bool:
        return not self.failed and self.launcher_error is None


def locate(sweep_dir: Path, jobs: list[Job]) -> None:
    """Find each job's folder by the overrides Hydra recorded in it (whatever hydra.sweep.subdir is); a job whose
    recorded overrides are nowhere, by the folder name Hydra gives it, where that folder exists (it holds another
    launch's .hydra/: a run of another config, which the job left as it was)."""
    missing = {job.key: job for job in jobs if job.path is None}
    if not missing or not Path(sweep_dir).is_dir():
        return
    _by_overrides(Path(sweep_dir), missing)
    for job in missing.values():
        if job.path is None and job.folder is not None and (Path(sweep_dir) / job.folder).is_dir():
            job.path = Path(sweep_dir) / job.folder


def _by_overrides(sweep_dir: Path, missing: dict[tuple[str, ...], Job]) -> None:
    """locate's search of .hydra/overrides.yaml files for the `missing` jobs (by their keys)."""
    elsewhere: dict[tuple[str, ...], Path] = {}  # found, but not in the folder the job is named for
    for file in override_files(sweep_dir):
        try:
            overrides = yaml.safe_load(file.read_text()) or []
        except (OSError, yaml.YAMLError):
            continue
        if not isinstance(overrides, list):
            continue
        key = tuple(sorted(str(o) for o in overrides))
        job = missing.get(key)
        if job is None:
            continue
        folder = file.parent.parent
        if job.folder is None or folder.name == job.folder:
            job.path = folder
            del missing[key]
        else:
            elsewhere.setdefault(key, folder)
        if not missing:
            return
    for key, folder in elsewhere.items():
        if key in missing:
            missing[key].path = folder


def check_sweep_dir(path: Path, key: str) -> None:
    """A sweep starts in a new or empty directory, or goes on in a sweep's own: never in a run's directory or among
    files of some other kind, which its summary.parquet and job folders would write over."""
    if not path.is_dir() or any((path / mark).is_file() for mark in SWEEP_MARKS):
        return
    if not [entry for entry in path.iterdir() if entry.name != lock.LOCK]:
        return
    if is_run_dir(path):
        raise BadInput(key, f"{path} holds a run of riskplan train, not a sweep; give a new directory")
    if other_output(path):
        raise BadInput(key, f"{path} holds {other_output(path)}, not a sweep; give a new directory")
    raise BadInput(key, f"{path} is not empty and holds no sweep; give a new or empty directory, or a sweep's own")


def check_job_folders(sweep_dir: Path, jobs: list[Job]) -> None:
    """Before a launch (its jobs located): BadInput if a job would write over what is not its own: a folder holding a
    run of another config that did not fail (a re-run in a sweep's directory skips or resumes its own jobs, and
    replaces failed ones), or a folder of files that are not a job's (sweep_worker.foreign_run). A folder another
    process holds is judged by its status.json (written whole), which names the config it trains (a task of an
    earlier launch of other configs); one without it yet is left to its job, which checks it by the same rule once
    it holds it, and fails alone touching nothing if it must."""
    clashes = []
    for job in jobs:
        folder = job.path if job.path is not None or job.folder is None else sweep_dir / job.folder
        if folder is None or not folder.is_dir():
            continue
        status = read_status(folder)
        if status is None and lock.holder(folder) is not None:  # being set up: its files are in flux
            continue
        problem = foreign_run(folder, job.sha, status)
        if problem is not None:
            clashes.append((folder, problem))
    if clashes:
        folder, problem = clashes[0]
        more = f" (and {len(clashes) - 1} more job folders)" if len(clashes) > 1 else ""
        raise BadInput(
            str(folder), f"{problem}{more}; {SAME_CONFIGS}: give a new hydra.sweep.dir, or remove what is there"
        )


def override_files(root: Path):
    """Every .hydra/overrides.yaml below root, not looking inside other hidden folders (.submitit, ...)."""
    for here, dirs, files in os.walk(root):
        if Path(here).name == ".hydra":
            dirs[:] = []
            if "overrides.yaml" in files:
                yield Path(here) / "overrides.yaml"
            continue
        dirs[:] = [d for d in dirs if d == ".hydra" or not d.startswith(".")]


def job_state(job: Job, since: float) -> tuple[str, dict | None]:
    """pending | running | done | failed, as far as this launch is concerned (older records are pending)."""
    if job.path is None:
        return "pending", None
    status = read_status(job.path)
    if status is not None and (job.sha is None or status.get("config_sha") == job.sha):
        state = status.get("status")
        if state == "running" and as_number(status.get("started")) >= since - 2:
            return "running", status
        if state in ("done", "failed") and as_number(status.get("finished")) >= since - 2:
            return state, status
    if lock.holder(job.path) is not None:  # a job of this launch about to start, or one of another process
        return "running", status
    return "pending", status


def as_number(value) -> float:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else 0.0
