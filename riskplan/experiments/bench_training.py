"""`riskplan bench`'s training rows: a training run's time and memory, checkpoints every 10 iterations against one,
an iteration under each risk measure against a CVaR iteration, and a team's iteration and memory against one robot
with the same total samples."""

from __future__ import annotations

import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from riskplan.engine.step import initial_state, step
from riskplan.experiments.bench_meters import best_time, reset_peak, rss_mb
from riskplan.run.build import build_setup
from riskplan.run.compose import compose
from riskplan.run.training import train

MEMORY_GROWTH = 1.2  # bytes per added sample between the largest sizes, against the smallest: 1 is linear


def bench_training(quick: bool) -> list[dict]:
    """200 iterations at W = 6000 with logging and checkpoints, evaluation excluded; memory over import."""
    import_rss = rss_mb()
    cfg = compose(
        ["train.eval_episodes=1000", "train.bootstrap=40", "train.paths=2"] + (["train.iterations=50"] if quick else [])
    )
    reset_peak()
    with tempfile.TemporaryDirectory() as tmp:
        run = train(cfg, Path(tmp) / "run")
    peak = rss_mb("VmHWM")
    iterations = cfg.train.iterations
    wall = run.summary["wall_time"]
    per_iteration = run.metrics.seconds.sum() / iterations
    return [
        {
            "measure": f"training, {iterations} iterations at W=6000 (s)",
            "value": wall,
            "unit": "s",
            "target": f"<= {0.2 * iterations / 200:g} (0.2 s per 200 iterations)",
            "ok": wall <= 0.2 * iterations / 200,
            "baseline": per_iteration * iterations,
            "ratio": wall / (per_iteration * iterations),
            "note": "baseline: the iterations' own compute; ratio = overhead of logging, checkpoints, JIT load",
        },
        {
            "measure": "memory growth over the post-import baseline (MB)",
            "value": peak - import_rss,
            "unit": "MB",
            "target": "< 100",
            "ok": peak - import_rss < 100,
            "baseline": import_rss,
            "ratio": peak / import_rss,
            "note": f"peak RSS {peak:.0f} MB during training vs {import_rss:.0f} MB after import",
        },
    ]


def bench_checkpoints(quick: bool) -> list[dict]:
    """Many cheap iterations with a checkpoint every 10 against one checkpoint at the end: O(1) per checkpoint."""
    iterations = 1000 if quick else 4000
    base = [
        "train.samples=20",
        f"train.iterations={iterations}",
        "train.eval_episodes=100",
        "train.bootstrap=40",
        "train.paths=1",
    ]
    walls = {}
    with tempfile.TemporaryDirectory() as tmp:
        train(compose([*base, "train.iterations=5"]), Path(tmp) / "warm-up")  # kernels loaded before timing
        for every in (iterations, 10):
            run = train(compose([*base, f"train.checkpoint_every={every}"]), Path(tmp) / f"every_{every}")
            walls[every] = run.summary["wall_time"]
        size = (Path(tmp) / "every_10" / "checkpoint").stat().st_size
    ratio = walls[10] / walls[iterations]
    return [
        {
            "measure": f"training, {iterations} iterations at W=20, a checkpoint every 10 (s)",
            "value": walls[10],
            "unit": "s",
            "target": "< 2x one checkpoint at the end",
            "ok": ratio < 2.0,
            "baseline": walls[iterations],
            "ratio": ratio,
            "note": f"baseline: one checkpoint at the end; each checkpoint is {size} bytes "
            f"(the state, not the rows so far), fsynced with the log",
        }
    ]


TEAM_SAMPLES = 100_000  # total samples per iteration of the team benchmarks and the scaling study's robots (N * W_i)
# The team and scaling rows time iterations only: a small evaluation keeps the run's memory check to what they use (1000
# robots' default evaluation, 100,000 episodes for each of 1001 policies, would need about 16 GB).
ITERATIONS_ONLY = "train.eval_episodes=1000"


def iteration_time(overrides: list[str], quick: bool) -> float:
    """Seconds of one training iteration (`engine.step.step`: rollouts, gradients, consensus, checks) of the set-up
    that overrides give, the best of several after a warm-up iteration."""
    setup = build_setup(compose(overrides))
    state, _ = step(setup, initial_state(setup))  # warm

    def one():
        nonlocal state
        state, _ = step(setup, state)

    return best_time(one, 3, 3 if quick else 10)


def bench_measures(quick: bool) -> list[dict]:
    """The paper set-up's first iteration (W = 6000, θ0: the same episodes) under each other risk measure, against
    a CVaR iteration. The measures take turns, one iteration each, so the machine's drift reaches them alike; each
    keeps the median of its iterations."""
    measures = ("cvar", "wang", "mean_cvar", "entropic")
    setups = {m: build_setup(compose([f"risk={m}"])) for m in measures}
    firsts = {m: initial_state(setup) for m, setup in setups.items()}
    seconds: dict[str, list[float]] = {m: [] for m in measures}
    for turn in range(60 if quick else 300):
        for measure in measures:
            started = time.perf_counter()
            step(setups[measure], firsts[measure])
            if turn:  # the first turn warms every measure up
                seconds[measure].append(time.perf_counter() - started)
    best = {m: float(np.median(times)) for m, times in seconds.items()}
    cvar = best["cvar"]
    rows = []
    for measure in measures[1:]:
        seconds = best[measure]
        rows.append(
            {
                "measure": f"iteration under risk={measure}, the paper set-up (s)",
                "value": seconds,
                "unit": "s",
                "target": "<= 1.2x a CVaR iteration",
                "ok": seconds <= 1.2 * cvar,
                "baseline": cvar,
                "ratio": seconds / cvar,
                "note": "baseline: a CVaR iteration (rollouts, gradient, step) on the same episodes; medians of "
                "iterations taken in turn",
            }
        )
    return rows


def bench_team(quick: bool) -> list[dict]:
    """100 robots (W_i = 1000) and 1000 robots (W_i = 100) on a random geometric graph, vs one robot with the same
    total samples (W = 100000)."""
    central = iteration_time([f"train.samples={TEAM_SAMPLES}"], quick)
    rows = []
    for robots in (100, 1000):
        team = iteration_time(
            [
                f"team.robots={robots}",
                "team.graph=random_geometric",
                f"train.samples={TEAM_SAMPLES // robots}",
                ITERATIONS_ONLY,
            ],
            quick,
        )
        rows.append(
            {
                "measure": f"team iteration, {robots} robots RGG, W_i={TEAM_SAMPLES // robots} (s)",
                "value": team,
                "unit": "s",
                "target": "<= 1.5x centralized",
                "ok": team <= 1.5 * central,
                "baseline": central,
                "ratio": team / central,
                "note": f"baseline: one robot, W={TEAM_SAMPLES} (same total samples)",
            }
        )
    sizes = [(25, 1000), (50, 1000), (100, 1000), (100, 2000), (200, 2000)]
    growth = []
    for robots, samples in sizes[:3] if quick else sizes:
        setup = build_setup(
            compose(
                [f"team.robots={robots}", "team.graph=random_geometric", f"train.samples={samples}", ITERATIONS_ONLY]
            )
        )
        state = initial_state(setup)
        tracemalloc.start()  # numpy reports its buffers to tracemalloc: exact peak bytes of one iteration
        step(setup, state)
        growth.append((robots * samples, tracemalloc.get_traced_memory()[1] / 2**20))
        tracemalloc.stop()
    n, mb = np.array(growth, dtype=float).T
    slope, intercept = np.polyfit(n, mb, 1)
    fit = 1 - np.sum((mb - (slope * n + intercept)) ** 2) / max(np.sum((mb - mb.mean()) ** 2), 1e-12)
    smallest, largest = ((mb[j] - mb[i]) / (n[j] - n[i]) * 2**20 for i, j in ((0, 1), (-2, -1)))
    rows.append(
        {
            "measure": "team iteration memory",
            "value": slope * 2**20,
            "unit": "bytes per sample",
            "target": f"linear in N*W_i (R^2 > 0.99; bytes per added sample at most {MEMORY_GROWTH:g}x the smallest's)",
            "ok": fit > 0.99 and largest <= MEMORY_GROWTH * smallest,
            "baseline": smallest,
            "ratio": largest / smallest,
            "note": "peak allocation at N*W_i = "
            + ", ".join(f"{int(a)}: {b:.1f} MB" for a, b in growth)
            + f"; value: a linear fit's slope (R^2 {fit:.4f}); baseline: bytes per sample added between the two "
            "smallest sizes; ratio: the same between the two largest over it (a term in N^2 would raise it)",
        }
    )
    return rows
