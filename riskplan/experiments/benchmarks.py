"""`riskplan bench`: the speed and memory targets, each printed with its baseline measured in the same run."""

from __future__ import annotations

import json
import math
import os
import random
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import NullLocator

from riskplan.engine import rng
from riskplan.engine.distributions import Dist
from riskplan.engine.rollout import simulate
from riskplan.engine.schedules import samples_at
from riskplan.engine.step import starts
from riskplan.run.build import build_setup
from riskplan.run.checkpoint import State
from riskplan.run.compose import compose
from riskplan.run.training import iterate, train


def rss_mb(field: str = "VmRSS") -> float:
    """Resident (VmRSS) or peak resident (VmHWM) memory of this process, in MB (Linux /proc)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def reset_peak() -> None:
    """Reset VmHWM to the current RSS (Linux >= 4.0), so the next peak is this section's own."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def best_time(fn, repeats: int, inner: int) -> float:
    """Best mean seconds per call over `repeats` rounds of `inner` calls (noise-robust)."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(inner):
            fn()
        best = min(best, (time.perf_counter() - start) / inner)
    return best


def python_draw(dist: Dist, rand: random.Random) -> float:
    """One draw of a reward distribution in plain Python (the baseline's reward model)."""
    kind, p = dist.kind, dist.params
    if kind == "constant":
        return p[0]
    if kind == "uniform":
        return p[0] + (p[1] - p[0]) * rand.random()
    if kind == "normal":
        return rand.gauss(p[0], p[1])
    if kind == "bernoulli":
        return 1.0 if rand.random() < p[0] else 0.0
    if kind == "scale":
        return p[0] * python_draw(dist.children[0], rand)
    if kind == "clip":
        return min(max(python_draw(dist.children[0], rand), p[0]), p[1])
    if kind == "sum":
        return sum(python_draw(c, rand) for c in dist.children)
    pick = rand.choices(range(len(p)), weights=p)[0]
    return python_draw(dist.children[pick], rand)


def python_rollouts(world, theta: np.ndarray, episodes: int, seed: int) -> tuple[np.ndarray, int]:
    """The baseline: a plain per-trajectory Python loop with the kernel's semantics (static sources)."""
    rand = random.Random(seed)
    signals = world.signals()
    source_at = {int(c): j for j, c in reversed(list(enumerate(world.source_cells)))}
    totals, steps = np.empty(episodes), 0
    for e in range(episodes):
        cell, z, score = int(world.starts[0]), 0.0, np.zeros(world.sources)
        for _ in range(world.horizon):
            feats = signals[world.next_cell[cell]]  # (5, M)
            logits = feats @ theta
            weights = np.exp(logits - logits.max())
            probs = weights / weights.sum()
            move = rand.choices(range(5), weights=probs)[0]
            score += feats[move] - probs @ feats
            cell = int(world.next_cell[cell, move])
            steps += 1
            region = world.region_of[cell]
            z += python_draw(world.region_rewards[region], rand) if region >= 0 else 0.0
            hit = source_at.get(cell, -1)
            if hit >= 0:
                z += python_draw(world.source_rewards[hit], rand)
                if world.stop_at_source:
                    break
        totals[e] = z
    return totals, steps


def bench_rollout(quick: bool) -> list[dict]:
    """Batched kernel vs the plain Python loop on the paper world at theta0, W = 6000."""
    setup = build_setup(compose([]))
    theta = setup.theta0[None, :]
    keys = rng.robot_keys(0, rng.TRAIN, 0, 1)
    batch = simulate(setup.world, setup.kernel, theta, setup.world.starts, keys, 6000)  # warm (JIT cache)
    # the same 5 x 40 calls (~0.4 s) with --quick: fewer gave readings 30% low on this noisy VM
    seconds = best_time(lambda: simulate(setup.world, setup.kernel, theta, setup.world.starts, keys, 6000), 5, 40)
    kernel_rate = batch.steps.sum() / seconds
    episodes = 50 if quick else 300
    start = time.perf_counter()
    _, steps = python_rollouts(setup.world, setup.theta0, episodes, 0)
    python_rate = steps / (time.perf_counter() - start)
    return [
        {
            "measure": "rollout, W=6000, theta0 (trajectory-steps/s)",
            "value": kernel_rate,
            "unit": "steps/s",
            "target": ">= 1.5e8",
            "ok": kernel_rate >= 1.5e8,
            "baseline": python_rate,
            "ratio": kernel_rate / python_rate,
            "note": f"{seconds * 1e3:.2f} ms per batch; baseline: plain Python "
            f"loop, {episodes} trajectories (ratio target > 1000x)",
        },
    ]


def bench_training(quick: bool) -> list[dict]:
    """200 iterations at W = 6000 with logging and checkpoints, evaluation excluded; memory over import."""
    import_rss = rss_mb()
    cfg = compose(
        ["train.eval_episodes=1000", "train.bootstrap=10", "train.paths=2"] + (["train.iterations=50"] if quick else [])
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
            "target": "<= 0.2 (200 iterations)",
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
        "train.bootstrap=5",
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


def bench_jit() -> list[dict]:
    """First-call time with an empty numba cache (compile) vs a warm on-disk cache, in fresh processes."""
    code = (
        "import time; t = time.perf_counter(); import riskplan.experiments.benchmarks as b; "
        "b.bench_rollout_once(); print(time.perf_counter() - t)"
    )
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        cold, warm = (
            float(
                subprocess.run(
                    [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
                ).stdout.split()[-1]
            )
            for _ in range(2)
        )
    return [
        {
            "measure": "first rollout in a new process, warm JIT cache (s)",
            "value": warm,
            "unit": "s",
            "target": "small next to a run",
            "ok": warm < 2.0,
            "baseline": cold,
            "ratio": warm / cold,
            "note": f"baseline: empty cache, compiles the kernels ({cold:.1f} s, once per install)",
        }
    ]


def bench_rollout_once() -> None:
    """One small rollout (used by bench_jit in a child process)."""
    setup = build_setup(compose([]))
    simulate(setup.world, setup.kernel, setup.theta0[None, :], setup.world.starts, rng.robot_keys(0, 1, 0, 1), 100)


# the child of bench_startup: `riskplan train`, printing the wall clock when the first iteration reports progress
FIRST_ITERATION = """
import sys, time
import riskplan.util.progress as progress
update = progress.TrainingBar.update
def first(self, *args):
    if not getattr(self, "_stamped", False):
        self._stamped = True
        sys.__stderr__.write(f"FIRST-ITERATION {time.time()!r}\\n")
        sys.__stderr__.flush()
    return update(self, *args)
progress.TrainingBar.update = first
sys.argv = ["riskplan", "train", "train.iterations=3", "train.eval_episodes=1000", "train.bootstrap=10",
            "train.paths=1"]
import runpy
runpy.run_module("riskplan", run_name="__main__")  # python -m riskplan train ...
"""


def user_env() -> dict[str, str]:
    """The environment a user's shell gives a command: Python writes and reads its bytecode caches (a machine
    that sets PYTHONDONTWRITEBYTECODE would compile every module from source at every start)."""
    return {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def wall(argv: list[str], cwd: Path, marker: str | None = None, env: dict[str, str] | None = None) -> float:
    """Seconds from starting `argv` to its end, or to the wall-clock time it prints after `marker`; `env`: variables
    set on top of the user's environment."""
    start = time.time()
    done = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, check=True, env={**user_env(), **(env or {})})
    end = time.time()
    if marker is None:
        return end - start
    stamps = [float(line.split()[1]) for line in done.stderr.splitlines() if line.startswith(marker)]
    if not stamps:
        raise RuntimeError(f"no {marker} line from {argv[:3]}: {done.stderr[-300:]}")
    return stamps[0] - start


def bench_startup(quick: bool) -> list[dict]:
    """`riskplan train` from the command to its first iteration (warm JIT cache), and `riskplan --help`, in new
    processes (best of several); baselines: a process that only imports numba, and one that only imports typer."""
    script = Path(sys.executable).with_name("riskplan")
    cli = [str(script)] if script.is_file() else [sys.executable, "-m", "riskplan"]
    runs = 2 if quick else 3
    with tempfile.TemporaryDirectory() as tmp:
        whole, loops = [], []
        for k in range(runs + 1):  # the first run writes the bytecode caches; it is not timed
            seconds = wall([*cli, "train", f"hydra.run.dir={Path(tmp) / f'whole{k}'}"], Path(tmp))
            summary = json.loads((Path(tmp) / f"whole{k}" / "summary.json").read_text())
            compute = float(pd.read_parquet(Path(tmp) / f"whole{k}" / "metrics.parquet").seconds.sum())
            if k:
                whole.append(seconds)
                loops.append((summary["wall_time"], compute))
        loop, compute = min(loops)
        train = min(wall([sys.executable, "-c", FIRST_ITERATION], Path(tmp), "FIRST-ITERATION") for _ in range(runs))
        numba_only = min(wall([sys.executable, "-c", "import numba"], Path(tmp)) for _ in range(runs))
        helps = min(wall([*cli, "--help"], Path(tmp)) for _ in range(runs + 2))
        typer_only = min(wall([sys.executable, "-c", "import typer"], Path(tmp)) for _ in range(runs + 2))
    return [
        {
            "measure": "riskplan train, the paper set-up, the whole command, warm JIT cache (s)",
            "value": min(whole),
            "unit": "s",
            "target": "<= 1.5",
            "ok": min(whole) <= 1.5,
            "baseline": numba_only,
            "ratio": min(whole) / numba_only,
            "note": f"best of {runs} new processes (200 iterations, W=6000, 100,000 evaluation episodes, files "
            f"written); baseline: a process that only imports numba",
        },
        {
            "measure": "training loop recorded in summary.json against its compute (s)",
            "value": loop,
            "unit": "s",
            "target": "<= 1.5x its compute",
            "ok": loop <= 1.5 * compute,
            "baseline": compute,
            "ratio": loop / compute,
            "note": "the same runs: summary.json wall_time (logging, checkpoints and progress included); baseline: "
            "the sum of metrics.parquet's per-iteration seconds (rollouts, gradients, consensus)",
        },
        {
            "measure": "start-up: riskplan train to its first iteration, warm JIT cache (s)",
            "value": train,
            "unit": "s",
            "target": "<= 1",
            "ok": train <= 1.0,
            "baseline": numba_only,
            "ratio": train / numba_only,
            "note": f"best of {runs} new processes, 3 iterations at W=6000; baseline: a process that only imports "
            f"numba",
        },
        {
            "measure": "start-up: riskplan --help (s)",
            "value": helps,
            "unit": "s",
            "target": "<= 0.3",
            "ok": helps <= 0.3,
            "baseline": typer_only,
            "ratio": helps / typer_only,
            "note": f"best of {runs + 2}; baseline: a process that only imports typer",
        },
    ]


TEAM_SAMPLES = 100_000  # total samples per iteration of the team benchmarks and the scaling study's robots (N * W_i)


def iteration_time(overrides: list[str], quick: bool) -> float:
    """Seconds of one training iteration (`training.iterate`: rollouts, gradients, consensus, step) of the set-up
    that overrides give, the best of several after a warm-up iteration."""
    setup = build_setup(compose(overrides))
    state = State(0, np.tile(setup.theta0, (setup.robots, 1)), setup.mixer.state(), [])
    state, _ = iterate(setup, state)  # warm

    def step():
        nonlocal state
        state, _ = iterate(setup, state)
        state.rows.clear()

    return best_time(step, 3, 3 if quick else 10)


def bench_measures(quick: bool) -> list[dict]:
    """The paper set-up's first iteration (W = 6000, θ0: the same episodes) under each other risk measure, against
    a CVaR iteration. The measures take turns, one iteration each, so the machine's drift reaches them alike; each
    keeps the median of its iterations."""
    measures = ("cvar", "wang", "mean_cvar", "entropic")
    setups = {m: build_setup(compose([f"risk={m}"])) for m in measures}
    firsts = {m: State(0, np.tile(setup.theta0, (1, 1)), setup.mixer.state(), []) for m, setup in setups.items()}
    seconds: dict[str, list[float]] = {m: [] for m in measures}
    for turn in range(60 if quick else 300):
        for measure in measures:
            started = time.perf_counter()
            iterate(setups[measure], firsts[measure])
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
            [f"team.robots={robots}", "team.graph=random_geometric", f"train.samples={TEAM_SAMPLES // robots}"], quick
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
            compose([f"team.robots={robots}", "team.graph=random_geometric", f"train.samples={samples}"])
        )
        state = State(0, np.tile(setup.theta0, (robots, 1)), setup.mixer.state(), [])
        tracemalloc.start()  # numpy reports its buffers to tracemalloc: exact peak bytes of one iteration
        iterate(setup, state)
        growth.append((robots * samples, tracemalloc.get_traced_memory()[1] / 2**20))
        tracemalloc.stop()
    n, mb = np.array(growth, dtype=float).T
    slope, intercept = np.polyfit(n, mb, 1)
    fit = 1 - np.sum((mb - (slope * n + intercept)) ** 2) / max(np.sum((mb - mb.mean()) ** 2), 1e-12)
    rows.append(
        {
            "measure": "team iteration memory",
            "value": slope * 2**20,
            "unit": "bytes per sample",
            "target": "linear in N*W_i",
            "ok": fit > 0.99,
            "baseline": float(mb.max()),
            "ratio": fit,
            "note": "peak allocation at N*W_i = "
            + ", ".join(f"{int(a)}: {b:.1f} MB" for a, b in growth)
            + "; baseline = largest MB, ratio = R^2 of a linear fit",
        }
    )
    return rows


# ---------------------------------------------------------------------------------------------------- scaling

PAPER_SOURCES = (
    "{name:safe,position:[9,3],covariance:[[16.0,0.0],[0.0,16.0]],scale:null,reward:1000.0}",
    "{name:risky,position:[3,9],covariance:[[16.0,0.0],[0.0,16.0]],scale:null,reward:{normal:[2000.0,2000.0]}}",
)


def source_overrides(count: int) -> list[str]:
    """A world with `count` (at most 141) sources: the paper's two, then constant-reward sources spread over the
    12 x 12 grid, one per cell (never the start), and theta0 (20, 20, 0, ...)."""
    items = list(PAPER_SOURCES[:count])
    cells = [((k * 67) % 144 % 12, (k * 67) % 144 // 12) for k in range(1, 144)]  # 67 is prime to 144: every cell
    cells = [c for c in cells if c not in ((0, 0), (9, 3), (3, 9))]  # not the start, not the paper's sources
    for j, (x, y) in zip(range(2, count), cells):
        items.append(f"{{name:s{j},position:[{x},{y}],covariance:[[16.0,0.0],[0.0,16.0]],scale:null,reward:500.0}}")
    theta0 = [20.0, 20.0, *[0.0] * (count - 2)][:count]
    return [f"world.sources=[{','.join(items)}]", f"train.theta0=[{','.join(f'{t:g}' for t in theta0)}]"]


def scaling_dimensions(quick: bool = False) -> dict[str, list[tuple[float, list[str]]]]:
    """What `riskplan bench --scaling` measures: dimension -> [(value, overrides)], each against the paper world.

    grid: only the size (and the safe region's rectangle, so it covers the grid) changes; start and sources stay,
    so episodes are the paper's and the extra cost is the per-iteration policy tables of every cell.
    horizon: world.stop_at_source=false at every horizon (20 included), so episodes last the horizon.
    sources: the paper's two, then constant-reward ones (source_overrides). mobile: both paper sources random
    walks (prob 0.5). robots: a random geometric graph, N * W_i = TEAM_SAMPLES.
    """
    del quick  # the same sizes; --quick only measures each fewer times
    return {
        "grid": [
            (float(s), [f"world.size=[{s},{s}]", f"world.regions.1.rect=[0,0,{s - 1},{s - 1}]"])
            for s in (12, 24, 48, 96, 128, 192, 256)
        ],
        "horizon": [(float(k), [f"world.horizon={k}", "world.stop_at_source=false"]) for k in (20, 50, 100, 200, 400)],
        "sources": [(float(m), source_overrides(m)) for m in (2, 4, 8, 16, 32, 64)],
        "mobile": [
            (0.0, []),
            (1.0, [f"world.sources.{j}.motion.{key}" for j in (0, 1) for key in ("kind=random_walk", "prob=0.5")]),
        ],
        "robots": [
            (
                float(n),
                ([] if n == 1 else [f"team.robots={n}", "team.graph=random_geometric"])
                + [f"train.samples={TEAM_SAMPLES // n}"],
            )
            for n in (1, 10, 100, 1000)
        ],
    }


def cache_bytes(level: int = 2) -> int:
    """Size of this CPU's level-`level` data cache per core (Linux sysfs), 1 MiB when unknown."""
    base = Path("/sys/devices/system/cpu/cpu0/cache")
    for index in sorted(base.glob("index*")) if base.is_dir() else []:
        try:
            if int((index / "level").read_text()) == level and (index / "type").read_text().strip() != "Instruction":
                text = (index / "size").read_text().strip().upper()
                scale = {"K": 2**10, "M": 2**20, "G": 2**30}.get(text[-1], 1)
                return int(text.rstrip("KMG")) * scale
        except (OSError, ValueError):
            continue
    return 2**20


class Point:
    """One world of the scaling benchmark, built once: its kernel call and its training iteration, ready to time."""

    def __init__(self, dimension: str, value: float, overrides: list[str]):
        self.dimension, self.value, self.overrides = dimension, value, list(overrides)
        setup = build_setup(compose(self.overrides))
        first = State(0, np.tile(setup.theta0, (setup.robots, 1)), setup.mixer.state(), [])
        episodes = samples_at(0, setup.params.train)
        keys = rng.robot_keys(setup.params.seed, rng.TRAIN, 0, setup.robots)
        cells = starts(setup)
        # the iteration's own batch: the kernel call (with its policy tables) that iterate() makes first
        self.kernel = lambda: simulate(setup.world, setup.kernel, first.thetas, cells, keys, episodes)
        self.iteration = lambda: iterate(setup, first)  # always from the first state: the same work every call
        self.steps = int(self.kernel().steps.sum())
        self.samples = setup.robots * episodes
        self.cells = setup.world.cells
        self.table_bytes = setup.robots * setup.world.cells * 5 * (1 + setup.world.sources) * 8
        self.best = {"kernel": float("inf"), "iteration": float("inf")}
        self.inner = {}
        for name in self.best:  # warm (a first call may compile or load), then size the rounds to ROUND_SECONDS
            fn = getattr(self, name)
            fn()
            start = time.perf_counter()
            fn()
            self.inner[name] = max(1, int(ROUND_SECONDS / max(time.perf_counter() - start, 1e-6)))
        tracemalloc.start()  # numpy reports its buffers to tracemalloc: the peak bytes of one iteration
        self.iteration()
        self.peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()

    def time_round(self) -> None:
        """One timed round of each measure; the best round is kept."""
        for name in self.best:
            self.best[name] = min(self.best[name], best_time(getattr(self, name), 1, self.inner[name]))

    def row(self) -> dict:
        return {
            "dimension": self.dimension,
            "value": self.value,
            "overrides": self.overrides,
            "steps_per_s": self.steps / self.best["iteration"],
            "kernel_steps_per_s": self.steps / self.best["kernel"],
            "bytes_per_sample": self.peak / self.samples,
            "iteration_seconds": self.best["iteration"],
            "steps": self.steps,
            "samples": self.samples,
            "cells": self.cells,
            "table_bytes": self.table_bytes,
        }


ROUND_SECONDS = 0.05  # each round times each world for about this long (several calls when it is fast)


def bench_scaling(
    quick: bool = False, dimensions: dict | None = None, baseline: list[str] | None = None, echo=None
) -> list[dict]:
    """Trajectory-steps/s and bytes per sample along each dimension, each row with its ratio to the paper world
    (row `baseline`, the first). Every world is built first; then each round times every world once, and each
    keeps its best round: on a shared machine all rows see the same minutes, not one quiet and one busy."""
    dimensions = scaling_dimensions(quick) if dimensions is None else dimensions
    points = [Point("baseline", 0.0, list(baseline or []))]
    points += [
        Point(dimension, value, overrides) for dimension, values in dimensions.items() for value, overrides in values
    ]
    for _ in range(4 if quick else 9):
        for point in points:
            point.time_round()
    rows = [point.row() for point in points]
    base = rows[0]
    for row in rows:
        row["rate_ratio"] = row["steps_per_s"] / base["steps_per_s"]
        row["kernel_ratio"] = row["kernel_steps_per_s"] / base["kernel_steps_per_s"]
        row["bytes_ratio"] = row["bytes_per_sample"] / base["bytes_per_sample"]
        if echo:
            echo(row)
    return rows


def scaling_slopes(rows: list[dict], cache: int | None = None) -> dict[str, dict]:
    """Per dimension: the log-log slopes of iteration and kernel steps/s against its value (grid: the number of
    cells), over all its rows and over those whose policy tables exceed the L2 cache; None where fewer than two
    distinct values qualify."""
    cache = cache_bytes() if cache is None else cache
    slopes = {}
    for dimension in dict.fromkeys(r["dimension"] for r in rows if r["dimension"] not in ("baseline", "mobile")):
        points = [r for r in rows if r["dimension"] == dimension and r["value"] > 0]
        x = (lambda r: r["cells"]) if dimension == "grid" else (lambda r: r["value"])
        beyond = [r for r in points if r["table_bytes"] > cache]

        def fit(subset, key, x=x):
            if len({x(r) for r in subset}) < 2:
                return None
            return float(np.polyfit(np.log([x(r) for r in subset]), np.log([r[key] for r in subset]), 1)[0])

        slopes[dimension] = {
            "all": fit(points, "steps_per_s"),
            "beyond_cache": fit(beyond, "steps_per_s"),
            "kernel_all": fit(points, "kernel_steps_per_s"),
            "kernel_beyond_cache": fit(beyond, "kernel_steps_per_s"),
            "cache_bytes": cache,
            "first_beyond": x(beyond[0]) if beyond else None,
        }
    return slopes


def scaling_table(rows: list[dict]) -> str:
    """The rows as a Markdown table (what the README shows)."""
    lines = [
        "| dimension | value | iteration steps/s | ratio | kernel steps/s | ratio | bytes per sample | ratio "
        "| policy tables |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        value = (
            "paper world"
            if r["dimension"] == "baseline"
            else ("mobile" if r["value"] else "static")
            if r["dimension"] == "mobile"
            else f"{int(r['value'])}²"
            if r["dimension"] == "grid"
            else f"{int(r['value'])}"
        )
        lines.append(
            f"| {r['dimension']} | {value} | {r['steps_per_s']:.3g} | {r['rate_ratio']:.2f} | "
            f"{r['kernel_steps_per_s']:.3g} | {r['kernel_ratio']:.2f} | "
            f"{r['bytes_per_sample']:.0f} | {r['bytes_ratio']:.2f} | {r['table_bytes'] / 2**20:.2f} MB |"
        )
    return "\n".join(lines)


def plot_scaling(rows: list[dict], path: Path, cache: int | None = None) -> Path:
    """Steps/s (top) and bytes per sample (bottom) against each dimension, log axes; the baseline dashed."""
    cache = cache_bytes() if cache is None else cache
    base = rows[0]
    dims = list(dict.fromkeys(r["dimension"] for r in rows if r["dimension"] != "baseline"))
    fig = Figure(figsize=(3.0 * len(dims), 5.2), constrained_layout=True)
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, len(dims), squeeze=False)
    for col, dimension in enumerate(dims):
        points = [r for r in rows if r["dimension"] == dimension]
        categorical = dimension == "mobile"
        xs = [r["value"] if not categorical else i for i, r in enumerate(points)]
        for row_index, (key, label) in enumerate(
            (("steps_per_s", "trajectory-steps/s"), ("bytes_per_sample", "bytes per sample"))
        ):
            ax = axes[row_index][col]
            ax.plot(
                xs,
                [r[key] for r in points],
                "o-",
                color="#0072B2",
                label="training iteration" if row_index == 0 else None,
            )
            if row_index == 0:
                ax.plot(
                    xs,
                    [r["kernel_steps_per_s"] for r in points],
                    "s--",
                    color="#009E73",
                    markersize=4,
                    label="kernel (with its tables)",
                )
            ax.axhline(base[key], color="#999999", linestyle=":", linewidth=1, label="paper world (iteration)")
            ax.set_yscale("log")
            values = (
                [r[key] for r in points]
                + [base[key]]
                + ([r["kernel_steps_per_s"] for r in points] if row_index == 0 else [])
            )
            low, high = min(values), max(values)
            if high < 10 * low:  # at least a decade shown, so log ticks stay readable
                middle = math.sqrt(low * high)
                low, high = middle / 3.2, middle * 3.2
            ax.set_ylim(low / 1.2, high * 1.2)
            if categorical:
                ax.set_xticks(xs, ["mobile" if r["value"] else "static" for r in points])
                ax.set_xlim(-0.5, len(points) - 0.5)
            else:
                ax.set_xscale("log")
                ax.set_xticks(xs, [f"{x:g}" for x in xs], rotation=45 if len(xs) > 6 else 0)
                ax.xaxis.set_minor_locator(NullLocator())
                beyond = [x for x, r in zip(xs, points) if r["table_bytes"] > cache]
                if beyond:
                    ax.axvspan(
                        min(beyond), max(xs) * 1.05, color="#E69F00", alpha=0.12, linewidth=0, label="tables > L2"
                    )
            ax.grid(True, which="both", alpha=0.3, linewidth=0.5)
            if row_index == 0:
                ax.set_title(
                    {
                        "grid": "grid side",
                        "horizon": "horizon K (no stop)",
                        "sources": "sources M",
                        "mobile": "source motion",
                        "robots": f"robots (N·W_i = {TEAM_SAMPLES:,})",
                    }.get(dimension, dimension),
                    fontsize=9,
                )
            if col == 0:
                ax.set_ylabel(label)
                ax.legend(fontsize=7, frameon=False)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, metadata={"Software": None})
    return path
