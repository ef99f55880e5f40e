"""`riskplan reproduce`: every experiment of the paper's Section V, several seeds each, then the report.

    outputs/reproduce/<timestamp>/
        single/      sweep: experiment=paper_single risk=neutral,cvar seed=range(0,S)    (Figs. 1-2)
        team/        sweep: experiment=paper_team seed=range(0,S)                         (Figs. 3-4; the
                     centralized comparator is single/'s CVaR runs: W = 6000 against W_i = 2000 x 3 robots)
        wander/      sweep: experiment=paper_single train.theta0=[0,0] seed=0,1           (the landscape's
                     local optimum that theta0 = 0 falls into)
        soft_risk/   sweep: wander/'s runs with risk.schedule.kind=linear                (soft risk, CeSoR)
        frontier/    sweep: experiment=paper_single risk.beta=0.05,0.2,0.5,1.0 seed=0,1   (the risk frontier)
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

import datetime as dt
import json
import sys
import time
from pathlib import Path

import typer

from riskplan.errors import BadInput
from riskplan.reporting import REPRODUCE_ROOT

SEEDS = 10
QUICK_SEEDS = 2
# (folder, what it reproduces, overrides without the seeds, at most this many seeds or None for all)
EXPERIMENTS = (
    ("single", "Figs. 1-2: one robot, risk-neutral vs CVaR (W = 6000)",
     ["experiment=paper_single", "risk=neutral,cvar"], None),
    ("team", "Figs. 3-4: three robots on a line graph (W_i = 2000), vs the centralized CVaR runs of single/",
     ["experiment=paper_team"], None),
    # theta0 = 0 falls into the landscape's other optimum: wander, reaching no source; two seeds show it
    ("wander", "The landscape's local optimum: CVaR from theta0 = (0, 0), which wanders and reaches no source",
     ["experiment=paper_single", "train.theta0=[0,0]"], 2),
    # soft risk (CeSoR): the same start, the gradient's CVaR level falling linearly from 1 to beta; vs wander/
    ("soft_risk", "Beyond the paper: soft risk from theta0 = (0, 0), CVaR level linear from 1 to beta (vs wander/)",
     ["experiment=paper_single", "train.theta0=[0,0]", "risk.schedule.kind=linear"], 2),
    # with single/'s beta = 0.1 runs, the report's risk frontier (beta = 1 is the mean, through the CVaR gradient)
    ("frontier", "Beyond the paper: the risk frontier, CVaR policies at beta = 0.05, 0.2, 0.5, 1",
     ["experiment=paper_single", "risk.beta=0.05,0.2,0.5,1.0"], 2),
)
# --quick: fewer iterations and evaluation episodes; the same experiments, for a first look
QUICK = ["train.iterations=60", "train.eval_episodes=20000", "train.bootstrap=200", "train.paths=10"]
# theta in [-30, 60]^2 in steps of 2 (3 with --quick): wide enough for where every reproduced run ends
LANDSCAPE = {"points": 46, "episodes": 4000, "ranges": ((-30.0, 60.0), (-30.0, 60.0))}
QUICK_LANDSCAPE = {"points": 31, "episodes": 1000, "ranges": ((-30.0, 60.0), (-30.0, 60.0))}


def reproduce(out: Path | None = None, quick: bool = False, seeds: int | None = None, jobs: int | None = None,
              formats: str = "png,pdf", overrides: list[str] | None = None) -> int:
    """Run Section V and the report; return the exit code (1 when a job or the report failed).

    `overrides` (plain key=value, no sweeps) apply to every experiment, e.g. train.samples=3000.
    """
    from riskplan import lock
    from riskplan.paths import check_output_dir, claim_dir
    from riskplan.reporting import check_formats

    seeds = seeds or (QUICK_SEEDS if quick else SEEDS)
    if seeds < 1:
        raise BadInput("--seeds", f"got {seeds}; expected at least 1")
    jobs_total = check_seeds(seeds)
    extra, configs = _check_overrides(list(overrides or []), quick)
    check_work(seeds, jobs_total, configs, list(overrides or []))
    fmts = check_formats(formats)
    if out is not None:
        check_output_dir(out, "--out")
    target = Path(out) if out is not None else claim_dir(REPRODUCE_ROOT)
    target.mkdir(parents=True, exist_ok=True)
    with lock.hold(target, "reproduction directory"):
        return _reproduce(target, quick, seeds, jobs, fmts, list(overrides or []), extra)


def experiment_jobs(seeds: int) -> list[int]:
    """Jobs of each sweep of EXPERIMENTS with this many seeds (counted from the overrides, nothing expanded)."""
    from riskplan.config import parse_overrides
    from riskplan.sweeping import sweep_size

    counts = []
    for _, _, experiment, most in EXPERIMENTS:
        counts.append(sweep_size(parse_overrides(experiment))[0] * min(seeds, most or seeds))
    return counts


def check_seeds(seeds: int) -> int:
    """Bad input when the sweeps with `seeds` seeds hold more jobs than RISKPLAN_MAX_JOBS; the total otherwise."""
    from riskplan.limits import JOBS_ENV, job_budget

    total = sum(experiment_jobs(seeds))
    budget = job_budget()
    if total > budget:
        raise BadInput("--seeds", f"got {seeds}: the {len(EXPERIMENTS)} sweeps would hold {total} jobs, more than "
                                  f"the {budget} "
                                  f"allowed; give fewer seeds, or raise the limit with {JOBS_ENV}=<jobs>")
    return total


def job_steps(cfg) -> float:
    """Trajectory-step equivalents one job takes (riskplan.budget's estimate of a run: training, evaluation,
    bootstrap, logging)."""
    from riskplan import budget

    width, height = (int(v) for v in cfg.world.size)
    sizes = budget.sizes_of(cfg, width, height, len(cfg.world.sources), int(cfg.team.robots))
    return sum(amount for amount, _, _ in budget.estimate(sizes)[1])


def check_work(seeds: int, total_jobs: int, configs: dict, overrides: list[str]) -> None:
    """Bad input when the sweeps are estimated to simulate for longer than RISKPLAN_MAX_HOURS."""
    from riskplan.limits import STEPS_PER_SECOND, check_time

    steps = 0.0
    for (_, _, experiment, _), jobs in zip(EXPERIMENTS, experiment_jobs(seeds)):
        steps += jobs * job_steps(configs[experiment[0]])
    what = f"reproducing with {seeds} seeds ({total_jobs} jobs" + (f", {' '.join(overrides)})" if overrides else ")")
    check_time("--seeds and overrides" if overrides else "--seeds", steps / STEPS_PER_SECOND, what)


def _reproduce(target: Path, quick: bool, seeds: int, jobs: int | None, fmts, overrides: list[str],
               extra: list[str]) -> int:
    """The reproduction into `target`, whose lock this process holds."""
    from riskplan.paths import write_atomic
    from riskplan.reporting import build_report
    from riskplan.sweeping import report_outcome, run_sweep

    started = time.time()
    typer.echo(f"reproduction directory: {target} ({'quick' if quick else 'full'}, {seeds} seeds)")
    record = {"quick": quick, "seeds": seeds, "overrides": list(overrides or []), "started": dt.datetime.now().isoformat(timespec="seconds"),
              "parts": {}}
    code = 0
    outcomes = []
    for folder, what, experiment, most in EXPERIMENTS:
        args = [*experiment, f"seed=range(0,{min(seeds, most or seeds)})", *_not_set_by(experiment, extra)]
        typer.echo(f"\n{what}\n  riskplan sweep {' '.join(_shell(a) for a in args)}")
        outcome = run_sweep(args, jobs, sweep_dir=target / folder, title=folder)
        outcomes.append(outcome)
        code = max(code, report_outcome(outcome, folder, hint=False))
        record["parts"][folder] = {"overrides": args, "jobs": len(outcome.summary), "ran": outcome.ran,
                                   "skipped": outcome.skipped, "failed": len(outcome.failed),
                                   "seconds": round(outcome.seconds, 2)}
    record["parts"]["landscape"] = _landscape(target / "landscape", quick, list(overrides or []))
    _print_comparison(outcomes)
    tic = time.time()
    try:
        page = build_report([target], target / "report", fmts)
        typer.echo(f"report: {page}")
        record["parts"]["report"] = {"seconds": round(time.time() - tic, 2), "page": str(page)}
    except BadInput:
        raise
    except Exception as err:  # noqa: BLE001 - the runs are safe; say what failed
        typer.echo(f"error: the report failed: {type(err).__name__}: {err} "
                   f"(the runs are in {target}; try riskplan report {target})", err=True)
        code = 1
    record["seconds"] = round(time.time() - started, 2)
    write_atomic(target / "reproduce.json", json.dumps(record, indent=2))
    typer.echo(f"reproduced in {record['seconds']:.0f} s: {target}")
    if code:
        import shlex

        again = ["--out", str(target), *(["--quick"] if quick else []), "--seeds", str(seeds), *(overrides or [])]
        typer.echo(f"to retry what did not finish (finished jobs are skipped): riskplan reproduce "
                   f"{shlex.join(again)}", err=True)
    return code


def _check_overrides(overrides: list[str], quick: bool) -> tuple[list[str], dict]:
    """The overrides every sweep gets (--quick's, then the user's), checked on both set-ups before anything runs;
    and the composed config of each set-up (by its experiment=... override)."""
    from riskplan.config import compose, parse_overrides

    for override in parse_overrides(overrides):
        if override.is_sweep_override() or override.is_hydra_override():
            raise BadInput(f"override '{override.input_line}'", "reproduce takes plain key=value overrides for "
                                                                "every experiment; run a grid with riskplan sweep")
        if override.key_or_group in ("seed", "experiment"):
            raise BadInput(f"override '{override.input_line}'", "is set by reproduce; use --seeds N, or riskplan "
                                                                "sweep for other experiments")
    extra = [*(QUICK if quick else []), *overrides]
    configs = {}
    for setup in dict.fromkeys(base[0] for _, _, base, _ in EXPERIMENTS):  # each set-up once, not per experiment
        configs[setup] = compose([setup, *extra])
    return extra, configs


def _not_set_by(experiment: list[str], extra: list[str]) -> list[str]:
    """The extra overrides whose key the experiment does not set itself (frontier/ sweeps risk.beta, whatever the
    user gave for the paper's set-ups)."""
    from riskplan.config import parse_overrides

    own = {o.key_or_group for o in parse_overrides(experiment)}
    return [o.input_line for o in parse_overrides(extra) if o.key_or_group not in own]


def _landscape(out: Path, quick: bool, overrides: list[str]) -> dict:
    """The objective landscape of the paper world (skipped when it is already there)."""
    from riskplan.config import compose
    from riskplan.reporting.landscape import compute_landscape

    grid = QUICK_LANDSCAPE if quick else LANDSCAPE
    done = out / "status.json"
    try:
        finished = json.loads(done.read_text()).get("status") == "done"
    except (OSError, ValueError, AttributeError):
        finished = False
    if finished:
        typer.echo(f"\nlandscape: {out} (already there)")
        return {"skipped": True, **grid}
    typer.echo(f"\nobjective landscape: {grid['points']}x{grid['points']} theta grid, {grid['episodes']} "
               f"episodes per point -> {out}")
    tic = time.time()
    args = ["experiment=paper_single", *overrides]
    compute_landscape(compose(args), out, overrides=args, **grid)
    return {"seconds": round(time.time() - tic, 2), **grid}


def _print_comparison(outcomes) -> None:
    """Across seeds: the mean and CVaR of each condition (the paper's claims in four lines)."""
    import pandas as pd
    from rich.console import Console
    from rich.table import Table

    frames = []
    for outcome in outcomes:
        frame = outcome.summary.copy()
        frame["sweep"] = outcome.sweep_dir.name
        frames.append(frame)
    if not frames:
        return
    data = pd.concat(frames, ignore_index=True)
    data = data[data.status == "done"]
    if data.empty:
        return
    if "risk" not in data:
        data["risk"] = "cvar"
    data["risk"] = data["risk"].fillna("cvar")
    table = Table(title="Section V across seeds (mean ± sd of the per-seed figures on the evaluation episodes)",
                  title_justify="left", show_edge=False, pad_edge=False)
    for column in ("set-up", "objective", "seeds", "mean", "CVaR", "VaR"):
        table.add_column(column, justify="left" if column in ("set-up", "objective") else "right")
    for (sweep, risk, beta), group in data.groupby(["sweep", "risk", "beta"], sort=False):
        setup = {"team": "3 robots, line graph", "wander": "1 robot, θ0 = (0, 0)",
                 "soft_risk": "1 robot, θ0 = (0, 0), soft risk (linear)"}.get(sweep, "1 robot (centralized)")
        table.add_row(setup, f"CVaR_{beta:g}" if risk == "cvar" else "mean (risk-neutral)", str(len(group)),
                      *(f"{group[c].mean():.1f} ± {group[c].std(ddof=1) if len(group) > 1 else 0:.1f}"
                        for c in ("mean", "cvar", "value_at_risk")))
    (Console() if sys.stdout.isatty() else Console(width=250)).print(table)


def _shell(arg: str) -> str:
    """Quote an argument for display as a shell command."""
    return f"'{arg}'" if any(c in arg for c in "()[]{} *?$") else arg
