"""A planned sweep launched under its directory's lock, shown live, and summarised."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import typer
from joblib import delayed

from riskplan.experiments.driver_watch import end_leftovers, name_driver
from riskplan.experiments.sweep_worker import OWN_FILES, THREADS_ENV, is_finished
from riskplan.experiments.sweeping.batched import PROGRESS, plan_chunks
from riskplan.experiments.sweeping.cluster_batches import task_chunks, write_tasks
from riskplan.experiments.sweeping.jobs import (
    BATCH_LAUNCHER,
    GRID_SWEEPER,
    LOCAL,
    POOLS,
    SUMMARY,
    TASKS,
    Outcome,
    Plan,
    check_job_folders,
    locate,
)
from riskplan.experiments.sweeping.launch import in_background, launch, pool_started, start_workers
from riskplan.experiments.sweeping.plan import plan_sweep
from riskplan.experiments.sweeping.search import run_optimiser
from riskplan.experiments.sweeping.summary import summarize, write_summary
from riskplan.experiments.sweeping.view import SweepView
from riskplan.run import cost
from riskplan.util import lock
from riskplan.util.interrupt import DriverSignals, Interrupted
from riskplan.util.limits import cpu_count, memory_budget, size


def run_sweep(
    args: list[str],
    jobs: int | None = None,
    sweep_dir: Path | None = None,
    title: str = "sweep",
    out=None,
    before_launch=None,
    expected: frozenset[str] = frozenset(),
    batch: bool | None = None,
) -> Outcome:
    """Plan, launch through Hydra, show progress, write summary.parquet. BadInput before anything runs.

    `before_launch`: called between planning and launching (reproduce waits there for its warmed-up workers).
    `expected`: warnings the caller chose on purpose (reproduce's own studies), not repeated. `batch`: the jobs
    that share a world train as one program (riskplan.experiments.sweeping.batched)."""
    plan = plan_sweep(args, jobs, sweep_dir, batch)
    plan.warnings = [note for note in plan.warnings if note not in expected]
    with lock.hold_lock(plan.sweep_dir, "sweep directory"):  # one driver per sweep directory, for the whole launch
        return _run_plan(plan, args, jobs, title, out, before_launch)


def _run_plan(plan: Plan, args: list[str], jobs: int | None, title: str, out, before_launch=None) -> Outcome:
    echo = out or (lambda text: typer.echo(text))
    for note in plan.warnings:
        typer.echo(f"warning: {note}", err=True)
    ended = end_leftovers(plan.sweep_dir)  # a killed driver's workers, before this launch needs their folders
    if ended:
        echo(ended)
    if plan.sweeper != GRID_SWEEPER:
        return run_optimiser(plan, args, jobs, title, echo)
    started = time.time()
    locate(plan.sweep_dir, plan.jobs)
    check_job_folders(plan.sweep_dir, plan.jobs)
    finished = {i for i, job in enumerate(plan.jobs) if job.path is not None and is_finished(job.path, job.sha)}
    todo = len(plan.jobs) - len(finished)
    if plan.workers_arg is not None and plan.workers and todo and todo < plan.workers:
        plan.workers = todo  # no more workers than jobs to run: each gets more threads
        plan.argv[plan.workers_arg] = f"hydra.launcher.n_jobs={todo}"
    plural = "s" if plan.workers != 1 else ""
    where = "as batches" if plan.launcher == BATCH_LAUNCHER else plan.launcher
    where += f", {plan.workers} worker{plural}" if plan.workers else ""
    echo(f"{title} directory: {plan.sweep_dir}")
    echo(
        f"{len(plan.jobs)} job{'s' if len(plan.jobs) != 1 else ''}: {todo} to run, {len(finished)} already "
        f"finished ({where})"
    )
    waiting = [job for i, job in enumerate(plan.jobs) if i not in finished]
    if todo:
        if plan.on_cluster:
            echo(tasks_line(waiting, plan))
        elif plan.batch:
            echo(batch_line(waiting, plan))
        echo(estimate_line(waiting, plan))
    launcher_error, interrupted = _launch(plan, waiting, finished, title, before_launch) if todo else (None, None)
    return _outcome(plan, args, jobs, todo, len(finished), time.time() - started, launcher_error, interrupted)


def _launch(plan: Plan, waiting: list, finished: set[int], title: str, before_launch) -> tuple[str | None, int | None]:
    """Launch the waiting jobs, shown live; the launcher's error and the signal that stopped it, if any."""
    if plan.launcher == "joblib" and plan.workers:
        os.environ[THREADS_ENV] = str(max(1, cpu_count() // plan.workers))
    name_driver(plan.local)  # its local workers end with this process
    if before_launch is not None:
        before_launch()
    if plan.on_cluster:  # the chunks the launcher submits, a task each
        write_tasks(plan.sweep_dir, waiting, task_chunks(waiting, plan.tasks))
    # Ctrl-C reaches local workers too, and they checkpoint and stop; the driver waits for that (see
    # DriverSignals), then reports the interruption.
    launcher_error, interrupted = None, None
    with (
        SweepView(plan.sweep_dir, plan.jobs, finished, title, batch_progress=PROGRESS if plan.batch else None),
        DriverSignals(plan.launcher not in LOCAL, passes_sigint=plan.launcher in POOLS) as stop,
    ):
        if plan.workers_arg is not None and plan.workers > 1 and not pool_started(plan.workers):
            in_background(lambda: start_workers(plan.workers, [delayed(os.getpid)()]))  # spawned with SIGINT held back
        # job by job, each job writes its .hydra/ once its folder is found to be its own (sweep_worker.OWN_FILES);
        # a batch's jobs are set up before Hydra's run_job (sweeping.batched)
        each = () if plan.batch else (OWN_FILES,)
        try:
            launcher_error = launch(plan.argv, plan.sweep_dir / "sweep.log", [job.overrides for job in waiting], each)
        except Interrupted as batch_stop:  # a batch trains here: it checkpointed and marked its jobs
            interrupted = batch_stop.signum
        finally:
            for part in [*plan.sweep_dir.glob(f"{PROGRESS}.*.json"), plan.sweep_dir / TASKS]:
                part.unlink(missing_ok=True)
    return launcher_error, interrupted or stop.received


def _outcome(
    plan: Plan, args: list[str], jobs: int | None, todo: int, skipped: int, seconds: float, launcher_error, interrupted
) -> Outcome:
    """Each job found where it ran, summary.parquet written, and what the sweep left."""
    for job in plan.jobs:  # a job found under another name (an older naming) ran in its own folder now
        if (
            job.folder is not None
            and job.path is not None
            and job.path.name != job.folder
            and (plan.sweep_dir / job.folder).is_dir()
        ):
            job.path = None
    locate(plan.sweep_dir, plan.jobs)
    summary = summarize(plan.jobs)
    write_summary(summary, plan.sweep_dir / SUMMARY)
    failed = [(row.job, row.error or row.status) for row in summary.itertuples() if row.status != "done"]
    resume = (
        [a for a in args if not a.startswith("hydra.sweep.dir=")]
        + [f"hydra.sweep.dir={plan.sweep_dir}"]
        + (["--jobs", str(jobs)] if jobs else [])
        + (["--batch"] if plan.batch else [])
    )
    return Outcome(
        plan.sweep_dir,
        summary,
        failed,
        todo,
        skipped,
        seconds,
        launcher_error,
        resume,
        None,
        False,
        interrupted,
    )


def estimate_seconds(jobs: list, plan: Plan) -> float:
    """The wall seconds these jobs of the plan should take on this machine (riskplan.run.cost): a batch pays one
    run's overhead per chunk, not per job."""
    model = cost.model()
    if plan.launcher == BATCH_LAUNCHER:
        return model.batch_seconds([job.steps for job in jobs], len(batch_chunks(jobs, plan)))
    return model.sweep_seconds([job.steps for job in jobs], plan.workers or 1)


def batch_chunks(jobs: list, plan: Plan) -> list[list]:
    """The batches these jobs will train in: grouped by what they share, cut to the memory a batch may use (as the
    batch launcher cuts them: riskplan.experiments.sweeping.batched)."""
    batchable = [job for job in jobs if job.batch]
    limit = (plan.memory or memory_budget())[0]
    return plan_chunks(batchable, limit, key=lambda job: job.batch, size=lambda job: job.memory)


def batch_line(jobs: list, plan: Plan) -> str:
    """A batched sweep's plan: its groups and chunks, and the memory they stay within."""
    chunks = batch_chunks(jobs, plan)
    groups = len({job.batch for job in jobs if job.batch})
    alone = sum(1 for job in jobs if not job.batch)
    budget, source = plan.memory or memory_budget()
    largest = max((sum(job.memory for job in chunk) for chunk in chunks), default=0.0)
    return (
        f"batched: {len(jobs) - alone} runs in {groups} group{'s' if groups != 1 else ''} of a shared world, "
        f"trained as {len(chunks)} batch{'es' if len(chunks) != 1 else ''} (the largest needs about {size(largest)}, "
        f"within the {size(budget)} memory budget: {source})" + (f"; {alone} jobs alone" if alone else "")
    )


def tasks_line(jobs: list, plan: Plan) -> str:
    """A batched sweep's plan on a cluster: its tasks, their largest, and the limits that sized them."""
    chunks, size_of = task_chunks(jobs, plan.tasks), plan.tasks
    largest = max(chunks, key=len)
    cpus = f"{size_of.cores} CPU{'s' if size_of.cores != 1 else ''}"
    time_limit = (
        f"; and half its time limit, {cost.duration(size_of.seconds)} on {cpus}"
        if size_of.seconds < math.inf
        else f"; on {cpus}"
    )
    return (
        f"batched on the cluster: {len(jobs)} runs as {len(chunks)} task{'s' if len(chunks) != 1 else ''} of up to "
        f"{len(largest)} runs (each within {size(size_of.memory)}: {size_of.source}{time_limit})"
    )


def estimate_line(jobs: list, plan: Plan) -> str:
    """What the jobs still to run should take: wall time for a local launcher, compute for a cluster's."""
    model = cost.model()
    if plan.launcher in LOCAL:
        return f"estimated time: {cost.say(estimate_seconds(jobs, plan), model)} ({model.describe()})"
    compute = sum(model.run_seconds(job.steps) for job in jobs)
    return f"estimated compute: {cost.say(compute, model)} of this machine's time ({model.describe()})"
