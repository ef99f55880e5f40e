"""`riskplan train`: one run, or --resume one."""

from __future__ import annotations

import contextlib
import json
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

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
from riskplan.util.errors import BadInput
from riskplan.util.interrupt import Interrupted
from riskplan.util.lock import LOCK, hold_lock
from riskplan.util.paths import check_output_dir, claim_dir, hydra_quote, write_atomic

if TYPE_CHECKING:  # the run's outcome, imported with the run itself
    from riskplan.experiments.hydra_app import SingleRun

OVERRIDES = ".hydra/overrides.yaml"  # Hydra's record of a run's overrides (riskplan train writes it through Hydra)
HYDRA_RECORD = ".hydra/hydra.yaml"  # Hydra's own config of the run, whose hydra.overrides.task lists them again


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

    from riskplan.experiments.hydra_app import RunFailed, SingleRun, run_composed, run_hydra
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
                run, started = run_composed(cfg, setup), True
            except RunFailed as err:  # before the task: Hydra could not write the run's .hydra/ (a full disk)
                run, started = SingleRun(failure=str(err), write_error=err.write_error), False
            if run.failure and (not started or run.write_error) and _untrained(out):  # nothing of it to keep
                _undo_start(out, made)
                typer.echo(f"error: run failed: {_start_failure(run, out, made)}", err=True)
                raise typer.Exit(1)
            _finish(out, run.failure, run.interrupted)
    except BadInput:
        if made:
            shutil.rmtree(out, ignore_errors=True)
        raise


def _untrained(out: Path) -> bool:
    """Whether a run that failed trained nothing: no checkpoint, and no iteration whole in its run.mcap."""
    from riskplan.run.record import log_header
    from riskplan.run.run_files import CHECKPOINT, RUN_LOG

    if (out / CHECKPOINT).exists():
        return False
    try:
        return not (out / RUN_LOG).is_file() or log_header(out / RUN_LOG)[1] == 0
    except BadInput:  # cut short inside its magic bytes
        return True


def _undo_start(out: Path, made: bool) -> None:
    """Remove what a run that trained nothing wrote, so that no half-written run is left: the directory this
    command made, or what it wrote into the empty one it was given (the writers' lock file aside)."""
    if made:
        shutil.rmtree(out, ignore_errors=True)
        return
    for entry in out.iterdir():
        with contextlib.suppress(OSError):
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            elif entry.name != LOCK:
                entry.unlink()


def _start_failure(run: SingleRun, out: Path, made: bool) -> str:
    """Why a run that trained nothing failed, and that its files are gone: what to do is to train it again."""
    from riskplan.experiments.hydra_app import write_failure

    gone = f"nothing was trained, so {out} was {'removed' if made else 'emptied again'}"
    if run.write_error is not None:
        return f"{write_failure(run.write_error, out, 'riskplan train again')} ({gone})"
    return f"{run.failure} ({gone})"


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
    from riskplan.run.run_files import CHECKPOINT, CONFIG, is_run_dir, other_output

    other = other_output(run_dir) if run_dir.is_dir() else None
    if other is not None:
        raise BadInput(
            str(run_dir), f"holds {other}, not a run; give the directory of a riskplan train run to --resume"
        )
    if run_dir.is_dir() and {entry.name for entry in run_dir.iterdir()} == {LOCK}:  # killed as it claimed it
        raise BadInput(
            str(run_dir),
            f"holds no run: its run was stopped before it wrote its config, so there is nothing to resume; train it "
            f"again with riskplan train ... hydra.run.dir={hydra_quote(str(run_dir))}",
        )
    if not run_dir.is_dir() or not is_run_dir(run_dir):
        raise BadInput(str(run_dir), "holds no run; give the directory of a riskplan train run to --resume")
    _refuse_sweep_job(run_dir)
    flags = sorted(HYDRA_FLAGS & set(args))
    if flags:
        raise BadInput(
            f"option '{flags[0]}'",
            f"riskplan train --resume passes no Hydra flag through; the run's config is {run_dir / CONFIG}",
        )
    change = _resumed_change(args)
    check_output_dir(run_dir, str(run_dir))
    with hold_lock(run_dir):  # before anything is read: another process may be writing it
        if not (run_dir / CONFIG).is_file():
            raise BadInput(str(run_dir / CONFIG), "is missing; a run cannot be resumed without its config")
        _resume_locked(run_dir, change, restart=not (run_dir / CHECKPOINT).is_file())


def _refuse_sweep_job(run_dir: Path) -> None:
    """A sweep's job folder is the sweep's: its status.json holds the sweep's fingerprint of the job (config_sha),
    which a resume here would drop, and the sweep would then refuse the folder. Re-running the sweep resumes it."""
    from riskplan.run.run_files import STATUS

    try:
        status = json.loads((run_dir / STATUS).read_text())
    except (OSError, ValueError):
        return
    if isinstance(status, dict) and "config_sha" in status:
        raise BadInput(
            str(run_dir),
            f"is a job of the sweep in {run_dir.parent}, which resumes its own jobs: run riskplan sweep again with "
            f"that sweep's overrides and hydra.sweep.dir={run_dir.parent} (it skips the finished jobs and resumes "
            f"the others)",
        )


def _resumed_change(args: list[str]) -> dict:
    """The train.iterations=N a resume was given, as a config to merge (empty without one), its value as Hydra
    reads it for a fresh run (040 is 40, not YAML's octal 32); BadInput for any other override."""
    from riskplan.run.compose import parse_overrides

    change: dict = {}
    for override in parse_overrides(args):
        line = f"override '{override.input_line}'"
        if override.key_or_group != "train.iterations" or override.is_sweep_override():
            raise BadInput(line, "cannot change a resumed run; only train.iterations=N may be given")
        if override.is_delete():
            raise BadInput(line, "cannot delete a key of a resumed run; only train.iterations=N may be given")
        if override.is_add():  # ++ sets the key whether it is there or not, as = does here
            raise BadInput(line, "+ adds a key, and train.iterations is in every run's config: give train.iterations=N")
        change = {"train": {"iterations": override.value()}}
    return change


def _resume_locked(run_dir: Path, change: dict, restart: bool = False) -> None:
    """The resume itself, under the run directory's lock, with the `change` of its config (train.iterations=N).
    `restart`: the run has no checkpoint (it stopped before its first one, or it was removed), so it trains again
    from its start, in its directory: nothing of it can be continued, and the same config and seed give the
    numbers of an uninterrupted run, those it logged included."""
    import yaml
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from riskplan.engine.step import NumericalTrouble
    from riskplan.experiments.hydra_app import write_failure, write_run_status
    from riskplan.run.run_files import CONFIG, SUMMARY
    from riskplan.run.training import prepare_resume
    from riskplan.run.training import train as train_run
    from riskplan.util.progress import TrainingBar

    try:
        cfg = OmegaConf.load(run_dir / CONFIG)
        longer = cfg.copy()
        longer.merge_with(change)
        extended = OmegaConf.select(longer, "train.iterations") != OmegaConf.select(cfg, "train.iterations")
    except (OmegaConfBaseException, ValueError, OSError, RecursionError, yaml.YAMLError) as err:
        raise BadInput(
            str(run_dir / CONFIG),
            f"cannot be read as a config ({type(err).__name__}); it was not written by riskplan: start the run again",
        ) from None
    if not cfg:  # Hydra writes it in place: a full disk or a kill as the run began left it empty
        raise BadInput(str(run_dir / CONFIG), "is empty: the run never started; remove the directory and train again")
    if extended and not restart:  # a restart trains every iteration with the new value
        _refuse_following_keys(cfg, longer, run_dir)
    cfg = longer
    if restart:
        (setup, logged), finished = _restart_setup(cfg, run_dir), False
    else:  # every check of config and checkpoint, before any write
        (setup, finished), logged = prepare_resume(cfg, run_dir), 0
    if finished:  # nothing to do: a finished run is left exactly as it is
        typer.echo(f"already finished: {run_dir}")
        _closing_lines(json.loads((run_dir / SUMMARY).read_text()), run_dir)
        return
    if extended:
        _record_iterations(run_dir, setup.params.train.iterations)
    start = f"restarting (no checkpoint yet): {run_dir}" if restart else f"resuming: {run_dir}"
    if logged:  # a checkpoint removed by hand, or none written yet: what becomes of the iterations logged
        start += f"; the {logged} iterations its run.mcap holds are trained again from the start, to the same numbers"
    typer.echo(start)
    try:
        write_run_status(run_dir, "running", None)
        with TrainingBar() as progress:
            train_run(setup, run_dir, resume=not restart, progress=progress)
    except Interrupted as stop:
        _try_status(run_dir, str(stop), "interrupted")
        _stopped(stop, run_dir)
    except (NumericalTrouble, OSError) as err:
        kept = f"riskplan train --resume {run_dir} (the last checkpoint is kept)"
        message = str(err) if isinstance(err, NumericalTrouble) else write_failure(err, run_dir, kept)
        _try_status(run_dir, message)
        typer.echo(f"error: {message}", err=True)
        raise typer.Exit(1) from None
    write_run_status(run_dir, "done", None)
    _finish(run_dir)


def _refuse_following_keys(cfg, longer, run_dir: Path) -> None:
    """BadInput when a key of the run's config follows train.iterations (risk.schedule.iterations:
    ${train.iterations}), so that `longer`, the config extended, has another value of it: the run would go on with
    a value its trained iterations did not have (the schedule stretched), a run of neither config, so it cannot be
    extended; a new run can have the new value."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from riskplan.config.typed import register_metres
    from riskplan.run.run_directory import differing
    from riskplan.run.run_files import CONFIG

    register_metres()  # a run placed in metres saved ${metres:x,y}
    try:
        follows = differing(OmegaConf.to_container(cfg, resolve=True), OmegaConf.to_container(longer, resolve=True))
    except (OmegaConfBaseException, ValueError, KeyError, TypeError, RecursionError):  # the build names what fails
        return
    follows = [key for key in follows if key != "train.iterations"]
    if follows:
        more = f" (and {len(follows) - 1} more)" if len(follows) > 1 else ""
        raise BadInput(
            follows[0],
            f"follows train.iterations in {run_dir / CONFIG}{more}, so extending the run would change it for the "
            f"iterations trained already; this run cannot be extended: train a new run with "
            f"train.iterations={longer.train.iterations}",
        )


def _record_iterations(run_dir: Path, iterations: int) -> None:
    """An extended run's .hydra/overrides.yaml and hydra.yaml's hydra.overrides.task say its new train.iterations
    (older values of it dropped), as its config does: replayed, the overrides give the run's config. The Python
    API's runs have none; Hydra's files are left as they are where they do not hold the lists Hydra writes."""
    import yaml

    def read(name: str):
        try:
            return yaml.safe_load((run_dir / name).read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, yaml.YAMLError):
            return None

    def extended(listed) -> list[str] | None:
        if not isinstance(listed, list) or not all(isinstance(item, str) for item in listed):
            return None
        kept = [item for item in listed if item.split("=", 1)[0].lstrip("+~") != "train.iterations"]
        return [*kept, f"train.iterations={iterations}"]

    overrides = extended(read(OVERRIDES))
    if overrides is not None:
        write_atomic(run_dir / OVERRIDES, yaml.safe_dump(overrides, default_flow_style=False))
    record = read(HYDRA_RECORD)
    hydra_node = record.get("hydra") if isinstance(record, dict) else None
    hydra_overrides = hydra_node.get("overrides") if isinstance(hydra_node, dict) else None
    task = extended(hydra_overrides.get("task")) if isinstance(hydra_overrides, dict) else None
    if task is not None:
        hydra_overrides["task"] = task
        write_atomic(run_dir / HYDRA_RECORD, yaml.safe_dump(record, default_flow_style=False, sort_keys=False))


def _restart_setup(cfg, run_dir: Path):
    """The RunSetup of a run to train again from its start, its own files of the first attempt removed (its config,
    status and log stay), and how many iterations its log held. A backend with checkpoints of its own
    (team.backend=ray) is not restarted here."""
    from omegaconf import OmegaConf

    from riskplan.config.backends import BACKENDS
    from riskplan.run.build import build_setup
    from riskplan.run.record import log_header
    from riskplan.run.run_directory import check_same_map
    from riskplan.run.run_files import CONFIG, RUN_LOG, remove_stale

    setup = build_setup(cfg, needs_ray=False)
    if BACKENDS[setup.params.team.backend].resume_check is not None:
        raise BadInput(str(run_dir), "has no checkpoint yet (stopped before its first one); remove it and start again")
    metadata, logged = log_header(run_dir / RUN_LOG) if (run_dir / RUN_LOG).is_file() else ({}, 0)
    check_same_map(run_dir, setup, metadata)  # its logged iterations are of that map: a restart trains them again
    remove_stale(run_dir)
    write_atomic(run_dir / CONFIG, OmegaConf.to_yaml(cfg))  # with any new train.iterations
    return setup, logged


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
