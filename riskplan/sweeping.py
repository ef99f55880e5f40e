"""`riskplan sweep`: a Hydra multirun over a grid of overrides, through a Hydra launcher plugin.

What riskplan adds around Hydra's own multirun (which does the expanding, the launching and the job folders):
- before anything runs: the overrides are parsed and every combination is composed against the schema (a
  malformed override, an unknown key or a badly typed value is bad input, exit 2) and checked by the model; a
  combination the model rejects fails alone when it runs, unless every combination is rejected (exit 2);
- a sweep may hold at most RISKPLAN_MAX_JOBS combinations (default 10,000), counted before they are expanded;
  two combinations that compose to the same config are bad input;
- a fresh sweep directory per command (`outputs/sweeps/<timestamp>[_n]`, claimed with mkdir, so two sweeps
  started in the same second never share one), or `hydra.sweep.dir=DIR` to resume a sweep; the driver holds the
  sweep directory's lock for the whole launch, so two drivers never run in one directory;
- job folders named by what varies, with anything that is not [A-Za-z0-9._=,+-] percent-encoded
  (`riskplan.sweepjob.folder_name`), so they are always direct children of the sweep directory;
- jobs that already finished with the same config are skipped (`riskplan.sweepjob`), killed ones resume; local
  workers die with the driver;
- one live view of the sweep on the terminal, while Hydra's messages go to `sweep.log` and each job's output
  to its own `job.log`;
- `summary.parquet`: one row per job, with the overrides as columns, the final figures with their 95%
  intervals, the wall time, the status and the error.

An optimising sweeper (hydra/sweeper=optuna) chooses the jobs as it goes (`plan_optimiser`): its search space is
checked with sample values instead of every combination, each trial runs as a sweep job in a numbered folder and
returns its CVaR (None when it failed, which optuna records as a failed trial), and summary.parquet has one row
per trial.
"""

from __future__ import annotations

import copy
import datetime as dt
import json
import os
import sys
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import typer

from riskplan.errors import BadInput
from riskplan.paths import atomic_path, check_output_dir, claim_dir, hydra_quote

SWEEPS_ROOT = Path("outputs") / "sweeps"
SUMMARY = "summary.parquet"
DEFAULT_LAUNCHER = "joblib"
FIGURES = ("mean", "cvar", "value_at_risk")
EXTRA_CVARS = ("cvar_0.05", "cvar_0.1", "cvar_0.2")
SWEEP_HELP = ("Hydra overrides; comma lists and range(...) sweep, e.g. risk.beta=0.05,0.1,0.2 'seed=range(0,5)' "
              "team.graph=line,ring. hydra/launcher=submitit_slurm|submitit_local|ray selects a cluster launcher "
              "(default: joblib on local cores); hydra.sweep.dir=DIR re-runs a sweep into DIR, skipping the jobs "
              "that finished. hydra/sweeper=optuna 'risk.beta=interval(0.05,1)' hydra.sweeper.n_trials=12 runs "
              "an Optuna study instead of a grid (pip install 'riskplan[optuna]'); its trials return their CVaR.")


@dataclass
class Job:
    """One combination of the sweep."""

    overrides: list[str]  # as Hydra passes them to the job (and writes them to .hydra/overrides.yaml)
    sha: str  # riskplan.sweepjob.config_sha of its composed config
    invalid: str | None = None  # why the model rejects it (the job will fail with this error)
    path: Path | None = None  # its folder, once known
    label: str = ""  # the overrides that vary between jobs: its name until its folder exists
    folder: str | None = None  # the folder name Hydra will give it (None when the user set hydra.sweep.subdir)
    trial: int = -1  # under an optimising sweeper: its trial number (hydra.job.num)

    @property
    def key(self) -> tuple[str, ...]:
        return tuple(sorted(self.overrides))

    @property
    def name(self) -> str:
        return self.path.name if self.path is not None else (self.label or ",".join(self.overrides))


@dataclass
class Plan:
    """A validated sweep, ready to launch."""

    sweep_dir: Path
    argv: list[str]  # Hydra's command line (after the program name)
    jobs: list[Job]
    launcher: str
    workers: int | None
    warnings: list[str] = field(default_factory=list)
    workers_arg: int | None = None  # index in argv of the hydra.launcher.n_jobs=... riskplan added
    sweeper: str = "basic"  # another one (optuna) chooses the jobs as it goes: `jobs` is empty until they ran
    trials: int | None = None  # how many jobs such a sweeper runs, when known
    search: list[str] = field(default_factory=list)  # the keys it searches


@dataclass
class Outcome:
    """What a sweep left: its directory, the summary table and the jobs that did not finish."""

    sweep_dir: Path
    summary: "object"  # pandas.DataFrame
    failed: list[tuple[str, str]]  # (job folder name, error)
    ran: int
    skipped: int
    seconds: float
    launcher_error: str | None = None
    command: list[str] = field(default_factory=list)  # the `riskplan sweep` arguments that resume this sweep
    best: str | None = None  # an optimising sweeper's best trial, as it reports it
    optimiser: bool = False

    @property
    def ok(self) -> bool:
        return not self.failed and self.launcher_error is None


# ----------------------------------------------------------------------------------------------------- planning


def plan_sweep(args: list[str], jobs: int | None = None, sweep_dir: Path | None = None) -> Plan:
    """Parse, expand and validate a sweep; claim its directory last, so bad input leaves nothing behind."""
    from riskplan.config import expand_shorthands, parse_overrides

    for arg in args:
        if arg.startswith("-"):
            raise BadInput(f"option '{arg}'", "is not known to riskplan sweep; give Hydra overrides (key=value) "
                                              "and --jobs N")
    args = expand_shorthands(args)  # risk.schedule=none,linear -> risk.schedule.kind=none,linear
    parsed = parse_overrides(args)
    hydra_ovs = [o for o in parsed if o.is_hydra_override()]
    task_ovs = [o for o in parsed if not o.is_hydra_override()]
    for o in hydra_ovs:
        if o.is_sweep_override():
            raise BadInput(f"override '{o.input_line}'", "sweeps over Hydra's own settings are not supported; "
                                                         "sweep over riskplan keys, e.g. risk.beta=0.1,0.2")
    hydra_keys = {o.key_or_group: o for o in hydra_ovs}
    launcher = str(hydra_keys["hydra/launcher"].value()) if "hydra/launcher" in hydra_keys else DEFAULT_LAUNCHER
    explicit_dir = None
    if "hydra.sweep.dir" in hydra_keys:
        raw = hydra_keys["hydra.sweep.dir"].value()
        value = "" if raw is None else str(raw)
        if "${" in value:
            raise BadInput("hydra.sweep.dir", f"got '{value}'; give a plain path (without it, riskplan sweep uses "
                                              f"outputs/sweeps/<timestamp>)")
        if sweep_dir is None:
            check_output_dir(value, "hydra.sweep.dir")
        explicit_dir = Path(value)
    if sweep_dir is not None and explicit_dir is not None:
        raise BadInput("hydra.sweep.dir", "is chosen by this command; do not give it")
    sweeper = str(hydra_keys["hydra/sweeper"].value()) if "hydra/sweeper" in hydra_keys else "basic"
    if sweeper != "basic":  # an optimiser: it chooses the jobs as it goes
        return plan_optimiser(args, task_ovs, hydra_ovs, launcher, sweeper, jobs, sweep_dir, explicit_dir)
    for o in task_ovs:
        if o.is_interval_sweep():
            raise BadInput(f"override '{o.input_line}'", "interval(...) is a search space for an optimising "
                                                         "sweeper (hydra/sweeper=optuna); a grid takes comma "
                                                         "lists, range(...), choice(...) or glob(...)")

    check_size(task_ovs)
    if "hydra.sweep.subdir" in hydra_keys:
        check_subdir(hydra_keys["hydra.sweep.subdir"].value(), len(task_ovs) > 0)
    combos = expand(task_ovs, args)
    job_list, notes = validate(combos)
    check_duplicates(job_list, task_ovs)
    if all(job.invalid for job in job_list):
        first = job_list[0].invalid
        raise BadInput(*_split_bad(first, len(job_list)))

    argv = ["-m", *args]
    workers = None
    workers_arg = None
    if launcher == "joblib":
        workers = min(jobs or cpu_count(), len(job_list))  # more workers than jobs would idle
        if "hydra.launcher.n_jobs" not in hydra_keys:
            workers_arg = len(argv)
            argv.append(f"hydra.launcher.n_jobs={workers}")
    elif jobs is not None:
        if launcher == "submitit_slurm":
            workers = min(jobs, len(job_list))
            argv.append(f"hydra.launcher.array_parallelism={workers}")
        else:
            raise BadInput("--jobs", f"applies to the joblib and submitit_slurm launchers, not to "
                                     f"hydra/launcher={launcher}")
    if "hydra/launcher" not in hydra_keys:
        argv.append(f"hydra/launcher={DEFAULT_LAUNCHER}")
    if not task_ovs and "hydra.sweep.subdir" not in hydra_keys:
        argv.append("hydra.sweep.subdir=defaults")  # one job without overrides: still a folder of its own
    elif "hydra.sweep.subdir" not in hydra_keys:
        # folder names that stay one path component, whatever the values hold ('/', '..', '%', NUL)
        from riskplan.sweepjob import SUBDIR

        argv.append(f"hydra.sweep.subdir={hydra_quote(SUBDIR)}")
        argv.append("+hydra.callbacks.riskplan_folders._target_=riskplan.sweepjob.FolderNames")
    constant = constant_keys(combos, {o.key_or_group for o in task_ovs if o.is_sweep_override()})
    for job in job_list:
        job.label = ",".join(sorted(o for o in job.overrides if o.split("=", 1)[0].lstrip("+~") not in constant))
    add_naming_and_logging(argv, hydra_keys, constant)

    naming = check_hydra(argv[1 + len(args):] + [o.input_line for o in hydra_ovs], combos[0])
    if task_ovs and "hydra.sweep.subdir" not in hydra_keys:
        name_folders(job_list, naming, task_ovs)

    target = _target_dir(sweep_dir, explicit_dir, argv)
    return Plan(target, argv, job_list, launcher, workers, notes, workers_arg)


def _target_dir(sweep_dir: Path | None, explicit_dir: Path | None, argv: list[str]) -> Path:
    """The sweep directory, made or claimed now that the input is known to be good."""
    if sweep_dir is not None:
        target = Path(sweep_dir)
        target.mkdir(parents=True, exist_ok=True)
    elif explicit_dir is not None:
        target = explicit_dir
        target.mkdir(parents=True, exist_ok=True)
    else:
        target = claim_dir(SWEEPS_ROOT)
    if explicit_dir is None:  # absolute: jobs on other machines (submitit, ray) may start in another directory
        argv.append(f"hydra.sweep.dir={hydra_quote(target.resolve())}")
    return target


OPTIMISER_FORMS = "choice(...), comma lists, range(...) or interval(...)"


def plan_optimiser(args: list[str], task_ovs: list, hydra_ovs: list, launcher: str, sweeper: str,
                   jobs: int | None, sweep_dir: Path | None, explicit_dir: Path | None) -> Plan:
    """A sweep whose sweeper chooses the jobs as it goes (hydra/sweeper=optuna): the combinations are not known
    before it runs, so the search space is checked instead. Every swept key is composed with a sample value of the
    type the sweeper will draw (every value of a choice), which makes an unknown key or a badly typed value bad
    input; a sample the model rejects is a warning (its trials fail alone), unless every sample is rejected for a
    key that is not searched (bad input). The trials run as jobs of the grid do (sweepjob), in folders numbered by
    trial; each returns its CVaR to the sweeper, or None when it failed (optuna records that trial as failed)."""
    from riskplan.sweepjob import TRIAL_SUBDIR

    hydra_keys = {o.key_or_group: o for o in hydra_ovs}
    search = [o for o in task_ovs if o.is_sweep_override()]
    fixed = [o for o in task_ovs if not o.is_sweep_override()]
    samples = {o.key_or_group: search_samples(o, sweeper) for o in search}
    base = [o.input_line for o in fixed] + [f"{o.get_key_element()}={samples[o.key_or_group][0]}" for o in search]
    combos = [base]
    for i, o in enumerate(search):
        for value in samples[o.key_or_group][1:]:
            combo = list(base)
            combo[len(fixed) + i] = f"{o.get_key_element()}={value}"
            combos.append(combo)
    try:
        sample_jobs, notes = validate(combos)
    except BadInput as err:  # name the search-space override whose sample does not compose
        for o in search:
            if err.where in (f"key '{o.key_or_group}'", o.key_or_group) and not o.is_choice_sweep():
                raise BadInput(err.where, f"{err.problem} (from override '{o.input_line}', composed with the "
                                          f"sample value {samples[o.key_or_group][0]})") from None
        raise
    searched = {o.key_or_group for o in search}
    rejected = [job.invalid for job in sample_jobs if job.invalid]
    if rejected and len(rejected) == len(sample_jobs) and rejected[0].partition(": ")[0] not in searched:
        where, _, problem = rejected[0].partition(": ")
        raise BadInput(where, f"{problem} (in every trial; nothing was run)")
    for job, error in zip(sample_jobs, (j.invalid for j in sample_jobs)):
        if error:
            tried = ",".join(job.overrides[len(fixed):])
            notes.append(f"{error} (with the sample {tried}); trials there will fail alone")

    argv = ["-m", *args]
    if sweeper == "optuna":
        if "hydra.sweeper.direction" not in hydra_keys:
            argv.append("hydra.sweeper.direction=maximize")  # the trials return their CVaR: higher is better
        if jobs is not None and "hydra.sweeper.n_jobs" not in hydra_keys:
            argv.append(f"hydra.sweeper.n_jobs={jobs}")  # trials per batch: as many as run at once
    if "hydra/launcher" not in hydra_keys:
        argv.append(f"hydra/launcher={DEFAULT_LAUNCHER}")
    if "hydra.sweep.subdir" in hydra_keys:
        check_subdir(hydra_keys["hydra.sweep.subdir"].value(), True)
    else:  # trial_007,risk.beta=0.31: numbered, so two trials that drew the same values never share a folder
        argv.append(f"hydra.sweep.subdir={hydra_quote(TRIAL_SUBDIR)}")
        argv.append("+hydra.callbacks.riskplan_folders._target_=riskplan.sweepjob.FolderNames")
    constant = [o.key_or_group for o in fixed] if search else []
    add_naming_and_logging(argv, hydra_keys, constant)
    _, settings = check_hydra(argv[1 + len(args):] + [o.input_line for o in hydra_ovs], base, sweeper=True)
    trials, batch = check_optimiser(sweeper, settings, search)

    workers = None
    workers_arg = None
    if launcher == "joblib":
        workers = min(jobs or cpu_count(), *(n for n in (batch, trials) if n))
        if "hydra.launcher.n_jobs" not in hydra_keys:
            workers_arg = len(argv)
            argv.append(f"hydra.launcher.n_jobs={workers}")
    elif jobs is not None:
        if launcher == "submitit_slurm":
            workers = min(jobs, *(n for n in (batch, trials) if n))
            argv.append(f"hydra.launcher.array_parallelism={workers}")
        else:
            raise BadInput("--jobs", f"applies to the joblib and submitit_slurm launchers, not to "
                                     f"hydra/launcher={launcher}")
    target = _target_dir(sweep_dir, explicit_dir, argv)
    return Plan(target, argv, [], launcher, workers, notes, workers_arg, sweeper=sweeper, trials=trials,
                search=sorted(searched))


def search_samples(override, sweeper: str) -> list[str]:
    """Values to compose a search-space override with, of the types the sweeper will draw: every value of a
    choice, the start of a range (and its next value), the middle of an interval (an int for an int interval)."""
    import math

    from hydra.core.override_parser.types import ChoiceSweep, IntervalSweep, RangeSweep

    value = override.value()
    line = f"override '{override.input_line}'"
    if isinstance(value, ChoiceSweep):
        return list(override.sweep_string_iterator())
    if isinstance(value, RangeSweep):
        bounds = (value.start, value.stop, value.step)
        if any(not isinstance(v, (int, float)) or not math.isfinite(v) for v in bounds) or not value.step:
            raise BadInput(line, "has a range bound or step that is not a finite number, or a step of 0; give "
                                 "finite numbers, e.g. range(0,5) or range(0,1,0.25)")
        if (value.stop - value.start) / value.step < 0:
            raise BadInput(line, "is an empty range; give a start below the stop, e.g. range(0,5)")
        first = value.start if all(isinstance(v, int) for v in bounds) else float(value.start)
        return [repr(first)]
    if isinstance(value, IntervalSweep):
        start, end = value.start, value.end
        if any(not isinstance(v, (int, float)) or not math.isfinite(v) for v in (start, end)):
            raise BadInput(line, "has a bound that is not a finite number; give finite numbers, e.g. "
                                 "interval(0.05,1)")
        if not start < end:
            raise BadInput(line, f"has its lower bound {start} not below its upper bound {end}; give "
                                 f"interval(low,high) with low < high")
        log = "log" in value.tags
        if log and start <= 0:
            raise BadInput(line, f"is a log interval from {start}; a log interval needs a lower bound above 0")
        if isinstance(start, int) and isinstance(end, int):
            return [repr(int(round(math.sqrt(start * end))) if log else (start + end) // 2)]
        return [repr(math.sqrt(start * end) if log else (start + end) / 2)]
    raise BadInput(line, f"the {sweeper} sweeper takes {OPTIMISER_FORMS}, not glob(...)")


def check_optimiser(sweeper: str, settings: dict, search: list) -> tuple[int | None, int | None]:
    """The optuna sweeper's settings that would fail only once it runs; returns (trials, trials per batch)."""
    from riskplan.limits import check_jobs

    if sweeper != "optuna":
        return None, None
    trials, batch = settings.get("n_trials"), settings.get("n_jobs")
    for key, value in (("hydra.sweeper.n_trials", trials), ("hydra.sweeper.n_jobs", batch)):
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise BadInput(key, f"got {value!r}; expected a whole number >= 1")
    check_jobs("hydra.sweeper.n_trials", trials)
    direction = settings.get("direction")
    if isinstance(direction, (list, tuple)):
        raise BadInput("hydra.sweeper.direction", f"got {list(direction)}: several objectives; riskplan's trials "
                                                  f"return one (the CVaR), so give maximize or minimize")
    if str(direction) not in ("maximize", "minimize"):
        raise BadInput("hydra.sweeper.direction", f"got {direction!r}; expected maximize or minimize")
    if settings.get("custom_search_space") is not None:
        raise BadInput("hydra.sweeper.custom_search_space", f"got {settings['custom_search_space']!r}: it names a "
                                                            f"function to run, and config strings are never code; "
                                                            f"give the search space as overrides, e.g. "
                                                            f"'risk.beta=interval(0.05,1)'")
    rate = settings.get("max_failure_rate")
    if not isinstance(rate, (int, float)) or isinstance(rate, bool) or not 0 <= rate <= 1:
        raise BadInput("hydra.sweeper.max_failure_rate", f"got {rate!r}; expected a number from 0 to 1")
    sampler = str((settings.get("sampler") or {}).get("_target_", ""))
    for o in search:
        if sampler.endswith("GridSampler") and o.is_interval_sweep():
            raise BadInput(f"override '{o.input_line}'", "the grid sampler takes choice(...), comma lists or "
                                                         "range(...), not interval(...)")
    return trials, batch


def sweep_size(task_ovs: list) -> tuple[int, object]:
    """How many combinations the overrides make, from their parsed values (a range is never listed), and the
    swept override with the most values."""
    import math

    from hydra.core.override_parser.types import ChoiceSweep, RangeSweep

    parser = _parser()
    total, biggest, most = 1, None, 0
    for override in task_ovs:
        if not override.is_sweep_override():
            continue
        value = override.value()
        if isinstance(value, RangeSweep):
            if any(isinstance(v, float) and not math.isfinite(v) for v in (value.start, value.stop, value.step)):
                raise BadInput(f"override '{override.input_line}'", "has a range bound or step that is not a finite "
                                                                    "number; give finite numbers, e.g. range(0,5) or "
                                                                    "range(0,1,0.25)")
            if not value.step:
                raise BadInput(f"override '{override.input_line}'", "has a range step of 0; give a step that is "
                                                                    "not 0, e.g. range(0,5) or range(0,1,0.25)")
            count = _range_length(value.start, value.stop, value.step)
        elif isinstance(value, ChoiceSweep):
            count = len(value.list)
        else:  # glob(...) over a config group's options: few
            try:
                reparsed = parser.parse_overrides([override.input_line])[0]
                count = sum(1 for _ in reparsed.sweep_string_iterator())
            except Exception:  # noqa: BLE001 - expand() reports a bad glob
                count = 1
        total *= count
        if count > most:
            biggest, most = override, count
    return total, biggest


def _range_length(start, stop, step) -> int | float:
    """len(range(start, stop, step)) for ints of any size and for floats, without listing it (inf when unbounded;
    0 for a zero or undefined step, which expand() then reports)."""
    import math
    from fractions import Fraction

    try:
        if all(isinstance(v, int) for v in (start, stop, step)):
            return max(0, math.ceil(Fraction(stop - start, step))) if step else 0
        ratio = (float(stop) - float(start)) / float(step)
    except (ZeroDivisionError, TypeError, ValueError, OverflowError):
        return 0
    if math.isnan(ratio):
        return 0
    return max(0, math.ceil(ratio)) if math.isfinite(ratio) else math.inf


def check_subdir(value, several: bool) -> None:
    """A hydra.sweep.subdir of the user's: without an interpolation it must be one relative folder, and it cannot
    serve several jobs (they would share it)."""
    import posixpath

    text = "" if value is None else str(value)
    if "${" in text:
        return  # per job (${hydra.job.num}, ...): the user's naming
    parts = [p for p in text.replace("\\", "/").split("/") if p not in ("", ".")]
    if not parts or posixpath.isabs(text) or ".." in parts or "\x00" in text:
        raise BadInput("hydra.sweep.subdir", f"got {text!r}; give a folder inside the sweep directory, e.g. "
                                             f"job_${{hydra.job.num}}, or leave it out (riskplan names each job's "
                                             f"folder from its overrides)")
    if several:
        raise BadInput("hydra.sweep.subdir", f"got {text!r}: every job of the sweep would write into that one "
                                             f"folder; use an interpolation such as job_${{hydra.job.num}}, or leave "
                                             f"it out (riskplan names each job's folder from its overrides)")


def check_size(task_ovs: list) -> None:
    """A sweep larger than the job budget (RISKPLAN_MAX_JOBS) is bad input, before anything is expanded."""
    from riskplan.limits import check_jobs

    total, biggest = sweep_size(task_ovs)
    swept = [o for o in task_ovs if o.is_sweep_override()]
    key = f"override '{biggest.input_line}'" if len(swept) == 1 and biggest is not None else "sweep"
    check_jobs(key, total)


def check_duplicates(job_list: list[Job], task_ovs: list) -> None:
    """Two combinations that compose to one config (seed=0,0 or risk.beta=0.1,0.10) would be one job twice, in two
    folders or one: bad input naming the override."""
    seen: dict[str, Job] = {}
    for job in job_list:
        other = seen.setdefault(job.sha, job)
        if other is job:
            continue
        mine, theirs = _by_key(job.overrides), _by_key(other.overrides)
        differ = [k for k in theirs if theirs[k] != mine.get(k)]
        by_key = {o.key_or_group: o for o in task_ovs}
        if differ:
            key = differ[0]
            line = by_key[key].input_line if key in by_key else key
            raise BadInput(f"override '{line}'", f"gives {theirs[key]} and {mine[key]}, which compose to the same "
                                                 f"config (one job twice); give each value once")
        for override in task_ovs:
            value = _repeated(override) if override.is_sweep_override() else None
            if value is not None:
                raise BadInput(f"override '{override.input_line}'", f"gives the value {value} twice (one job "
                                                                    f"twice); give each value once")
        raise BadInput("sweep", f"gives the combination {job.label or ','.join(sorted(job.overrides))} twice (one "
                                f"job twice); give each combination once")


def _by_key(overrides: list[str]) -> dict[str, str]:
    """{key: 'key=value'} of a job's overrides."""
    return {line.split("=", 1)[0].lstrip("+~"): line for line in overrides}


def _repeated(override) -> str | None:
    """A value a sweep override lists twice (as Hydra passes it to the job: 0.10 is 0.1), or None."""
    try:
        values = list(override.sweep_string_iterator())
    except Exception:  # noqa: BLE001
        return None
    seen: set[str] = set()
    for value in values:
        if value in seen:
            return value
        seen.add(value)
    return None


def name_folders(job_list: list[Job], naming: dict, task_ovs: list) -> None:
    """The folder each job gets (Hydra's override_dirname through riskplan.sweepjob.folder_name); two jobs that
    would share one are bad input."""
    from hydra._internal.config_loader_impl import get_overrides_dirname

    from riskplan.sweepjob import folder_name

    parser = _parser()
    owners: dict[str, Job] = {}
    for job in job_list:
        dirname = get_overrides_dirname(parser.parse_overrides(job.overrides), list(naming["exclude_keys"]),
                                        str(naming["item_sep"]), str(naming["kv_sep"]))
        job.folder = folder_name(dirname)
        other = owners.setdefault(job.folder, job)
        if other is not job:
            swept = [o for o in task_ovs if o.is_sweep_override()] or task_ovs
            raise BadInput(f"override '{swept[0].input_line}'",
                           f"makes two combinations share the job folder {job.folder} "
                           f"({','.join(sorted(other.overrides))} and {','.join(sorted(job.overrides))}); give "
                           f"values that differ in their text, or set hydra.sweep.subdir")


def add_naming_and_logging(argv: list[str], hydra_keys: dict, constant: list[str]) -> None:
    """riskplan's Hydra settings for a sweep, unless the user gave their own: job folders named by what varies
    (risk.beta=0.1,seed=0), not by every fixed setting (the job's .hydra/overrides.yaml keeps them all, and resuming
    matches jobs by their full config anyway), and logging into sweep.log and each job's job.log."""
    if constant and not {"hydra.sweep.subdir", "hydra.job.config.override_dirname.exclude_keys"} & set(hydra_keys):
        argv.append("hydra.job.config.override_dirname.exclude_keys=["
                    + ",".join(hydra_quote(k) for k in constant) + "]")
    if "hydra/hydra_logging" not in hydra_keys:
        argv.append("hydra/hydra_logging=riskplan_sweep")
    if "hydra/job_logging" not in hydra_keys:
        argv.append("hydra/job_logging=riskplan_job")


def expand(task_ovs: list, args: list[str]) -> list[list[str]]:
    """Every combination, as Hydra's basic sweeper makes it (the same grammar, the same job overrides)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.errors import HydraException

    parser = _parser()
    try:
        reparsed = parser.parse_overrides([o.input_line for o in task_ovs])
        batches = BasicSweeper.split_arguments(reparsed, None)
    except (HydraException, ValueError, TypeError, ArithmeticError) as err:
        raise BadInput("sweep", f"{_first_line(err)}; use comma lists, range(...), choice(...) or glob(...)") from None
    combos = [list(job) for batch in batches for job in batch]
    if not combos or (task_ovs and any(not job for job in combos)):
        raise BadInput("sweep", f"'{' '.join(args)}' expands to no job; check empty range(...) values")
    return combos


def check_hydra(hydra_args: list[str], first_job: list[str], sweeper: bool = False):
    """Compose Hydra's own config (launcher and its settings) once: a bad one is bad input, before anything runs.
    Returns hydra.job.config.override_dirname (exclude_keys, item_sep, kv_sep), which names the job folders, and
    with `sweeper` also hydra.sweeper (its settings, enums as text)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from omegaconf import OmegaConf

    from riskplan import schema
    from riskplan.config import CONF_DIR, explain, parse_overrides
    from riskplan.hydra_checks import check_hydra_node

    schema.register()
    GlobalHydra.instance().clear()

    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name="config", overrides=[*hydra_args, *first_job], return_hydra_config=True)
            check_hydra_node(cfg, [o for o in parse_overrides(hydra_args) if o.is_hydra_override()])
            naming = OmegaConf.to_container(cfg.hydra.job.config.override_dirname, resolve=True)
            if sweeper:
                return naming, OmegaConf.to_container(cfg.hydra.sweeper, resolve=True, enum_to_str=True)
            return naming
    except (HydraException, OmegaConfBaseException) as err:
        where, message = explain(err)
        if where == "key 'hydra/launcher'":
            message += " (pip install 'riskplan[slurm]' for submitit_local|submitit_slurm, 'riskplan[ray]' for ray)"
        if where == "key 'hydra/sweeper'":
            message += " (pip install 'riskplan[optuna]' for optuna)"
        raise BadInput(where, message) from None
    finally:
        GlobalHydra.instance().clear()


def constant_keys(combos: list[list[str]], swept: set[str] = frozenset()) -> list[str]:
    """The override keys left out of job folder names: those with one value in every job that were not typed as a
    sweep (`seed=range(0,1)` keeps its key), as long as some key remains."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    values: dict[str, set[str]] = {}
    for combo in combos:
        for o in parser.parse_overrides(combo):
            values.setdefault(o.key_or_group, set()).add(o.input_line)
    constant = [k for k, v in values.items() if len(v) == 1 and k not in swept]
    return constant if len(constant) < len(values) else []


def validate(combos: list[list[str]]) -> tuple[list[Job], list[str]]:
    """Compose every combination against the schema (BadInput on the first failure), then check each with the
    model. Compositions are shared between combinations that choose the same config groups."""
    from hydra import compose, initialize_config_dir
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from riskplan import schema
    from riskplan.config import CONF_DIR
    from riskplan.config import compose as riskplan_compose
    from riskplan.setup import build_setup
    from riskplan.sweepjob import config_sha

    parser = _parser()
    schema.register()
    GlobalHydra.instance().clear()
    bases: dict[tuple[str, ...], object] = {}
    jobs: list[Job] = []
    notes: list[str] = []
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            for combo in combos:
                parsed = parser.parse_overrides(combo)
                groups = tuple(o.input_line for o in parsed if _is_group(o, CONF_DIR))
                keys = [o for o in parsed if not _is_group(o, CONF_DIR)]
                try:
                    if groups not in bases:
                        bases[groups] = compose(config_name="config", overrides=list(groups))
                    cfg = copy.deepcopy(bases[groups])
                    ConfigLoaderImpl._apply_overrides_to_config(keys, cfg)
                except (HydraException, OmegaConfBaseException):
                    riskplan_compose(combo, validate=False)  # raises BadInput naming the key
                    cfg = compose(config_name="config", overrides=combo)  # composes after all: use Hydra's own
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    try:
                        build_setup(cfg)
                        invalid = None
                    except BadInput as err:
                        invalid = str(err)
                for w in caught:
                    if str(w.message) not in notes:
                        notes.append(str(w.message))
                jobs.append(Job(list(combo), config_sha(cfg), invalid))
    finally:
        GlobalHydra.instance().clear()
    return jobs, notes


def _parser():
    """Hydra's override parser, with a config loader so that glob(...) over config groups works."""
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from hydra._internal.utils import create_config_search_path
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from riskplan.config import CONF_DIR

    loader = ConfigLoaderImpl(config_search_path=create_config_search_path(str(CONF_DIR)))
    return OverridesParser.create(config_loader=loader)


def _is_group(override, conf_dir: Path) -> bool:
    """Whether an override selects a config group option (experiment=..., risk=...) rather than sets a key."""
    return override.package is not None or (conf_dir / override.key_or_group).is_dir()


def _split_bad(message: str, count: int) -> tuple[str, str]:
    """BadInput parts for 'every combination is invalid'."""
    where, _, problem = message.partition(": ")
    if count > 1:
        problem = f"{problem} (in every one of the {count} combinations; nothing was run)"
    return where, problem


def cpu_count() -> int:
    """Cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def _first_line(err: Exception) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


# ----------------------------------------------------------------------------------------------------- running


def run_sweep(args: list[str], jobs: int | None = None, sweep_dir: Path | None = None, title: str = "sweep",
              out=None) -> Outcome:
    """Plan, launch through Hydra, show progress, write summary.parquet. BadInput before anything runs."""
    from riskplan import lock

    plan = plan_sweep(args, jobs, sweep_dir)
    with lock.hold(plan.sweep_dir, "sweep directory"):  # one driver per sweep directory, for the whole launch
        return _run_plan(plan, args, jobs, title, out)


def _run_plan(plan: Plan, args: list[str], jobs: int | None, title: str, out) -> Outcome:
    from riskplan.sweepjob import DRIVER_ENV, THREADS_ENV, is_finished

    echo = out or (lambda text: typer.echo(text))
    for note in plan.warnings:
        typer.echo(f"warning: {note}", err=True)
    if plan.sweeper != "basic":
        return _run_optimiser(plan, args, jobs, title, echo)
    started = time.time()
    locate(plan.sweep_dir, plan.jobs)
    finished = {i for i, job in enumerate(plan.jobs) if job.path is not None and is_finished(job.path, job.sha)}
    todo = len(plan.jobs) - len(finished)
    if plan.workers_arg is not None and plan.workers and todo and todo < plan.workers:
        plan.workers = todo  # no more workers than jobs to run: each gets more threads
        plan.argv[plan.workers_arg] = f"hydra.launcher.n_jobs={todo}"
    where = f"{plan.launcher}" + (f", {plan.workers} workers" if plan.workers else "")
    echo(f"{title} directory: {plan.sweep_dir}")
    echo(f"{len(plan.jobs)} job{'s' if len(plan.jobs) != 1 else ''}: {todo} to run, {len(finished)} already "
         f"finished ({where})")
    launcher_error = None
    if todo:
        if plan.launcher == "joblib" and plan.workers:
            os.environ[THREADS_ENV] = str(max(1, cpu_count() // plan.workers))
        os.environ[DRIVER_ENV] = str(os.getpid())  # local workers SIGKILL themselves when this process is gone
        with SweepView(plan.sweep_dir, plan.jobs, finished, title):
            launcher_error = _launch(plan.argv, plan.sweep_dir / "sweep.log")
    for job in plan.jobs:  # a job found under another name (an older naming) ran in its own folder now
        if job.folder is not None and job.path is not None and job.path.name != job.folder \
                and (plan.sweep_dir / job.folder).is_dir():
            job.path = None
    locate(plan.sweep_dir, plan.jobs)
    summary = summarize(plan.jobs)
    write_summary(summary, plan.sweep_dir / SUMMARY)
    failed = [(row.job, row.error or row.status) for row in summary.itertuples() if row.status != "done"]
    resume = ([a for a in args if not a.startswith("hydra.sweep.dir=")] + [f"hydra.sweep.dir={plan.sweep_dir}"]
              + (["--jobs", str(jobs)] if jobs else []))
    return Outcome(plan.sweep_dir, summary, failed, todo, len(finished), time.time() - started, launcher_error,
                   resume)


def _run_optimiser(plan: Plan, args: list[str], jobs: int | None, title: str, echo) -> Outcome:
    """Launch a sweep whose sweeper chooses the trials; then one summary row per trial it ran."""
    from riskplan.sweepjob import DRIVER_ENV, THREADS_ENV

    started = time.time()
    where = f"{plan.launcher}" + (f", {plan.workers} workers" if plan.workers else "")
    echo(f"{title} directory: {plan.sweep_dir}")
    count = f"{plan.trials} trials" if plan.trials else "trials"
    echo(f"{count} chosen by hydra/sweeper={plan.sweeper} over {', '.join(plan.search) or 'no key'}, each "
         f"returning its CVaR ({where})")
    if plan.launcher == "joblib" and plan.workers:
        os.environ[THREADS_ENV] = str(max(1, cpu_count() // plan.workers))
    os.environ[DRIVER_ENV] = str(os.getpid())
    if plan.sweeper == "optuna":  # optuna's messages go where Hydra's go (sweep.log), not to the terminal
        try:
            import optuna

            optuna.logging.disable_default_handler()
            optuna.logging.enable_propagation()
        except ImportError:
            pass
    with SweepView(plan.sweep_dir, [], set(), title, total=plan.trials,
                   discover=lambda since: discover_trials(plan.sweep_dir, since)):
        launcher_error = _launch(plan.argv, plan.sweep_dir / "sweep.log")
    trials = trial_jobs(plan.sweep_dir, started)
    summary = summarize(trials)
    if len(summary):
        summary.insert(1, "trial", [job.trial for job in trials])
    write_summary(summary, plan.sweep_dir / SUMMARY)
    failed = [(row.job, row.error or row.status) for row in summary.itertuples() if row.status != "done"]
    if plan.trials and len(trials) < plan.trials and launcher_error is None:
        launcher_error = (f"the sweeper ran {len(trials)} of {plan.trials} trials (see "
                          f"{plan.sweep_dir / 'sweep.log'})")
    resume = ([a for a in args if not a.startswith("hydra.sweep.dir=")] + [f"hydra.sweep.dir={plan.sweep_dir}"]
              + (["--jobs", str(jobs)] if jobs else []))
    from riskplan.sweepjob import read_status

    earlier = sum(1 for job in trials if _number((read_status(job.path) or {}).get("finished")) < started - 2
                  and (read_status(job.path) or {}).get("status") == "done")  # finished before: skipped now
    outcome = Outcome(plan.sweep_dir, summary, failed, len(trials) - earlier, earlier, time.time() - started,
                      launcher_error, resume)
    outcome.best = best_trial(plan.sweep_dir, started)
    outcome.optimiser = True
    return outcome


def discover_trials(sweep_dir: Path, since: float) -> list[Job]:
    """The job folders Hydra wrote since `since` (each launch rewrites a job's .hydra/), as Jobs of any config."""
    import yaml

    found = []
    for file in _override_files(Path(sweep_dir)):
        try:
            if file.stat().st_mtime < since - 2:
                continue
            overrides = yaml.safe_load(file.read_text()) or []
        except (OSError, yaml.YAMLError):
            continue
        if isinstance(overrides, list):
            folder = file.parent.parent
            found.append(Job([str(o) for o in overrides], None, path=folder, label=folder.name))
    return found


def trial_jobs(sweep_dir: Path, since: float) -> list[Job]:
    """The trials launched since `since`, in the sweeper's order (hydra.job.num), each with the fingerprint of
    its composed config."""
    import yaml

    from riskplan.errors import BadInput as _Bad

    trials = discover_trials(sweep_dir, since)
    for job in trials:
        try:
            hydra_yaml = yaml.safe_load((job.path / ".hydra" / "hydra.yaml").read_text())
            job.trial = int(hydra_yaml["hydra"]["job"]["num"])
        except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError):
            job.trial = -1
        try:
            checked, _ = validate([job.overrides])
            job.sha, job.invalid = checked[0].sha, checked[0].invalid
        except _Bad as err:
            job.sha, job.invalid = "", str(err)
    return sorted(trials, key=lambda j: (j.trial, j.name))


def best_trial(sweep_dir: Path, since: float) -> str | None:
    """What the sweeper reports as its best (optuna's optimization_results.yaml), written by this launch."""
    import yaml

    file = Path(sweep_dir) / "optimization_results.yaml"
    try:
        if file.stat().st_mtime < since - 2:
            return None
        result = yaml.safe_load(file.read_text()) or {}
    except (OSError, yaml.YAMLError):
        return None
    if not isinstance(result, dict) or "best_params" not in result:
        return None
    params = ",".join(f"{k}={v}" for k, v in (result.get("best_params") or {}).items())
    return f"best trial: {params} with CVaR {result.get('best_value')} ({file.name})"


def _launch(argv: list[str], log_file: Path) -> str | None:
    """Run Hydra's multirun, its printed output going to sweep.log; return the launcher's error, if any."""
    import contextlib

    from riskplan.app import run_hydra

    with open(log_file, "a", buffering=1) as log, contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        try:
            run_hydra(argv)
        except SystemExit as stop:  # Hydra prints an exception in the launcher, then exits 1
            if stop.code not in (0, None):
                return _launcher_error(log_file)
        except KeyboardInterrupt:
            return "interrupted (Ctrl-C)"
        except Exception as err:  # noqa: BLE001 - the jobs' own records say what finished
            import traceback

            traceback.print_exc()
            return f"the launcher stopped: {type(err).__name__}: {err} (see {log_file})"
    return None


def _launcher_error(log_file: Path) -> str:
    """The last line of the error Hydra printed into sweep.log."""
    try:
        lines = [line.strip() for line in log_file.read_text().splitlines() if line.strip()]
    except OSError:
        lines = []
    errors = [line for line in lines if "Error" in line.split(":")[0] or "Exception" in line.split(":")[0]]
    last = errors[-1] if errors else (lines[-1] if lines else "no message")
    return f"the launcher stopped: {last[:300]} (see {log_file})"


def locate(sweep_dir: Path, jobs: list[Job]) -> None:
    """Find each job's folder by the overrides Hydra recorded in it (whatever hydra.sweep.subdir is)."""
    import yaml

    missing = {job.key: job for job in jobs if job.path is None}
    if not missing or not Path(sweep_dir).is_dir():
        return
    elsewhere: dict[tuple[str, ...], Path] = {}  # found, but not in the folder the job is named for
    for file in _override_files(Path(sweep_dir)):
        try:
            overrides = yaml.safe_load(file.read_text()) or []
        except (OSError, yaml.YAMLError):
            continue
        if not isinstance(overrides, list):
            continue
        key = tuple(sorted(str(o) for o in overrides))
        job = missing.get(key)
        if job is None:
            continue
        folder = file.parent.parent
        if job.folder is None or folder.name == job.folder:
            job.path = folder
            del missing[key]
        else:
            elsewhere.setdefault(key, folder)
        if not missing:
            return
    for key, folder in elsewhere.items():
        if key in missing:
            missing[key].path = folder


def _override_files(root: Path):
    """Every .hydra/overrides.yaml below root, not looking inside other hidden folders (.submitit, ...)."""
    for here, dirs, files in os.walk(root):
        if Path(here).name == ".hydra":
            dirs[:] = []
            if "overrides.yaml" in files:
                yield Path(here) / "overrides.yaml"
            continue
        dirs[:] = [d for d in dirs if d == ".hydra" or not d.startswith(".")]


def job_state(job: Job, since: float) -> tuple[str, dict | None]:
    """pending | running | done | failed, as far as this launch is concerned (older records are pending)."""
    from riskplan import lock
    from riskplan.sweepjob import read_status

    if job.path is None:
        return "pending", None
    status = read_status(job.path)
    if status is not None and (job.sha is None or status.get("config_sha") == job.sha):
        state = status.get("status")
        if state == "running" and _number(status.get("started")) >= since - 2:
            return "running", status
        if state in ("done", "failed") and _number(status.get("finished")) >= since - 2:
            return state, status
    if lock.holder(job.path) is not None:  # a job of this launch about to start, or one of another process
        return "running", status
    return "pending", status


def _number(value) -> float:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else 0.0


# ----------------------------------------------------------------------------------------------------- summary


def summarize(jobs: list[Job]):
    """One row per job: its overrides as columns, final figures with 95% intervals, wall time, status, error."""
    import pandas as pd

    from riskplan import lock
    from riskplan.sweepjob import is_finished, read_status

    rows = []
    for job in jobs:
        row: dict = {"job": job.name}
        row.update(_override_columns(job.overrides))
        status = read_status(job.path) if job.path is not None else None
        holder = lock.holder(job.path) if job.path is not None else None
        summary = None
        if holder is not None and holder != os.getpid():
            status = None  # whatever its status says, that process owns it now
            state, error = "running", (f"running in another process (pid {holder or 'unknown'}); re-run the sweep "
                                       f"when that process has ended")
        elif job.path is None or status is None:
            state, error = "not run", job.invalid or "not started: the sweep stopped before it"
        elif status.get("config_sha") != job.sha:
            state, error = "not run", "its folder holds a run of another config"
        elif status.get("status") == "done" and is_finished(job.path, job.sha, status):
            state, error = "done", None
            try:
                summary = json.loads((job.path / "summary.json").read_text())
            except (OSError, ValueError) as err:
                state, error = "failed", f"unreadable summary.json: {err}"
        elif status.get("status") == "done":
            state, error = "failed", "finished, but some of its output files are missing"
        elif status.get("status") == "running":
            state, error = "interrupted", "killed while running; re-run the sweep to resume it"
        else:
            state, error = "failed", status.get("error") or "no error recorded"
        for name in FIGURES:
            figure = (summary or {}).get(name) or {}
            row[name] = figure.get("value", float("nan"))
            row[f"{name}_low"] = figure.get("low", float("nan"))
            row[f"{name}_high"] = figure.get("high", float("nan"))
        for name in EXTRA_CVARS:
            row[name] = ((summary or {}).get(name) or {}).get("value", float("nan"))
        row["beta"] = (summary or {}).get("beta", float("nan"))
        row["risky_fraction"] = (summary or {}).get("risky_fraction", float("nan"))
        reached = (summary or {}).get("source_reached") or {}
        for name, value in (reached.items() if isinstance(reached, dict) else ()):
            row[f"reached_{name}"] = value
        row["wall_time"] = (float(status["seconds"]) if status and state == "done"
                            and isinstance(status.get("seconds"), (int, float)) else float("nan"))
        row["train_time"] = (summary or {}).get("wall_time", float("nan"))
        row["status"] = state
        row["error"] = error
        row["path"] = str(job.path) if job.path is not None else None
        rows.append(row)
    frame = pd.DataFrame(rows)
    reached = [c for c in frame.columns if str(c).startswith("reached_")]
    if reached:  # right after risky_fraction, whichever job first had them
        rest = [c for c in frame.columns if c not in reached]
        at = rest.index("risky_fraction") + 1
        frame = frame[rest[:at] + reached + rest[at:]]
    for column in frame.columns:  # a column mixing numbers and text is stored as text
        kinds = {type(v) for v in frame[column] if v is not None and v == v}
        if len(kinds) > 1 and not kinds <= {int, float, bool}:
            frame[column] = frame[column].map(lambda v: None if v is None else str(v))
    return frame


def _override_columns(overrides: list[str]) -> dict:
    """{key: value} of a job's overrides; numbers stay numbers, lists and dicts become their JSON text."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    out = {}
    for o in OverridesParser.create().parse_overrides(overrides):
        value = o.value()
        if isinstance(value, (list, dict)):
            value = json.dumps(value)
        elif value is not None and not isinstance(value, (int, float, bool, str)):
            value = str(value)
        out[o.key_or_group] = value
    return out


def write_summary(frame, path: Path) -> None:
    """Write summary.parquet atomically (no half file, and no temp file left on a full disk)."""
    with atomic_path(path) as tmp:
        frame.to_parquet(tmp, index=False)


def varying_columns(frame) -> list[str]:
    """The override columns whose value differs between jobs (all of them if none differs)."""
    fixed = {"job", "trial", "status", "error", "path", "beta", "wall_time", "train_time", "risky_fraction",
             *EXTRA_CVARS, *[f"{n}{s}" for n in FIGURES for s in ("", "_low", "_high")]}
    overrides = [c for c in frame.columns if c not in fixed and not str(c).startswith("reached_")]
    varying = [c for c in overrides if frame[c].astype(str).nunique() > 1]
    return varying or overrides[:3]


def print_table(frame, title: str, limit: int = 40) -> None:
    """The summary as a terminal table (the varying overrides, status, figures with intervals, wall time)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, title_justify="left", show_edge=False, pad_edge=False)
    keys = (["trial"] if "trial" in frame.columns else []) + varying_columns(frame)
    reached = [c for c in frame.columns if str(c).startswith("reached_")]
    for key in keys:
        table.add_column(key, no_wrap=True)
    table.add_column("status", no_wrap=True)
    for name, label in (("mean", "mean [95% CI]"), ("cvar", "CVaR [95% CI]"), ("value_at_risk", "VaR")):
        table.add_column(label, justify="right", no_wrap=True)
    for column in reached:
        table.add_column(column, justify="right", no_wrap=True)
    table.add_column("wall s", justify="right", no_wrap=True)
    for values in frame.head(limit).to_dict("records"):
        cells = [str(values[k]) for k in keys]
        status = values["status"]
        cells.append(status if status == "done" else f"[red]{status}[/red]")
        for name in ("mean", "cvar"):
            v, lo, hi = values[name], values[f"{name}_low"], values[f"{name}_high"]
            cells.append("" if v != v else f"{v:.1f} [{lo:.1f}, {hi:.1f}]")
        var = values["value_at_risk"]
        cells.append("" if var != var else f"{var:.1f}")
        for column in reached:
            share = values[column]
            cells.append("" if share is None or share != share else f"{share:.0%}")
        wall = values["wall_time"]
        cells.append("" if wall != wall else f"{wall:.1f}")
        table.add_row(*cells)
    console = Console() if sys.stdout.isatty() else Console(width=250)
    console.print(table)
    if len(frame) > limit:
        console.print(f"... {len(frame) - limit} more rows in {SUMMARY}")


# ----------------------------------------------------------------------------------------------------- live view


class SweepView:
    """One live line for a running sweep (done / running / failed / ETA), redrawn from the jobs' status files.

    On a terminal it is a rich progress bar; otherwise (CI, a pipe) one line per finished job. It writes to a
    duplicate of stderr taken before launch, so it stays on the terminal even while a job runs in this process
    and sends its own output to its folder.
    """

    def __init__(self, sweep_dir: Path, jobs: list[Job], finished: set[int], title: str, every: float = 0.5,
                 total: int | None = None, discover=None):
        self.sweep_dir, self.jobs, self.finished, self.title, self.every = sweep_dir, jobs, finished, title, every
        self.todo = [i for i in range(len(jobs)) if i not in finished]
        self.discover = discover  # an optimiser's trials: found as the sweeper launches them (discover(since))
        self.total = total
        self.reported: set[int] = set()
        self.stop = threading.Event()

    def __enter__(self):
        from rich.console import Console

        sys.stderr.flush()
        self.stream = os.fdopen(os.dup(2), "w", buffering=1)
        self.tty = self.stream.isatty()
        self.console = Console(file=self.stream, force_terminal=self.tty or None)
        self.since = time.time()
        self.bar = None
        if self.tty:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self.bar = Progress(TextColumn(f"[bold]{self.title}"), BarColumn(), MofNCompleteColumn(),
                                TextColumn("{task.fields[state]}"), TimeElapsedColumn(),
                                TextColumn("{task.fields[eta]}"), console=self.console, transient=False)
            self.bar.__enter__()
            self.task = self.bar.add_task(self.title, total=self._total(), state="", eta="")
        self.thread = threading.Thread(target=self._loop, name="riskplan-sweep-view", daemon=True)
        self.thread.start()
        return self

    def _loop(self) -> None:
        while not self.stop.wait(self.every):
            self.refresh()

    def _total(self) -> int:
        return max(self.total or 0, len(self.todo))

    def refresh(self) -> None:
        """Read the jobs' status files and redraw."""
        try:
            if self.discover is not None:
                known = {job.path for job in self.jobs}
                for job in self.discover(self.since):
                    if job.path not in known:
                        self.jobs.append(job)
                        self.todo.append(len(self.jobs) - 1)
            if any(self.jobs[i].path is None for i in self.todo):
                locate(self.sweep_dir, self.jobs)
            counts = {"pending": 0, "running": 0, "done": 0, "failed": 0}
            for i in self.todo:
                state, status = job_state(self.jobs[i], self.since)
                counts[state] += 1
                if state in ("done", "failed") and i not in self.reported:
                    self.reported.add(i)
                    self._finished_line(i, state, status)
            ended = counts["done"] + counts["failed"]
            elapsed = time.time() - self.since
            eta = (f"ETA {dt.timedelta(seconds=round(elapsed / ended * (self._total() - ended)))}"
                   if 0 < ended < self._total() else "")
            state = (f"running {counts['running']} · failed {counts['failed']}"
                     + (f" · skipped {len(self.finished)} finished before" if self.finished else ""))
            if self.bar is not None:
                self.bar.update(self.task, completed=ended, total=self._total(), state=state, eta=eta)
        except Exception:  # noqa: BLE001 - the view must never break the sweep
            pass

    def _finished_line(self, i: int, state: str, status: dict | None) -> None:
        job = self.jobs[i]
        seconds = (status or {}).get("seconds")
        took = f" ({seconds:.1f} s)" if isinstance(seconds, (int, float)) else ""
        if state == "failed":
            line = f"[red]failed[/red] {job.name}: {(status or {}).get('error')}"
        else:
            line = f"done {job.name}{took}"
        if self.bar is not None:
            if state == "failed":
                self.bar.console.print(line, markup=True, highlight=False)
        else:
            self.console.print(f"[{len(self.reported)}/{self._total()}] {line}", markup=True, highlight=False,
                               soft_wrap=True)

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join()
        self.refresh()
        if self.bar is not None:
            self.bar.__exit__(*exc)
        self.stream.close()
        return False


# ----------------------------------------------------------------------------------------------------- command


def report_outcome(outcome: Outcome, title: str = "sweep", hint: bool = True) -> int:
    """Print the summary table and the failures; return the exit code (0, or 1 when a job failed)."""
    print_table(outcome.summary, f"{title}: {outcome.sweep_dir}")
    typer.echo(f"summary: {outcome.sweep_dir / SUMMARY} ({outcome.ran} launched, {outcome.skipped} skipped, "
               f"{outcome.seconds:.1f} s)")
    if outcome.best:
        typer.echo(outcome.best)
    if outcome.launcher_error:
        typer.echo(f"error: {outcome.launcher_error}", err=True)
    if outcome.failed:
        typer.echo(f"error: {len(outcome.failed)} of {len(outcome.summary)} "
                   f"{'trials' if outcome.optimiser else 'jobs'} did not finish:", err=True)
        for name, error in outcome.failed:
            typer.echo(f"  {name}: {error}", err=True)
    if hint and not outcome.ok and outcome.command:
        import shlex

        what = ("to run the study again in this directory (a trial that draws the values of a finished one, as "
                "with a seeded sampler, is skipped)" if outcome.optimiser
                else "to retry the jobs that did not finish (finished ones are skipped)")
        typer.echo(f"{what}: riskplan sweep {shlex.join(outcome.command)}", err=True)
    return 0 if outcome.ok else 1
