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
from dataclasses import dataclass
from pathlib import Path

import hydra
from hydra._internal.callbacks import Callbacks
from hydra._internal.core_plugins import basic_sweeper
from hydra._internal.hydra import Hydra
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.core.utils import configure_log, run_job
from hydra.types import HydraContext, RunMode
from omegaconf import DictConfig, open_dict

from riskplan.config import schema
from riskplan.engine.step import NumericalTrouble
from riskplan.experiments.sweep_worker import sweep_job, write_status
from riskplan.run.training import train_summary
from riskplan.util.errors import BadInput
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


def single_run(out: Path, setup, stderr) -> SingleRun:
    """Train the run into `out` (Hydra's output directory) from its built Setup; record it in status.json."""
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
            where = f" {err.filename}" if err.filename else ""
            return _failed(
                out, f"cannot write{where}: {err.strerror or err}; free space, then riskplan train --resume {out}"
            )
        except Exception as err:  # any other error: its status records why
            return _failed(out, f"{type(err).__name__}: {err}", traceback.format_exc())
        write_run_status(out, "done", None)
    return SingleRun(value=summary["cvar"]["value"])


def _failed(out: Path, error: str, trace: str | None = None) -> SingleRun:
    """A single run's failure: in status.json if the disk takes it, and for the CLI in any case."""
    with contextlib.suppress(OSError):
        write_run_status(out, "failed", error, trace)
    return SingleRun(failure=error)


def run_hydra(args: list[str], capture: bool = False, skip: frozenset = frozenset(), launched: list | None = None):
    """Call the Hydra app as if `riskplan <args>` were its command line.

    In a multirun, the basic sweeper's jobs whose overrides are in `skip` (finished ones) are not handed to the
    launcher, so a re-run sweep submits only the jobs that need to run; `launched` receives those it hands over,
    in order (a launcher's task k is launched[k]).

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
        with (
            contextlib.redirect_stderr(held) if capture else contextlib.nullcontext(),
            _without_repeat_compositions("-m" in args or "--multirun" in args, skip, launched),
        ):
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


def run_composed(config: DictConfig, setup) -> SingleRun:
    """Hydra's single run of a config riskplan composed and checked already, with its hydra node, and the Setup
    built from it (riskplan.run.compose.compose_run): what `Hydra.run` does after composing, so the config is
    neither composed nor built a second time. The run's directory is hydra.run.dir; `.hydra/`, logging and
    callbacks are Hydra's. A failure outside the task (Hydra cannot write `.hydra/`: a full disk) is RunFailed,
    one line."""
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
    except Exception as err:
        raise RunFailed(f"{type(err).__name__}: {err}") from None
    finally:
        _restore_logging(logs)


@contextlib.contextmanager
def _without_repeat_compositions(multirun: bool, skip: frozenset = frozenset(), launched: list | None = None):
    """Skip two compositions Hydra repeats that riskplan has already done: `Hydra.get_mode` composes the config
    only to read hydra.mode (riskplan's commands fix the mode: train runs, sweep multiruns), and the basic sweeper
    composes every job once more to validate it (`plan_sweep` composed and validated each one, and Hydra's own
    comment there calls it slow for large sweeps). Each takes 0.07-0.1 s: per job, in a sweep's driver.

    The basic sweeper's batches also leave out the jobs in `skip` (`get_job_batch`), and note the rest in
    `launched`.

    All are Hydra internals (hydra-core is pinned to 1.3.x): if they move, nothing is skipped. Optimising
    sweepers (optuna) choose their own jobs, so they still validate them."""
    mode = RunMode.MULTIRUN if multirun else RunMode.RUN
    # the class as it is now: Hydra's plugin scan executes its module again, defining a new BasicSweeper
    BasicSweeper = basic_sweeper.BasicSweeper
    own_batch = BasicSweeper.get_job_batch

    def job_batch(sweeper) -> list:
        batch = [job for job in own_batch(sweeper) if tuple(job) not in skip]
        if launched is not None:
            launched.extend(tuple(job) for job in batch)
        return batch

    replacements = {
        (Hydra, "get_mode"): lambda *args, **kwargs: mode,
        (BasicSweeper, "validate_batch_is_legal"): lambda *args, **kwargs: None,
        (BasicSweeper, "get_job_batch"): job_batch,
    }
    originals = {key: key[0].__dict__.get(key[1]) for key in replacements if hasattr(*key)}
    try:
        for owner, name in originals:
            setattr(owner, name, replacements[owner, name])
        yield
    finally:
        for (owner, name), own in originals.items():
            if own is None:  # inherited (Sweeper's): uncover it again
                delattr(owner, name)
            else:
                setattr(owner, name, own)


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


class RunFailed(RuntimeError):
    """Hydra stopped a single run outside the task (it could not write the run directory)."""


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
