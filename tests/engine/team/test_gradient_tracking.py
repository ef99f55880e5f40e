"""Gradient tracking (team.order=gradient_tracking): the tracking invariant, exact consensus under constant
gradients at the SLEM rate, running sums under delays and drops, checkpoints, bad input. How `riskplan check`
describes it is in tests/commands/test_check_command.py, the report's figure in tests/experiments/reporting."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from support import TINY, team_conf

from riskplan import compose, train
from riskplan.engine.team.convergence import consensus_error, second_largest_eigenvalue_modulus
from riskplan.engine.team.mixer import Mixer
from riskplan.engine.team.network import build_network
from riskplan.run.checkpoint import CHECKPOINT, load_checkpoint
from riskplan.util.errors import BadInput

SINGLE = TINY  # one robot, combine then adapt
TEAM = ["experiment=paper_team", *TINY]
TRACKING = [*TEAM, "team.order=gradient_tracking"]


def make_team(**values):
    return team_conf(**{"order": "gradient_tracking", **values})


def mixer_of(seed: int = 0, m: int = 2, **values) -> Mixer:
    team = make_team(**values)
    return Mixer(build_network(team, m, seed), team, seed)


def raw_tracker(mixer: Mixer, grads: np.ndarray) -> np.ndarray:
    """y_l before the call to track: the mixed tracker kept from the last call plus Delta_l - Delta_{l-1}."""
    state, m = mixer.state(), grads.shape[1]
    return state["tracker"][:, :m] + (grads - state["gradient"])


# ---------------------------------------------------------------------------------------------- exact case
@pytest.mark.parametrize(
    "values",
    [
        {"robots": 5, "graph": "line"},
        {"robots": 12, "graph": "random_geometric", "radius": 0.5},
        {"robots": 6, "graph": "grid", "consensus_rounds": 3},
    ],
)
def test_tracking_invariant_is_exact_on_a_doubly_stochastic_graph_without_delays(values):
    """sum_i y^i_l = sum_i Delta^i_l at every iteration, for any gradients (Metropolis weights, no delays)."""
    mixer = mixer_of(**values)
    assert np.allclose(mixer.network.weights.sum(axis=0), 1.0)  # doubly stochastic
    n, rng = mixer.network.robots, np.random.default_rng(3)
    thetas = rng.normal(size=(n, 2))
    for l in range(60):
        grads = rng.normal(size=(n, 2)) * 100
        mixed, tracker = mixer.track(thetas, grads, l)
        np.testing.assert_allclose(tracker.sum(axis=0), grads.sum(axis=0), rtol=0, atol=1e-9)
        np.testing.assert_allclose(mixer.state()["tracker"][:, 2:], 1.0, rtol=0, atol=1e-12)  # v stays 1
        assert np.all(mixer.in_flight() == 0)
        thetas = mixed + 0.01 * tracker
    if l == 0:
        np.testing.assert_array_equal(tracker, grads)


def test_first_tracker_is_the_gradient_and_theta_follows_diging():
    """y_0 = Delta_0; theta_{l+1} = A theta_l + eps y_l; y_{l+1} = A y_l + Delta_{l+1} - Delta_l (the matrix form)."""
    mixer = mixer_of(robots=4, graph="ring")
    a = mixer.network.weights[:, :, 0]
    rng = np.random.default_rng(1)
    thetas, y_prev, g_prev = rng.normal(size=(4, 2)), None, None
    for l in range(8):
        grads = rng.normal(size=(4, 2))
        expected_y = grads if l == 0 else a @ y_prev + grads - g_prev
        mixed, tracker = mixer.track(thetas, grads, l)
        np.testing.assert_allclose(tracker, expected_y, rtol=0, atol=1e-12)
        np.testing.assert_allclose(mixed, a @ thetas, rtol=0, atol=1e-12)
        thetas, y_prev, g_prev = mixed + 0.1 * tracker, tracker, grads


# ---------------------------------------------------------------------------------------------- rate
def test_constant_gradients_reach_exact_consensus_at_the_slem_rate():
    """With Delta^i constant, y - mean(y) contracts by A each iteration: the error falls as SLEM^l (and theta's as
    l SLEM^l), down to rounding; combine-then-adapt keeps the floor eps |Delta^i - Delta^j| instead."""
    mixer = mixer_of(robots=6, graph="grid")  # 2 x 3 grid, Metropolis: SLEM 0.75
    slem = second_largest_eigenvalue_modulus(mixer.network.weights[:, :, 0])
    eigen = np.sort(np.abs(np.linalg.eigvalsh(mixer.network.weights[:, :, 0])))
    assert slem == pytest.approx(eigen[-2]) and eigen[-1] == pytest.approx(1.0)
    rng = np.random.default_rng(0)
    grads, eps = rng.normal(size=(6, 2)) * 10, 0.05
    thetas = np.tile(rng.normal(size=2), (6, 1))
    cta = thetas.copy()
    theta_errors, tracker_errors = [], []
    for l in range(130):
        mixed, tracker = mixer.track(thetas, grads, l)
        thetas = mixed + eps * tracker
        theta_errors.append(consensus_error(thetas))
        tracker_errors.append(consensus_error(tracker))
        cta = np.einsum("ijm,jm->im", mixer.network.weights, cta) + eps * grads
    np.testing.assert_allclose(tracker[0], grads.mean(axis=0), rtol=1e-9)  # every robot tracks the average
    ratios = np.array(tracker_errors[11:61]) / np.array(tracker_errors[10:60])
    np.testing.assert_allclose(ratios, slem, rtol=1e-3)  # the tracker error contracts by exactly the SLEM
    late = np.arange(30, 70)
    fitted = math.exp(np.polyfit(late, np.log(np.array(theta_errors)[late] / late), 1)[0])  # l * SLEM^l
    assert fitted == pytest.approx(slem, rel=0.02)
    assert theta_errors[-1] < 1e-9 * max(theta_errors)
    assert consensus_error(cta) > 0.05 * eps * consensus_error(grads)  # the floor of eq. (14)


# ---------------------------------------------------------------------------------------------- delays and drops
NOISY = {"robots": 6, "graph": "ring", "delay": {"max": 3}, "drop": 0.3, "max_gap": 4}


@pytest.mark.parametrize(
    "values",
    [
        NOISY,
        {**NOISY, "stale": "latest", "consensus_rounds": 2},
        {**NOISY, "switching": {"enabled": True, "up": 0.5, "window": 3}},
    ],
)
def test_under_delays_and_drops_the_mass_in_flight_closes_the_invariant(values):
    """Running sums: sum_i y^i + the mass still in flight = sum_i Delta^i exactly; late mass is bounded (it arrives
    within B + B0 iterations), and with constant gradients the normalised trackers y / v still agree exactly."""
    mixer = mixer_of(**values)
    n, rng = mixer.network.robots, np.random.default_rng(4)
    thetas = rng.normal(size=(n, 2))
    constant = rng.normal(size=(n, 2))
    largest = 0.0
    for l in range(300):
        grads = constant if l >= 100 else rng.normal(size=(n, 2))
        before = mixer.in_flight()[:2]
        y = raw_tracker(mixer, grads)
        mixed, tracker = mixer.track(thetas, grads, l)
        np.testing.assert_allclose(y.sum(axis=0) + before, grads.sum(axis=0), rtol=0, atol=1e-9)
        np.testing.assert_allclose(
            mixer.in_flight()[2:] + mixer.state()["tracker"][:, 2:].sum(axis=0), n, rtol=0, atol=1e-9
        )  # the push-sum weights: sum v + in flight = N
        largest = max(largest, float(np.abs(before).max()))
        thetas = mixed + 0.01 * tracker
    assert 0 < largest < 20 * n  # not zero (messages were late), and bounded
    np.testing.assert_allclose(tracker, np.tile(constant.mean(axis=0), (n, 1)), rtol=0, atol=1e-9)


def test_same_seed_same_trackers_and_restore_is_bit_identical():
    values = {**NOISY, "consensus_rounds": 2, "switching": {"enabled": True}}
    rng = np.random.default_rng(9)
    grads = rng.normal(size=(30, 6, 2))
    thetas0 = rng.normal(size=(6, 2))

    def run(mixer, thetas, first, last):
        out = []
        for l in range(first, last):
            mixed, tracker = mixer.track(thetas, grads[l], l)
            thetas = mixed + 0.1 * tracker
            out.append(thetas)
        return out

    full = run(mixer_of(seed=5, **values), thetas0, 0, 30)
    half = mixer_of(seed=5, **values)
    first = run(half, thetas0, 0, 13)
    saved = json.loads(json.dumps({k: v.tolist() for k, v in half.state().items()}))  # a JSON checkpoint
    resumed = mixer_of(seed=5, **values).restore(saved)
    rest = run(resumed, first[-1], 13, 30)
    assert all(np.array_equal(a, b) for a, b in zip(first + rest, full))
    assert {"pending_sums", "sums", "seen_sums", "seen_sent", "tracker", "gradient"} <= set(half.state())


def test_other_orders_carry_no_tracker_state():
    team = team_conf(robots=3)
    mixer = Mixer(build_network(team, 2, 0), team, 0)
    assert "tracker" not in mixer.state() and not mixer.tracking
    with pytest.raises(ValueError):
        mixer.track(np.zeros((3, 2)), np.zeros((3, 2)), 0)


# ---------------------------------------------------------------------------------------------- runs
def test_a_team_of_one_with_tracking_equals_a_centralized_run(tmp_path):
    a = train(compose(SINGLE), tmp_path / "single")
    b = train(compose([*SINGLE, "team.order=gradient_tracking"]), tmp_path / "tracking_of_one")
    np.testing.assert_array_equal(a.metrics.theta_0, b.metrics.theta_0)


def test_checkpoint_holds_the_tracker_and_a_checkpoint_without_it_is_bad_input(tmp_path):
    cfg = compose([*TRACKING, "team.delay.max=1", "team.drop=0.2"])
    out = tmp_path / "run"
    train(cfg, out)
    from riskplan.run.build import build_setup

    payload = json.loads((out / CHECKPOINT).read_text())
    assert {"tracker", "gradient", "sums", "seen_sums", "pending_sums", "seen_sent"} <= set(payload["mixer"])
    assert np.shape(payload["mixer"]["tracker"]) == (3, 4) and np.any(np.array(payload["mixer"]["gradient"]) != 0)
    state = load_checkpoint(out, build_setup(cfg))
    assert state.mixer["tracker"].shape == (3, 4)
    for key, bad in (("tracker", None), ("gradient", [[float("nan")] * 2] * 3), ("sums", [[0.0]])):
        broken = json.loads(json.dumps(payload))
        if bad is None:
            del broken["mixer"][key]
        else:
            broken["mixer"][key] = bad
        (out / CHECKPOINT).write_text(json.dumps(broken))
        with pytest.raises(BadInput, match="consensus state"):
            load_checkpoint(out, build_setup(cfg))
    # A checkpoint of a combine-then-adapt run cannot resume a gradient-tracking one (and the other way round).
    other = build_setup(compose([*TEAM, "team.delay.max=1", "team.drop=0.2"]))
    (out / CHECKPOINT).write_text(json.dumps(payload))
    with pytest.raises(BadInput, match="consensus state"):
        load_checkpoint(out, other)


# ---------------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "overrides,where",
    [
        (["team.weights=lazy"], "team.weights"),
        (["team.graph=edges", "team.directed=true", "team.edges=[[1,0],[2,1],[0,2],[0,1]]"], "team.weights"),
        (["'team.matrix=[[0.5,0.5,0],[0.25,0.5,0.25],[0,0.5,0.5]]'".strip("'"), "team.weights=matrix"], "team.matrix"),
    ],
)
def test_gradient_tracking_needs_doubly_stochastic_weights(overrides, where):
    with pytest.raises(BadInput, match="doubly stochastic") as err:
        compose(["experiment=paper_team", "team.order=gradient_tracking", *overrides])
    assert err.value.where == where


def test_unknown_order_lists_the_three():
    with pytest.raises(BadInput, match="combine_then_adapt, adapt_then_combine, gradient_tracking"):
        compose(["team.order=sideways"])
