"""`riskplan bench`: the speed and memory targets, each printed with its baseline measured in the same run."""

from __future__ import annotations

import os
import random
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from riskplan.distributions import Dist


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
    from riskplan import rng
    from riskplan.config import compose
    from riskplan.rollout import simulate
    from riskplan.setup import build_setup

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
        {"measure": "rollout, W=6000, theta0 (trajectory-steps/s)", "value": kernel_rate, "unit": "steps/s",
         "target": ">= 5e7", "ok": kernel_rate >= 5e7, "baseline": python_rate,
         "ratio": kernel_rate / python_rate, "note": f"{seconds * 1e3:.2f} ms per batch; baseline: plain Python "
                                                     f"loop, {episodes} trajectories (ratio target > 1000x)"},
    ]


def bench_training(quick: bool) -> list[dict]:
    """200 iterations at W = 6000 with logging and checkpoints, evaluation excluded; memory over import."""
    from riskplan.config import compose
    from riskplan.training import train

    import_rss = rss_mb()
    cfg = compose(["train.eval_episodes=1000", "train.bootstrap=10", "train.paths=2"]
                  + (["train.iterations=50"] if quick else []))
    reset_peak()
    with tempfile.TemporaryDirectory() as tmp:
        run = train(cfg, Path(tmp) / "run")
    peak = rss_mb("VmHWM")
    iterations = cfg.train.iterations
    wall = run.summary["wall_time"]
    per_iteration = run.metrics.seconds.sum() / iterations
    return [
        {"measure": f"training, {iterations} iterations at W=6000 (s)", "value": wall, "unit": "s",
         "target": "< 2 (200 iterations)", "ok": wall < 2.0 * iterations / 200, "baseline": per_iteration * iterations,
         "ratio": wall / (per_iteration * iterations),
         "note": "baseline: the iterations' own compute; ratio = overhead of logging, checkpoints, JIT load"},
        {"measure": "memory growth over the post-import baseline (MB)", "value": peak - import_rss, "unit": "MB",
         "target": "< 100", "ok": peak - import_rss < 100, "baseline": import_rss, "ratio": peak / import_rss,
         "note": f"peak RSS {peak:.0f} MB during training vs {import_rss:.0f} MB after import"},
    ]


def bench_checkpoints(quick: bool) -> list[dict]:
    """Many cheap iterations with a checkpoint every 10 against one checkpoint at the end: O(1) per checkpoint."""
    from riskplan.config import compose
    from riskplan.training import train

    iterations = 1000 if quick else 4000
    base = ["train.samples=20", f"train.iterations={iterations}", "train.eval_episodes=100", "train.bootstrap=5",
            "train.paths=1"]
    walls = {}
    with tempfile.TemporaryDirectory() as tmp:
        train(compose([*base, "train.iterations=5"]), Path(tmp) / "warm-up")  # kernels loaded before timing
        for every in (iterations, 10):
            run = train(compose([*base, f"train.checkpoint_every={every}"]), Path(tmp) / f"every_{every}")
            walls[every] = run.summary["wall_time"]
        size = (Path(tmp) / "every_10" / "checkpoint").stat().st_size
    ratio = walls[10] / walls[iterations]
    return [{"measure": f"training, {iterations} iterations at W=20, a checkpoint every 10 (s)", "value": walls[10],
             "unit": "s", "target": "< 2x one checkpoint at the end", "ok": ratio < 2.0, "baseline": walls[iterations],
             "ratio": ratio, "note": f"baseline: one checkpoint at the end; each checkpoint is {size} bytes "
                                     f"(the state, not the rows so far), fsynced with the log"}]


def bench_jit() -> list[dict]:
    """First-call time with an empty numba cache (compile) vs a warm on-disk cache, in fresh processes."""
    code = ("import time; t = time.perf_counter(); import riskplan.bench as b; "
            "b.bench_rollout_once(); print(time.perf_counter() - t)")
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        cold, warm = (float(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                                           check=True).stdout.split()[-1]) for _ in range(2))
    return [{"measure": "first rollout in a new process, warm JIT cache (s)", "value": warm, "unit": "s",
             "target": "small next to a run", "ok": warm < 2.0, "baseline": cold, "ratio": warm / cold,
             "note": f"baseline: empty cache, compiles the kernels ({cold:.1f} s, once per install)"}]


def bench_rollout_once() -> None:
    """One small rollout (used by bench_jit in a child process)."""
    from riskplan import rng
    from riskplan.config import compose
    from riskplan.rollout import simulate
    from riskplan.setup import build_setup

    setup = build_setup(compose([]))
    simulate(setup.world, setup.kernel, setup.theta0[None, :], setup.world.starts, rng.robot_keys(0, 1, 0, 1), 100)


def bench_team(quick: bool) -> list[dict]:
    """100 robots on a random geometric graph, W_i = 1000, vs one robot with the same total samples."""
    from riskplan.config import compose
    from riskplan.setup import build_setup
    from riskplan.training import State, iterate

    def iteration_time(overrides: list[str]) -> float:
        setup = build_setup(compose(overrides))
        state = State(0, np.tile(setup.theta0, (setup.robots, 1)), setup.mixer.state(), [])
        state, _ = iterate(setup, state)  # warm

        def step():
            nonlocal state
            state, _ = iterate(setup, state)
            state.rows.clear()

        return best_time(step, 3, 3 if quick else 10)

    team = iteration_time(["team.robots=100", "team.graph=random_geometric", "train.samples=1000"])
    central = iteration_time(["train.samples=100000"])
    rows = [{"measure": "team iteration, 100 robots RGG, W_i=1000 (s)", "value": team, "unit": "s",
             "target": "<= 1.5x centralized", "ok": team <= 1.5 * central, "baseline": central,
             "ratio": team / central, "note": "baseline: one robot, W=100000 (same total samples)"}]
    sizes = [(25, 1000), (50, 1000), (100, 1000), (100, 2000), (200, 2000)]
    growth = []
    for robots, samples in sizes[:3] if quick else sizes:
        setup = build_setup(compose([f"team.robots={robots}", "team.graph=random_geometric",
                                     f"train.samples={samples}"]))
        state = State(0, np.tile(setup.theta0, (robots, 1)), setup.mixer.state(), [])
        tracemalloc.start()  # numpy reports its buffers to tracemalloc: exact peak bytes of one iteration
        iterate(setup, state)
        growth.append((robots * samples, tracemalloc.get_traced_memory()[1] / 2**20))
        tracemalloc.stop()
    n, mb = np.array(growth, dtype=float).T
    slope, intercept = np.polyfit(n, mb, 1)
    fit = 1 - np.sum((mb - (slope * n + intercept)) ** 2) / max(np.sum((mb - mb.mean()) ** 2), 1e-12)
    rows.append({"measure": "team iteration memory", "value": slope * 2**20, "unit": "bytes per sample",
                 "target": "linear in N*W_i", "ok": fit > 0.99, "baseline": float(mb.max()), "ratio": fit,
                 "note": "peak allocation at N*W_i = " + ", ".join(f"{int(a)}: {b:.1f} MB" for a, b in growth)
                         + "; baseline = largest MB, ratio = R^2 of a linear fit"})
    return rows
