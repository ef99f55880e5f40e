"""`riskplan bench`'s kernel floors: the time of the kernels a sweep or a reproduction ran, replayed in this process
on every core, against the wall time of the whole command. The arithmetic no recording, evaluation or launcher can
go under (the issue that made the loop the engine's asks a 256-run sweep to spend at least half of its wall time in
the episode kernels, and a reproduction to take at most 75 s).

`replay` simulates again every episode of finished runs: each run's training episodes at the θ_l its
metrics.parquet logged for each robot, from the run's own streams, one kernel call per iteration for all the runs
that share a world (`step.batch_episodes`, as their batch made them); then each run's evaluation, its sampled paths
and its summary, whose bootstrap intervals are kernels too (1,000 resamples of every evaluation, each drawing as
many indices as it has episodes) and which simulates θ0's episodes for the diagnosis. The replayed episodes are the
runs' (each robot's logged mean at the first and last iteration is checked against them, bit for bit), and only the
kernels are timed: the episode kernels and the bootstrap kernels apart.
"""

from __future__ import annotations

import contextlib
import tempfile
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd

from riskplan.engine import rollout, threads
from riskplan.engine.risk_measures import summary_stats
from riskplan.engine.step import RunSetup, TrainState, batch_episodes, batch_key, rollouts
from riskplan.experiments.bench_sweep import MORE_BETAS, grid, sweep
from riskplan.run.build import build_setup
from riskplan.run.checkpoint import load_checkpoint
from riskplan.run.columns import read_parquet
from riskplan.run.evaluation import evaluate, sample_paths, summarize
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
        runs = read_parquet(Path(tmp) / "batched" / "summary.parquet")
        done = runs[runs["status"] == "done"]
        floor = replay([Path(path) for path in done["path"]])
    share = floor.episodes / wall
    return {
        "measure": f"a {len(runs)}-run beta x seed sweep, batched: its wall time (s)",
        "value": wall,
        "unit": "s",
        "target": f"episode kernels >= {SHARE_TARGET:g} of it",
        "ok": share >= SHARE_TARGET and floor.faithful and len(done) == len(runs),
        "baseline": floor.episodes,
        "ratio": share,
        "note": f"baseline: {replayed(floor, len(done), len(runs))}; ratio: the kernels' share; value: `riskplan "
        f"sweep --batch` from its start to its exit; {' '.join(args)}",
    }


def replayed(floor: Replay, done: int, runs: int, bootstrap: bool = False) -> str:
    """What a row's baseline is: the episode kernels' seconds, with the bootstrap kernels' where `bootstrap`; and
    whether the replay was the runs' own episodes."""
    same = "equal to" if floor.faithful else "DIFFERENT from"
    kernels = (
        f"the episode and bootstrap kernels' seconds ({floor.episodes:.1f} s and {floor.bootstrap:.1f} s)"
        if bootstrap
        else f"the episode kernels' seconds (the bootstrap kernels' {floor.bootstrap:.1f} s not counted)"
    )
    return (
        f"{kernels} of the same runs, replayed in this process on every core (training at each run's logged theta, "
        f"evaluation, paths, theta0's episodes, the summary's intervals; {done} of {runs} runs done, their logged "
        f"means {same} the replay's)"
    )


class Replay(NamedTuple):
    """What replaying finished runs took in their kernels, and whether it was the runs' own episodes."""

    episodes: float  # seconds in the episode kernels: training, evaluation, paths, theta0's episodes
    bootstrap: float  # seconds in the bootstrap kernels of the runs' summaries
    faithful: bool  # every replayed robot's mean the logged one, bit for bit


class _Logged(NamedTuple):
    setup: RunSetup
    thetas: np.ndarray  # the robots' logged theta_l, (L, N, M)
    means: np.ndarray  # their logged means, (L, N)
    state: TrainState  # the final one, from the checkpoint
    metrics: pd.DataFrame


def replay(paths: list[Path]) -> Replay:
    """The kernels' seconds to simulate again every episode of the finished runs at `paths` and bootstrap their
    summaries, and whether the replayed training episodes are the logged ones."""
    runs = [_logged(path) for path in paths]
    groups: dict[str, list[_Logged]] = {}
    for run in runs:  # the runs a batch could share its kernel calls between
        groups.setdefault(batch_key(run.setup.params), []).append(run)
    if runs:  # the first run's episode and bootstrap kernels loaded from numba's cache, untimed
        first = runs[0]
        rollouts(first.setup, 0, first.thetas[0])
        summarize(first.setup, first.state, evaluate(first.setup, first.state.thetas), first.metrics, 1.0)
    faithful = True
    with kernel_clock() as spent:
        for group in groups.values():
            for l in range(max(len(run.thetas) for run in group)):
                live = [run for run in group if l < len(run.thetas)]
                z, _, bounds = batch_episodes([run.setup for run in live], l, [run.thetas[l] for run in live])
                for run, start, stop in zip(live, bounds[:-1], bounds[1:]):
                    if l in (0, len(run.thetas) - 1):  # the loop's own statistics, row by row: the logged means
                        mean = summary_stats(z[start:stop], run.setup.params.risk.beta, parallel=True)["mean"]
                        faithful &= bool(np.array_equal(mean, run.means[l]))
        for run in runs:
            evaluation = evaluate(run.setup, run.state.thetas)
            sample_paths(run.setup, run.state.thetas)
            summarize(run.setup, run.state, evaluation, run.metrics, 1.0)  # its intervals and theta0's episodes
    return Replay(spent["episodes"], spent["bootstrap"], faithful)


def _logged(path: Path) -> _Logged:
    """A finished run's set-up, its robots' logged theta_l and means, its final state and its metrics."""
    with warnings.catch_warnings():  # a config's warnings (a step size outside Assumption 6) were its run's to give
        warnings.simplefilter("ignore", UserWarning)
        setup = build_setup(run_config(path), needs_ray=False)
    metrics = read_parquet(path / table_file("metrics"))
    rows = metrics[metrics["robot"] >= 0].sort_values(["iteration", "robot"])  # the team average's row is not a robot's
    names = [f"theta_{j}" for j in range(len(setup.theta0))]
    thetas = rows[names].to_numpy().reshape(-1, setup.robots, len(names))
    means = rows["mean"].to_numpy().reshape(-1, setup.robots)
    return _Logged(setup, thetas, means, load_checkpoint(path, setup), metrics)


@contextlib.contextmanager
def kernel_clock() -> Iterator[dict[str, float]]:
    """rollout's episode kernels and the bootstrap kernels (every one runs through threads.over_threads) timed
    while inside the block: yields {"episodes": seconds, "bootstrap": seconds}, summed as they run."""
    spent = {"episodes": 0.0, "bootstrap": 0.0}
    timed_here = [(rollout, name, "episodes") for name in KERNELS] + [(threads, "over_threads", "bootstrap")]
    originals = [(module, name, getattr(module, name)) for module, name, _ in timed_here]

    def timed(kernel, kind):
        def call(*args):
            started = time.perf_counter()
            kernel(*args)
            spent[kind] += time.perf_counter() - started

        return call

    for (module, name, kind), (_, _, kernel) in zip(timed_here, originals):
        setattr(module, name, timed(kernel, kind))
    try:
        yield spent
    finally:
        for module, name, kernel in originals:
            setattr(module, name, kernel)
