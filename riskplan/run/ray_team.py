"""team.backend=ray: each robot a Ray actor, and the asynchrony of paper eq. (14) real, bounded as Assumption 5 says.

The simulated backend (`riskplan.run.training`) steps every robot in lockstep and simulates delays and drops; here
each robot runs its own loop in its own process, on any node of a Ray cluster, and the wall clock decides which
neighbour values it mixes. This module is the driver: the team of actors, their reports, the log, the checkpoints
and the run's files. One robot's side of the algorithm is `riskplan.run.ray_robot` (`RobotCore`, without Ray: its
iteration, messages, mixing and the staleness rule), its actor and Ray itself `riskplan.run.ray_actor`.

Rows and the log. The driver (this process) takes the reports (`drain(after, wait)`, a call that returns as soon as
a report of iteration `after` or later is there, or after a second; the robot keeps a report until a later drain
acknowledges it, so an answer the driver never reads loses nothing) and logs each robot's row to run.mcap as it
comes, with the wall-clock time it was logged
(consensus_error null: a team figure, not known yet). Once every robot has finished iteration l it logs the network
average row (robot -1: the healthy robots' pooled episodes, as in the simulated backend) and the iteration's
/consensus_error message, which marks it complete. metrics.parquet holds the same columns as the simulated
backend's, plus `staleness`; each robot row gets its iteration's consensus error there. summary.json says
`deterministic: false`, and the MCAP metadata "ray_team" where each robot ran (node id, ip, pid).

Checkpoints. Every report carries the robot's state after its iteration, so the driver holds a short history of
each. Every train.checkpoint_every team iterations (and at the end, on a signal, and on a failure) it writes the
newest consistent cut of them (`consistent_cut`: no robot holds a message from a neighbour's iteration after that
neighbour's own checkpoint) as one atomically replaced file (`checkpoint.save_team_checkpoint`), with the rows of
the iterations not every robot has finished. Resume starts every actor from its own checkpoint; the messages that
were in flight are lost, which the running sums of gradient tracking absorb and the waiting rule replaces.

A robot actor that dies (its process killed, its node lost) stops the whole run: the driver writes the last
consistent cut of every robot's state (the dead robot's last report included), stops the other actors and fails with
one line naming the robot (`TeamFailure`, exit 1); `riskplan train --resume` restarts all actors from their
checkpoints. Why not carry on without it, as a crash of team.faults: the dead robot took state nobody else has (its
share of the gradient-tracking mass, the messages it had received), so the survivors would run a different algorithm
than the config says, and the run could not be resumed to what it should have been; crashes as a studied fault are
what team.faults is for. Ctrl-C or SIGTERM: the driver stops the actors, writes the cut, and stops with
`Interrupted` (status interrupted, exit 130 or 143); Ctrl-C in a terminal also reaches the local Ray instance's own
processes (they share the driver's process group), and the actors that die of it then are part of the same stop.

Where it runs: a local Ray instance or a cluster (`ray_actor.ray_runtime`). Every node needs riskplan (the same
version: checked) installed. Each robot's kernels use max(1, cluster CPUs // robots) numba threads. An unreachable
cluster is BadInput naming team.address, raised before anything is written: the Python API raises it, `riskplan
train` reports it as a failed run in one line (exit 1). Whatever stops the run, every actor it started is killed
before it returns, and a local instance is shut down.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from riskplan.config.schema import Order
from riskplan.config.validate import check_extra
from riskplan.engine.step import NumericalTrouble, RunSetup, TrainState, check_agreement, team_statistics
from riskplan.engine.team.convergence import consensus_error
from riskplan.run.checkpoint import TeamCheckpoint, load_team_checkpoint, save_team_checkpoint
from riskplan.run.columns import Columns, from_rows, sorted_by
from riskplan.run.evaluation import evaluate, sample_paths, summarize
from riskplan.run.metrics_rows import AVERAGE, average_row
from riskplan.run.ray_actor import RobotActor, placements, ray_runtime
from riskplan.run.ray_robot import consistent_cut, in_neighbours, initial_state, out_neighbours, tracking_balance
from riskplan.run.record import RunLog
from riskplan.run.run_directory import logged_rows, reopen_log, start_log, write_finished
from riskplan.run.run_files import RUN_LOG, has_finished
from riskplan.util.errors import BadInput, first_line
from riskplan.util.interrupt import Interrupted, StopSignals
from riskplan.version import __version__

POLL_SECONDS = 0.2  # the driver looks at signals and finished actors this often
DRAIN_SECONDS = 1.0  # an actor's drain call returns after this long when it has nothing to report
START_SECONDS = 900.0  # actors that are not all up by then (a cluster without room for them) fail the run
STOP_SECONDS = 5.0  # after a stop, reports still arriving within this are taken


class TeamFailure(NumericalTrouble):
    """The ray team stopped: a robot's actor died or failed. Every robot's last consistent state is checkpointed
    (a NumericalTrouble, so that every caller reports it in one line, exit 1, and keeps the checkpoint)."""


class _RobotDied(Exception):
    def __init__(self, robot: int, detail: str):
        self.robot, self.detail = robot, detail


class _RobotFailed(Exception):
    def __init__(self, robot: int, cause: BaseException):
        self.robot, self.cause = robot, cause


class _Team:
    """The driver's side: the actors, their reports, the log, the checkpoints."""

    def __init__(self, ray, setup: RunSetup, out: Path, log: RunLog, states: list[dict], pending: list[dict], rows):
        self.ray, self.setup, self.out, self.log = ray, setup, out, log
        self.n = setup.robots
        self.ins = [in_neighbours(setup, i) for i in range(self.n)]
        self.history: list[list[dict]] = [[state] for state in states]
        self.reached = [int(state["iteration"]) for state in states]  # per robot: its next iteration, as reported
        self.partial: dict[int, dict[int, dict]] = {}  # iteration -> robot -> report (row, z, grad)
        self.rows: list[dict] = list(rows)
        self.actors: list = []
        self.where: list[dict] = []
        self.timing = [{"iterations": 0, "compute": 0.0, "wait": 0.0, "seconds": 0.0} for _ in range(self.n)]
        self.balance = 0.0  # gradient tracking: the largest |residual| of the invariant over the cuts written
        self.every = setup.params.train.checkpoint_every
        self.next_checkpoint = (min(self.reached) // self.every + 1) * self.every
        self.progress: Callable | None = None
        self.cut = [h[0] for h in self.history]  # the last consistent cut written (at first: where it starts)
        self.started = time.perf_counter()  # when the actors were all up (start)
        self.startup = 0.0  # seconds from creating the actors to all of them up and connected
        for entry in pending:
            row = entry["row"]
            log.rows([row])
            self.rows.append(row)
            self.partial.setdefault(int(row["iteration"]), {})[int(row["robot"])] = entry

    # -- the actors
    def start(self, stop: StopSignals) -> None:
        """One actor per robot (spread over the nodes, no CPUs reserved), connected to its out-neighbours."""
        ray, setup = self.ray, self.setup
        began = time.perf_counter()
        actor = ray.remote(RobotActor)
        cpus = int(ray.cluster_resources().get("CPU", 1)) or 1
        threads = max(1, cpus // self.n)
        places = placements(ray, self.n)
        for i in range(self.n):
            self.actors.append(
                actor.options(
                    num_cpus=0,
                    max_concurrency=len(self.ins[i]) + 4,
                    scheduling_strategy=places[i],
                    max_restarts=0,
                    max_task_retries=0,
                ).remote(setup.config, i, self.history[i][-1], threads)
            )
        self.where = self._get([a.where.remote() for a in self.actors], stop, START_SECONDS)
        for place in self.where:
            if place["version"] != __version__:
                raise BadInput(
                    "team.address",
                    f"robot {place['robot']} runs on {place['ip']} with riskplan {place['version']}, this driver has "
                    f"{__version__}; install the same riskplan on every node",
                )
        peers = [[self.actors[k] for k in out_neighbours(setup, i)] for i in range(self.n)]
        self._get([a.connect.remote(p) for a, p in zip(self.actors, peers)], stop, START_SECONDS)
        self.startup = time.perf_counter() - began
        speeds = setup.params.team.speeds
        self.log.metadata(
            "ray_team",
            {
                "robots": [
                    {**place, "speed": float(speeds[place["robot"]]) if speeds else 1.0, "threads": threads}
                    for place in self.where
                ],
                "nodes": sorted({place["node_id"] for place in self.where}),
                "staleness": setup.params.team.staleness,
                "ray": ray.__version__,
            },
        )

    def _get(self, refs: list, stop: StopSignals, seconds: float) -> list:
        """ray.get of refs made of actor calls, a few at a time so that a signal is seen; a dead actor is
        _RobotDied."""
        deadline = time.monotonic() + seconds
        waiting = list(refs)
        while waiting:
            if stop.received is not None:
                raise _Interrupt
            if time.monotonic() > deadline:
                raise TeamFailure(
                    f"the {self.n} robot actors did not all start within {seconds:.0f} s; is there room for them "
                    f"on the Ray cluster?"
                )
            _, waiting = self.ray.wait(waiting, num_returns=len(waiting), timeout=POLL_SECONDS)
        return [self._result(ref, i) for i, ref in enumerate(refs)]

    def run(self, stop: StopSignals, total: int) -> None:
        """Every robot's iterations up to `total`, their reports logged and checkpointed as they come."""
        ray = self.ray
        calls = {a.run.remote(total): ("run", i) for i, a in enumerate(self.actors)}
        calls |= {a.drain.remote(self.reached[i], DRAIN_SECONDS): ("drain", i) for i, a in enumerate(self.actors)}
        running = set(range(self.n))
        while running:
            if stop.received is not None:
                raise _Interrupt
            ready, _ = ray.wait(list(calls), num_returns=len(calls), timeout=POLL_SECONDS)
            for ref in ready:
                kind, i = calls.pop(ref)
                value = self._result(ref, i)
                if kind == "run":
                    running.discard(i)
                    continue
                self.take(i, value)
                if i in running:
                    calls[self.actors[i].drain.remote(self.reached[i], DRAIN_SECONDS)] = ("drain", i)
            if min(self.reached) >= self.next_checkpoint:
                self.checkpoint()
        for ref, (_, i) in calls.items():  # every robot has finished: the drains still out, then one more each
            self.take(i, self._result(ref, i))
        last = [a.drain.remote(self.reached[i], 0.0) for i, a in enumerate(self.actors)]
        for i, ref in enumerate(last):
            self.take(i, self._result(ref, i))

    def _result(self, ref, i: int):
        """ray.get of robot i's call: _RobotDied when its actor died, _RobotFailed when the call raised."""
        try:
            return self.ray.get(ref)
        except self.ray.exceptions.RayActorError as err:
            raise _RobotDied(i, first_line(err)) from None
        except self.ray.exceptions.RayTaskError as err:
            raise _RobotFailed(i, getattr(err, "cause", err)) from None

    def collect(self, seconds: float) -> None:
        """The reports the actors still hold (after a stop): whatever arrives within `seconds`."""
        ray = self.ray
        calls = {a.drain.remote(self.reached[i], 0.0): i for i, a in enumerate(self.actors)}
        ready, _ = ray.wait(list(calls), num_returns=len(calls), timeout=seconds)
        for ref in ready:
            with contextlib.suppress(Exception):
                self.take(calls[ref], ray.get(ref))

    def kill(self) -> None:
        """Kill every actor it started, whatever it is doing."""
        for a in self.actors:
            with contextlib.suppress(Exception):
                self.ray.kill(a, no_restart=True)
        self.actors = []

    # -- reports, rows, checkpoints
    def take(self, i: int, reports: list[dict]) -> None:
        """Robot i's reports: its rows logged, its states kept, the iterations every robot finished completed."""
        for report in reports:
            row = report["row"]
            l = int(row["iteration"])
            if l < self.reached[i]:  # already taken (a report seen twice)
                continue
            if l > self.reached[i]:  # drains hand reports over until they are acknowledged: never a gap
                raise RuntimeError(f"robot {i} reported iteration {l} before {self.reached[i]}")
            self.log.rows([row])
            self.rows.append(row)
            self.history[i].append(report["state"])
            self.reached[i] = l + 1
            timing = self.timing[i]
            timing["iterations"] += 1
            timing["compute"] += report["compute"]
            timing["wait"] += report["wait"]
            timing["seconds"] += row["seconds"]
            self.partial.setdefault(l, {})[i] = {"row": row, "z": report["z"], "grad": report["grad"]}
            if len(self.partial[l]) == self.n:
                self.complete(l)

    def complete(self, l: int) -> None:
        """Iteration l, which every robot has finished: its network average row (a team) and its mark."""
        setup, params = self.setup, self.setup.params
        entries = [self.partial[l][i] for i in range(self.n)]
        healthy = setup.mixer.healthy(l)
        ok = [i for i in range(self.n) if healthy[i]]
        thetas = np.array([[e["row"][f"theta_{j}"] for j in range(setup.network.n_params)] for e in entries])
        error = consensus_error(thetas[ok]) if setup.team else math.nan
        rows = []
        if setup.team:
            check_agreement(l, thetas[ok], error)  # as the simulated step: never a non-finite row
            objectives = np.array([e["row"]["objective"] for e in entries])
            team = team_statistics(setup, l, np.stack([e["z"] for e in entries]), objectives)
            levels = np.array([e["row"]["beta_l"] for e in entries])
            grads = np.array([e["grad"] for e in entries])
            stale = [e["row"]["staleness"] for e in entries if not math.isnan(e["row"]["staleness"])]
            first, seconds = entries[0]["row"], max(e["row"]["seconds"] for e in entries)
            rows.append(
                average_row(
                    l,
                    team,
                    thetas,
                    grads,
                    levels,
                    healthy,
                    first["step_size"],
                    error,
                    first["samples"],
                    seconds,
                    staleness=float(max(stale)) if stale else math.nan,
                )
            )
        self.log.rows(rows, (l, error))
        self.rows.extend(rows)
        if self.progress is not None:
            self.progress(l + 1, params.train.iterations, rows[-1] if rows else entries[0]["row"])

    def checkpoint(self) -> None:
        """The newest consistent cut of the robots' states, with the rows of the iterations not every robot of it
        has finished, written atomically after the log is synced."""
        index = consistent_cut(self.history, self.ins)
        if index is None:  # cannot happen: the oldest states kept are the last cut written
            return
        cut = [h[k] for h, k in zip(self.history, index)]
        self.history = [h[k:] for h, k in zip(self.history, index)]
        reached = [int(state["iteration"]) for state in cut]
        low = min(reached)
        pending = [
            entry
            for l, robots in sorted(self.partial.items())
            if l >= low
            for i, entry in sorted(robots.items())
            if l < reached[i]
        ]
        if self.setup.params.team.order == Order.gradient_tracking and self.setup.team:
            held, want = tracking_balance(self.setup, cut)
            self.balance = max(self.balance, float(np.max(np.abs(held - want))))
        self.log.sync()
        save_team_checkpoint(self.out, cut, pending)
        self.partial = {l: robots for l, robots in self.partial.items() if l >= low}
        self.next_checkpoint = (low // self.every + 1) * self.every
        self.cut = cut

    def final_thetas(self) -> np.ndarray:
        return np.array([h[-1]["theta"] for h in self.history])


class _Interrupt(Exception):
    """A signal arrived while the team ran."""


# --------------------------------------------------------------------------------------------- the run
def train_ray(setup: RunSetup, out: Path, resume: bool, progress) -> dict:
    """`training.train_summary` for team.backend=ray, under the run directory's lock: the same files, written the
    same way, from a team of Ray actors (see the module docstring); returns the summary."""
    total = setup.params.train.iterations
    expected = [initial_state(setup, i) for i in range(setup.robots)]
    checkpoint = load_team_checkpoint(out, setup, expected) if resume else None
    with contextlib.ExitStack() as ray_up:
        idle = checkpoint is not None and checkpoint.iteration >= total  # every robot is done: evaluation only
        if not idle:
            check_extra("team.backend", setup.params.team.backend)  # bad input before anything is written
        # First Ray (an unreachable cluster writes nothing), unless no robot has an iteration left to run
        ray = ray_up.enter_context(contextlib.nullcontext() if idle else ray_runtime(setup.params.team))
        if checkpoint is not None:
            log, rows = reopen_log(out, setup, checkpoint.iteration)
            states, pending = checkpoint.robots, checkpoint.pending
        else:
            log = start_log(out, setup)
            states, pending, rows = expected, [], []
        with log, StopSignals() as stop:
            team = _Team(ray, setup, out, log, states, pending, rows)
            team.progress = progress
            _run_team(team, stop, total, out)
            train_seconds = time.perf_counter() - team.started
            ray_up.close()  # every actor is gone: Ray's own processes (a local instance) go too, before evaluating
            log.metadata("ray_team_end", _end_record(team, train_seconds))
            thetas = team.final_thetas()
            metrics = _metrics_table(team.rows)
            evaluation = evaluate(setup, thetas)
            trajectories = sample_paths(setup, thetas)
            resumed_at = checkpoint.iteration if checkpoint is not None else 0  # the throughput's: this run's part
            summary = summarize(setup, TrainState(total, thetas, {}), evaluation, metrics, train_seconds, resumed_at)
            stop.check(total)  # before the final files: a resumed run evaluates again
            log.trajectories(trajectories)
            log.evaluation(evaluation)
            log.summary(summary)
    write_finished(out, setup, metrics, evaluation, trajectories, summary)
    return summary


def _run_team(team: _Team, stop: StopSignals, total: int, out: Path) -> None:
    """The team's iterations up to `total` and its final checkpoint; whatever stops it, its actors are killed and
    the last consistent cut is written first (a signal: Interrupted; a dead or failed robot: TeamFailure or
    NumericalTrouble)."""
    try:
        if min(team.reached) < total:
            team.start(stop)
            team.started = time.perf_counter()  # the training time counts from here (as the simulated loop's)
            team.run(stop, total)
        team.checkpoint()  # every robot at train.iterations: the final states
    except _Interrupt:
        _stop_team(team)
        raise Interrupted(stop.received, min(int(s["iteration"]) for s in team.cut)) from None
    except _RobotDied as died:
        _stop_team(team)
        if stop.received is not None:  # Ctrl-C in a terminal reaches Ray's processes too: a stop, not a failure
            raise Interrupted(stop.received, min(int(s["iteration"]) for s in team.cut)) from None
        place = team.where[died.robot] if died.robot < len(team.where) else None
        at = f"pid {place['pid']} on {place['ip']}, " if place else ""
        raise TeamFailure(
            f"robot {died.robot}'s Ray actor died ({at}at its iteration {team.reached[died.robot]}: {died.detail}); "
            f"every robot's last state is checkpointed: resume with riskplan train --resume {out}"
        ) from None
    except _RobotFailed as failed:
        _stop_team(team)
        if isinstance(failed.cause, NumericalTrouble):
            raise NumericalTrouble(str(failed.cause)) from None
        raise TeamFailure(
            f"robot {failed.robot} failed ({type(failed.cause).__name__}: {first_line(failed.cause)}); every "
            f"robot's last state is checkpointed: resume with riskplan train --resume {out}"
        ) from None
    finally:
        team.kill()


def _end_record(team: _Team, train_seconds: float) -> dict:
    """The MCAP metadata "ray_team_end": each robot's iterations and seconds (computing, waiting, in all), the
    largest gradient-tracking residual over the checkpoints and the largest staleness mixed."""
    stale = [r["staleness"] for r in team.rows if r["robot"] >= 0 and not math.isnan(r.get("staleness", math.nan))]
    return {
        "robots": [{"robot": i, **timing} for i, timing in enumerate(team.timing)],
        "tracking_residual": team.balance,
        "max_staleness": max(stale) if stale else None,
        "train_seconds": train_seconds,
        "startup_seconds": team.startup,
    }


def _stop_team(team: _Team) -> None:
    """After a signal or a failure: the actors stopped, their last reports taken, the last consistent cut written,
    the actors killed."""
    for a in team.actors:
        with contextlib.suppress(Exception):
            a.stop.remote()
    if team.actors:
        with contextlib.suppress(Exception):  # Ray itself may be going down (a signal to the whole group)
            team.collect(STOP_SECONDS)
    team.kill()
    team.checkpoint()


def _metrics_table(rows: list[dict]) -> Columns:
    """metrics.parquet: every row, sorted; each robot row with its iteration's consensus error (the team's)."""
    metrics = sorted_by(from_rows(rows), "iteration", "robot")
    average = metrics["robot"] == AVERAGE
    if average.any():
        team = dict(zip(metrics["iteration"][average].tolist(), metrics["consensus_error"][average].tolist()))
        metrics["consensus_error"] = np.array([team.get(i, np.nan) for i in metrics["iteration"].tolist()], dtype=float)
    return metrics


def prepare_ray_resume(setup: RunSetup, out: Path) -> bool:
    """Every check of a ray run's checkpoint and log before it resumes (nothing is written); whether it is
    finished already."""
    expected = [initial_state(setup, i) for i in range(setup.robots)]
    checkpoint = load_team_checkpoint(out, setup, expected)
    logged_rows(out / RUN_LOG, checkpoint.iteration, setup.robots, setup.config)
    if min(checkpoint.iterations) < setup.params.train.iterations:  # robots to run: Ray (else evaluation only)
        check_extra("team.backend", setup.params.team.backend)
    return min(checkpoint.iterations) == setup.params.train.iterations and has_finished(out)


__all__ = ["TeamCheckpoint", "TeamFailure", "prepare_ray_resume", "train_ray"]
