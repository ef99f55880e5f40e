"""`riskplan bench --sweep`: β × seed sweeps of the paper world, each against a baseline measured in the same run.

- A 24-run sweep (risk.beta=0.05,0.1,0.2 x 8 seeds) batched (`riskplan sweep --batch`) against the same sweep
  with a worker process per job (`--jobs` one per core), and whether both left the same numbers.
- A 64-run sweep batched, with every file it writes, against the bare loops of the same 64 trainings run one after
  another in this warm process: the rollout kernel and the CVaR gradient, nothing recorded, no evaluation. That
  baseline is the arithmetic a sweep cannot do without.
- A 1,000-job sweep planned and set up for a batch (each job's folder, `.hydra/` files, status, lock and run, as
  data), against the set-up of the same jobs through one Hydra `run_job` each (timed on 50, scaled).
"""

from __future__ import annotations

import contextlib
import functools
import subprocess
import tempfile
import time
from pathlib import Path

import pandas as pd
from hydra._internal.callbacks import Callbacks
from hydra._internal.config_loader_impl import ConfigLoaderImpl
from hydra._internal.utils import create_config_search_path
from hydra.core.utils import setup_globals
from hydra.types import HydraContext, RunMode

from riskplan.config import schema
from riskplan.engine.estimators import cvar_gradient
from riskplan.engine.schedules import step_size
from riskplan.engine.step import initial_state, rollouts
from riskplan.experiments.bench_meters import riskplan_command
from riskplan.experiments.sweeping.batched import prepare_job, prepare_jobs
from riskplan.experiments.sweeping.plan import plan_sweep
from riskplan.run.build import build_setup
from riskplan.run.columns import read_parquet
from riskplan.run.compose import CONF_DIR, compose
from riskplan.util.limits import cpu_count

BETAS = (0.05, 0.1, 0.2)  # the 24-run sweep's (x 8 seeds)
MORE_BETAS = (0.05, 0.1, 0.2, 0.3)  # the 64-run sweep's (x 16 seeds)
RUN = ["train.samples=6000", "train.eval_episodes=10000"]
JOBS_TARGET = 3.0  # batched at least this many times quicker than a worker per job, on 2 cores
BARE_TARGET = 1.0  # the batched sweep at most this many times the bare loops of its trainings
COMPARED = ["job", "status", "mean", "cvar", "value_at_risk"]
SETUP_JOBS = 1000
SETUP_TARGET = 5.0  # seconds to plan and set up SETUP_JOBS jobs
HYDRA_SAMPLE = 50  # jobs the set-up row's baseline sets up through run_job, scaled to the row's


def bench_sweep(quick: bool) -> list[dict]:
    """The three rows (--quick: fewer seeds and 50 iterations)."""
    iterations = 50 if quick else 200
    return [
        jobs_row(4 if quick else 8, iterations),
        bare_row(4 if quick else 16, iterations),
        setup_row(SETUP_JOBS),
    ]


def grid(betas: tuple[float, ...], seeds: int, iterations: int) -> list[str]:
    return [f"risk.beta={','.join(map(str, betas))}", f"seed=range(0,{seeds})", f"train.iterations={iterations}", *RUN]


def sweep(args: list[str], folder: Path, extra: list[str]) -> tuple[float, pd.DataFrame]:
    """`riskplan sweep ARGS EXTRA` into `folder`, in a process of its own (its own start-up, as a user's): its wall
    seconds and the numbers of its summary."""
    command = [*riskplan_command(), "sweep", *args, f"hydra.sweep.dir={folder}", *extra]
    started = time.perf_counter()
    subprocess.run(command, cwd=folder.parent, capture_output=True, check=True)
    wall = time.perf_counter() - started
    return wall, read_parquet(folder / "summary.parquet")[COMPARED].reset_index(drop=True)


def jobs_row(seeds: int, iterations: int) -> dict:
    args = grid(BETAS, seeds, iterations)
    with tempfile.TemporaryDirectory() as tmp:
        workers = cpu_count()
        jobs_wall, jobs = sweep(args, Path(tmp) / "jobs", ["--jobs", str(workers)])
        batch_wall, batched = sweep(args, Path(tmp) / "batched", ["--batch"])
    same, runs, ratio = batched.equals(jobs), len(batched), jobs_wall / batch_wall
    return {
        "measure": f"a {runs}-run beta x seed sweep, batched (s)",
        "value": batch_wall,
        "unit": "s",
        "target": f">= {JOBS_TARGET:g}x quicker than --jobs {workers}",
        "ok": ratio >= JOBS_TARGET and same,
        "baseline": jobs_wall,
        "ratio": ratio,
        "note": f"baseline: the same sweep with --jobs {workers} (a worker process per job); {' '.join(args)}; "
        f"every run's mean, CVaR and VaR {'identical' if same else 'DIFFERENT'}",
    }


def bare_row(seeds: int, iterations: int) -> dict:
    args = grid(MORE_BETAS, seeds, iterations)
    with tempfile.TemporaryDirectory() as tmp:
        batch_wall, batched = sweep(args, Path(tmp) / "batched", ["--batch"])
    runs = [
        [f"risk.beta={b}", f"seed={s}", f"train.iterations={iterations}", *RUN]
        for b in MORE_BETAS
        for s in range(seeds)
    ]
    bare = bare_loops(runs)
    ratio = batch_wall / bare
    return {
        "measure": f"a {len(batched)}-run beta x seed sweep, batched, with its files (s)",
        "value": batch_wall,
        "unit": "s",
        "target": f"<= {BARE_TARGET:g}x the bare loops of its trainings",
        "ok": ratio <= BARE_TARGET,
        "baseline": bare,
        "ratio": ratio,
        "note": "baseline: each training's rollout kernel and CVaR gradient, one run after another in a warm "
        "process, nothing recorded, no evaluation; value: `riskplan sweep --batch` from its start to its exit",
    }


def setup_row(jobs: int) -> dict:
    args = ["train.iterations=1", *RUN]
    with tempfile.TemporaryDirectory() as tmp:
        started = time.perf_counter()
        plan = plan_sweep([f"seed=range(0,{jobs})", *args], None, Path(tmp) / "data", batch=True)
        planned = time.perf_counter() - started
        set_up = prepared_in(plan, as_data=True)
        sample = plan_sweep([f"seed=range(0,{HYDRA_SAMPLE})", *args], None, Path(tmp) / "hydra", batch=True)
        baseline = prepared_in(sample, as_data=False) * jobs / HYDRA_SAMPLE
    return {
        "measure": f"{jobs:,} jobs of a batched sweep planned and set up (s)",
        "value": planned + set_up,
        "unit": "s",
        "target": f"< {SETUP_TARGET:g} s",
        "ok": planned + set_up < SETUP_TARGET,
        "baseline": baseline,
        "ratio": baseline / (planned + set_up),
        "note": f"planned in {planned:.2f} s (parsed, composed, validated, named), set up in {set_up:.2f} s (folders, "
        f".hydra/ files, status, locks, runs built); baseline: the set-up alone through one Hydra run_job a job, "
        f"timed on {HYDRA_SAMPLE} jobs and scaled",
    }


def prepared_in(plan, as_data: bool) -> float:
    """Seconds to set up the plan's jobs for its batch launcher, in this process (nothing trained)."""
    setup_globals()
    schema.register()
    loader = ConfigLoaderImpl(config_search_path=create_config_search_path(str(CONF_DIR)))
    hydra_args = [a for a in plan.argv[1:] if a.lstrip("+").startswith("hydra")]
    config = loader.load_configuration("config", hydra_args, RunMode.MULTIRUN)
    context = HydraContext(config_loader=loader, callbacks=Callbacks(config))
    started = time.perf_counter()
    with contextlib.ExitStack() as held:
        begin = functools.partial(prepare_job, held=held)
        prepare_jobs(context, config, [job.overrides for job in plan.jobs], 0, begin, as_data)
    return time.perf_counter() - started


def bare_loops(runs: list[list[str]]) -> float:
    """Seconds of the runs' bare training loops, one after another (their set-ups built and the kernel loaded
    first, untimed)."""
    setups = [build_setup(compose(overrides)) for overrides in runs]
    rollouts(setups[0], 0, initial_state(setups[0]).thetas)  # the kernel, loaded from numba's cache
    started = time.perf_counter()
    for setup in setups:
        thetas, params = initial_state(setup).thetas, setup.params
        for l in range(params.train.iterations):
            z, scores = rollouts(setup, l, thetas)
            thetas = thetas + step_size(l, params.train.step_size) * cvar_gradient(z, scores, params.risk.beta)
    return time.perf_counter() - started
