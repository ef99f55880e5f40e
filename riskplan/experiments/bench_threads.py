"""`riskplan bench --threads`: the rollout kernel and the whole training iteration with numba's thread count at 1, 2,
4, ... up to the cores, at W = 6000 and W = 600,000, each against 1 thread in the same run (issue 26: a large run's
statistics and gradient on every core, so the iteration scales nearly as well as its rollouts)."""

from __future__ import annotations

import math

import numba

from riskplan.engine import rng
from riskplan.engine.estimators import cvar_gradient, summary_stats
from riskplan.engine.reductions import PARALLEL_SAMPLES
from riskplan.engine.rollout import simulate
from riskplan.engine.schedules import samples_at
from riskplan.engine.step import initial_state, starts, step
from riskplan.experiments.bench_meters import best_time
from riskplan.run.build import build_setup
from riskplan.run.compose import compose

SAMPLES = (6000, 600_000)  # W: the paper's, and a large run's
ROUND_SECONDS = 0.05  # each round times each measure for about this long (one call when a call takes longer)
EFFICIENCY = 0.8  # target: the iteration's speed-up at least this share of the kernel's at the same thread count


def thread_counts(cores: int | None = None) -> list[int]:
    """1, 2, 4, ... below the cores numba may use, and the cores themselves."""
    cores = numba.config.NUMBA_NUM_THREADS if cores is None else cores
    counts = [1]
    while counts[-1] * 2 < cores:
        counts.append(counts[-1] * 2)
    return counts + [cores] if cores > 1 else counts


class Sample:
    """The paper set-up at W samples, built once: its kernel call and its training iteration, ready to time."""

    def __init__(self, samples: int, overrides: list[str] | None = None):
        setup = build_setup(compose([f"train.samples={samples}", *(overrides or [])]))
        first = initial_state(setup)
        episodes = samples_at(0, setup.params.train)
        keys = rng.robot_keys(setup.params.seed, rng.TRAIN, 0, setup.robots)
        cells = starts(setup)
        self.samples = samples
        self.kernel = lambda: simulate(setup.world, setup.kernel, first.thetas, cells, keys, episodes)
        self.iteration = lambda: step(setup, first)  # always from the first state: the same work every call
        batch = self.kernel()
        self.steps = int(batch.steps.sum())
        z, scores = batch.total_reward.reshape(setup.robots, -1), batch.score.reshape(setup.robots, episodes, -1)
        beta = setup.params.risk.beta

        def statistics(parallel: bool):  # the CVaR step's statistics and gradient (eqs. 5-6, 9)
            stats = summary_stats(z, beta, parallel=parallel)
            return cvar_gradient(z, scores, beta, var=stats["value_at_risk"], parallel=parallel)

        self.statistics = lambda: statistics(True)  # the kernels of riskplan.engine.reductions from W >= 32768
        self.numpy = lambda: statistics(False)  # numpy's serial functions: the same numbers
        self.iteration()  # compiles or loads what a large sample's statistics use
        self.best: dict[tuple[str, int], float] = {}
        self.inner: dict[str, int] = {}

    def time_round(self, threads: int) -> None:
        """One timed round of each measure at `threads` threads (numpy's statistics at 1 thread alone: numba's
        thread count is nothing to them); the best round is kept."""
        numba.set_num_threads(threads)
        for name in ("kernel", "iteration", "statistics", "numpy")[: 4 if threads == 1 else 3]:
            fn = getattr(self, name)
            if name not in self.inner:  # sized once, at 1 thread: as many calls as take about ROUND_SECONDS
                self.inner[name] = max(1, int(ROUND_SECONDS / max(best_time(fn, 1, 1), 1e-6)))
            seconds = best_time(fn, 1, self.inner[name])
            self.best[name, threads] = min(self.best.get((name, threads), math.inf), seconds)


def bench_threads(quick: bool, samples: tuple[int, ...] = SAMPLES, counts: list[int] | None = None) -> list[dict]:
    """Trajectory-steps/s of the kernel and of the iteration at each thread count above 1, against 1 thread; the
    thread counts take turns within each round, so a busy machine's minutes reach them alike."""
    counts = thread_counts() if counts is None else counts
    before = numba.get_num_threads()
    rows = []
    try:
        for w in samples:
            numba.set_num_threads(1)
            sample = Sample(w)
            for _ in range(rounds(w, quick)):
                for threads in counts:
                    sample.time_round(threads)
            rows += scaling_rows(sample, counts)
    finally:
        numba.set_num_threads(before)
    return rows


def rounds(samples: int, quick: bool) -> int:
    """Rounds of every thread count: fewer at W = 600,000, where a call does a hundred times the work of one at
    W = 6000."""
    if quick:
        return 3
    return 5 if samples > 100_000 else 9


def scaling_rows(sample: Sample, counts: list[int]) -> list[dict]:
    """The rows of one sample size: the kernel's and the iteration's speed-up at each thread count above 1, and
    from PARALLEL_SAMPLES on, the statistics and gradient at each thread count against numpy's serial ones."""
    rate = {key: sample.steps / seconds for key, seconds in sample.best.items()}
    rows = []
    if sample.samples >= PARALLEL_SAMPLES:
        numpy = sample.best["numpy", 1]
        for threads in counts:
            seconds = sample.best["statistics", threads]
            rows.append(
                {
                    "measure": f"statistics and CVaR gradient, W={sample.samples:,}, {threads} "
                    f"thread{'s' if threads > 1 else ''} (s)",
                    "value": seconds,
                    "unit": "s",
                    "target": "< numpy's serial statistics",
                    "ok": seconds < numpy,
                    "baseline": numpy,
                    "ratio": seconds / numpy,
                    "note": "summary_stats and cvar_gradient of the kernel's episodes (riskplan.engine.reductions); "
                    "baseline: numpy's partition, sums and einsum (the same numbers) in this run",
                }
            )
    for threads in counts[1:]:
        kernel = rate["kernel", threads] / rate["kernel", 1]
        for name in ("kernel", "iteration"):
            speedup = rate[name, threads] / rate[name, 1]
            rows.append(
                {
                    "measure": f"{name}, W={sample.samples:,}, {threads} threads (trajectory-steps/s)",
                    "value": rate[name, threads],
                    "unit": "steps/s",
                    "target": "faster than 1 thread"
                    if name == "kernel"
                    else f">= {EFFICIENCY:g}x the kernel's speed-up ({kernel:.2f}x)",
                    "ok": speedup > 1.0 if name == "kernel" else speedup >= EFFICIENCY * kernel,
                    "baseline": rate[name, 1],
                    "ratio": speedup,
                    "note": f"baseline: the same {name} at 1 thread in this run (numba.set_num_threads); "
                    f"{sample.best[name, threads] * 1e3:.2f} ms per call, {sample.steps:,} steps",
                }
            )
    return rows
