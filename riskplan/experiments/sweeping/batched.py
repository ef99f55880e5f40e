"""`riskplan sweep --batch`: the sweep's jobs trained as batches in the driver process, behind Hydra's launcher
interface (hydra_plugins.riskplan_batch_launcher), so every job keeps its folder, `.hydra/` files, status.json,
job.log and results as under any other launcher.

Hydra sets up each job (its folder and `.hydra/` files) with a task that only takes the folder's lock and reads
where the job stands (riskplan.experiments.sweep_worker.begin_job). The jobs still to train are then grouped by
what they must share (riskplan.engine.step.batch_key), each group cut into chunks that fit the memory a batch may
use, and each chunk trained as one batch (riskplan.run.batch). A job that cannot share a batch (the ray backend)
runs as it would under the basic launcher. A job that fails, fails alone.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numba
from hydra.core.hydra_config import HydraConfig
from hydra.core.utils import JobReturn, JobStatus, configure_log, run_job, setup_globals
from joblib import delayed
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from riskplan.config.backends import BACKENDS
from riskplan.config.schema import Backend
from riskplan.engine.step import RunSetup, batch_key
from riskplan.experiments.driver_watch import arrive, take_interrupts, working
from riskplan.experiments.sweep_worker import (
    JOB_LOG,
    JobStart,
    begin_job,
    end_job,
    failure,
    holds_another_run,
    interrupt_job,
    outcome,
    say_refused,
    sweep_job,
)
from riskplan.experiments.sweeping.grid import JobConfigs
from riskplan.experiments.sweeping.job_setup import JobSetup
from riskplan.experiments.sweeping.launch import pool_started, start_workers
from riskplan.run import cost
from riskplan.run.batch import BatchRun, train_batch
from riskplan.run.build import build_planned
from riskplan.run.cost import run_bytes
from riskplan.util import lock
from riskplan.util.errors import BadInput
from riskplan.util.interrupt import Interrupted, StopSignals, pending_signal
from riskplan.util.limits import cpu_count, memory_budget
from riskplan.util.paths import write_atomic

PARALLEL_SECONDS = 20.0  # a batch's estimated work from which splitting it over worker processes pays
NO_JOB_LOG = {  # the job logging of a job left out: nothing into its folder's job.log, another run's
    "version": 1,
    "handlers": {"null": {"class": "logging.NullHandler"}},
    "root": {"handlers": ["null"]},
    "disable_existing_loggers": False,
}
PROGRESS = ".batch_progress"  # <sweep>/.batch_progress.<chunk>.<part>.json: {"done", "total"} iterations, summed
# over the files by the sweep's live view; the sweep removes them when the launch ends


@dataclass
class Prepared:
    """A job after Hydra set it up: its folder, where it stands, and its RunSetup when it trains in a batch."""

    out: Path
    start: JobStart | None = None  # None: another process holds its folder
    setup: RunSetup | None = None
    value: float | None = None  # its CVaR once done (or the finished job's)
    seconds: float = 0.0  # its set-up through Hydra, the first part of its own time


def launch_batches(launcher, job_overrides, initial_job_idx: int) -> list[JobReturn]:
    """The Launcher's launch: set up every job, train the waiting ones in batches, record each."""
    setup_globals()
    config, context = launcher.config, launcher.hydra_context
    configure_log(config.hydra.hydra_logging, config.hydra.verbose)
    sweep_dir = Path(str(config.hydra.sweep.dir))
    sweep_dir.mkdir(parents=True, exist_ok=True)
    numba.set_num_threads(min(cpu_count(), numba.config.NUMBA_NUM_THREADS))  # one process: every core
    with contextlib.ExitStack() as held:  # each job folder's lock, until its job is recorded
        begin = functools.partial(prepare_job, held=held)
        returns = prepare_jobs(context, config, job_overrides, initial_job_idx, begin)
        waiting = [p for _, p in returns if p is not None and p.setup is not None]
        limit = launcher.memory_gb * 1e9 if launcher.memory_gb else memory_budget()[0]
        total = sum(p.setup.params.train.iterations for p in waiting)
        stop: Interrupted | None = None
        for number, chunks in enumerate(side_by_side(plan_chunks(waiting, limit), limit)):
            signum = stop.signum if stop else pending_signal()  # Ctrl-C while the jobs were set up, or a round ago
            if signum is not None:
                stop = stop or Interrupted(signum, 0)
                _not_trained([job for chunk in chunks for job in chunk], stop)
                continue
            workers = launcher.workers or workers_for([job for chunk in chunks for job in chunk])
            try:
                train_chunks(chunks, sweep_dir / f"{PROGRESS}.{number}", total, workers)
            except Interrupted as err:  # its jobs checkpointed and marked; the later rounds' are marked above
                stop = err
        if stop is not None:
            raise stop
    for done, prepared in returns:
        if prepared is not None:
            done.return_value = prepared.value
    return [done for done, _ in returns]


def prepare_jobs(
    context, config: DictConfig, job_overrides, first: int, begin, as_data: bool = True
) -> list[tuple[JobReturn, Prepared | None]]:
    """Set up each job: its folder and `.hydra/` files, then `begin(config, plain, out)`, which makes of it what
    the launcher needs (Prepared: locked, where it stands, its run; or a cluster task's job). Most jobs as data
    (sweeping.job_setup), their config typed and their plain config apart; the rest, or all of them without
    `as_data`, through Hydra's run_job, their DictConfig as both."""
    sweep_dir = Path(str(config.hydra.sweep.dir))

    def prepare(cfg: DictConfig):
        return begin(cfg, cfg, Path(HydraConfig.get().runtime.output_dir))

    configs = JobConfigs(context.config_loader, config)  # each job's config as Hydra makes it, quicker
    setup = JobSetup(configs, sweep_dir)
    returns = []
    for idx, overrides in enumerate(job_overrides, start=first):
        tic = time.perf_counter()
        job = setup(list(overrides), idx) if as_data else None  # most jobs: their files written directly
        if job is not None:
            done = JobReturn(list(overrides), working_dir=os.getcwd(), task_name=config.hydra.job.name)
            done.return_value = begin(job.config.params, job.config.plain, job.out)
            done.status = JobStatus.COMPLETED
        else:
            done = _run_job(context, prepare, configs(list(overrides)), idx)
            configure_log(config.hydra.hydra_logging, config.hydra.verbose)
        prepared = done.return_value if done.status == JobStatus.COMPLETED else None
        if prepared is not None:
            prepared.seconds = time.perf_counter() - tic
        returns.append((done, prepared))
    return returns


def _run_job(context, prepare, sweep_config: DictConfig, number: int) -> JobReturn:
    """A job set up through Hydra's run_job (what JobSetup cannot write as data)."""
    with open_dict(sweep_config):
        sweep_config.hydra.job.id = number
        sweep_config.hydra.job.num = number
        if _holds_another_run(sweep_config):  # Hydra writes no .hydra/ over that run's, nor a log line into its
            sweep_config.hydra.output_subdir = None  # job.log (a callback's): the job then refuses the folder
            sweep_config.hydra.job_logging = NO_JOB_LOG
    return run_job(
        hydra_context=context,
        task_function=prepare,
        config=sweep_config,
        job_dir_key="hydra.sweep.dir",
        job_subdir_key="hydra.sweep.subdir",
    )


def _holds_another_run(sweep_config: DictConfig) -> bool:
    """Whether the folder run_job would set this job up in holds a run of another config that did not fail
    (sweep_worker.foreign_run), as far as can be told before run_job: False when the folder or the job's config
    cannot be made out here (its start still refuses such a folder, once Hydra has written its .hydra/)."""
    try:
        out = Path(str(OmegaConf.select(sweep_config, "hydra.sweep.dir"))) / str(
            OmegaConf.select(sweep_config, "hydra.sweep.subdir")
        )
        if not out.is_dir():
            return False
        full = copy.deepcopy(sweep_config)  # set_config makes its hydra node read-only
        HydraConfig.instance().set_config(full)  # as run_job sets it, for ${hydra:...} in the config
        task = copy.deepcopy(full)  # the job's config as run_job hands it over: its hydra node removed
        with read_write(task), open_dict(task):
            del task["hydra"]
        return holds_another_run(out, task)
    except Exception:  # an interpolation only the job resolves, say: Hydra writes as it always did
        return False


def prepare_job(cfg, plain, out: Path, held: contextlib.ExitStack) -> Prepared:
    """Take the job's folder (its lock into `held`), read where it stands, and build its run (`cfg`: its config;
    `plain`: the same as a DictConfig or plain dict, for its identity). A ray-backend job (`cfg` a DictConfig)
    trains now, as it would alone."""
    if not BACKENDS[Backend(cfg.team.backend)].batched:
        return Prepared(out, value=sweep_job(cfg, out))
    with contextlib.ExitStack() as own:
        try:
            own.enter_context(lock.hold_lock(out, "sweep job folder"))
        except BadInput:  # another process writes it: that process records it
            return Prepared(out)
        start = begin_job(plain, out)
        if start.refused is not None:  # another config's run: left as it is, and its lock let go at once
            say_refused(start)
            return Prepared(out)
        held.push(own.pop_all())
    if start.finished:
        return Prepared(out, start, value=start.value)
    try:
        setup = build_planned(cfg)
    except Exception as err:  # bad input for this combination: it fails alone
        _log(out, start.opening + ")")
        return Prepared(out, start, value=_record(start, failure(err)))
    return Prepared(out, start, setup)


def plan_chunks(jobs: list, limit: float, key=lambda job: batch_key(job.setup.params), size=None) -> list[list]:
    """The jobs grouped by what they must share (`key`: batch_key), each group cut into chunks whose runs' memory
    (`size`: run_bytes) together stays within `limit` bytes; a run larger than that alone is a chunk of its own."""
    size = size or (lambda job: run_bytes(job.setup))
    groups: dict[str, list] = {}
    for job in jobs:
        groups.setdefault(key(job), []).append(job)
    chunks = []
    for group in groups.values():
        chunk, used = [], 0.0
        for job in group:
            need = size(job)
            if chunk and used + need > limit:
                chunks.append(chunk)
                chunk, used = [], 0.0
            chunk.append(job)
            used += need
        chunks.append(chunk)
    return chunks


def side_by_side(chunks: list[list], limit: float, size=lambda job: run_bytes(job.setup)) -> list[list[list]]:
    """The chunks in rounds trained at once: consecutive chunks whose runs' memory together stays within `limit`
    (a sweep of many worlds, a few runs each, trains them side by side, not one world after another)."""
    rounds: list[list[list]] = []
    used = 0.0
    for chunk in chunks:
        need = sum(size(job) for job in chunk)
        if not rounds or used + need > limit:
            rounds.append([])
            used = 0.0
        rounds[-1].append(chunk)
        used += need
    return rounds


def workers_for(chunk: list[Prepared]) -> int:
    """Processes to split a batch over: one per core when the local workers are up already (reproduce starts
    them while it plans), or when its work is large enough to pay for starting them (PARALLEL_SECONDS by
    riskplan.run.cost's model of this machine); else this process alone."""
    workers = min(cpu_count(), len(chunk))
    if workers > 1 and pool_started(workers):
        return workers
    seconds = sum(cost.model().run_seconds(cost.setup_steps(job.setup)) for job in chunk)
    return workers if seconds >= PARALLEL_SECONDS else 1


def train_chunks(chunks: list[list[Prepared]], progress: Path, total: int, workers: int, threads=None) -> None:
    """Train chunks (each its runs of one world) as batches and record each of their jobs (a signal: each is
    interrupted, resumable). With several `workers`, each chunk's runs are split into up to a part per worker, and
    the parts are trained as batches on the worker processes (the runs' own steps and files then go on in
    parallel too, and so do the chunks); with one, in this process, one chunk after another. `threads`: numba's
    in each (default: the cores, shared out)."""
    for chunk in chunks:
        for job in chunk:
            _log(job.out, job.start.opening + f", in a batch of {len(chunk)})")
    workers = max(1, min(workers, sum(len(chunk) for chunk in chunks)))
    parts = [chunk[i::split] for chunk in chunks for split in [min(workers, len(chunk))] for i in range(split)]
    files = [progress.with_name(f"{progress.name}.{i}.json") for i in range(len(parts))]
    for file in files:  # a killed launch's files would tell this one's parts their siblings had finished
        file.unlink(missing_ok=True)
    work = [
        delayed(train_part)(
            [job.setup if workers == 1 else job.setup.params for job in part],  # a worker builds from the params
            [job.out for job in part],
            [job.start.resume for job in part],
            threads or max(1, cpu_count() // workers),
            files[i],
            total,
            files[:i] + files[i + 1 :],
        )
        for i, part in enumerate(parts)
    ]
    if workers == 1:
        results = [call(*args, **kwargs) for call, args, kwargs in work]
    else:
        results = list(start_workers(workers, work))
    stopped = None
    for part, records in zip(parts, results):
        for job, record in zip(part, records):
            if record["status"] == "interrupted":
                stopped = record["signal"]
                _log(job.out, f"=== {record['error']}")
                interrupt_job(job.start, Interrupted(record["signal"], record["finished"]))
            else:
                job.value = _record(job.start, {**record, "seconds": job.seconds + record.get("seconds", 0.0)})
    if stopped is not None:
        raise Interrupted(stopped, min(r.get("finished", 0) for records in results for r in records))


def _not_trained(jobs: list[Prepared], stop: Interrupted) -> None:
    """Jobs set up but left untrained by a signal: marked interrupted (not running), each to start or resume when
    the sweep runs again."""
    for job in jobs:
        _log(job.out, f"=== interrupted by {stop.name} before it trained")
        interrupt_job(job.start, stop, f"interrupted by {stop.name} before it trained")


def train_part(
    setups, outs, resumes, threads: int, progress_file: Path, total: int, siblings: list[Path] = ()
) -> list[dict]:
    """A part of a batch in a worker process (or this one): its runs trained together under their folders' locks,
    which the driver holds; one status record per run ("interrupted" with the signal when one stopped them). Its
    iterations done go to `progress_file` (of `total` over the whole launch), and at its end that it finished.
    `siblings`: the other parts' files, whose cores this part takes as they finish (`FreedCores`). A finished
    run's record holds its own `seconds` of the part (`own_seconds`). `setups`: each run's RunSetup, or in a worker
    process its frozen config, built here (typed already: building it is a few milliseconds, typing a config dict
    again tens)."""
    arrive()  # in a worker process: it ends with the driver
    started = time.perf_counter()
    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    setups = [s if isinstance(s, RunSetup) else build_planned(s) for s in setups]
    runs = [BatchRun(setup, Path(out), resume) for setup, out, resume in zip(setups, outs, resumes)]
    freed = FreedCores(threads, list(siblings))
    shown = {"at": 0.0, "done": 0}

    def progress(done: int, own: int) -> None:
        now = time.time()
        if now - shown["at"] >= 0.5 or done == own:
            shown.update(at=now, done=done)
            with contextlib.suppress(OSError):
                write_atomic(progress_file, json.dumps({"done": done, "total": total}))
            freed.take()

    try:
        with working(), StopSignals():  # a Ctrl-C from this worker's start on stops the batch (which takes it up)
            take_interrupts()
            train_batch(runs, progress, locked=True, between=freed.take)
    except Interrupted as stop:
        return [
            outcome(run.summary)
            if run.summary is not None
            else (failure(run.error) if run.error is not None else _interrupted(stop, run))
            for run in runs
        ]
    finally:
        with contextlib.suppress(OSError):
            write_atomic(progress_file, json.dumps({"done": shown["done"], "total": total, "finished": True}))
    own = own_seconds(runs, time.perf_counter() - started)
    return [
        outcome(run.summary) | {"seconds": s} if run.error is None else failure(run.error) for run, s in zip(runs, own)
    ]


class FreedCores:
    """A part's share of the cores as the other parts of its launch finish: numba's threads raised to the cores
    over the parts still training (their files not yet marked finished). A batch of 5 like runs on 2 workers is
    parts of 3 and 2 runs; once the part of 2 has finished, the part of 3 goes on on both cores instead of one. The
    numbers do not depend on the threads (the kernels' streams and sums are fixed per episode and per resample)."""

    def __init__(self, threads: int, siblings: list[Path]):
        self.threads, self.siblings = threads, siblings

    def take(self) -> None:
        if not self.siblings:
            return
        self.siblings = [path for path in self.siblings if not _finished(path)]
        want = max(self.threads, cpu_count() // (1 + len(self.siblings)))
        if want > numba.get_num_threads():
            numba.set_num_threads(min(want, numba.config.NUMBA_NUM_THREADS))


def _finished(progress_file: Path) -> bool:
    """Whether the part that writes `progress_file` has marked it finished."""
    try:
        return json.loads(progress_file.read_text()).get("finished") is True
    except (OSError, ValueError, AttributeError):
        return False


def own_seconds(runs: list[BatchRun], seconds: float) -> list[float]:
    """Each run's own time of a part that took `seconds`: its share of the loop and its own evaluation and files
    (BatchRun.seconds; none for a run that failed), plus an equal share of the rest, what no run had alone
    (building the set-ups, loading the kernels, opening the logs). They add up to `seconds`."""
    rest = max(0.0, seconds - sum(run.seconds or 0.0 for run in runs)) / max(len(runs), 1)
    return [(run.seconds or 0.0) + rest for run in runs]


def _interrupted(stop: Interrupted, run: BatchRun) -> dict:
    finished = run.driver.state.iteration if run.driver is not None else 0
    return {"status": "interrupted", "error": str(stop), "signal": stop.signum, "finished": finished}


def _record(start: JobStart, record: dict) -> float | None:
    """A job's last job.log line and its final status.json."""
    _log(start.out, f"=== {record['status']}" + (f": {record['error']}" if record["error"] else ""))
    if "traceback" in record:
        _log(start.out, record["traceback"])
    return end_job(start, record)


def _log(out: Path, line: str) -> None:
    """A line of the job's job.log (its batch prints nothing else there)."""
    with contextlib.suppress(OSError), open(out / JOB_LOG, "a") as handle:
        handle.write(line.rstrip("\n") + "\n")
