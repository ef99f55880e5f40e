"""`riskplan bench --sweep`: β × seed sweeps of the paper world, each against a baseline measured in the same run.

- A 24-run sweep (risk.beta=0.05,0.1,0.2 x 8 seeds) batched (`riskplan sweep --batch`) against the same sweep
  with a worker process per job (`--jobs` one per core), and whether both left the same numbers.
- A 64-run sweep batched, with every file it writes, against the bare loops of the same 64 trainings run one after
  another in this warm process: the rollout kernel and the CVaR gradient, nothing recorded, no evaluation. That
  baseline is the arithmetic a sweep cannot do without.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

from riskplan.engine.estimators import cvar_gradient
from riskplan.engine.schedules import step_size
from riskplan.engine.step import initial_state, rollouts
from riskplan.run.build import build_setup
from riskplan.run.compose import compose
from riskplan.util.limits import cpu_count

BETAS = (0.05, 0.1, 0.2)  # the 24-run sweep's (x 8 seeds)
MORE_BETAS = (0.05, 0.1, 0.2, 0.3)  # the 64-run sweep's (x 16 seeds)
RUN = ["train.samples=6000", "train.eval_episodes=10000"]
JOBS_TARGET = 3.0  # batched at least this many times quicker than a worker per job, on 2 cores
BARE_TARGET = 1.0  # the batched sweep at most this many times the bare loops of its trainings
COMPARED = ["job", "status", "mean", "cvar", "value_at_risk"]


def bench_sweep(quick: bool) -> list[dict]:
    """The two rows (--quick: fewer seeds and 50 iterations)."""
    iterations = 50 if quick else 200
    return [jobs_row(4 if quick else 8, iterations), bare_row(4 if quick else 16, iterations)]


def grid(betas: tuple[float, ...], seeds: int, iterations: int) -> list[str]:
    return [f"risk.beta={','.join(map(str, betas))}", f"seed=range(0,{seeds})", f"train.iterations={iterations}", *RUN]


def sweep(args: list[str], folder: Path, extra: list[str]) -> tuple[float, pd.DataFrame]:
    """`riskplan sweep ARGS EXTRA` into `folder`, in a process of its own (its own start-up, as a user's): its wall
    seconds and the numbers of its summary."""
    command = [*riskplan_command(), "sweep", *args, f"hydra.sweep.dir={folder}", *extra]
    started = time.perf_counter()
    subprocess.run(command, cwd=folder.parent, capture_output=True, check=True)
    wall = time.perf_counter() - started
    return wall, pd.read_parquet(folder / "summary.parquet")[COMPARED].reset_index(drop=True)


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


def riskplan_command() -> list[str]:
    """The console script beside this interpreter, or the module."""
    script = Path(sys.executable).with_name("riskplan")
    return [str(script)] if script.is_file() else [sys.executable, "-m", "riskplan"]
