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
              "that finished.")


@dataclass
class Job:
    """One combination of the sweep."""

    overrides: list[str]  # as Hydra passes them to the job (and writes them to .hydra/overrides.yaml)
    sha: str  # riskplan.sweepjob.config_sha of its composed config
    invalid: str | None = None  # why the model rejects it (the job will fail with this error)
    path: Path | None = None  # its folder, once known
    label: str = ""  # the overrides that vary between jobs: its name until its folder exists
    folder: str | None = None  # the folder name Hydra will give it (None when the user set hydra.sweep.subdir)

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

    @property
    def ok(self) -> bool:
        return not self.failed and self.launcher_error is None


# ----------------------------------------------------------------------------------------------------- planning


def plan_sweep(args: list[str], jobs: int | None = None, sweep_dir: Path | None = None) -> Plan:
    """Parse, expand and validate a sweep; claim its directory last, so bad input leaves nothing behind."""
    from riskplan.config import parse_overrides

    for arg in args:
        if arg.startswith("-"):
            raise BadInput(f"option '{arg}'", "is not known to riskplan sweep; give Hydra overrides (key=value) "
                                              "and --jobs N")
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
    if constant and not {"hydra.sweep.subdir", "hydra.job.config.override_dirname.exclude_keys"} & set(hydra_keys):
        # folders named by what varies (risk.beta=0.1,seed=0), not by every fixed setting; the job's
        # .hydra/overrides.yaml keeps them all, and resuming matches jobs by their full config anyway
        argv.append("hydra.job.config.override_dirname.exclude_keys=["
                    + ",".join(hydra_quote(k) for k in constant) + "]")
    if "hydra/hydra_logging" not in hydra_keys:
        argv.append("hydra/hydra_logging=riskplan_sweep")
    if "hydra/job_logging" not in hydra_keys:
        argv.append("hydra/job_logging=riskplan_job")

    naming = check_hydra(argv[1 + len(args):] + [o.input_line for o in hydra_ovs], combos[0])
    if task_ovs and "hydra.sweep.subdir" not in hydra_keys:
        name_folders(job_list, naming, task_ovs)

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
    return Plan(target, argv, job_list, launcher, workers, notes, workers_arg)


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


def check_hydra(hydra_args: list[str], first_job: list[str]) -> dict:
    """Compose Hydra's own config (launcher and its settings) once: a bad one is bad input, before anything runs.
    Returns hydra.job.config.override_dirname (exclude_keys, item_sep, kv_sep), which names the job folders."""
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
            return OmegaConf.to_container(cfg.hydra.job.config.override_dirname, resolve=True)
    except (HydraException, OmegaConfBaseException) as err:
        where, message = explain(err)
        if where == "key 'hydra/launcher'":
            message += " (pip install 'riskplan[slurm]' for submitit_local|submitit_slurm, 'riskplan[ray]' for ray)"
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
    if status is not None and status.get("config_sha") == job.sha:
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
        row["wall_time"] = (float(status["seconds"]) if status and state == "done"
                            and isinstance(status.get("seconds"), (int, float)) else float("nan"))
        row["train_time"] = (summary or {}).get("wall_time", float("nan"))
        row["status"] = state
        row["error"] = error
        row["path"] = str(job.path) if job.path is not None else None
        rows.append(row)
    frame = pd.DataFrame(rows)
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
    fixed = {"job", "status", "error", "path", "beta", "wall_time", "train_time", *EXTRA_CVARS,
             *[f"{n}{s}" for n in FIGURES for s in ("", "_low", "_high")]}
    overrides = [c for c in frame.columns if c not in fixed]
    varying = [c for c in overrides if frame[c].astype(str).nunique() > 1]
    return varying or overrides[:3]


def print_table(frame, title: str, limit: int = 40) -> None:
    """The summary as a terminal table (the varying overrides, status, figures with intervals, wall time)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, title_justify="left", show_edge=False, pad_edge=False)
    keys = varying_columns(frame)
    for key in keys:
        table.add_column(key, no_wrap=True)
    table.add_column("status", no_wrap=True)
    for name, label in (("mean", "mean [95% CI]"), ("cvar", "CVaR [95% CI]"), ("value_at_risk", "VaR")):
        table.add_column(label, justify="right", no_wrap=True)
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

    def __init__(self, sweep_dir: Path, jobs: list[Job], finished: set[int], title: str, every: float = 0.5):
        self.sweep_dir, self.jobs, self.finished, self.title, self.every = sweep_dir, jobs, finished, title, every
        self.todo = [i for i in range(len(jobs)) if i not in finished]
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
            self.task = self.bar.add_task(self.title, total=len(self.todo), state="", eta="")
        self.thread = threading.Thread(target=self._loop, name="riskplan-sweep-view", daemon=True)
        self.thread.start()
        return self

    def _loop(self) -> None:
        while not self.stop.wait(self.every):
            self.refresh()

    def refresh(self) -> None:
        """Read the jobs' status files and redraw."""
        try:
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
            eta = (f"ETA {dt.timedelta(seconds=round(elapsed / ended * (len(self.todo) - ended)))}"
                   if 0 < ended < len(self.todo) else "")
            state = (f"running {counts['running']} · failed {counts['failed']}"
                     + (f" · skipped {len(self.finished)} finished before" if self.finished else ""))
            if self.bar is not None:
                self.bar.update(self.task, completed=ended, state=state, eta=eta)
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
            self.console.print(f"[{len(self.reported)}/{len(self.todo)}] {line}", markup=True, highlight=False,
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
    if outcome.launcher_error:
        typer.echo(f"error: {outcome.launcher_error}", err=True)
    if outcome.failed:
        typer.echo(f"error: {len(outcome.failed)} of {len(outcome.summary)} jobs did not finish:", err=True)
        for name, error in outcome.failed:
            typer.echo(f"  {name}: {error}", err=True)
    if hint and not outcome.ok and outcome.command:
        import shlex

        typer.echo(f"to retry the jobs that did not finish (finished ones are skipped): riskplan sweep "
                   f"{shlex.join(outcome.command)}", err=True)
    return 0 if outcome.ok else 1
