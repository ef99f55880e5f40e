"""`riskplan bench`'s kernel floors: the time of the episode kernels a sweep or a reproduction ran, replayed in this
process on every core, against the wall time of the whole command. The arithmetic no recording, evaluation or
launcher can go under (the issue that made the loop the engine's asks a 256-run sweep to spend at least half of
its wall time in them, and a reproduction to take at most 75 s).

`replay` simulates again every episode of finished runs: each run's training episodes at the θ_l its
metrics.parquet logged for each robot, from the run's own streams, one kernel call per iteration for all the runs
that share a world (`step.batch_episodes`, as their batch made them); then each run's evaluation, its sampled paths
and θ0's episodes for the diagnosis. The replayed episodes are the runs' (each robot's logged mean at the first and
last iteration is checked against them, bit for bit), and only the kernels are timed.
"""

from __future__ import annotations

import contextlib
import tempfile
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pandas as pd

from riskplan.engine import rollout
from riskplan.engine.risk_measures import summary_stats
from riskplan.engine.step import RunSetup, batch_episodes, batch_key, rollouts
from riskplan.experiments.bench_sweep import MORE_BETAS, grid, sweep
from riskplan.run.build import build_setup
from riskplan.run.checkpoint import load_checkpoint
from riskplan.run.evaluation import evaluate, initial_objective, sample_paths
from riskplan.run.results import run_config
from riskplan.run.run_files import table_file

SEEDS = 64  # x len(MORE_BETAS): the 256 runs
SHARE_TARGET = 0.5  # the kernels' share of the sweep's wall time, at least
KERNELS = ("_simulate", "_simulate_affine")  # rollout.simulate's two episode kernels


def bench_kernel_share(quick: bool) -> list[dict]:
    """The sweep's row (--quick: 64 runs of 50 iterations)."""
    return [kernel_share_row(SEEDS // 4 if quick else SEEDS, 50 if quick else 200)]


def kernel_share_row(seeds: int, iterations: int) -> dict:
    """A len(MORE_BETAS) x `seeds` sweep of `iterations` iterations: its wall time against the kernel time of its
    replay."""
    args = grid(MORE_BETAS, seeds, iterations)
    with tempfile.TemporaryDirectory() as tmp:
        wall, _ = sweep(args, Path(tmp) / "batched", ["--batch"])
        runs = pd.read_parquet(Path(tmp) / "batched" / "summary.parquet")
        done = runs[runs["status"] == "done"]
        kernels, faithful = replay([Path(path) for path in done["path"]])
    share = kernels / wall
    return {
        "measure": f"a {len(runs)}-run beta x seed sweep, batched: its wall time (s)",
        "value": wall,
        "unit": "s",
        "target": f"episode kernels >= {SHARE_TARGET:g} of it",
        "ok": share >= SHARE_TARGET and faithful and len(done) == len(runs),
        "baseline": kernels,
        "ratio": share,
        "note": f"baseline: {replayed(faithful, len(done), len(runs))}; ratio: the kernels' share; value: `riskplan "
        f"sweep --batch` from its start to its exit; {' '.join(args)}",
    }


def replayed(faithful: bool, done: int, runs: int) -> str:
    """What a row's baseline is, and whether its replay was the runs' own episodes."""
    same = "equal to" if faithful else "DIFFERENT from"
    return (
        f"the episode kernels' seconds of the same runs, replayed in this process on every core (training at each "
        f"run's logged theta, evaluation, paths, theta0's episodes; {done} of {runs} runs done, their logged means "
        f"{same} the replay's)"
    )


def replay(paths: list[Path]) -> tuple[float, bool]:
    """Seconds inside the episode kernels to simulate again every episode of the finished runs at `paths`, and
    whether the replayed training episodes are the logged ones."""
    runs = [_logged(path) for path in paths]
    groups: dict[str, list[tuple]] = {}
    for run in runs:  # the runs a batch could share its kernel calls between
        groups.setdefault(batch_key(run[0].params), []).append(run)
    if runs:
        rollouts(runs[0][0], 0, runs[0][1][0])  # the kernel loaded from numba's cache, untimed
    faithful = True
    with kernel_clock() as spent:
        for group in groups.values():
            for l in range(max(len(thetas) for _, thetas, _, _ in group)):
                live = [run for run in group if l < len(run[1])]
                z, _, bounds = batch_episodes([run[0] for run in live], l, [run[1][l] for run in live])
                for (setup, thetas, means, _), start, stop in zip(live, bounds[:-1], bounds[1:]):
                    if l in (0, len(thetas) - 1):  # the loop's own statistics, row by row: the logged means
                        mean = summary_stats(z[start:stop], setup.params.risk.beta, parallel=True)["mean"]
                        faithful &= bool(np.array_equal(mean, means[l]))
        for setup, _, _, final in runs:
            evaluate(setup, final)
            sample_paths(setup, final)
            initial_objective(setup)
    return spent[0], faithful


def _logged(path: Path) -> tuple[RunSetup, np.ndarray, np.ndarray, np.ndarray]:
    """A finished run's set-up, its robots' logged theta_l (L, N, M) and means (L, N), and its final thetas."""
    with warnings.catch_warnings():  # a config's warnings (a step size outside Assumption 6) were its run's to give
        warnings.simplefilter("ignore", UserWarning)
        setup = build_setup(run_config(path), needs_ray=False)
    metrics = pd.read_parquet(path / table_file("metrics"))
    rows = metrics[metrics["robot"] >= 0].sort_values(["iteration", "robot"])  # the team average's row is not a robot's
    names = [f"theta_{j}" for j in range(len(setup.theta0))]
    thetas = rows[names].to_numpy().reshape(-1, setup.robots, len(names))
    means = rows["mean"].to_numpy().reshape(-1, setup.robots)
    return setup, thetas, means, load_checkpoint(path, setup).thetas


@contextlib.contextmanager
def kernel_clock() -> Iterator[list[float]]:
    """rollout's episode kernels timed while inside the block: yields a list whose one item sums their seconds."""
    spent = [0.0]
    originals = {name: getattr(rollout, name) for name in KERNELS}

    def timed(kernel):
        def call(*args):
            started = time.perf_counter()
            kernel(*args)
            spent[0] += time.perf_counter() - started

        return call

    for name, kernel in originals.items():
        setattr(rollout, name, timed(kernel))
    try:
        yield spent
    finally:
        for name, kernel in originals.items():
            setattr(rollout, name, kernel)
