"""`riskplan train`: one run, or --resume one."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import typer

from riskplan.commands.common import (
    CONFIG_DIR_HELP,
    HYDRA_FLAGS,
    MULTIRUN_FLAGS,
    PASS_THROUGH,
    TRAIN_OVERRIDES_HELP,
    bad_input_exits,
    path_option,
    with_config_dirs,
)
from riskplan.util.collector import pause_collection, resume_collection
from riskplan.util.errors import BadInput, remedy
from riskplan.util.interrupt import Interrupted
from riskplan.util.lock import hold_lock
from riskplan.util.paths import check_output_dir, claim_dir, hydra_quote, write_atomic


def register(app: typer.Typer) -> None:
    """Add `train` to the riskplan app."""
    app.command("train", context_settings=PASS_THROUGH)(bad_input_exits(train_command))


def train_command(
    overrides: list[str] | None = typer.Argument(None, help=TRAIN_OVERRIDES_HELP + CONFIG_DIR_HELP, show_default=False),
    resume: str | None = typer.Option(
        None,
        "--resume",
        help="Continue the run in RUN_DIR from its last checkpoint (also: extend a finished run "
        "with a larger train.iterations=...). Only train.iterations may be overridden.",
        metavar="RUN_DIR",
    ),
) -> None:
    """Train one experiment (default: experiment=paper_single) into outputs/runs/<timestamp>_<experiment>/."""
    pause_collection()  # the start-up only allocates; the training loop resumes it (riskplan.util.collector)
    try:
        _train_or_resume(list(overrides or []), path_option(resume, "--resume", "a run directory"))
    finally:
        resume_collection()


def _train_or_resume(overrides: list[str], resume: Path | None) -> None:
    """The train command, for its overrides and --resume."""
    from omegaconf import open_dict

    from riskplan.experiments.hydra_app import RunFailed, run_composed, run_hydra
    from riskplan.run.build import reach_lines
    from riskplan.run.compose import check_hydra_args, compose_run, parse_overrides
    from riskplan.run.run_directory import check_new_run_dir

    args = with_config_dirs(overrides)
    multirun = sorted(MULTIRUN_FLAGS & set(args))
    if multirun:
        raise BadInput(
            f"option '{multirun[0]}'",
            "riskplan train runs one experiment; run a multirun with riskplan "
            "sweep and the same overrides (e.g. riskplan sweep seed=0,1,2)",
        )
    if resume is not None:
        _resume(resume, args)
        return
    if HYDRA_FLAGS & set(args):
        check_hydra_args(args)
        run_hydra(args)
        return
    cfg, setup = compose_run(args)  # checked and built once, and run as it is: Hydra composes nothing again
    explicit = run_dir_override(parse_overrides(args))
    if explicit is None:
        out, made = claim_dir(Path("outputs") / "runs", f"_{cfg.experiment}"), True
        with open_dict(cfg.hydra):  # as if given as an override
            cfg.hydra.run.dir = str(out)
            cfg.hydra.overrides.hydra.append(f"hydra.run.dir={hydra_quote(out)}")
    else:
        out, made = explicit, not explicit.exists()
        check_new_run_dir(out, "hydra.run.dir")
        out.mkdir(parents=True, exist_ok=True)
    try:
        with hold_lock(out):
            check_new_run_dir(out, "hydra.run.dir")  # again under the lock: another process may have won the race
            typer.echo(f"run directory: {out}")
            typer.echo("\n".join(reach_lines(setup)))
            try:
                run = run_composed(cfg, setup)
            except RunFailed as err:
                typer.echo(f"error: run failed: {err} (see {out})", err=True)
                raise typer.Exit(1) from None
            _finish(out, run.failure, run.interrupted)
    except BadInput:
        if made:
            shutil.rmtree(out, ignore_errors=True)
        raise


def run_dir_override(parsed: list) -> Path | None:
    """The hydra.run.dir=... the user typed, if any, as a plain path."""
    for override in parsed:
        if override.key_or_group == "hydra.run.dir":
            value = str(override.value())
            if "${" in value:
                raise BadInput(
                    "hydra.run.dir",
                    f"got '{value}'; give a plain path (without it, riskplan train "
                    f"uses outputs/runs/<timestamp>_<experiment>)",
                )
            check_output_dir(value, "hydra.run.dir")
            return Path(value)
    return None


def _resume(run_dir: Path, args: list[str]) -> None:
    """`train --resume RUN_DIR [train.iterations=N]`."""
    from riskplan.run.compose import parse_overrides
    from riskplan.run.run_files import CHECKPOINT, CONFIG, is_run_dir

    if not run_dir.is_dir() or not is_run_dir(run_dir):
        raise BadInput(str(run_dir), "holds no run; give the directory of a riskplan train run to --resume")
    for override in parse_overrides(args):
        if override.key_or_group != "train.iterations" or override.is_sweep_override():
            raise BadInput(
                f"override '{override.input_line}'", "cannot change a resumed run; only train.iterations=N may be given"
            )
    check_output_dir(run_dir, str(run_dir))
    with hold_lock(run_dir):  # before anything is read: another process may be writing it
        if not (run_dir / CONFIG).is_file():
            raise BadInput(str(run_dir / CONFIG), "is missing; a run cannot be resumed without its config")
        _resume_locked(run_dir, args, restart=not (run_dir / CHECKPOINT).is_file())


def _resume_locked(run_dir: Path, args: list[str], restart: bool = False) -> None:
    """The resume itself, under the run directory's lock. `restart`: the run stopped before its first checkpoint, so
    it trains again from its start, in its directory: nothing of it was kept, and the same config and seed give the
    numbers of an uninterrupted run."""
    import yaml
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from riskplan.engine.step import NumericalTrouble
    from riskplan.experiments.hydra_app import write_run_status
    from riskplan.run.run_files import CONFIG, SUMMARY
    from riskplan.run.training import prepare_resume
    from riskplan.run.training import train as train_run
    from riskplan.util.progress import TrainingBar

    try:
        cfg = OmegaConf.load(run_dir / CONFIG)
        cfg.merge_with(OmegaConf.from_dotlist(args))
    except (OmegaConfBaseException, ValueError, OSError, RecursionError, yaml.YAMLError) as err:
        raise BadInput(
            str(run_dir / CONFIG),
            f"cannot be read as a config ({type(err).__name__}); it was not written by riskplan: start the run again",
        ) from None
    if restart:
        setup, finished = _restart_setup(cfg, run_dir), False
    else:
        setup, finished = prepare_resume(cfg, run_dir)  # every check of config and checkpoint, before any write
    if finished:  # nothing to do: a finished run is left exactly as it is
        typer.echo(f"already finished: {run_dir}")
        _closing_lines(json.loads((run_dir / SUMMARY).read_text()), run_dir)
        return
    typer.echo(f"restarting (no checkpoint yet): {run_dir}" if restart else f"resuming: {run_dir}")
    try:
        write_run_status(run_dir, "running", None)
        with TrainingBar() as progress:
            train_run(setup, run_dir, resume=not restart, progress=progress)
    except Interrupted as stop:
        _try_status(run_dir, str(stop), "interrupted")
        _stopped(stop, run_dir)
    except (NumericalTrouble, OSError) as err:
        message = str(err) if isinstance(err, NumericalTrouble) else _os_error(err, run_dir)
        _try_status(run_dir, message)
        typer.echo(f"error: {message}", err=True)
        raise typer.Exit(1) from None
    write_run_status(run_dir, "done", None)
    _finish(run_dir)


def _restart_setup(cfg, run_dir: Path):
    """The RunSetup of a run to train again from its start, its own files of the first attempt removed (its config,
    status and log stay). A backend with checkpoints of its own (team.backend=ray) is not restarted here."""
    from omegaconf import OmegaConf

    from riskplan.config.backends import BACKENDS
    from riskplan.run.build import build_setup
    from riskplan.run.run_files import CONFIG, remove_stale

    setup = build_setup(cfg, needs_ray=False)
    if BACKENDS[setup.params.team.backend].resume_check is not None:
        raise BadInput(str(run_dir), "has no checkpoint yet (stopped before its first one); remove it and start again")
    remove_stale(run_dir)
    write_atomic(run_dir / CONFIG, OmegaConf.to_yaml(cfg))  # with any new train.iterations
    return setup


def _stopped(stop: Interrupted, out: Path) -> None:
    """One line for a run a signal stopped (its last iteration checkpointed), and the shell's code for it."""
    typer.echo(f"{stop}; resume with riskplan train --resume {out}", err=True)
    raise typer.Exit(stop.exit_code)


def _finish(out: Path, failure: str | None = None, interrupted: Interrupted | None = None) -> None:
    """Print the one-line summary of a finished run, or why it stopped with its exit code (1, 130 or 143)."""
    from riskplan.run.run_files import STATUS, SUMMARY

    if interrupted is not None:
        _stopped(interrupted, out)
    try:
        status = json.loads((out / STATUS).read_text())
    except (OSError, ValueError):
        status = {"status": "failed", "error": "no status written"}
    if failure:  # status.json may still say running: the disk that failed refused the failure too
        status = {"status": "failed", "error": failure}
    if status.get("status") != "done":
        typer.echo(f"error: run failed: {status.get('error')} (see {out})", err=True)
        raise typer.Exit(1)
    _closing_lines(json.loads((out / SUMMARY).read_text()), out)


def _closing_lines(summary: dict, out: Path) -> None:
    """The run's one-line summary, then a warning line for each degenerate finding of its diagnosis (what the
    run learned and the likely cause), so that the last line says so."""
    from riskplan.run.evaluation import degenerate_findings

    typer.echo(summary_line(summary, out))
    for finding in degenerate_findings(summary):
        typer.echo(f"warning: degenerate run: {finding['message']}", err=True)


def _os_error(err: OSError, out: Path) -> str:
    """One line for a failure to write at run time (a full disk, a vanished directory)."""
    where = f" {err.filename}" if err.filename else ""
    return (
        f"cannot write{where}: {err.strerror or err}; the last checkpoint is kept: {remedy(err)}, then riskplan "
        f"train --resume {out}"
    )


def _try_status(out: Path, message: str, status: str = "failed") -> None:
    """Record a failure in status.json if the disk still takes it (it may be the full disk that failed)."""
    from riskplan.experiments.hydra_app import write_run_status

    try:
        write_run_status(out, status, message)
    except OSError:
        pass


def summary_line(summary: dict, out: Path) -> str:
    """One line: what ran, how long, the headline figures with 95% intervals."""
    from riskplan.engine.measures.registry import parameter_keys

    def fig(name: str) -> str:
        f = summary[name]
        return f"{f['value']:.1f} [{f['low']:.1f}, {f['high']:.1f}]"

    reached = ", ".join(f"{k} {v:.1%}" for k, v in summary["source_reached"].items())
    robots = summary.get("team_size", summary.get("robots"))  # summaries of schema 1 held the count as robots
    own = summary.get("objective", {})
    figure = {k: v for k, v in own.items() if k != "measure"}
    # the line shows the mean and CVaR at beta anyway; a measure that is neither is named with its figure
    objective = (
        "" if not own or figure in (summary["cvar"], summary["mean"]) else f"{own['measure']} {fig('objective')}, "
    )
    beta = f"{summary['beta']:g}"
    takes = "risk.beta" in parameter_keys({"measure": summary["risk"]})  # the others only report at beta
    trained = f" beta={beta}" if takes else ""
    resumed = summary.get("resumed_at")
    loop = (
        f"{summary['iterations']} iterations (resumed at {resumed}: the last {summary['iterations'] - resumed} "
        f"in {summary['wall_time']:.2f} s)"
        if resumed
        else f"{summary['iterations']} iterations in {summary['wall_time']:.2f} s"
    )
    own_measures = [r["objective_at_average"].get("measure") for r in summary.get("robots") or []]
    mixed = (  # team.risk: the robots' own measures and their sum, beside the measure the figures report
        f" (own measures: {', '.join(map(str, own_measures))}; team objective {fig('team_objective')})"
        if set(own_measures) - {summary["risk"]}
        else ""
    )
    return (
        f"{summary['experiment']} risk={summary['risk']}{trained} robots={robots}{mixed}: {loop} | eval "
        f"{summary['eval_episodes']} episodes: {objective}mean {fig('mean')}, CVaR_{beta} {fig('cvar')}, "
        f"VaR_{beta} {fig('value_at_risk')} | P(risky) {summary['risky_fraction']:.1%} | reached {reached} -> {out}"
    )
