"""`riskplan bench --reproduce`: `riskplan reproduce --quick` (Section V and the studies, 2 seeds, 50 runs) in a
process of its own, as its breakdown counts it, against the same reproduction job by job (`--jobs`, a worker per
core) in the same run, and whether both left the same numbers in every sweep's summary; then (not with --quick) the
whole `riskplan reproduce` (122 runs) against its floor, the time of the episode and bootstrap kernels its runs ran,
replayed (riskplan.experiments.bench_kernel_share)."""

from __future__ import annotations

import json
import subprocess
import tempfile
from pathlib import Path

import pandas as pd

from riskplan.experiments.bench_kernel_share import replay, replayed
from riskplan.experiments.bench_meters import riskplan_command, user_env
from riskplan.run.columns import read_parquet
from riskplan.util.limits import cpu_count

TARGET = 30.0  # seconds for reproduce --quick on 2 idle cores, the kernels cached
FULL_TARGET = 75.0  # seconds for the whole reproduce, the same way
COMPARED = ["job", "status", "mean", "cvar", "value_at_risk"]


def bench_reproduce(quick: bool = False) -> list[dict]:
    """The rows: reproduce --quick batched (the default) against job by job; unless `quick`, the whole reproduction
    against its kernels."""
    return [quick_row()] + ([] if quick else [full_row()])


def quick_row() -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        job_wall, job_numbers = reproduce(Path(tmp) / "jobs", ["--jobs", str(cpu_count())])
        batch_wall, batch_numbers = reproduce(Path(tmp) / "batched", [])
    same = job_numbers.keys() == batch_numbers.keys() and all(
        job_numbers[sweep].equals(batch_numbers[sweep]) for sweep in job_numbers
    )
    return {
        "measure": "riskplan reproduce --quick, 50 runs (s)",
        "value": batch_wall,
        "unit": "s",
        "target": f"<= {TARGET:g} s on 2 idle cores",
        "ok": batch_wall <= TARGET and same,
        "baseline": job_wall,
        "ratio": batch_wall / job_wall,
        "note": f"baseline: the same reproduction job by job (--jobs {cpu_count()}); each in a process of its own, "
        "from its start to its end as its time breakdown gives it (report included), the kernels cached; "
        + ("the same numbers in every sweep" if same else "THE NUMBERS DIFFER"),
    }


def full_row() -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "full"
        wall, numbers = reproduce(out, [], quick=False)
        runs = sum(len(table) for table in numbers.values())
        done = [
            out / sweep / job for sweep, table in numbers.items() for job in table["job"][table["status"] == "done"]
        ]
        floor = replay(done)
    kernels = floor.episodes + floor.bootstrap
    return {
        "measure": f"riskplan reproduce, {runs} runs (s)",
        "value": wall,
        "unit": "s",
        "target": f"<= {FULL_TARGET:g} s on 2 idle cores",
        "ok": wall <= FULL_TARGET and floor.faithful and len(done) == runs,
        "baseline": kernels,
        "ratio": wall / kernels,
        "note": f"baseline, its floor: {replayed(floor, len(done), runs, bootstrap=True)}, the landscape's not counted; "
        "value: from its start to its end as its time breakdown gives it (report included), the kernels cached",
    }


def reproduce(out: Path, extra: list[str], quick: bool = True) -> tuple[float, dict[str, pd.DataFrame]]:
    """`riskplan reproduce [--quick] --out OUT EXTRA` in a process of its own: what `read_reproduction` reads of
    it."""
    command = [*riskplan_command(), "reproduce", *(["--quick"] if quick else []), "--out", str(out), *extra]
    subprocess.run(command, cwd=out.parent, capture_output=True, check=True, env=user_env())
    return read_reproduction(out)


def read_reproduction(out: Path) -> tuple[float, dict[str, pd.DataFrame]]:
    """A reproduction's total seconds (reproduce.json's breakdown, from its process's start) and the numbers of
    each of its sweeps, by folder."""
    total = json.loads((out / "reproduce.json").read_text())["breakdown"]["total"]
    numbers = {
        summary.parent.name: read_parquet(summary)[COMPARED].reset_index(drop=True)
        for summary in sorted(out.glob("*/summary.parquet"))
    }
    return float(total), numbers
