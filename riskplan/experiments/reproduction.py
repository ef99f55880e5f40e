"""`riskplan reproduce`: every experiment of the paper's Section V, several seeds each, then the report.

    outputs/reproduce/<timestamp>/
        single/      sweep: experiment=paper_single risk=neutral,cvar seed=range(0,S)    (Figs. 1-2)
        team/        sweep: experiment=paper_team seed=range(0,S)                         (Figs. 3-4; the
                     centralized comparator is single/'s CVaR runs: W = 6000 against W_i = 2000 x 3 robots)
        wander/      sweep: experiment=paper_single train.theta0=[0,0] seed=0,1           (the landscape's
                     local optimum that theta0 = 0 falls into)
        soft_risk/   sweep: wander/'s runs with risk.schedule.kind=linear                (soft risk, CeSoR)
        frontier/    sweep: experiment=paper_single risk.beta=0.05,0.2,0.5,1.0 seed=0,1   (the risk frontier)
      beyond the paper, 5 seeds each (STUDY_SEEDS; 2 with --quick):
        measures/    sweep: experiment=paper_single risk=cvar,neutral,wang,mean_cvar,entropic (risk measures)
        policies/    sweep: experiment=paper_single train.theta0=[0,0]
                     policy.features=[signals],[signals,risky]                            (policies that see more)
        tabular/     sweep: policies/'s with policy.kind=tabular                          (a table of logits)
        hetero_team/ sweep: 8 robots on a ring from 8 start cells, constant step 0.05,
                     team.order=gradient_tracking,combine_then_adapt                      (a heterogeneous team)
        hetero_central/ sweep: the same team on a complete graph, exact averaging         (its centralized run)
        faults/      sweep: 7 robots, complete graph, robot 6 Byzantine from iteration 0,
                     team.aggregate=mean,trimmed_mean team.trim=1                         (resilient consensus)
        faults_free/ sweep: the same team without the fault                               (its reference)
        floor_plan/  sweep: experiment=floor_plan risk=neutral,cvar (a map from ROS map files)  (maps)
        landscape/   mean and CVaR on a grid of theta for the paper world
        report/      report.html, figures, report.csv
        reproduce.json   what ran, with which options, and how long each part took

The sweeps go through `riskplan sweep`'s machinery (a Hydra multirun, joblib on local cores), so re-running
with `--out` on an existing reproduction runs only what is missing. One process at a time writes a reproduction
directory (its lock is held for the whole command). `--seeds N` is bounded before anything runs: the sweeps
together may hold at most RISKPLAN_MAX_JOBS jobs (default 10,000) and an estimated RISKPLAN_MAX_HOURS of
simulation (default 24).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import os
import shlex
import signal
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import typer

from riskplan.experiments.landscape import compute_landscape
from riskplan.experiments.reporting import REPRODUCE_ROOT, build_report, check_formats
from riskplan.experiments.reporting.parallel import workers as report_workers
from riskplan.experiments.seed_comparison import print_comparison
from riskplan.experiments.study_registry import EXPERIMENTS
from riskplan.experiments.sweeping import as_job, report_outcome, run_sweep, sweep_size, warm_workers
from riskplan.experiments.timing import (
    Schedule,
    Stage,
    plan_key,
    plan_line,
    print_breakdown,
    report_seconds,
    sweep_timing,
    time_breakdown,
)
from riskplan.run import cost, maps
from riskplan.run.build import build_setup
from riskplan.run.compose import check_extras, check_override_values, compose, parse_overrides
from riskplan.util import lock
from riskplan.util.errors import BadInput
from riskplan.util.interrupt import StopSignals
from riskplan.util.limits import JOBS_ENV, STEPS_PER_SECOND, check_time, cpu_count, job_budget
from riskplan.util.paths import check_output_dir, claim_dir, write_atomic
from riskplan.util.progress import PhaseBars

# --quick: fewer iterations and evaluation episodes; the same experiments, for a first look
QUICK = ["train.iterations=60", "train.eval_episodes=20000", "train.bootstrap=200", "train.paths=10"]
# theta in [-30, 60]^2 in steps of 2 (3 with --quick): wide enough for where every reproduced run ends
LANDSCAPE = {"points": 46, "episodes": 4000, "ranges": ((-30.0, 60.0), (-30.0, 60.0))}
QUICK_LANDSCAPE = {"points": 31, "episodes": 1000, "ranges": ((-30.0, 60.0), (-30.0, 60.0))}


PAPER = ("single", "team")  # the folders of Section V itself (--paper-only): Figs. 1-4
RECORD = "reproduce.json"  # a reproduction's settings when it starts; what it did when it ends


def chosen(paper_only: bool) -> tuple:
    """The experiments a reproduction runs: all of EXPERIMENTS, or Section V's alone."""
    return tuple(e for e in EXPERIMENTS if e[0] in PAPER) if paper_only else EXPERIMENTS


def reproduce(
    out: Path | None,
    quick: bool,
    seeds: int,
    jobs: int | None = None,
    formats: str = "png,pdf",
    overrides: list[str] | None = None,
    *,
    since: float | None = None,
    paper_only: bool = False,
    batch: bool | None = None,
) -> int:
    """Run Section V (and, unless `paper_only`, the studies beyond it and the landscape), then the report,
    `seeds` seeds per condition; return the exit code (1 when a job or the report failed).

    `overrides` (plain key=value, no sweeps) apply to every experiment, e.g. train.samples=3000. `since`: when the
    command started (epoch seconds; the CLI gives its process's start), so the time breakdown includes start-up.
    `batch`: each sweep trains as batches (riskplan.experiments.sweeping.batched), the default unless `jobs` asks
    for job by job; False: job by job.
    """
    entered = time.time()
    if seeds < 1:
        raise BadInput("--seeds", f"got {seeds}; expected at least 1")
    experiments = chosen(paper_only)
    jobs_total = check_seeds(seeds, experiments)
    batch = jobs is None if batch is None else batch
    if batch and jobs is not None:
        raise BadInput(
            "--jobs", "sets the workers of a job-by-job reproduction; --batch trains each sweep as one batch"
        )
    warmed = _warm_workers(jobs, seeds, experiments)  # the workers start while the checks run (a batch's parts too)
    try:
        extra, configs, own = _check_overrides(list(overrides or []), quick)
        check_work(seeds, jobs_total, configs, list(overrides or []), experiments)
        fmts = check_formats(formats)
        report_workers()  # a bad RISKPLAN_REPORT_WORKERS is bad input now, not after the sweeps
        if out is not None:
            check_reproduction_dir(out, quick, list(overrides or []))
    except BadInput:
        stop_workers()
        raise
    target = Path(out) if out is not None else claim_dir(REPRODUCE_ROOT)
    target.mkdir(parents=True, exist_ok=True)
    checked = time.time()
    with lock.hold_lock(target, "reproduction directory"):
        return _reproduce(
            target,
            Options(quick, seeds, jobs, fmts, list(overrides or []), extra, experiments, own, batch),
            schedule_of(seeds, configs, experiments, jobs, quick, batch, list(overrides or [])),
            {"since": since, "entered": entered, "checked": checked},
            warmed,
        )


def check_reproduction_dir(out: Path, quick: bool, overrides: list[str]) -> None:
    """--out: a directory riskplan may write, new, empty or a reproduction's own (its record, its experiments'
    sweeps, landscape and report), which it completes with the same --quick and overrides; never a folder of other
    files, which its sweeps would join."""
    check_output_dir(out, "--out")
    path = Path(out)
    if not path.is_dir():
        return
    if (path / RECORD).is_file():
        _check_same_settings(out, quick, overrides)
        return
    own = {folder for folder, *_ in EXPERIMENTS} | {"landscape", "report", lock.LOCK}
    foreign = sorted(e.name for e in path.iterdir() if e.name not in own and not e.name.startswith(f".{RECORD}"))
    if foreign:
        more = f" and {len(foreign) - 1} more" if len(foreign) > 1 else ""
        raise BadInput(
            "--out",
            f"{out} holds files that are not a reproduction's ({foreign[0]}{more}); give a new or empty directory, "
            f"or a reproduction's own to complete it",
        )


def _check_same_settings(out: Path, quick: bool, overrides: list[str]) -> None:
    """A reproduction is completed only with the settings it was started with (its jobs' configs): another --quick
    or other overrides were found only once its first sweep met its jobs, after the plan, and the line said to
    give a new hydra.sweep.dir."""
    try:
        record = json.loads((Path(out) / RECORD).read_text())
        settings = (bool(record["quick"]), list(record["overrides"]))
    except (OSError, ValueError, KeyError, TypeError):
        return  # a record riskplan did not write whole: its sweeps' own checks judge the jobs
    if settings != (quick, overrides):
        again = shlex.join([*(["--quick"] if settings[0] else []), *settings[1]]) or "no overrides"
        raise BadInput(
            "--out",
            f"{out} holds a reproduction started with other settings ({again}); give a new --out, or those "
            f"settings to complete it",
        )


@dataclass(frozen=True)
class Options:
    """What a reproduction was asked for, checked."""

    quick: bool
    seeds: int
    jobs: int | None
    formats: list[str]
    overrides: list[str]  # the user's, for every experiment
    extra: list[str]  # --quick's and the user's: what every sweep gets
    experiments: tuple
    own_warnings: dict  # set-up -> the warnings it raises of its own (see _check_overrides)
    batch: bool = False  # each sweep as one batch

    @property
    def paper_only(self) -> bool:
        return len(self.experiments) < len(EXPERIMENTS)


def _warm_workers(jobs: int | None, seeds: int, experiments: tuple = EXPERIMENTS):
    """Start and warm up the sweeps' local workers in the background (riskplan.experiments.sweeping.warm_workers); returns
    the function that waits for them, or None when the sweeps run their jobs in this process (one worker)."""
    workers = _workers(jobs, seeds, experiments)
    return warm_workers(workers) if workers > 1 else None


def _workers(jobs: int | None, seeds: int, experiments: tuple) -> int:
    return min(jobs or cpu_count(), max(experiment_jobs(seeds, experiments)))


def experiment_jobs(seeds: int, experiments: tuple = EXPERIMENTS) -> list[int]:
    """Jobs of each sweep of `experiments` with this many seeds (counted from the overrides, nothing expanded)."""
    counts = []
    for _, _, experiment, most in experiments:
        counts.append(sweep_size(parse_overrides(experiment))[0] * min(seeds, most or seeds))
    return counts


def check_seeds(seeds: int, experiments: tuple = EXPERIMENTS) -> int:
    """Bad input when the sweeps with `seeds` seeds hold more jobs than RISKPLAN_MAX_JOBS; the total otherwise."""
    total = sum(experiment_jobs(seeds, experiments))
    budget = job_budget()
    if total > budget:
        raise BadInput(
            "--seeds",
            f"got {seeds}: the {len(experiments)} sweeps would hold {total} jobs, more than "
            f"the {budget} "
            f"allowed; give fewer seeds, or raise the limit with {JOBS_ENV}=<jobs>",
        )
    return total


def job_steps(cfg) -> float:
    """Trajectory-step equivalents one job of a composed config takes (riskplan.run.cost); a map's grid is the
    map's (its header, riskplan.run.maps), not world.size."""
    found = maps.read_map(cfg.world)
    width, height = (int(v) for v in cfg.world.size) if found is None else found.cells
    return cost.config_steps(cfg, width, height, len(cfg.world.sources), int(cfg.team.robots))


def check_work(
    seeds: int, total_jobs: int, configs: dict, overrides: list[str], experiments: tuple = EXPERIMENTS
) -> None:
    """Bad input when the sweeps are estimated to simulate for longer than RISKPLAN_MAX_HOURS."""
    steps = 0.0
    for (_, _, experiment, _), jobs in zip(experiments, experiment_jobs(seeds, experiments)):
        steps += jobs * job_steps(configs[setup_of(experiment)])
    what = f"reproducing with {seeds} seeds ({total_jobs} jobs" + (f", {' '.join(overrides)})" if overrides else ")")
    check_time("--seeds and overrides" if overrides else "--seeds", steps / STEPS_PER_SECOND, what)


def schedule_of(
    seeds: int,
    configs: dict,
    experiments: tuple,
    jobs: int | None,
    quick: bool,
    batch: bool = False,
    overrides: list[str] | None = None,
) -> Schedule:
    """The stages and their estimated seconds on this machine: each sweep, the landscape, the report; each as the
    last reproduction of the same plan took it, where this machine ran one."""
    model = cost.model()
    workers = _workers(jobs, seeds, experiments)
    stages = []
    for (folder, _, experiment, _), count in zip(experiments, experiment_jobs(seeds, experiments)):
        steps = [job_steps(configs[setup_of(experiment)])] * count
        seconds = model.batch_seconds(steps) if batch else model.sweep_seconds(steps, min(workers, count))
        stages.append(Stage(folder, seconds, count))
    if len(experiments) == len(EXPERIMENTS):
        grid = QUICK_LANDSCAPE if quick else LANDSCAPE
        horizon = int(next(iter(configs.values())).world.horizon)
        stages.append(Stage("landscape", model.run_seconds(grid["points"] ** 2 * grid["episodes"] * horizon)))
    stages.append(Stage("report", report_seconds(sum(stage.jobs for stage in stages))))
    plan = plan_key(
        seeds=seeds,
        experiments=[folder for folder, *_ in experiments],
        jobs=jobs,
        quick=quick,
        batch=batch,
        overrides=overrides or [],
    )
    return Schedule.remembered(stages, plan)


def _reproduce(target: Path, options: Options, schedule: Schedule, clock: dict | None = None, warmed=None) -> int:
    """The reproduction into `target`, whose lock this process holds (`clock`: when reproduce() was entered and
    when its checks ended, for the time breakdown; `warmed`: waits for the warmed-up workers, see _warm_workers).

    Ctrl-C (or SIGTERM) stops it: a sweep checkpoints its jobs and ends, and no later stage starts; during the
    report, the report stops. Either way one line says how to resume (finished jobs are skipped)."""
    started = time.time()
    warm_up: dict = {}
    record = _start(target, options, schedule)
    with StopSignals() as stop:  # a signal between or inside the stages is noted; each stage is checked below
        code, outcomes, stage = _run_sweeps(target, options, schedule, record, _waiter(warmed, warm_up), stop)
        if warm_up:
            record["warm_up"] = warm_up
        stop_workers()  # before the report, which may fork: no idle workers, nor their threads, in this process
        if stop.received is None and not options.paper_only:
            typer.echo(f"\n{schedule.header('landscape')}")
            tic = time.time()
            stage = "landscape"
            record["parts"]["landscape"] = _landscape(target / "landscape", options.quick, list(options.overrides))
            schedule.finished("landscape", time.time() - tic, whole="skipped" not in record["parts"]["landscape"])
        signum = stop.received
    if signum is not None:
        return _stopped(target, options, record, signal.Signals(signum), stage, outcomes)
    tic = time.time()
    print_comparison(outcomes)
    record["parts"]["comparison"] = {"seconds": round(time.time() - tic, 2)}
    typer.echo(f"\n{schedule.header('report')}")
    tic = time.time()
    try:
        code = max(code, _report(target, options, record))
    except KeyboardInterrupt:  # the report's forked children ignore Ctrl-C; this process stops drawing
        return _stopped(target, options, record, signal.SIGINT, "report", outcomes)
    schedule.finished("report", time.time() - tic, whole=code == 0)
    record["seconds"] = round(time.time() - started, 2)
    total = _breakdown(record, clock or {}, started, options)
    write_atomic(target / RECORD, json.dumps(record, indent=2))
    estimated = schedule.total
    typer.echo(f"reproduced in {total:.1f} s (estimated {cost.say(estimated).removeprefix('about ')}): {target}")
    if code:
        typer.echo(
            f"to retry what did not finish (finished jobs are skipped): riskplan reproduce {_again(target, options)}",
            err=True,
        )
    return code


def _stopped(target: Path, options: Options, record: dict, signum: signal.Signals, stage: str, outcomes) -> int:
    """A reproduction a signal stopped during `stage`: reproduce.json says so, one line says what is kept and how to
    resume; the shell's code for the signal (130 for Ctrl-C)."""
    unfinished = sum(len(outcome.failed) for outcome in outcomes if outcome.interrupted is not None)
    kept = f": {unfinished} job{'s' if unfinished != 1 else ''} did not finish (each keeps its last checkpoint)"
    record["interrupted"] = {"signal": signum.name, "stage": stage}
    write_atomic(target / RECORD, json.dumps(record, indent=2))
    typer.echo(
        f"error: interrupted by {signum.name} during {stage}{kept if unfinished else ''}; resume with riskplan "
        f"reproduce {_again(target, options)} (finished jobs are skipped)",
        err=True,
    )
    return 128 + signum


def _waiter(warmed, warm_up: dict):
    """What runs before each sweep's launch: the first time, wait for the warmed-up workers (when there are any)
    and note in `warm_up` how many there are, their start-up seconds and how long the wait took."""

    def wait_for_workers() -> None:
        if warmed is not None and not warm_up:
            tic = time.time()
            workers = warmed()
            warm_up.update(
                {
                    "workers": len(workers),
                    "pids": [pid for pid, _ in workers],
                    "seconds": [round(s, 2) for _, s in workers],
                    "waited": round(time.time() - tic, 2),
                }
            )

    return wait_for_workers


def _start(target: Path, options: Options, schedule: Schedule) -> dict:
    """Say what runs where and how long it should take; the record reproduce.json starts from, written now."""
    what = ("quick" if options.quick else "full") + (", Section V only" if options.paper_only else "")
    typer.echo(f"reproduction directory: {target} ({what}, {options.seeds} seeds)")
    workers = None if options.batch else _workers(options.jobs, options.seeds, options.experiments)
    typer.echo(plan_line(schedule, workers))
    record = {
        "quick": options.quick,
        "paper_only": options.paper_only,
        "batched": options.batch,
        "seeds": options.seeds,
        "overrides": list(options.overrides),
        "started": dt.datetime.now().isoformat(timespec="seconds"),
        "estimate": {stage.name: round(stage.estimate, 1) for stage in schedule.stages},
        "parts": {},
    }
    write_atomic(target / RECORD, json.dumps(record, indent=2))  # its settings, should it stop before the end
    return record


def _run_sweeps(
    target: Path, options: Options, schedule: Schedule, record: dict, before_launch, stop: StopSignals
) -> tuple[int, list, str]:
    """Every experiment's sweep into its folder, each noted in record["parts"], until a signal stops one (`stop`
    noted it, or the sweep was interrupted); the exit code, the outcomes and the last stage started."""
    code = 0
    outcomes = []
    seeds = options.seeds
    stage = "the start"
    for folder, what, experiment, most in options.experiments:
        if stop.received is not None:
            break
        stage = f"{folder}/"
        args = [*experiment, f"seed=range(0,{min(seeds, most or seeds)})", *_not_set_by(experiment, options.extra)]
        typer.echo(f"\n{schedule.header(folder)}\n{what}\n  riskplan sweep {' '.join(_shell(a) for a in args)}")
        tic = time.time()
        outcome = run_sweep(
            args,
            options.jobs,
            sweep_dir=target / folder,
            title=folder,
            before_launch=before_launch,
            expected=options.own_warnings.get(setup_of(experiment), frozenset()),
            batch=options.batch,
        )
        toc = time.time()
        schedule.finished(folder, toc - tic, whole=not outcome.skipped and not outcome.failed)
        outcomes.append(outcome)
        code = max(code, report_outcome(outcome, folder, hint=False))
        record["parts"][folder] = {
            "overrides": args,
            "jobs": len(outcome.summary),
            "ran": outcome.ran,
            "skipped": outcome.skipped,
            "failed": len(outcome.failed),
            "seconds": round(outcome.seconds, 2),
            "wall": round(toc - tic, 2),
            "timing": sweep_timing(outcome, tic, toc),
        }
        if outcome.interrupted is not None and stop.received is None:
            stop.received = outcome.interrupted  # the sweep's own handler took the signal
    return code, outcomes, stage


def _report(target: Path, options: Options, record: dict) -> int:
    """The report of the whole reproduction; its exit code (1 when it failed: the runs stay, and a line says how to
    try it again)."""
    tic = time.time()
    try:
        with PhaseBars() as progress:
            page = build_report([target], target / "report", options.formats, progress=progress)
        typer.echo(f"report: {page}")
        record["parts"]["report"] = {"seconds": round(time.time() - tic, 2), "page": str(page)}
    except BadInput as err:  # what the runs left cannot be reported (none finished): the input was fine, exit 1
        typer.echo(f"error: no report: {err}", err=True)
        return 1
    except Exception as err:
        typer.echo(
            f"error: the report failed: {type(err).__name__}: {err} "
            f"(the runs are in {target}; try riskplan report {target})",
            err=True,
        )
        return 1
    return 0


def _breakdown(record: dict, clock: dict, started: float, options: Options) -> float:
    """Print where the time went and add it to the record; the total seconds (from the command's start when the
    breakdown has it, else from `started`)."""
    total = record["seconds"]
    try:  # never fails the reproduction: it only says where the time went
        folders = [folder for folder, *_ in options.experiments]
        record["breakdown"] = time_breakdown(record, clock, started, folders)
        total = record["breakdown"]["total"]  # from the command's start: the one total both lines give
        print_breakdown(record["breakdown"])
    except Exception as err:
        typer.echo(f"(no time breakdown: {type(err).__name__}: {err})", err=True)
    return total


def _again(target: Path, options: Options) -> str:
    """The arguments of `riskplan reproduce` that complete this reproduction."""
    again = [
        "--out",
        str(target),
        *(["--quick"] if options.quick else []),
        *(["--paper-only"] if options.paper_only else []),
        "--seeds",
        str(options.seeds),
        *options.overrides,
    ]
    return shlex.join(again)


def _check_overrides(overrides: list[str], quick: bool) -> tuple[list[str], dict, dict]:
    """The overrides every sweep gets (--quick's, then the user's), checked on both set-ups before anything runs;
    the composed config of each set-up (by its experiment=... override); and the warnings each set-up raises of
    its own (hetero_team's constant step breaks Assumption 6 on purpose): its sweep does not repeat those, while a
    warning the user's overrides bring still prints."""
    for override in parse_overrides(overrides):
        if override.is_sweep_override() or override.is_hydra_override():
            raise BadInput(
                f"override '{override.input_line}'",
                "reproduce takes plain key=value overrides for every experiment; run a grid with riskplan sweep",
            )
        if override.key_or_group in ("seed", "experiment"):
            raise BadInput(
                f"override '{override.input_line}'",
                "is set by reproduce; use --seeds N, or riskplan sweep for other experiments",
            )
    extra = [*_not_set_by(overrides, QUICK if quick else []), *overrides]  # the user's value over --quick's
    configs, own = {}, {}
    for _, _, experiment, _ in EXPERIMENTS:  # each set-up once, not per experiment: its plain overrides
        setup = setup_of(experiment)
        if setup not in configs:
            with warnings.catch_warnings(record=True) as caught:  # a set-up's warnings print with its sweep
                warnings.simplefilter("always")
                configs[setup] = _set_up([*setup, *_not_set_by(experiment, extra)])
                own[setup] = frozenset()
                if caught:
                    caught.clear()
                    _set_up(list(setup))
                    own[setup] = frozenset(str(w.message) for w in caught)
    return extra, configs, own


def _set_up(overrides: list[str]):
    """A set-up's config, typed and checked (its RunSetup built), as a sweep's planning makes a job's: its keys set
    as data on its groups' composition, which the sweeps reuse (sweeping.as_job). Through compose() when that
    needs Hydra or finds the config bad: compose() names what is wrong."""
    check_override_values(parse_overrides(overrides))
    check_extras(overrides)
    job = as_job(overrides)
    if job is not None:
        try:
            build_setup(job.params)
            return job.params
        except BadInput:
            pass
    return compose(overrides)


def setup_of(experiment: list[str]) -> tuple[str, ...]:
    """An experiment's set-up: its overrides without the swept ones (one job's config but for the swept keys)."""
    return tuple(o.input_line for o in parse_overrides(experiment) if not o.is_sweep_override())


def _not_set_by(experiment: list[str], extra: list[str]) -> list[str]:
    """The extra overrides whose key the experiment does not set itself (frontier/ sweeps risk.beta, whatever the
    user gave for the paper's set-ups)."""
    own = {o.key_or_group for o in parse_overrides(experiment)}
    return [o.input_line for o in parse_overrides(extra) if o.key_or_group not in own]


def _landscape(out: Path, quick: bool, overrides: list[str]) -> dict:
    """The objective landscape of the paper world (skipped when it is already there)."""
    grid = QUICK_LANDSCAPE if quick else LANDSCAPE
    done = out / "status.json"
    try:
        finished = json.loads(done.read_text()).get("status") == "done"
    except (OSError, ValueError, AttributeError):
        finished = False
    if finished:
        typer.echo(f"\nlandscape: {out} (already there)")
        return {"skipped": True, **grid}
    typer.echo(
        f"\nobjective landscape: {grid['points']}x{grid['points']} theta grid, {grid['episodes']} "
        f"episodes per point -> {out}"
    )
    tic = time.time()
    args = ["experiment=paper_single", *overrides]
    compute_landscape(compose(args), out, overrides=args, **grid)
    return {"seconds": round(time.time() - tic, 2), **grid}


def stop_workers() -> None:
    """End the sweeps' joblib (loky) worker processes now: idle once every job has finished and written its files
    (left alone, they are shut down gracefully at interpreter exit, which kept the command waiting after the last
    line here), or still warming up when the input turned out bad.

    The workers are killed here, then the executor shut down: loky's own `kill_workers=True` cancels the queued work
    from its manager thread and then fails on a work item submitted just before (a KeyError traceback from
    "ExecutorManagerThread" under a bad input's line, seen once in CI); a killed worker is a broken pool to loky,
    which fails the pending work quietly."""
    module = sys.modules.get("joblib.externals.loky.reusable_executor")  # absent: no sweep ran in worker processes
    executor = getattr(module, "_executor", None)
    if executor is None:
        return
    for pid in list(getattr(executor, "_processes", None) or {}):
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)
    executor.shutdown(wait=False)


def _shell(arg: str) -> str:
    """Quote an argument for display as a shell command."""
    return f"'{arg}'" if any(c in arg for c in "()[]{} *?$") else arg
