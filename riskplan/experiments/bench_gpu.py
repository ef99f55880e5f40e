"""`riskplan bench`'s GPU rows (engine.device=cuda), measured only where a GPU is present: the rollout kernel on
1,024 runs x 6,000 episodes of the paper world, against the CPU kernel on the same inputs in the same run, and how
many of the GPU's episodes are the CPU's bit for bit. Without numba-cuda or a GPU, `bench_gpu` raises Skipped with
the reason, which the command prints in place of the rows.
"""

from __future__ import annotations

import time

import numpy as np

from riskplan.config.keys import KEYS
from riskplan.engine import rng
from riskplan.engine.rollout import simulate
from riskplan.run.build import build_setup
from riskplan.run.compose import compose
from riskplan.util.checks import installed

RUNS, EPISODES = 1024, 6000  # the sweep: 1,024 runs (one robot each) x W = 6,000 of the paper world
TARGET = 50e9  # steps/s of the rollout kernel on an H100


class Skipped(Exception):
    """The GPU rows cannot be measured here; str() says why."""


def gpu_or_skip(simulator_ok: bool = False):
    """riskplan.engine.cuda_rollout, once numba-cuda and a GPU are known to be there; else Skipped(why).
    `simulator_ok`: numba-cuda's simulator will do (the tests run this module's code on it, at a tiny size)."""
    if not installed("numba_cuda"):
        raise Skipped("numba-cuda is not installed (pip install 'riskplan[cuda]')")
    from riskplan.engine import cuda_rollout  # optional: numba-cuda, imported only to measure the GPU

    if cuda_rollout.SIMULATOR and not simulator_ok:
        raise Skipped("numba-cuda's simulator is on (NUMBA_ENABLE_CUDASIM=1): nothing runs on a GPU")
    problem = cuda_rollout.gpu_problem()
    if problem is not None:
        raise Skipped(problem)
    return cuda_rollout


def bench_gpu(quick: bool, runs: int = RUNS, episodes: int = EPISODES, simulator_ok: bool = False) -> list[dict]:
    """The GPU rollout kernel (inputs on the device, kernel alone), the whole GPU call (tables, copies both ways)
    and the CPU kernel, on the same `runs` x `episodes` of the paper world; and how many episodes agree."""
    cuda_rollout = gpu_or_skip(simulator_ok)
    from numba import cuda  # optional: numba-cuda, as above

    setup = build_setup(compose([f"{KEYS.engine.device}=cuda"]))
    thetas = np.random.default_rng(0).normal(20.0, 6.0, size=(runs, setup.theta0.size))  # a sweep's spread
    keys = rng.robot_keys(0, rng.TRAIN, 0, runs)
    cells = np.repeat(setup.world.starts[:1], runs)
    args = (setup.world, setup.kernel, thetas, cells, keys, episodes)
    repeats = 3 if quick else 10

    launch = cuda_rollout.Launch(*args).run()  # compiles the kernel (numba-cuda, once per process)
    gpu = launch.batch()
    kernel_s = _best(lambda: (launch.run(), cuda.synchronize()), repeats)
    call_s = _best(lambda: cuda_rollout.simulate(*args), max(2, repeats // 3))
    simulate(setup.world, setup.kernel, thetas[:1], cells[:1], keys[:1], 1)  # the CPU kernel, from numba's cache
    cpu, cpu_s = None, float("inf")
    for _ in range(1 if quick else 2):
        start = time.perf_counter()
        cpu = simulate(*args)
        cpu_s = min(cpu_s, time.perf_counter() - start)
    device = getattr(cuda.get_current_device(), "name", "numba-cuda's simulator")
    device = device.decode() if isinstance(device, bytes) else str(device)
    shape = f"{runs:,} runs x {episodes:,} episodes of the paper world"
    return _rows(shape, device, float(cpu.steps.sum()), kernel_s, call_s, cpu_s, gpu, cpu)


def _rows(shape: str, device: str, steps: float, kernel_s: float, call_s: float, cpu_s: float, gpu, cpu) -> list[dict]:
    """bench's three GPU rows: the kernel's and the whole call's steps/s against the CPU kernel's, and how many of
    the GPU's episodes (`gpu`, an EpisodeBatch) are the CPU's (`cpu`) bit for bit."""
    same = np.ones(len(cpu.total_reward), dtype=bool)
    for field in ("total_reward", "score", "risky_steps", "source_reached", "steps"):
        same &= np.all(_bits(getattr(gpu, field), len(same)) == _bits(getattr(cpu, field), len(same)), axis=1)
    differ = np.abs(gpu.total_reward - cpu.total_reward)
    return [
        {
            "measure": f"GPU rollout kernel, {shape} (steps/s)",
            "value": steps / kernel_s,
            "unit": "steps/s",
            "target": f">= {TARGET:.0e} (an H100)",
            "ok": steps / kernel_s >= TARGET,
            "baseline": steps / cpu_s,
            "ratio": cpu_s / kernel_s,
            "note": f"{kernel_s * 1e3:.2f} ms per launch on {device}, inputs on the device; baseline: the CPU "
            f"kernel on the same episodes, {cpu_s * 1e3:.1f} ms",
        },
        {
            "measure": f"GPU simulate call, {shape}, tables and copies included (steps/s)",
            "value": steps / call_s,
            "unit": "steps/s",
            "target": "> the CPU kernel",
            "ok": call_s < cpu_s,
            "baseline": steps / cpu_s,
            "ratio": cpu_s / call_s,
            "note": f"{call_s * 1e3:.1f} ms per call: the policy tables on the CPU, inputs to the device, the "
            f"outputs (z, scores, risky steps, sources, steps) back",
        },
        {
            "measure": "GPU episodes equal to the CPU's, bit for bit (fraction)",
            "value": float(same.mean()),
            "unit": "",
            "target": "= 1",
            "ok": bool(same.all()),
            "baseline": float(len(same)),
            "ratio": float(same.mean()),
            "note": f"{int((~same).sum())} of {len(same):,} episodes differ, |z| by at most {differ.max():.3g} "
            f"(CUDA's exp and log in the ziggurat's tail and wedges, docs/sweeps.md)",
        },
    ]


def _bits(values: np.ndarray, rows: int) -> np.ndarray:
    """An output's rows as integers: floats by their bits (so equal means bit for bit)."""
    return (values.view(np.uint64) if values.dtype == np.float64 else values).reshape(rows, -1)


def _best(fn, repeats: int) -> float:
    """Best seconds of one call over `repeats` calls."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best
