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
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numba
from hydra.core.hydra_config import HydraConfig
from hydra.core.utils import JobReturn, JobStatus, configure_log, run_job, setup_globals
from omegaconf import DictConfig, open_dict

from riskplan.config.schema import Backend
from riskplan.engine.step import Setup, batch_key
from riskplan.experiments.sweep_worker import (
    JOB_LOG,
    JobStart,
    begin_job,
    end_job,
    failure,
    interrupt_job,
    outcome,
    sweep_job,
)
from riskplan.run.batch import BatchRun, train_batch
from riskplan.run.build import build_setup
from riskplan.run.cost import run_bytes
from riskplan.util import lock
from riskplan.util.errors import BadInput
from riskplan.util.interrupt import Interrupted
from riskplan.util.limits import cpu_count, memory_budget
from riskplan.util.paths import write_atomic

PROGRESS = ".batch_progress.json"  # in the sweep directory: iterations done of all, for the sweep's live view


@dataclass
class Prepared:
    """A job after Hydra set it up: its folder, where it stands, and its Setup when it trains in a batch."""

    out: Path
    start: JobStart | None = None  # None: another process holds its folder
    setup: Setup | None = None
    value: float | None = None  # its CVaR once done (or the finished job's)


def launch_batches(launcher, job_overrides, initial_job_idx: int) -> list[JobReturn]:
    """The Launcher's launch: set up every job through Hydra, train the waiting ones in batches, record each."""
    setup_globals()
    config, context = launcher.config, launcher.hydra_context
    configure_log(config.hydra.hydra_logging, config.hydra.verbose)
    sweep_dir = Path(str(config.hydra.sweep.dir))
    sweep_dir.mkdir(parents=True, exist_ok=True)
    numba.set_num_threads(min(cpu_count(), numba.config.NUMBA_NUM_THREADS))  # one process: every core
    returns: list[tuple[JobReturn, Prepared]] = []
    with contextlib.ExitStack() as held:  # each job folder's lock, until its job is recorded

        def prepare(cfg: DictConfig) -> Prepared:
            return _prepare(cfg, Path(HydraConfig.get().runtime.output_dir), held)

        for idx, overrides in enumerate(job_overrides, start=initial_job_idx):
            sweep_config = context.config_loader.load_sweep_config(config, list(overrides))
            with open_dict(sweep_config):
                sweep_config.hydra.job.id = idx
                sweep_config.hydra.job.num = idx
            done = run_job(
                hydra_context=context,
                task_function=prepare,
                config=sweep_config,
                job_dir_key="hydra.sweep.dir",
                job_subdir_key="hydra.sweep.subdir",
            )
            returns.append((done, done.return_value if done.status == JobStatus.COMPLETED else None))
            configure_log(config.hydra.hydra_logging, config.hydra.verbose)
        waiting = [p for _, p in returns if p is not None and p.setup is not None]
        limit = launcher.memory_gb * 1e9 if launcher.memory_gb else memory_budget()[0]
        chunks = plan_chunks(waiting, limit)
        total = sum(p.setup.params.train.iterations for p in waiting)
        done_before = 0
        for chunk in chunks:
            _train_chunk(chunk, sweep_dir, done_before, total)
            done_before += sum(p.setup.params.train.iterations for p in chunk)
    for done, prepared in returns:
        if prepared is not None:
            done.return_value = prepared.value
    return [done for done, _ in returns]


def _prepare(cfg: DictConfig, out: Path, held: contextlib.ExitStack) -> Prepared:
    """Take the job's folder and read where it stands; a ray-backend job trains now, as it would alone."""
    if cfg.team.backend == Backend.ray:
        return Prepared(out, value=sweep_job(cfg, out))
    try:
        held.enter_context(lock.hold(out, "sweep job folder"))
    except BadInput:  # another process writes it: that process records it
        return Prepared(out)
    start = begin_job(cfg, out)
    if start.finished:
        return Prepared(out, start, value=start.value)
    try:
        setup = build_setup(cfg)
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


def _train_chunk(chunk: list[Prepared], sweep_dir: Path, done_before: int, total: int) -> None:
    """Train one chunk as a batch and record each of its jobs (a signal: each is interrupted, resumable)."""
    for job in chunk:
        _log(job.out, job.start.opening + f", in a batch of {len(chunk)})")
    runs = [BatchRun(job.setup, job.out, job.start.resume) for job in chunk]
    shown = {"at": 0.0}

    def progress(done: int, _: int) -> None:
        now = time.time()
        if now - shown["at"] >= 0.5 or done_before + done == total:
            shown["at"] = now
            with contextlib.suppress(OSError):
                write_atomic(sweep_dir / PROGRESS, json.dumps({"done": done_before + done, "total": total}))

    try:
        train_batch(runs, progress)
    except Interrupted as stop:
        for job, run in zip(chunk, runs):
            if run.summary is None and run.error is None:
                _log(job.out, f"=== {stop}")
                interrupt_job(job.start, stop)
        raise
    for job, run in zip(chunk, runs):
        record = outcome(run.summary) if run.error is None else failure(run.error)
        job.value = _record(job.start, record)


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
