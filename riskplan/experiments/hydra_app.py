"""The Hydra application: one task function serves `riskplan train` (a run) and `riskplan sweep` (a multirun).

Going through Hydra's own main gives users what they expect of a Hydra app: `.hydra/` in every run directory,
`--cfg job`, `hydra.run.dir`, sweepers and launchers (joblib, submitit, ray).
"""

from __future__ import annotations

import contextlib
import io
import logging
import re
import sys
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path

import hydra
from hydra._internal.hydra import Hydra
from hydra._internal.utils import (
    create_automatic_config_search_path,
    detect_calling_file_or_module_from_task_function,
    detect_task_name,
    run_and_report,
)
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.core.utils import configure_log, run_job
from hydra.types import HydraContext, RunMode
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf, open_dict

from riskplan.config import schema
from riskplan.engine.step import NumericalTrouble
from riskplan.experiments.sweep_worker import sweep_job, write_status
from riskplan.run.training import train_summary
from riskplan.util.errors import BadInput, remedy
from riskplan.util.interrupt import Interrupted
from riskplan.util.progress import TrainingBar

CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")  # absolute: riskplan/conf is a symlinked data dir


def _task(cfg: DictConfig) -> float | None:
    """A sweep's job in Hydra's output directory: it skips itself when finished, resumes when killed, and logs to
    its own folder (riskplan.experiments.sweep_worker). A single run goes through `run_composed`."""
    return sweep_job(cfg, Path(HydraConfig.get().runtime.output_dir))


task = hydra.main(config_path=CONF_DIR, config_name="config", version_base="1.3")(_task)


@dataclass
class SingleRun:
    """How a single run (`run_composed`) ended, for the CLI: its CVaR when it finished, else why not."""

    value: float | None = None
    failure: str | None = None  # the error, also when status.json could not take it (a full disk)
    interrupted: Interrupted | None = None  # the signal that stopped it, checkpointed
    write_error: OSError | None = None  # what stopped it when it could not write its files (a full disk)


def single_run(out: Path, setup, stderr) -> SingleRun:
    """Train the run into `out` (Hydra's output directory) from its built RunSetup; record it in status.json."""
    with contextlib.redirect_stderr(stderr):
        try:
            write_run_status(out, "running", None)
            with TrainingBar() as progress:
                summary = train_summary(setup, out, progress=progress)
        except Interrupted as stop:  # checkpointed: status interrupted, and the CLI exits 130 or 143
            with contextlib.suppress(OSError):
                write_run_status(out, "interrupted", str(stop))
            return SingleRun(interrupted=stop)
        except (BadInput, NumericalTrouble) as err:
            return _failed(out, str(err))
        except OSError as err:  # a full disk, a directory removed under the run
            return _failed(out, write_failure(err, out, f"riskplan train --resume {out}"), write_error=err)
        except Exception as err:  # any other error: its status records why
            return _failed(out, f"{type(err).__name__}: {err}", traceback.format_exc())
        write_run_status(out, "done", None)
    return SingleRun(value=summary["cvar"]["value"])


def _failed(out: Path, error: str, trace: str | None = None, write_error: OSError | None = None) -> SingleRun:
    """A single run's failure: in status.json if the disk takes it, and for the CLI in any case."""
    with contextlib.suppress(OSError):
        write_run_status(out, "failed", error, trace)
    return SingleRun(failure=error, write_error=write_error)


def write_failure(err: OSError, out: Path, then: str) -> str:
    """One line for a failure to write into the run directory `out` at run time (a full disk, a directory removed):
    the file (an error at the close of a file names none: then the directory), the cause, its fix, and `then`, what
    to run once it is fixed."""
    where = err.filename or f"into {out}"
    return f"cannot write {where}: {err.strerror or err}; {remedy(err)}, then {then}"


def run_hydra(args: list[str], capture: bool = False):
    """Call the Hydra app as if `riskplan <args>` were its command line (a sweep's multirun, or Hydra's own flags).

    With `capture`, what Hydra itself prints on stderr (it prints a traceback for an error outside the task, e.g.
    a full disk while it writes .hydra/) is held back, and a failure becomes one line (RunFailed); the task gets
    Hydra's own flags (--cfg job, --info, ...) run no task.
    """
    schema.register()
    GlobalHydra.instance().clear()
    argv = sys.argv
    sys.argv = ["riskplan", *args]
    held = io.StringIO()
    logs = _logging_state()
    try:
        with contextlib.redirect_stderr(held) if capture else contextlib.nullcontext():
            task()
    except SystemExit as stop:
        if not capture or stop.code in (0, None):
            raise
        raise RunFailed(_last_error(held.getvalue())) from None
    finally:
        sys.argv = argv
        GlobalHydra.instance().clear()
        _restore_logging(logs)
        if capture and held.getvalue() and not isinstance(sys.exc_info()[1], RunFailed):
            sys.stderr.write(held.getvalue())


MULTIRUN = "hydra.mode=MULTIRUN"


def run_multirun(overrides: list[str]) -> None:
    """Hydra's multirun of these overrides (a sweep's launch), as `riskplan -m <overrides>` runs it through Hydra's
    main, less the composition that main spends to find the mode, which a launch knows (70 ms a sweep, 13 in a
    reproduction). Hydra's own steps as its main takes them: the task's name and search path from the task
    function, `hydra.mode=MULTIRUN` added as for a config that leaves the mode unset (riskplan sweep refuses a
    hydra.mode override), then Hydra.multirun; an error is printed and exits 1, as there."""
    schema.register()
    GlobalHydra.instance().clear()
    calling_file, calling_module = detect_calling_file_or_module_from_task_function(_task)
    search_path = create_automatic_config_search_path(calling_file, calling_module, CONF_DIR)
    name = detect_task_name(calling_file, calling_module)
    logs = _logging_state()
    try:
        app = run_and_report(lambda: Hydra.create_main_hydra2(task_name=name, config_search_path=search_path))
        run_and_report(
            lambda: app.multirun(config_name="config", task_function=_task, overrides=[*overrides, MULTIRUN])
        )
    finally:
        GlobalHydra.instance().clear()
        _restore_logging(logs)


def run_composed(config: DictConfig, setup) -> SingleRun:
    """Hydra's single run of a config riskplan composed and checked already, with its hydra node, and the RunSetup
    built from it (riskplan.run.compose.compose_run): what `Hydra.run` does after composing, so the config is
    neither composed nor built a second time. The run's directory is hydra.run.dir; `.hydra/`, logging and
    callbacks are Hydra's. A failure outside the task (Hydra cannot write `.hydra/`: a full disk) is RunFailed,
    one line, with the OSError naming the file."""
    with open_dict(config.hydra):
        config.hydra.mode = RunMode.RUN
    stderr = sys.stderr  # the terminal's, for the progress bar, whatever Hydra does with its own output

    def train_task(_cfg: DictConfig) -> SingleRun:
        return single_run(Path(HydraConfig.get().runtime.output_dir), setup, stderr)

    logs = _logging_state()
    try:
        configure_log(config.hydra.hydra_logging, config.hydra.verbose)
        callbacks = Callbacks(config)
        callbacks.on_run_start(config=config, config_name="config")
        done = run_job(
            hydra_context=HydraContext(config_loader=None, callbacks=callbacks),
            task_function=train_task,
            config=config,
            job_dir_key="hydra.run.dir",
            job_subdir_key=None,
        )
        callbacks.on_run_end(config=config, config_name="config", job_return=done)
        return done.return_value  # raises what the task raised (it records its own failures)
    except OSError as err:  # Hydra's own writes before the task: app.log, then .hydra/'s files
        if not err.filename:  # a write to an open file: the last of .hydra/'s files begun (run_job's order)
            files = Path(str(config.hydra.run.dir)) / str(config.hydra.output_subdir)
            begun = [files / name for name in HYDRA_FILES if (files / name).exists()]
            err = OSError(err.errno, err.strerror, str(begun[-1] if begun else files))
        raise RunFailed(f"{type(err).__name__}: {err}", err) from None
    except Exception as err:
        raise RunFailed(f"{type(err).__name__}: {err}") from None
    finally:
        _restore_logging(logs)


class Callbacks:
    """The run's Hydra callbacks (hydra.callbacks), told of its start and end as Hydra's own run tells them: the
    config's callback objects, each called in turn (in reverse at the end), a failing one a warning."""

    def __init__(self, config: DictConfig) -> None:
        found = OmegaConf.select(config, "hydra.callbacks")
        self.callbacks = [instantiate(params) for params in found.values()] if found else []

    def _notify(self, event: str, reverse: bool = False, **kwargs) -> None:
        for callback in reversed(self.callbacks) if reverse else self.callbacks:
            try:
                getattr(callback, event)(**kwargs)
            except Exception as err:
                warnings.warn(
                    f"Callback {type(callback).__name__}.{event} raised {type(err).__name__}: {err}", stacklevel=2
                )

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        self._notify("on_run_start", config=config, **kwargs)

    def on_run_end(self, config: DictConfig, **kwargs) -> None:
        self._notify("on_run_end", reverse=True, config=config, **kwargs)

    def on_job_start(self, config: DictConfig, **kwargs) -> None:
        self._notify("on_job_start", config=config, **kwargs)

    def on_job_end(self, config: DictConfig, **kwargs) -> None:
        self._notify("on_job_end", reverse=True, config=config, **kwargs)


def _logging_state() -> dict:
    """The level and handlers of the root logger and of every named logger, before Hydra configures logging."""
    loggers = [logging.getLogger()] + [logging.getLogger(name) for name in logging.root.manager.loggerDict]
    return {logger: (logger.level, list(logger.handlers), logger.propagate) for logger in loggers}


def _restore_logging(state: dict) -> None:
    """Undo Hydra's logging set-up: its handlers (the run's app.log, a console bound to this call's stdout) are
    closed, so a later log record in this process (a notebook, a test) never writes to a closed stream or a run's
    log file."""
    for logger in [logging.getLogger()] + [logging.getLogger(name) for name in logging.root.manager.loggerDict]:
        level, handlers, propagate = state.get(logger, (logging.NOTSET, [], True))
        for handler in logger.handlers:
            if handler not in handlers:
                handler.close()
        logger.handlers[:] = handlers
        logger.setLevel(level)
        logger.propagate = propagate


HYDRA_FILES = ("config.yaml", "hydra.yaml", "overrides.yaml")  # in the order run_job writes them, in place


class RunFailed(RuntimeError):
    """Hydra stopped a single run outside the task (it could not write the run directory); `write_error`: the
    OSError that stopped it, naming the file, where it was one."""

    def __init__(self, message: str, write_error: OSError | None = None) -> None:
        super().__init__(message)
        self.write_error = write_error


def _last_error(text: str) -> str:
    """The exception line of what Hydra printed (`OSError: [Errno 28] No space left on device: ...`)."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    errors = [line for line in lines if re.match(r"^[\w.]*(Error|Exception)\b.*:", line)]
    return errors[-1] if errors else (lines[-1] if lines else "Hydra stopped without a message")


def write_run_status(out: Path, status: str, error: str | None, trace: str | None = None) -> None:
    """A single run's status.json (riskplan train): its state and error, and the traceback of an unexpected one."""
    record = {"status": status, "error": error}
    if trace:
        record["traceback"] = trace
    write_status(out, record)
