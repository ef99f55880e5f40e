"""How long runs will take on this machine, said before they start: budget.estimate's cost of a run, in
trajectory-step equivalents, turned into seconds by a model calibrated on the runs that finished here.

Every run that finishes records (its estimated steps at the whole machine's rate, its wall seconds) in a small
file of this host's (RISKPLAN_CACHE_DIR, else $XDG_CACHE_HOME/riskplan or ~/.cache/riskplan). A run that had only
some of the cores (a sweep job with fewer numba threads) counts its steps divided by its share of the cores, so
sweeps and single runs calibrate one rate, while its overhead stays the wall seconds each sweep worker pays. The
model is seconds = overhead + steps / rate, fitted to the latest records by medians; before any run has finished
here it assumes DEFAULT_RATE and half a second of overhead, and says so, with its estimate as a range. A sweep
adds what no run's own seconds hold: its start and finish, and each job's set-up by Hydra. The file is a hint: a
missing, unreadable, read-only or corrupt one never stops a run.
"""

from __future__ import annotations

import json
import math
import os
import platform
import re
from dataclasses import dataclass
from pathlib import Path

from numba.core import event

from riskplan.run import budget
from riskplan.util.limits import duration
from riskplan.util.paths import write_atomic

CACHE_ENV = "RISKPLAN_CACHE_DIR"
VERSION = 3  # of how steps are counted (3: a job's share divides its steps, not its seconds): others left behind
KEEP = 64  # records kept: the latest runs say most about the machine as it is now
# A bootstrap resample-episode is an addition, not a trajectory step: 1000 resamples of 100,000 episodes take
# about what 8M steps do. The budget counts it as a step to bound the time limit from above.
BOOTSTRAP_WEIGHT = 0.08
# Before calibration: about half the rate, and the overhead rounded up, that full reproductions on a 2-core VM
# fitted (the time limit's limits.STEPS_PER_SECOND is far more cautious: it bounds, where this estimates)
DEFAULT_RATE = 80e6  # trajectory-step equivalents per second
DEFAULT_OVERHEAD = 0.5  # seconds a run takes beyond its steps (its log opened, evaluation set up, files written)
# What a sweep takes beyond its runs' own seconds (the calibration never sees it), measured on a 2-core VM: 12
# small jobs that each ran 1 s took 17 s, where these constants were missing and the estimate said under 10 s.
LAUNCH = 5.0  # a local sweep's start and finish: Hydra's multirun, each worker's Python, riskplan and cached
# kernels loaded (in parallel), the summary and the workers' shutdown
SWEEP_JOB = 0.7  # each job of a local sweep before its run starts: Hydra composes it again, writes .hydra/, logs
BATCH_LAUNCH = 1.0  # the same for a batched sweep, which starts no workers
# Before calibration the defaults may be this far off either way (the runs of a loaded 2-core VM took twice the
# default model's seconds), so an uncalibrated estimate is said as the range they span.
UNCALIBRATED = (0.7, 2.0)


@dataclass(frozen=True)
class Model:
    """seconds = overhead + steps / rate, for one run on the whole machine."""

    rate: float  # trajectory-step equivalents per second
    overhead: float  # seconds per run beyond its steps
    runs: int  # finished runs it was fitted to (0: the defaults)

    def run_seconds(self, steps: float) -> float:
        return self.overhead + steps / self.rate

    def sweep_seconds(self, steps: list[float], workers: int) -> float:
        """A sweep's wall seconds: its steps share the machine's cores whatever the workers, while each worker
        pays its own jobs' set-up by Hydra and their runs' overhead, one job after another."""
        if not steps:
            return 0.0
        return LAUNCH + sum(steps) / self.rate + len(steps) * (SWEEP_JOB + self.overhead) / max(workers, 1)

    def batch_seconds(self, steps: list[float], batches: int = 1) -> float:
        """A batched sweep's wall seconds: its steps on the whole machine, a run's overhead for each batch's set-up
        and for each job's own evaluation and files, which follow one another."""
        if not steps:
            return 0.0
        return BATCH_LAUNCH + sum(steps) / self.rate + (batches + len(steps)) * self.overhead

    def describe(self) -> str:
        if self.runs:
            return f"calibrated on {self.runs} run{'s' if self.runs != 1 else ''} finished on this machine"
        return (
            f"not yet calibrated on this machine: {DEFAULT_RATE / 1e6:.0f}M steps/s and {DEFAULT_OVERHEAD:g} s per "
            f"run assumed"
        )


def setup_steps(setup) -> float:
    """A built run's estimated cost in trajectory-step equivalents (riskplan.run.build.RunSetup)."""
    world = setup.world
    return config_steps(setup.params, world.width, world.height, world.sources, setup.robots)


def config_steps(params, width: int, height: int, sources: int, robots: int) -> float:
    """A typed config's estimated cost in trajectory-step equivalents, given its grid and team sizes: the budget's
    parts (riskplan.run.budget, an upper bound for the time limit) with the bootstrap at its real weight."""
    sizes = budget.sizes_of(params, width, height, sources, robots)
    return sum(
        amount * (BOOTSTRAP_WEIGHT if what.startswith("its bootstrap") else 1.0)
        for amount, what, _ in budget.estimate(sizes)[1]
    )


def run_bytes(setup) -> float:
    """The memory a built run needs (riskplan.run.budget's estimate): what a batch of runs adds up."""
    world = setup.world
    sizes = budget.sizes_of(setup.params, world.width, world.height, world.sources, setup.robots)
    return sum(amount for amount, _, _ in budget.estimate(sizes)[0])


def cache_file(kind: str = "cost") -> Path:
    """This host's calibration file (`kind`: another file of timings kept beside it, such as a reproduction's
    stages)."""
    root = os.environ.get(CACHE_ENV, "").strip()
    if not root:
        base = os.environ.get("XDG_CACHE_HOME", "").strip() or str(Path.home() / ".cache")
        root = str(Path(base) / "riskplan")
    host = re.sub(r"[^A-Za-z0-9._-]", "_", platform.node() or "host")[:64]
    return Path(root) / f"{kind}-v{VERSION}-{host}-{os.cpu_count() or 1}cpu.json"


def _records() -> list[tuple[float, float]]:
    try:
        data = json.loads(cache_file().read_text())
    except (OSError, ValueError):
        return []
    records = data.get("runs", []) if isinstance(data, dict) else []
    return [
        (float(r[0]), float(r[1]))
        for r in records
        if isinstance(r, list)
        and len(r) == 2
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0 for v in r)
    ][-KEEP:]


class CompileCounter(event.Listener):
    """Counts numba's compilations in this process (a kernel loaded from the disk cache is not one)."""

    def __init__(self) -> None:
        self.count = 0

    def on_start(self, event) -> None:
        self.count += 1

    def on_end(self, event) -> None:
        pass


_COMPILES = CompileCounter()
event.register("numba:compile", _COMPILES)


def compiles() -> int:
    """numba's compilations in this process so far: a run during which this grew spent its time mostly compiling
    (the first run after an install, or in a new checkout), and says little about the machine's speed."""
    return _COMPILES.count


def record(steps: float, seconds: float, share: float = 1.0) -> None:
    """Add a finished run: its estimated steps, its wall seconds, and the share of the cores it had. Its steps
    count as those the whole machine would have done in its time; its seconds, overhead included, stay as they
    were (scaling them by the share instead made a sweep job's overhead look half as long on 2 cores)."""
    share = min(share, 1.0)
    if not (share > 0 and math.isfinite(steps) and math.isfinite(seconds) and steps > 0 and seconds > 0):
        return
    runs = [*_records(), (steps / share, seconds)][-KEEP:]
    try:
        path = cache_file()
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, json.dumps({"runs": [list(r) for r in runs]}), durable=False)  # a cache: not synced
    except OSError:
        pass  # a read-only or full cache costs the next estimate its calibration, nothing else


def model() -> Model:
    """The model fitted to this machine's records: a Theil-Sen line of seconds on steps (the median of the
    slopes between records of different sizes, then the median overhead) when the runs' sizes differ enough to tell
    overhead from rate, else the default overhead and the median rate of the runs long enough to say it (over twice
    that overhead: a tiny run's seconds are its overhead, such as a sweep worker's warm-up). Medians, not least
    squares: one run slowed by a busy minute pulled a least-squares line far enough to say minutes for a run of
    seconds, while the median moves only when most of the records do."""
    runs = _records()
    if not runs:
        return Model(DEFAULT_RATE, DEFAULT_OVERHEAD, 0)
    steps = [s for s, _ in runs]
    if len(runs) >= 3 and max(steps) > 1.5 * min(steps):
        fitted = _theil_sen(runs)
        if fitted is not None:
            return Model(*fitted, len(runs))
    rates = sorted(s / (t - DEFAULT_OVERHEAD) for s, t in runs if t > 2 * DEFAULT_OVERHEAD)
    if not rates:
        return Model(DEFAULT_RATE, DEFAULT_OVERHEAD, 0)
    return Model(_median(rates), DEFAULT_OVERHEAD, len(rates))


def _theil_sen(runs: list[tuple[float, float]]) -> tuple[float, float] | None:
    """(rate, overhead) of the Theil-Sen line through (steps, seconds), over the pairs whose steps differ by more
    than a tenth (closer sizes give a slope that is mostly noise); through the origin where its overhead would be
    negative; None where seconds do not grow with steps."""
    slopes = [
        (t2 - t1) / (s2 - s1)
        for i, (s1, t1) in enumerate(runs)
        for s2, t2 in runs[i + 1 :]
        if abs(s2 - s1) > 0.1 * max(s1, s2)
    ]
    if not slopes:
        return None
    slope = _median(slopes)
    if slope <= 0:
        return None
    overhead = _median([t - slope * s for s, t in runs])
    if overhead < 0:  # runs of different kinds, whose line would give a small run no time: the median rate instead
        return _median([s / t for s, t in runs]), 0.0
    return 1.0 / slope, overhead


def _median(values: list[float]) -> float:
    ordered, half = sorted(values), len(values) // 2
    return ordered[half] if len(ordered) % 2 else (ordered[half - 1] + ordered[half]) / 2


def say(seconds: float, model: Model | None = None) -> str:
    """An estimate, rounded as an estimate should be; one of a model not yet calibrated (`model.runs` 0) as the
    range its defaults may be off by."""
    if model is not None and not model.runs:
        low, high = (seconds * factor for factor in UNCALIBRATED)
        return f"roughly {duration(low)} to {duration(high)}"
    return "under 10 s" if seconds < 10 else f"about {duration(seconds)}"
