"""riskplan.envs: the Gymnasium and PettingZoo environments follow the numba kernel's world.

The distribution tests compare environment episodes with `riskplan.engine.rollout.simulate` under the same softmax policy:
mean, quantiles and CVaR of the total reward, risky steps, moves and the source reached. Each tolerance is 4
standard errors of the difference, estimated from the two samples themselves (never a fixed number).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

gymnasium = pytest.importorskip("gymnasium")
pettingzoo = pytest.importorskip("pettingzoo")

from gymnasium.utils.env_checker import check_env  # noqa: E402
from pettingzoo.test import parallel_api_test, parallel_seed_test  # noqa: E402

from riskplan.engine import rng as R  # noqa: E402
from riskplan.engine.policy import move_features  # noqa: E402
from riskplan.engine.rollout import simulate  # noqa: E402
from riskplan.envs import SensorPlanningEnv, SensorTeamEnv, SoftmaxPolicy, Worlds, make_setup, run_episodes  # noqa: E402
from riskplan.experiments.environments.gym import ENV_ID  # noqa: E402
from riskplan.risk import cvar, value_at_risk  # noqa: E402

TRAINED, THETA0 = (46.6, -0.8), (20.0, 20.0)  # the paper's trained CVaR policy and its initial one
KERNEL_EPISODES = 200_000
BATCH_EPISODES = 20_000  # riskplan.envs.run_episodes: the environments' dynamics, all episodes at once
GYM_EPISODES = 3_000  # one by one through SensorPlanningEnv.step (~1 ms an episode in Python)
TEAM_EPISODES = 700  # SensorTeamEnv episodes of the paper's 3-robot team
MOBILE = [
    "world.sources.0.motion.kind=random_walk",
    "world.sources.0.motion.prob=0.5",
    "world.sources.1.motion.kind=random_walk",
    "world.sources.1.motion.prob=0.3",
]
SIGMAS = 4.0
BETA = 0.1
MEASURED: list[str] = []  # the statistics compared, printed with pytest -s


@pytest.fixture(scope="module")
def paper():
    return make_setup([])


@pytest.fixture(scope="module")
def mobile():
    return make_setup(MOBILE)


def kernel(setup, theta, episodes=KERNEL_EPISODES, seed=11):
    """The kernel's outcomes of `episodes` episodes of theta from the first robot's start."""
    return simulate(
        setup.world, setup.kernel, np.array([theta]), setup.world.starts[:1], R.robot_keys(seed, R.EVAL, 0, 1), episodes
    )


def quantile_se(z: np.ndarray, p: float) -> float:
    """Standard error of the empirical p-quantile, distribution-free: half the spread of the order statistics one
    binomial standard deviation sqrt(p(1-p)/n) either side of p (the sectioning estimate of sqrt(p(1-p)/n) / f)."""
    d = math.sqrt(p * (1 - p) / z.size)
    return (value_at_risk(z, min(p + d, 1.0)) - value_at_risk(z, max(p - d, 1.0 / z.size))) / 2


def cvar_se(z: np.ndarray, beta: float) -> float:
    """Standard error of the empirical CVaR (Rockafellar-Uryasev): its influence function is (z - v) 1{z <= v} / beta
    plus constants, so the variance is Var((z - v) 1{z <= v}) / (beta^2 n)."""
    v = value_at_risk(z, beta)
    return float(np.std(np.minimum(z - v, 0.0), ddof=1) / (beta * math.sqrt(z.size)))


def mean_se(x: np.ndarray) -> float:
    return float(np.std(x, ddof=1) / math.sqrt(x.size))


def agree(label: str, env, ker) -> None:
    """Every statistic of the environment's episodes within SIGMAS standard errors of the kernel's."""
    z, k = np.asarray(env.total_reward, float), np.asarray(ker.total_reward, float)
    checks = [
        ("mean", z.mean(), k.mean(), mean_se(z), mean_se(k)),
        (f"cvar{BETA}", cvar(z, BETA), cvar(k, BETA), cvar_se(z, BETA), cvar_se(k, BETA)),
    ]
    for p in (BETA, 0.5, 0.9):
        checks.append((f"q{p}", value_at_risk(z, p), value_at_risk(k, p), quantile_se(z, p), quantile_se(k, p)))
    for field in ("risky_steps", "steps"):
        x, y = np.asarray(getattr(env, field), float), np.asarray(getattr(ker, field), float)
        checks.append((f"mean {field}", x.mean(), y.mean(), mean_se(x), mean_se(y)))
    for j in (-1, 0, 1):
        x, y = np.asarray(env.source_reached) == j, np.asarray(ker.source_reached) == j
        checks.append((f"P(source {j})", x.mean(), y.mean(), mean_se(x.astype(float)), mean_se(y.astype(float))))
    bad = []
    for name, a, b, se_a, se_b in checks:
        se = math.hypot(se_a, se_b)
        gap = abs(a - b) / se if se > 0 else (0.0 if a == b else math.inf)
        MEASURED.append(f"{label} n={z.size}: {name} env {a:.4g} kernel {b:.4g} (se {se:.3g}, {gap:.2f} se)")
        if gap > SIGMAS:
            bad.append(MEASURED[-1])
    print("\n".join(MEASURED[-len(checks) :]))
    assert not bad, "\n".join(bad)


class Outcomes:
    """Episode outcomes collected from an environment loop, named as riskplan.engine.rollout.EpisodeBatch names them."""

    def __init__(self):
        self.rows: list[tuple[float, int, int, int]] = []

    def add(self, total: float, info: dict) -> None:
        self.rows.append((total, info["risky_steps"], info["source_reached"], info["steps"]))

    def __getattr__(self, name):
        column = ("total_reward", "risky_steps", "source_reached", "steps").index(name)
        return np.array([row[column] for row in self.rows])


def gym_episodes(env, theta, episodes, seed) -> Outcomes:
    policy, rng, out = SoftmaxPolicy(theta), np.random.default_rng(seed + 1), Outcomes()
    obs, info = env.reset(seed=seed)
    for _ in range(episodes):
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, info = env.step(policy(obs, rng))
            total += reward
            done = terminated or truncated
        out.add(total, info)
        obs, info = env.reset()
    return out


# -- the returns' distribution --------------------------------------------------------------------------------------


@pytest.mark.slow  # thousands of episodes stepped one by one in Python
@pytest.mark.parametrize("theta", [TRAINED, THETA0], ids=["trained", "theta0"])
def test_gym_episodes_have_the_kernels_distribution(paper, theta):
    env = SensorPlanningEnv(paper)
    agree(f"gym {theta}", gym_episodes(env, theta, GYM_EPISODES, seed=5), kernel(paper, theta))


@pytest.mark.parametrize("theta", [TRAINED, THETA0], ids=["trained", "theta0"])
def test_batched_episodes_have_the_kernels_distribution(paper, theta):
    agree(
        f"batched {theta}", run_episodes(paper, theta, BATCH_EPISODES, np.random.default_rng(3)), kernel(paper, theta)
    )


@pytest.mark.slow  # over a second of episodes
def test_mobile_sources_have_the_kernels_distribution(mobile):
    assert mobile.world.mobile
    agree(
        f"mobile {THETA0}",
        run_episodes(mobile, THETA0, BATCH_EPISODES, np.random.default_rng(4)),
        kernel(mobile, THETA0),
    )


@pytest.mark.slow  # over a second of episodes
def test_team_robots_each_have_the_kernels_distribution():
    """The paper's 3 robots, all at theta0: with static sources their episodes are independent kernel samples."""
    env = SensorTeamEnv(["experiment=paper_team"])
    policy, rng, out = SoftmaxPolicy(THETA0), np.random.default_rng(8), Outcomes()
    obs, infos = env.reset(seed=7)
    totals = dict.fromkeys(env.possible_agents, 0.0)
    for _ in range(TEAM_EPISODES):
        while env.agents:
            moves = policy.act(np.stack([obs[a]["signals"] for a in env.agents]), rng)
            obs, rewards, terms, truncs, infos = env.step(dict(zip(env.agents, moves.tolist())))
            for agent, reward in rewards.items():
                totals[agent] += reward
                if terms[agent] or truncs[agent]:
                    out.add(totals[agent], infos[agent])
        obs, infos = env.reset()
        totals = dict.fromkeys(env.possible_agents, 0.0)
    assert len(out.rows) == 3 * TEAM_EPISODES
    agree(f"team {THETA0}", out, kernel(env.setup, THETA0))


# -- the APIs --------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "overrides", [[], MOBILE + ["world.stop_at_source=false", "world.horizon=6"]], ids=["paper", "mobile_no_stop"]
)
def test_the_gym_env_passes_the_gymnasium_checker(overrides):
    env = gymnasium.make(ENV_ID, config=overrides, render_mode="ansi")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    assert [str(w.message) for w in caught] == []
    env.close()


def test_gymnasium_make_finds_the_env_by_module_path():
    env = gymnasium.make(f"riskplan.envs:{ENV_ID}", config=["world.horizon=12"])  # the sources are 12 moves away
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert env.unwrapped.world.horizon == 12


@pytest.mark.parametrize(
    "overrides",
    [["experiment=paper_team"], ["experiment=paper_team", "world.stop_at_source=false", "world.horizon=5"] + MOBILE],
    ids=["paper_team", "mobile_no_stop"],
)
def test_the_team_env_passes_the_pettingzoo_checks(overrides):
    parallel_api_test(SensorTeamEnv(overrides), num_cycles=100)
    parallel_seed_test(lambda: SensorTeamEnv(overrides))


# -- the world's rules, step by step ---------------------------------------------------------------------------------

CONSTANT = ["world.regions.0.reward=-1", "world.regions.1.reward=1", "world.sources.1.reward=2000"]
E, W, STAY, N, S = range(5)


def test_moves_in_order_blocked_moves_stay_and_every_entered_cell_pays():
    env = SensorPlanningEnv(CONSTANT)
    obs, info = env.reset(seed=0)
    assert obs["position"].tolist() == [0, 0] and obs["step"] == 0 and info["risky_steps"] == 0
    expected = [
        (W, [0, 0], 1),
        (S, [0, 0], 1),
        (E, [1, 0], 1),
        (N, [1, 1], 1),
        (N, [1, 2], -1),
        (STAY, [1, 2], -1),
        (S, [1, 1], 1),
    ]
    risky = 0
    for k, (action, position, reward) in enumerate(expected, 1):
        obs, r, terminated, truncated, info = env.step(action)
        risky += reward < 0
        assert (obs["position"].tolist(), r, obs["step"]) == (position, reward, k)
        assert (terminated, truncated, info["risky_steps"], info["steps"]) == (False, False, risky, k)


def test_a_source_pays_and_ends_the_episode():
    env = SensorPlanningEnv(CONSTANT)
    env.reset(seed=0)
    total = 0.0
    for action in [E] * 9 + [N] * 3:  # (0, 0) to the safe source at (9, 3) through safe cells only
        _obs, reward, terminated, truncated, info = env.step(action)
        total += reward
    assert (terminated, truncated, info["source_reached"], info["steps"], info["risky_steps"]) == (
        True,
        False,
        0,
        12,
        0,
    )
    assert total == 12 * 1 + 1000.0  # 12 cells entered (the start is not paid), plus the source
    with pytest.raises(RuntimeError, match="reset"):
        env.step(STAY)


def test_the_horizon_truncates_and_without_stopping_a_source_pays_each_step():
    env = SensorPlanningEnv(
        CONSTANT + ["world.stop_at_source=false", "world.horizon=14", "world.sources.0.position=[1,0]"]
    )
    env.reset(seed=0)
    rewards = []
    for k in range(14):
        _, reward, terminated, truncated, info = env.step(E if k == 0 else STAY)
        rewards.append(reward)
        assert terminated is False and truncated is (k == 13)
    assert rewards == [1001.0] * 14 and info["source_reached"] == 0


@pytest.mark.slow  # about a second
def test_a_step_draws_the_kernels_stream_and_law(paper):
    """Worlds.step is the kernel's step: robot b's rewards come from episode b of the key (seed, ENVIRONMENT), by the
    affine law of the paper world's regions (safe: 100 U; risky: clip(200 U + 100 N)), U then N at every step."""
    worlds = Worlds(paper.world, np.zeros(2, dtype=np.int64), seed=7)
    key = np.uint64(R.stream_key(7, R.ENVIRONMENT))
    streams = [R.episode_state(key, b) for b in range(2)]
    expected = [[], []]
    for move, cells in [((E, N), (12, 1)), ((N, E), (13, 13))]:  # robot 0 into safe cells, robot 1 a risky one
        reward, *_ = worlds.step(np.array(move))
        for b in range(2):
            streams[b], u = R.next_uniform(np.uint64(streams[b]))  # numba hands a uint64 back as a Python int
            streams[b], g = R.next_normal(np.uint64(streams[b]))
            risky = paper.world.region_risky[paper.world.region_of[cells[b]]]
            expected[b].append(min(max(200.0 * u + 100.0 * g, -1e4), 1e4) if risky else 100.0 * u)
        np.testing.assert_array_equal(reward, [expected[0][-1], expected[1][-1]])
    assert worlds.cell.tolist() == [13, 13] and worlds.risky_steps.tolist() == [0, 1]
    worlds.reset(seed=7)
    np.testing.assert_array_equal(worlds.step(np.array([E, N]))[0], [expected[0][0], expected[1][0]])


def test_observed_signals_are_the_policys_features(paper):
    env = SensorPlanningEnv(paper)
    obs, _ = env.reset(seed=1)
    features = move_features(paper.world)
    for action in [E, E, N, STAY, W]:
        x, y = obs["position"]
        np.testing.assert_array_equal(obs["signals"], features[x * paper.world.height + y])
        obs, *_ = env.step(action)
    policy = SoftmaxPolicy(TRAINED)
    np.testing.assert_allclose(policy.probabilities(obs["signals"]).sum(), 1.0)


def test_team_robots_share_mobile_sources():
    """Two robots that stand still see the same walking sources; robots in separate copies would not."""
    overrides = [
        "team.robots=2",
        "world.stop_at_source=false",
        "world.sources.0.motion.kind=random_walk",
        "world.sources.0.motion.prob=1.0",
        "world.sources.1.motion.kind=random_walk",
        "world.sources.1.motion.prob=1.0",
    ]
    env = SensorTeamEnv(overrides)
    obs, _ = env.reset(seed=0)
    seen = []
    for _ in range(10):
        obs, *_ = env.step({a: STAY for a in env.agents})
        np.testing.assert_array_equal(obs["robot_0"]["signals"], obs["robot_1"]["signals"])
        seen.append(obs["robot_0"]["signals"].copy())
    assert any(not np.array_equal(seen[0], s) for s in seen[1:])  # the sources did walk
    separate = Worlds(env.world, np.zeros(2, dtype=np.int64))
    for _ in range(10):
        separate.step(np.full(2, STAY))
    assert not np.array_equal(separate.sources[0], separate.sources[1])


def test_bad_actions_are_refused():
    env = SensorPlanningEnv(["world.horizon=12"])
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"0\.\.4"):
        env.step(5)
    team = SensorTeamEnv(["experiment=paper_team"])
    team.reset(seed=0)
    with pytest.raises(ValueError, match="robot_2"):
        team.step({"robot_0": STAY, "robot_1": STAY})
    with pytest.raises(ValueError, match=r"0\.\.4"):
        env.step(True)  # a bool is not a move, though Discrete takes it for 1
    with pytest.raises(ValueError, match="no robot 'robot_99'"):
        team.step({"robot_0": STAY, "robot_1": STAY, "robot_2": STAY, "robot_99": STAY})
    with pytest.raises(ValueError, match="no robot 'bogus'"):
        team.observation_space("bogus")
    with pytest.raises(TypeError, match=r"^actions: got list; give a dict of robot to move, e\.g\. \{'robot_0': 4, "):
        team.step([STAY, STAY, STAY])  # its moves were taken for robots' names: "no robot 4"
    with pytest.raises(RuntimeError, match=r"call reset\(\) before step\(\)"):
        SensorPlanningEnv(["world.horizon=12"]).step(STAY)


@pytest.mark.parametrize(
    ("starts", "problem"),
    [
        ([10**7], "starts: cell 10000000 is off the grid; give cell indices 0..143"),  # a segfault in the kernel
        ([0, 144], "starts: cell 144 is off the grid"),
        ([-1], "starts: cell -1 is off the grid"),  # read as the last cell
        ([1.5], "starts: got [1.5]; give cell indices, whole numbers 0..143"),  # read as cell 1
        ([True], "starts: got [True]; give cell indices"),
    ],
)
def test_start_cells_off_the_grid_or_not_whole_are_refused(starts, problem):
    with pytest.raises(ValueError) as refused:
        Worlds(make_setup(None).world, starts)
    assert str(refused.value).startswith(problem)


def test_run_episodes_takes_one_free_start_cell():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match=r"^start: cell 65 \(5, 5\) is an obstacle; start on a free cell$"):
        run_episodes(["world.obstacles=[[5,5]]"], TRAINED, 3, rng, start=65)
    with pytest.raises(ValueError, match=r"^start: got \(3, 3\); give one start cell"):
        run_episodes(None, TRAINED, 3, rng, start=(3, 3))
    episodes = run_episodes(None, TRAINED, 50, rng, start=np.int64(13))  # (1, 1): 20 moves from both sources
    assert episodes.steps.min() >= 1 and episodes.total_reward.shape == (50,)


@pytest.mark.parametrize("seed", [-1, 2**63, 2**64 + 5, True, 1.0])
def test_a_seed_out_of_range_is_refused_never_reduced(seed):
    """Seeds are never reduced modulo 2^64 (docs/robustness.md): 2^64 + 5 gave seed 5's streams."""
    worlds = Worlds(make_setup(None).world, [0])
    with pytest.raises(ValueError, match=r"^seed: got .*; give a whole number 0 <= seed < 2\^63"):
        worlds.reset(seed)
    worlds.reset(2**63 - 1)  # the largest


def test_a_theta_whose_logits_overflow_is_refused_not_nan():
    """Probabilities of NaN picked East every time, and run_episodes returned finite rewards of that policy."""
    with pytest.raises(ValueError, match=r"^theta: the softmax logits theta \. f\(x, u\) overflow to infinity at this"):
        SoftmaxPolicy([1e308, 1e308]).probabilities(np.ones((5, 2)))
    with pytest.raises(ValueError, match=r"^theta: the softmax logits .* overflow to infinity; give a smaller"):
        run_episodes(None, [1e308, 1e308], 5, np.random.default_rng(0))
    assert SoftmaxPolicy([1e300, 0.0]).probabilities(np.array([[1.0, 0.0]] + [[0.0, 0.0]] * 4))[0] == 1.0


@pytest.mark.parametrize("theta", [[], [math.nan, 1.0], [math.inf, 0.0]])
def test_a_policy_takes_finite_thetas_of_the_observations_length(theta):
    with pytest.raises(ValueError, match="theta must be one or more finite numbers"):
        SoftmaxPolicy(theta)
    signals = np.zeros((5, 2))  # the paper world's two sources
    with pytest.raises(ValueError, match="theta has 3 entries; the observation gives 2 features"):
        SoftmaxPolicy([1.0, 2.0, 3.0]).act(signals, np.random.default_rng(0))
    with pytest.raises(ValueError, match="config: got 5"):
        SensorPlanningEnv(5)


def test_render_shows_the_robot_and_the_sources(paper):
    env = SensorPlanningEnv(paper, render_mode="ansi")
    env.reset(seed=0)
    rows = env.render().splitlines()
    assert len(rows) == paper.world.height and rows[-1][0] == "R"  # row -1 - y is y, north up
    assert rows[-1 - 3][9] == "S" and rows[-1 - 9][3] == "S"
