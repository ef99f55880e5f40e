"""Where a reproduction's time goes: the estimate said before it starts, the stage and overall ETA while it runs,
and the breakdown of the wall time at its end (reproduce.json's `breakdown`).

The estimate of a stage is what it took the last time this machine reproduced the same plan (the same options and
overrides, so the same jobs), else riskplan.run.cost's model of this machine applied to its jobs: the model counts
trajectory steps, which weigh a team's bootstrap or a tabular policy's kernel alike, while a stage's own time says
it all. While the stages run, the remaining estimate is scaled by how the finished stages compared with theirs, so
the ETA follows the machine's load. Like the cost model's, the file of stage times is a hint: a missing,
unreadable or read-only one never stops a reproduction.
"""

from __future__ import annotations

import datetime as dt
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd
import typer

from riskplan.run import cost
from riskplan.run.columns import read_parquet
from riskplan.run.run_files import STATUS, SUMMARY, table_file
from riskplan.util.paths import write_atomic

REPORT_SECONDS = (3.0, 0.1)  # the report: a fixed part and a part per run (figures, tables, page)
PLANS_KEPT = 16  # reproduction plans whose stage times this machine keeps


@dataclass
class Stage:
    """One part of a reproduction: a sweep, the landscape or the report, with its estimated wall seconds."""

    name: str
    estimate: float
    jobs: int = 0


@dataclass
class Schedule:
    """The stages in order, and what the finished ones took: the ETA of the rest."""

    stages: list[Stage]
    taken: dict[str, float] = field(default_factory=dict)
    plan: str = ""  # what the stage times are remembered under (`plan_key`); "" remembers nothing
    measured: int = 0  # stages whose estimate is what they took last time

    @classmethod
    def remembered(cls, stages: list[Stage], plan: str) -> Schedule:
        """The stages, each estimated as it took the last time this machine ran `plan`, where it did."""
        past = _plans().get(plan, {})
        for stage in stages:
            if isinstance(past.get(stage.name), (int, float)) and past[stage.name] > 0:
                stage.estimate = float(past[stage.name])
        return cls(stages, plan=plan, measured=sum(stage.name in past for stage in stages))

    @property
    def total(self) -> float:
        return sum(stage.estimate for stage in self.stages)

    def remaining(self) -> float:
        """Seconds left: the unfinished stages' estimates, times how the finished ones compared with theirs."""
        done = [stage for stage in self.stages if stage.name in self.taken]
        expected = sum(stage.estimate for stage in done)
        scale = (sum(self.taken[stage.name] for stage in done) / expected) if expected > 0 else 1.0
        scale = min(max(scale, 0.1), 10.0)  # one odd stage (all its jobs skipped, a cold cache) says little
        return scale * sum(stage.estimate for stage in self.stages if stage.name not in self.taken)

    def header(self, name: str) -> str:
        """`stage k of n` and the overall ETA, printed as a stage starts."""
        index = next(i for i, stage in enumerate(self.stages) if stage.name == name)
        left = self.remaining()
        ends = (dt.datetime.now() + dt.timedelta(seconds=left)).strftime("%H:%M")
        return f"[stage {index + 1} of {len(self.stages)}: {name}] {cost.say(left)} left in all (ETA {ends})"

    def finished(self, name: str, seconds: float, whole: bool = True) -> None:
        """Stage `name` took `seconds`; `whole`: it did all its work (no job skipped or failed), so the next
        reproduction of this plan may expect as much."""
        self.taken[name] = seconds
        if self.plan and whole:
            _remember(self.plan, name, seconds)


def plan_key(**options) -> str:
    """What a reproduction's stage times are remembered under: its options, which decide its jobs."""
    return json.dumps(options, sort_keys=True)


def _plans() -> dict[str, dict[str, float]]:
    try:
        data = json.loads(cost.cache_file("stages").read_text())
    except (OSError, ValueError):
        return {}
    return {k: v for k, v in data.items() if isinstance(v, dict)} if isinstance(data, dict) else {}


def _remember(plan: str, name: str, seconds: float) -> None:
    """Keep what stage `name` of `plan` took (the latest PLANS_KEPT plans); a cache that cannot be written costs
    the next estimate, nothing else."""
    plans = _plans()
    stages = {**plans.pop(plan, {}), name: round(seconds, 2)}
    plans = {**dict(list(plans.items())[-(PLANS_KEPT - 1) :]), plan: stages}
    try:
        path = cost.cache_file("stages")
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, json.dumps(plans), durable=False)
    except OSError:
        pass


def plan_line(schedule: Schedule, workers: int | None) -> str:
    """The estimate said before anything runs (`workers`: parallel job processes, None for batches)."""
    jobs = sum(stage.jobs for stage in schedule.stages)
    how = (
        "each sweep one batch on every core" if workers is None else f"on {workers} worker{'s' if workers != 1 else ''}"
    )
    model = cost.model()
    basis = model.describe()
    if schedule.measured == len(schedule.stages):
        basis, model = "each stage as this machine's last reproduction of this plan took it", None
    elif schedule.measured:
        basis = f"{schedule.measured} stages as this machine's last reproduction of this plan took them, the rest by the cost model, {basis}"
    return (
        f"plan: {len(schedule.stages)} stages, {jobs} jobs, {how}; "
        f"estimated time {cost.say(schedule.total, model)} ({basis}; finished jobs are skipped)"
    )


def report_seconds(runs: int) -> float:
    fixed, per_run = REPORT_SECONDS
    return fixed + per_run * runs


def process_started() -> float | None:
    """When this process started (epoch seconds, Linux /proc; None elsewhere): the CLI's `since`."""
    return _started_of("self")


def _started_of(pid) -> float | None:
    """When process `pid` started (epoch seconds) from /proc/<pid>/stat and /proc/stat's btime; None if unknown."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        boot = next(
            float(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines() if line.startswith("btime ")
        )
        return boot + int(fields[19]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return None


def sweep_timing(outcome, tic: float, toc: float) -> dict:
    """Where a sweep's wall time went, from its jobs' status.json (started, finished, seconds, pid), their
    summary.json (wall_time: the training loop) and metrics.parquet (iteration 0's extra time in a worker's first
    job: the numba cache load). Only the jobs that ran in this launch count."""
    launched = toc - outcome.seconds  # _run_plan's start: planning (composing and validating every job) is before
    jobs = []
    for path in outcome.summary.get("path", pd.Series(dtype=object)).dropna():
        try:
            status = json.loads((Path(path) / STATUS).read_text())
            summary = json.loads((Path(path) / SUMMARY).read_text())
        except (OSError, ValueError):
            continue
        if (
            status.get("status") != "done"
            or not isinstance(status.get("started"), (int, float))
            or status["started"] < launched - 2
        ):
            continue
        jobs.append(
            {
                "path": str(path),
                "pid": status.get("pid"),
                "started": status["started"],
                "finished": status["finished"],
                "seconds": status["seconds"],
                "training": float(summary.get("wall_time") or 0.0),
            }
        )
    timing = {"planning": round(launched - tic, 3), "jobs": len(jobs)}
    if not jobs:
        return timing
    first, last = min(j["started"] for j in jobs), max(j["finished"] for j in jobs)
    timing.update(
        {
            "to_first_job": round(first - launched, 3),
            "running": round(last - first, 3),
            "after_last_job": round(toc - last, 3),
            "job_seconds": round(sum(j["seconds"] for j in jobs), 3),
            "training": round(sum(j["training"] for j in jobs), 3),
            "workers": {},
        }
    )
    for pid in dict.fromkeys(j["pid"] for j in jobs):
        own = sorted((j for j in jobs if j["pid"] == pid), key=lambda j: j["started"])
        load = None
        try:
            seconds = read_parquet(Path(own[0]["path"]) / table_file("metrics"), columns=["iteration", "seconds"])
            per = seconds.groupby("iteration").seconds.first()
            if len(per) > 1:
                load = max(0.0, float(per.iloc[0] - per.iloc[1:].median()))
        except (OSError, ValueError, KeyError, ImportError):
            pass
        spawned = _started_of(pid) if pid != os.getpid() else None  # a one-job sweep runs in this process
        timing["workers"][str(pid)] = {
            "jobs": len(own),
            "first_job": own[0]["started"],
            "spawned": spawned,
            "numba_load": load,
        }
    return timing


def time_breakdown(record: dict, clock: dict, started: float, folders: list[str]) -> dict:
    """Wall seconds of the command by part, and inside the sweeps' jobs (core-seconds, summed over the jobs);
    `folders`: the sweeps' parts of `record`."""
    sweeps = [record["parts"][folder] for folder in folders if folder in record["parts"]]
    timings = [part.get("timing", {}) for part in sweeps]
    begun = clock.get("since")
    ended = started + record["seconds"]
    wall = _wall_parts(record, clock, timings)
    known = sum(v for v in wall.values() if v is not None)
    total = ended - (begun or clock.get("entered", started))
    wall["other (lock, directories, record)"] = max(0.0, total - known)
    jobs = _job_parts(record.get("warm_up"), timings)
    return {
        "batched": bool(record.get("batched")),
        "total": round(total, 2),
        "wall": {k: None if v is None else round(v, 2) for k, v in wall.items()},
        "jobs": {k: round(v, 2) if isinstance(v, float) else v for k, v in jobs.items()},
    }


def _wall_parts(record: dict, clock: dict, timings: list[dict]) -> dict[str, float | None]:
    """The command's wall seconds by part (None: a part whose clock was not read)."""
    begun = clock.get("since")
    parts = record["parts"]
    waited = record.get("warm_up", {}).get("waited", 0.0)
    return {
        "start-up (interpreter, imports)": (clock["entered"] - begun) if begun and "entered" in clock else None,
        "checks (compose each set-up, budget)": (clock["checked"] - clock["entered"]) if "checked" in clock else None,
        "sweeps: planning (compose and validate every job)": sum(t.get("planning", 0.0) for t in timings),
        "sweeps: waiting for the warmed-up workers": waited,
        "sweeps: launch to first job (Hydra, worker start and imports)": sum(
            t.get("to_first_job", 0.0) for t in timings
        )
        - waited,
        "sweeps: jobs running (first start to last finish)": sum(t.get("running", 0.0) for t in timings),
        "sweeps: after the last job (summary, Hydra)": sum(t.get("after_last_job", 0.0) for t in timings),
        "landscape": parts.get("landscape", {}).get("seconds", 0.0),
        "comparison table": parts.get("comparison", {}).get("seconds", 0.0),
        "report (figures, tables, page)": parts.get("report", {}).get("seconds", 0.0),
    }


def _job_parts(warm: dict | None, timings: list[dict]) -> dict[str, float | int]:
    """Inside the jobs: their count, their workers', and their core-seconds by part, summed over the jobs."""
    workers: dict[str, dict] = {}
    for t in timings:
        for pid, w in t.get("workers", {}).items():
            entry = workers.setdefault(
                pid, {"jobs": 0, "spawned": w["spawned"], "first_job": w["first_job"], "numba_load": w["numba_load"]}
            )
            entry["jobs"] += w["jobs"]
    load = "numba cache load (iteration 0's extra, first job of each worker)"
    jobs = {
        "jobs": sum(t.get("jobs", 0) for t in timings),
        "workers": len(workers),
        **(
            {"worker warm-up (imports, numba cache; while the checks and planning ran)": sum(warm["seconds"])}
            if warm
            else {
                "worker start to its first job (imports, unpickling)": sum(
                    w["first_job"] - w["spawned"] for w in workers.values() if w["spawned"]
                )
            }
        ),
        load: sum(w["numba_load"] or 0.0 for w in workers.values()),
        "training loop (summary wall_time)": sum(t.get("training", 0.0) for t in timings),
        "set-up, evaluation episodes, bootstrap, files (job seconds - wall_time)": sum(
            t.get("job_seconds", 0.0) - t.get("training", 0.0) for t in timings
        ),
    }
    jobs["training loop (summary wall_time)"] -= jobs[load]
    return jobs


def print_breakdown(breakdown: dict) -> None:
    """Where the time went, as two short tables."""
    typer.echo(f"\nwhere the time went ({breakdown['total']:.1f} s from the command's start to its end):")
    for name, seconds in breakdown["wall"].items():
        typer.echo(f"  {'?' if seconds is None else f'{seconds:6.1f}'} s  {name}")
    jobs = breakdown["jobs"]
    if breakdown.get("batched"):  # a batch's jobs share their time: summing it per job says nothing
        typer.echo(f"{jobs['jobs']} jobs ran, each sweep as one batch")
        return
    typer.echo(
        f"inside the {jobs['jobs']} jobs that ran, on {jobs['workers']} worker processes (seconds summed over "
        f"jobs; they run in parallel):"
    )
    for name, seconds in jobs.items():
        if name not in ("jobs", "workers"):
            typer.echo(f"  {seconds:6.1f} s  {name}")
