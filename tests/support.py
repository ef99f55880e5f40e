"""What several test files share: the small run configs, typed team settings and networks, set-ups built from
overrides, the 3x3 world whose every path is enumerated, `riskplan` in a subprocess, and the comparison of a run's outputs with another run's.

Test files import it as `from support import ...`: pytest puts tests/ on sys.path when it loads tests/conftest.py
(the test folders have no __init__.py). Fixtures live in tests/conftest.py.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from riskplan.config.schema import RiskplanConf, TeamConf
from riskplan.config.typed import typed
from riskplan.config.validate import check_team
from riskplan.engine import rng
from riskplan.engine.policy import probabilities
from riskplan.engine.rollout import simulate
from riskplan.engine.team.mixer import Mixer
from riskplan.engine.team.network import Network, build_network
from riskplan.experiments.driver_watch import ENV as DRIVER_ENV
from riskplan.run.build import build_setup
from riskplan.run.checkpoint import CHECKPOINT, CRASH_ENV
from riskplan.run.compose import compose
from riskplan.run.log_reader import read_log
from riskplan.run.recorder import STOP_ENV
from riskplan.run.run_files import FINISHED, STATUS
from riskplan.util.errors import BadInput
from riskplan.util.lock import holder

# ------------------------------------------------------------------------------------------------ run configs
# The fastest overrides that still make a meaningful run: a few iterations, every output written (a checkpoint, the
# evaluation, the bootstrap intervals, one path per policy). A test that needs other numbers adds them after it
# ([*TINY, "train.iterations=12", ...]: the last value of a key wins), so the differences are visible.
TINY = ["train.iterations=3", "train.samples=200", "train.eval_episodes=200", "train.bootstrap=40", "train.paths=1"]
# A little more of everything (the `fast_overrides` fixture): the CLI, sweep, report and reproduce tests, whose
# assertions know these numbers (5 iterations, 500 samples per robot).
FAST = ["train.iterations=5", "train.samples=500", "train.eval_episodes=2000", "train.bootstrap=50", "train.paths=3"]
# A run long enough to checkpoint several times (every 5 of its 30 iterations): killed and resumed runs, and the
# runs the determinism checks compare.
CHECKPOINTED = [*TINY, "train.iterations=30", "train.checkpoint_every=5"]
CHECKPOINTED_TEAM = [*CHECKPOINTED, "experiment=paper_team", "team.delay.max=2", "team.drop=0.2"]  # mixer state


# ------------------------------------------------------------------------------------------------ set-ups, teams
def setup_of(*overrides: str):
    """The built RunSetup of TINY plus overrides (composed without the model's checks: build_setup makes them)."""
    return build_setup(compose([*TINY, *overrides], validate=False))


def bad_input(*overrides: str) -> BadInput:
    """The BadInput that building TINY plus overrides raises, checked to be one plain line."""
    with pytest.raises(BadInput) as err:
        setup_of(*overrides)
    assert "\n" not in str(err.value) and "`" not in str(err.value) and "|" not in str(err.value)
    return err.value


def team_conf(**values) -> TeamConf:
    """The typed TeamConf of these `team` values (nested dicts allowed), checked as a build checks it: BadInput
    naming `team.<key>` on a bad type, choice or range."""
    team = typed({"team": values}).team
    check_team(team)
    return team


def net_of(m: int = 2, seed: int = 0, **values) -> Network:
    """Network of a team built from overrides."""
    return build_network(team_conf(**values), m, seed)


def run_rounds(network, team, thetas, iterations, seed=0, rounds=1):
    """Mix `iterations` times (each with `rounds` rounds); return the per-iteration trajectory."""
    mixer = Mixer(network, team, seed)
    out = [thetas]
    for l in range(iterations):
        for r in range(rounds):
            thetas = mixer.mix(thetas, l, r)
        out.append(thetas)
    return out


# ------------------------------------------------------------------------------------------------ exact enumeration
# A 3x3 world, K = 3, deterministic rewards: few enough paths to enumerate every one, so objectives are exact.
WORLD_3X3 = {
    "world": {
        "size": [3, 3],
        "start": [0, 0],
        "horizon": 3,
        "stop_at_source": True,
        "sources": [
            {"position": [2, 0], "covariance": [[1.0, 0.0], [0.0, 1.0]], "reward": 10.0},
            {"position": [0, 2], "covariance": [[2.0, 0.5], [0.5, 1.0]], "reward": 4.0},
        ],
        "regions": [
            {"name": "bad", "rect": [1, 1, 1, 2], "reward": -6.0, "risky": True},
            {"name": "rest", "rect": [0, 0, 2, 2], "reward": 1.0},
        ],
    },
    "train": {"theta0": [0.5, 0.2]},
}


def world_3x3(*extra: dict):
    """The built RunSetup of WORLD_3X3 merged with extra config dicts."""
    return build_setup(OmegaConf.merge(OmegaConf.structured(RiskplanConf), WORLD_3X3, *extra))


def exact_outcomes(setup, probs: np.ndarray, step_scores: np.ndarray | None = None):
    """Every path of the policy with move probabilities probs (C, 5), enumerated (episodes stop at a source): the
    distinct totals z_k (ascending), their probabilities p_k and, given the per-move scores (C, 5, d), d p_k / d theta
    = sum over the paths to z_k of p(path) * score(path) (the score of eq. 10; None without step_scores)."""
    world = setup.world
    sources = {int(c): j for j, c in enumerate(world.source_cells)}
    rewards = [r.params[0] for r in world.region_rewards]
    source_rewards = [r.params[0] for r in world.source_rewards]
    out: dict[float, tuple[float, np.ndarray]] = {}

    def add(z, p, score):
        q, dq = out.get(z, (0.0, 0.0))
        out[z] = (q + p, dq + p * score)

    def walk(cell, k, z, p, score):
        if k == world.horizon:
            add(z, p, score)
            return
        for a in range(5):
            nxt = int(world.next_cell[cell, a])
            gain = rewards[world.region_of[nxt]]
            p_next = p * probs[cell, a]
            score_next = score if step_scores is None else score + step_scores[cell, a]
            if nxt in sources:
                add(z + gain + source_rewards[sources[nxt]], p_next, score_next)
            else:
                walk(nxt, k + 1, z + gain, p_next, score_next)

    walk(int(world.starts[0]), 0, 0.0, 1.0, 0.0 if step_scores is None else np.zeros(step_scores.shape[-1]))
    z = np.array(sorted(out))
    gradient = None if step_scores is None else np.array([out[v][1] for v in z])
    return z, np.array([out[v][0] for v in z]), gradient


def exact_distribution(setup, theta) -> dict[float, float]:
    """P(Z = z) under the setup's features policy with weights theta, by enumerating every path."""
    probs = probabilities(setup.policy.move_features(setup.world), np.asarray(theta, dtype=float))
    z, p, _ = exact_outcomes(setup, probs)
    return dict(zip(z.tolist(), p.tolist()))


def exact_mean(setup, theta) -> float:
    """E[Z] under the setup's features policy with weights theta, exactly."""
    return sum(z * p for z, p in exact_distribution(setup, theta).items())


def rollouts(setup, theta, episodes: int, seed: int = 0):
    """One robot's episodes of the setup's kernel under theta (the training stream of `seed`)."""
    keys = rng.robot_keys(seed, rng.TRAIN, 0, 1)
    return simulate(setup.world, setup.kernel, np.array([theta]), setup.world.starts, keys, episodes)


# ------------------------------------------------------------------------------------------------ the CLI
CLI = [sys.executable, "-c", "from riskplan.cli import main; main()"]
TIMEOUT = 300


def riskplan_cli(cwd: Path, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    """`riskplan ARGS` in cwd, in a subprocess of this interpreter (no terminal: a sweep's view prints one line per
    finished job)."""
    return subprocess.run(
        [*CLI, *args], cwd=cwd, capture_output=True, text=True, timeout=TIMEOUT, env={**os.environ, **(env or {})}
    )


def riskplan_command() -> list[str]:
    """The installed console script next to this interpreter (the way users run it)."""
    script = Path(sys.executable).with_name("riskplan")
    return [str(script)] if script.is_file() else [sys.executable, "-c", "from riskplan.cli import main; main()"]


def child_env(**extra: str) -> dict[str, str]:
    """The test's environment without the fault-injection variables, plus `extra`; nor the name of a sweep driver
    that a sweep run in this test process gave itself (its workers' variable: a child would take itself for one)."""
    env = {k: v for k, v in os.environ.items() if k not in (CRASH_ENV, STOP_ENV, DRIVER_ENV)}
    env.update(extra)
    return env


def run_cli(args: list[str], cwd: Path, **env: str) -> subprocess.CompletedProcess:
    """`riskplan <args>` through the console script in a subprocess; returns when it exits (or is killed)."""
    return subprocess.run(
        [*riskplan_command(), *args], cwd=cwd, env=child_env(**env), capture_output=True, text=True, timeout=TIMEOUT
    )


def train_cli(overrides: list[str], out: Path, **env: str) -> subprocess.CompletedProcess:
    """`riskplan train <overrides> hydra.run.dir=<out>` in a subprocess."""
    return run_cli(["train", *overrides, f"hydra.run.dir={out}"], out.parent, **env)


def resume_cli(out: Path, *overrides: str, **env: str) -> subprocess.CompletedProcess:
    """`riskplan train --resume <out> [overrides]` in a subprocess."""
    return run_cli(["train", "--resume", str(out), *overrides], out.parent, **env)


@contextlib.contextmanager
def mounted(target: Path, *options: str):
    """A real mount at target (tmpfs or a read-only bind), unmounted afterwards; skip when mounting is refused."""
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs or a read-only bind needs root")
    target.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(["mount", *options, str(target)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"mount refused here: {done.stderr.strip()}")
    try:
        yield target
    finally:
        subprocess.run(["umount", "-l", str(target)], capture_output=True)


@contextlib.contextmanager
def held_by_another_process(directory: Path):
    """Another process holds DIR's writers' lock (riskplan.util.lock) for the block, as a running riskplan would;
    yields its pid."""
    code = f"from riskplan.util.lock import hold_lock\nwith hold_lock({str(directory)!r}):\n input()"
    other = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE)
    try:
        deadline = time.time() + 30
        while holder(directory) != other.pid and time.time() < deadline:
            time.sleep(0.05)
        yield other.pid
    finally:
        other.communicate(b"\n", timeout=30)


def kill_after_iteration(overrides: list[str], out: Path, iteration: int) -> int:
    """Start `riskplan train`, let it log `iteration` (it then stops itself), SIGKILL it; its return code."""
    proc = subprocess.Popen(
        [*riskplan_command(), "train", *overrides, f"hydra.run.dir={out}"],
        cwd=out.parent,
        env=child_env(**{STOP_ENV: str(iteration)}),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        _, status = os.waitpid(proc.pid, os.WUNTRACED)  # returns once the child is stopped (or has exited)
        assert os.WIFSTOPPED(status), f"the run ended before iteration {iteration} (status {status})"
        proc.send_signal(signal.SIGKILL)
        return proc.wait(timeout=TIMEOUT)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def alive(pid: int) -> bool:
    """Whether pid is a live process (a zombie, state Z, counts as gone)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


# ------------------------------------------------------------------------------------------------ run outputs
TABLES = ("metrics", "eval", "trajectories")
# summary.json fields that say how the run was carried out (its time, where it was resumed), not its results
WALL_CLOCK = {"wall_time", "throughput_episodes_per_s", "resumed_at"}


def files(root: Path) -> dict[str, bytes]:
    """Every file below root with its bytes."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def stand_in_job(out: Path, status: dict) -> None:
    """A folder as a finished sweep job leaves it, for the checks that read no more than whether its files are there
    (and its .hydra/ files' shapes): stand-ins of every file a finished job has, and its status.json."""
    (out / ".hydra").mkdir(parents=True, exist_ok=True)
    (out / ".hydra" / "config.yaml").write_text("seed: 0\n")
    (out / ".hydra" / "hydra.yaml").write_text("hydra: {}\n")
    (out / ".hydra" / "overrides.yaml").write_text("- seed=0\n")
    for name in FINISHED:
        (out / name).write_text("{}")
    (out / STATUS).write_text(json.dumps(status))


def checkpoint_iteration(out: Path, name: str = CHECKPOINT) -> int:
    """The iteration a checkpoint file was written at (it parses: never half a file)."""
    return json.loads((out / name).read_text())["iteration"]


def comparable_summary(summary: dict) -> dict:
    """summary.json without wall-clock fields and the git SHA (the shared tree may get commits meanwhile)."""
    out = {k: v for k, v in summary.items() if k not in WALL_CLOCK}
    out["provenance"] = {k: v for k, v in summary.get("provenance", {}).items() if k != "git_sha"}
    return json.loads(json.dumps(out))  # NaN-safe comparison through one JSON round trip


def assert_same_outputs(run: Path, reference: Path) -> None:
    """Every value of every table and of summary.json equal, wall-clock fields aside; the same for run.mcap."""
    for name in TABLES:
        got, want = (pd.read_parquet(d / f"{name}.parquet") for d in (run, reference))
        if name == "metrics":
            got, want = got.drop(columns="seconds"), want.drop(columns="seconds")
        pd.testing.assert_frame_equal(got, want, check_exact=True, obj=name)
    got, want = (json.loads((d / "summary.json").read_text()) for d in (run, reference))
    assert comparable_summary(got) == comparable_summary(want)
    got_log, want_log = read_log(run / "run.mcap"), read_log(reference / "run.mcap")
    assert got_log.complete and want_log.complete, got_log.problem
    pd.testing.assert_frame_equal(
        got_log.metrics.drop(columns="seconds"),
        want_log.metrics.drop(columns="seconds"),
        check_exact=True,
        obj="run.mcap metrics",
    )
    pd.testing.assert_frame_equal(got_log.eval, want_log.eval, check_exact=True, obj="run.mcap eval")
    pd.testing.assert_frame_equal(
        got_log.trajectories, want_log.trajectories, check_exact=True, obj="run.mcap trajectories"
    )
    assert comparable_summary(got_log.summary) == comparable_summary(want_log.summary)


def assert_log_holds_each_iteration_once(run: Path, iterations: int, robots: tuple[int, ...]) -> None:
    """run.mcap's /metrics: every (iteration, robot) exactly once, and the same rows as metrics.parquet."""
    log = read_log(run / "run.mcap")
    pairs = list(zip(log.metrics.iteration, log.metrics.robot))
    assert pairs == [(i, r) for i in range(iterations) for r in sorted(robots)]
    pd.testing.assert_frame_equal(log.metrics, pd.read_parquet(run / "metrics.parquet"), check_exact=True)
