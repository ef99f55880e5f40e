"""`riskplan bench --sweep`: a beta x seed sweep of the paper world run batched (`riskplan sweep --batch`) against
the same sweep unbatched (joblib, a worker per core), in the same bench run, and the check that both left the same
numbers."""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

from riskplan.util.limits import cpu_count

BETAS = "risk.beta=0.05,0.1,0.2,0.3"
FULL = [BETAS, "seed=range(0,16)", "train.iterations=200", "train.samples=6000", "train.eval_episodes=10000"]
QUICK = [BETAS, "seed=range(0,4)", "train.iterations=50", "train.samples=6000", "train.eval_episodes=10000"]
TARGET = 4.0  # batched at least this many times quicker on 2 cores (issue "A sweep is one program")
COMPARED = ["job", "status", "mean", "cvar", "value_at_risk"]


def bench_sweep(quick: bool) -> list[dict]:
    """The sweep unbatched, then batched, each a `riskplan sweep` of its own (so each pays its own start-up, as a
    user's would) into a temporary folder: their wall times and whether they left the same numbers."""
    args = QUICK if quick else FULL
    with tempfile.TemporaryDirectory() as tmp:
        walls, summaries = {}, {}
        for name, batch in (("unbatched", []), ("batched", ["--batch"])):
            command = [*riskplan_command(), "sweep", *args, f"hydra.sweep.dir={Path(tmp) / name}", *batch]
            tic = time.perf_counter()
            subprocess.run(command, cwd=tmp, capture_output=True, check=True)
            walls[name] = time.perf_counter() - tic
            summary = pd.read_parquet(Path(tmp) / name / "summary.parquet")
            summaries[name] = summary[COMPARED].reset_index(drop=True)
        same = summaries["batched"].equals(summaries["unbatched"])
    runs = len(summaries["batched"])
    ratio = walls["unbatched"] / walls["batched"]
    return [
        {
            "measure": f"a {runs}-run beta x seed sweep, batched (s)",
            "value": walls["batched"],
            "unit": "s",
            "target": f">= {TARGET:g}x quicker than unbatched",
            "ok": ratio >= TARGET and same,
            "baseline": walls["unbatched"],
            "ratio": ratio,
            "note": (
                f"baseline: the same sweep unbatched, joblib with {cpu_count()} workers; "
                f"{' '.join(args)}; every run's mean, CVaR and VaR "
                + ("identical" if same else "DIFFERENT")
                + f"; {runs / walls['batched']:.2f} runs/s batched against {runs / walls['unbatched']:.2f}"
            ),
        }
    ]


def riskplan_command() -> list[str]:
    """The console script beside this interpreter, or the module."""
    script = Path(sys.executable).with_name("riskplan")
    return [str(script)] if script.is_file() else [sys.executable, "-m", "riskplan"]
