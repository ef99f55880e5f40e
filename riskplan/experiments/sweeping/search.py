"""An optimising sweeper (hydra/sweeper=optuna): its search space checked with sample values, its trials found
as they run, one summary row per trial."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import yaml
from hydra.core.override_parser.types import ChoiceSweep, IntervalSweep, RangeSweep
from hydra.utils import instantiate

from riskplan.experiments.driver_watch import name_driver
from riskplan.experiments.sweep_worker import THREADS_ENV, TRIAL_SUBDIR, read_status
from riskplan.experiments.sweeping.grid import (
    add_naming_and_logging,
    check_hydra,
    check_subdir,
    target_dir,
    validate,
)
from riskplan.experiments.sweeping.jobs import (
    DEFAULT_LAUNCHER,
    SUMMARY,
    TRAVELS,
    Job,
    Outcome,
    Plan,
    as_number,
    override_files,
)
from riskplan.experiments.sweeping.launch import launch
from riskplan.experiments.sweeping.launcher_settings import launcher_workers, ray_init_overrides, runs_here
from riskplan.experiments.sweeping.summary import summarize, write_summary
from riskplan.experiments.sweeping.view import SweepView
from riskplan.util.errors import BadInput, first_line
from riskplan.util.limits import check_jobs, cpu_count
from riskplan.util.paths import hydra_quote

OPTIMISER_FORMS = "choice(...), comma lists, range(...) or interval(...)"


def plan_optimiser(
    args: list[str],
    task_ovs: list,
    hydra_ovs: list,
    launcher: str,
    sweeper: str,
    jobs: int | None,
    sweep_dir: Path | None,
    explicit_dir: Path | None,
) -> Plan:
    """A sweep whose sweeper chooses the jobs as it goes (hydra/sweeper=optuna): the combinations are not known
    before it runs, so the search space is checked instead. Every swept key is composed with a sample value of the
    type the sweeper will draw (every value of a choice), which makes an unknown key or a badly typed value bad
    input; a sample the model rejects is a warning (its trials fail alone), unless every sample is rejected for a
    key that is not searched (bad input). The trials run as jobs of the grid do (sweepjob), in folders numbered by
    trial; each returns its CVaR to the sweeper, or None when it failed (optuna records that trial as failed)."""
    hydra_keys = {o.key_or_group: o for o in hydra_ovs}
    search = [o for o in task_ovs if o.is_sweep_override()]
    fixed = [o for o in task_ovs if not o.is_sweep_override()]
    samples = {o.key_or_group: search_samples(o, sweeper) for o in search}
    base, notes = _check_samples(search, fixed, samples)
    searched = {o.key_or_group for o in search}

    argv = ["-m", *args]
    if sweeper == "optuna":
        if "hydra.sweeper.direction" not in hydra_keys:
            argv.append("hydra.sweeper.direction=maximize")  # the trials return their CVaR: higher is better
        if jobs is not None and "hydra.sweeper.n_jobs" not in hydra_keys:
            argv.append(f"hydra.sweeper.n_jobs={jobs}")  # trials per batch: as many as run at once
    argv += ray_init_overrides(launcher, hydra_keys)
    if "hydra/launcher" not in hydra_keys:
        argv.append(f"hydra/launcher={DEFAULT_LAUNCHER}")
    if "hydra.sweep.subdir" in hydra_keys:
        check_subdir(hydra_keys["hydra.sweep.subdir"].value(), True)
    else:  # trial_007,risk.beta=0.31: numbered, so two trials that drew the same values never share a folder
        argv.append(f"hydra.sweep.subdir={hydra_quote(TRIAL_SUBDIR)}")
    argv.append(TRAVELS)
    constant = [o.key_or_group for o in fixed] if search else []
    add_naming_and_logging(argv, hydra_keys, constant)
    _, settings = check_hydra(argv[1 + len(args) :] + [o.input_line for o in hydra_ovs], base, sweeper=True)
    trials, batch = check_optimiser(sweeper, settings, search)
    at_once = min([n for n in (batch, trials) if n], default=None)  # a sweeper may give neither
    workers, workers_arg = launcher_workers(argv, launcher, hydra_keys, jobs, at_once)
    target = target_dir(sweep_dir, explicit_dir, argv)
    return Plan(
        target,
        argv,
        [],
        launcher,
        workers,
        notes,
        workers_arg,
        sweeper=sweeper,
        trials=trials,
        search=sorted(searched),
        local=runs_here(launcher, hydra_keys),
    )


def _check_samples(search: list, fixed: list, samples: dict) -> tuple[list[str], list[str]]:
    """Every swept key composed with its sample values (the others at their first): bad input when a sample does
    not compose, or when the model rejects every sample for a key that is not searched; a warning for each sample
    it rejects. Returns the first sample's overrides and the warnings."""
    base = [o.input_line for o in fixed] + [f"{o.get_key_element()}={samples[o.key_or_group][0]}" for o in search]
    combos = [base]
    varying: dict[str, list[int]] = {}  # each swept key's combos: the base and those that vary it alone
    for i, o in enumerate(search):
        varying[o.key_or_group] = [0]
        for value in samples[o.key_or_group][1:]:
            combo = list(base)
            combo[len(fixed) + i] = f"{o.get_key_element()}={value}"
            varying[o.key_or_group].append(len(combos))
            combos.append(combo)
    try:
        sample_jobs, notes = validate(combos)
    except BadInput as err:  # name the search-space override whose sample does not compose
        for o in search:
            if err.where in (f"key '{o.key_or_group}'", o.key_or_group) and not o.is_choice_sweep():
                # Hydra's interval() has float bounds whatever is typed: a whole-number key needs int(interval(...))
                whole = "; for whole numbers write int(interval(...))" if o.is_interval_sweep() else ""
                raise BadInput(
                    err.where,
                    f"{err.problem} (from override '{o.input_line}', composed with the "
                    f"sample value {samples[o.key_or_group][0]}){whole if 'whole number' in err.problem else ''}",
                ) from None
        raise
    searched = {o.key_or_group for o in search}
    rejected = [job.invalid for job in sample_jobs if job.invalid]
    if rejected and len(rejected) == len(sample_jobs) and rejected[0].partition(": ")[0] not in searched:
        where, _, problem = rejected[0].partition(": ")
        raise BadInput(where, f"{problem} (in every trial; nothing was run)")
    for o in search:  # a choice's samples are all its values: every one rejected for itself, no trial can run
        errors = [sample_jobs[k].invalid or "" for k in varying[o.key_or_group]]
        if o.is_choice_sweep() and all(e.partition(": ")[0] == o.key_or_group for e in errors):
            others = f", and the other {len(errors) - 1} values likewise" if len(errors) > 1 else ""
            raise BadInput(
                f"override '{o.input_line}'",
                f"every value is rejected ({errors[0].partition(': ')[2]}{others}); no trial could run",
            )
    for job, error in zip(sample_jobs, (j.invalid for j in sample_jobs)):
        if error:
            tried = ",".join(job.overrides[len(fixed) :])
            notes.append(f"{error} (with the sample {tried}); trials there will fail alone")
    return base, notes


def search_samples(override, sweeper: str) -> list[str]:
    """Values to compose a search-space override with, of the types the sweeper will draw: every value of a
    choice, the start of a range (and its next value), the middle of an interval (an int for an int interval)."""
    value = override.value()
    line = f"override '{override.input_line}'"
    if isinstance(value, ChoiceSweep):
        return list(override.sweep_string_iterator())
    if isinstance(value, RangeSweep):
        bounds = (value.start, value.stop, value.step)
        if any(not isinstance(v, (int, float)) or not math.isfinite(v) for v in bounds) or not value.step:
            raise BadInput(
                line,
                "has a range bound or step that is not a finite number, or a step of 0; give "
                "finite numbers, e.g. range(0,5) or range(0,1,0.25)",
            )
        if (value.stop - value.start) / value.step < 0:
            raise BadInput(line, "is an empty range; give a start below the stop, e.g. range(0,5)")
        first = value.start if all(isinstance(v, int) for v in bounds) else float(value.start)
        return [repr(first)]
    if isinstance(value, IntervalSweep):
        start, end = value.start, value.end
        if any(not isinstance(v, (int, float)) or not math.isfinite(v) for v in (start, end)):
            raise BadInput(line, "has a bound that is not a finite number; give finite numbers, e.g. interval(0.05,1)")
        if not start < end:
            raise BadInput(
                line,
                f"has its lower bound {start} not below its upper bound {end}; give interval(low,high) with low < high",
            )
        log = "log" in value.tags
        if log and start <= 0:
            raise BadInput(line, f"is a log interval from {start}; a log interval needs a lower bound above 0")
        if isinstance(start, int) and isinstance(end, int):
            return [repr(round(math.sqrt(start * end)) if log else (start + end) // 2)]
        return [repr(math.sqrt(start * end) if log else (start + end) / 2)]
    raise BadInput(line, f"the {sweeper} sweeper takes {OPTIMISER_FORMS}, not glob(...)")


def check_optimiser(sweeper: str, settings: dict, search: list) -> tuple[int | None, int | None]:
    """The optuna sweeper's settings that would fail only once it runs; returns (trials, trials per batch)."""
    if sweeper != "optuna":
        return None, None
    trials, batch = settings.get("n_trials"), settings.get("n_jobs")
    for key, value in (("hydra.sweeper.n_trials", trials), ("hydra.sweeper.n_jobs", batch)):
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise BadInput(key, f"got {value!r}; expected a whole number >= 1")
    check_jobs("hydra.sweeper.n_trials", trials)
    direction = settings.get("direction")
    if isinstance(direction, (list, tuple)):
        raise BadInput(
            "hydra.sweeper.direction",
            f"got {list(direction)}: several objectives; riskplan's trials "
            f"return one (the CVaR), so give maximize or minimize",
        )
    if str(direction) not in ("maximize", "minimize"):
        raise BadInput("hydra.sweeper.direction", f"got {direction!r}; expected maximize or minimize")
    if settings.get("custom_search_space") is not None:
        raise BadInput(
            "hydra.sweeper.custom_search_space",
            f"got {settings['custom_search_space']!r}: it names a "
            f"function to run, and config strings are never code; "
            f"give the search space as overrides, e.g. "
            f"'risk.beta=interval(0.05,1)'",
        )
    rate = settings.get("max_failure_rate")
    if not isinstance(rate, (int, float)) or isinstance(rate, bool) or not 0 <= rate <= 1:
        raise BadInput("hydra.sweeper.max_failure_rate", f"got {rate!r}; expected a number from 0 to 1")
    _check_storage(settings.get("storage"))
    _check_sampler(settings.get("sampler") or {})
    sampler = str((settings.get("sampler") or {}).get("_target_", ""))
    if sampler.endswith("GridSampler"):
        for o in search:
            if o.is_interval_sweep():
                raise BadInput(
                    f"override '{o.input_line}'",
                    "the grid sampler takes choice(...), comma lists or range(...), not interval(...)",
                )
        # optuna ends the study once every point of the grid ran: more trials asked for are not run, not failed
        trials = min(trials, math.prod(len(list(o.sweep_string_iterator())) for o in search))
    return trials, batch


def _check_storage(storage) -> None:
    """hydra.sweeper.storage: a database URL Optuna can open, checked here, for it failed only at launch (exit 1,
    a sweep folder left behind)."""
    if storage is None:
        return
    from sqlalchemy.engine import make_url  # optional: optuna's dependency, with the optuna extra

    key = "hydra.sweeper.storage"
    try:
        url = make_url(str(storage))
    except Exception as err:
        raise BadInput(
            key, f"got {storage!r}: {first_line(err)}; expected a database URL, e.g. sqlite:///study.db"
        ) from None
    if url.get_backend_name() == "sqlite" and url.database not in (None, "", ":memory:"):
        folder = Path(url.database).expanduser().absolute().parent
        if not folder.is_dir():
            raise BadInput(key, f"got {storage!r}: {folder} is not a directory; give a database file in one")


def _check_sampler(sampler: dict) -> None:
    """hydra.sweeper.sampler made as Optuna's sweeper will make it (an Optuna class, hydra_safety checked that):
    settings another sampler's class does not take (`sampler._target_=optuna.samplers.RandomSampler` over TPE's
    settings) failed only at launch."""
    target = str(sampler.get("_target_", ""))
    if not target.startswith("optuna.samplers."):
        return
    try:
        instantiate(sampler)
    except Exception as err:
        cause = err.__cause__ or err
        raise BadInput(
            "hydra.sweeper.sampler",
            f"{target} cannot be made from these settings: {type(cause).__name__}: {first_line(cause)}; pick a sampler "
            f"with its own settings, e.g. hydra/sweeper/sampler=random",
        ) from None


def run_optimiser(plan: Plan, args: list[str], jobs: int | None, title: str, echo) -> Outcome:
    """Launch a sweep whose sweeper chooses the trials; then one summary row per trial it ran."""
    started = time.time()
    where = f"{plan.launcher}" + (f", {plan.workers} workers" if plan.workers else "")
    echo(f"{title} directory: {plan.sweep_dir}")
    count = f"{plan.trials} trials" if plan.trials else "trials"
    echo(
        f"{count} chosen by hydra/sweeper={plan.sweeper} over {', '.join(plan.search) or 'no key'}, each "
        f"returning its CVaR ({where})"
    )
    if plan.launcher == "joblib" and plan.workers:
        os.environ[THREADS_ENV] = str(max(1, cpu_count() // plan.workers))
    name_driver(plan.local)  # its local workers end with this process
    if plan.sweeper == "optuna":  # optuna's messages go where Hydra's go (sweep.log), not to the terminal
        try:
            import optuna  # optional: the optuna extra (hydra/sweeper=optuna installs it)

            optuna.logging.disable_default_handler()
            optuna.logging.enable_propagation()
        except ImportError:
            pass
    with SweepView(
        plan.sweep_dir,
        [],
        set(),
        title,
        total=plan.trials,
        discover=lambda since: discover_trials(plan.sweep_dir, since),
    ):
        launcher_error = launch(plan.argv, plan.sweep_dir / "sweep.log")
    trials = trial_jobs(plan.sweep_dir, started)
    summary = summarize(trials)
    if len(summary):
        summary.insert(1, "trial", [job.trial for job in trials])
    write_summary(summary, plan.sweep_dir / SUMMARY)
    failed = [(row.job, row.error or row.status) for row in summary.itertuples() if row.status != "done"]
    if failed and len(failed) == len(trials) and "No trials are completed yet" in (launcher_error or ""):
        launcher_error = None  # optuna's answer to "the best trial" when every trial failed: the failures say why
    if plan.trials and len(trials) < plan.trials and launcher_error is None:
        launcher_error = f"the sweeper ran {len(trials)} of {plan.trials} trials (see {plan.sweep_dir / 'sweep.log'})"
    resume = (
        [a for a in args if not a.startswith("hydra.sweep.dir=")]
        + [f"hydra.sweep.dir={plan.sweep_dir}"]
        + (["--jobs", str(jobs)] if jobs else [])
    )
    earlier = sum(
        1
        for job in trials
        if as_number((read_status(job.path) or {}).get("finished")) < started - 2
        and (read_status(job.path) or {}).get("status") == "done"
    )  # finished before: skipped now
    outcome = Outcome(
        plan.sweep_dir, summary, failed, len(trials) - earlier, earlier, time.time() - started, launcher_error, resume
    )
    outcome.best = best_trial(plan.sweep_dir, started)
    outcome.optimiser = True
    return outcome


def discover_trials(sweep_dir: Path, since: float) -> list[Job]:
    """The job folders Hydra wrote since `since` (each launch rewrites a job's .hydra/), as Jobs of any config."""
    found = []
    for file in override_files(Path(sweep_dir)):
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
        except BadInput as err:
            job.sha, job.invalid = "", str(err)
    return sorted(trials, key=lambda j: (j.trial, j.name))


def best_trial(sweep_dir: Path, since: float) -> str | None:
    """What the sweeper reports as its best (optuna's optimization_results.yaml), written by this launch."""
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
