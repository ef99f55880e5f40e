"""policy.kind=tabular: theta is the (C * 5,) table of logits, the kernel's scores are e_(c, a) - mu(. | c) summed
over an episode's steps.

Known answers: a table set to a features policy's logits draws the features kernel's very episodes, and maps its
scores through the features' Jacobian onto the features scores; the sample gradient of E[Z] matches finite
differences of an exact enumeration; the budget refuses a grid whose scores do not fit, before building anything.
"""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf
from support import WORLD_3X3, exact_outcomes, world_3x3

from riskplan.engine import rng
from riskplan.engine.policy import (
    feature_logits,
    make_policy,
    move_features,
    tables,
    tabular_probabilities,
    tabular_tables,
)
from riskplan.engine.rollout import make_kernel, simulate
from riskplan.engine.step import logit_bound
from riskplan.engine.world import MOVE_NAMES
from riskplan.risk import mean_gradient
from riskplan.run import build
from riskplan.run.build import build_setup
from riskplan.run.compose import compose
from riskplan.util.errors import BadInput

TABULAR = {"policy": {"kind": "tabular"}}
MOBILE = ["world.sources.0.motion.kind=random_walk", "world.sources.0.motion.prob=0.5"]


def tiny_setup(*extra: dict):
    """The tabular policy on the 3x3 world of tests/support.py."""
    return world_3x3(TABULAR, *extra)


def run(setup, thetas, episodes, seed=0, **kw):
    thetas = np.atleast_2d(thetas)
    keys = rng.robot_keys(seed, rng.TRAIN, 0, len(thetas))
    starts = np.repeat(setup.world.starts[:1], len(thetas))
    return simulate(setup.world, setup.kernel, thetas, starts, keys, episodes, **kw)


# -- theta0, names, tables ------------------------------------------------------------------------------------------


@pytest.mark.slow  # several set-ups and kernel runs
def test_the_table_starts_from_the_features_policys_logits():
    paper = build_setup(compose([]))
    table = build_setup(compose(["policy.kind=tabular"]))
    world = table.world
    assert table.theta0.shape == (world.cells * 5,) and table.policy.tabular and table.kernel.tables.tabular
    logits = np.einsum("caj,j->ca", move_features(world), paper.theta0)
    np.testing.assert_allclose(table.theta0.reshape(world.cells, 5), logits, rtol=1e-15, atol=0)
    # the same move probabilities as the paper's initial policy, bit for bit (the kernel's tables)
    cum_features, _ = tables(world, paper.theta0[None, :], paper.kernel.features)
    cum_table, _ = tabular_tables(table.theta0[None, :], world.cells)
    np.testing.assert_array_equal(cum_table, cum_features)
    uniform = build_setup(compose(["policy.kind=tabular", "train.theta0=[0,0]"]))
    assert not uniform.theta0.any()
    np.testing.assert_allclose(tabular_probabilities(uniform.theta0, world.cells), 0.2)


def test_tabular_theta_names_and_theta0_rules():
    setup = build_setup(compose(["policy.kind=tabular", "world.size=[3,2]", "world.start=[0,0]",
                                 "world.sources.0.position=[2,1]", "world.sources.1.position=[1,0]",
                                 "world.regions=[]"]))  # fmt: skip
    names = setup.theta_names
    assert len(names) == 30 == len(set(names)) == setup.network.n_params
    assert names[:6] == ("x0_y0_E", "x0_y0_W", "x0_y0_Stay", "x0_y0_N", "x0_y0_S", "x0_y1_E")
    assert names[2 * 5 + 3] == "x1_y0_N"  # cell c = x * height + y = 2, move N: theta[c * 5 + 3]
    assert names[-1] == f"x2_y1_{MOVE_NAMES[-1]}"
    with pytest.raises(BadInput) as err:
        build_setup(compose(["policy.kind=tabular", "train.theta0=[1,2,3]"]))
    assert err.value.where == "train.theta0"
    assert "2 signal weights to seed its table (safe, risky); give at most 2 numbers" in str(err.value)
    padded = build_setup(compose(["policy.kind=tabular", "train.theta0=[20]"]))
    np.testing.assert_allclose(padded.theta0.reshape(-1, 5), 20.0 * move_features(padded.world)[..., 0])


def test_tabular_tables_are_the_softmax_of_each_cell():
    thetas = np.random.default_rng(0).normal(scale=3.0, size=(3, 4 * 5))
    cum, probs = tabular_tables(thetas, 4)
    expected = tabular_probabilities(thetas, 4)
    np.testing.assert_allclose(probs, expected, rtol=1e-13)
    np.testing.assert_allclose(cum[..., :4], np.cumsum(expected, axis=-1)[..., :4], rtol=1e-13)
    assert np.all(cum[..., 4] == 1.0)


def test_logit_bound_of_a_table_is_its_largest_entry():
    setup = build_setup(compose(["policy.kind=tabular"]))
    thetas = np.zeros((2, setup.world.cells * 5))
    thetas[1, 7] = -3e307
    thetas[0, 9] = 1e307
    assert logit_bound(setup.world, thetas, setup.policy) == 3e307
    assert logit_bound(setup.world, thetas) == 3e307  # length C * 5: a table, also without the policy


# -- (a) the same draws as the features kernel ----------------------------------------------------------------------


@pytest.mark.parametrize("features", [["signals"], ["signals", "risky", "stay"]])
@pytest.mark.parametrize("record", [False, True], ids=["fast", "recorded"])
def test_a_table_of_a_features_policys_logits_draws_the_same_episodes(features, record):
    """Same stream keys: identical rewards and steps; the features scores are J^T the tabular scores, with
    J[c * 5 + a, j] = f_j(c, a)."""
    paper = build_setup(compose([f"policy.features=[{','.join(features)}]"]))
    world = paper.world
    thetas = np.array([[20.0, 20.0, -3.0, 1.5][: paper.policy.size], [46.6, -0.8, 2.0, -1.0][: paper.policy.size]])
    jacobian = paper.kernel.features.reshape(world.cells * 5, -1)  # (C * 5, F)
    logits = np.stack([feature_logits(paper.kernel.features, theta).reshape(-1) for theta in thetas])
    tabular = make_kernel(world, make_policy(world, "tabular"))
    keys = rng.robot_keys(3, rng.TRAIN, 0, 2)
    starts = np.repeat(world.starts, 2)
    ours = simulate(world, paper.kernel, thetas, starts, keys, 4000, record=record)
    theirs = simulate(world, tabular, logits, starts, keys, 4000, record=record)
    np.testing.assert_array_equal(theirs.total_reward, ours.total_reward)
    np.testing.assert_array_equal(theirs.steps, ours.steps)
    np.testing.assert_array_equal(theirs.risky_steps, ours.risky_steps)
    np.testing.assert_array_equal(theirs.source_reached, ours.source_reached)
    if record:
        np.testing.assert_array_equal(theirs.path_cells, ours.path_cells)
    assert theirs.score.shape == (8000, world.cells * 5)
    np.testing.assert_allclose(theirs.score @ jacobian, ours.score, rtol=1e-9, atol=1e-9)
    # an episode's tabular score sums to 0 over each visited cell's moves (sum_a e_a - mu = 0)
    np.testing.assert_allclose(theirs.score.reshape(8000, world.cells, 5).sum(axis=-1), 0.0, atol=1e-12)


def test_without_scores_a_table_draws_the_same_episodes():
    setup = build_setup(compose(["policy.kind=tabular"]))
    full = run(setup, setup.theta0, 3000)
    bare = run(setup, setup.theta0, 3000, scores=False)
    assert bare.score.shape == (3000, 0)
    np.testing.assert_array_equal(bare.total_reward, full.total_reward)
    np.testing.assert_array_equal(bare.steps, full.steps)


# -- (b) the gradient of E[Z] against an exact enumeration ----------------------------------------------------------


def exact_mean(setup, table) -> float:
    """E[Z] by enumerating every path of the tabular policy `table` (C * 5,)."""
    z, p, _ = exact_outcomes(setup, tabular_probabilities(table, setup.world.cells))
    return float(z @ p)


@pytest.fixture(scope="module", params=["static", "mobile"])
def tiny(request):
    """The tiny world; "mobile": a source that almost never walks, the same law through the mobile kernel."""
    data = OmegaConf.to_container(OmegaConf.create(WORLD_3X3))
    if request.param == "mobile":
        data["world"]["sources"][0]["motion"] = {"kind": "random_walk", "prob": 1e-12}
    setup = tiny_setup(data)
    assert setup.world.mobile == (request.param == "mobile")
    return setup


@pytest.mark.slow  # 200,000 kernel episodes against the exact enumeration
def test_the_sample_gradient_of_a_table_matches_the_exact_enumeration(tiny):
    world = tiny.world
    table = tiny.theta0 + np.random.default_rng(5).normal(scale=0.7, size=world.cells * 5)
    h = 1e-5
    truth = np.array(
        [
            (exact_mean(tiny, table + h * np.eye(table.size)[i]) - exact_mean(tiny, table - h * np.eye(table.size)[i]))
            / (2 * h)
            for i in range(table.size)
        ]
    )
    episodes = 400_000
    batch = run(tiny, table, episodes, seed=2)
    estimate = mean_gradient(batch.total_reward, batch.score)
    centred = (batch.total_reward - batch.total_reward.mean())[:, None] * batch.score
    stderr = np.std(centred, axis=0) / np.sqrt(episodes)
    seen = stderr > 0
    assert seen.sum() >= 20 and np.abs(truth[seen]).max() > 0.5  # most of the table matters
    np.testing.assert_array_less(np.abs(estimate - truth)[seen], 4 * stderr[seen])
    # a (cell, move) no episode visits has score 0, and there the exact gradient is 0 too
    np.testing.assert_array_equal(estimate[~seen], 0.0)
    np.testing.assert_allclose(truth[~seen], 0.0, atol=1e-8)


# -- mobile sources -------------------------------------------------------------------------------------------------


@pytest.mark.slow  # rollouts of two worlds (near a second)
def test_a_table_with_mobile_sources_ignores_where_they_are():
    """Same table, static and walking sources: the moves' law is the table's either way; the sources still pay."""
    walking = build_setup(compose(["policy.kind=tabular", *MOBILE]))
    still = build_setup(compose(["policy.kind=tabular"]))
    assert walking.world.mobile and np.array_equal(walking.theta0, still.theta0)
    a = run(walking, walking.theta0, 50_000, record=True, scores=False)
    b = run(still, still.theta0, 50_000, record=True, scores=False)
    # the first move (before any source can matter) is the start cell's row of the table in both
    first_a, first_b = a.path_cells[:, 1], b.path_cells[:, 1]
    for cell in np.unique(np.concatenate([first_a, first_b])):
        pa, pb = np.mean(first_a == cell), np.mean(first_b == cell)
        assert abs(pa - pb) < 5 * np.sqrt(pa * (1 - pa) / 25_000 + 1e-12)
    scored = run(walking, walking.theta0, 2000)  # and the scores: e_(c, a) - mu(. | c) sums to 0 over each cell's moves
    assert np.abs(scored.score).max() > 0.5
    np.testing.assert_allclose(scored.score.reshape(2000, -1, 5).sum(axis=-1), 0.0, atol=1e-9)
    assert np.any(a.source_reached == 0) and np.any(a.source_reached == 1)


# -- (c) the budget -------------------------------------------------------------------------------------------------


def test_the_budget_refuses_tabular_scores_that_do_not_fit_before_building_anything(monkeypatch):
    monkeypatch.setenv("RISKPLAN_MEMORY_GB", "2")
    big = ["world.size=[100,100]", "world.start=[0,0]", "train.eval_episodes=1000"]
    assert build_setup(compose(big)).world.cells == 10_000  # the features policy fits

    def no_world(*args, **kwargs):
        raise AssertionError("the world was built before the budget refused the run")

    monkeypatch.setattr(build, "build_world", no_world)
    with pytest.raises(BadInput) as err:
        build_setup(compose([*big, "policy.kind=tabular"]))
    message = str(err.value)
    assert err.value.where == "world.size" and "\n" not in message
    assert message.startswith("world.size: got [100, 100]; the run, mostly its training batches")
    assert "tabular policy's 50000 scores" in message and "RISKPLAN_MEMORY_GB" in message


def test_tabular_numbers_do_not_depend_on_the_thread_count():
    import numba

    setup = build_setup(compose(["policy.kind=tabular", *MOBILE]))
    table = setup.theta0 + np.random.default_rng(3).normal(size=setup.theta0.size)
    thetas = np.stack([table, setup.theta0])
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = run(setup, thetas, 700)
    finally:
        numba.set_num_threads(before)
    many = run(setup, thetas, 700)
    for field in ("total_reward", "score", "steps", "risky_steps", "source_reached"):
        np.testing.assert_array_equal(getattr(many, field), getattr(one, field))
