"""team.backend=ray (riskplan.run.ray_team): each robot a Ray actor.

Quick tier (no Ray needed): one robot's side of the algorithm (`RobotCore`) driven by hand, in lockstep against the
simulated Mixer, and asynchronously with random message delays against the staleness bound and gradient tracking's
sum invariant; the estimators and the rows against the simulated backend's; Ray missing is one line.

Slow tier (a local Ray instance; skipped without Ray): whole runs of paper_team, which the wall clock orders, so the
checks are invariants and tolerances, never exact numbers: the run directory, the consensus error, the staleness
bound with a slow robot, the tracking invariant, SIGINT and resume, kill -9 of a robot's actor and resume, an
unreachable cluster, and no Ray process left behind by any of them.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import riskplan
import riskplan.engine.step as engine_step
import riskplan.run.metrics_rows as metrics_rows
import riskplan.run.training as training
from riskplan.engine.schedules import step_size
from riskplan.run.build import build_setup
from riskplan.run.checkpoint import CHECKPOINT, load_team_checkpoint, save_team_checkpoint
from riskplan.run.log_reader import read_log
from riskplan.run.ray_robot import (
    STATE_KEYS,
    RobotCore,
    Step,
    consistent_cut,
    in_neighbours,
    initial_state,
    out_neighbours,
    tracking_balance,
)
from riskplan.util.errors import BadInput, MissingExtra

HAVE_RAY = importlib.util.find_spec("ray") is not None
needs_ray = pytest.mark.skipif(not HAVE_RAY, reason="ray is not installed here (pip install 'riskplan[distributed]')")
SMALL = ["train.samples=400", "train.eval_episodes=1000", "train.bootstrap=40", "train.paths=1"]
TIMEOUT = 600


def setup_of(*overrides: str):
    return build_setup(riskplan.compose(["experiment=paper_team", "team.backend=ray", *SMALL, *overrides]))


# ------------------------------------------------------------------------------------------------ no Ray needed
def fake_step(l: int, grad: np.ndarray) -> Step:
    """A Step with a given gradient (the consensus part does not look at the episodes)."""
    stats = {"mean": 0.0, "cvar": 0.0, "value_at_risk": 0.0, "std": 0.0, "objective": 0.0}
    return Step(l, np.zeros(1), np.asarray(grad, dtype=float), 0.1, stats, 1)


@pytest.mark.parametrize(
    "overrides",
    [
        [],
        ["team.order=adapt_then_combine"],
        ["team.order=gradient_tracking"],
        ["team.consensus_rounds=3", "team.stale=latest"],
        ["team.robots=5", "team.graph=ring", "team.order=gradient_tracking", "team.consensus_rounds=2"],
        ["team.robots=4", "team.graph=complete", "team.aggregate=median"],
        ["team.robots=4", "team.graph=complete", "team.faults=[{robot: 1, kind: byzantine, from: 2, value: 50.0}]"],
        ["team.robots=4", "team.graph=complete", "team.faults=[{robot: 2, kind: stuck, from: 1}]"],
    ],
)
def test_robots_in_lockstep_step_as_the_simulated_team(overrides):
    """With every message of iteration l delivered before anyone mixes (staleness 0, the synchronous schedule), the
    robots' own rows give the simulated backend's consensus step (riskplan.engine.step.consensus_step, the Mixer) to rounding."""
    ray_setup = setup_of("team.staleness=0", *overrides)
    sim_setup = build_setup(riskplan.compose(["experiment=paper_team", *SMALL, *overrides]))
    n, m = ray_setup.robots, ray_setup.network.n_params
    cores = [RobotCore(ray_setup, i) for i in range(n)]
    thetas = np.tile(sim_setup.theta0, (n, 1))
    noise = np.random.default_rng(7)
    for l in range(6):
        grads = noise.normal(0.0, 0.3, (n, m))
        want = engine_step.consensus_step(
            sim_setup, sim_setup.mixer, thetas, grads, step_size(l, sim_setup.params.train.step_size), l
        )
        steps = [fake_step(l, grads[i]) for i in range(n)]
        begun = [core.begin(step) for core, step in zip(cores, steps)]
        values, carried = [b[0] for b in begun], [b[1] for b in begun]
        for r in range(cores[0].rounds):
            messages = [core.send(l, r, values[i], carried[i]) for i, core in enumerate(cores)]
            for i, message in enumerate(messages):
                for k in out_neighbours(ray_setup, i):
                    if message is not None:
                        cores[k].receive(message)
            for i, core in enumerate(cores):
                assert core.waiting_for(l, r) == [] or core.crash_from
                values[i], carried[i], staleness = core.mix(l, r, values[i], carried[i])
                assert math.isnan(staleness) or staleness == 0
        for i, core in enumerate(cores):
            core.finish(steps[i], values[i], carried[i], begun[i][2], 0.0, 0.0)
        thetas = np.array([core.theta for core in cores])
        np.testing.assert_allclose(thetas, want, rtol=1e-12, atol=1e-12)


def run_async(setup, iterations: int, seed: int, slow: int | None = None):
    """The team in one thread, the robots taking turns at random, every message delayed by a random number of
    turns (a robot mixes once `waiting_for` is empty): each robot's state after each iteration, in order, and the
    largest staleness mixed."""
    n, m = setup.robots, setup.network.n_params
    cores = [RobotCore(setup, i) for i in range(n)]
    draw = np.random.default_rng(seed)
    histories = [[core.state()] for core in cores]
    in_flight: list[tuple[int, int, object]] = []  # (due turn, receiver, message)
    busy: list[dict | None] = [None] * n
    worst, turn = -math.inf, 0
    while any(core.iteration < iterations for core in cores) or any(busy):
        turn += 1
        due = [x for x in in_flight if x[0] <= turn]
        in_flight = [x for x in in_flight if x[0] > turn]
        for _, k, message in sorted(due, key=lambda x: draw.random()):  # in any order
            cores[k].receive(message)
        i = int(draw.integers(n))
        if slow is not None and i == slow and draw.random() < 0.75:  # the slow robot gets a quarter of its turns
            continue
        core = cores[i]
        if busy[i] is None:
            if core.iteration >= iterations:
                continue
            l = core.iteration
            step = fake_step(l, draw.normal(0.0, 0.3, m))
            value, carried, eps = core.begin(step)
            busy[i] = {"step": step, "value": value, "carried": carried, "eps": eps, "round": 0, "sent": False}
        job = busy[i]
        l, r = job["step"].iteration, job["round"]
        if not job["sent"]:
            message = core.send(l, r, job["value"], job["carried"])
            for k in out_neighbours(setup, i):
                if message is not None:
                    in_flight.append((turn + int(draw.integers(0, 6)), k, message))
            job["sent"] = True
            continue
        if core.waiting_for(l, r):
            continue
        job["value"], job["carried"], staleness = core.mix(l, r, job["value"], job["carried"])
        worst = max(worst, staleness) if not math.isnan(staleness) else worst
        if r + 1 < core.rounds:
            job["round"], job["sent"] = r + 1, False
            continue
        core.finish(job["step"], job["value"], job["carried"], job["eps"], staleness, 0.0)
        histories[i].append(core.state())
        busy[i] = None
    return histories, worst


@pytest.mark.parametrize("stale", ["arrival", "latest"])
@pytest.mark.parametrize("staleness", [0, 1, 3])
def test_staleness_never_exceeds_the_bound_under_random_delays(stale, staleness):
    setup = setup_of(f"team.staleness={staleness}", f"team.stale={stale}", "team.robots=4", "team.graph=ring")
    histories, worst = run_async(setup, 25, seed=staleness, slow=2)
    assert all(int(h[-1]["iteration"]) == 25 for h in histories)  # no robot was left waiting forever
    assert worst <= staleness


@pytest.mark.parametrize("seed", range(4))
def test_tracking_mass_is_conserved_under_random_delays(seed):
    """sum_i y^i + the tracker mass in flight = sum_i Delta^i (and the push-sum weights sum to N) on every
    consistent cut of the robots' states, however late the messages."""
    setup = setup_of(
        "team.order=gradient_tracking",
        "team.robots=5",
        "team.graph=ring",
        "team.consensus_rounds=2",
        "team.staleness=2",
    )
    histories, _ = run_async(setup, 20, seed=seed, slow=seed % 5)
    ins = [in_neighbours(setup, i) for i in range(setup.robots)]
    draw = np.random.default_rng(seed)
    for _ in range(30):  # cuts of random prefixes of the histories
        prefixes = [h[: int(draw.integers(1, len(h) + 1))] for h in histories]
        index = consistent_cut(prefixes, ins)
        assert index is not None
        cut = [p[k] for p, k in zip(prefixes, index)]
        for i, state in enumerate(cut):  # consistent: nobody holds a message from after its sender's cut
            for k, j in enumerate(ins[i]):
                assert state["latest_sent"][:, k].max() <= int(cut[j]["iteration"]) - 1
        held, want = tracking_balance(setup, cut)
        np.testing.assert_allclose(held, want, rtol=1e-12, atol=1e-9)
    held, want = tracking_balance(setup, [h[-1] for h in histories])
    np.testing.assert_allclose(held, want, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize(
    "risk", ["risk=cvar", "risk=neutral", "risk=wang", "risk=mean_cvar", "risk=entropic", "risk.schedule.kind=linear"]
)
def test_each_robot_estimates_its_gradient_as_the_simulated_team_does(risk):
    """engine.step.estimate for robot i alone (what a Ray robot runs) gives the whole team's row i."""
    setup = setup_of(risk)
    draw = np.random.default_rng(3)
    z = draw.normal(1500.0, 400.0, (3, 300))
    scores = draw.normal(0.0, 1.0, (3, 300, 2))
    for l in (0, 7):
        team = engine_step.estimate(setup, l, z, scores)
        for i in range(3):
            alone = engine_step.estimate(setup, l, z[i : i + 1], scores[i : i + 1], robots=[i], where=f"robot {i}")
            np.testing.assert_array_equal(alone.grads[0], team.grads[i])
            np.testing.assert_array_equal(alone.levels[0], team.levels[i])
            assert {k: v[0] for k, v in alone.stats.items()} == {k: v[i] for k, v in team.stats.items()}


def test_a_robots_row_has_the_simulated_columns_then_staleness():
    core = RobotCore(setup_of(), 1)
    step = fake_step(0, np.array([0.3, 0.4]))
    value, carried, eps = core.begin(step)
    row = core.finish(step, value, carried, eps, 2.0, 0.01)
    stats = {k: np.array([v]) for k, v in step.stats.items()}
    (simulated,) = metrics_rows._robot_rows(
        0, stats, np.array([core.theta]), np.array([step.grad]), eps, math.nan, 1, 0.01, [0.1], [True]
    )
    assert list(row) == [*simulated, "staleness"] and row["staleness"] == 2.0
    assert [type(v) for v in row.values()][:-1] == [type(v) for v in simulated.values()]


def test_a_robot_alone_steps_as_the_centralized_loop():
    setup = setup_of("team.robots=1")
    core = RobotCore(setup, 0)
    step = core.compute(0)
    value, carried, eps = core.begin(step)
    assert core.rounds == 0 and carried is None
    row = core.finish(step, value, carried, eps, math.nan, 0.0)
    np.testing.assert_allclose(core.theta, setup.theta0 + eps * step.grad)
    assert row["iteration"] == 0 and core.iteration == 1


def test_checkpoints_are_checked_against_the_team(tmp_path):
    setup = setup_of()
    expected = [initial_state(setup, i) for i in range(setup.robots)]
    assert tuple(expected[0]) == STATE_KEYS

    save_team_checkpoint(tmp_path, expected, [])
    loaded = load_team_checkpoint(tmp_path, setup, expected)
    assert loaded.iterations == [0, 0, 0]
    for state, want in zip(loaded.robots, expected):
        assert all(np.array_equal(state[k], want[k]) and state[k].dtype == want[k].dtype for k in want)
    bigger = setup_of("team.robots=4", "team.graph=ring")
    with pytest.raises(BadInput, match="4"):
        load_team_checkpoint(tmp_path, bigger, [initial_state(bigger, i) for i in range(4)])


def test_without_ray_the_backend_is_one_line(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    with pytest.raises(MissingExtra) as err:  # bad input, before the run directory is made
        riskplan.train(riskplan.compose(["experiment=paper_team", "team.backend=ray", *SMALL]), tmp_path / "r")
    assert err.value.where == "team.backend=ray"
    assert str(err.value).endswith("pip install 'riskplan[distributed]'"), str(err.value)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "r").exists()


# ------------------------------------------------------------------------------------------------ a local Ray
def _start_time(pid: int) -> int | None:
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19])
    except (OSError, IndexError, ValueError):
        return None


def _descendants(pid: int) -> dict[int, int]:
    """{pid: start time} of the live processes below pid."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
                children.setdefault(parent, []).append(int(entry.name))
    found, todo = {}, list(children.get(pid, []))
    while todo:
        child = todo.pop()
        start = _start_time(child)
        if start is not None and child not in found:
            found[child] = start
            todo.extend(children.get(child, []))
    return found


def _alive(processes: dict[int, int]) -> list[int]:
    alive = []
    for pid, start in processes.items():
        with contextlib.suppress(OSError, IndexError):
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
            if _start_time(pid) == start and state != "Z":
                alive.append(pid)
    return alive


def _cli() -> list[str]:
    script = Path(sys.executable).with_name("riskplan")
    return [str(script)] if script.is_file() else [sys.executable, "-m", "riskplan"]


class Watched:
    """`riskplan ARGS` in a session of its own, with every process it ever started recorded (Ray's own included),
    so that a test can check none outlives it."""

    def __init__(self, args: list[str], cwd: Path):
        env = {k: v for k, v in os.environ.items() if not k.startswith("RISKPLAN_TEST_")}
        self.proc = subprocess.Popen(
            [*_cli(), *args],
            cwd=cwd,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        self.seen: dict[int, int] = {}

    def look(self) -> None:
        self.seen.update(_descendants(self.proc.pid))

    def wait_for(self, condition, what: str) -> None:
        """Poll until condition() holds (the run still going), recording processes meanwhile."""
        deadline = time.monotonic() + TIMEOUT
        while not condition():
            self.look()
            assert self.proc.poll() is None, f"the run ended before {what}: {self.proc.stderr.read()}"
            assert time.monotonic() < deadline, f"no {what} within {TIMEOUT} s"
            time.sleep(0.1)
        self.look()

    def finish(self) -> tuple[int, str, str]:
        out, err = self.proc.communicate(timeout=TIMEOUT)
        deadline = time.monotonic() + 30
        while _alive(self.seen) and time.monotonic() < deadline:  # Ray's processes take a moment to go
            time.sleep(0.2)
        assert not _alive(self.seen), f"left running: {_alive(self.seen)}"
        return self.proc.returncode, out, err


def logged_iterations(out: Path) -> int:
    """How many iterations run.mcap holds complete (0 before it exists)."""
    path = out / "run.mcap"
    if not path.exists():
        return 0
    with contextlib.suppress(Exception):
        return int(read_log(path).metrics.iteration.nunique())
    return 0


def actors_of(out: Path) -> list[dict]:
    with contextlib.suppress(Exception):
        return read_log(out / "run.mcap").metadata["ray_team"]["robots"]
    return []


def assert_complete_run(out: Path, iterations: int, robots: int, staleness: int) -> pd.DataFrame:
    """A finished ray run: every (iteration, robot) row once (and the network average), staleness bounded."""
    metrics = pd.read_parquet(out / "metrics.parquet")
    pairs = sorted(zip(metrics.iteration, metrics.robot))
    assert pairs == [(l, r) for l in range(iterations) for r in [-1, *range(robots)]]
    mixed = metrics.staleness[metrics.robot >= 0].dropna()
    assert len(mixed) and mixed.max() <= staleness
    summary = json.loads((out / "summary.json").read_text())
    assert summary["deterministic"] is False and summary["iterations"] == iterations
    return metrics


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray instance for the in-process runs of this module (a run uses a Ray that is up as it is)."""
    if not HAVE_RAY:
        pytest.skip("ray is not installed here (pip install 'riskplan[distributed]')")
    import ray

    ray.init(
        address="local",
        num_cpus=2,
        include_dashboard=False,
        object_store_memory=100 * 10**6,
        log_to_driver=False,
        logging_level="ERROR",
    )
    try:
        yield ray
    finally:
        ray.shutdown()


def train_ray(out: Path, *overrides: str):
    return riskplan.train(
        riskplan.compose(["experiment=paper_team", "team.backend=ray", *SMALL, *overrides]), out, progress=False
    )


@pytest.mark.slow
def test_a_ray_run_writes_what_a_simulated_run_writes(local_ray, tmp_path):
    ray_run = train_ray(tmp_path / "ray", "train.iterations=8")
    sim_run = riskplan.train(
        riskplan.compose(["experiment=paper_team", *SMALL, "train.iterations=8"]), tmp_path / "sim", progress=False
    )
    names = lambda d: sorted(str(p.relative_to(d)) for p in d.rglob("*") if p.is_file() and p.name != ".riskplan.lock")
    assert names(tmp_path / "ray") == names(tmp_path / "sim")
    assert list(ray_run.metrics.columns) == [*sim_run.metrics.columns, "staleness"]
    for table in ("eval", "trajectories"):
        assert list(getattr(ray_run, table).columns) == list(getattr(sim_run, table).columns)
    assert sim_run.summary["deterministic"] is True
    assert set(ray_run.summary) == set(sim_run.summary)
    metrics = assert_complete_run(tmp_path / "ray", 8, 3, 2)
    average = metrics[metrics.robot == -1].set_index("iteration")
    robots = metrics[metrics.robot >= 0]
    assert (robots.consensus_error.to_numpy() == average.consensus_error.loc[robots.iteration].to_numpy()).all()
    assert (average.samples == 3 * 400).all()
    log = read_log(tmp_path / "ray" / "run.mcap")
    assert log.complete
    assert set(log.metadata) == set(read_log(tmp_path / "sim" / "run.mcap").metadata) | {"ray_team", "ray_team_end"}
    assert log.metadata["policy"]["theta_names"] == list(sim_run.summary["theta_names"])
    where = log.metadata["ray_team"]["robots"]
    assert [r["robot"] for r in where] == [0, 1, 2] and all(r["node_id"] and r["pid"] for r in where)
    checkpoint = json.loads((tmp_path / "ray" / CHECKPOINT).read_text())
    assert checkpoint["format"] == "ray" and [int(r["arrays"]["iteration"]) for r in checkpoint["robots"]] == [8] * 3


@pytest.mark.slow
def test_the_consensus_error_shrinks(local_ray, tmp_path):
    """paper_team, a step that decays slowly (eps from 0.1 to 0.05 in 60 iterations): the robots drift apart while
    the gradients are large, then agree more and more."""
    run = train_ray(tmp_path / "r", "train.iterations=60", "train.samples=1000", "train.step_size.decay=60")
    error = run.metrics[run.metrics.robot == -1].set_index("iteration").consensus_error
    assert error.iloc[-10:].mean() < 0.5 * error.iloc[1:20].max()
    assert error.iloc[-10:].mean() < error.iloc[1:20].mean()


@pytest.mark.slow
@pytest.mark.parametrize("stale,staleness", [("arrival", 2), ("latest", 1)])
def test_the_staleness_bound_holds_with_a_robot_four_times_slower(local_ray, tmp_path, stale, staleness):
    run = train_ray(
        tmp_path / "r",
        "train.iterations=25",
        "team.speeds=[1,4,1]",
        f"team.stale={stale}",
        f"team.staleness={staleness}",
    )
    metrics = assert_complete_run(tmp_path / "r", 25, 3, staleness)
    slow = metrics[metrics.robot == 1]
    assert slow.staleness.dropna().max() <= staleness
    assert run.summary["deterministic"] is False


@pytest.mark.slow
def test_gradient_tracking_keeps_its_sum_with_real_messages(local_ray, tmp_path):
    out = tmp_path / "r"
    train_ray(
        out,
        "train.iterations=20",
        "train.checkpoint_every=2",
        "team.order=gradient_tracking",
        "team.consensus_rounds=2",
        "team.speeds=[1,3,1]",
    )
    assert_complete_run(out, 20, 3, 2)
    end = read_log(out / "run.mcap").metadata["ray_team_end"]
    assert end["tracking_residual"] <= 1e-9  # the largest |residual| over every checkpointed cut
    setup = build_setup(
        riskplan.compose(
            [
                "experiment=paper_team",
                "team.backend=ray",
                *SMALL,
                "train.iterations=20",
                "team.order=gradient_tracking",
                "team.consensus_rounds=2",
                "team.speeds=[1,3,1]",
                "train.checkpoint_every=2",
            ]
        )
    )
    final = load_team_checkpoint(out, setup, [initial_state(setup, i) for i in range(3)])
    held, want = tracking_balance(setup, final.robots)
    np.testing.assert_allclose(held, want, rtol=1e-12, atol=1e-9)


# 40 iterations: the signal or kill lands after the first checkpoint (iteration 5) with 35 slowed iterations to spare
# (with 15, a loaded CI machine once let a robot reach the last before SIGTERM was handled), and the resume, which runs
# every iteration left at the same slowed speed, has at most those 35 to finish
LONG_ITERATIONS = 40
LONG = [
    "experiment=paper_team",
    "team.backend=ray",
    f"train.iterations={LONG_ITERATIONS}",
    "train.samples=3000",
    "train.eval_episodes=1000",
    "train.bootstrap=40",
    "train.paths=1",
    "train.checkpoint_every=5",
    "team.speeds=[40,40,40]",  # an iteration sleeps 39x its compute: a signal lands mid-run however loaded the machine
]


@pytest.mark.slow
@needs_ray
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_checkpoints_every_robot_and_resume_finishes(tmp_path, signum):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it: Ray's own processes get it too) or
    SIGTERM to the driver: interrupted, exit 130/143, every robot checkpointed; --resume finishes the run; no Ray
    process outlives either."""
    out = tmp_path / "r"
    run = Watched(["train", *LONG, f"hydra.run.dir={out}"], tmp_path)
    # the first checkpoint (team iteration 5) is written at once; run.mcap shows iterations a chunk at a time, so
    # waiting for it let a loaded machine run nearly all of them before the signal
    run.wait_for(lambda: (out / CHECKPOINT).exists(), "a checkpoint")
    if signum == signal.SIGINT:
        os.killpg(run.proc.pid, signal.SIGINT)
    else:
        run.proc.send_signal(signal.SIGTERM)
    code, _, err = run.finish()
    assert code == 128 + signum, err
    assert json.loads((out / "status.json").read_text())["status"] == "interrupted"
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "--resume" in lines[0], err
    checkpoint = json.loads((out / CHECKPOINT).read_text())
    reached = [int(r["arrays"]["iteration"]) for r in checkpoint["robots"]]
    assert checkpoint["format"] == "ray" and min(reached) >= 1 and max(reached) < LONG_ITERATIONS
    again = Watched(["train", "--resume", str(out)], tmp_path)
    code, _, err = again.finish()
    assert code == 0, err
    assert_complete_run(out, LONG_ITERATIONS, 3, 2)
    assert json.loads((out / "status.json").read_text())["status"] == "done"


@pytest.mark.slow
@needs_ray
def test_kill_9_of_a_robot_stops_the_run_and_resume_restarts_every_robot(tmp_path):
    """The documented rule: a robot's actor that dies stops the run with one line naming it, every robot
    checkpointed; --resume restarts all the actors and finishes."""
    out = tmp_path / "r"
    run = Watched(["train", *LONG, f"hydra.run.dir={out}"], tmp_path)
    run.wait_for(lambda: logged_iterations(out) >= 4 and len(actors_of(out)) == 3, "4 iterations")
    victim = actors_of(out)[1]
    os.kill(victim["pid"], signal.SIGKILL)
    code, _, err = run.finish()
    assert code == 1, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "robot 1's Ray actor died" in lines[0] and "Traceback" not in err, err
    assert json.loads((out / "status.json").read_text())["status"] == "failed"
    reached = [int(r["arrays"]["iteration"]) for r in json.loads((out / CHECKPOINT).read_text())["robots"]]
    assert min(reached) >= 1 and max(reached) < LONG_ITERATIONS
    again = Watched(["train", "--resume", str(out)], tmp_path)
    code, _, err = again.finish()
    assert code == 0, err
    assert_complete_run(out, LONG_ITERATIONS, 3, 2)
    new = {r["robot"]: r["pid"] for r in read_log(out / "run.mcap").metadata["ray_team"]["robots"]}
    assert new[1] != victim["pid"]


@pytest.mark.slow
@needs_ray
def test_an_unreachable_cluster_is_one_line(tmp_path):
    out = tmp_path / "r"
    run = Watched(
        ["train", "experiment=paper_team", "team.backend=ray", "team.address=127.0.0.1:9", f"hydra.run.dir={out}"],
        tmp_path,
    )
    code, _, err = run.finish()
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 1 and len(lines) == 1 and "team.address" in lines[0] and "127.0.0.1:9" in lines[0], err
    assert not (out / "run.mcap").exists()


@pytest.mark.slow
def test_a_finished_run_extends_and_one_killed_in_its_evaluation_finishes(local_ray, tmp_path, monkeypatch):
    out = tmp_path / "r"
    train_ray(out, "train.iterations=6")
    longer = riskplan.compose(["experiment=paper_team", "team.backend=ray", *SMALL, "train.iterations=10"])
    _, done = training.prepare_resume(longer, out)
    assert not done
    files = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    with monkeypatch.context() as without_ray:  # robots with iterations left need Ray: bad input, nothing touched
        without_ray.setitem(sys.modules, "ray", None)
        for resume in (lambda: training.prepare_resume(longer, out), lambda: training.train(longer, out, resume=True)):
            with pytest.raises(MissingExtra) as err:
                resume()
            assert err.value.where == "team.backend=ray" and "\n" not in str(err.value)
            assert str(err.value).endswith("pip install 'riskplan[distributed]'"), str(err.value)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == files
    training.train(longer, out, resume=True)
    assert_complete_run(out, 10, 3, 2)
    for name in ("summary.json", "metrics.parquet"):  # as if killed while it evaluated
        (out / name).unlink()
    with monkeypatch.context() as without_ray:  # every robot is at train.iterations: it only evaluates, without Ray
        without_ray.setitem(sys.modules, "ray", None)
        _, done = training.prepare_resume(longer, out)
        assert not done
        training.train(longer, out, resume=True)
    assert_complete_run(out, 10, 3, 2)
