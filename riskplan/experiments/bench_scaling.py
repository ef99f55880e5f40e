"""`riskplan bench --scaling`: trajectory-steps/s and bytes per sample along grid size, horizon, sources, source
motion and robots, each against the paper world in the same run; the slopes, the table and the plot."""

from __future__ import annotations

import math
import time
import tracemalloc
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import NullLocator

from riskplan.config.keys import KEYS
from riskplan.engine import rng
from riskplan.engine.rollout import simulate
from riskplan.engine.schedules import samples_at
from riskplan.engine.step import initial_state, starts, step
from riskplan.experiments.bench_meters import best_time
from riskplan.experiments.bench_training import ITERATIONS_ONLY, TEAM_SAMPLES
from riskplan.run.build import build_setup
from riskplan.run.compose import compose

PAPER_SOURCES = (
    "{name:safe,position:[9,3],covariance:[[16.0,0.0],[0.0,16.0]],scale:null,reward:1000.0}",
    "{name:risky,position:[3,9],covariance:[[16.0,0.0],[0.0,16.0]],scale:null,reward:{normal:[2000.0,2000.0]}}",
)


def source_overrides(count: int) -> list[str]:
    """A world with `count` (at most 138) sources: the paper's two, then constant-reward sources spread over the
    12 x 12 grid, one per cell within the horizon's 20 moves of the start (never the start), and theta0 (20, 20, 0,
    ...)."""
    items = list(PAPER_SOURCES[:count])
    cells = [((k * 67) % 144 % 12, (k * 67) % 144 // 12) for k in range(1, 144)]  # 67 is prime to 144: every cell
    # not the start, not the paper's sources, none beyond the horizon (a source no episode reaches is bad input)
    cells = [c for c in cells if c not in ((0, 0), (9, 3), (3, 9)) and c[0] + c[1] <= 20]
    for j, (x, y) in zip(range(2, count), cells):
        items.append(f"{{name:s{j},position:[{x},{y}],covariance:[[16.0,0.0],[0.0,16.0]],scale:null,reward:500.0}}")
    theta0 = [20.0, 20.0, *[0.0] * (count - 2)][:count]
    return [f"{KEYS.world.sources}=[{','.join(items)}]", f"{KEYS.train.theta0}=[{','.join(f'{t:g}' for t in theta0)}]"]


def scaling_dimensions(quick: bool = False) -> dict[str, list[tuple[float, list[str]]]]:
    """What `riskplan bench --scaling` measures: dimension -> [(value, overrides)], each against the paper world.

    grid: only the size (and the safe region's rectangle, so it covers the grid) changes; start and sources stay,
    so episodes are the paper's and the extra cost is the per-iteration policy tables of every cell.
    horizon: world.stop_at_source=false at every horizon (20 included), so episodes last the horizon.
    sources: the paper's two, then constant-reward ones (source_overrides). mobile: both paper sources random
    walks (prob 0.5). robots: a random geometric graph, N * W_i = TEAM_SAMPLES.
    """
    del quick  # the same sizes; --quick only measures each fewer times
    world, team = KEYS.world, KEYS.team
    motions = [world.sources.at(j).motion for j in (0, 1)]
    return {
        "grid": [
            (float(s), [f"{world.size}=[{s},{s}]", f"{world.regions.at(1).rect}=[0,0,{s - 1},{s - 1}]"])
            for s in (12, 24, 48, 96, 128, 192, 256)
        ],
        "horizon": [
            (float(k), [f"{world.horizon}={k}", f"{world.stop_at_source}=false"]) for k in (20, 50, 100, 200, 400)
        ],
        "sources": [(float(m), source_overrides(m)) for m in (2, 4, 8, 16, 32, 64)],
        "mobile": [
            (0.0, []),
            (1.0, [o for m in motions for o in (f"{m.kind}=random_walk", f"{m.prob}=0.5")]),
        ],
        "robots": [
            (
                float(n),
                ([] if n == 1 else [f"{team.robots}={n}", f"{team.graph}=random_geometric"])
                + [f"{KEYS.train.samples}={TEAM_SAMPLES // n}"],
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
        setup = build_setup(compose([*self.overrides, ITERATIONS_ONLY]))  # kernel calls and iterations only
        first = initial_state(setup)
        episodes = samples_at(0, setup.params.train)
        keys = rng.robot_keys(setup.params.seed, rng.TRAIN, 0, setup.robots)
        cells = starts(setup)
        # the iteration's own batch: the kernel call (with its policy tables) that step() makes first
        self.kernel = lambda: simulate(setup.world, setup.kernel, first.thetas, cells, keys, episodes)
        self.iteration = lambda: step(setup, first)  # always from the first state: the same work every call
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


PANELS = (("steps_per_s", "trajectory-steps/s"), ("bytes_per_sample", "bytes per sample"))  # (row key, y label)
TITLES = {
    "grid": "grid side",
    "horizon": "horizon K (no stop)",
    "sources": "sources M",
    "mobile": "source motion",
    "robots": f"robots (N·W_i = {TEAM_SAMPLES:,})",
}


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
        for row_index, (key, label) in enumerate(PANELS):
            ax = axes[row_index][col]
            _draw_panel(ax, points, dimension == "mobile", key, row_index == 0, base[key], cache)
            if row_index == 0:
                ax.set_title(TITLES.get(dimension, dimension), fontsize=9)
            if col == 0:
                ax.set_ylabel(label)
                ax.legend(fontsize=7, frameon=False)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, metadata={"Software": None})
    return path


def _draw_panel(ax, points: list[dict], categorical: bool, key: str, top: bool, base: float, cache: int) -> None:
    """One dimension's `key` (top: steps/s, with the kernel's too) against its values, the paper world's dotted."""
    xs = [r["value"] if not categorical else i for i, r in enumerate(points)]
    ax.plot(xs, [r[key] for r in points], "o-", color="#0072B2", label="training iteration" if top else None)
    if top:
        ax.plot(
            xs,
            [r["kernel_steps_per_s"] for r in points],
            "s--",
            color="#009E73",
            markersize=4,
            label="kernel (with its tables)",
        )
    ax.axhline(base, color="#999999", linestyle=":", linewidth=1, label="paper world (iteration)")
    ax.set_yscale("log")
    values = [r[key] for r in points] + [base] + ([r["kernel_steps_per_s"] for r in points] if top else [])
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
            ax.axvspan(min(beyond), max(xs) * 1.05, color="#E69F00", alpha=0.12, linewidth=0, label="tables > L2")
    ax.grid(True, which="both", alpha=0.3, linewidth=0.5)
