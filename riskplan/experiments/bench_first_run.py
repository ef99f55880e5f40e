"""`riskplan bench`'s first-run rows: the first `riskplan train` after an install, every numba kernel compiled into
an empty cache, against a process that compiles one rollout kernel (issue 26: within 1.5x of it)."""

from __future__ import annotations

import math
import sys
import tempfile
from pathlib import Path

from riskplan.experiments.bench_meters import wall

# the baseline of bench_first_run: a process that imports numba and compiles riskplan's training kernel alone
# (rollout_kernels._simulate_affine, the one episode kernel a paper run compiles), on the paper world's 12 x 12 arrays
TRAINING_KERNEL = """
import numpy as np
from riskplan.engine.distributions import pack_programs, parse
from riskplan.engine.rollout_kernels import KernelTables, _simulate_affine
side, episodes = 12, 100
cells = side * side
x, y = np.divmod(np.arange(cells), side)
moves = [(1, 0), (-1, 0), (0, 0), (0, 1), (0, -1)]
next_cell = np.stack([np.clip(x + dx, 0, side - 1) * side + np.clip(y + dy, 0, side - 1) for dx, dy in moves], 1)
cum = np.cumsum(np.full((1, cells, 5), 0.2), axis=2)
bins = np.minimum(cum[..., :4] * 2.0**53, 2.0**53).astype(np.int64)
affine = np.tile([0.0, 100.0, 0.0, -np.inf, np.inf], (cells, 1))
affine[y > x] = [0.0, 200.0, 100.0, -1e4, 1e4]
source_at = np.full(cells, -1)
source_at[9 * side + 3], source_at[3 * side + 9] = 0, 1
region, sources = pack_programs([parse(0.0)]), pack_programs([parse(1000.0), parse({"normal": [2000.0, 2000.0]})])
tables = KernelTables(
    next_cell=next_cell, region_of=(y > x).astype(np.int64), region_risky=np.ones(1, np.int64), reg_off=region[0],
    reg_ops=region[1], reg_par=region[2], src_off=sources[0], src_ops=sources[1], src_par=sources[2],
    source_at=source_at, source_cells=np.array([9 * side + 3, 3 * side + 9]), source_motion=np.zeros(2),
    source_amplitude=np.ones(2), source_precision=np.ones((2, 3)), cell_affine=affine,
    cell_risky=(y > x).astype(np.int64), extra_at=np.zeros(0, np.int64), extras=np.zeros((cells, 5, 0)), height=side,
    width=side, horizon=20, stop_at_source=True, mobile=False, affine=True, draw_uniform=True, draw_normal=True,
    tabular=False, signal_at=0,
)
out = (np.empty(episodes), np.empty((episodes, 2)), *(np.empty(episodes, np.int64) for _ in range(3)))
_simulate_affine(tables, bins, np.zeros((1, cells, 5, 2)), np.zeros(1, np.int64), np.array([7], np.uint64), episodes,
                 False, *out, np.zeros((0, 0), np.int64), np.zeros((0, 0)))
"""


def bench_first_run(quick: bool) -> list[dict]:
    """The first `riskplan train` after an install, the paper set-up and the paper team, each in a new process
    with an empty numba cache (every kernel compiled), against a process that imports numba and compiles
    riskplan's training kernel alone, also with an empty cache; best of a few rounds taken in turn. A plain
    kernel written for the paper world alone (riskplan/experiments/baselines/one_kernel.py) is the second reference."""
    script = Path(sys.executable).with_name("riskplan")
    cli = [str(script)] if script.is_file() else [sys.executable, "-m", "riskplan"]
    plain = str(Path(__file__).with_name("baselines") / "one_kernel.py")  # installed with the package
    commands = {
        "kernel": [sys.executable, "-c", TRAINING_KERNEL],
        "plain": [sys.executable, plain],
        "paper_single": [*cli, "train"],
        "paper_team": [*cli, "train", "experiment=paper_team"],
    }
    best = dict.fromkeys(commands, math.inf)
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(1 if quick else 2):
            for name, argv in commands.items():
                cache = Path(tmp) / f"cache_{name}_{k}"
                cache.mkdir()
                run_dir = [f"hydra.run.dir={Path(tmp) / f'{name}_{k}'}"] if name.startswith("paper") else []
                seconds = wall([*argv, *run_dir], Path(tmp), env={"NUMBA_CACHE_DIR": str(cache)})
                best[name] = min(best[name], seconds)
    kernel, plain_kernel = best["kernel"], best["plain"]
    return [
        {
            "measure": f"first riskplan train after an install, {name}, empty numba cache (s)",
            "value": best[name],
            "unit": "s",
            "target": "<= 1.5x one kernel",
            "ok": best[name] <= 1.5 * kernel,
            "baseline": kernel,
            "ratio": best[name] / kernel,
            "note": f"the whole command (200 iterations, 100,000 evaluation episodes, files written), best of "
            f"{1 if quick else 2} new processes, each with an empty NUMBA_CACHE_DIR; baseline: a process that "
            f"imports numba and compiles riskplan's training kernel alone; a plain kernel for the paper world "
            f"alone (experiments/baselines/one_kernel.py) takes {plain_kernel:.2f} s (ratio {best[name] / plain_kernel:.2f})",
        }
        for name in ("paper_single", "paper_team")
    ]
