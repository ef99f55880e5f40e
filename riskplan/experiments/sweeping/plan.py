"""A sweep planned from its command line: parsed, counted, expanded and validated, its directory chosen last,
so bad input leaves nothing behind."""

from __future__ import annotations

import math
from pathlib import Path

from riskplan.config.hydra_safety import check_resolvers
from riskplan.experiments.sweep_worker import SUBDIR
from riskplan.experiments.sweeping.cluster_batches import check_sbatch, task_size
from riskplan.experiments.sweeping.grid import (
    ParsedOnce,
    add_naming_and_logging,
    check_duplicates,
    check_hydra,
    check_repeats,
    check_size,
    check_subdir,
    constant_keys,
    expand,
    name_folders,
    split_bad,
    target_dir,
    unnamed_key,
    validate,
)
from riskplan.experiments.sweeping.jobs import (
    BATCH_LAUNCHER,
    CLUSTER_BATCHES,
    DEFAULT_LAUNCHER,
    GRID_SWEEPER,
    TRAVELS,
    Plan,
    check_sweep_dir,
)
from riskplan.experiments.sweeping.launcher_settings import (
    launcher_workers,
    ray_init_overrides,
    runs_here,
)
from riskplan.experiments.sweeping.search import plan_optimiser
from riskplan.run.compose import check_override_values, expand_shorthands, parse_overrides
from riskplan.util.errors import BadInput
from riskplan.util.paths import check_output_dir, hydra_quote

SUBMITIT = ("submitit_slurm", "submitit_local")  # Hydra's submitit launchers: timeout_min, cpus_per_task, mem_gb
REQUEUES = 3  # submitit_slurm: times a job that reaches its time limit is requeued (it resumes from its checkpoint)


def plan_sweep(
    args: list[str], jobs: int | None = None, sweep_dir: Path | None = None, batch: bool | None = None
) -> Plan:
    """Parse, expand and validate a sweep; claim its directory last, so bad input leaves nothing behind. `batch`:
    the jobs train in batches in this process (hydra/launcher=riskplan_batch), or with a cluster launcher
    (submitit's) a chunk of them per task (sweeping.cluster_batches)."""
    _check_options(args)
    args = expand_shorthands(args)  # risk.schedule=none,linear -> risk.schedule.kind=none,linear
    parsed = parse_overrides(args)
    check_repeats(parsed)
    hydra_ovs = [o for o in parsed if o.is_hydra_override()]
    task_ovs = [o for o in parsed if not o.is_hydra_override()]
    _check_hydra_overrides(hydra_ovs)
    check_override_values(task_ovs)
    for override in task_ovs:  # the jobs take them as data, not through compose's check of the whole config
        check_resolvers(override.input_line.partition("=")[2], override.key_or_group)
    hydra_keys = {o.key_or_group: o for o in hydra_ovs}
    batch = default_batch(hydra_keys, jobs) if batch is None else batch
    launcher = _launcher(hydra_keys, jobs, batch)
    memory = batch_memory(hydra_keys) if launcher == BATCH_LAUNCHER else None
    if launcher == BATCH_LAUNCHER:
        check_batch_workers(hydra_keys)
    on_cluster = batch and launcher in CLUSTER_BATCHES
    # a task's numbers (timeout_min, cpus_per_task, mem_gb) checked for every submitit launch, not only --batch's:
    # SLURM reads timeout_min=0 as no limit, and sbatch's refusal of mem_gb=-1 came after the folders were written
    size = task_size(hydra_keys, jobs, launcher) if on_cluster or launcher in SUBMITIT else None
    tasks = size if on_cluster else None
    explicit_dir = _explicit_dir(hydra_keys, sweep_dir)
    if sweep_dir is not None:  # a reproduction's study
        check_sweep_dir(Path(sweep_dir), str(sweep_dir))
    sweeper = str(hydra_keys["hydra/sweeper"].value()) if "hydra/sweeper" in hydra_keys else GRID_SWEEPER
    if sweeper not in ("basic", GRID_SWEEPER):  # an optimiser: it chooses the jobs as it goes
        check_sbatch(launcher, hydra_keys)  # what SLURM refuses, asked before anything is written
        return plan_optimiser(args, task_ovs, hydra_ovs, launcher, sweeper, jobs, sweep_dir, explicit_dir)
    _check_grid(task_ovs, hydra_ovs)
    check_size(task_ovs)
    if "hydra.sweep.subdir" in hydra_keys:
        check_subdir(hydra_keys["hydra.sweep.subdir"].value(), len(task_ovs) > 0)
    combos = expand(task_ovs, args)
    search = [o.input_line for o in hydra_ovs if o.key_or_group == "hydra.searchpath"]  # --config-dir
    parse = ParsedOnce()  # each distinct override parsed once, for every step below
    parse.learn(task_ovs)
    job_list, notes = validate(combos, search, parse)
    check_duplicates(job_list, task_ovs)
    if all(job.invalid for job in job_list):
        raise BadInput(*split_bad(job_list[0].invalid, len(job_list)))
    # what SLURM refuses, asked before anything is written: job by job, the array of the valid jobs (at most: those
    # finished already are left out at launch); under --batch a task per chunk, counted only at launch
    check_sbatch(launcher, hydra_keys, tasks=None if on_cluster else sum(not job.invalid for job in job_list))

    argv = ["-m", *args]
    if "hydra/sweeper" in hydra_keys:  # basic or riskplan, typed: riskplan's sweeper launches the planned grid
        argv[1 + parsed.index(hydra_keys["hydra/sweeper"])] = f"hydra/sweeper={GRID_SWEEPER}"
    else:
        argv.append(f"hydra/sweeper={GRID_SWEEPER}")
    workers, workers_arg = _launcher_settings(
        argv, launcher, hydra_keys, jobs if tasks is None else None, len(job_list)
    )
    if tasks is not None:
        _cluster_batch_settings(argv, launcher, jobs, len(job_list))
    named = [o for o in task_ovs if not unnamed_key(o.key_or_group)]  # engine.device names no folder
    if not named and "hydra.sweep.subdir" not in hydra_keys:
        argv.append("hydra.sweep.subdir=defaults")  # one job without overrides: still a folder of its own
    elif "hydra.sweep.subdir" not in hydra_keys:
        # folder names that stay one path component, whatever the values hold ('/', '..', '%', NUL)
        argv.append(f"hydra.sweep.subdir={hydra_quote(SUBDIR)}")
    argv.append(TRAVELS)
    constant = constant_keys(combos, {o.key_or_group for o in task_ovs if o.is_sweep_override()}, parse)
    for job in job_list:
        job.label = ",".join(sorted(o for o in job.overrides if o.split("=", 1)[0].lstrip("+~") not in constant))
    add_naming_and_logging(argv, hydra_keys, constant)

    naming = check_hydra(argv[1 + len(args) :] + [o.input_line for o in hydra_ovs], combos[0])
    if named and "hydra.sweep.subdir" not in hydra_keys:
        name_folders(job_list, naming, task_ovs, parse)

    target = target_dir(sweep_dir, explicit_dir, argv)
    plan = Plan(target, argv, job_list, launcher, workers, notes, workers_arg)
    plan.memory, plan.tasks, plan.batch = memory, tasks, batch
    plan.local = runs_here(launcher, hydra_keys)
    return plan


def _cluster_batch_settings(argv: list[str], launcher: str, jobs: int | None, count: int) -> None:
    """--batch on a cluster: riskplan's launcher class in the launcher's config (its keys stay submitit's), and
    --jobs as SLURM's array parallelism (the tasks that run at once; the plan makes at least that many)."""
    argv.append(f"hydra.launcher._target_={CLUSTER_BATCHES[launcher]}")
    if jobs is not None and launcher == "submitit_slurm":
        argv.append(f"hydra.launcher.array_parallelism={min(jobs, count)}")


def _check_options(args: list[str]) -> None:
    """An option riskplan sweep does not know (it takes Hydra overrides and its own --jobs, --batch)."""
    for arg in args:
        if arg.startswith("-"):
            raise BadInput(
                f"option '{arg}'", "is not known to riskplan sweep; give Hydra overrides (key=value) and --jobs N"
            )


def _check_hydra_overrides(hydra_ovs: list) -> None:
    """Hydra's own settings a sweep cannot take: its mode, or a sweep over them."""
    for o in hydra_ovs:
        if o.key_or_group == "hydra.mode":
            raise BadInput(
                f"override '{o.input_line}'", "riskplan sweep always runs a multirun; drop it (one run: riskplan train)"
            )
        if o.is_sweep_override():
            raise BadInput(
                f"override '{o.input_line}'",
                "sweeps over Hydra's own settings are not supported; sweep over riskplan keys, e.g. risk.beta=0.1,0.2",
            )


def default_batch(hydra_keys: dict, jobs: int | None) -> bool:
    """Whether a sweep given neither --batch nor --jobs trains as batches: yes, unless it names a launcher or a
    sweeper (a cluster's jobs, an optimiser's trials), or --jobs asks for a worker process per job."""
    return jobs is None and "hydra/launcher" not in hydra_keys and "hydra/sweeper" not in hydra_keys


def _launcher(hydra_keys: dict, jobs: int | None, batch: bool) -> str:
    """The launcher: hydra/launcher's, riskplan's batches with --batch (which takes neither it nor --jobs), or
    joblib."""
    launcher = str(hydra_keys["hydra/launcher"].value()) if "hydra/launcher" in hydra_keys else DEFAULT_LAUNCHER
    if not batch:
        return launcher
    if "hydra/sweeper" in hydra_keys:
        given = hydra_keys["hydra/sweeper"].input_line
        raise BadInput("--batch", f"trains a grid's jobs together; drop '{given}' (an optimiser picks jobs one by one)")
    if "hydra/launcher" in hydra_keys:
        if launcher not in CLUSTER_BATCHES:
            raise BadInput(
                "--batch",
                f"trains in this process, or a chunk per task with hydra/launcher=submitit_slurm, submitit_local, "
                f"ray or ray_cluster; "
                f"drop '{hydra_keys['hydra/launcher'].input_line}'",
            )
        return launcher
    if jobs is not None:
        raise BadInput(
            "--jobs", "applies to parallel launchers and to --batch on a cluster; --batch alone trains on every core"
        )
    return BATCH_LAUNCHER


def _explicit_dir(hydra_keys: dict, sweep_dir: Path | None) -> Path | None:
    """The user's hydra.sweep.dir (a plain path, checked as an output directory), or None."""
    if "hydra.sweep.dir" not in hydra_keys:
        return None
    if sweep_dir is not None:
        raise BadInput("hydra.sweep.dir", "is chosen by this command; do not give it")
    raw = hydra_keys["hydra.sweep.dir"].value()
    value = "" if raw is None else str(raw)
    if "${" in value:
        raise BadInput(
            "hydra.sweep.dir",
            f"got '{value}'; give a plain path (without it, riskplan sweep uses outputs/sweeps/<timestamp>)",
        )
    check_output_dir(value, "hydra.sweep.dir")
    check_sweep_dir(Path(value), "hydra.sweep.dir")
    return Path(value)


def _check_grid(task_ovs: list, hydra_ovs: list) -> None:
    """What a grid does not take: an optimiser's search space, or an optimiser's settings."""
    for o in task_ovs:
        if o.is_interval_sweep():
            raise BadInput(
                f"override '{o.input_line}'",
                "interval(...) is a search space for an optimising "
                "sweeper (hydra/sweeper=optuna); a grid takes comma "
                "lists, range(...), choice(...) or glob(...)",
            )
    for o in hydra_ovs:
        if o.key_or_group.startswith("hydra.sweeper."):
            raise BadInput(
                f"override '{o.input_line}'",
                "a grid sweep takes no sweeper settings (riskplan launches the planned jobs itself); hydra.sweeper.* "
                "configures an optimising sweeper, e.g. hydra/sweeper=optuna",
            )


def _launcher_settings(
    argv: list[str], launcher: str, hydra_keys: dict, jobs: int | None, count: int
) -> tuple[int | None, int | None]:
    """The launcher's settings riskplan adds to `argv`: its workers (joblib's n_jobs, SLURM's array parallelism),
    SLURM's requeues, Ray's init arguments, the launcher itself. Returns the workers and the index in argv of the
    n_jobs riskplan added (None when the user gave it)."""
    workers, workers_arg = launcher_workers(argv, launcher, hydra_keys, jobs, count)
    if launcher == "submitit_slurm" and "hydra.launcher.max_num_timeout" not in hydra_keys:
        argv.append(f"hydra.launcher.max_num_timeout={REQUEUES}")  # a job at its time limit is requeued, resumes
    argv += ray_init_overrides(launcher, hydra_keys)
    if "hydra/launcher" not in hydra_keys:
        argv.append(f"hydra/launcher={launcher}")
    return workers, workers_arg


def batch_memory(hydra_keys: dict) -> tuple[float, str] | None:
    """hydra.launcher.memory_gb, the memory a batch may use, as (bytes, its source); None when not given (the
    memory budget holds then). Bad input unless it is a positive, finite number of GB."""
    if MEMORY_KEY not in hydra_keys:
        return None
    value = hydra_keys[MEMORY_KEY].value()
    try:
        gb = float(value)
    except (TypeError, ValueError):
        gb = math.nan
    if isinstance(value, bool) or not (math.isfinite(gb) and gb > 0):
        raise BadInput(MEMORY_KEY, f"got {value!r}; expected a positive number of GB that a batch may use, e.g. 4")
    if gb < 1e-9:  # below one byte: no batch fits, and the plan said "within the 0.001 B memory budget"
        raise BadInput(MEMORY_KEY, f"got {value!r}; expected at least 1e-9 GB (one byte) that a batch may use, e.g. 4")
    return gb * 1e9, MEMORY_KEY


def check_batch_workers(hydra_keys: dict) -> None:
    """hydra.launcher.workers, the processes a batch is split over: a whole number >= 1 when given (0 and -1 passed
    unnoticed, as the default)."""
    if WORKERS_KEY not in hydra_keys:
        return
    value = hydra_keys[WORKERS_KEY].value()
    if value is None or (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
        return
    raise BadInput(
        WORKERS_KEY, f"got {value!r}; expected a whole number of processes >= 1, or null (one per core for large work)"
    )


MEMORY_KEY = "hydra.launcher.memory_gb"
WORKERS_KEY = "hydra.launcher.workers"
