"""A simulated run from its config to its files: the directory and its lock, then the engine's loop
(riskplan.engine.loop, a batch of one) with its effects through the recorder (riskplan.run.recorder), then the
final evaluation and files. team.backend=ray goes to riskplan.run.ray_team instead.

One loop serves both: a centralized run is a team of one robot whose consensus step is the identity.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from riskplan.config.backends import BACKENDS, load
from riskplan.engine.loop import make_train
from riskplan.engine.step import RunSetup, TrainState, simulator, starts
from riskplan.engine.team.kernels import Links, mix_linked
from riskplan.run.build import build_setup
from riskplan.run.checkpoint import load_checkpoint
from riskplan.run.recorder import Driver, Recorder
from riskplan.run.run_directory import check_same_map, logged_rows
from riskplan.run.run_files import CONFIG, has_finished
from riskplan.util.collector import resume_collection
from riskplan.util.errors import BadInput
from riskplan.util.interrupt import StopSignals
from riskplan.util.lock import hold_lock
from riskplan.util.paths import check_output_dir

if TYPE_CHECKING:
    from riskplan.run.results import Run


def train(
    config, out_dir: str | Path, *, resume: bool = False, progress: Callable[[int, int, dict], None] | None = None
) -> Run:
    """Train, evaluate and record one experiment into out_dir; with resume, continue from its checkpoint. Returns
    the Run, its tables read back from the files just written (`train_summary` skips that).

    `config` is a composed config (or a RunSetup built from one). The directory is locked for the whole run: a second
    process writing it gets BadInput naming this one's pid. A fresh run refuses a directory that holds another run.
    """
    setup = config if isinstance(config, RunSetup) else build_setup(config, needs_ray=not resume)
    summary = train_summary(setup, out_dir, resume=resume, progress=progress)
    from riskplan.run.results import finished_run  # lazy: pandas, for the Run's tables; train_summary needs none

    return finished_run(Path(out_dir), setup.config, summary)


def train_summary(
    config, out_dir: str | Path, *, resume: bool = False, progress: Callable[[int, int, dict], None] | None = None
) -> dict:
    """`train`, returning summary.json's dict instead of the Run: what `riskplan train` and sweep jobs need, and
    without pandas."""
    setup = config if isinstance(config, RunSetup) else build_setup(config, needs_ray=not resume)
    out = Path(out_dir)
    check_output_dir(out, str(out))
    out.mkdir(parents=True, exist_ok=True)
    with hold_lock(out):
        return _train_locked(setup, out, resume, progress)


def _train_locked(setup: RunSetup, out: Path, resume: bool, progress) -> dict:
    """train() under the directory's lock: the engine's loop for a batch of one, its effects through the recorder."""
    driver = BACKENDS[setup.params.team.backend].driver
    if driver is not None:  # a backend with a loop of its own (team.backend=ray: each robot a Ray actor)
        return load(driver)(setup, out, resume, progress)
    run = Driver(setup, out, resume, progress)
    load_kernels(setup, run.state)  # numba's cache, before the loop: wall_time is the loop's own
    resume_collection()  # the start-up is over: a command that paused the collector for it gets it back here
    wall = time.perf_counter()
    with run.log, StopSignals() as stop:  # SIGINT or SIGTERM: checkpoint the iteration in progress, then Interrupted
        make_train([setup])([run.state], Recorder([run], stop))
        run.evaluate(time.perf_counter() - wall)
        stop.check(run.state.iteration)  # before the final files: a resumed run evaluates again
        run.log_results()
    return run.finish()


def load_kernels(setup: RunSetup, state: TrainState) -> None:
    """Load the compiled kernels an iteration runs from numba's cache (a few tenths of a second, once per process)
    by running them on one episode with throwaway keys, and the synchronous team's mixing kernel on a copy of
    theta: no state changes and no number drawn here is used."""
    cells = starts(setup)[:1]
    simulator(setup)(setup.world, setup.kernel, state.thetas[:1], cells, np.zeros(1, dtype=np.uint64), 1)
    if setup.team and state.thetas.shape[1] > 1:
        mix_linked(setup.network, Links(setup.network), state.thetas.copy(), state.thetas.copy())


def prepare_resume(config, out: Path) -> tuple[RunSetup, bool]:
    """The RunSetup of a run to resume, after every check of its config, checkpoint and log (nothing is written), and
    whether the run is finished already (its checkpoint is at train.iterations and its tables are there)."""
    for own in (out / Path(CONFIG).parent, out / CONFIG):  # an extended run rewrites its config: never another's
        if own.is_symlink():
            raise BadInput(str(own), "is a symbolic link; a run keeps its own config: copy the run rather than link it")
    setup = build_setup(config, needs_ray=False)
    check_same_map(out, setup)  # first: a tabular policy's checkpoint would not fit another map's cells either
    check = BACKENDS[setup.params.team.backend].resume_check
    if check is not None:  # checkpoints of its own (ray: one per robot; Ray only if a robot has iterations left)
        return setup, load(check)(setup, out)
    state = load_checkpoint(out, setup)
    logged_rows(out / "run.mcap", state.iteration, setup.robots, setup.config)
    done = state.iteration == setup.params.train.iterations and has_finished(out)
    return setup, done
