"""Hydra's multirun, launched in this process, its printed output going to sweep.log; and the local workers
started ahead of it (`warm_workers`, `start_workers`)."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import signal
import threading
import traceback
from collections.abc import Callable, Iterator
from multiprocessing import resource_tracker
from pathlib import Path

import numba
from hydra_plugins.hydra_joblib_launcher.config import JobLibLauncherConf
from joblib import Parallel, delayed

from riskplan.experiments.driver_watch import name_driver, recorded, scratch
from riskplan.experiments.hydra_app import run_multirun
from riskplan.experiments.sweep_worker import THREADS_ENV, warm_up
from riskplan.experiments.sweeping.jobs import TASKS
from riskplan.util.interrupt import Interrupted, StopSignals, sigint_blocked
from riskplan.util.limits import cpu_count
from riskplan.util.paths import hydra_quote, write_atomic

NUMBA_THREADS_ENV = "NUMBA_NUM_THREADS"
JOB_LIST = ".jobs.json"  # a grid's jobs to launch, beside sweep.log while the launch lasts (hydra/sweeper=riskplan)


def launch(
    argv: list[str], log_file: Path, jobs: list[list[str]] | None = None, each: tuple[str, ...] = ()
) -> str | None:
    """Run Hydra's multirun (`argv`: -m and its overrides), its printed output going to sweep.log; return the
    launcher's error, if any.

    `jobs`: a grid's jobs still to run, in order, for riskplan's sweeper (hydra_plugins.riskplan_sweeper), which
    launches exactly these (a re-run sweep submits only what needs to run). An optimising sweeper chooses its own.
    `each`: Hydra overrides added to every job's, not to the launch's (multirun.yaml stays as the user's)."""
    if jobs is not None:
        listed = (log_file.parent / JOB_LIST).resolve()
        write_atomic(listed, json.dumps([[*job, *each] for job in jobs]))
        argv = [*argv, f"hydra.sweeper.jobs={hydra_quote(listed)}"]
    ours = _sigterm_handler()
    try:
        with (
            recorded(log_file.parent),
            open(log_file, "a", buffering=1) as log,
            contextlib.redirect_stdout(log),
            contextlib.redirect_stderr(log),
        ):
            try:
                run_multirun(argv[1:])  # argv[0] is -m
            except SystemExit as stop:  # Hydra prints an exception in the launcher, then exits 1
                if stop.code == signal.SIGTERM and _sigterm_handler() != ours:
                    # ray.init's handler took SIGTERM from the driver's (sys.exit(15)): the sweep was interrupted
                    raise Interrupted(signal.SIGTERM, 0) from None
                if stop.code not in (0, None):
                    return _launcher_error(log_file, _task_names(log_file.parent, jobs or []))
            except KeyboardInterrupt:
                return "interrupted (Ctrl-C)"
            except Exception as err:
                traceback.print_exc()
                return f"the launcher stopped: {type(err).__name__}: {err} (see {log_file})"
        return None
    finally:
        if jobs is not None:
            listed.unlink(missing_ok=True)
        if ours is not None and _sigterm_handler() != ours and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, ours)  # the driver's handler again, for the summary that follows


def _sigterm_handler():
    """This process's SIGTERM handler (a library may replace it: ray.init does)."""
    return signal.getsignal(signal.SIGTERM)


# submitit's word for a SLURM job that ended without a result: its id, its task index and the state SLURM gave it
UNCOMPLETED = re.compile(r"UncompletedJobError: Job (\S+) \(task: \d+\).*?\(state: ([A-Z_]+)", re.DOTALL)
# its word from inside a job it did not requeue (out of requeues: max_num_timeout), raised in the job and handed
# back with the job's log paths, whose folder is the job's id (.submitit/<array job>_<index>/)
NOT_REQUEUED = re.compile(
    r"UncompletedJobError: Job not requeued because: ([^\n]*?)\.?\n(?:.*?\.submitit/([0-9]+(?:_[0-9]+)?)/)?", re.DOTALL
)


def _task_names(sweep_dir: Path, jobs: list[list[str]]) -> list[str]:
    """What each task of the launch ran, by its index: a job's overrides, or a cluster batch's jobs (TASKS)."""
    try:
        return [str(name) for name in json.loads((sweep_dir / TASKS).read_text())["names"]]
    except (OSError, ValueError, KeyError, TypeError):
        return [",".join(job) for job in jobs]


def _launcher_error(log_file: Path, launched: list[str]) -> str:
    """The cause of the error Hydra printed into sweep.log: for a SLURM job that ended without a result (cancelled,
    preempted, out of time or memory), which job (`launched`: what each task ran) and the state SLURM gave it; else
    the last error line."""
    try:
        text = log_file.read_text()
    except OSError:
        text = ""
    uncompleted = UNCOMPLETED.findall(text)
    if uncompleted:
        job, state = uncompleted[-1]
        return (
            f"the launcher stopped: SLURM job {job} ({_ran(job, launched)}) ended {state} without a result "
            f"(submitit's UncompletedJobError; see {log_file})"
        )
    not_requeued = NOT_REQUEUED.findall(text)
    if not_requeued:
        reason, job = not_requeued[-1]
        named = f"SLURM job {job} ({_ran(job, launched)})" if job else "a SLURM job"
        return (
            f"the launcher stopped: {named} ended without a result, not requeued: {reason} "
            f"(hydra.launcher.max_num_timeout; submitit's UncompletedJobError; see {log_file})"
        )
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    errors = [line for line in lines if "Error" in line.split(":")[0] or "Exception" in line.split(":")[0]]
    errors = [line for line in errors if not line.startswith("Error stream produced")] or errors
    # never a line that is not an error: Ray's last INFO line ("Connected to Ray cluster.") read as the cause
    last = errors[-1] if errors else next((line for line in reversed(lines) if "rror" in line), None)
    return f"the launcher stopped: {(last or 'no error message')[:300]} (see {log_file})"


def _ran(job: str, launched: list[str]) -> str:
    """What SLURM job `job` (<array job>_<index>, or a plain job for a sweep of one task) ran: its task's jobs."""
    index = job.partition("_")[2]
    task = int(index) if index.isdigit() else (0 if len(launched) == 1 else -1)
    return launched[task] if 0 <= task < len(launched) else f"job {job}"


WARMED = 1  # workers warmed up: one takes the core the planning leaves idle; more would slow the planning down


def warm_workers(workers: int) -> Callable[[], list[tuple[int, float]]]:
    """Spawn the `workers` joblib (loky) processes of the local sweeps to come now, and warm WARMED of them up
    (imports and numba's cache: riskplan.experiments.sweep_worker.warm_up), on a background thread. Returns a
    function that waits for them and gives [(pid, seconds)], or [] when the warm-up failed (the sweeps then start
    workers of their own).

    One warmed worker shortens `reproduce`; warming every worker lengthened it, since they compete with the
    planning for the cores (docs/benchmarks.md has the figures).

    joblib reuses a loky executor made with the same arguments, so the call uses the joblib launcher's own
    settings, and the environment `_run_plan` gives a sweep's workers is set before they are spawned."""
    os.environ[THREADS_ENV] = str(max(1, cpu_count() // workers))
    name_driver(True)
    with StopSignals() as stop:  # a Ctrl-C while they spawn stops this process once a thread holds the results
        folder = scratch()  # None: no temporary folder could be made, so no warm-up (the sweeps start workers)
        tasks = [delayed(warm_up)(folder) for _ in range(WARMED)] if folder is not None else []
        wait = in_background(lambda: start_workers(workers, tasks))
    if stop.received is not None:
        signal.raise_signal(stop.received)  # as it would have come, now that nothing is left half done
    return wait


def start_workers(workers: int, tasks: list) -> Iterator:
    """Hand `tasks` to the `workers` local worker processes, spawning them (all at once) if they are not up yet;
    returns their results as they come, in order. Spawned here, in the calling thread, not on a thread that ends
    first: a worker dies with the thread that spawned it (driver_watch); and with SIGINT blocked, which the workers
    inherit until their first job lets it in (driver_watch.take_interrupts): a Ctrl-C while they import printed a
    traceback from each. The generator dispatches the first tasks, and so spawns, in this call."""
    # The workers' semaphores start Python's resource tracker on first use; starting it unblocks SIGINT in the
    # thread (SIG_UNBLOCK, not the mask it found), so it starts first.
    resource_tracker.ensure_running()
    with sigint_blocked():
        return local_pool(workers, return_as="generator")(tasks)


def in_background(start: Callable[[], Iterator]) -> Callable[[], list]:
    """Results that `start` begins here, collected on a background thread (a generator joblib hands back aborts
    its tasks when dropped unread). Returns a function that waits for them: [] when they failed, a Ctrl-C in a
    worker included (the driver stops on its own)."""
    collected: list = []
    try:
        results = start()
    except Exception:
        results = iter(())

    def run() -> None:
        try:
            collected.extend(results)
        except (Exception, KeyboardInterrupt):
            collected.clear()

    thread = threading.Thread(target=run, name="riskplan-workers-start", daemon=True)
    thread.start()

    def wait() -> list:
        thread.join()
        return list(collected)

    return wait


_pools: set[int] = set()  # the sizes of the local worker pools this process started: they stay up, reused


def local_pool(workers: int, **options) -> Parallel:
    """joblib's Parallel over this process's local workers, made with the joblib launcher's own settings: joblib
    reuses one loky executor for the same settings, so the workers warm_workers started (or a batch's parts
    started before) serve the joblib launcher's jobs and the batches' parts alike."""
    settings = {key: value for key, value in dataclasses.asdict(JobLibLauncherConf()).items() if key != "_target_"}
    settings.update(n_jobs=workers, backend="loky", **options)
    # joblib caps a worker's numba at cores // workers threads (NUMBA_NUM_THREADS, fixed for the process's life)
    # unless this process's environment sets it: set, a worker keeps numba's whole pool, trains on its share of
    # the cores (train_part sets it) and takes those of parts that finished (sweeping.batched.FreedCores).
    os.environ.setdefault(NUMBA_THREADS_ENV, str(numba.config.NUMBA_NUM_THREADS))
    _pools.add(workers)
    return Parallel(**settings)


def pool_started(workers: int) -> bool:
    """Whether this process has started a pool of `workers` local workers (they are up: using them costs no start)."""
    return workers in _pools
