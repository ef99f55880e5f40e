"""`riskplan sweep --batch` on a cluster (hydra/launcher=submitit_slurm, submitit_local, ray or ray_cluster): the
sweep's runs cut into chunks, each chunk one task (of one SLURM job array, or of Ray) that trains it as one batch
(riskplan.run.batch), so a 10,000-run sweep is tens or hundreds of tasks, not 10,000.

The driver plans the chunks (`task_chunks`: by what the runs must share, the task's memory, half its time limit,
and --jobs) and writes them beside the sweep (TASKS). Hydra's launcher call (`launch_chunks`, behind
hydra_plugins.riskplan_batch_launcher's SubmititBatchLauncher, which takes every hydra.launcher.* key of submitit's)
sets up each job's folder and `.hydra/` files as a local batched sweep does, then submits one task per chunk
through submitit, as Hydra's submitit launcher would (the same executor and parameters, the same requeue on
SIGUSR2 and the same error for a task that ends without a result), or to Ray, as Hydra's Ray launcher would (Ray
started or joined with its init options, each task with its remote options).

A task (`ChunkTask`, on its node) takes its jobs' folder locks, skips the finished, resumes the checkpointed and
trains the rest as one batch in its process, the kernels on the CPUs the task was granted; each job is recorded
as under any launcher. A signal checkpoints every run of the batch: SIGTERM (scancel, preemption) ends the task
without a result, SIGUSR2 (a time limit near) lets submitit requeue the same chunk, and the next run of the task or
of the sweep resumes each job to the numbers of an uninterrupted one.
"""

from __future__ import annotations

import contextlib
import json
import math
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numba
from hydra.core.utils import JobReturn, configure_log, setup_globals
from omegaconf import DictConfig, OmegaConf

from riskplan.config.backends import BACKENDS
from riskplan.config.schema import Backend
from riskplan.config.typed import typed
from riskplan.experiments.sweep_worker import job_threads
from riskplan.experiments.sweeping.batched import PROGRESS, plan_chunks, prepare_job, prepare_jobs, train_chunks
from riskplan.experiments.sweeping.jobs import TASKS
from riskplan.experiments.sweeping.launcher_settings import given_value
from riskplan.run import cost
from riskplan.util.errors import BadInput
from riskplan.util.interrupt import Interrupted
from riskplan.util.limits import cpu_count, memory_budget
from riskplan.util.paths import write_atomic

TASK_SECONDS = 300.0  # without --jobs, a task gets about this much estimated work on its CPUs
TASK_MEMORY_SHARE = 0.8  # of hydra.launcher.mem_gb, for the batch's runs; the rest for Python and the kernels' code
SUBMITIT_TIMEOUT_MIN = 60  # submitit's defaults (hydra_plugins.hydra_submitit_launcher.config.BaseQueueConf)
SUBMITIT_CPUS = 1


@dataclass(frozen=True)
class TaskSize:
    """What one task may hold: `memory` bytes (and where that limit comes from), `seconds` of estimated work on its
    `cores`, and the number of tasks asked for (--jobs; None: by the work)."""

    memory: float
    source: str
    seconds: float
    cores: int
    tasks: int | None


def task_size(hydra_keys: dict, jobs: int | None, launcher: str = "submitit_slurm") -> TaskSize:
    """A task's limits from the launcher's overrides. submitit: hydra.launcher.mem_gb (or riskplan's memory budget
    of this machine), half of hydra.launcher.timeout_min, hydra.launcher.cpus_per_task (submitit's defaults
    otherwise). Ray: hydra.launcher.ray.remote.memory (bytes) and num_cpus, and no time limit."""

    def given(key: str, default, kind: type = int):
        node, _, name = f"hydra.launcher.{key}".rpartition(".")
        value = given_value(hydra_keys, node, name)  # a dotted key, or inside its mapping (ray.remote={num_cpus: 2})
        if value is None:
            return default
        if isinstance(value, bool) or not isinstance(value, (int, kind)) or not 0 < value < math.inf:
            what = "a whole number of at least 1" if kind is int else "a positive number"
            raise BadInput(f"hydra.launcher.{key}", f"got {value!r}; expected {what}")
        return value

    budget = memory_budget()
    if launcher.startswith("ray"):
        cores, memory = max(1, int(given("ray.remote.num_cpus", 1, float))), given("ray.remote.memory", None)
        if memory is not None:
            budget = TASK_MEMORY_SHARE * memory, f"80% of hydra.launcher.ray.remote.memory={memory}"
        return TaskSize(*budget, math.inf, cores, jobs)
    cores, minutes, gb = (
        given("cpus_per_task", SUBMITIT_CPUS),
        given("timeout_min", SUBMITIT_TIMEOUT_MIN),
        given("mem_gb", None),
    )
    if gb is not None:
        budget = TASK_MEMORY_SHARE * gb * 1e9, f"80% of hydra.launcher.mem_gb={gb}"
    return TaskSize(*budget, 0.5 * minutes * 60.0, cores, jobs)


def task_chunks(jobs: list, size: TaskSize) -> list[list]:
    """The planned jobs (sweeping.jobs.Job) still to run, cut into the tasks that train them: grouped by what a
    batch shares, each chunk within the task's memory and half its time limit (riskplan.run.cost's estimate, on its
    cores), then the chunks cut evenly until there are as many as --jobs asks for (or, without it, one per
    TASK_SECONDS of work), the largest first. A job that cannot share a batch (the ray backend) is a task of its own."""
    model = cost.model()

    def seconds(job) -> float:
        return model.run_seconds(job.steps) / size.cores

    batchable = [job for job in jobs if job.batch]
    by_memory = plan_chunks(batchable, size.memory, key=lambda job: job.batch, size=lambda job: job.memory)
    chunks = [
        part for chunk in by_memory for part in plan_chunks(chunk, size.seconds, key=lambda job: "", size=seconds)
    ]
    wanted = size.tasks or math.ceil(sum(seconds(job) for job in batchable) / TASK_SECONDS)
    parts = [1] * len(chunks)  # each chunk's share of the tasks: one more to the largest tasks, while any holds 2+
    while sum(parts) < wanted:
        i = max(range(len(chunks)), key=lambda i: len(chunks[i]) / parts[i])
        if len(chunks[i]) <= parts[i]:
            break
        parts[i] += 1
    even = [piece for chunk, n in zip(chunks, parts) for piece in _split(chunk, n)]
    return even + [[job] for job in jobs if not job.batch]


def _split(chunk: list, n: int) -> list[list]:
    """`chunk` in `n` consecutive pieces whose lengths differ by at most one."""
    q, r = divmod(len(chunk), n)
    ends = [(i + 1) * q + min(i + 1, r) for i in range(n)]
    return [chunk[end - q - (i < r) : end] for i, end in enumerate(ends)]


def write_tasks(sweep_dir: Path, waiting: list, chunks: list[list]) -> None:
    """The chunks for the launcher, as positions in the list of jobs it is handed (the jobs to run, in order), and
    each task's jobs by name, for the error line of a task that ends without a result."""
    position = {id(job): i for i, job in enumerate(waiting)}
    tasks = [[position[id(job)] for job in chunk] for chunk in chunks]
    names = ["; ".join(job.shown for job in chunk) for chunk in chunks]
    write_atomic(sweep_dir / TASKS, json.dumps({"tasks": tasks, "names": names}))


def read_tasks(sweep_dir: Path, count: int) -> list[list[int]]:
    """The chunks the driver planned for these `count` jobs (TASKS); a launch without them was not started by
    `riskplan sweep --batch`."""
    try:
        tasks = json.loads((sweep_dir / TASKS).read_text())["tasks"]
    except (OSError, ValueError, KeyError, TypeError):
        raise BadInput(
            "--batch", f"{sweep_dir / TASKS} holds no task plan; start the sweep with riskplan sweep --batch"
        ) from None
    if sorted(i for task in tasks for i in task) != list(range(count)):
        raise BadInput("--batch", f"{sweep_dir / TASKS} does not plan these {count} jobs; run the sweep again")
    return tasks


@dataclass
class Pending:
    """A job set up by the driver, for its task: its folder, its config (typed, or a DictConfig for a job that
    cannot share a batch), its plain config (its identity) and its set-up time."""

    out: Path
    config: object
    plain: dict
    seconds: float = 0.0


def _pending(cfg, plain, out: Path) -> Pending:
    """A job as its task needs it. One set up through run_job comes as its DictConfig: typed and made plain here,
    where Hydra's own interpolations still resolve."""
    if isinstance(cfg, DictConfig):
        plain = OmegaConf.to_container(cfg, resolve=True)
        if BACKENDS[Backend(cfg.team.backend)].batched:
            cfg = typed(cfg)
    return Pending(Path(out), cfg, plain)


def launch_chunks(launcher, job_overrides, initial_job_idx: int) -> list[JobReturn]:
    """The launcher's launch: every job's folder set up here, then one task per planned chunk through submitit or
    Ray; waits for them all, as Hydra's launchers do."""
    setup_globals()
    config, context = launcher.config, launcher.hydra_context
    configure_log(config.hydra.hydra_logging, config.hydra.verbose)
    sweep_dir = Path(str(config.hydra.sweep.dir))
    sweep_dir.mkdir(parents=True, exist_ok=True)
    tasks = read_tasks(sweep_dir, len(job_overrides))
    returns = prepare_jobs(context, config, job_overrides, initial_job_idx, _pending)
    total = sum(int(pending.config.train.iterations) for _, pending in returns if pending is not None)
    chunks = [[returns[i][1] for i in task] for task in tasks]
    progress = [str(sweep_dir / f"{PROGRESS}.{number}") for number in range(len(chunks))]
    submit = _on_ray if launcher.cluster == "ray" else _on_submitit
    for task, values in zip(tasks, submit(launcher, chunks, progress, total)):
        for i, value in zip(task, values):
            returns[i][0].return_value = value
    return [done for done, _ in returns]


def _on_submitit(launcher, chunks: list[list[Pending]], progress: list[str], total: int) -> list[list]:
    """The chunks as one job array through submitit, as Hydra's submitit launcher would submit them (its
    executor and parameters); each task's values, once all are done."""
    executor = submitit_executor(launcher.params, launcher.cluster)
    cpus = int(launcher.params.get("cpus_per_task") or 1)  # what each task asked for (SLURM's default: 1)
    count = len(chunks)
    submitted = executor.map_array(ChunkTask(), chunks, progress, [total] * count, [cpus] * count)
    return [job.results()[0] for job in submitted]


def _on_ray(launcher, chunks: list[list[Pending]], progress: list[str], total: int) -> list[list]:
    """The chunks as Ray tasks, Ray started (or joined) as Hydra's Ray launcher does, each task with the launcher's
    ray.remote options (num_cpus, memory, ...); each task's values, once all are done."""
    import ray  # optional: the ray extra
    from hydra_plugins.hydra_ray_launcher._launcher_util import start_ray  # optional: the ray extra

    config = _plain(launcher.params["ray"])
    start_ray(OmegaConf.create(config.get("init") or {}))  # it takes a config node, as the launcher has it
    options = config.get("remote") or {}
    cpus = int(options.get("num_cpus") or 1)
    remote = ray.remote(**options)(_chunk_task) if options else ray.remote(_chunk_task)
    return ray.get([remote.remote(chunk, part, total, cpus) for chunk, part in zip(chunks, progress)])


def _chunk_task(jobs: list[Pending], progress: str, total: int, cpus: int) -> list[float | None]:
    """A chunk trained in a Ray task (Ray runs functions, submitit callables with a checkpoint)."""
    return ChunkTask()(jobs, progress, total, cpus)


def submitit_executor(params: dict, cluster: str):
    """submitit's executor for the launcher's parameters, set up as Hydra's submitit launcher sets it up."""
    import submitit  # optional: the slurm extra
    from hydra_plugins.hydra_submitit_launcher.config import BaseQueueConf  # optional: the slurm extra

    params = {key: _plain(value) for key, value in params.items()}
    init = {"folder": params.pop("submitit_folder")}
    if "max_num_timeout" in params:
        init[f"{cluster}_max_num_timeout"] = params.pop("max_num_timeout")
    executor = submitit.AutoExecutor(cluster=cluster, **init)
    shared = set(OmegaConf.structured(BaseQueueConf).keys())
    executor.update_parameters(**{k if k in shared else f"{cluster}_{k}": v for k, v in params.items()})
    return executor


def _plain(value):
    """A launcher parameter as plain data (Hydra hands nested ones over as OmegaConf nodes)."""
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


class ChunkTask:
    """One task of the array: its chunk of jobs trained as one batch, on the task's node. submitit calls it, and
    on SIGUSR2 (after riskplan checkpointed every run) its `checkpoint`, which requeues the same chunk."""

    def __call__(self, jobs: list[Pending], progress: str, total: int, cpus: int) -> list[float | None]:
        threads = min(job_threads() or cpu_count(), cpus)  # the CPUs the task asked for and was granted
        numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
        with contextlib.ExitStack() as held:  # each job folder's lock, until its job is recorded
            prepared = []
            for job in jobs:
                start = prepare_job(job.config, job.plain, job.out, held)
                start.seconds = job.seconds
                prepared.append(start)
            waiting = [start for start in prepared if start.setup is not None]
            if waiting:
                try:
                    train_chunks([waiting], Path(progress), total, workers=1, threads=threads)
                except Interrupted as stop:  # every run checkpointed and marked interrupted: end by the signal,
                    stop.end()  # without a result, so that the task runs again (requeued) or the sweep resumes it
        return [start.value for start in prepared]

    def checkpoint(self, *args):
        """submitit's requeue on SIGUSR2: the same chunk again; each job resumes from its checkpoint."""
        import submitit  # optional: the slurm extra

        return submitit.helpers.DelayedSubmission(self, *args)


LAUNCHER = "hydra.launcher."
SBATCH_SECONDS = 5.0  # sbatch --test-only asks the controller once: quick on a cluster that answers at all
# submitit's keys that never reach an #SBATCH line (its own settings), so never the cause of sbatch's refusal
NOT_SBATCH = ("_target_", "submitit_folder", "max_num_timeout", "setup", "stderr_to_stdout")
# sbatch could not ask the controller (no slurm.conf, the controller down): no verdict on the settings
UNREACHABLE = re.compile(
    r"fatal:|unable to contact slurm controller|socket timed out|zero bytes were transmitted|"
    r"communication connection failure|connection refused|configuration source",
    re.IGNORECASE,
)


def check_sbatch(launcher: str, hydra_keys: dict, timeout: float = SBATCH_SECONDS, tasks: int | None = None) -> None:
    """submitit_slurm's settings as SLURM will judge them, before anything is written: the batch script submitit
    would submit (its #SBATCH lines from the launcher's settings; an array of `tasks` tasks, one job alone without
    --array as submitit submits it, an array of 2 when the count is not known yet) goes to `sbatch --test-only`,
    which submits nothing. A refusal is bad input naming the hydra.launcher keys without which sbatch accepts the
    rest (else all the user gave) and sbatch's own reason, or the array's size when sbatch takes a smaller one
    (MaxArraySize, 1001 by default); it also catches a request no node can ever meet (cpus_per_task beyond every
    node), which would otherwise pend in silence. No check without sbatch on PATH, or when sbatch cannot reach its
    controller or answer within `timeout` s: the submission says what is wrong then."""
    if launcher != "submitit_slurm" or shutil.which("sbatch") is None:
        return
    tasks = 2 if tasks is None else tasks
    params = slurm_params(hydra_keys)
    refusal = None if params is None else sbatch_refusal(params, timeout, tasks)
    if refusal is None:
        return
    if tasks > 2 and sbatch_refusal(params, timeout, 2) is None:
        raise BadInput(
            "hydra/launcher=submitit_slurm",
            f"sbatch refuses a job array of {tasks} tasks, one a job: {refusal} (sbatch --test-only), and takes a "
            f"smaller one (the cluster's MaxArraySize: scontrol show config); sweep fewer jobs at once, or give "
            f"--batch (a task per chunk of jobs)",
        )
    defaults = slurm_params({})
    given = list(dict.fromkeys(key[len(LAUNCHER) :].split(".")[0] for key in hydra_keys if key.startswith(LAUNCHER)))
    given = [key for key in given if key not in NOT_SBATCH and key in defaults]
    culprits = [key for key in given if sbatch_refusal({**params, key: defaults[key]}, timeout, tasks) is None]
    where = ", ".join(LAUNCHER + key for key in culprits or given) or "hydra/launcher=submitit_slurm"
    raise BadInput(
        where,
        f"sbatch refuses it: {refusal} (sbatch --test-only); give settings this cluster accepts (sinfo lists its "
        f"partitions and nodes)",
    )


def slurm_params(hydra_keys: dict) -> dict | None:
    """submitit_slurm's settings: Hydra's launcher defaults with the user's hydra.launcher overrides. None when they
    do not apply cleanly (an unknown key, a bad type, a deletion, an interpolation) or the launcher is not
    installed: Hydra refuses those in its own words, later in the plan."""
    try:
        from hydra_plugins.hydra_submitit_launcher.config import SlurmQueueConf  # optional: the slurm extra

        conf = OmegaConf.structured(SlurmQueueConf)
        for key, override in hydra_keys.items():
            if key.startswith(LAUNCHER):
                if override.is_delete():
                    return None
                OmegaConf.update(conf, key[len(LAUNCHER) :], override.value(), merge=True)
        params = OmegaConf.to_container(conf, resolve=False)
    except Exception:  # ImportError, OmegaConf's errors: no verdict here
        return None
    params.pop("_target_", None)
    params["name"] = "riskplan"  # ${hydra.job.name}, resolved at launch; submitit_folder is set per check
    if "${" in repr({key: value for key, value in params.items() if key != "submitit_folder"}):
        return None
    return params


def sbatch_refusal(params: dict, timeout: float, tasks: int) -> str | None:
    """sbatch's reason for refusing submitit's batch script with these settings for `tasks` tasks (sbatch
    --test-only, in a scratch folder), or None when it accepts them or gives no verdict (unreachable, slow, not
    startable)."""
    with tempfile.TemporaryDirectory(prefix="riskplan-sbatch-") as scratch:
        try:
            slurm = submitit_executor({**params, "submitit_folder": f"{scratch}/%j"}, "slurm")._executor
            if tasks > 1:  # an array, as submitit submits more than one task (one alone: a plain job)
                slurm.parameters["map_count"] = tasks
            script = Path(scratch, "check.sh")
            script.write_text(slurm._make_submission_file_text("true", "check"))
            done = subprocess.run(
                ["sbatch", "--test-only", str(script)],
                capture_output=True,
                text=True,
                timeout=timeout,
                cwd=scratch,
                stdin=subprocess.DEVNULL,
            )
        except Exception:  # submitit's own errors come again at submission; a timeout or OSError: no verdict
            return None
    lines = [line.strip() for line in (done.stderr + "\n" + done.stdout).splitlines() if line.strip()]
    if done.returncode == 0 or any(UNREACHABLE.search(line) for line in lines):
        return None
    return re.sub(r"^sbatch: (error: )?", "", lines[0]) if lines else f"sbatch exited {done.returncode}"
