"""`riskplan bench`'s new-process rows: the first rollout with an empty and with a warm numba cache, `riskplan train`
from the command to its end and to its first iteration, and `riskplan --help`, each against a bare process."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import NamedTuple

from riskplan.engine import rng
from riskplan.engine.rollout import simulate
from riskplan.experiments.bench_meters import wall
from riskplan.run.build import build_setup
from riskplan.run.columns import read_parquet
from riskplan.run.compose import compose


def bench_jit() -> list[dict]:
    """First-call time with an empty numba cache (compile) vs a warm on-disk cache, in fresh processes."""
    code = (
        "import time; t = time.perf_counter(); import riskplan.experiments.bench_startup as b; "
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
            "target": "< 2 s, small next to a run",
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
sys.argv = ["riskplan", "train", "train.iterations=3", "train.eval_episodes=1000", "train.bootstrap=40",
            "train.paths=1"]
import runpy
runpy.run_module("riskplan", run_name="__main__")  # python -m riskplan train ...
"""


def bench_startup(quick: bool) -> list[dict]:
    """`riskplan train` from the command to its first iteration (warm JIT cache), and `riskplan --help`, in new
    processes (best of several); baselines: a process that only imports numba, and one that only imports typer."""
    script = Path(sys.executable).with_name("riskplan")
    cli = [str(script)] if script.is_file() else [sys.executable, "-m", "riskplan"]
    runs = 2 if quick else 3
    whole, loop, compute, train, numba_only, helps, typer_only = _best_walls(cli, runs)
    return [
        {
            "measure": "riskplan train, the paper set-up, the whole command, warm JIT cache (s)",
            "value": whole,
            "unit": "s",
            "target": "<= 1.5",
            "ok": whole <= 1.5,
            "baseline": numba_only,
            "ratio": whole / numba_only,
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


class _Walls(NamedTuple):
    """Best seconds of what bench_startup times, each in new processes."""

    whole: float  # riskplan train, the whole command
    loop: float  # its training loop, as summary.json records it (of the run whose loop was quickest)
    compute: float  # that run's iterations' compute (metrics.parquet's seconds)
    train: float  # riskplan train to its first iteration
    numba_only: float  # a process that only imports numba
    helps: float  # riskplan --help
    typer_only: float  # a process that only imports typer


def _best_walls(cli: list[str], runs: int) -> _Walls:
    """The _Walls of `cli` (the riskplan command), best of `runs` (`--help` and typer: of runs + 2)."""
    with tempfile.TemporaryDirectory() as tmp:
        whole, loops = [], []
        for k in range(runs + 1):  # the first run writes the bytecode caches; it is not timed
            seconds = wall([*cli, "train", f"hydra.run.dir={Path(tmp) / f'whole{k}'}"], Path(tmp))
            summary = json.loads((Path(tmp) / f"whole{k}" / "summary.json").read_text())
            compute = float(read_parquet(Path(tmp) / f"whole{k}" / "metrics.parquet").seconds.sum())
            if k:
                whole.append(seconds)
                loops.append((summary["wall_time"], compute))
        loop, compute = min(loops)
        return _Walls(
            min(whole),
            loop,
            compute,
            min(wall([sys.executable, "-c", FIRST_ITERATION], Path(tmp), "FIRST-ITERATION") for _ in range(runs)),
            min(wall([sys.executable, "-c", "import numba"], Path(tmp)) for _ in range(runs)),
            min(wall([*cli, "--help"], Path(tmp)) for _ in range(runs + 2)),
            min(wall([sys.executable, "-c", "import typer"], Path(tmp)) for _ in range(runs + 2)),
        )
